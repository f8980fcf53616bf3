#!/usr/bin/env python3
"""RMS of `headalign demo --json` errors over a range of seeds.

usage: bench/seeds.py FIRST LAST [extra demo flags...]
(env HEADALIGN_BIN: the binary, default target/release/headalign; BENCH_DUMP=DIR: keep each run's JSON)
"""
import json, math, subprocess, sys

first, last = int(sys.argv[1]), int(sys.argv[2])
extra = sys.argv[3:]
# BENCH_DUMP=DIR keeps every run's JSON (seed<N>.json) for later analysis.
import os
extra_env = {"--dump": os.environ["BENCH_DUMP"]} if os.environ.get("BENCH_DUMP") else {}
keys = ["pan_err_deg", "steer_err_deg", "verge_err_l_deg", "verge_err_r_deg", "elev_err_l_deg", "elev_err_r_deg", "elev_err_r_excess_deg", "f_err_pct", "pp_err_pct", "recon_err_pct"]
rows, fails, times = [], 0, []
zs = {}  # name -> list of (estimate - truth) / sigma
for seed in range(first, last + 1):
    # Image-mode runs record a session by default; a seed sweep does not need them.
    quiet = ["--no-session"] if "--images" in extra and "--session" not in extra else []
    p = subprocess.run([os.environ.get("HEADALIGN_BIN", "target/release/headalign"), "demo", "--json", "--seed", str(seed), *extra, *quiet], capture_output=True, text=True)
    if p.returncode != 0:
        fails += 1
        print(f"seed {seed}: FAILED {p.stderr.strip()}")
        continue
    v = json.loads(p.stdout)
    rows.append(v["errors"])
    est, tru = v["estimate"], v["truth"]
    for cam in ("left", "right"):
        if "K" in tru[cam]:
            K = tru[cam]["K"]
            truth_k = {"fx": K[0][0], "fy": K[1][1], "cx": K[0][2], "cy": K[1][2]}
        else:  # image mode: the truth as fx, fy, cx, cy
            truth_k = {k: tru[cam][k] for k in ("fx", "fy", "cx", "cy")}
        for k, t in truth_k.items():
            sig = est[cam].get("sigma", {}).get(k)
            if sig:
                zs.setdefault(f"{cam}.{k}", []).append((est[cam][k] - t) / sig)
    for j in ("elevation", "verge_left", "verge_right"):
        sig = (est.get("aligned_sigma_deg") or {}).get(f"{j}_deg")
        if sig:
            zs.setdefault(f"aligned.{j}", []).append((est["aligned_encoders"][j] - tru["aligned_encoders"][j]) / sig)
    # Robot stages: the last pan correction's sigma is that of the final pan reading;
    # the steering zero against the truth.
    pans = [s for stage in v.get("pan") or [] for s in stage.get("steps", [])]
    if pans and v["errors"].get("pan_err_deg") is not None and pans[-1].get("sigma_deg"):
        zs.setdefault("pan", []).append(v["errors"]["pan_err_deg"] / pans[-1]["sigma_deg"])
    st = v.get("steering") or {}
    if st.get("sigma_steer_zero_deg") and tru.get("steer_zero_deg") is not None:
        zs.setdefault("steer_zero", []).append((st["steer_zero_deg"] - tru["steer_zero_deg"]) / st["sigma_steer_zero_deg"])
    if "--dump" in extra_env:
        with open(f"{extra_env['--dump']}/seed{seed}.json", "w") as f:
            json.dump(v, f)
    times.append(v["timings"]["total_s"])
    print(f"seed {seed}: " + " ".join(f"{k.replace('_deg','').replace('_pct','%')}={v['errors'][k]:+.3f}" for k in keys if v["errors"].get(k) is not None))
print(f"{len(rows)} runs, {fails} failures, mean time {1e3*sum(times)/max(1,len(times)):.1f} ms")
for k in keys:
    vals = [r[k] for r in rows if r.get(k) is not None]
    if vals:
        print(f"RMS {k:16s} {math.sqrt(sum(x*x for x in vals)/len(vals)):.4f}   max {max(abs(x) for x in vals):.4f}")
print("z-scores (estimate - truth) / sigma: RMS 1 and mean 0 when the sigmas are calibrated")
for k, vals in zs.items():
    rms = math.sqrt(sum(x * x for x in vals) / len(vals))
    cov = sum(abs(x) <= 1.96 for x in vals) / len(vals)
    print(f"  {k:22s} RMS {rms:.2f}   mean {sum(vals) / len(vals):+.2f}   95% coverage {100 * cov:.0f} % (n {len(vals)})")
allz = [x for vals in zs.values() for x in vals]
if allz:
    print(f"  {'all':22s} RMS {math.sqrt(sum(x * x for x in allz) / len(allz)):.2f}   95% coverage {100 * sum(abs(x) <= 1.96 for x in allz) / len(allz):.0f} % (n {len(allz)})")
