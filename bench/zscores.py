#!/usr/bin/env python3
"""Per-trial z-scores of an `headalign experiment` CSV: why an RMS-error / Cramer-Rao
ratio or a 95 % coverage misses its bar (a heavy tail, a bias, or a sigma too small).

usage: bench/zscores.py CSV [QUANTITY[,QUANTITY...]] [--group G] [--noise N] [--top K]

For every (group, noise) row and quantity it prints, over the successful trials:
  ratio    RMS(est - truth) / RMS(crb)          (the docs' ratio; CI from chi-square, n dof)
  bias     mean(est - truth) / RMS(crb)
  sd       std(est - truth) / RMS(crb)
  cov      % of trials with |est - truth| <= 1.96 sigma   (the docs' coverage)
  sd(z)    std of z = (est - truth) / sigma  (the reported sigma, at the estimate)
  s/c      median over trials of sigma / crb  (covariance at the estimate vs at the truth)
  |z|>3    trials beyond 3 reported sigmas (0.7 expected in 250)
  wo3      the ratio without the 3 trials of largest |est - truth| / crb
  recon>20 trials whose reconstruction error exceeds 20 % (the far-scene regime) and
           the coverage without them
With --top K, the K trials of largest |z| of the selected quantities (seed, z, z at the
bound, sigma / crb, reconstruction error).
Rows of one grid share their seeds and the simulator scales one noise draw by the noise
level, so the rows of a grid are not independent samples (zc correlates 0.7-0.98 between
noise levels); only another seed range is.
"""
import csv, math, sys

args = sys.argv[1:]
if not args:
    sys.exit(__doc__)
opt = {}
pos = []
i = 0
while i < len(args):
    if args[i].startswith("--"):
        opt[args[i][2:]] = args[i + 1]
        i += 2
    else:
        pos.append(args[i])
        i += 1
rows = [r for r in csv.DictReader(open(pos[0])) if r["ok"] == "true"]
if not rows:
    sys.exit("no successful trials")
qs = [k[:-4] for k in rows[0] if k.endswith(".est")]
if len(pos) > 1:
    qs = [q for q in qs if q in pos[1].split(",")]


def num(r, k):
    try:
        return float(r[k])
    except (ValueError, KeyError):
        return math.nan


def mean(v):
    return sum(v) / len(v)


def median(v):
    s = sorted(v)
    return s[len(s) // 2] if len(s) % 2 else 0.5 * (s[len(s) // 2 - 1] + s[len(s) // 2])


groups = {}
for r in rows:
    key = (r["group"], num(r, "noise_px"))
    if "group" in opt and key[0] != opt["group"]:
        continue
    if "noise" in opt and abs(key[1] - float(opt["noise"])) > 1e-9:
        continue
    groups.setdefault(key, []).append(r)
top = []
for (g, n), rs in sorted(groups.items()):
    if n == 0:
        continue
    for q in qs:
        t = []
        for r in rs:
            e, s, c = num(r, q + ".est") - num(r, q + ".truth"), num(r, q + ".sigma"), num(r, q + ".crb")
            if all(math.isfinite(x) for x in (e, s, c)) and s > 0 and c > 0:
                t.append((e, s, c, num(r, "recon_err_pct"), r["seed"]))
        if len(t) < 2:
            continue
        m = len(t)
        e = [x[0] for x in t]
        crb = math.sqrt(mean([x[2] ** 2 for x in t]))
        ratio = math.sqrt(mean([x * x for x in e])) / crb
        # chi-square with m dof: 95 % band of the ratio of an efficient estimator
        lo, hi = math.sqrt(1 - 1.96 * math.sqrt(2 / m)), math.sqrt(1 + 1.96 * math.sqrt(2 / m))
        z = [x[0] / x[1] for x in t]
        mz = mean(z)
        cov = 100 * mean([abs(v) <= 1.96 for v in z])
        worst = sorted(range(m), key=lambda k: -abs(t[k][0] / t[k][2]))[:3]
        keep = [k for k in range(m) if k not in worst]
        wo3 = math.sqrt(mean([t[k][0] ** 2 for k in keep])) / math.sqrt(mean([t[k][2] ** 2 for k in keep]))
        far = [k for k in range(m) if t[k][3] > 20]
        near = [k for k in range(m) if t[k][3] <= 20]
        cov_near = 100 * mean([abs(z[k]) <= 1.96 for k in near]) if near else math.nan
        print(
            f"{g:6} {n:4} {q:24} n={m:4} ratio={ratio:.3f} [{ratio / hi:.2f}-{ratio / lo:.2f}] wo3={wo3:.3f} "
            f"bias={mean(e) / crb:+.3f} sd={math.sqrt(mean([(x - mean(e)) ** 2 for x in e])) / crb:.3f} "
            f"cov={cov:5.1f} sd(z)={math.sqrt(mean([(v - mz) ** 2 for v in z])):.3f} "
            f"s/c={median([x[1] / x[2] for x in t]):.3f} |z|>3={sum(abs(v) > 3 for v in z)} "
            f"recon>20={len(far)} cov_without={cov_near:5.1f}"
        )
        for k in range(m):
            top.append((abs(z[k]), g, n, q, t[k]))
if "top" in opt:
    print("\nlargest |z| (seed group noise quantity: z, z at the bound, sigma/crb, reconstruction error %):")
    for az, g, n, q, (e, s, c, rec, seed) in sorted(top, key=lambda x: -x[0])[: int(opt["top"])]:
        print(f"  {seed:>5} {g} {n} {q}: z={e / s:+.2f} zc={e / c:+.2f} s/c={s / c:.3f} recon={rec:.1f}")
