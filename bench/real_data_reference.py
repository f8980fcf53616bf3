#!/usr/bin/env python3
"""Reference numbers for docs/real-data.md from the data's own calibration, with OpenCV
(pip opencv-python-headless; a script, not a dependency of the crates).

1. OpenCV stereo chessboard (data/opencv_samples/stereo_chessboard): the board's
   corners in every pair (findChessboardCorners + cornerSubPix, 9x6, 25 mm), then
   cv2.stereoCalibrate: once with the data's intrinsics.yml held fixed (its RMS shows how
   well that file fits), once re-estimating everything from it (the reference: M1 D1 M2 D2
   R T written to crates/headalign-cli/tests/data/chessboard_reference.yml). The corners,
   undistorted with the reference M/D (pixels of the same K), are written to
   crates/headalign-cli/tests/data/chessboard_corners.json so that the Rust tests can
   check an F against exact correspondences without OpenCV.
2. Prints the epipolar distances of those corners under F_ref.

Usage: python3 bench/real_data_reference.py [DATA_DIR]
"""
import json
import os
import sys

import cv2
import numpy as np

here = os.path.dirname(os.path.abspath(__file__))
root = os.path.dirname(here)
data = sys.argv[1] if len(sys.argv) > 1 else os.path.join(root, "data")
board = os.path.join(data, "opencv_samples", "stereo_chessboard")

fs = cv2.FileStorage(os.path.join(board, "intrinsics.yml"), cv2.FILE_STORAGE_READ)
M1, D1, M2, D2 = (fs.getNode(n).mat() for n in ("M1", "D1", "M2", "D2"))
pattern = (9, 6)
square = 0.025
obj = np.zeros((pattern[0] * pattern[1], 3), np.float32)
obj[:, :2] = np.mgrid[0 : pattern[0], 0 : pattern[1]].T.reshape(-1, 2) * square

names = sorted(n for n in os.listdir(board) if n.startswith("left") and n.endswith(".jpg"))
objs, pts_l, pts_r, used = [], [], [], []
crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
for n in names:
    gl = cv2.imread(os.path.join(board, n), cv2.IMREAD_GRAYSCALE)
    gr = cv2.imread(os.path.join(board, n.replace("left", "right")), cv2.IMREAD_GRAYSCALE)
    ok_l, cl = cv2.findChessboardCorners(gl, pattern)
    ok_r, cr = cv2.findChessboardCorners(gr, pattern)
    if not (ok_l and ok_r):
        print(f"{n}: board not found in both images, skipped")
        continue
    cl = cv2.cornerSubPix(gl, cl, (11, 11), (-1, -1), crit)
    cr = cv2.cornerSubPix(gr, cr, (11, 11), (-1, -1), crit)
    objs.append(obj)
    pts_l.append(cl)
    pts_r.append(cr)
    used.append(n)

size = (640, 480)
rms_fixed, _, _, _, _, R0, T0, _, _ = cv2.stereoCalibrate(
    objs, pts_l, pts_r, M1, D1, M2, D2, size, flags=cv2.CALIB_FIX_INTRINSIC
)
print(f"stereoCalibrate with the data's intrinsics.yml held fixed: RMS {rms_fixed:.3f} px")
# The reference: everything re-estimated from the board (intrinsics.yml as the start),
# plumb_bob with k3, square pixels as the data's file assumes.
flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_ASPECT_RATIO
rms, M1, D1, M2, D2, R, T, E, F = cv2.stereoCalibrate(
    objs, pts_l, pts_r, M1.copy(), D1.copy(), M2.copy(), D2.copy(), size, flags=flags
)
print("reference (all re-estimated):")
print("M1", np.round(M1, 3).tolist(), "D1", np.round(D1.ravel(), 4).tolist())
print("M2", np.round(M2, 3).tolist(), "D2", np.round(D2.ravel(), 4).tolist())
ref_path = os.path.join(root, "crates", "headalign-cli", "tests", "data", "chessboard_reference.yml")
os.makedirs(os.path.dirname(ref_path), exist_ok=True)
out_fs = cv2.FileStorage(ref_path, cv2.FILE_STORAGE_WRITE)
for k, v in (("M1", M1), ("D1", D1), ("M2", M2), ("D2", D2), ("R", R), ("T", T)):
    out_fs.write(k, v)
out_fs.release()
print(f"wrote {ref_path}")
angle = np.degrees(np.linalg.norm(cv2.Rodrigues(R)[0]))
axis = (cv2.Rodrigues(R)[0].ravel() / np.linalg.norm(cv2.Rodrigues(R)[0])).tolist()
print(f"stereoCalibrate (reference) over {len(used)} pairs: RMS {rms:.3f} px")
print(f"R: {angle:.3f} deg about {np.round(axis, 4).tolist()}")
print(f"T: {T.ravel().tolist()} m, |T| = {np.linalg.norm(T):.5f} m, direction {np.round(T.ravel() / np.linalg.norm(T), 4).tolist()}")

# Undistorted corners, in pixels of the same K.
ul = [cv2.undistortPoints(p, M1, D1, P=M1).reshape(-1, 2) for p in pts_l]
ur = [cv2.undistortPoints(p, M2, D2, P=M2).reshape(-1, 2) for p in pts_r]
tx = np.array([[0, -T[2, 0], T[1, 0]], [T[2, 0], 0, -T[0, 0]], [-T[1, 0], T[0, 0], 0]])
F_ref = np.linalg.inv(M2).T @ tx @ R @ np.linalg.inv(M1)


def epi(Fm, a, b):
    a1 = np.c_[a, np.ones(len(a))]
    b1 = np.c_[b, np.ones(len(b))]
    lr = a1 @ Fm.T
    ll = b1 @ Fm
    dr = np.abs(np.sum(b1 * lr, 1)) / np.hypot(lr[:, 0], lr[:, 1])
    dl = np.abs(np.sum(a1 * ll, 1)) / np.hypot(ll[:, 0], ll[:, 1])
    return np.r_[dr, dl]


d = epi(F_ref, np.vstack(ul), np.vstack(ur))
print(f"corners under F_ref (undistorted): RMS {np.sqrt(np.mean(d**2)):.3f} px, max {d.max():.3f} px")
out = {
    "source": "OpenCV 4.6.0 samples/data stereo chessboard; corners by cv2.findChessboardCorners + cornerSubPix, undistorted with chessboard_reference.yml (M1 D1, M2 D2) into pixels of the same K (bench/real_data_reference.py)",
    "views": used,
    "left": [p.tolist() for p in ul],
    "right": [p.tolist() for p in ur],
    "reference_R": R.tolist(),
    "reference_T_m": T.ravel().tolist(),
    "stereo_calibrate_rms_px": rms,
}
dest = os.path.join(root, "crates", "headalign-cli", "tests", "data")
os.makedirs(dest, exist_ok=True)
with open(os.path.join(dest, "chessboard_corners.json"), "w") as f:
    json.dump(out, f)
print(f"wrote {os.path.join(dest, 'chessboard_corners.json')}")
