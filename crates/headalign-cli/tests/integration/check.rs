//! `headalign check` on the four real EuRoC pairs (data/euroc_v101_pairs) with the
//! dataset's own calibration (the fixture `opencv_stereo.yaml`, from the Kalibr
//! `cam0_sensor.yaml` and `cam1_sensor.yaml`: bench/check_baseline.py) and with that
//! calibration's right camera turned by a known angle (docs/check.md, "Measured").
//! Bars of issue 46: every change within 0.03 deg of zero and a verdict other than
//! `recalibrate` for the dataset's calibration; a turn of 0.3 deg of yaw, 0.1 deg of pitch
//! or of roll found within 0.02 deg, with a verdict other than `good`; `--update` within
//! 0.02 deg of the dataset's rotation. Bad input: one clear line.

use std::path::{Path, PathBuf};

use headalign::check::turned;
use headalign_geometry::so3;
use headalign_io::export::CalibrationFiles as _;
use headalign_io::import::read_calibration;
use nalgebra::Vector3;
use serde_json::Value;

use super::common::{assert_clean_failure, bin, data_dir, ok_json, tmp, tmp_dir};

fn pairs() -> PathBuf {
    data_dir().join("euroc_v101_pairs")
}

fn check(calibration: &Path, extra: &[&str]) -> Value {
    let out = bin()
        .arg("check")
        .arg(pairs())
        .arg("--calibration")
        .arg(calibration)
        .arg("--json")
        .args(extra)
        .output()
        .unwrap();
    ok_json(&out)
}

fn change(v: &Value) -> Vector3<f64> {
    let c = &v["rotation_change_deg"];
    Vector3::new(c["pitch"].as_f64().unwrap(), c["yaw"].as_f64().unwrap(), c["roll"].as_f64().unwrap())
}

/// The dataset's calibration: no change beyond 0.03 deg, not `recalibrate`, and the
/// report's JSON names.
#[test]
fn dataset_calibration_is_not_recalibrate() {
    let v = check(&pairs().join("opencv_stereo.yaml"), &[]);
    assert!(change(&v).abs().max() < 0.03, "{}", v["rotation_change_deg"]);
    assert_ne!(v["verdict"], "recalibrate");
    for key in ["rotation_change_sigma_deg", "vertical_disparity_px", "sampson_px", "pairs"] {
        assert!(!v[key].is_null(), "{key}");
    }
    for z in ["1", "2", "5", "10"] {
        assert!(v["depth_error_pct"][z].as_f64().is_some(), "depth_error_pct.{z}");
    }
    assert_eq!(v["pairs"].as_array().map(Vec::len), Some(4));
}

/// The dataset's calibration with the right camera turned back by `w` (degrees; the
/// images then show a change of `w`), written as an OpenCV stereo YAML.
fn turned_file(w_deg: [f64; 3], name: &str) -> PathBuf {
    let given = read_calibration(&pairs().join("opencv_stereo.yaml")).unwrap();
    let w = Vector3::from(w_deg).map(f64::to_radians);
    let path = tmp(name);
    std::fs::write(&path, turned(&given, &so3::exp(&-w)).opencv_yaml().unwrap()).unwrap();
    path
}

/// 0.3 deg of yaw: found within 0.02 deg, not `good`, and the update lies within 0.02 deg
/// of the dataset's rotation (each axis of `log(R_update R_dataset^T)`).
#[test]
fn yaw_turn_is_found_and_updated() {
    let file = turned_file([0.0, 0.3, 0.0], "yaw.yaml");
    let out = tmp_dir("update");
    let v = check(&file, &["--update", out.to_str().unwrap()]);
    let found = change(&v);
    assert!((found - Vector3::new(0.0, 0.3, 0.0)).abs().max() < 0.02, "{found}");
    assert_ne!(v["verdict"], "good");
    let updated = read_calibration(&out.join("calibration.json")).unwrap();
    let dataset = read_calibration(&pairs().join("opencv_stereo.yaml")).unwrap();
    let d = so3::log(&nalgebra::Rotation3::from_matrix_unchecked(
        updated.rotation() * dataset.rotation().transpose(),
    ));
    assert!(d.map(f64::to_degrees).abs().max() < 0.02, "update off the dataset by {d} rad");
    for f in ["opencv_stereo.yaml", "camchain.yaml", "left.yaml", "right.yaml"] {
        assert!(out.join(f).is_file(), "{f}");
    }
}

/// 0.1 deg of pitch, then of roll: each found within 0.02 deg.
#[test]
fn pitch_and_roll_turns_are_found() {
    for (w, name) in [([0.1, 0.0, 0.0], "pitch.yaml"), ([0.0, 0.0, 0.1], "roll.yaml")] {
        let found = change(&check(&turned_file(w, name), &[]));
        assert!((found - Vector3::from(w)).abs().max() < 0.02, "{name}: {found}");
    }
}

/// A missing calibration, a file of no known format, a calibration of other images, and
/// a bad option: one line naming the problem.
#[test]
fn bad_input_is_one_clear_line() {
    let run = |cal: &Path, extra: &[&str]| {
        bin().arg("check").arg(pairs()).arg("--calibration").arg(cal).args(extra).output().unwrap()
    };
    assert_clean_failure(&run(&pairs().join("missing.yaml"), &[]), &["cannot read", "missing.yaml"]);
    assert_clean_failure(&run(&pairs().join("cam0_sensor.yaml"), &[]), &["not a calibration file"]);
    let mut other = read_calibration(&pairs().join("opencv_stereo.yaml")).unwrap();
    other.image_size = [640, 480];
    let path = tmp("other.yaml");
    std::fs::write(&path, other.opencv_yaml().unwrap()).unwrap();
    assert_clean_failure(&run(&path, &[]), &["640x480", "752x480"]);
    assert_clean_failure(
        &run(&pairs().join("opencv_stereo.yaml"), &["--significance=-1"]),
        &["significance"],
    );
}
