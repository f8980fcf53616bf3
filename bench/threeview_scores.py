#!/usr/bin/env python3
"""Score `headalign align` on three-view sessions with truth (the format of
data/threeview_sessions: seedNN/session.json and seedNN/truth.json, whose
README defines the scoring) against three sigmas, per image axis:

  readings   the fixation point's error over the true focal length, in degrees, against
             `aligned_sigma_deg` (x: the camera's vergence sigma, y: the elevation
             sigma): the README's scoring
  fixation   the fixation point's error in pixels against `fixation_sigma_px`
  pp-rel     the angle of the fixation point from the principal point (what a reading
             turns: the optical axis onto the target), estimate against truth, against
             `aligned_sigma_deg`

For each: z RMS, mean z and the share within 1.96 (both cameras pooled); then the x
sigmas (medians over the cameras) of the fixation point, the principal point and the
vergence reading (in pixels at the estimated focal length) and their ratio, and the
elevation reading's sigma over the fixation point's y sigma; the correlation of the
fixation points' x z-scores with the true fx and (where the truth has the axes) with the
axes' non-orthogonality.
A reading's error is the fixation point's less the principal point's, so `readings`
mixes two quantities (docs/accuracy.md, "Three-view sessions").

usage: bench/threeview_scores.py [DIR] [--bin PATH] [--first N]
  DIR    default data/threeview_sessions (in the repository)
  --bin  default target/release/headalign
"""
import glob, json, math, os, subprocess, sys

args = sys.argv[1:]
if "-h" in args or "--help" in args:
    sys.exit(__doc__)
repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
exe = os.path.join(repo, "target/release/headalign")
first = None
pos = []
while args:
    a = args.pop(0)
    if a == "--bin":
        exe = args.pop(0)
    elif a == "--first":
        first = int(args.pop(0))
    else:
        pos.append(a)
root = os.path.normpath(pos[0] if pos else os.path.join(repo, "data/threeview_sessions"))
dirs = sorted(glob.glob(os.path.join(root, "seed*")))[:first]
if not dirs:
    sys.exit(f"no seed*/ folders in {root}")

z = {(m, a): [] for m in ("readings", "fixation", "pp-rel") for a in ("x", "y")}
sx = []  # per camera: x sigmas in pixels of the fixation point, the principal point, the reading
sy = []  # per camera: y sigmas of the fixation point and of the elevation reading, pixels
tied = []  # per camera: (fixation x z, axes' non-orthogonality in degrees or None, true fx)
for d in dirs:
    truth = json.load(open(os.path.join(d, "truth.json")))
    run = subprocess.run([exe, "align", "--observations", os.path.join(d, "session.json"), "--json"],
                         capture_output=True, text=True)
    if run.returncode != 0:
        print(f"{d}: align failed: {run.stderr.strip()[:300]}")
        continue
    out = json.loads(run.stdout)
    s = out["aligned_sigma_deg"]
    for cam in ("left", "right"):
        k, e = truth[f"{cam}_K"], out[cam]
        sx.append((out["fixation_sigma_px"][cam][0], e["sigma"]["cx"], math.radians(s[f"verge_{cam}_deg"]) * e["fx"]))
        sy.append((out["fixation_sigma_px"][cam][1], math.radians(s["elevation_deg"]) * e["fy"]))
        reading_sigma = {"x": s[f"verge_{cam}_deg"], "y": s["elevation_deg"]}
        for i, a in enumerate(("x", "y")):
            f_true, c_true = k[i][i], k[i][2]
            f_est, c_est = e["fx" if a == "x" else "fy"], e["cx" if a == "x" else "cy"]
            u_true, u_est = truth["fixation_px"][cam][i], out["fixation_px"][cam][i]
            z["readings", a].append(math.degrees((u_est - u_true) / f_true) / reading_sigma[a])
            z["fixation", a].append((u_est - u_true) / out["fixation_sigma_px"][cam][i])
            turn = math.atan((u_est - c_est) / f_est) - math.atan((u_true - c_true) / f_true)
            z["pp-rel", a].append(math.degrees(turn) / reading_sigma[a])
        p, e_ax = truth.get("pan_axis"), truth.get("elevation_axis")
        skew = math.degrees(math.asin(abs(sum(x * y for x, y in zip(p, e_ax))))) if p and e_ax else None
        tied.append((z["fixation", "x"][-1], skew, k[0][0]))

print(f"{len(dirs)} sessions in {root}")
print("| scoring | axis | z RMS | mean z | within 1.96 |")
print("|---|---|---|---|---|")
for (m, a), v in z.items():
    n = len(v)
    rms = math.sqrt(sum(x * x for x in v) / n)
    cov = 100.0 * sum(abs(x) < 1.96 for x in v) / n
    print(f"| {m} | {a} | {rms:.2f} | {sum(v) / n:+.2f} | {cov:.0f} % ({n}) |")
med = lambda v: sorted(v)[len(v) // 2]
ratios = [f / r for f, _, r in sx]
print(f"x sigmas, median over cameras: fixation point {med([f for f, _, _ in sx]):.1f} px, "
      f"principal point {med([c for _, c, _ in sx]):.1f} px, vergence reading {med([r for _, _, r in sx]):.1f} px; "
      f"fixation over reading {min(ratios):.2f}-{max(ratios):.2f} (median {med(ratios):.2f})")
ry = [r / f for f, r in sy]
print(f"y: the elevation reading's sigma over the fixation point's {min(ry):.2f}-{max(ry):.2f} (median {med(ry):.2f})")


def corr(a, b):
    ma, mb = sum(a) / len(a), sum(b) / len(b)
    cov = sum((x - ma) * (y - mb) for x, y in zip(a, b))
    return cov / math.sqrt(sum((x - ma) ** 2 for x in a) * sum((y - mb) ** 2 for y in b))


zx = [t[0] for t in tied]
line = f"fixation x z: correlation with the true fx {corr(zx, [t[2] for t in tied]):+.2f}"
if all(t[1] is not None for t in tied):
    skews = [t[1] for t in tied]
    line += f", with the axes' non-orthogonality ({min(skews):.2f}-{max(skews):.2f} deg) {corr(zx, skews):+.2f}"
print(line)
