//! `headalign run --check-only --calibration FILE` on the simulated head's driver
//! (`headalign-sim-driver --seed 1 --no-base`, the robot demo's room): the simulator's true
//! calibration at the head's start position (the test may see the simulator's truth; the
//! driver's scenario rebuilt here) is not `recalibrate`, the same calibration with the
//! right camera turned by 0.5 deg of yaw is `recalibrate` with the turn found, and the
//! head's final readings equal its start readings.

use std::path::Path;

use headalign::calibration::{IntrinsicSigmas, StereoCalibration, TranslationUnit};
use headalign::check::turned;
use headalign_geometry::distortion::Distortion;
use headalign_geometry::so3;
use headalign_io::export::CalibrationFiles as _;
use headalign_sim::{Scenario, SimulatedRobot};
use nalgebra::Vector3;
use serde_json::Value;

use super::common::{bin, driver, ok_json, tmp};

/// The true calibration of the driver's head (`--seed 1`, its near panels) at its start.
fn true_calibration() -> StereoCalibration {
    let scenario = Scenario { seed: 1, near_panels: Scenario::ROBOT_NEAR_PANELS, ..Scenario::default() };
    let robot = SimulatedRobot::new(scenario).unwrap();
    let head = robot.head();
    let (left, right) = head.world_from_cameras(&head.encoders());
    StereoCalibration {
        image_size: head.scenario().image_size,
        left: head.truth().left,
        right: head.truth().right,
        sigmas: [IntrinsicSigmas::default(); 2],
        right_from_left: right.inverse() * left,
        unit: TranslationUnit::Metres,
        distortion: [Distortion::default(); 2],
    }
}

fn live_check(calibration: &Path) -> Value {
    let cmd = format!("{} --seed 1 --no-base", driver());
    let out = bin()
        .args(["run", "--head-cmd", &cmd, "--check-only", "--json", "--calibration"])
        .arg(calibration)
        .output()
        .unwrap();
    ok_json(&out)
}

fn written(c: &StereoCalibration, name: &str) -> std::path::PathBuf {
    let path = tmp(name);
    std::fs::write(&path, c.json().unwrap().to_string()).unwrap();
    path
}

#[test]
fn live_check_of_the_true_and_a_turned_calibration() {
    let truth = true_calibration();
    let v = live_check(&written(&truth, "true.json"));
    let r = &v["report"];
    assert_ne!(r["verdict"], "recalibrate", "{r:#}");
    assert_eq!(v["returned"], true);
    assert_eq!(v["start"], v["end"], "{v:#}");
    // 0.5 deg of yaw shifts disparities by 6 px (f 700 px), 17 % of the 35 px at 5 m.
    let w = Vector3::new(0.0, 0.5_f64.to_radians(), 0.0);
    // The given calibration is the truth turned back: the head's rig is the given one
    // turned by +0.5 deg of yaw.
    let given = turned(&truth, &so3::exp(&-w));
    let v = live_check(&written(&given, "turned.json"));
    let r = &v["report"];
    assert_eq!(r["verdict"], "recalibrate", "{r:#}");
    let yaw = r["rotation_change_deg"]["yaw"].as_f64().unwrap();
    let sigma = r["rotation_change_sigma_deg"]["yaw"].as_f64().unwrap();
    assert!((yaw - 0.5).abs() < (4.0 * sigma).max(0.02), "yaw {yaw} +- {sigma}");
    assert_eq!(v["start"], v["end"], "{v:#}");
}
