#!/usr/bin/env python3
"""Write three-view observation sessions with truth from a head model written from the
description in data/threeview_sessions/README.md (a reading of that README,
not its generator): held-out sessions for bench/threeview_scores.py.

Each session: views `initial`, `elevation` (+3 deg) and `pan` (+3 deg), no vergence
view; 240 points seen in all six images (uniform in a box 5 x 3.6 m, 1.5-6 m deep);
1 px Gaussian noise per coordinate and 10 % uniform outliers per image; exact encoder
readings. Left camera fx 650-900 px, fy/fx 0.97-1.05, principal point 370-400 /
270-300; the right within 2 % and 8 px, rotated 2-6 deg, 0.15-0.35 m along the left's
x; the cameras rotated 3-10 deg from the head frame; the pan axis 5-15 cm beside the
camera; the elevation axis 2 deg from perpendicular to it, offset by 3-8 cm. truth.json:
both `K`s and `fixation_px` (where each camera sees the direction perpendicular to the
pan and elevation axes, at the initial view).

usage: bench/threeview_sessions.py OUT FIRST LAST    (writes OUT/seedNN for seeds FIRST..LAST)
"""
import json, os, sys

import numpy as np

W, H = 768, 576


def rot(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def random_rotation(rng, lo_deg, hi_deg):
    return rot(rng.normal(size=3), np.radians(rng.uniform(lo_deg, hi_deg)))


def project(k, r_world_from_cam, centre, x):
    xc = (x - centre) @ r_world_from_cam
    uv = xc @ k.T
    return uv[:, :2] / uv[:, 2:3], xc[:, 2] > 0.1


def session(seed):
    rng = np.random.default_rng(1000 + seed)
    fx = rng.uniform(650, 900)
    kl = np.array([[fx, 0, rng.uniform(370, 400)], [0, fx * rng.uniform(0.97, 1.05), rng.uniform(270, 300)], [0, 0, 1]])
    kr = kl.copy()
    kr[0, 0] *= 1 + rng.uniform(-0.02, 0.02)
    kr[1, 1] *= 1 + rng.uniform(-0.02, 0.02)
    kr[0, 2] += rng.uniform(-8, 8)
    kr[1, 2] += rng.uniform(-8, 8)
    # World = head frame at the initial view: x right, y down, z forward.
    r_wl, c_l = random_rotation(rng, 3, 10), np.zeros(3)
    r_lr = random_rotation(rng, 2, 6)
    c_r = c_l + r_wl @ np.array([rng.uniform(0.15, 0.35), rng.normal(0, 0.01), rng.normal(0, 0.01)])
    r_wr = r_wl @ r_lr.T
    pan_dir = np.array([0.0, -1.0, 0.0])
    pan_pt = np.array([rng.uniform(0.05, 0.15) * rng.choice([-1, 1]), 0.0, rng.uniform(-0.05, 0.05)])
    tilt = np.radians(2.0) * rng.choice([-1, 1])
    el_dir = np.array([np.cos(tilt), np.sin(tilt), 0.0])
    el_pt = np.array([0.0, rng.uniform(0.03, 0.08), rng.uniform(-0.06, 0.06)])

    def poses(pan_deg, el_deg):
        rp, re = rot(pan_dir, np.radians(pan_deg)), rot(el_dir, np.radians(el_deg))
        out = []
        for r, c in ((r_wl, c_l), (r_wr, c_r)):
            c1 = re @ (c - el_pt) + el_pt
            out.append((rp @ re @ r, rp @ (c1 - pan_pt) + pan_pt))
        return out

    e0 = {"pan": rng.uniform(-5, 5), "elevation": rng.uniform(-5, 5),
          "verge_left": rng.uniform(-8, 0), "verge_right": rng.uniform(0, 8)}
    plan = [("initial", 0, 0), ("elevation", 0, 3), ("pan", 3, 0)]
    view_poses = [poses(p, e) for _, p, e in plan]
    points = np.zeros((0, 3))
    while len(points) < 240:
        x = np.column_stack([rng.uniform(-2.5, 2.5, 2000), rng.uniform(-1.8, 1.8, 2000), rng.uniform(1.5, 6, 2000)])
        seen = np.ones(len(x), bool)
        for pair in view_poses:
            for k, (r, c) in zip((kl, kr), pair):
                uv, front = project(k, r, c, x)
                seen &= front & (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
        points = np.vstack([points, x[seen]])[:240]
    views = []
    for (name, dp, de), pair in zip(plan, view_poses):
        enc = dict(e0, pan=e0["pan"] + dp, elevation=e0["elevation"] + de)
        view = {"name": name, "encoders": enc}
        for side, k, (r, c) in zip(("left", "right"), (kl, kr), pair):
            uv, _ = project(k, r, c, points)
            uv = uv + rng.normal(0, 1, uv.shape)
            wrong = rng.random(len(uv)) < 0.10
            uv[wrong] = np.column_stack([rng.uniform(0, W, wrong.sum()), rng.uniform(0, H, wrong.sum())])
            view[side] = [[i, round(float(u), 4), round(float(v), 4)] for i, (u, v) in enumerate(uv)]
        views.append(view)
    d = np.cross(el_dir, pan_dir)
    fixation = {}
    for side, k, r in (("left", kl, r_wl), ("right", kr, r_wr)):
        dc = r.T @ d
        dc = dc if dc[2] > 0 else -dc
        p = k @ dc
        fixation[side] = [p[0] / p[2], p[1] / p[2]]
    obs = {"format": "headalign-observations/1", "image_size": [W, H], "views": views}
    return obs, {"left_K": kl.tolist(), "right_K": kr.tolist(), "fixation_px": fixation}


if len(sys.argv) != 4:
    sys.exit(__doc__)
out, first, last = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
for seed in range(first, last + 1):
    obs, truth = session(seed)
    d = os.path.join(out, f"seed{seed:02d}")
    os.makedirs(d, exist_ok=True)
    json.dump(obs, open(os.path.join(d, "session.json"), "w"))
    json.dump(truth, open(os.path.join(d, "truth.json"), "w"), indent=1)
print(f"wrote seeds {first}-{last} to {out}")
