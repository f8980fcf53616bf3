//! The steering stage ([`super`] module docs, "steering"; paper section 7,
//! `docs/how-it-works.md#5-steering`): drives at known steering differences, each a planar turn about the
//! pan axis whose turning centre (stereo baselines, left camera frame at the stage's
//! start) lies on the rear-axle line; the centres give the steering zero (degrees), the
//! wheelbase and the forward direction ([`steering_from_turns`]); the wheel is then set
//! straight.
//!
//! Degrees of freedom: per drive 6 (its rigid motion), of which the planar turn keeps 3;
//! the solution 3 (zero, wheelbase, forward direction), or 2 with a known wheelbase. The
//! zero's sigma: each drive's motion covariance through its centre plus the calibration's
//! (every drive refitted under each perturbed calibration), by central differences.
//! Thresholds: `min_turn_deg` (degrees), `planarity_chi2_max` (chi-square, 3 dof),
//! `max_sigma_zero_deg` (degrees).
//!
//! Pitfalls: the free 3D screw axis is too noisy in direction (depth noise of the stereo
//! points) to place a centre well, so each turn is taken as planar about the pan axis; one
//! drive failing the planarity test while the others pass is left out as an outlier when
//! three remain and they all pass; a zero with a sigma above `max_sigma_zero_deg` is an
//! error before the wheel is commanded.

use headalign_geometry::rigmotion::{perturb, refine_rig_motion};
use headalign_geometry::so3::screw_from_isometry;
use headalign_geometry::steering::{SteeringSolution, Turn, steering_from_turns};
use headalign_platform::{StereoHead, Vehicle};
use nalgebra::{
    DMatrix, DVector, Isometry3, Matrix3, Point3, SMatrix, Unit, UnitQuaternion, Vector3, Vector6,
};

use super::drive::{DriveMotion, drive_motion};
use super::pan::{angle_about, head_forward};
use super::propagation::{
    Readings, calibration_covariance_dyn, out_of_plane, out_of_plane_covariance, perpendicular_basis,
    planarity_chi2, refit_options,
};
use super::rig::{Rig, RigCheck, check_rig, rig_at};
use super::{SteeringOptions, SteeringOutcome, TurnStep};
use crate::alignment::VergeAxes;
use crate::error::{AlignError, StepContext};
use crate::estimate::RigCalibration;
use crate::procedure::AxisPerturbations;

/// The turning centre of a drive `m = cam1_from_cam2` seen as a planar motion about
/// `up`: rotation about `up` by the measured angle's component along it; centre from the
/// horizontal translation (`(I - R + u u^T) p = t_perp`). The free 3D screw axis is too
/// noisy in direction (depth noise of the stereo points) to place the centre well.
fn turn_centre(m: &Isometry3<f64>, up: &Unit<Vector3<f64>>) -> Option<Point3<f64>> {
    let u = up.into_inner();
    let phi = m.rotation.scaled_axis().dot(&u);
    let r_planar = UnitQuaternion::from_axis_angle(up, phi).to_rotation_matrix().into_inner();
    let t = m.translation.vector;
    let t_perp = t - u * u.dot(&t);
    let a = Matrix3::identity() - r_planar + u * u.transpose();
    a.try_inverse().map(|inv| Point3::from(inv * t_perp))
}

/// Steering zero (degrees) from the drives' motions `cam2_from_cam1` under `up`.
fn steer_zero_of(
    up: &Unit<Vector3<f64>>,
    motions: &[Isometry3<f64>],
    settings: &[f64],
    hint: &Vector3<f64>,
    wheelbase: Option<f64>,
) -> Option<f64> {
    let turns: Option<Vec<Turn>> = motions
        .iter()
        .zip(settings)
        .map(|(m, s)| Some(Turn { steer_encoder_deg: *s, centre: turn_centre(&m.inverse(), up)? }))
        .collect();
    steering_from_turns(up, &turns?, hint, wheelbase).ok().map(|s| s.steer_zero_deg)
}

/// Fewest steering drives a solution keeps after leaving one out (three determine the
/// zero, the wheelbase and the forward direction).
const MIN_STEERING_DRIVES: usize = 3;

/// What the steering solution of a set of drives needs besides the drives.
struct SteeringContext<'a> {
    calib: &'a RigCalibration,
    verge: &'a VergeAxes,
    axes: Option<&'a AxisPerturbations>,
    readings: Readings,
    up: &'a Unit<Vector3<f64>>,
    wheelbase: Option<f64>,
    /// The correction of the predicted rig ([`check_rig`]), applied to every perturbed one.
    correction: Option<Isometry3<f64>>,
}

/// The steering solution of a set of drives, the zero's variance (degrees squared) and
/// each drive's planarity chi-square.
struct SteeringFit {
    solution: SteeringSolution,
    var_zero: f64,
    chi2: Vec<f64>,
}

/// Solve the steering from `motions` (drives at `settings`, centres `turns`) and
/// propagate (module docs).
fn steering_fit(
    ctx: &SteeringContext,
    motions: &[DriveMotion],
    settings: &[f64],
    turns: &[Turn],
) -> Result<SteeringFit, AlignError> {
    let (calib, verge, up, wheelbase) = (ctx.calib, ctx.verge, ctx.up, ctx.wheelbase);
    let hint: Vector3<f64> = motions.iter().map(|m| m.cam2_from_cam1.inverse().translation.vector).sum();
    let sol = steering_from_turns(up, turns, &hint, wheelbase).step("steering zero")?;
    // Uncertainty: every drive's motion covariance (independent drives) and the
    // calibration's (each drive refitted under each perturbed calibration), propagated by
    // central differences to the out-of-plane parts and the steering zero.
    let basis = perpendicular_basis(up);
    let nominal: Vec<Isometry3<f64>> = motions.iter().map(|m| m.cam2_from_cam1).collect();
    let n = motions.len();
    let cal =
        calibration_covariance_dyn(calib, verge, ctx.axes, &ctx.readings, 3 * n + 1, |cp, verge_p, enc_p| {
            let rig_p = rig_at(cp, verge_p, enc_p).ok()?.corrected(ctx.correction.as_ref());
            let up_p = cp.pan_axis()?.transformed(&rig_p.ref_from_left.inverse()).direction;
            let q = UnitQuaternion::rotation_between(up, &up_p).unwrap_or_else(UnitQuaternion::identity);
            let basis_p = [q * basis[0], q * basis[1]];
            let mut out = DVector::zeros(3 * n + 1);
            let mut refits = Vec::with_capacity(n);
            for (k, d) in motions.iter().enumerate() {
                let ml = refine_rig_motion(
                    &rig_p.stereo,
                    &d.tracks,
                    &d.cam2_from_cam1,
                    &d.ml.points,
                    &refit_options(),
                )
                .ok()?;
                out.fixed_rows_mut::<3>(3 * k).copy_from(&out_of_plane(&ml.cam2_from_cam1, &up_p, &basis_p));
                refits.push(ml.cam2_from_cam1);
            }
            out[3 * n] = steer_zero_of(&up_p, &refits, settings, &hint, wheelbase)?;
            Some(out)
        })
        .unwrap_or_else(|| DMatrix::from_element(3 * n + 1, 3 * n + 1, f64::NAN));
    let mut var_zero = cal[(3 * n, 3 * n)];
    let mut chi2s = Vec::with_capacity(n);
    for (k, d) in motions.iter().enumerate() {
        let v = out_of_plane(&d.cam2_from_cam1, up, &basis);
        let v_cov = out_of_plane_covariance(&d.ml, up, &basis) + cal.fixed_view::<3, 3>(3 * k, 3 * k);
        chi2s.push(planarity_chi2(&v, &v_cov));
        // The drive's own noise, through its centre to the zero.
        let h = 1e-6;
        let mut j = SMatrix::<f64, 1, 6>::zeros();
        for p in 0..6 {
            let mut delta = Vector6::zeros();
            let mut at = |sign: f64| {
                delta[p] = sign * h;
                let mut ms = nominal.clone();
                ms[k] = perturb(&nominal[k], &delta);
                steer_zero_of(up, &ms, settings, &hint, wheelbase)
            };
            match (at(1.0), at(-1.0)) {
                (Some(a), Some(b)) => j[p] = (a - b) / (2.0 * h),
                _ => j[p] = f64::NAN,
            }
        }
        var_zero += (j * d.ml.covariance * j.transpose())[(0, 0)];
    }
    Ok(SteeringFit { solution: sol, var_zero, chi2: chi2s })
}

/// Find the steering zero from drives at known steering differences and straighten the
/// wheel (module docs).
pub fn zero_steering<R: StereoHead + Vehicle>(
    robot: &mut R,
    calib: &RigCalibration,
    verge: &VergeAxes,
    axes: Option<&AxisPerturbations>,
    options: &SteeringOptions,
) -> Result<SteeringOutcome, AlignError> {
    options.validate()?;
    let options = &options.scaled_to_noise(calib.report.sigma_px);
    let enc = robot.read_encoders()?;
    let predicted = rig_at(calib, verge, &enc)?;
    let pan_axis = calib.pan_axis().ok_or_else(|| AlignError::MissingMotion("pan axis".into()))?;
    // The vergence readings do not change during the stage, so neither does the rig: it
    // is checked on the first drive's captures ([`check_rig`]; its correction, if any,
    // leaves `ref_from_left` and so `up` as predicted).
    let up = pan_axis.transformed(&predicted.ref_from_left.inverse()).direction;
    let mut checked: Option<(Rig, Option<Isometry3<f64>>, RigCheck)> = None;
    let s0 = robot.read_steering()?;
    let mut turns = Vec::new();
    let mut steps = Vec::new();
    let mut motions = Vec::new();
    let mut settings = Vec::new();
    for s in &options.settings_deg {
        robot.steer_to(s0 + s)?;
        let before = robot.capture()?;
        robot.drive(options.drive_m)?;
        let after = robot.capture()?;
        robot.drive(-options.drive_m)?;
        let (rig, _, _) = match &checked {
            Some(c) => c,
            None => {
                checked.insert(check_rig(predicted.clone(), &[&before, &after], calib.report.sigma_px, &enc)?)
            }
        };
        let motion = drive_motion(rig, &before, &after, &options.registration)?;
        let m = motion.cam2_from_cam1.inverse();
        let angle = m.rotation.angle().to_degrees();
        if angle < options.min_turn_deg {
            return Err(AlignError::TurnTooSmall { angle_deg: angle, min_deg: options.min_turn_deg });
        }
        let screw = screw_from_isometry(&m, options.min_turn_deg.to_radians())
            .ok_or(AlignError::TurnTooSmall { angle_deg: angle, min_deg: options.min_turn_deg })?
            .oriented_along(&up);
        let tilt = screw.axis.direction.angle(&up).to_degrees();
        let centre = turn_centre(&m, &up)
            .ok_or(AlignError::TurnTooSmall { angle_deg: angle, min_deg: options.min_turn_deg })?;
        turns.push(Turn { steer_encoder_deg: s0 + s, centre });
        steps.push(TurnStep {
            steer_encoder_deg: s0 + s,
            turn_deg: screw.angle.to_degrees(),
            axis_tilt_deg: tilt,
            planarity_chi2: f64::NAN,
            inliers: motion.inliers,
            centre: [centre.x, centre.y, centre.z],
        });
        settings.push(s0 + s);
        motions.push(motion);
    }
    let scale = options.baseline_m;
    let wheelbase = options.wheelbase_m.map(|l| l / scale);
    let (rig, correction, rig_check) =
        checked.ok_or_else(|| AlignError::InvalidOption("steering: no steering settings".into()))?;
    let readings = Readings { enc, sigma_deg: options.encoder_sigma_deg };
    let ctx = SteeringContext { calib, verge, axes, readings, up: &up, wheelbase, correction };
    let mut fit = steering_fit(&ctx, &motions, &settings, &turns)?;
    for (step, chi2) in steps.iter_mut().zip(&fit.chi2) {
        step.planarity_chi2 = *chi2;
    }
    // A drive that fails the planarity test while the others pass is an outlier (one
    // drive's reconstruction, e.g. a view of far points only, under the rig predicted
    // at the readings); it is left out when enough drives remain and the rest then pass.
    // A robot that really pitches or rolls, or a pan axis off perpendicular, shows in
    // every drive.
    let failing: Vec<usize> =
        (0..steps.len()).filter(|&k| fit.chi2[k] > options.planarity_chi2_max).collect();
    let mut dropped = Vec::new();
    if let [k] = failing[..]
        && steps.len() > MIN_STEERING_DRIVES
    {
        let m2: Vec<DriveMotion> =
            motions.iter().enumerate().filter(|(i, _)| *i != k).map(|(_, m)| m.clone()).collect();
        let s2: Vec<f64> = settings.iter().enumerate().filter(|(i, _)| *i != k).map(|(_, x)| *x).collect();
        let t2: Vec<Turn> = turns.iter().enumerate().filter(|(i, _)| *i != k).map(|(_, x)| *x).collect();
        let refit = steering_fit(&ctx, &m2, &s2, &t2)?;
        if !refit.chi2.iter().any(|c| *c > options.planarity_chi2_max) {
            dropped.push(k);
            fit = refit;
        }
    }
    if dropped.is_empty()
        && let Some(&k) = failing.first()
    {
        return Err(AlignError::NotPlanar(format!(
            "steering {:+.1} deg: screw axis {:.2} deg from the pan axis; chi-square {:.1} (3 dof) above {} ({} of {} drives failed the test)",
            settings[k],
            steps[k].axis_tilt_deg,
            fit.chi2[k],
            options.planarity_chi2_max,
            failing.len(),
            steps.len()
        )));
    }
    let sol = fit.solution;
    let sigma_zero = fit.var_zero.sqrt();
    // A NaN sigma (not propagated) passes: the zero itself may be well determined.
    if sigma_zero > options.max_sigma_zero_deg {
        return Err(AlignError::SteeringUndetermined {
            zero_deg: sol.steer_zero_deg,
            sigma_deg: sigma_zero,
            max_sigma_deg: options.max_sigma_zero_deg,
            drives: steps.len() - dropped.len(),
            dropped_turns: dropped,
        });
    }
    robot.steer_to(sol.steer_zero_deg)?;
    let pan_check = angle_about(&up, &head_forward(&rig), &sol.forward);
    Ok(SteeringOutcome {
        turns: steps,
        dropped_turns: dropped,
        steer_zero_deg: sol.steer_zero_deg,
        sigma_steer_zero_deg: sigma_zero,
        wheelbase_m: sol.wheelbase * scale,
        pan_check_deg: pan_check.to_degrees(),
        across_rms_m: sol.across_rms * scale,
        rig_check,
    })
}
