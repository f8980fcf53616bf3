//! The pan stage ([`super`] module docs, "pan", "uncertainty of the pan"; paper section
//! 4, `docs/how-it-works.md#4-pan`): from the captures before and after a forward drive,
//! two estimates of the pan correction, their covariance and their combination; the
//! stage itself ([`align_pan`]) drives, corrects and repeats.
//!
//! Per drive ([`pan_step`], a pipeline of named steps): [`measure_drive`] (the rig checked
//! against the drive's stereo pairs, the pan axis in its frame, the drive's rigid motion,
//! the floor normal fitted to it, [`super::floor`]);
//! [`image_estimate`] (left-left flow derotated by the measured rotation, guided by the
//! reconstruction's prediction, the epipole by [`translation_from_flow`]); [`pan_geometry`]
//! (both estimates as travel directions of the pan axis, turned back about the floor
//! normal by half the heading change, and their angles about the pan axis from the head's
//! forward direction);
//! [`image_noise`] (the flow's and the drive motion's noise through both estimates);
//! [`calibration_part`] (the calibration's and the readings' covariance of both estimates
//! and of the out-of-plane part and the pan axis' tilt, the whole computation re-run under
//! each perturbation); [`planarity_test`] (about the fitted normal, on the degrees of
//! freedom its fit leaves); [`combine`] (the minimum-variance convex combination and its
//! stated sigma).
//!
//! Units: angles in radians inside, degrees in [`PanStep`]; lengths in stereo baselines;
//! thresholds in pixels (`guide_px`, `min_flow_px`, the epipole's RANSAC), scaled to the
//! calibration's noise ([`PanOptions::scaled_to_noise`]). Degrees of freedom: the drive
//! 6, the epipole 2, the floor normal 2 (one fixed by the drive, one by its prior); the
//! pan correction is 1.
//!
//! Pitfalls: the half-turn correction is exact for the rear-axle line, so it assumes the
//! pan axis stands over it (a no-op with a straight wheel; a pan axis tilted from the
//! floor normal puts the point `o` at camera height off that line too); the flow and the motion share
//! the left images, whose correlation is not modelled: the stated sigma takes the bound
//! valid for any correlation of the two ([`combine`]).

use headalign_geometry::rigmotion::refine_rig_motion;
use headalign_geometry::translation::{
    FlowMatch, TranslationEstimate, derotate, refit_translation, translation_from_flow,
};
use headalign_platform::{Encoders, Joint, StereoCapture, StereoHead, Vehicle};
use nalgebra::{
    Isometry3, Matrix2, Matrix3, Point3, SMatrix, SVector, Unit, UnitQuaternion, Vector2, Vector3,
};

use super::drive::{DriveMotion, drive_motion};
use super::floor::{FloorFit, fit_floor_normal, floor_weights, planarity_limit};
use super::propagation::{
    Readings, calibration_covariance, motion_covariance, out_of_plane, out_of_plane_covariance,
    perpendicular_basis, planarity_chi2, refit_options,
};
use super::rig::{Rig, RigCheck, by_track, check_rig, rig_at};
use super::{FloorNormal, PanOptions, PanOutcome, PanStep};
use crate::alignment::VergeAxes;
use crate::error::{AlignError, StepContext};
use crate::procedure::AxisPerturbations;
use crate::verge_tilt::RigCalibration;

/// Signed angle about `up` from `a` to `b` (both projected onto the plane perpendicular
/// to `up`), radians.
pub(crate) fn angle_about(up: &Vector3<f64>, a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    let ah = a - up * up.dot(a);
    let bh = b - up * up.dot(b);
    up.dot(&ah.cross(&bh)).atan2(ah.dot(&bh))
}

/// Head forward direction (mean of optical axes) in the current left frame.
pub(crate) fn head_forward(rig: &Rig) -> Vector3<f64> {
    Vector3::z() + rig.left_from_right.rotation * Vector3::z()
}

/// Align the pan joint with the robot's direction of travel (module docs).
pub fn align_pan<R: StereoHead + Vehicle>(
    robot: &mut R,
    calib: &RigCalibration,
    verge: &VergeAxes,
    axes: Option<&AxisPerturbations>,
    options: &PanOptions,
) -> Result<PanOutcome, AlignError> {
    options.validate()?;
    let mut steps = Vec::new();
    // Moves are made from the last commanded readings, read once: re-commanding a fresh
    // (noisy) reading would move every joint by its read noise at each step (with 0.01 deg
    // readings the elevation drifted 0.02 deg RMS over the two pan stages' four steps).
    let mut commanded = robot.read_encoders()?;
    for _ in 0..options.iterations {
        let before = robot.capture()?;
        robot.drive(options.drive_m)?;
        let after = robot.capture()?;
        robot.drive(-options.drive_m)?;
        let step = pan_step(calib, verge, axes, &before, &after, options)?;
        commanded = commanded.moved(Joint::Pan, step.pan_correction_deg);
        robot.move_to(&commanded)?;
        steps.push(step);
    }
    let floor = steps.last().map(|s: &PanStep| s.floor);
    Ok(PanOutcome { steps, floor, final_encoders: robot.read_encoders()? })
}

/// The pan axis (direction, a point) in the left camera frame of `rig`.
fn pan_axis_in(calib: &RigCalibration, rig: &Rig) -> Result<(Vector3<f64>, Vector3<f64>), AlignError> {
    let axis = calib.pan_axis().ok_or_else(|| AlignError::MissingMotion("pan axis".into()))?;
    let axis = axis.transformed(&rig.ref_from_left.inverse());
    Ok((axis.direction.into_inner(), axis.point.coords))
}

/// The two pan estimates of a drive (module docs) from its measured motion and image
/// direction: `(a_img, a_st, f_img, f_st)`, angles in radians from the head's forward
/// direction about the pan axis `up`, and the two travel directions of the pan axis' point
/// `o` (the chord turned back by half the heading change about the floor normal `n`).
#[allow(clippy::too_many_arguments)]
fn pan_geometry(
    rig: &Rig,
    up: &Vector3<f64>,
    n: &Vector3<f64>,
    o: &Vector3<f64>,
    motion: &Isometry3<f64>,
    c: &Vector3<f64>,
    direction: &Vector3<f64>,
    use_stereo_rotation: bool,
) -> (f64, f64, Vector3<f64>, Vector3<f64>) {
    let (r, heading) = if use_stereo_rotation {
        let w = motion.rotation.inverse().scaled_axis();
        (motion.rotation.to_rotation_matrix().into_inner(), w.dot(n))
    } else {
        (Matrix3::identity(), 0.0)
    };
    let half_back = UnitQuaternion::from_axis_angle(&Unit::new_normalize(*n), -0.5 * heading);
    let forward_of = |c: &Vector3<f64>| half_back * ((r.transpose() - Matrix3::identity()) * o + c);
    let f_img = forward_of(&(direction * c.norm()));
    let f_st = forward_of(c);
    let h = head_forward(rig);
    (angle_about(up, &h, &f_img), angle_about(up, &h, &f_st), f_img, f_st)
}

/// One pan measurement from the captures before and after a forward drive (module docs:
/// the steps in order).
pub fn pan_step(
    calib: &RigCalibration,
    verge: &VergeAxes,
    axes: Option<&AxisPerturbations>,
    before: &StereoCapture,
    after: &StereoCapture,
    options: &PanOptions,
) -> Result<PanStep, AlignError> {
    let options = &options.scaled_to_noise(calib.report.sigma_px);
    let drive = measure_drive(calib, verge, before, after, options)?;
    let (up, n, motion) = (drive.up, drive.floor.n, &drive.motion);
    let c = motion.ml.centre_displacement;
    let w = motion.cam2_from_cam1.rotation.inverse().scaled_axis();
    let heading_stereo = w.dot(&n);
    let off_axis = (w - n * heading_stereo).norm().to_degrees();
    let flow = image_estimate(&drive, before, after, options)?;
    let dir = flow.estimate.direction.into_inner();
    let (a_img, a_st, f_img, f_st) =
        pan_geometry(&drive.rig, &up, &n, &drive.o, &motion.cam2_from_cam1, &c, &dir, drive.use_rot);
    let noise = image_noise(&drive, &flow, &f_img, &f_st, options);
    let cal = calibration_part(calib, verge, axes, &drive, &flow, options);
    let (chi2, dof) = planarity_test(&drive, &cal, off_axis, options)?;
    let comb = combine(a_img, a_st, &cal, &noise);
    let fc = f_st.normalize();
    Ok(PanStep {
        encoders: drive.enc,
        pan_image_deg: a_img.to_degrees(),
        sigma_image_deg: comb.var_i_all.sqrt().to_degrees(),
        pan_stereo_deg: a_st.to_degrees(),
        sigma_stereo_deg: comb.var_s_all.sqrt().to_degrees(),
        pan_correction_deg: comb.combined.to_degrees(),
        weight_image: comb.w_i,
        sigma_calibration_deg: comb.var_cal.sqrt().to_degrees(),
        sigma_deg: (comb.var_cal + comb.data_sd * comb.data_sd)
            .sqrt()
            .to_degrees()
            .hypot(options.encoder_sigma_deg),
        turn_deg: heading_stereo.to_degrees(),
        off_axis_deg: off_axis,
        planarity_chi2: chi2,
        planarity_dof: dof,
        floor: FloorNormal {
            sigma_pan_tilt_deg: drive
                .floor
                .report
                .sigma_pan_tilt_deg
                .hypot(cal[(5, 5)].max(0.0).sqrt().to_degrees()),
            ..drive.floor.report
        },
        elevation_check_deg: fc.dot(&up).clamp(-1.0, 1.0).asin().to_degrees(),
        median_flow_px: flow.estimate.median_flow_px,
        inliers: [flow.estimate.inliers.len(), motion.inliers],
        rig_check: drive.rig_check,
    })
}

/// A drive measured under the checked rig ([`measure_drive`]).
struct PanDrive {
    /// Head readings during the drive.
    enc: Encoders,
    /// The rig predicted at `enc`, corrected if it misfit the drive's stereo pairs.
    rig: Rig,
    /// That correction of `right_from_left` ([`check_rig`]), applied to every perturbed rig.
    correction: Option<Isometry3<f64>>,
    /// The check's report.
    rig_check: RigCheck,
    /// The pan axis' direction in the rig's left camera frame.
    up: Vector3<f64>,
    /// A point of the pan axis, same frame (baselines).
    o: Vector3<f64>,
    /// The drive's rigid motion.
    motion: DriveMotion,
    /// The floor normal fitted to the drive ([`fit_floor_normal`]), same frame.
    floor: FloorFit,
    /// The weights of that fit ([`floor_weights`]).
    floor_weights: Vec<Matrix3<f64>>,
    /// [`PanOptions::use_stereo_rotation`].
    use_rot: bool,
}

/// The rig at the drive's readings checked against its stereo pairs (and corrected), the
/// pan axis in its frame, and the drive's rigid motion (module docs).
fn measure_drive(
    calib: &RigCalibration,
    verge: &VergeAxes,
    before: &StereoCapture,
    after: &StereoCapture,
    options: &PanOptions,
) -> Result<PanDrive, AlignError> {
    let enc = before.encoders;
    let (rig, correction, rig_check) =
        check_rig(rig_at(calib, verge, &enc)?, &[before, after], calib.report.sigma_px, &enc)?;
    let (up, o) = pan_axis_in(calib, &rig)?;
    let motion = drive_motion(&rig, before, after, &options.registration)?;
    let (floor, floor_weights) = drive_floor(&up, &motion)?;
    floor.plausible(options.planarity_chi2_max, "pan drive")?;
    let use_rot = options.use_stereo_rotation;
    Ok(PanDrive { enc, rig, correction, rig_check, up, o, motion, floor, floor_weights, use_rot })
}

/// The floor normal of one drive (module docs, "floor normal"; [`fit_floor_normal`]),
/// weighted by the drive motion's own out-of-plane covariance about the pan axis `up`,
/// and those weights.
fn drive_floor(up: &Vector3<f64>, motion: &DriveMotion) -> Result<(FloorFit, Vec<Matrix3<f64>>), AlignError> {
    let basis = perpendicular_basis(up);
    let unfit =
        || AlignError::NotPlanar("pan drive: the floor normal could not be fitted to the drive".into());
    let weights = floor_weights(&[out_of_plane_covariance(&motion.ml, up, &basis)]).ok_or_else(unfit)?;
    let fit = fit_floor_normal(up, &[motion.cam2_from_cam1], &weights).ok_or_else(unfit)?;
    Ok((fit, weights))
}

/// The image estimate of a drive ([`image_estimate`]).
struct FlowEstimate {
    /// The epipole's direction, its covariance, its inliers among the guided matches.
    estimate: TranslationEstimate,
    /// The inliers' matches before derotation (first image, second image), pixels.
    raw: Vec<FlowMatch>,
}

/// The image estimate (module docs): left-left matches, the second image derotated by the
/// measured rotation (with `use_stereo_rotation`), kept within `guide_px` of the flow the
/// reconstruction predicts, then the epipole; a median flow below `min_flow_px` is
/// [`AlignError::DriveTooShort`].
fn image_estimate(
    drive: &PanDrive,
    before: &StereoCapture,
    after: &StereoCapture,
    options: &PanOptions,
) -> Result<FlowEstimate, AlignError> {
    let (motion, use_rot) = (&drive.motion, drive.use_rot);
    let r = if use_rot {
        motion.cam2_from_cam1.rotation.to_rotation_matrix().into_inner()
    } else {
        Matrix3::identity()
    };
    let c = motion.ml.centre_displacement;
    let k = drive.rig.k_left;
    let la = by_track(&after.left);
    let mut flow = Vec::new();
    let mut raw = Vec::new();
    for o in &before.left {
        let (Some(x2), Some(xb)) = (la.get(&o.track), motion.before.get(&o.track)) else { continue };
        let Some(d2) = derotate(&k, &r, x2) else { continue };
        let Some(pred) = k.project(&Point3::from(xb.coords - c)) else { continue };
        if !use_rot || (pred - d2).norm() <= options.guide_px {
            flow.push((o.pixel, d2));
            raw.push((o.pixel, *x2));
        }
    }
    let image = translation_from_flow(&k, &flow, &options.translation).step("pan epipole")?;
    if image.median_flow_px < options.min_flow_px {
        return Err(AlignError::DriveTooShort {
            median_flow_px: image.median_flow_px,
            min_flow_px: options.min_flow_px,
        });
    }
    let raw: Vec<FlowMatch> = image.inliers.iter().map(|&i| raw[i]).collect();
    Ok(FlowEstimate { estimate: image, raw })
}

/// The image noise of the two estimates ([`image_noise`]), radians squared.
struct ImageNoise {
    /// The flow's variance of the image estimate, given the motion.
    var_img: f64,
    /// The drive motion's covariance of (image, stereo) estimates.
    c_motion: Matrix2<f64>,
}

/// Data variances of the two estimates (first order; module docs): the epipole's
/// covariance through the image estimate's travel direction `f_img`, and the drive
/// motion's own covariance (all 6 dof) through both estimates by [`motion_covariance`];
/// if that cannot be propagated, the centre's covariance through the stereo one's `f_st`
/// alone.
fn image_noise(
    drive: &PanDrive,
    flow: &FlowEstimate,
    f_img: &Vector3<f64>,
    f_st: &Vector3<f64>,
    options: &PanOptions,
) -> ImageNoise {
    let (up, n, o, rig, use_rot) = (drive.up, drive.floor.n, drive.o, &drive.rig, drive.use_rot);
    let (motion, k, image, raw) = (&drive.motion, drive.rig.k_left, &flow.estimate, &flow.raw);
    let c = motion.ml.centre_displacement;
    let grad = |f: &Vector3<f64>| {
        let fh = f - up * up.dot(f);
        up.cross(&fh) / fh.norm_squared().max(1e-300)
    };
    let g_img = grad(f_img);
    let var_img = c.norm_squared() * (g_img.transpose() * image.covariance * g_img)[(0, 0)];
    let g_st = grad(f_st);
    let var_centre = (g_st.transpose() * motion.ml.centre_covariance * g_st)[(0, 0)];
    // The drive motion's own noise (all 6 dof) through both estimates: the image one
    // depends on the rotation through the derotation of the flow (a rotation error
    // `dw` shifts the epipole by about `dw Z / d`, depth over drive: the largest
    // image-noise term), both on it through the half-turn and the pan axis' offset.
    let angles_at = |m: &Isometry3<f64>| -> Option<Vector2<f64>> {
        let r_p = if use_rot { m.rotation.to_rotation_matrix().into_inner() } else { Matrix3::identity() };
        let flow_p: Vec<FlowMatch> =
            raw.iter().filter_map(|(x1, x2)| Some((*x1, derotate(&k, &r_p, x2)?))).collect();
        let dir_p =
            refit_translation(&k, &flow_p, &image.direction, options.translation.max_iterations).ok()?;
        let c_p = -(m.rotation.inverse() * m.translation.vector);
        let (ai, as_, _, _) = pan_geometry(rig, &up, &n, &o, m, &c_p, &dir_p, use_rot);
        Some(Vector2::new(ai, as_))
    };
    let c_motion = motion_covariance(&motion.ml, angles_at).unwrap_or_else(|| {
        // Not propagated (a refit failed): the centre's part alone, on the stereo estimate.
        Matrix2::new(0.0, 0.0, 0.0, var_centre)
    });
    ImageNoise { var_img, c_motion }
}

/// Calibration covariance (6x6) of both estimates (image, stereo; radians), of the
/// out-of-plane part about the drive's floor normal (radians, radians, baselines) and of
/// the pan axis' tilt from the normal (radians; the normal refitted): the
/// whole computation after the data selections, re-run under each perturbed calibration,
/// vergence axes and readings ([`calibration_covariance`]; the floor normal held: what
/// its fit absorbs is counted in the test's degrees of freedom); NaN where it cannot be
/// propagated.
fn calibration_part(
    calib: &RigCalibration,
    verge: &VergeAxes,
    axes: Option<&AxisPerturbations>,
    drive: &PanDrive,
    flow: &FlowEstimate,
    options: &PanOptions,
) -> SMatrix<f64, 6, 6> {
    let (correction, motion, use_rot) = (&drive.correction, &drive.motion, drive.use_rot);
    let (n, basis) = (drive.floor.n, drive.floor.basis);
    let (image, raw) = (&flow.estimate, &flow.raw);
    let iterations = options.translation.max_iterations;
    let readings = Readings { enc: drive.enc, sigma_deg: options.encoder_sigma_deg };
    let cal = calibration_covariance(calib, verge, axes, &readings, |cp, verge_p, enc_p| {
        let rig_p = rig_at(cp, verge_p, enc_p).ok()?.corrected(correction.as_ref());
        let (up_p, o_p) = pan_axis_in(cp, &rig_p).ok()?;
        let ml_p = refine_rig_motion(
            &rig_p.stereo,
            &motion.tracks,
            &motion.cam2_from_cam1,
            &motion.ml.points,
            &refit_options(),
        )
        .ok()?;
        let m_p = ml_p.cam2_from_cam1;
        let r_p = if use_rot { m_p.rotation.to_rotation_matrix().into_inner() } else { Matrix3::identity() };
        let flow_p: Vec<FlowMatch> =
            raw.iter().filter_map(|(x1, x2)| Some((*x1, derotate(&rig_p.k_left, &r_p, x2)?))).collect();
        let dir_p = refit_translation(&rig_p.k_left, &flow_p, &image.direction, iterations).ok()?;
        let c_p = ml_p.centre_displacement;
        let (ai, as_, _, _) = pan_geometry(&rig_p, &up_p, &n, &o_p, &m_p, &c_p, &dir_p, use_rot);
        let v_p = out_of_plane(&m_p, &n, &basis);
        // The pan axis' tilt from the normal refitted to the refitted drive.
        let tilt_p = fit_floor_normal(&drive.up, &[m_p], &drive.floor_weights)?.n.angle(&up_p);
        Some(SVector::<f64, 6>::from([ai, as_, v_p.x, v_p.y, v_p.z, tilt_p]))
    });
    cal.unwrap_or_else(|| SMatrix::<f64, 6, 6>::from_diagonal_element(f64::NAN))
}

/// The planarity test of the drive (module docs): the chi-square of its out-of-plane part
/// about the fitted floor normal against the motion's covariance plus the calibration's
/// (`cal`'s lower 3x3 block), on `3 - h` degrees of freedom (`h` the drive's leverage in
/// the normal's fit); above [`planarity_limit`] at those is [`AlignError::NotPlanar`]
/// (`off_axis_deg` names the rotation in the message). Returns the chi-square and its
/// degrees of freedom.
fn planarity_test(
    drive: &PanDrive,
    cal: &SMatrix<f64, 6, 6>,
    off_axis_deg: f64,
    options: &PanOptions,
) -> Result<(f64, f64), AlignError> {
    let (n, basis) = (drive.floor.n, drive.floor.basis);
    let v = out_of_plane(&drive.motion.cam2_from_cam1, &n, &basis);
    let v_cov = out_of_plane_covariance(&drive.motion.ml, &n, &basis) + cal.fixed_view::<3, 3>(2, 2);
    let chi2 = planarity_chi2(&v, &v_cov);
    let dof = (3.0 - drive.floor.leverage.first().copied().unwrap_or(0.0)).clamp(0.5, 3.0);
    let limit = planarity_limit(options.planarity_chi2_max, dof);
    if chi2 > limit {
        return Err(AlignError::NotPlanar(format!(
            "pan drive: the robot rotated {off_axis_deg:.3} deg about an axis perpendicular to the floor normal and moved {:.4} baselines along it; chi-square {chi2:.1} ({dof:.2} dof) above {limit:.3} (the pan axis stands {:.2} deg from the fitted floor normal)",
            v.z, drive.floor.report.pan_tilt_deg
        )));
    }
    Ok((chi2, dof))
}

/// The combined pan correction ([`combine`]), radians and radians squared.
struct Combination {
    /// Weight of the image estimate.
    w_i: f64,
    /// The combined correction.
    combined: f64,
    /// Its variance from the calibration (and the readings).
    var_cal: f64,
    /// The bound on its standard deviation from the image noise.
    data_sd: f64,
    /// Image noise variance of the image estimate (flow and motion).
    var_i_all: f64,
    /// Image noise variance of the stereo estimate (motion).
    var_s_all: f64,
}

/// Combination of the image estimate `a_img` and the stereo one `a_st`: weights
/// minimising the variance of `w_i a_img + w_s a_st` under the calibration covariance
/// (`cal`'s upper 2x2 block), the motion's (both estimates, correlated) and the flow's
/// (image estimate), the last two taken as uncorrelated (clamped to [0, 1]: a convex
/// combination). Its stated variance is the calibration part plus a bound on the data
/// part valid for any correlation of the motion's and the flow's errors (both use the
/// left images): `(sqrt(w^T C_m w) + w_i s_flow)^2`.
fn combine(a_img: f64, a_st: f64, cal: &SMatrix<f64, 6, 6>, noise: &ImageNoise) -> Combination {
    let (var_img, c_motion) = (noise.var_img, noise.c_motion);
    let c_cal = cal.fixed_view::<2, 2>(0, 0).into_owned();
    let c_all = c_cal + c_motion + Matrix2::new(var_img, 0.0, 0.0, 0.0);
    let (var_i_all, var_s_all) = (var_img + c_motion[(0, 0)], c_motion[(1, 1)]);
    let w_i = match c_all.try_inverse() {
        Some(inv) if c_all.iter().all(|x| x.is_finite()) => {
            let u = inv * Vector2::new(1.0, 1.0);
            (u.x / (u.x + u.y)).clamp(0.0, 1.0)
        }
        _ => var_s_all / (var_i_all + var_s_all).max(1e-300),
    };
    let wv = Vector2::new(w_i, 1.0 - w_i);
    let combined = w_i * a_img + (1.0 - w_i) * a_st;
    let var_cal = (wv.transpose() * c_cal * wv)[(0, 0)];
    let motion_sd = (wv.transpose() * c_motion * wv)[(0, 0)].max(0.0).sqrt();
    let data_sd = motion_sd + w_i * var_img.sqrt();
    Combination { w_i, combined, var_cal, data_sd, var_i_all, var_s_all }
}
