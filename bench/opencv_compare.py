#!/usr/bin/env python3
"""OpenCV reference timings for the headalign-vision benches (crates/headalign-vision/benches/vision.rs).

Same image, same crops, same three operations, one thread (cv2.setNumThreads(1); set
OPENCV_THREADS=2 for two, to compare with RAYON_NUM_THREADS=2):
  detect_describe_768x576  ORB_create(nfeatures=1000).detectAndCompute (default 8-level pyramid),
                           plus a single-level ORB for reference
  match_1000x1000          BFMatcher(NORM_HAMMING, crossCheck=True).match
  pyramid_register         pyrDown pyramids (5 levels) + matchTemplate(TM_CCOEFF_NORMED): the central
                           part of the reference searched exhaustively at the top level, then +-1 px
                           per finer level (the paper's pyramid correlation). Like for like,
                           ours does more: its coarsest search covers shifts of +-50 % of
                           the side over the whole overlap (this one +-25 % with a central
                           half template), then the same +-1 px central-half search per
                           level, plus a sub-pixel fit.
Needs `pip install opencv-python-headless` (for this script only; never a crate dependency).
Image: OpenCV sample textures/building.jpg (Apache-2.0 / BSD-3-Clause), override with argv[1].
"""
import os
import sys
import time

import cv2
import numpy as np

cv2.setNumThreads(int(os.environ.get("OPENCV_THREADS", "1")))
# The default image: the repository's data/ folder (as the vision bench's default).
DEFAULT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "data",
                       "opencv_samples", "textures", "building.jpg")
PATH = sys.argv[1] if len(sys.argv) > 1 else os.path.normpath(DEFAULT)
if not os.path.isfile(PATH):
    sys.exit(f"{PATH} is absent: give the image's path")


def timeit(fn, reps=50):
    fn()
    best, times = float("inf"), []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    times.sort()
    return 1e3 * times[len(times) // 2]  # median, ms


def cputime(fn, reps=50):
    """Process CPU time per call, mean, ms: on a loaded machine a fairer cross-check than wall time."""
    fn()
    t = time.process_time()
    for _ in range(reps):
        fn()
    return 1e3 * (time.process_time() - t) / reps


def register(ref, mov, levels=5, max_frac=0.5):
    pr, pm = [ref.astype(np.float32)], [mov.astype(np.float32)]
    for _ in range(levels - 1):
        pr.append(cv2.pyrDown(pr[-1]))
        pm.append(cv2.pyrDown(pm[-1]))
    # Top level: template = reference minus a margin of max_frac/2 per side, searched exhaustively.
    h, w = pr[-1].shape
    mx, my = int(w * max_frac / 2), int(h * max_frac / 2)
    tmpl = pr[-1][my:h - my, mx:w - mx]
    res = cv2.matchTemplate(pm[-1], tmpl, cv2.TM_CCOEFF_NORMED)
    _, _, _, loc = cv2.minMaxLoc(res)
    d = np.array([loc[0] - mx, loc[1] - my])
    for k in range(levels - 2, -1, -1):
        d = 2 * d
        h, w = pr[k].shape
        mx, my = int(w * max_frac / 2), int(h * max_frac / 2)
        tmpl = pr[k][my:h - my, mx:w - mx]
        x0, y0 = mx + d[0] - 1, my + d[1] - 1
        x0, y0 = max(0, min(x0, w - tmpl.shape[1] - 2)), max(0, min(y0, h - tmpl.shape[0] - 2))
        win = pm[k][y0:y0 + tmpl.shape[0] + 2, x0:x0 + tmpl.shape[1] + 2]
        res = cv2.matchTemplate(win, tmpl, cv2.TM_CCOEFF_NORMED)
        _, _, _, loc = cv2.minMaxLoc(res)
        d = np.array([x0 + loc[0] - mx, y0 + loc[1] - my])
    return d


def main():
    full = cv2.imread(PATH, cv2.IMREAD_GRAYSCALE)
    ref = np.ascontiguousarray(full[20:20 + 576, 60:60 + 768])
    mov = np.ascontiguousarray(full[8:8 + 576, 40:40 + 768])
    print(f"OpenCV {cv2.__version__}, threads {cv2.getNumThreads()}, image {PATH} crops 768x576")

    orb = cv2.ORB_create(nfeatures=1000)
    t_orb = timeit(lambda: orb.detectAndCompute(ref, None))
    orb1 = cv2.ORB_create(nfeatures=1000, nlevels=1)
    t_orb1 = timeit(lambda: orb1.detectAndCompute(ref, None))
    ka, da = orb.detectAndCompute(ref, None)
    kb, db = orb.detectAndCompute(mov, None)
    print(f"detect_describe_768x576  ORB 8 levels: {t_orb:.2f} ms ({len(ka)} features); "
          f"ORB 1 level: {t_orb1:.2f} ms")

    bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    t_bf = timeit(lambda: bf.match(da, db))
    m = bf.match(da, db)
    ok = sum(1 for x in m if np.hypot(kb[x.trainIdx].pt[0] - ka[x.queryIdx].pt[0] - 20,
                                      kb[x.trainIdx].pt[1] - ka[x.queryIdx].pt[1] - 12) < 1.5)
    print(f"match_1000x1000          BFMatcher Hamming crossCheck: {t_bf:.2f} ms "
          f"({len(da)}x{len(db)}, {len(m)} matches, {ok} at the true shift)")

    t_reg = timeit(lambda: register(ref, mov))
    print(f"pyramid_register         pyrDown + matchTemplate: {t_reg:.2f} ms (shift {register(ref, mov)}, "
          f"true [20 12])")
    c_orb, c_bf = cputime(lambda: orb.detectAndCompute(ref, None)), cputime(lambda: bf.match(da, db))
    c_reg = cputime(lambda: register(ref, mov))
    print(f"CPU per call (process time, mean): ORB {c_orb:.2f} ms, BFMatcher {c_bf:.2f} ms, "
          f"registration {c_reg:.2f} ms")


if __name__ == "__main__":
    main()
