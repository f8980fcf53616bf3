#!/usr/bin/env python3
"""RMS of `headalign demo --json` errors over a range of seeds.

usage: bench/seeds.py FIRST LAST [extra demo flags...]
"""
import json, math, subprocess, sys

first, last = int(sys.argv[1]), int(sys.argv[2])
extra = sys.argv[3:]
keys = ["verge_err_l_deg", "verge_err_r_deg", "elev_err_l_deg", "elev_err_r_deg", "elev_err_r_excess_deg", "f_err_pct", "pp_err_pct", "recon_err_pct"]
rows, fails, times = [], 0, []
for seed in range(first, last + 1):
    p = subprocess.run(["target/release/headalign", "demo", "--json", "--seed", str(seed), *extra], capture_output=True, text=True)
    if p.returncode != 0:
        fails += 1
        print(f"seed {seed}: FAILED {p.stderr.strip()}")
        continue
    v = json.loads(p.stdout)
    rows.append(v["errors"])
    times.append(v["timings"]["total_s"])
    print(f"seed {seed}: " + " ".join(f"{k.replace('_deg','').replace('_pct','%')}={v['errors'][k]:+.3f}" for k in keys if v['errors'][k] is not None))
print(f"{len(rows)} runs, {fails} failures, mean time {1e3*sum(times)/max(1,len(times)):.1f} ms")
for k in keys:
    vals = [r[k] for r in rows if r[k] is not None]
    if vals:
        print(f"RMS {k:16s} {math.sqrt(sum(x*x for x in vals)/len(vals)):.4f}   max {max(abs(x) for x in vals):.4f}")
