//! The robot stages end to end on the simulated robot, through the public API only:
//! simulate, run the verge/tilt procedure, the steering and pan stages, check the truth
//! (pan and steering errors, the floor's tilt) against the stated sigmas. Units: degrees,
//! pixels. The tests that reach private items (the covariance propagations, the
//! planarity test's internals) stay in `crates/headalign/src/robot/tests.rs`.

use headalign::AlignError;
use headalign::procedure::{AxisPerturbations, VergeTiltOptions, VergeTiltOutcome, VergeTiltRun};
use headalign::robot::{PanOptions, SteeringOptions, align_pan, zero_steering};
use headalign::verge_tilt::EstimationOptions;
use headalign_sim::{Scenario, SimulatedRobot};

/// A simulated robot for `s` and its verge/tilt calibration (estimation seed = the
/// scenario's seed).
fn calibrated_robot(s: Scenario) -> (SimulatedRobot, VergeTiltOutcome) {
    let opts = VergeTiltOptions {
        estimation: EstimationOptions { seed: s.seed, ..EstimationOptions::default() },
        ..VergeTiltOptions::default()
    };
    let mut robot = SimulatedRobot::new(s).unwrap();
    let vt = VergeTiltRun::default().run(robot.head_mut(), &opts).unwrap();
    (robot, vt)
}

/// Seed 6 at 1 px in the robot's scene (pan zeros up to 40 deg) after the verge/tilt
/// and pan stages, with the axes' perturbations.
fn pan_aligned_seed_6() -> (SimulatedRobot, VergeTiltOutcome, AxisPerturbations) {
    let s = Scenario {
        seed: 6,
        noise_px: 1.0,
        pan_zero_max_deg: 40.0,
        near_panels: Scenario::ROBOT_NEAR_PANELS,
        ..Scenario::default()
    };
    let (mut robot, vt) = calibrated_robot(s);
    let axes = vt.axis_perturbations();
    align_pan(&mut robot, &vt.calibration, &vt.verge_axes, Some(&axes), &PanOptions::default()).unwrap();
    (robot, vt, axes)
}

/// A steering zero whose sigma exceeds `max_sigma_zero_deg` is named, with the drives
/// that determined it, and the wheel is not commanded to it. (Seed 170 at 3 px with
/// exact readings once showed this with the default limit: 64 deg from three drives;
/// since its points are re-triangulated by support it completes, 2.5 sigmas off, so
/// the limit is lowered here instead.)
#[test]
fn an_undetermined_steering_zero_is_named() {
    let (mut robot, vt, axes) = pan_aligned_seed_6();
    let (cal, verge) = (&vt.calibration, &vt.verge_axes);
    let strict = SteeringOptions { max_sigma_zero_deg: 1e-3, ..SteeringOptions::default() };
    let err = zero_steering(&mut robot, cal, verge, Some(&axes), &strict).unwrap_err();
    match err {
        AlignError::SteeringUndetermined { zero_deg, sigma_deg, max_sigma_deg, drives, .. } => {
            assert!(sigma_deg > max_sigma_deg && max_sigma_deg == 1e-3, "{err}");
            assert!(drives >= 3, "{err}");
            assert!((robot.steering_encoder_deg() - zero_deg).abs() > 1e-6, "{err}");
        }
        e => panic!("expected SteeringUndetermined, got {e}"),
    }
}

/// At 1 px a planar robot passes the planarity tests of every drive (the false alarm
/// rate is 1e-5 per drive when the covariances are right; the former fixed limits
/// failed 3 of 260 experiment trials), and the stated sigmas are of the size of the
/// errors (within 4 sigma: one seed, so only a gross inconsistency fails).
#[test]
fn noisy_planar_drives_pass_and_sigmas_are_plausible() {
    let (mut robot, vt, axes) = pan_aligned_seed_6();
    let (cal, verge) = (&vt.calibration, &vt.verge_axes);
    let st = zero_steering(&mut robot, cal, verge, Some(&axes), &SteeringOptions::default()).unwrap();
    let err = robot.steer_err_deg(robot.steering_encoder_deg());
    assert!(st.sigma_steer_zero_deg > 0.0 && err.abs() < 4.0 * st.sigma_steer_zero_deg, "{err} {st:?}");
    let pan = align_pan(&mut robot, cal, verge, Some(&axes), &PanOptions::default()).unwrap();
    let last = pan.steps.last().unwrap();
    let err = robot.pan_err_deg(&robot.head().encoders());
    assert!(last.sigma_calibration_deg > 0.0 && last.sigma_deg >= last.sigma_calibration_deg);
    assert!(err.abs() < 4.0 * last.sigma_deg, "{err} {last:?}");
}

/// Pan axes tilted 0-5 deg from the floor normal (the tilt's direction drawn per seed).
/// Noise-free: the steering zero (its turns fix the normal) and the pan of the stage
/// after it (wheel straight) are exact to 1e-6 deg (the verge/tilt solver's tolerance
/// and the normal's prior, which pulls the fit by about 1e-12 / s^2 of the tilt, are far
/// below it), and the fitted tilt is the truth's to 1e-4 deg. At 1 px with a 4 deg tilt:
/// both errors and the fitted tilt within 4 sigma of the truth (one seed, so only a gross
/// inconsistency fails), and every drive passes its planarity test.
#[test]
fn tilted_pan_axis_keeps_pan_and_steering_right() {
    let exact_pan = PanOptions { encoder_sigma_deg: 0.0, ..PanOptions::default() };
    let exact_steering = SteeringOptions { encoder_sigma_deg: 0.0, ..SteeringOptions::default() };
    for (seed, tilt) in [(1, 0.0), (2, 1.0), (3, 3.0), (4, 5.0)] {
        let s = Scenario {
            seed,
            noise_px: 0.0,
            outlier_fraction: 0.0,
            pan_tilt_deg: tilt,
            near_panels: Scenario::ROBOT_NEAR_PANELS,
            ..Scenario::default()
        };
        let (mut robot, vt) = calibrated_robot(s);
        let (cal, verge) = (&vt.calibration, &vt.verge_axes);
        let axes = vt.axis_perturbations();
        let st = zero_steering(&mut robot, cal, verge, Some(&axes), &exact_steering).unwrap();
        let steer_err = robot.steer_err_deg(robot.steering_encoder_deg());
        assert!(steer_err.abs() < 1e-6, "tilt {tilt}: steering error {steer_err} {st:?}");
        assert!((st.floor.pan_tilt_deg - tilt).abs() < 1e-4, "tilt {tilt}: {:?}", st.floor);
        let pan = align_pan(&mut robot, cal, verge, Some(&axes), &exact_pan).unwrap();
        let pan_err = robot.pan_err_deg(&robot.head().encoders());
        assert!(pan_err.abs() < 1e-6, "tilt {tilt}: pan error {pan_err} {pan:?}");
    }
    let s = Scenario {
        seed: 5,
        noise_px: 1.0,
        pan_tilt_deg: 4.0,
        near_panels: Scenario::ROBOT_NEAR_PANELS,
        ..Scenario::default()
    };
    let (mut robot, vt) = calibrated_robot(s);
    let (cal, verge) = (&vt.calibration, &vt.verge_axes);
    let axes = vt.axis_perturbations();
    align_pan(&mut robot, cal, verge, Some(&axes), &PanOptions::default()).unwrap();
    let st = zero_steering(&mut robot, cal, verge, Some(&axes), &SteeringOptions::default()).unwrap();
    let steer_err = robot.steer_err_deg(robot.steering_encoder_deg());
    assert!(steer_err.abs() < 4.0 * st.sigma_steer_zero_deg, "{steer_err} {st:?}");
    let tilt_err = st.floor.pan_tilt_deg - 4.0;
    assert!(tilt_err.abs() < 4.0 * st.floor.sigma_pan_tilt_deg, "{tilt_err} {:?}", st.floor);
    let pan = align_pan(&mut robot, cal, verge, Some(&axes), &PanOptions::default()).unwrap();
    let last = pan.steps.last().unwrap();
    let pan_err = robot.pan_err_deg(&robot.head().encoders());
    assert!(pan_err.abs() < 4.0 * last.sigma_deg, "{pan_err} {last:?}");
}
