"""The Python package on real data: the EuRoC V1_01 raw pairs 3 and 2 (one general motion
of a VI-Sensor rig with a barrel lens, data/euroc_v101_pairs) passed as numpy arrays, and
the three-view observation sessions of an independent head model (data/threeview_sessions).

Run by .ci/run (`pip install ./crates/headalign-py pytest numpy`, then pytest here).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

import headalign

DATA = Path(__file__).resolve().parents[3] / "data"
EUROC = DATA / "euroc_v101_pairs"


def sensor_focal(name: str) -> tuple[float, float]:
    """fu, fv of a Kalibr/EuRoC sensor.yaml (the dataset's own target calibration)."""
    text = (EUROC / name).read_text()
    m = re.search(r"^intrinsics:\s*\[([^\]]*)\]", text, re.MULTILINE)
    assert m, f"no intrinsics in {name}"
    fu, fv, _, _ = (float(v) for v in m.group(1).split(","))
    return fu, fv


def euroc_pair(i: int) -> tuple[np.ndarray, np.ndarray]:
    return (
        headalign.read_image(EUROC / f"left_img_{i}.png"),
        headalign.read_image(EUROC / f"right_img_{i}.png"),
    )


@pytest.fixture(scope="module")
def pairs() -> list[tuple[np.ndarray, np.ndarray]]:
    # Pairs 3 then 2, in time order (the CLI's real-data test reads them in this order).
    return [euroc_pair(3), euroc_pair(2)]


PROGRESS: list[tuple[str, str, int, int]] = []


@pytest.fixture(scope="module")
def calibration(pairs) -> headalign.Calibration:
    # The defaults of `headalign calibrate DIR`, with the progress reports recorded.
    return headalign.calibrate(pairs, progress=lambda *report: PROGRESS.append(report))


def test_read_image_gives_grey_uint8(pairs):
    left, right = pairs[0]
    assert left.dtype == np.uint8 and left.shape == (480, 752) and right.shape == left.shape


def test_focal_lengths_within_one_percent(calibration):
    # The bar: 1 % of the dataset's Kalibr calibration. Measured with the default
    # `lens="auto"` (equidistant k1 k2 chosen by BIC): +0.11, +0.43, +0.07, +0.46 %, focal
    # sigma 0.4 %, the same numbers as `headalign calibrate` on a folder of these pairs.
    errors = []
    for K, name in [(calibration.K1, "cam0_sensor.yaml"), (calibration.K2, "cam1_sensor.yaml")]:
        fu, fv = sensor_focal(name)
        errors += [K[0, 0] / fu - 1.0, K[1, 1] / fv - 1.0]
    assert all(abs(e) < 0.01 for e in errors), [f"{100 * e:+.2f} %" for e in errors]


def test_calibration_is_in_opencv_shapes(calibration):
    assert calibration.image_size == (752, 480)
    for K in (calibration.K1, calibration.K2):
        assert K.shape == (3, 3) and K.dtype == np.float64 and K[2, 2] == 1.0 and K[1, 0] == 0.0
    R, T = calibration.R, calibration.T
    assert R.shape == (3, 3) and np.allclose(R @ R.T, np.eye(3), atol=1e-12)
    # In baselines: a unit vector; the right camera is to the left camera's right, so
    # x_right = R x_left + T has T along -x.
    assert T.shape == (3, 1) and abs(np.linalg.norm(T) - 1.0) < 1e-12 and T[0, 0] < -0.99
    assert calibration.translation_unit == "baselines"
    n = {"plumb_bob": 5, "fisheye": 4}[calibration.lens_model]
    assert calibration.D1.shape == (n,) and calibration.D2.shape == (n,)
    names = calibration.covariance_names
    assert calibration.covariance.shape == (len(names), len(names))
    sigmas = calibration.sigmas
    assert set(sigmas) == set(names) and 0.0 < sigmas["left.fx"] < 0.01 * calibration.K1[0, 0]
    assert isinstance(calibration.warnings, list)
    assert calibration.report["views"] == ["view00", "view01"]


def test_stereo_rectify_accepts_the_result(calibration):
    cv2 = pytest.importorskip("cv2")
    c = calibration
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(c.K1, c.D1, c.K2, c.D2, c.image_size, c.R, c.T)
    assert np.all(np.isfinite(P2)) and np.allclose(R1 @ R1.T, np.eye(3), atol=1e-9)
    # Rectified, the right camera sits at -1 baseline along x: P2[0, 3] = -f'.
    assert P2[0, 3] < 0 and abs(P2[0, 3] + P2[0, 0]) < 1e-6 * P2[0, 0]
    if c.lens_model == "fisheye":
        flags = cv2.fisheye.CALIB_ZERO_DISPARITY
        out = cv2.fisheye.stereoRectify(c.K1, c.D1, c.K2, c.D2, c.image_size, c.R, c.T, flags)
        assert all(np.all(np.isfinite(m)) for m in out)


def test_write_gives_every_file(calibration, tmp_path):
    written = {Path(p).name for p in calibration.write(tmp_path)}
    assert {"calibration.json", "opencv_stereo.yaml", "left.yaml", "right.yaml", "camchain.yaml"} <= written
    saved = json.loads((tmp_path / "calibration.json").read_text())
    assert saved["left"]["fx"] == calibration.K1[0, 0]


def test_float32_image_raises_value_error(pairs):
    (left, right), second = pairs
    with pytest.raises(ValueError, match="float32"):
        headalign.calibrate([(left.astype(np.float32) / 255, right), second])


def test_pair_of_different_sizes_raises_value_error(pairs):
    (left, right), second = pairs
    with pytest.raises(ValueError, match="752x480 but right image is 700x480"):
        headalign.calibrate([(left, right[:, :700]), second])


def test_views_of_different_sizes_raise_value_error(pairs):
    first, (left, right) = pairs
    with pytest.raises(ValueError, match="first pair's are 752x480"):
        headalign.calibrate([first, (left[:400], right[:400])])


def test_colour_and_malformed_input_raise_value_error(pairs):
    (left, right), second = pairs
    colour = np.stack([left] * 3, axis=-1)
    with pytest.raises(ValueError, match="3 channels"):
        headalign.calibrate([(colour, right), second])
    with pytest.raises(ValueError, match="pair"):
        headalign.calibrate([(left,), second])
    with pytest.raises(ValueError, match="no views"):
        headalign.calibrate([])
    with pytest.raises(ValueError, match="unknown lens model"):
        headalign.calibrate(pairs, lens="fisheye-ish")
    with pytest.raises(ValueError, match="not a folder"):
        headalign.calibrate(DATA / "no-such-folder")


def test_one_view_raises_runtime_error(pairs):
    # One view has no motion to self-calibrate from: a failed estimation, not bad input.
    with pytest.raises(RuntimeError):
        headalign.calibrate(pairs[:1])


def test_progress_reports_each_view(calibration):
    tracked = [r for r in PROGRESS if r[0] == "tracking"]
    assert tracked and tracked[-1][2:] == (2, 2) and PROGRESS[-1][0] == "solved"


@pytest.mark.parametrize("seed", ["seed01", "seed02"])
def test_align_an_observation_session(seed):
    # The independent head model's three-view sessions (no vergence view): the fixation
    # points against the truth, in units of the reported sigmas. 4 sigmas: the sigmas are
    # calibrated on these sessions (z RMS near 1, data/threeview_sessions/README.md), so a
    # correct estimate fails this about once in 16,000 coordinates.
    session = DATA / "threeview_sessions" / seed
    a = headalign.align(session / "session.json")
    truth = json.loads((session / "truth.json").read_text())["fixation_px"]
    assert a.route == "general" and a.calibration is not None
    for est, sig, true in zip(a.fixation_px, a.fixation_sigma_px, [truth["left"], truth["right"]]):
        z = [(e - t) / s for e, t, s in zip(est, true, sig)]
        assert all(abs(v) < 4 for v in z), (est, true, sig)
    assert not a.verge_axes_measured and any("vergence joints" in w for w in a.warnings)
    assert set(a.sigmas) == {"elevation", "verge_left", "verge_right"}
    assert all(0 < s < 2 for s in a.sigmas.values())
    assert a.K1.shape == (3, 3) and a.calibration.K1[0, 0] == a.K1[0, 0]


def test_align_bad_path_raises_value_error():
    with pytest.raises(ValueError):
        headalign.align(DATA / "no-such-session.json")


def test_read_calibration_of_the_dataset():
    # The dataset's own calibration as an OpenCV stereo YAML (data/euroc_v101_pairs).
    given = headalign.read_calibration(EUROC / "opencv_stereo.yaml")
    fu, fv = sensor_focal("cam0_sensor.yaml")
    assert given.K1[0, 0] == fu and given.K1[1, 1] == fv and given.image_size == (752, 480)
    assert given.lens_model == "plumb_bob" and given.translation_unit == "m"
    assert abs(np.linalg.norm(given.T) - 0.110) < 0.001


@pytest.fixture(scope="module")
def four_pairs() -> list[tuple[np.ndarray, np.ndarray]]:
    return [euroc_pair(i) for i in range(4)]


def test_check_the_dataset_calibration(four_pairs):
    # Issue 46's bar, as the CLI's test holds it on the same four pairs: the dataset's
    # calibration shows no change beyond 0.03 deg and is not `recalibrate`. The numpy
    # arrays and the folder give the same check (the same images, the same seed).
    given = headalign.read_calibration(EUROC / "opencv_stereo.yaml")
    r = headalign.check(four_pairs, given)
    assert max(abs(v) for v in r.rotation_change_deg.values()) < 0.03, r.rotation_change_deg
    assert r.verdict != "recalibrate" and all(s > 0 for s in r.rotation_change_sigma_deg.values())
    assert len(r.report["pairs"]) == 4
    from_folder = headalign.check(EUROC, EUROC / "opencv_stereo.yaml")
    assert from_folder.rotation_change_deg == r.rotation_change_deg


def test_check_of_a_calibration_in_baselines_needs_the_baseline(calibration, four_pairs):
    with pytest.raises(ValueError, match="baseline"):
        headalign.check(four_pairs, calibration)
