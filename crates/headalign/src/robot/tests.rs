//! Tests of the robot stages ([`super`]) that reach their private items: option checks,
//! noise-free pan and steering, the covariance propagations against their definitions
//! and against Monte-Carlo runs, the planarity test and the rig check. The end-to-end
//! runs through the public API (the steering zero's sigma bound, noisy and tilted
//! drives) are in `crates/headalign/tests/integration/robot_stages.rs`. Some run whole
//! simulated verge/tilt calibrations first (slow); the experiments are ignored: run them
//! by name. Units as in the module: degrees, pixels, stereo baselines.

use headalign_geometry::rigmotion::RigMotionEstimate;
use headalign_platform::{Encoders, Joint, StereoCapture, StereoHead, Vehicle};
use headalign_sim::{Scenario, SimulatedRobot};
use nalgebra::{Isometry3, Matrix2, Matrix3, SVector, Vector2, Vector3};

use super::propagation::{Readings, calibration_covariance, motion_covariance};
use super::*;
use crate::alignment::VergeAxes;
use crate::error::AlignError;
use crate::procedure::{AxisPerturbations, VergeTiltOptions, VergeTiltRun};
use crate::verge_tilt::{ENCODER_SIGMA_DEG, EstimationOptions};

/// A simulated robot for `s` and its verge/tilt calibration (estimation seed = the
/// scenario's seed), as every test here starts.
fn calibrated_robot(s: Scenario) -> (SimulatedRobot, crate::procedure::VergeTiltOutcome) {
    let opts = VergeTiltOptions {
        estimation: EstimationOptions { seed: s.seed, ..EstimationOptions::default() },
        ..VergeTiltOptions::default()
    };
    let mut robot = SimulatedRobot::new(s).unwrap();
    let vt = VergeTiltRun::default().run(robot.head_mut(), &opts).unwrap();
    (robot, vt)
}

/// A robot-scene simulated robot at `noise` px and its verge/tilt calibration as the
/// experiments run it (noise-scaled estimation options, 3 deg vergence rotations), with
/// the depth-scale profile `depth_profile` (the default's:
/// `EstimationOptions::default().depth_profile`).
fn experiment_robot(
    seed: u64,
    noise: f64,
    depth_profile: Option<crate::verge_tilt::DepthProfile>,
    image_border: bool,
) -> (SimulatedRobot, crate::procedure::VergeTiltOutcome, Scenario) {
    let s =
        Scenario { seed, noise_px: noise, near_panels: Scenario::ROBOT_NEAR_PANELS, ..Scenario::default() };
    let opts = VergeTiltOptions {
        verge_rotation_deg: 3.0,
        estimation: EstimationOptions {
            depth_profile,
            image_border,
            ..EstimationOptions::scaled_for_noise(noise, seed)
        },
        ..VergeTiltOptions::default()
    };
    let mut robot = SimulatedRobot::new(s.clone()).unwrap();
    let vt = VergeTiltRun::default().run(robot.head_mut(), &opts).unwrap();
    (robot, vt, s)
}

/// Every option the stages check is rejected when out of range, by a named
/// [`AlignError::InvalidOption`]; the defaults pass.
#[test]
fn robot_options_validate() {
    assert!(PanOptions::default().validate().is_ok());
    assert!(SteeringOptions::default().validate().is_ok());
    let pans = [
        PanOptions { drive_m: f64::NAN, ..PanOptions::default() },
        PanOptions { drive_m: 0.0, ..PanOptions::default() },
        PanOptions { iterations: 0, ..PanOptions::default() },
        PanOptions { planarity_chi2_max: f64::NAN, ..PanOptions::default() },
        PanOptions { encoder_sigma_deg: -0.1, ..PanOptions::default() },
        PanOptions { guide_px: 0.0, ..PanOptions::default() },
    ];
    for o in &pans {
        assert!(matches!(o.validate(), Err(AlignError::InvalidOption(_))), "{o:?}");
    }
    let steerings = [
        SteeringOptions { drive_m: f64::INFINITY, ..SteeringOptions::default() },
        SteeringOptions { baseline_m: 0.0, ..SteeringOptions::default() },
        SteeringOptions { settings_deg: vec![-20.0, 20.0], ..SteeringOptions::default() },
        SteeringOptions { settings_deg: vec![-20.0, f64::NAN, 20.0], ..SteeringOptions::default() },
        SteeringOptions { min_turn_deg: -1.0, ..SteeringOptions::default() },
        SteeringOptions { planarity_chi2_max: 0.0, ..SteeringOptions::default() },
        SteeringOptions { max_sigma_zero_deg: 0.0, ..SteeringOptions::default() },
        SteeringOptions { max_sigma_zero_deg: f64::NAN, ..SteeringOptions::default() },
        SteeringOptions { encoder_sigma_deg: f64::NAN, ..SteeringOptions::default() },
        SteeringOptions { wheelbase_m: Some(-0.5), ..SteeringOptions::default() },
    ];
    for o in &steerings {
        assert!(matches!(o.validate(), Err(AlignError::InvalidOption(_))), "{o:?}");
    }
    // Two settings suffice with a known wheelbase.
    let known = SteeringOptions {
        settings_deg: vec![-20.0, 20.0],
        wheelbase_m: Some(0.5),
        ..SteeringOptions::default()
    };
    assert!(known.validate().is_ok());
}

/// Noise-free end to end: steering zero then pan, both exact to 1e-9 deg (rounding
/// through triangulation, two least-squares fits and the epipole; before the
/// maximum-likelihood passes a wrong track inside the RANSAC threshold left 0.006
/// deg on demo seed 1) with sigmas near zero; and the named degenerate cases.
#[test]
fn noise_free_steering_and_pan_and_degenerate_cases() {
    let s = Scenario { seed: 1, noise_px: 0.0, outlier_fraction: 0.0, ..Scenario::default() };
    let (mut robot, vt) = calibrated_robot(s);
    let (cal, verge) = (&vt.calibration, &vt.verge_axes);
    let axes = vt.axis_perturbations();
    // The simulated readings are exact.
    let steering = SteeringOptions { encoder_sigma_deg: 0.0, ..SteeringOptions::default() };
    let st = zero_steering(&mut robot, cal, verge, Some(&axes), &steering).unwrap();
    let now = robot.steering_encoder_deg();
    assert!(robot.steer_err_deg(now).abs() < 1e-9, "{st:?}");
    assert!(st.sigma_steer_zero_deg < 1e-4, "{st:?}");
    let exact = PanOptions { encoder_sigma_deg: 0.0, ..PanOptions::default() };
    let pan = align_pan(&mut robot, cal, verge, Some(&axes), &exact).unwrap();
    let enc = robot.head().encoders();
    assert!(robot.pan_err_deg(&enc).abs() < 1e-9, "{pan:?}");
    assert!(pan.steps.iter().all(|s| s.sigma_deg < 1e-4 && s.planarity_chi2 < 1.0), "{pan:?}");

    let short = PanOptions { drive_m: 0.002, ..PanOptions::default() };
    assert!(matches!(
        align_pan(&mut robot, cal, verge, Some(&axes), &short),
        Err(AlignError::DriveTooShort { .. })
    ));
    let small = SteeringOptions { settings_deg: vec![0.3, 0.6, 0.9], ..SteeringOptions::default() };
    assert!(matches!(
        zero_steering(&mut robot, cal, verge, Some(&axes), &small),
        Err(AlignError::TurnTooSmall { .. })
    ));
}

/// The calibration propagation against the covariance itself: for quantities that are
/// calibration parameters (the left camera's fx and cx, linear in the tangent step)
/// the central differences must return the covariance block exactly (1e-9 relative:
/// rounding); and a quantity that no calibration parameter moves gets zero.
#[test]
fn calibration_covariance_matches_the_covariance_block() {
    let s = Scenario { seed: 3, noise_px: 1.0, ..Scenario::default() };
    let (_, vt) = calibrated_robot(s);
    let cal = &vt.calibration;
    let c =
        calibration_covariance(cal, &vt.verge_axes, None, &Readings::exact(vt.final_encoders), |cp, _, _| {
            let k = cp.bundle.state.left;
            Some(SVector::<f64, 3>::new(k.fx, k.cx, 1.0))
        })
        .unwrap();
    let cov = &cal.bundle.covariance;
    let (i, j) = (cov.index("left.fx").unwrap(), cov.index("left.cx").unwrap());
    let expect = [[cov.matrix[(i, i)], cov.matrix[(i, j)]], [cov.matrix[(j, i)], cov.matrix[(j, j)]]];
    for r in 0..2 {
        for k in 0..2 {
            let tol = 1e-9 * (expect[r][r] * expect[k][k]).sqrt();
            assert!((c[(r, k)] - expect[r][k]).abs() <= tol, "{r} {k}: {} vs {}", c[(r, k)], expect[r][k]);
        }
    }
    assert!(c[(2, 2)] == 0.0 && c[(0, 2)] == 0.0);
    assert!(expect[1][1] > 0.0);
}

/// The readings' noise: for quantities linear in the readings and independent of the
/// calibration (the pan reading; the sum of the elevation and left vergence readings)
/// the modes give exactly `2 sigma^2` per joint (the reading and the reference
/// reading), uncorrelated across joints (1e-9 relative: rounding); a quantity the
/// readings do not move gets zero; and the rig predicted at the readings turns by the
/// vergence readings' noise (its rotation's variance, radians, `2 sigma^2` per
/// vergence joint, the calibration noise-free; 1 % for the rotations' nonlinearity).
#[test]
fn reading_noise_adds_each_joints_variance() {
    let s = Scenario { seed: 3, noise_px: 0.0, ..Scenario::default() };
    let (_, vt) = calibrated_robot(s);
    let cal = &vt.calibration;
    let sigma = 0.01;
    let readings = Readings { enc: vt.final_encoders, sigma_deg: sigma };
    let c = calibration_covariance(cal, &vt.verge_axes, None, &readings, |_, _, e| {
        Some(SVector::<f64, 3>::new(
            e.get(Joint::Pan),
            e.get(Joint::Elevation) + e.get(Joint::VergeLeft),
            1.0,
        ))
    })
    .unwrap();
    let var = 2.0 * sigma * sigma;
    let expect = [[var, 0.0], [0.0, 2.0 * var]];
    for r in 0..2 {
        for k in 0..2 {
            assert!((c[(r, k)] - expect[r][k]).abs() <= 1e-9 * var, "{r} {k}: {}", c[(r, k)]);
        }
    }
    assert!(c[(2, 2)] == 0.0);
    let nominal = rig_at(cal, &vt.verge_axes, &vt.final_encoders).unwrap().stereo.right_from_left;
    let rot = calibration_covariance(cal, &vt.verge_axes, None, &readings, |cp, va, e| {
        let d = rig_at(cp, va, e).ok()?.stereo.right_from_left * nominal.inverse();
        Some(d.rotation.scaled_axis())
    })
    .unwrap();
    let s_rad = sigma.to_radians();
    let expect = 4.0 * s_rad * s_rad;
    assert!((rot.trace() - expect).abs() <= 0.01 * expect, "{} vs {expect}", rot.trace());
}

/// The vergence axes' pose part of the rig predicted at other readings against a
/// Monte-Carlo: seed 2 at 3 px in the robot scene (the experiments' verge/tilt
/// options), the axis sources' captures re-drawn 100 times (every calibration point
/// the capture observes, projected at the estimate, plus 3 px Gaussian noise: the
/// model the bootstrap draws from), resected by [`crate::alignment::measure_cameras`]
/// and turned into axes, the calibration held; the spread of the predicted rig's
/// rotation at the stage's final readings against [`predicted_rig`]'s covariance with
/// only the pose modes of [`AxisPerturbations`]. Measured: Monte-Carlo / predicted
/// standard deviation 0.89 here (at c46cdb3 and with the 0.1-sigma difference step
/// alike; 1.10 when this test was written, on an earlier calibration). Exact pixels
/// of the true scene, as a first version drew (they add the calibration's fixed
/// misfit through the Huber weights), gave 1.10
/// with the image border not modelled and 1.07-1.30 over seeds 1-8
/// (a past measurement, no command reproduces it); with `EstimationOptions::min_camera_observations` 2 the
/// calibration differs and it was 1.22 (exact pixels 1.33). The least-squares pose
/// covariance gave 1.40 (1.29-1.51).
/// Tolerance [0.8, 1.3]: 100 draws know a standard deviation to 7 %, the bootstrap's
/// 200 to 5 %, and it keeps out the least-squares value.
#[test]
fn axis_pose_part_matches_monte_carlo_at_3px() {
    use crate::alignment::{measure_cameras, verge_axes_from_motion};
    use crate::procedure::AxisMeasurement;
    use rand::{RngExt, SeedableRng};
    let noise = 3.0;
    let (_, vt, _) = experiment_robot(
        2,
        noise,
        EstimationOptions::default().depth_profile,
        EstimationOptions::default().image_border,
    );
    let cal = &vt.calibration;
    let r0 = cal.reference_encoders;
    let enc = vt.final_encoders;
    let all = vt.axis_perturbations();
    let pose_only = AxisPerturbations { calibration: vec![None; all.calibration.len()], pose: all.pose };
    let (rig, cov) = predicted_rig(cal, &vt.verge_axes, Some(&pose_only), &enc).unwrap();
    let predicted = cov.unwrap().fixed_view::<3, 3>(0, 0).trace().sqrt();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let points: std::collections::HashMap<u64, nalgebra::Point3<f64>> = cal.points().into_iter().collect();
    let mut samples: Vec<Vector3<f64>> = Vec::new();
    for _ in 0..100 {
        let mut redraw = |src: &Option<AxisMeasurement>| -> VergeAxes {
            let Some(src) = src else { return vt.verge_axes };
            // The model the bootstrap draws from: every calibration point the capture
            // observes, projected at the estimate, plus noise.
            let mut c = src.capture.clone();
            let st = &cal.bundle.state;
            for (obs, k, pose) in [
                (&mut c.left, &st.left, &src.measured.ref_from_left),
                (&mut c.right, &st.right, &src.measured.ref_from_right),
            ] {
                obs.retain_mut(|o| {
                    let Some(p) =
                        points.get(&o.track).and_then(|x| k.project(&pose.inverse_transform_point(x)))
                    else {
                        return false;
                    };
                    o.pixel.x = p.x + noise * rng.sample::<f64, _>(rand_distr::StandardNormal);
                    o.pixel.y = p.y + noise * rng.sample::<f64, _>(rand_distr::StandardNormal);
                    true
                });
            }
            let m =
                measure_cameras(cal, &c, &src.measured.ref_from_left, &src.measured.ref_from_right).unwrap();
            verge_axes_from_motion(&cal.bundle.state, &r0, &c.encoders, &m).unwrap()
        };
        let axes = VergeAxes {
            left: redraw(&vt.axis_sources.left).left,
            right: redraw(&vt.axis_sources.right).right,
        };
        let (p, _) = predicted_rig(cal, &axes, None, &enc).unwrap();
        samples.push((p.right_from_left * rig.right_from_left.inverse()).rotation.scaled_axis());
    }
    let n = samples.len() as f64;
    let mean: Vector3<f64> = samples.iter().sum::<Vector3<f64>>() / n;
    let mc = (samples.iter().map(|v| (v - mean).norm_squared()).sum::<f64>() / (n - 1.0)).sqrt();
    let ratio = mc / predicted;
    assert!((0.8..1.3).contains(&ratio), "Monte-Carlo {mc} vs predicted {predicted}: {ratio}");
}

/// The steering drives' planarity chi-squares of the robot experiment at `seed`, 3 px,
/// with the vergence axes held as exact and with their uncertainty, on the same drives
/// (the robot cloned after the pan stage: a second run whose pan stage used the axes'
/// uncertainty would leave the head elsewhere and drive different drives).
fn steering_chi2(seed: u64, image_border: bool) -> [Vec<f64>; 2] {
    let noise = 3.0;
    let (mut robot, vt, s) = experiment_robot(seed, noise, None, image_border);
    let perturbations = vt.axis_perturbations();
    // The stages scale their thresholds with the calibration's noise estimate.
    let pan = PanOptions { drive_m: s.drive_m, planarity_chi2_max: f64::INFINITY, ..PanOptions::default() };
    let st = SteeringOptions {
        baseline_m: s.baseline_m,
        planarity_chi2_max: f64::INFINITY,
        ..SteeringOptions::default()
    };
    align_pan(&mut robot, &vt.calibration, &vt.verge_axes, None, &pan).unwrap();
    [None, Some(&perturbations)].map(|axes| {
        let z = zero_steering(&mut robot.clone(), &vt.calibration, &vt.verge_axes, axes, &st).unwrap();
        z.turns.iter().map(|t| t.planarity_chi2).collect()
    })
}

/// Seeds 100-399 whose steering drives fail the planarity test with the axes held,
/// printed with the chi-squares on the same drives with the axes' uncertainty (a
/// diagnostic, not a test: `[IMAGE_BORDER=1] cargo test --release -p headalign --lib
/// scan_steering_chi2 -- --ignored --nocapture`, about 3.5 min). Measured: with the
/// image border modelled only seed 170 (fourth drive 43.5 held, 42.8 with the axes) and
/// 216 (third, 28.5 / 28.4); without it only seed 170 (first drive 42.7 / 42.8).
#[test]
#[ignore]
fn scan_steering_chi2() {
    for seed in 100..400 {
        let [held, with] = steering_chi2(seed, std::env::var("IMAGE_BORDER").is_ok_and(|v| v == "1"));
        if held.iter().any(|&c| c > 25.9) {
            eprintln!("SCAN seed {seed} held {held:.1?} with {with:.1?}");
        }
    }
}

/// The motion propagation against the covariance itself: for a quantity linear in the
/// perturbation (two components of the tangent step) the Cholesky central differences
/// return the covariance block exactly (1e-9 relative: rounding of the retraction at
/// steps of 1e-3).
#[test]
fn motion_covariance_matches_the_covariance_block() {
    let a = nalgebra::Matrix6::<f64>::from_fn(|r, k| {
        ((r * 7 + k * 3) % 5) as f64 - 2.0 + if r == k { 6.0 } else { 0.0 }
    });
    let cov = (a * a.transpose()) * 1e-8;
    let m = Isometry3::new(Vector3::new(0.0, 0.0, 1.0), Vector3::new(0.0, 0.02, 0.0));
    let ml = RigMotionEstimate {
        cam2_from_cam1: m,
        covariance: cov,
        centre_displacement: Vector3::zeros(),
        centre_covariance: Matrix3::zeros(),
        points: Vec::new(),
        rms_px: 0.0,
        sigma_px: 0.0,
        iterations: 0,
    };
    // The tangent step of `perturb` recovered from the moved motion (left perturbation).
    let q = |p: &Isometry3<f64>| {
        let d = p * m.inverse();
        Some(Vector2::new(d.rotation.scaled_axis().y, d.translation.vector.z))
    };
    let c = motion_covariance(&ml, q).unwrap();
    let expect = Matrix2::new(cov[(1, 1)], cov[(1, 5)], cov[(5, 1)], cov[(5, 5)]);
    assert!((c - expect).norm() <= 1e-6 * expect.norm(), "{c} vs {expect}");
}

/// The data part of the pan sigma (motion and flow; the calibration exact: estimated
/// noise-free on the same head): z-scores of repeated 1 px drives from one pose (RMS z
/// 0.83 here). 40 drives: an RMS z of a calibrated sigma lies in [0.78, 1.21] with 95 %
/// probability; the bound on the correlation of the motion's and the flow's errors may
/// only make it smaller, hence [0.5, 1.3].
#[test]
fn pan_data_sigma_covers_repeated_drives() {
    let base = Scenario { seed: 4, near_panels: Scenario::ROBOT_NEAR_PANELS, ..Scenario::default() };
    let (exact, vt) = calibrated_robot(Scenario { noise_px: 0.0, ..base.clone() });
    let (cal, verge) = (&vt.calibration, &vt.verge_axes);
    let axes = vt.axis_perturbations();
    let mut robot = SimulatedRobot::new(Scenario { noise_px: 1.0, ..base }).unwrap();
    let enc = exact.head().encoders();
    robot.move_to(&enc).unwrap();
    // The simulated readings are exact: the data's sigma alone.
    let opt = PanOptions { encoder_sigma_deg: 0.0, ..PanOptions::default() };
    let mut z2 = Vec::new();
    for _ in 0..40 {
        let before = robot.capture().unwrap();
        robot.drive(opt.drive_m).unwrap();
        let after = robot.capture().unwrap();
        robot.drive(-opt.drive_m).unwrap();
        let step = pan_step(cal, verge, Some(&axes), &before, &after, &opt).unwrap();
        let err = robot.pan_err_deg(&enc.moved(Joint::Pan, step.pan_correction_deg));
        assert!(step.sigma_calibration_deg < 1e-3 * step.sigma_deg, "{step:?}");
        z2.push((err / step.sigma_deg).powi(2));
    }
    let rms_z = (z2.iter().sum::<f64>() / z2.len() as f64).sqrt();
    assert!((0.5..1.3).contains(&rms_z), "RMS z {rms_z}");
}

/// A robot on a ramp: every drive also pitches it about its own x axis (a motion
/// that is not planar).
struct Ramp {
    inner: SimulatedRobot,
    pitch_deg: f64,
}

impl StereoHead for Ramp {
    fn image_size(&self) -> [u32; 2] {
        self.inner.image_size()
    }
    fn read_encoders(&mut self) -> Result<Encoders, headalign_platform::PlatformError> {
        self.inner.read_encoders()
    }
    fn move_to(&mut self, target: &Encoders) -> Result<(), headalign_platform::PlatformError> {
        self.inner.move_to(target)
    }
    fn capture(&mut self) -> Result<StereoCapture, headalign_platform::PlatformError> {
        self.inner.capture()
    }
}

impl Vehicle for Ramp {
    fn drive(&mut self, d: f64) -> Result<(), headalign_platform::PlatformError> {
        self.inner.drive(d)?;
        let pitch = Isometry3::rotation(Vector3::x() * self.pitch_deg.to_radians() * d.signum());
        let pose = self.inner.head().world_from_robot() * pitch;
        self.inner.head_mut().set_world_from_robot(pose);
        Ok(())
    }
    fn steer_to(&mut self, e: f64) -> Result<(), headalign_platform::PlatformError> {
        self.inner.steer_to(e)
    }
    fn read_steering(&mut self) -> Result<f64, headalign_platform::PlatformError> {
        self.inner.read_steering()
    }
}

/// Non-planar drives are named, in both stages, by the chi-square test (noise-free,
/// so only the pitch can trip it: 0.3 deg, below the former fixed 1 deg limit, and 3
/// deg for the pan stage; 5 deg with a 10-15 deg turn for the steering stage); flat
/// drives pass it with chi-square values near zero. The pan axis stands 5 deg off the
/// floor's normal, the most the stages must take: the fitted normal absorbs that tilt
/// but not a pitch (a straight drive's best "floor" for a pitch is 90 deg off, which the
/// prior's test refuses; turns of both signs pitch about different axes).
#[test]
fn non_planar_motion_is_named() {
    let s = Scenario {
        seed: 2,
        noise_px: 0.0,
        outlier_fraction: 0.0,
        near_panels: Scenario::ROBOT_NEAR_PANELS,
        pan_tilt_deg: 5.0,
        ..Scenario::default()
    };
    let (mut robot, vt) = calibrated_robot(s);
    let (cal, verge) = (&vt.calibration, &vt.verge_axes);
    let axes = vt.axis_perturbations();
    // Planar: fine, and the pan stage reports its planarity check near zero.
    let flat = align_pan(&mut robot, cal, verge, Some(&axes), &PanOptions::default()).unwrap();
    assert!(flat.steps.iter().all(|s| s.off_axis_deg < 1e-6 && s.planarity_chi2 < 1.0), "{flat:?}");
    let mut ramp = Ramp { inner: robot, pitch_deg: 0.3 };
    assert!(matches!(
        align_pan(&mut ramp, cal, verge, Some(&axes), &PanOptions::default()),
        Err(AlignError::NotPlanar(_))
    ));
    ramp.pitch_deg = 3.0;
    assert!(matches!(
        align_pan(&mut ramp, cal, verge, Some(&axes), &PanOptions::default()),
        Err(AlignError::NotPlanar(_))
    ));
    ramp.pitch_deg = 5.0;
    assert!(matches!(
        zero_steering(&mut ramp, cal, verge, Some(&axes), &SteeringOptions::default()),
        Err(AlignError::NotPlanar(_))
    ));
}

/// The rig check (`check_rig`): a predicted rig that fits the capture is used as it
/// is (no correction, the same rig); one turned 1.5 deg about the cameras' x axis
/// (a vertical misalignment of about 18 px) is detected and re-fitted to the
/// capture; a capture whose right pixels belong to other tracks fits no rig and is
/// named.
#[test]
fn rig_check_corrects_a_misfitting_rig_and_names_a_hopeless_one() {
    let s =
        Scenario { seed: 1, noise_px: 1.0, near_panels: Scenario::ROBOT_NEAR_PANELS, ..Scenario::default() };
    let (mut robot, vt) = calibrated_robot(s);
    let cal = &vt.calibration;
    let enc = robot.read_encoders().unwrap();
    let cap = robot.capture().unwrap();
    let predicted = rig_at(cal, &vt.verge_axes, &enc).unwrap();
    let noise = cal.report.sigma_px;
    let (rig, correction, check) = check_rig(predicted.clone(), &[&cap], noise, &enc).unwrap();
    assert!(correction.is_none() && check.misfit_px <= check.bound_px, "{check:?}");
    assert_eq!(rig.stereo, predicted.stereo);
    assert!(check.matches > 100, "{check:?}");

    let tilt = Isometry3::rotation(Vector3::x() * 1.5f64.to_radians());
    let off = predicted.clone().corrected(Some(&tilt));
    let (fixed, correction, check) = check_rig(off, &[&cap], noise, &enc).unwrap();
    assert!(correction.is_some() && check.misfit_px > 4.0 * check.bound_px, "{check:?}");
    assert!(check.used_misfit_px <= check.bound_px, "{check:?}");
    // The re-fit undoes the tilt: measured 0.038 deg about x and 0.004 about z from the
    // predicted rig, which is itself off the truth by a few hundredths of a degree at
    // 1 px (the fit is to the data, not to the prediction); nothing about y, which the
    // check keeps (a five-parameter re-fit had drifted 0.36 deg there).
    let d =
        (fixed.stereo.right_from_left * predicted.stereo.right_from_left.inverse()).rotation.scaled_axis();
    assert!(d.norm().to_degrees() < 0.1, "{d:?}");
    assert!(d.y.to_degrees().abs() < 1e-3, "{d:?}");
    assert!(
        (fixed.stereo.right_from_left.translation.vector.norm()
            - predicted.stereo.right_from_left.translation.vector.norm())
        .abs()
            < 1e-12
    );

    let mut shuffled = cap.clone();
    let n = shuffled.right.len();
    let pixels: Vec<_> = shuffled.right.iter().map(|o| o.pixel).collect();
    for (i, o) in shuffled.right.iter_mut().enumerate() {
        o.pixel = pixels[(i + n / 2) % n];
    }
    let err = check_rig(predicted, &[&shuffled], noise, &enc).err();
    assert!(matches!(err, Some(AlignError::RigMisfit { .. })), "{err:?}");
    assert!(err.is_some_and(|e| e.to_string().contains("run the verge/tilt stage again")));
}

/// Seed 78 of `experiment coverage`'s robot group at 3 px (readings with 0.01 deg of
/// noise) once had its right vergence axis 12 deg off (a 3 deg vergence move at 3 px),
/// so the rig predicted at the aligned readings, 9 deg of right vergence away, was
/// 1.9 deg off and misfitted the pan drive's captures by a median 13 px; the drive
/// registration then found 3 consistent tracks and the pan stage failed. The estimate
/// no longer errs so there (its points re-triangulated by support, session 19), so the
/// test tilts that axis by 12 deg itself: the rig check must see the misfit, re-fit
/// the rig and let the stage complete.
#[test]
fn a_misfitting_rig_is_corrected() {
    let s = Scenario {
        seed: 78,
        noise_px: 3.0,
        encoder_noise_deg: ENCODER_SIGMA_DEG,
        near_panels: Scenario::ROBOT_NEAR_PANELS,
        ..Scenario::default()
    };
    let opts = VergeTiltOptions {
        estimation: EstimationOptions::scaled_for_noise(3.0, 78),
        ..VergeTiltOptions::default()
    };
    let mut robot = SimulatedRobot::new(s).unwrap();
    let vt = VergeTiltRun::default().run(robot.head_mut(), &opts).unwrap();
    let axes = vt.axis_perturbations();
    let mut verge = vt.verge_axes;
    let right = verge.right.unwrap();
    let d = right.direction.into_inner();
    let about = nalgebra::Unit::new_normalize(d.cross(&nalgebra::Vector3::x()));
    let tilted = nalgebra::Rotation3::from_axis_angle(&about, 12f64.to_radians()) * d;
    verge.right =
        Some(headalign_geometry::so3::Line::new(nalgebra::Unit::new_normalize(tilted), right.point));
    let pan = PanOptions::default();
    let out = align_pan(&mut robot, &vt.calibration, &verge, Some(&axes), &pan).unwrap();
    let check = out.steps[0].rig_check;
    assert!(check.misfit_px > check.bound_px && check.correction_deg > 1.0, "{check:?}");
}
