//! The check after the move, for the planar route ([`super`] module docs): each camera's
//! orientation at the aligned readings measured from its image of the plane, and the
//! alignment errors that orientation leaves against the camera's own estimated axes.
//!
//! The general route resects the cameras against the calibrated 3D points
//! ([`crate::alignment::measure_cameras`]); a plane gives no such points, but each camera's
//! view of it after the move is related to its reference view by the plane's homography
//! `K (R + t m^T) K^-1` (Hartley & Zisserman result 13.1). The translation `t` comes from
//! rotating about lines that miss the camera centre; a free homography cannot tell it from
//! rotation (a wall 1 m away and an axis 0.1 m off the centre turn 8 deg of elevation into
//! up to 0.8 deg of apparent extra rotation), so the check takes the pose the camera's
//! planar model predicts at the reached readings (its joint lines and plane `m`, in the
//! model's scale gauge: only `t m^T` enters, and that is gauge-free) and measures a
//! rotation `delta` about the camera centre on top of it: `ref_from_cam = G(readings)
//! Rot(delta)`, 3 dof, fitted to the tracks the check view shares with the reference view
//! (least squares on pixel residuals by the project's Levenberg-Marquardt,
//! `headalign_geometry::lm`, numeric Jacobian; matches beyond
//! [`CHECK_SIGMAS`] robust sigmas of the prediction, then of each fit, dropped:
//! [`REFITS`] rounds). The measured optical axis
//! `z = R e3` then gives, as [`crate::alignment::measured_errors`] does: the vergence error
//! `asin(z . a_e)` (the elevation axis turned by the pan difference) and the elevation
//! error `asin(z . a_p)`, degrees.
//!
//! Its own precision ([`PlanarCheck::sigma`], for the verdict of
//! [`crate::procedure::check_verdict`]): `rms_px / (f sqrt(n))` radians per camera, the
//! rotation about the centre fitted to `n` tracks of residual `rms_px`.
//!
//! What it measures: whatever moved the camera other than the model says (a joint that
//! did not reach its reading, a wrong vergence axis, a camera loose on its mount) shows
//! in `delta` and in the errors. What it cannot check ([`UNCHECKED`]): errors of the
//! estimated pan and elevation axes themselves (each camera is measured against its own
//! estimated axes, as the general route's check is), and the right camera's elevation
//! relative to the left's, which no joint removes. Pitfall: the reference view's pixels
//! stand for the points (no refined positions), so their noise enters once more; with
//! hundreds of tracks that costs a few thousandths of a degree.

use headalign_geometry::lm;
use headalign_geometry::so3::{exp, rotation_about_line};
use headalign_platform::{Encoders, StereoCapture};
use nalgebra::{Isometry3, Matrix3, Point2, Rotation3, Vector3};
use serde::Serialize;

use super::{CameraPlanar, PlanarCalibration};
use crate::alignment::MeasuredErrors;
use crate::error::AlignError;

/// Matches farther than this many robust sigmas (1.4826 MAD of the residual norms, at
/// least [`MIN_CHECK_SIGMA_PX`]) from the first fit are dropped: a wrong track, or a point
/// off the plane (4 sigmas: a Gaussian residual lies beyond with probability `exp(-8)`).
pub const CHECK_SIGMAS: f64 = 4.0;

/// Floor of the check's robust sigma, pixels (noise-free data).
pub const MIN_CHECK_SIGMA_PX: f64 = 0.1;

/// Selections and fits of the check's rotation (module docs): the first at the model's
/// prediction, each later one at the previous fit.
pub const REFITS: usize = 3;

/// Fewest shared tracks a camera's check needs (3 dof; many more keep noise down).
pub const MIN_CHECK_TRACKS: usize = 12;

/// What the planar check cannot check (module docs), reported by name.
pub const UNCHECKED: [&str; 2] = [
    "errors of the estimated pan and elevation axes themselves (each camera is measured against its own estimated axes)",
    "the right camera's elevation relative to the left camera's (no joint removes it)",
];

/// One camera's part of the check.
#[derive(Debug, Clone, Serialize)]
pub struct CameraCheck {
    /// Tracks shared with the reference view and kept.
    pub tracks: usize,
    /// RMS pixel residual of the fit.
    pub rms_px: f64,
    /// Rotation of the camera beyond the model's prediction at the reached readings,
    /// degrees (the size of `delta`, module docs).
    pub unmodelled_rotation_deg: f64,
}

/// The check after moving to the planar route's aligned readings.
#[derive(Debug, Clone, Serialize)]
pub struct PlanarCheck {
    /// Readings of the check view.
    pub encoders: Encoders,
    /// The alignment errors measured (each camera against its own axes).
    pub measured: MeasuredErrors,
    /// The check's own 1-sigma of each measured error, degrees: `rms_px / (f sqrt(n))`
    /// radians per camera (a rotation about the centre fitted to `n` tracks of residual
    /// `rms_px`, `f` the mean focal length), the same for both of its components
    /// ([`crate::procedure::check_verdict`]).
    pub sigma: MeasuredErrors,
    /// Left camera's fit.
    pub left: CameraCheck,
    /// Right camera's fit.
    pub right: CameraCheck,
    /// What this check cannot check, by name.
    pub unchecked: Vec<String>,
}

/// The 1-sigma of a camera's fitted rotation about its centre, degrees: `rms_px / (f
/// sqrt(n))` radians (each of `n` tracks fixes the rotation about an axis across the view
/// to one coordinate's noise over the focal length).
fn fit_sigma(fit: &CameraCheck, camera: &CameraPlanar) -> f64 {
    let f = 0.5 * (camera.intrinsics.fx + camera.intrinsics.fy);
    (fit.rms_px / (f.max(1e-9) * (fit.tracks.max(1) as f64).sqrt())).to_degrees()
}

/// Check the capture `check` (after the move) against the reference view's capture
/// `reference` (module docs).
pub fn check_alignment(
    calibration: &PlanarCalibration,
    reference: &StereoCapture,
    check: &StereoCapture,
) -> Result<PlanarCheck, AlignError> {
    let e0 = &calibration.reference_encoders;
    let (zl, left) = camera_check(&calibration.left, &reference.left, &check.left, e0, &check.encoders)?;
    let (zr, right) = camera_check(&calibration.right, &reference.right, &check.right, e0, &check.encoders)?;
    let d_pan = (check.encoders.pan - e0.pan).to_radians();
    let ang = |z: &Vector3<f64>, a: &Vector3<f64>| z.dot(a).clamp(-1.0, 1.0).asin().to_degrees();
    let axes = |c: &CameraPlanar| {
        let a_p = Vector3::from(c.pan).normalize();
        let a_e = Rotation3::new(a_p * d_pan) * Vector3::from(c.elevation).normalize();
        (a_p, a_e)
    };
    let ((pl, el), (pr, er)) = (axes(&calibration.left), axes(&calibration.right));
    Ok(PlanarCheck {
        encoders: check.encoders,
        measured: MeasuredErrors {
            verge_err_l_deg: ang(&zl, &el),
            verge_err_r_deg: ang(&zr, &er),
            elev_err_l_deg: ang(&zl, &pl),
            elev_err_r_deg: ang(&zr, &pr),
        },
        sigma: MeasuredErrors {
            verge_err_l_deg: fit_sigma(&left, &calibration.left),
            verge_err_r_deg: fit_sigma(&right, &calibration.right),
            elev_err_l_deg: fit_sigma(&left, &calibration.left),
            elev_err_r_deg: fit_sigma(&right, &calibration.right),
        },
        left,
        right,
        unchecked: UNCHECKED.iter().map(|s| s.to_string()).collect(),
    })
}

/// The model's `ref_from_cam` of camera `c` at readings `enc` (reference readings `e0`).
fn predicted_pose(c: &CameraPlanar, e0: &Encoders, enc: &Encoders) -> Isometry3<f64> {
    c.joint_lines.iter().fold(Isometry3::identity(), |acc, (joint, line)| {
        acc * rotation_about_line(line, (enc.get(*joint) - e0.get(*joint)).to_radians())
    })
}

/// One camera: its measured optical axis (reference camera frame) and the fit's numbers.
fn camera_check(
    c: &CameraPlanar,
    reference: &[headalign_platform::TrackObservation],
    check: &[headalign_platform::TrackObservation],
    e0: &Encoders,
    enc: &Encoders,
) -> Result<(Vector3<f64>, CameraCheck), AlignError> {
    let side = if c.side == headalign_geometry::bundle::Side::Left { "left" } else { "right" };
    let pose = predicted_pose(c, e0, enc);
    let k = c.intrinsics;
    let (km, k_inv) = (k.matrix(), k.inverse_matrix());
    let m = Vector3::from(c.plane_m);
    let by_track: std::collections::HashMap<u64, Point2<f64>> =
        reference.iter().map(|o| (o.track, o.pixel)).collect();
    // Each shared track: the plane point seen from the predicted pose (homogeneous, so a
    // far plane needs no division), and the observed pixel.
    let r_inv = pose.rotation.inverse();
    let data: Vec<(Vector3<f64>, Point2<f64>)> = check
        .iter()
        .filter_map(|o| {
            let p = by_track.get(&o.track)?;
            let r = k_inv * Vector3::new(p.x, p.y, 1.0);
            Some((r_inv * (r - pose.translation.vector * m.dot(&r)), o.pixel))
        })
        .collect();
    let too_few = |n: usize| {
        AlignError::Observations(format!(
            "planar check: the {side} camera's check view shares {n} tracks with the reference view, need {MIN_CHECK_TRACKS}"
        ))
    };
    if data.len() < MIN_CHECK_TRACKS {
        return Err(too_few(data.len()));
    }
    // Select at the model's prediction (delta = 0, close: a wrong match is hundreds of
    // pixels off, an unmodelled turn of 0.1 deg about 1.5 px), fit, and select again at the
    // fit, from every shared track each time (a least-squares first fit through 10 %
    // random matches is pulled far enough to keep some of them).
    let mut delta = Vector3::zeros();
    let mut kept: Vec<(Vector3<f64>, Point2<f64>)> = Vec::new();
    for _ in 0..REFITS {
        let norms: Vec<f64> = data.iter().map(|(q, px)| residual(&km, &delta, q, px).norm()).collect();
        let mut sorted = norms.clone();
        sorted.sort_by(f64::total_cmp);
        let sigma = (1.4826 * sorted[sorted.len() / 2]).max(MIN_CHECK_SIGMA_PX);
        kept =
            data.iter().zip(&norms).filter(|(_, n)| **n <= CHECK_SIGMAS * sigma).map(|(d, _)| *d).collect();
        if kept.len() < MIN_CHECK_TRACKS {
            return Err(too_few(kept.len()));
        }
        delta = fit_rotation(&kept, &km, delta);
    }
    let norms: Vec<f64> = kept.iter().map(|(q, px)| residual(&km, &delta, q, px).norm()).collect();
    let rms_px = (norms.iter().map(|n| n * n).sum::<f64>() / (2 * norms.len()) as f64).sqrt();
    let z = pose.rotation * (exp(&delta) * Vector3::z());
    Ok((z, CameraCheck { tracks: kept.len(), rms_px, unmodelled_rotation_deg: delta.norm().to_degrees() }))
}

/// Pixel residual of point `q` (predicted camera frame) under the extra rotation `delta`.
fn residual(
    km: &Matrix3<f64>,
    delta: &Vector3<f64>,
    q: &Vector3<f64>,
    px: &Point2<f64>,
) -> nalgebra::Vector2<f64> {
    let w = km * (exp(delta).inverse() * q);
    if w.z.abs() < 1e-12 {
        return nalgebra::Vector2::new(1e6, 1e6);
    }
    nalgebra::Vector2::new(w.x / w.z - px.x, w.y / w.z - px.y)
}

/// Most iterations of [`fit_rotation`] (it stops at the cost's rounding level long
/// before: a 3-dof fit from a start within a degree).
const FIT_ITERATIONS: usize = 50;

/// The least-squares `delta` (3 dof) from `start` by [`lm::minimise_with`] (the project's
/// Levenberg-Marquardt with the dense back end) until no step lowers the cost, numeric
/// Jacobian (central differences at 1e-7 rad).
fn fit_rotation(
    data: &[(Vector3<f64>, Point2<f64>)],
    km: &Matrix3<f64>,
    start: Vector3<f64>,
) -> Vector3<f64> {
    let cost = |delta: &Vector3<f64>| {
        data.iter().map(|(q, px)| residual(km, delta, q, px).norm_squared()).sum::<f64>()
    };
    let normal = |delta: &Vector3<f64>| {
        let mut jtj = Matrix3::zeros();
        let mut jtr = Vector3::zeros();
        for (q, px) in data {
            let r = residual(km, delta, q, px);
            let mut j = nalgebra::Matrix2x3::zeros();
            for c in 0..3 {
                let mut e = Vector3::zeros();
                e[c] = 1e-7;
                let d = (residual(km, &(delta + e), q, px) - residual(km, &(delta - e), q, px)) / 2e-7;
                j.set_column(c, &d);
            }
            jtj += j.transpose() * j;
            jtr += j.transpose() * r;
        }
        Some((jtj, jtr))
    };
    // To rounding (no function tolerance), as a Gauss-Newton run to convergence.
    let options =
        lm::LmOptions { max_iterations: FIT_ITERATIONS, function_tolerance: 0.0, parameter_tolerance: 0.0 };
    lm::minimise_with(start, cost(&start), &options, normal, |d, step| Some(d + step), cost).0
}
