//! The rigid motion of one drive ([`super`] module docs, "rigid motion of a drive"),
//! `cam2_from_cam1` (6 dof; rotation in radians, translation in stereo baselines), from
//! the stereo captures before and after it under the rig predicted at the readings.
//!
//! Triangulate before and after (linear, points in front of the left camera); RANSAC over
//! 3-point rigid fits (Umeyama) of `Y = R X + t`, each track scored by the largest of its
//! four reprojection errors (pixels, threshold of the registration options) after its
//! linear triangulation from all four views under the model; the maximum-likelihood
//! motion (motion and points on the reprojection error in all four images, Huber loss,
//! covariance) and a guided re-selection with it (twice); then a least-squares pass on the
//! tracks within [`ML_GATE_SIGMAS`] robust sigmas (floor [`ML_GATE_FLOOR_PX`]), when at
//! least [`MIN_ML_TRACKS`] remain. Hartley & Zisserman 2nd ed., sections 4.7 and 18.1;
//! paper section 4.
//!
//! Pitfalls: the Huber loss bounds a wrong track's influence but does not remove it (a
//! wrong track within the RANSAC threshold biased even noise-free drives, 0.006 deg of
//! pan on demo seed 1), hence the final least-squares pass; a track whose point ends
//! behind a camera or at infinity is dropped and the fit redone rather than failing the
//! drive.

use std::collections::HashMap;

use headalign_geometry::camera::dehomogenise3;
use headalign_geometry::ransac::{Estimator, RansacOptions, ransac};
use headalign_geometry::registration::similarity_fit;
use headalign_geometry::rigmotion::{
    RigMotionEstimate, RigMotionOptions, RigTrack, StereoRig, consistent_tracks, four_cameras,
    refine_rig_motion_dropping, track_error, track_residuals,
};
use headalign_geometry::triangulation::triangulate_linear;
use headalign_platform::StereoCapture;
use nalgebra::{Isometry3, Point3};

use super::rig::{Rig, by_track};
use crate::error::{AlignError, StepContext};

/// The stereo matches of `cap` triangulated (linear) under `rig`, by track; only points
/// in front of the left camera.
fn triangulate(rig: &Rig, cap: &StereoCapture) -> HashMap<u64, Point3<f64>> {
    let right = by_track(&cap.right);
    cap.left
        .iter()
        .filter_map(|o| {
            let r = right.get(&o.track)?;
            let x = triangulate_linear(&rig.p_left, &rig.p_right, &o.pixel, r).ok()?;
            let p = dehomogenise3(&x)?;
            (p.z > 0.0).then_some((o.track, p))
        })
        .collect()
}

/// Datum of the drive registration: a point before, its pixels after.
#[derive(Debug, Clone, Copy)]
struct Moved {
    before: Point3<f64>,
    after: Point3<f64>,
    /// Pixels left/right before, left/right after.
    pixels: RigTrack,
}

struct DriveEstimator<'a> {
    rig: &'a Rig,
}

impl DriveEstimator<'_> {
    fn fit(&self, data: &[Moved], idx: &[usize]) -> Option<Isometry3<f64>> {
        let xs: Vec<_> = idx.iter().filter_map(|&i| data.get(i).map(|d| d.before)).collect();
        let ys: Vec<_> = idx.iter().filter_map(|&i| data.get(i).map(|d| d.after)).collect();
        similarity_fit(&xs, &ys, false).ok().map(|s| s.isometry)
    }
}

impl Estimator for DriveEstimator<'_> {
    type Datum = Moved;
    type Model = Isometry3<f64>;
    fn sample_size(&self) -> usize {
        3
    }
    fn fit_minimal(&self, data: &[Moved], sample: &[usize]) -> Vec<Isometry3<f64>> {
        self.fit(data, sample).into_iter().collect()
    }
    fn fit_inliers(&self, data: &[Moved], inliers: &[usize]) -> Option<Isometry3<f64>> {
        self.fit(data, inliers)
    }
    fn residual(&self, m: &Isometry3<f64>, d: &Moved) -> f64 {
        let cams = four_cameras(&self.rig.stereo, m);
        track_error(&self.rig.stereo, m, &cams, &d.pixels).map_or(f64::INFINITY, |(_, e)| e)
    }
}

/// The measured rigid motion of one drive.
#[derive(Clone)]
pub(crate) struct DriveMotion {
    pub(crate) cam2_from_cam1: Isometry3<f64>,
    pub(super) before: HashMap<u64, Point3<f64>>,
    pub(crate) inliers: usize,
    /// The maximum-likelihood refinement (covariance of the centre's displacement).
    pub(super) ml: RigMotionEstimate,
    /// The tracks of that refinement (same order as `ml.points`).
    pub(super) tracks: Vec<RigTrack>,
}

pub(crate) fn drive_motion(
    rig: &Rig,
    before: &StereoCapture,
    after: &StereoCapture,
    options: &RansacOptions,
) -> Result<DriveMotion, AlignError> {
    let xb = triangulate(rig, before);
    let xa = triangulate(rig, after);
    let (la, ra) = (by_track(&after.left), by_track(&after.right));
    let (lb, rb) = (by_track(&before.left), by_track(&before.right));
    let mut data = Vec::new();
    let mut tracks: Vec<&u64> = xb.keys().collect();
    tracks.sort_unstable();
    for t in tracks {
        if let (Some(b), Some(a), Some(l), Some(r), Some(bl), Some(br)) =
            (xb.get(t), xa.get(t), la.get(t), ra.get(t), lb.get(t), rb.get(t))
        {
            data.push(Moved { before: *b, after: *a, pixels: [*bl, *br, *l, *r] });
        }
    }
    let est = DriveEstimator { rig };
    let rep = ransac(&est, &data, options).step("drive registration")?;
    let obs: Vec<RigTrack> = rep.inliers.iter().map(|&i| data[i].pixels).collect();
    let pts: Vec<Point3<f64>> = rep.inliers.iter().map(|&i| data[i].before).collect();
    // Every refinement leaves out a track whose point ends behind a camera or at infinity
    // (an outlier the gates let through) and re-fits, rather than failing the drive.
    let (mut ml, mut obs) =
        refine_dropping(rig, &obs, &rep.model, &pts, &RigMotionOptions::default()).step("drive motion")?;
    let all: Vec<RigTrack> = data.iter().map(|d| d.pixels).collect();
    let mut n = obs.len();
    // Guided re-selection: the refined motion is far better than the 3-point RANSAC
    // model that chose the inliers (whose threshold must allow for its depth noise).
    for _ in 0..2 {
        let kept = consistent_tracks(&rig.stereo, &ml.cam2_from_cam1, &all, options.threshold);
        if kept.len() < n {
            break;
        }
        let o: Vec<RigTrack> = kept.iter().map(|(i, _)| all[*i]).collect();
        let pts: Vec<Point3<f64>> = kept.iter().map(|(_, x)| *x).collect();
        (ml, obs) = refine_dropping(rig, &o, &ml.cam2_from_cam1, &pts, &RigMotionOptions::default())
            .step("drive motion")?;
        n = obs.len();
    }
    // Maximum-likelihood pass (as the verge/tilt estimator's): the Huber loss bounds an
    // outlier's influence but does not remove it, and a wrong track within the RANSAC
    // threshold biased even noise-free drives (0.006 deg of pan, seed 1). The noise is
    // estimated robustly from the median residual, tracks within `ML_GATE_SIGMAS` of it
    // are kept, and plain least squares gives the estimate and its covariance.
    let sigma = robust_sigma_px(&rig.stereo, &ml, &obs).max(ML_GATE_FLOOR_PX);
    let kept = consistent_tracks(&rig.stereo, &ml.cam2_from_cam1, &all, ML_GATE_SIGMAS * sigma);
    if kept.len() >= MIN_ML_TRACKS {
        let o: Vec<RigTrack> = kept.iter().map(|(i, _)| all[*i]).collect();
        let pts: Vec<Point3<f64>> = kept.iter().map(|(_, x)| *x).collect();
        let ls = RigMotionOptions { huber_px: LEAST_SQUARES_HUBER_PX, ..RigMotionOptions::default() };
        (ml, obs) =
            refine_dropping(rig, &o, &ml.cam2_from_cam1, &pts, &ls).step("drive motion (least squares)")?;
        n = obs.len();
    }
    Ok(DriveMotion { cam2_from_cam1: ml.cam2_from_cam1, before: xb, inliers: n, ml, tracks: obs })
}

/// [`refine_rig_motion_dropping`] on `rig`: the estimate and the tracks it kept (same
/// order as its points).
fn refine_dropping(
    rig: &Rig,
    obs: &[RigTrack],
    start: &Isometry3<f64>,
    pts: &[Point3<f64>],
    options: &RigMotionOptions,
) -> Result<(RigMotionEstimate, Vec<RigTrack>), headalign_geometry::GeometryError> {
    let (ml, kept) = refine_rig_motion_dropping(&rig.stereo, obs, start, pts, options)?;
    Ok((ml, kept.iter().map(|&i| obs[i]).collect()))
}

/// Gate of the maximum-likelihood pass, in robust standard deviations of one pixel
/// coordinate: a track is kept when its largest 2D residual is within this (a Gaussian
/// 2D residual exceeds 3.5 sigma with probability 0.2 %, like the verge/tilt estimator's
/// `reselect_sigmas`).
const ML_GATE_SIGMAS: f64 = 3.5;
/// Smallest noise the gate assumes, pixels (noise-free data: keeps the gate above
/// rounding, far below any wrong track).
const ML_GATE_FLOOR_PX: f64 = 0.01;
/// Fewest tracks for the least-squares pass (else the Huber estimate stands).
const MIN_ML_TRACKS: usize = 8;
/// A Huber threshold far beyond any residual: plain least squares.
pub(super) const LEAST_SQUARES_HUBER_PX: f64 = 1e9;

/// Robust noise of a rig motion fit, pixels per coordinate: the median 2D residual norm
/// over the four images of every track, divided by `sqrt(2 ln 2)` (the median of a
/// Rayleigh variable), so outliers still in the fit do not inflate it.
fn robust_sigma_px(rig: &StereoRig, ml: &RigMotionEstimate, obs: &[RigTrack]) -> f64 {
    let mut norms: Vec<f64> = Vec::new();
    for (x, o) in ml.points.iter().zip(obs) {
        if let Some(r) = track_residuals(rig, &ml.cam2_from_cam1, x, o) {
            norms.extend((0..4).map(|j| r[2 * j].hypot(r[2 * j + 1])));
        }
    }
    if norms.is_empty() {
        return f64::INFINITY;
    }
    norms.sort_by(f64::total_cmp);
    norms[norms.len() / 2] / (2.0 * std::f64::consts::LN_2).sqrt()
}
