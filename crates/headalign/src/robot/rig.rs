//! The calibrated stereo rig at a robot stage's readings ([`super`] module docs): the
//! cameras predicted by the calibrated kinematics (the pan/elevation chain and the
//! vergence axes moving each camera from the reference readings), in the current left
//! camera frame, stereo baselines; the **rig check** against the stage's own stereo pairs
//! and its correction; [`predicted_rig`] with the prediction's covariance, and the
//! predicted stereo [`stereo_fundamental`] the image front end can be guided by.
//!
//! Rig check: each stereo match triangulated (linear) from its two pixels, the larger of
//! its two reprojection errors (pixels), median over the matches, against
//! [`RIG_MISFIT_SIGMAS`] times the calibration's noise estimate (at least
//! [`RIG_MISFIT_FLOOR_PX`]). A misfitting rig is re-fitted to the pairs on the Sampson
//! distance (5 dof, gate 3.5 sigma), of which only the 3 vertical components are kept
//! (rotations about the right camera's x and z axes, the baseline's y component: what
//! vertical disparities determine; the baseline's length stays the gauge).
//! Pitfalls: one pair leaves the rotation about y and the baseline's z component weakly
//! determined (the points' depths absorb them), hence they stay as predicted; a rig that
//! still misfits after the correction is [`AlignError::RigMisfit`].

use std::collections::HashMap;

use headalign_geometry::camera::{Intrinsics, ProjectiveCamera};
use headalign_geometry::essential::refine_relative_pose;
use headalign_geometry::rigmotion::StereoRig;
use headalign_geometry::triangulation::triangulate_linear;
use headalign_platform::{Encoders, StereoCapture};
use nalgebra::{Isometry3, Matrix3, Matrix6, Point2, Translation3, UnitQuaternion, Vector3, Vector6};
use serde::Serialize;

use super::propagation::{Readings, calibration_covariance};
use crate::alignment::VergeAxes;
use crate::error::AlignError;
use crate::procedure::{AxisPerturbations, predicted_poses};
use crate::verge_tilt::RigCalibration;

/// The calibrated stereo cameras at readings `enc`, in the current left camera frame,
/// plus `ref_from_left` (to move calibrated axes into that frame).
#[derive(Clone)]
pub(crate) struct Rig {
    pub(super) k_left: Intrinsics,
    pub(super) p_left: ProjectiveCamera,
    pub(super) p_right: ProjectiveCamera,
    pub(crate) ref_from_left: Isometry3<f64>,
    pub(crate) left_from_right: Isometry3<f64>,
    pub(super) stereo: StereoRig,
}

pub(crate) fn rig_at(calib: &RigCalibration, verge: &VergeAxes, enc: &Encoders) -> Result<Rig, AlignError> {
    let (ref_from_left, ref_from_right) = predicted_poses(calib, verge, &calib.reference_encoders, enc)?;
    let left_from_right = ref_from_left.inverse() * ref_from_right;
    let st = &calib.bundle.state;
    Ok(Rig {
        k_left: st.left,
        p_left: ProjectiveCamera::from_pose(&st.left, &Isometry3::identity()),
        p_right: ProjectiveCamera::from_pose(&st.right, &left_from_right.inverse()),
        ref_from_left,
        left_from_right,
        stereo: StereoRig { left: st.left, right: st.right, right_from_left: left_from_right.inverse() },
    })
}

impl Rig {
    /// This rig with its relative pose `right_from_left` replaced by `correction *
    /// right_from_left` ([`check_rig`]); `None` leaves it unchanged.
    pub(crate) fn corrected(self, correction: Option<&Isometry3<f64>>) -> Rig {
        let Some(c) = correction else { return self };
        let right_from_left = c * self.stereo.right_from_left;
        Rig {
            p_right: ProjectiveCamera::from_pose(&self.stereo.right, &right_from_left),
            left_from_right: right_from_left.inverse(),
            stereo: StereoRig { right_from_left, ..self.stereo },
            ..self
        }
    }
}

/// Largest median misfit of the predicted rig accepted as it is, in the calibration's
/// noise estimate (module docs, "rig check"). Over 713 drives of 90 robot-scene trials at
/// 3 px (a past measurement, readings with 0.01 deg of noise) the median misfit
/// was 0.63 sigma, its 99th percentile 1.5 sigma; the one trial whose rig was 1.9 deg off
/// (a vergence axis 12 deg off) had 4.4 sigma.
pub const RIG_MISFIT_SIGMAS: f64 = 2.0;
/// Smallest misfit bound, pixels: a misfit below it never troubles the drive
/// registration (threshold 4 px), and noise-free data (noise estimate near 0) would
/// otherwise test the readings' own noise.
pub const RIG_MISFIT_FLOOR_PX: f64 = 1.0;
/// Sampson gate of the relative-pose refit, in the calibration's noise estimate (floored
/// at [`RIG_MISFIT_FLOOR_PX`]): a Gaussian match exceeds 3.5 sigma with probability 5e-4.
const RIG_REFIT_SIGMAS: f64 = 3.5;

/// The stereo rig predicted at a stage's readings, checked against the stage's own
/// stereo captures (module docs, "rig check").
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RigCheck {
    /// Stereo matches (tracks seen by both cameras, over the captures) it was measured on.
    pub matches: usize,
    /// Median misfit of the predicted rig: each match triangulated from its two pixels,
    /// the larger of its two reprojection errors, pixels.
    pub misfit_px: f64,
    /// The largest median misfit accepted without correction, pixels:
    /// [`RIG_MISFIT_SIGMAS`] times the calibration's noise estimate, at least
    /// [`RIG_MISFIT_FLOOR_PX`].
    pub bound_px: f64,
    /// Rotation of the correction of `right_from_left`, degrees (0: none was needed).
    pub correction_deg: f64,
    /// Median misfit of the rig used (after the correction, if any), pixels.
    pub used_misfit_px: f64,
}

/// The stereo matches `(left, right)` pixels of `captures` (tracks seen by both cameras).
fn stereo_matches(captures: &[&StereoCapture]) -> Vec<(Point2<f64>, Point2<f64>)> {
    let mut out = Vec::new();
    for cap in captures {
        let right = by_track(&cap.right);
        out.extend(cap.left.iter().filter_map(|o| right.get(&o.track).map(|r| (o.pixel, *r))));
    }
    out
}

/// Median two-view misfit of `rig` over `matches`, pixels ([`RigCheck::misfit_px`]);
/// infinite without a usable match.
fn stereo_misfit_px(rig: &Rig, matches: &[(Point2<f64>, Point2<f64>)]) -> f64 {
    let mut e: Vec<f64> = matches
        .iter()
        .filter_map(|(l, r)| {
            let x = triangulate_linear(&rig.p_left, &rig.p_right, l, r).ok()?;
            let el = (rig.p_left.project(&x)? - l).norm();
            let er = (rig.p_right.project(&x)? - r).norm();
            Some(el.max(er))
        })
        .filter(|v| v.is_finite())
        .collect();
    if e.is_empty() {
        return f64::INFINITY;
    }
    let mid = e.len() / 2;
    *e.select_nth_unstable_by(mid, f64::total_cmp).1
}

/// Check the predicted `rig` against the stereo pairs of `captures` (module docs, "rig
/// check"): when its median misfit exceeds the bound, its relative pose is re-fitted to
/// those pairs ([`refine_relative_pose`], Sampson distances), its vertical components
/// (rotations about the right camera's x and z axes, the baseline's y component) taken
/// from the fit and the rest (rotation about y, the baseline's length and z component)
/// kept, and the correction `fitted * predicted^-1` is returned with the corrected rig.
/// `noise_px` is the calibration's noise estimate. [`AlignError::RigMisfit`] when the
/// re-fitted rig still misfits.
pub(crate) fn check_rig(
    rig: Rig,
    captures: &[&StereoCapture],
    noise_px: f64,
    readings: &Encoders,
) -> Result<(Rig, Option<Isometry3<f64>>, RigCheck), AlignError> {
    let matches = stereo_matches(captures);
    let noise = if noise_px.is_finite() { noise_px.max(0.0) } else { 0.0 };
    let bound_px = (RIG_MISFIT_SIGMAS * noise).max(RIG_MISFIT_FLOOR_PX);
    let misfit_px = stereo_misfit_px(&rig, &matches);
    let mut check = RigCheck {
        matches: matches.len(),
        misfit_px,
        bound_px,
        correction_deg: 0.0,
        used_misfit_px: misfit_px,
    };
    if misfit_px <= bound_px {
        return Ok((rig, None, check));
    }
    let predicted = rig.stereo.right_from_left;
    let length = predicted.translation.vector.norm();
    let gate = RIG_REFIT_SIGMAS * noise.max(RIG_MISFIT_FLOOR_PX);
    let refit = refine_relative_pose(&rig.stereo.left, &rig.stereo.right, &predicted, &matches, gate);
    let misfit_err =
        |used: f64| AlignError::RigMisfit { readings: *readings, misfit_px, bound_px, refit_px: used };
    let Some((fitted, _)) = refit else { return Err(misfit_err(f64::INFINITY)) };
    // Only the vertical components are taken from the re-fit: the rotations about the
    // right camera's x and z axes and the baseline's y component, which the pairs'
    // vertical disparities determine. The rotation about y and the baseline's z
    // component change the horizontal disparities, which the points' depths absorb: a
    // single pair leaves them weakly determined (a rig tilted 1.5 deg about x, re-fitted
    // in all five, came back 0.36 deg off about y), so they stay as predicted.
    let w = (fitted.rotation * predicted.rotation.inverse()).scaled_axis();
    let rotation = UnitQuaternion::from_scaled_axis(Vector3::new(w.x, 0.0, w.z)) * predicted.rotation;
    let (tp, tf) = (predicted.translation.vector, fitted.translation.vector);
    let t = Vector3::new(tp.x, tf.y * length / tf.norm(), tp.z);
    let fitted = Isometry3::from_parts(Translation3::from(t * (length / t.norm())), rotation);
    let correction = fitted * predicted.inverse();
    let corrected = rig.corrected(Some(&correction));
    let used = stereo_misfit_px(&corrected, &matches);
    // `used` is finite or infinite (no usable match), never NaN.
    if used > bound_px {
        return Err(misfit_err(used));
    }
    check.correction_deg = correction.rotation.angle().to_degrees();
    check.used_misfit_px = used;
    Ok((corrected, Some(correction), check))
}

/// The calibrated stereo rig predicted at readings `enc` (both `K`s and
/// `right_from_left`, the vergence axes moving the cameras from the reference readings),
/// and the covariance (6x6) of that prediction's `right_from_left` in the left
/// perturbation of [`perturb`] (rotation first, radians; translation in baselines),
/// propagated from the calibration and, given `axes`, the vergence axes' uncertainty
/// (`calibration_covariance`, module docs), the readings taken as exact. The covariance is
/// `None` if the propagation failed.
///
/// [`perturb`]: headalign_geometry::rigmotion::perturb
pub fn predicted_rig(
    calib: &RigCalibration,
    verge: &VergeAxes,
    axes: Option<&AxisPerturbations>,
    enc: &Encoders,
) -> Result<(StereoRig, Option<Matrix6<f64>>), AlignError> {
    let rig = rig_at(calib, verge, enc)?.stereo;
    let nominal = rig.right_from_left;
    let cov = calibration_covariance(calib, verge, axes, &Readings::exact(*enc), |cp, va, e| {
        let p = rig_at(cp, va, e).ok()?.stereo.right_from_left;
        // Left perturbation: p = exp(d) nominal.
        let d = p * nominal.inverse();
        let w = d.rotation.scaled_axis();
        Some(Vector6::new(w.x, w.y, w.z, d.translation.x, d.translation.y, d.translation.z))
    });
    Ok((rig, cov))
}

/// The fundamental matrix `F` (`x_right^T F x_left = 0`, pixels) of the calibrated stereo
/// rig at readings `enc`: `K_r^-T [t]x R K_l^-1` with `(R, t)` = `right_from_left`
/// predicted by the calibrated kinematics (vergence axes included). The image front end
/// uses it to guide stereo matching where free matching fails (near, wide-disparity
/// scenes: [`crate::tracking::TrackingHead::with_stereo_prior`]).
pub fn stereo_fundamental(
    calib: &RigCalibration,
    verge: &VergeAxes,
    enc: &Encoders,
) -> Result<Matrix3<f64>, AlignError> {
    let rig = rig_at(calib, verge, enc)?;
    let right_from_left = rig.stereo.right_from_left;
    let t = right_from_left.translation.vector;
    let r = right_from_left.rotation.to_rotation_matrix().into_inner();
    let e = t.cross_matrix() * r;
    Ok(rig.stereo.right.inverse_matrix().transpose() * e * rig.stereo.left.inverse_matrix())
}

/// Each observation's pixel by track id.
pub(super) fn by_track(obs: &[headalign_platform::TrackObservation]) -> HashMap<u64, Point2<f64>> {
    obs.iter().map(|o| (o.track, o.pixel)).collect()
}
