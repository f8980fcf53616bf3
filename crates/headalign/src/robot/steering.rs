//! The steering stage ([`super`] module docs, "steering"; paper section 7,
//! `docs/how-it-works.md#5-steering`): drives at known steering differences, each a planar
//! turn about the floor normal (fitted to the turns, [`super::floor`]) whose turning centre
//! (stereo baselines, left camera frame at the stage's
//! start) lies on the rear-axle line; the centres give the steering zero (degrees), the
//! wheelbase and the forward direction ([`steering_from_turns`]); the wheel is then set
//! straight.
//!
//! Degrees of freedom: per drive 6 (its rigid motion), of which the planar turn keeps 3;
//! the floor normal 2 (shared by the drives); the solution 3 (zero, wheelbase, forward
//! direction), or 2 with a known wheelbase. The
//! zero's sigma: each drive's motion covariance through its centre plus the calibration's
//! (every drive refitted under each perturbed calibration), by central differences.
//! Thresholds: `min_turn_deg` (degrees), `planarity_chi2_max` (chi-square, 3 dof),
//! `max_sigma_zero_deg` (degrees).
//!
//! Pitfalls: the free 3D screw axis is too noisy in direction (depth noise of the stereo
//! points) to place a centre well, so each turn is taken as planar about the floor normal
//! all the turns share (the pan axis, 1-3 deg off it on a real robot, would move the
//! centres: 1.4-1.7 deg screw axes failed the planarity test on the independent head); one
//! drive failing the planarity test while the others pass is left out as an outlier when
//! three remain and they all pass; a zero with a sigma above `max_sigma_zero_deg` is an
//! error before the wheel is commanded.

use headalign_geometry::rigmotion::{perturb, refine_rig_motion};
use headalign_geometry::so3::screw_from_isometry;
use headalign_geometry::steering::{SteeringSolution, Turn, steering_from_turns};
use headalign_platform::{Encoders, StereoHead, Vehicle};
use nalgebra::{
    DMatrix, DVector, Isometry3, Matrix3, Point3, SMatrix, Unit, UnitQuaternion, Vector3, Vector6,
};

use super::drive::{DriveMotion, drive_motion};
use super::floor::{FloorFit, fit_floor_normal, floor_weights, planarity_limit};
use super::pan::{angle_about, head_forward};
use super::propagation::{
    Readings, calibration_covariance_dyn, out_of_plane, out_of_plane_covariance, perpendicular_basis,
    planarity_chi2, refit_options,
};
use super::rig::{Rig, RigCheck, check_rig, rig_at};
use super::{SteeringOptions, SteeringOutcome, TurnStep};
use crate::alignment::VergeAxes;
use crate::error::{AlignError, StepContext};
use crate::procedure::AxisPerturbations;
use crate::verge_tilt::RigCalibration;

/// The turning centre of a drive `m = cam1_from_cam2` seen as a planar motion about
/// `up` (the floor normal): rotation about `up` by the measured angle's component along it; centre from the
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
    /// The calibrated pan axis in the stage's left camera frame (the floor normal's prior).
    up: &'a Unit<Vector3<f64>>,
    wheelbase: Option<f64>,
    /// The correction of the predicted rig ([`check_rig`]), applied to every perturbed one.
    correction: Option<Isometry3<f64>>,
}

/// The steering solution of a set of drives, the zero's variance (degrees squared), the
/// floor normal fitted to them, each drive's turning centre and planarity chi-square with
/// its degrees of freedom.
struct SteeringFit {
    solution: SteeringSolution,
    var_zero: f64,
    floor: FloorFit,
    centres: Vec<Point3<f64>>,
    chi2: Vec<f64>,
    dof: Vec<f64>,
}

/// The floor normal of a set of drives `motions` (`cam2_from_cam1`) with the fixed
/// weights `weights`, and the steering zero (degrees) from their turning centres about it.
fn zero_with_floor(
    up: &Unit<Vector3<f64>>,
    weights: &[Matrix3<f64>],
    motions: &[Isometry3<f64>],
    settings: &[f64],
    hint: &Vector3<f64>,
    wheelbase: Option<f64>,
) -> Option<f64> {
    let fit = fit_floor_normal(up, motions, weights)?;
    steer_zero_of(&fit.unit(), motions, settings, hint, wheelbase)
}

/// Solve the steering from `motions` (drives at `settings`): the floor normal fitted to
/// their turns, the turning centres about it, the solution, and the propagation (module
/// docs).
fn steering_fit(
    ctx: &SteeringContext,
    motions: &[DriveMotion],
    settings: &[f64],
) -> Result<SteeringFit, AlignError> {
    let (calib, verge, up, wheelbase) = (ctx.calib, ctx.verge, ctx.up, ctx.wheelbase);
    let hint: Vector3<f64> = motions.iter().map(|m| m.cam2_from_cam1.inverse().translation.vector).sum();
    let nominal: Vec<Isometry3<f64>> = motions.iter().map(|m| m.cam2_from_cam1).collect();
    let unfit =
        || AlignError::NotPlanar("steering: the floor normal could not be fitted to the turns".into());
    let up_basis = perpendicular_basis(up);
    let covs: Vec<Matrix3<f64>> =
        motions.iter().map(|d| out_of_plane_covariance(&d.ml, up, &up_basis)).collect();
    let weights = floor_weights(&covs).ok_or_else(unfit)?;
    let floor = fit_floor_normal(up, &nominal, &weights).ok_or_else(unfit)?;
    let n = floor.unit();
    let turns: Vec<Turn> = nominal
        .iter()
        .zip(settings)
        .map(|(m, s)| Some(Turn { steer_encoder_deg: *s, centre: turn_centre(&m.inverse(), &n)? }))
        .collect::<Option<_>>()
        .ok_or_else(|| {
            AlignError::NotPlanar("steering: a turn has no centre about the floor normal".into())
        })?;
    let sol = steering_from_turns(&n, &turns, &hint, wheelbase).step("steering zero")?;
    // Uncertainty: every drive's motion covariance (independent drives) and the
    // calibration's (each drive refitted under each perturbed calibration), propagated by
    // central differences to the out-of-plane parts (about the fitted normal, held), the
    // steering zero and the pan axis' tilt (the normal refitted to the refitted drives).
    let basis = floor.basis;
    let k_n = motions.len();
    let cal = calibration_covariance_dyn(
        calib,
        verge,
        ctx.axes,
        &ctx.readings,
        3 * k_n + 2,
        |cp, verge_p, enc_p| {
            let rig_p = rig_at(cp, verge_p, enc_p).ok()?.corrected(ctx.correction.as_ref());
            let up_p = cp.pan_axis()?.transformed(&rig_p.ref_from_left.inverse()).direction;
            let mut out = DVector::zeros(3 * k_n + 2);
            let mut refits = Vec::with_capacity(k_n);
            for (k, d) in motions.iter().enumerate() {
                let ml = refine_rig_motion(
                    &rig_p.stereo,
                    &d.tracks,
                    &d.cam2_from_cam1,
                    &d.ml.points,
                    &refit_options(),
                )
                .ok()?;
                out.fixed_rows_mut::<3>(3 * k).copy_from(&out_of_plane(&ml.cam2_from_cam1, &n, &basis));
                refits.push(ml.cam2_from_cam1);
            }
            let floor_p = fit_floor_normal(up, &refits, &weights)?;
            out[3 * k_n] = steer_zero_of(&floor_p.unit(), &refits, settings, &hint, wheelbase)?;
            out[3 * k_n + 1] = floor_p.n.angle(&up_p);
            Some(out)
        },
    )
    .unwrap_or_else(|| DMatrix::from_element(3 * k_n + 2, 3 * k_n + 2, f64::NAN));
    let mut floor = floor;
    let tilt_cal_deg = cal[(3 * k_n + 1, 3 * k_n + 1)].max(0.0).sqrt().to_degrees();
    floor.report.sigma_pan_tilt_deg = floor.report.sigma_pan_tilt_deg.hypot(tilt_cal_deg);
    let mut var_zero = cal[(3 * k_n, 3 * k_n)];
    let mut chi2s = Vec::with_capacity(k_n);
    let mut dofs = Vec::with_capacity(k_n);
    for (k, d) in motions.iter().enumerate() {
        let v = out_of_plane(&d.cam2_from_cam1, &n, &basis);
        let v_cov = out_of_plane_covariance(&d.ml, &n, &basis) + cal.fixed_view::<3, 3>(3 * k, 3 * k);
        chi2s.push(planarity_chi2(&v, &v_cov));
        dofs.push((3.0 - floor.leverage[k]).clamp(0.5, 3.0));
        // The drive's own noise, through its centre (and the normal) to the zero.
        let h = 1e-6;
        let mut j = SMatrix::<f64, 1, 6>::zeros();
        for p in 0..6 {
            let mut delta = Vector6::zeros();
            let mut at = |sign: f64| {
                delta[p] = sign * h;
                let mut ms = nominal.clone();
                ms[k] = perturb(&nominal[k], &delta);
                zero_with_floor(up, &weights, &ms, settings, &hint, wheelbase)
            };
            match (at(1.0), at(-1.0)) {
                (Some(a), Some(b)) => j[p] = (a - b) / (2.0 * h),
                _ => j[p] = f64::NAN,
            }
        }
        var_zero += (j * d.ml.covariance * j.transpose())[(0, 0)];
    }
    let centres = turns.iter().map(|t| t.centre).collect();
    Ok(SteeringFit { solution: sol, var_zero, floor, centres, chi2: chi2s, dof: dofs })
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
    let Drives { mut steps, motions, settings, checked } =
        drive_turns(robot, calib, options, &predicted, &enc, &up)?;
    let scale = options.baseline_m;
    let wheelbase = options.wheelbase_m.map(|l| l / scale);
    let (rig, correction, rig_check) =
        checked.ok_or_else(|| AlignError::InvalidOption("steering: no steering settings".into()))?;
    let readings = Readings { enc, sigma_deg: options.encoder_sigma_deg };
    let ctx = SteeringContext { calib, verge, axes, readings, up: &up, wheelbase, correction };
    let (fit, failing, dropped) =
        fit_leaving_out_an_outlier(&ctx, &motions, &settings, options.planarity_chi2_max)?;
    set_floor_quantities(&mut steps, &ctx, &motions, &settings, &fit, &dropped);
    let limit = |fit: &SteeringFit, k: usize| planarity_limit(options.planarity_chi2_max, fit.dof[k]);
    fit.floor.plausible(options.planarity_chi2_max, "steering")?;
    if dropped.is_empty()
        && let Some(&k) = failing.first()
    {
        return Err(AlignError::NotPlanar(format!(
            "steering {:+.1} deg: screw axis {:.2} deg from the fitted floor normal ({:.2} deg from the pan axis, which stands {:.2} deg from that normal); chi-square {:.1} ({:.2} dof) above {:.3} ({} of {} drives failed the test)",
            settings[k],
            steps[k].axis_from_floor_deg,
            steps[k].axis_tilt_deg,
            fit.floor.report.pan_tilt_deg,
            fit.chi2[k],
            fit.dof[k],
            limit(&fit, k),
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
        floor: fit.floor.report,
        pan_check_deg: pan_check.to_degrees(),
        across_rms_m: sol.across_rms * scale,
        rig_check,
    })
}

/// The drives of [`zero_steering`], one per steering setting, and the rig checked on the
/// first drive's captures.
struct Drives {
    /// Per drive, its report (the floor-normal quantities not yet filled).
    steps: Vec<TurnStep>,
    /// Per drive, the rig's measured motion.
    motions: Vec<DriveMotion>,
    /// Per drive, the steering reading, degrees.
    settings: Vec<f64>,
    /// The rig checked on the first drive ([`check_rig`]); `None` without settings.
    checked: Option<(Rig, Option<Isometry3<f64>>, RigCheck)>,
}

/// Steer to each setting of `options` (from the present reading), drive forward and back
/// capturing before and after, and measure each drive's motion and screw about `up`
/// (module docs). A turn below `min_turn_deg` is an error.
fn drive_turns<R: StereoHead + Vehicle>(
    robot: &mut R,
    calib: &RigCalibration,
    options: &SteeringOptions,
    predicted: &Rig,
    enc: &Encoders,
    up: &Unit<Vector3<f64>>,
) -> Result<Drives, AlignError> {
    let mut checked: Option<(Rig, Option<Isometry3<f64>>, RigCheck)> = None;
    let s0 = robot.read_steering()?;
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
                checked.insert(check_rig(predicted.clone(), &[&before, &after], calib.report.sigma_px, enc)?)
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
            .oriented_along(up);
        steps.push(TurnStep {
            steer_encoder_deg: s0 + s,
            turn_deg: screw.angle.to_degrees(),
            axis_tilt_deg: screw.axis.direction.angle(up).to_degrees(),
            axis_from_floor_deg: f64::NAN,
            planarity_chi2: f64::NAN,
            planarity_dof: f64::NAN,
            inliers: motion.inliers,
            centre: [f64::NAN; 3],
        });
        settings.push(s0 + s);
        motions.push(motion);
    }
    Ok(Drives { steps, motions, settings, checked })
}

/// The steering fit over every drive; a drive that alone fails the planarity test (while
/// more than [`MIN_STEERING_DRIVES`] drives were made) is left out when the rest then pass
/// (module docs). Returns the fit that decided, the drives failing over all of them and
/// the drive left out, if any.
fn fit_leaving_out_an_outlier(
    ctx: &SteeringContext,
    motions: &[DriveMotion],
    settings: &[f64],
    planarity_chi2_max: f64,
) -> Result<(SteeringFit, Vec<usize>, Vec<usize>), AlignError> {
    let mut fit = steering_fit(ctx, motions, settings)?;
    let limit = |fit: &SteeringFit, k: usize| planarity_limit(planarity_chi2_max, fit.dof[k]);
    // A drive that fails the planarity test while the others pass is an outlier (one
    // drive's reconstruction, e.g. a view of far points only, under the rig predicted
    // at the readings); it is left out when enough drives remain and the rest then pass.
    // A robot that really pitches or rolls shows in every drive.
    let failing: Vec<usize> = (0..motions.len()).filter(|&k| fit.chi2[k] > limit(&fit, k)).collect();
    let mut dropped = Vec::new();
    if let [k] = failing[..]
        && motions.len() > MIN_STEERING_DRIVES
    {
        let m2: Vec<DriveMotion> =
            motions.iter().enumerate().filter(|(i, _)| *i != k).map(|(_, m)| m.clone()).collect();
        let s2: Vec<f64> = settings.iter().enumerate().filter(|(i, _)| *i != k).map(|(_, x)| *x).collect();
        let refit = steering_fit(ctx, &m2, &s2)?;
        if !(0..m2.len()).any(|i| refit.chi2[i] > limit(&refit, i)) {
            dropped.push(k);
            fit = refit;
        }
    }
    Ok((fit, failing, dropped))
}

/// Each step's floor-normal quantities from the fit that decided (`fit`, over the drives
/// but `dropped`); a dropped drive keeps those of the fit over every drive, which it
/// failed.
fn set_floor_quantities(
    steps: &mut [TurnStep],
    ctx: &SteeringContext,
    motions: &[DriveMotion],
    settings: &[f64],
    fit: &SteeringFit,
    dropped: &[usize],
) {
    let kept: Vec<usize> = (0..steps.len()).filter(|k| !dropped.contains(k)).collect();
    let all = if dropped.is_empty() { None } else { steering_fit(ctx, motions, settings).ok() };
    for (k, step) in steps.iter_mut().enumerate() {
        let (f, i) = match kept.iter().position(|&j| j == k) {
            Some(i) => (fit, i),
            None => match &all {
                Some(a) => (a, k),
                None => continue,
            },
        };
        let m = motions[k].cam2_from_cam1.inverse();
        let axis = m.rotation.axis().map_or(f64::NAN, |a| {
            let a = if a.dot(&f.floor.n) < 0.0 { -a.into_inner() } else { a.into_inner() };
            a.angle(&f.floor.n).to_degrees()
        });
        step.axis_from_floor_deg = axis;
        step.planarity_chi2 = f.chi2[i];
        step.planarity_dof = f.dof[i];
        let c = f.centres[i];
        step.centre = [c.x, c.y, c.z];
    }
}
