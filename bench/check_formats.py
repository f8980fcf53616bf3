#!/usr/bin/env python3
"""Read every calibration file `headalign align --out DIR` or `headalign calibrate --out
DIR` writes with its ecosystem's reader and check it against calibration.json (head.json
and alignment.json only where align wrote them; calibrate writes calibrate_report.json).

usage: bench/check_formats.py DIR
needs: pip install opencv-python-headless pyyaml numpy (for this script only)
"""
import json, sys
import numpy as np
import cv2, yaml

d = sys.argv[1]
cal = json.load(open(f"{d}/calibration.json"))
ok = True

def check(name, a, b, tol=1e-12):
    global ok
    a, b = np.asarray(a, float), np.asarray(b, float)
    good = a.shape == b.shape and np.allclose(a, b, rtol=tol, atol=tol)
    ok &= good
    print(f"{'ok ' if good else 'BAD'} {name}")

# OpenCV FileStorage
fs = cv2.FileStorage(f"{d}/opencv_stereo.yaml", cv2.FILE_STORAGE_READ)
if not fs.isOpened():
    sys.exit("cv2.FileStorage cannot open opencv_stereo.yaml")
m = {k: fs.getNode(k).mat() for k in ["M1", "D1", "M2", "D2", "R", "T", "R1", "R2", "P1", "P2", "Q"]}
check("opencv M1 == left K", m["M1"], cal["left"]["K"])
check("opencv M2 == right K", m["M2"], cal["right"]["K"])
check("opencv R", m["R"], cal["right_from_left"]["R"])
check("opencv T", m["T"].ravel(), cal["right_from_left"]["t"])
check("opencv D1 == left distortion", m["D1"].ravel(), cal["left"]["distortion_coefficients"])
check("opencv D2 == right distortion", m["D2"].ravel(), cal["right"]["distortion_coefficients"])
for k in ["R1", "R2", "P1", "P2", "Q"]:
    check(f"opencv {k}", m[k], cal["rectification"][k])
w, h = int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real())
# OpenCV can build the rectification maps from them.
m1, m2 = cv2.initUndistortRectifyMap(m["M1"], m["D1"], m["R1"], m["P1"], (w, h), cv2.CV_32FC1)
print(f"ok  cv2.initUndistortRectifyMap {m1.shape}")
# A point triangulated from the rectified pair reprojects on one row in both images.
X = np.array([[0.3, -0.2, 3.0]]).T
R, T = m["R"], m["T"].reshape(3, 1)
xl, _ = cv2.projectPoints(X.T, np.zeros(3), np.zeros(3), m["M1"], m["D1"])
xr, _ = cv2.projectPoints(X.T, cv2.Rodrigues(R)[0], T, m["M2"], m["D2"])
ul = cv2.undistortPoints(xl, m["M1"], m["D1"], R=m["R1"], P=m["P1"]).ravel()
ur = cv2.undistortPoints(xr, m["M2"], m["D2"], R=m["R2"], P=m["P2"]).ravel()
check("rectified rows agree (OpenCV undistortPoints)", ul[1], ur[1], tol=1e-6)

# ROS camera_info
for side in ["left", "right"]:
    ci = yaml.safe_load(open(f"{d}/{side}.yaml"))
    for key in ["image_width", "image_height", "camera_name", "camera_matrix", "distortion_model",
                "distortion_coefficients", "rectification_matrix", "projection_matrix"]:
        if key not in ci:
            ok = False
            print(f"BAD ros {side} missing {key}")
    check(f"ros {side} camera_matrix", np.reshape(ci["camera_matrix"]["data"], (3, 3)), cal[side]["K"])
    check(f"ros {side} distortion_coefficients", ci["distortion_coefficients"]["data"], cal[side]["distortion_coefficients"])
    P = cal["rectification"]["P1" if side == "left" else "P2"]
    check(f"ros {side} projection_matrix", np.reshape(ci["projection_matrix"]["data"], (3, 4)), P)

# Kalibr camchain
kc = yaml.safe_load(open(f"{d}/camchain.yaml"))
for i, side in enumerate(["left", "right"]):
    c = kc[f"cam{i}"]
    K = cal[side]["K"]
    check(f"kalibr cam{i} intrinsics", c["intrinsics"], [K[0][0], K[1][1], K[0][2], K[1][2]])
    check(f"kalibr cam{i} distortion_coeffs (k1 k2 p1 p2)", c["distortion_coeffs"], cal[side]["distortion_coefficients"][:4])
T = np.array(kc["cam1"]["T_cn_cnm1"])
check("kalibr T_cn_cnm1 rotation", T[:3, :3], cal["right_from_left"]["R"])
check("kalibr T_cn_cnm1 translation", T[:3, 3], cal["right_from_left"]["t"])
import os
written_by_align = os.path.exists(f"{d}/head.json") or os.path.exists(f"{d}/alignment.json")
for f in ["head.json", "alignment.json"] if written_by_align else ["calibrate_report.json"]:
    try:
        json.load(open(f"{d}/{f}"))
        print(f"ok  {f} parses")
    except (OSError, ValueError) as e:
        ok = False
        print(f"BAD {f}: {e}")
print("all files read back" if ok else "FAILURES")
sys.exit(0 if ok else 1)
