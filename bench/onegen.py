#!/usr/bin/env python3
"""Focal length error of `calibrate` on rendered one-general-motion sessions over seeds.

usage: bench/onegen.py FIRST LAST [--distortion K1 K2] [--estimate-distortion] [--keep DIR]
                        [--motion general|rotations] [--exe PATH] [--reuse] [--near N] [--procedural]
                        [-- CALIBRATE FLAGS...]

For each seed: `headalign simulate --images --motion general --seed N --scenario S` (S: the
default scenario with square-pixel cameras, as `--square-pixels` assumes; with
--distortion a barrel lens in the renderer), then `headalign calibrate DIR --zero-skew
--square-pixels --json` (plus --estimate-distortion), and the errors against the
simulator's truth.json. `--motion rotations` records two head rotations instead (the
default scenario's cameras, calibrated with no constraints). Flags after `--` go to
`calibrate` (e.g. `-- --tracking reference`); `--procedural` renders the
procedural textures (`render.use_photos = false`); `--near N` adds N near
panels (Scenario::near_panels) to the scene; `--reuse` keeps the sessions already in
the --keep folder (compare calibrate flags on the same images). Prints one line per seed and a summary; a seed whose calibrate
warns is marked "warned", and one that `calibrate` re-detected with more corners (its
first calibration weak or failed; the JSON's `density`) names the first result and the
corners kept.
"""
import json, math, os, subprocess, sys, tempfile

args = sys.argv[1:]
extra = []
if "--" in args:
    extra = args[args.index("--") + 1:]
    args = args[:args.index("--")]
first, last = int(args[0]), int(args[1])
rest = args[2:]
k = None
if "--distortion" in rest:
    i = rest.index("--distortion")
    k = (float(rest[i + 1]), float(rest[i + 2]))
estimate = "--estimate-distortion" in rest
keep = rest[rest.index("--keep") + 1] if "--keep" in rest else None
exe = rest[rest.index("--exe") + 1] if "--exe" in rest else "target/release/headalign"
motion = rest[rest.index("--motion") + 1] if "--motion" in rest else "general"
general = motion == "general"
tmp = keep or tempfile.mkdtemp(prefix="onegen-")
os.makedirs(tmp, exist_ok=True)
scenario = os.path.join(tmp, "square.toml")
with open(scenario, "w") as f:
    if "--near" in rest:
        f.write(f"near_panels = {int(rest[rest.index('--near') + 1])}\n")
    if general:
        f.write("[left]\nfx = 700.0\nfy = 700.0\nskew = 0.0\ncx = 390.0\ncy = 284.0\n")
        f.write("[right]\nfx = 705.0\nfy = 705.0\nskew = 0.0\ncx = 380.0\ncy = 290.0\n")
    if "--procedural" in rest:
        f.write("[render]\nuse_photos = false\n")
    if k:
        f.write(f"[render.distortion]\nk1 = {k[0]}\nk2 = {k[1]}\n")
errs, fails, warned = [], 0, 0
for seed in range(first, last + 1):
    d = os.path.join(tmp, f"gen{seed}")
    if os.path.exists(os.path.join(d, "truth.json")) and "--reuse" in rest:
        p = subprocess.CompletedProcess([], 0)
    else:
        subprocess.run(["rm", "-rf", d])
        p = subprocess.run([exe, "simulate", "--images", "--motion", motion, "--seed", str(seed), "--scenario", scenario, "--out", d], capture_output=True, text=True)
    if p.returncode != 0:
        print(f"seed {seed}: simulate FAILED {p.stderr.strip()}")
        fails += 1
        continue
    cmd = [exe, "calibrate", d, "--json"] + (["--zero-skew", "--square-pixels"] if general else [])
    cmd += (["--estimate-distortion"] if estimate else []) + extra
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        print(f"seed {seed}: calibrate FAILED {p.stderr.strip()}")
        fails += 1
        continue
    v = json.loads(p.stdout)
    truth = json.load(open(os.path.join(d, "truth.json")))
    e = {c: 100.0 * (v[c]["fx"] - truth[c]["fx"]) / truth[c]["fx"] for c in ("left", "right")}
    s = {c: 100.0 * (v[c]["sigma"]["fx"] or float("nan")) / v[c]["fx"] for c in ("left", "right")}
    w = bool(v["report"].get("warnings"))
    warned += w
    line = f"seed {seed}: f err L {e['left']:+.3f} % R {e['right']:+.3f} % (sigma {s['left']:.3f} / {s['right']:.3f} %), noise {v['report']['sigma_px']:.3f} px"
    if estimate:
        dl, dr = v["distortion"]["left"], v["distortion"]["right"]
        sk = v["distortion"]["sigma"]
        line += f", k1 {dl[0]:+.4f}/{dr[0]:+.4f} (sigma {sk['left.k1'] or float('nan'):.4f}), k2 {dl[1]:+.4f}/{dr[1]:+.4f}"
    d = v.get("density") or {}
    if len(d.get("trials", [])) > 1:
        first = d["trials"][0]
        was = "failed" if first["error"] else f"f {100.0 * (first['focal_px'][0] - truth['left']['fx']) / truth['left']['fx']:+.3f} %"
        line += f", re-detected ({first['corners']} corners: {was}), kept {d['trials'][d['kept']]['corners']}"
        if d.get("disagreement_sigmas") is not None:
            line += f" (the two differ by {d['disagreement_sigmas']:.1f} combined sigmas)"
    if w:
        line += " warned"
    print(line, flush=True)
    errs.append(max(abs(e["left"]), abs(e["right"])))
if errs:
    within = sum(1 for x in errs if x < 1.0)
    rms = math.sqrt(sum(x * x for x in errs) / len(errs))
    print(f"{len(errs)} ran, {fails} failed, {warned} warned; worse camera within 1 %: {within} of {len(errs)}; RMS {rms:.3f} %, worst {max(errs):.3f} %")
