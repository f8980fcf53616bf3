#!/usr/bin/env python3
"""The OpenCV baseline of `headalign check` (docs/check.md), and its fixture.

1. The fixture: the EuRoC pairs' own calibration (data/euroc_v101_pairs/cam0_sensor.yaml,
   cam1_sensor.yaml: Kalibr intrinsics, radial-tangential lenses, and T_BS, camera to body)
   as an OpenCV stereo FileStorage YAML (M1 D1 M2 D2 R T, OpenCV's right-from-left R and T:
   x_right = R x_left + T, so R = R_BS1^T R_BS0 and T = R_BS1^T (t_BS0 - t_BS1)). Written to
   data/euroc_v101_pairs/opencv_stereo.yaml with --write-fixture.
2. The simplest OpenCV check: LK matches left -> right on the four pairs
   (goodFeaturesToTrack 2000 corners, calcOpticalFlowPyrLK both ways, kept within 0.5 px of
   the back-track), undistorted with the given K and D held (undistortPoints, P = K), the
   essential matrix by RANSAC (findEssentialMat on normalised points, 0.5 px / f), then a
   robust Sampson refit of the pose (5 degrees of freedom: rotation and the direction of t;
   Gauss-Newton with Huber weights at 1.345 MAD sigma). Prints the rotation change
   R_est R_given^T as pitch, yaw, roll about the right camera's axes (degrees) for the
   dataset's calibration and for it with the right camera turned by 0.3 deg of yaw (the
   file's R = exp(-0.3 deg y) R: the images then show a change of +0.3 deg).

3. With --write-turned DIR: the fixture with the right camera turned back by 0.3 deg of
   yaw, 0.1 deg of pitch and 0.1 deg of roll (DIR/yaw0.3.yaml, pitch0.1.yaml, roll0.1.yaml:
   R = exp(-w) R, T = exp(-w) T), the files `headalign check` is measured with.

Usage: python3 bench/check_baseline.py [--write-fixture] [--write-turned DIR]
(numpy and opencv-python; a script, not a dependency of the crates.)
"""
import os
import sys

import cv2
import numpy as np

here = os.path.dirname(os.path.abspath(__file__))
data = os.path.join(os.path.dirname(here), "data", "euroc_v101_pairs")


def sensor(name):
    """K, D, T_BS of one EuRoC sensor.yaml."""
    text = open(os.path.join(data, name)).read()
    nums = lambda key: [float(v) for v in text.split(key)[1].split("[")[1].split("]")[0].split(",")]
    fu, fv, cu, cv = nums("intrinsics:")
    k = np.array([[fu, 0, cu], [0, fv, cv], [0, 0, 1.0]])
    d = np.array(nums("distortion_coefficients:"))
    t_bs = np.array(nums("data:")).reshape(4, 4)
    return k, d, t_bs


def so3_exp(w):
    r, _ = cv2.Rodrigues(np.asarray(w, float).reshape(3, 1))
    return r


def so3_log(r):
    w, _ = cv2.Rodrigues(r)
    return w.ravel()


def fixture():
    k1, d1, b0 = sensor("cam0_sensor.yaml")
    k2, d2, b1 = sensor("cam1_sensor.yaml")
    r = b1[:3, :3].T @ b0[:3, :3]
    t = b1[:3, :3].T @ (b0[:3, 3] - b1[:3, 3])
    return k1, d1, k2, d2, r, t


def write_fixture(path, turn=np.eye(3)):
    k1, d1, k2, d2, r, t = fixture()
    r, t = turn @ r, turn @ t
    fmt = lambda m: ", ".join(repr(float(v)) for v in np.asarray(m).ravel())
    mat = lambda name, m, rows, cols: (
        f"{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n   data: [ {fmt(m)} ]\n"
    )
    with open(path, "w") as f:
        f.write("%YAML:1.0\n---\n")
        f.write("# EuRoC V1_01_easy stereo calibration (Kalibr), from cam0_sensor.yaml and cam1_sensor.yaml:\n")
        f.write("# R = R_BS1^T R_BS0, T = R_BS1^T (t_BS0 - t_BS1) (x_right = R x_left + T, metres);\n")
        f.write("# written by bench/check_baseline.py --write-fixture\n")
        f.write("image_width: 752\nimage_height: 480\ndistortion_model: plumb_bob\n")
        f.write(mat("M1", k1, 3, 3) + mat("D1", d1, 1, 4) + mat("M2", k2, 3, 3) + mat("D2", d2, 1, 4))
        f.write(mat("R", r, 3, 3) + mat("T", t, 3, 1))


def lk_matches():
    k1, d1, k2, d2, _, _ = fixture()
    pl, pr = [], []
    for i in range(4):
        a = cv2.imread(os.path.join(data, f"left_img_{i}.png"), cv2.IMREAD_GRAYSCALE)
        b = cv2.imread(os.path.join(data, f"right_img_{i}.png"), cv2.IMREAD_GRAYSCALE)
        p0 = cv2.goodFeaturesToTrack(a, 2000, 0.01, 7)
        p1, s1, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, None, winSize=(21, 21), maxLevel=3)
        p2, s2, _ = cv2.calcOpticalFlowPyrLK(b, a, p1, None, winSize=(21, 21), maxLevel=3)
        ok = (s1.ravel() == 1) & (s2.ravel() == 1) & (np.linalg.norm((p2 - p0).reshape(-1, 2), axis=1) < 0.5)
        pl.append(cv2.undistortPoints(p0[ok], k1, d1, P=k1).reshape(-1, 2))
        pr.append(cv2.undistortPoints(p1[ok], k2, d2, P=k2).reshape(-1, 2))
    return np.vstack(pl), np.vstack(pr)


def sampson(f, xl, xr):
    hl = np.hstack([xl, np.ones((len(xl), 1))])
    hr = np.hstack([xr, np.ones((len(xr), 1))])
    fx = hl @ f.T
    ftx = hr @ f
    return np.sum(hr * fx, axis=1) / np.sqrt(fx[:, 0] ** 2 + fx[:, 1] ** 2 + ftx[:, 0] ** 2 + ftx[:, 1] ** 2)


def refit(r, t, k1, k2, xl, xr):
    """Huber-weighted Gauss-Newton of the Sampson distances in (rotation, t direction)."""
    ki1, ki2 = np.linalg.inv(k1), np.linalg.inv(k2)
    f_of = lambda r, t: ki2.T @ (np.cross(np.eye(3), t) @ r) @ ki1

    def step(r, t, d):
        a = np.array([1.0, 0, 0]) if abs(t[0]) < 0.9 else np.array([0, 1.0, 0])
        b1 = np.cross(t, a)
        b1 /= np.linalg.norm(b1)
        b2 = np.cross(t, b1)
        tn = t + b1 * d[3] + b2 * d[4]
        return so3_exp(d[:3]) @ r, tn / np.linalg.norm(tn)

    t = t / np.linalg.norm(t)
    for _ in range(30):
        res = sampson(f_of(r, t), xl, xr)
        sigma = 1.4826 * np.median(np.abs(res))
        w = np.minimum(1.0, 1.345 * sigma / np.maximum(np.abs(res), 1e-12))
        jac = np.zeros((len(res), 5))
        for k in range(5):
            d = np.zeros(5)
            d[k] = 1e-7
            jac[:, k] = (sampson(f_of(*step(r, t, d)), xl, xr) - sampson(f_of(*step(r, t, -d)), xl, xr)) / 2e-7
        h = jac.T @ (jac * w[:, None])
        g = jac.T @ (w * res)
        d = -np.linalg.solve(h, g)
        r, t = step(r, t, d)
        if np.linalg.norm(d) < 1e-12:
            break
    return r, t


def baseline(r_given, t_given, xl, xr):
    k1, _, k2, _, _, _ = fixture()
    nl = cv2.undistortPoints(xl.reshape(-1, 1, 2), k1, None).reshape(-1, 2)
    nr = cv2.undistortPoints(xr.reshape(-1, 1, 2), k2, None).reshape(-1, 2)
    e, mask = cv2.findEssentialMat(nl, nr, np.eye(3), cv2.RANSAC, 0.999, 0.5 / k1[0, 0])
    _, r, t, mask = cv2.recoverPose(e, nl, nr, np.eye(3), mask=mask)
    keep = mask.ravel() > 0
    r, t = refit(r, t.ravel() * np.sign(t.ravel() @ t_given), k1, k2, xl[keep], xr[keep])
    return np.degrees(so3_log(r @ r_given.T)), int(keep.sum())


def main():
    if "--write-fixture" in sys.argv:
        write_fixture(os.path.join(data, "opencv_stereo.yaml"))
    if "--write-turned" in sys.argv:
        out = sys.argv[sys.argv.index("--write-turned") + 1]
        os.makedirs(out, exist_ok=True)
        for name, w in [("yaw0.3", [0, 0.3, 0]), ("pitch0.1", [0.1, 0, 0]), ("roll0.1", [0, 0, 0.1])]:
            write_fixture(os.path.join(out, name + ".yaml"), so3_exp(-np.radians(w)))
    _, _, _, _, r, t = fixture()
    xl, xr = lk_matches()
    print(f"{len(xl)} LK matches over 4 pairs")
    for name, w in [("dataset", [0, 0, 0]), ("yaw +0.3", [0, 0.3, 0]), ("pitch +0.1", [0.1, 0, 0]), ("roll +0.1", [0, 0, 0.1])]:
        turn = so3_exp(-np.radians(w))
        change, inliers = baseline(turn @ r, turn @ t, xl, xr)
        err = change - np.array(w)
        print(f"{name:10s}: change pitch {change[0]:+.4f} yaw {change[1]:+.4f} roll {change[2]:+.4f} deg "
              f"(error {err[0]:+.4f} {err[1]:+.4f} {err[2]:+.4f}; {inliers} RANSAC inliers)")


if __name__ == "__main__":
    main()
