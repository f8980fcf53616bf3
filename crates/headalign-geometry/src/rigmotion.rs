//! Rigid motion of a calibrated stereo rig between two stereo views, by maximum
//! likelihood (a small bundle adjustment; Hartley & Zisserman 2nd ed. section 18.1 and
//! appendix A6.3 for the Schur complement). Paper section 4 (the "3D motion of the
//! reconstruction") and section 7 (screw axes of robot motions).
//!
//! What it computes: the motion `cam2_from_cam1 = (R, t)` of the left camera (6 degrees
//! of freedom; the rig's own `right_from_left` and both `K`s are known and fixed, so the
//! scale is that of the rig's baseline) and every track's 3D point `X` (3 each, first
//! left camera frame), minimising the reprojection error of each track in the four
//! images: left and right before (`X`), left and right after (`R X + t`). Residuals are
//! pixels, with a Huber loss (threshold `huber_px`) by iteratively reweighted least
//! squares.
//!
//! Parametrisation: a left-multiplied perturbation, `exp(dw, dt) (R, t) = (R_dw R,
//! R_dw t + dt)`, rotation part first; analytic Jacobians (checked against central
//! differences in the tests). The project's Levenberg-Marquardt ([`crate::lm`]: its
//! damping policy, a relative function tolerance of 1e-12, at most `max_iterations`) with
//! the bundle adjustment's point-Schur back end: a 6x6 reduced system per iteration, then
//! each point's 3x3 back substitution.
//!
//! Covariance: `sigma^2 S^-1` of `(dw, dt)` at the optimum (`S` the undamped reduced
//! normal matrix, `sigma^2` the weighted residual variance with `n_obs - 6 - 3 n_pts`
//! degrees of freedom). The displacement of the camera centre, `c = -R^T t` (first
//! frame), has covariance `R^T C_tt R`, since `dc = -R^T dt` (the rotation part drops
//! out to first order).
//!
//! Why not the 3D registration of triangulated points alone: stereo depth errors grow
//! with the square of the depth, and a registration of the two noisy reconstructions
//! confuses a small turn with a sideways translation (both shift the image); this
//! estimator weighs every pixel by what it measures, so a turn and a sideways move are
//! separated by the parallax between near and far points.
//!
//! Pitfalls: needs a starting motion and points (e.g. 3-point RANSAC on triangulated
//! points); points far away constrain only the rotation; a step that would put a point
//! behind a camera is rejected (infinite cost). A point unusable at the optimum (so far
//! away that its 3x3 normal block is singular: a point that crept outwards) fails
//! [`refine_rig_motion`]; [`refine_rig_motion_dropping`] leaves such a track out as an
//! outlier and re-fits the rest (a 3 px robot drive failed this way on one tree).

use nalgebra::{
    DMatrix, DVector, Isometry3, Matrix3, Matrix6, Point2, Point3, SMatrix, Translation3, UnitQuaternion,
    Vector3, Vector6,
};

use crate::bundle::Normal;
use crate::camera::{Intrinsics, ProjectiveCamera, dehomogenise3};
use crate::triangulation::triangulate_views;
use crate::{GeometryError, Result, lm};

/// A calibrated stereo rig: both intrinsics and the right camera's pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StereoRig {
    /// Left camera intrinsics.
    pub left: Intrinsics,
    /// Right camera intrinsics.
    pub right: Intrinsics,
    /// `right_from_left`: maps points from the left camera frame to the right one.
    pub right_from_left: Isometry3<f64>,
}

/// One track seen in both cameras before and after the motion: pixels
/// `[left_before, right_before, left_after, right_after]`.
pub type RigTrack = [Point2<f64>; 4];

/// Options of [`refine_rig_motion`].
#[derive(Debug, Clone, PartialEq)]
pub struct RigMotionOptions {
    /// Huber threshold on each image residual's length, pixels. Default 2 (2 sigma at 1
    /// px noise: full weight for inliers, bounded influence for the rest).
    pub huber_px: f64,
    /// Iteration limit. Default 30.
    pub max_iterations: usize,
}

impl Default for RigMotionOptions {
    fn default() -> Self {
        Self { huber_px: 2.0, max_iterations: 30 }
    }
}

impl RigMotionOptions {
    /// Check the options.
    pub fn validate(&self) -> Result<()> {
        if !(self.huber_px.is_finite() && self.huber_px > 0.0) || self.max_iterations == 0 {
            return Err(GeometryError::InvalidOption(format!(
                "huber_px must be positive and max_iterations >= 1, got {} {}",
                self.huber_px, self.max_iterations
            )));
        }
        Ok(())
    }
}

/// Result of [`refine_rig_motion`].
#[derive(Debug, Clone, PartialEq)]
pub struct RigMotionEstimate {
    /// Motion of the left camera: maps first-frame points into the second frame.
    pub cam2_from_cam1: Isometry3<f64>,
    /// Covariance of the perturbation `(dw, dt)` (module docs), rotation first.
    pub covariance: Matrix6<f64>,
    /// Displacement of the left camera centre, first frame: `-R^T t`.
    pub centre_displacement: Vector3<f64>,
    /// Its covariance.
    pub centre_covariance: Matrix3<f64>,
    /// The refined points, first left camera frame.
    pub points: Vec<Point3<f64>>,
    /// RMS image residual at the optimum, pixels.
    pub rms_px: f64,
    /// Estimated noise (weighted residual standard deviation), pixels.
    pub sigma_px: f64,
    /// Iterations run.
    pub iterations: usize,
}

/// Pixel Jacobian `d(u, v) / d(point)` of a point in a camera frame.
fn projection_jacobian(k: &Intrinsics, p: &Vector3<f64>) -> SMatrix<f64, 2, 3> {
    let iz = 1.0 / p.z;
    let iz2 = iz * iz;
    SMatrix::<f64, 2, 3>::new(
        k.fx * iz,
        k.skew * iz,
        -(k.fx * p.x + k.skew * p.y) * iz2,
        0.0,
        k.fy * iz,
        -k.fy * p.y * iz2,
    )
}

fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// The four points in their camera frames: left before, right before, left after, right
/// after.
fn in_cameras(rig: &StereoRig, m: &Isometry3<f64>, x: &Point3<f64>) -> [Vector3<f64>; 4] {
    let y = m * x;
    [x.coords, (rig.right_from_left * x).coords, y.coords, (rig.right_from_left * y).coords]
}

/// Residuals (predicted minus observed pixels, 8 values) of one track; `None` when the
/// point is behind a camera.
pub fn track_residuals(
    rig: &StereoRig,
    m: &Isometry3<f64>,
    x: &Point3<f64>,
    obs: &RigTrack,
) -> Option<[f64; 8]> {
    let ps = in_cameras(rig, m, x);
    let ks = [&rig.left, &rig.right, &rig.left, &rig.right];
    let mut r = [0.0; 8];
    for i in 0..4 {
        let px = ks[i].project(&Point3::from(ps[i]))?;
        r[2 * i] = px.x - obs[i].x;
        r[2 * i + 1] = px.y - obs[i].y;
    }
    Some(r)
}

/// Jacobians of [`track_residuals`]: with respect to the motion perturbation (8x6) and
/// the point (8x3).
pub fn track_jacobians(
    rig: &StereoRig,
    m: &Isometry3<f64>,
    x: &Point3<f64>,
) -> Option<(SMatrix<f64, 8, 6>, SMatrix<f64, 8, 3>)> {
    let ps = in_cameras(rig, m, x);
    if ps.iter().any(|p| p.z <= 0.0) {
        return None;
    }
    let r_rl = rig.right_from_left.rotation.to_rotation_matrix().into_inner();
    let r_m = m.rotation.to_rotation_matrix().into_inner();
    let y = ps[2];
    let mut dy_dm = SMatrix::<f64, 3, 6>::zeros();
    dy_dm.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-skew(&y)));
    dy_dm.fixed_view_mut::<3, 3>(0, 3).copy_from(&Matrix3::identity());
    let mut jm = SMatrix::<f64, 8, 6>::zeros();
    let mut jx = SMatrix::<f64, 8, 3>::zeros();
    let j0 = projection_jacobian(&rig.left, &ps[0]);
    let j1 = projection_jacobian(&rig.right, &ps[1]) * r_rl;
    let j2 = projection_jacobian(&rig.left, &ps[2]);
    let j3 = projection_jacobian(&rig.right, &ps[3]) * r_rl;
    jx.fixed_view_mut::<2, 3>(0, 0).copy_from(&j0);
    jx.fixed_view_mut::<2, 3>(2, 0).copy_from(&j1);
    jx.fixed_view_mut::<2, 3>(4, 0).copy_from(&(j2 * r_m));
    jx.fixed_view_mut::<2, 3>(6, 0).copy_from(&(j3 * r_m));
    jm.fixed_view_mut::<2, 6>(4, 0).copy_from(&(j2 * dy_dm));
    jm.fixed_view_mut::<2, 6>(6, 0).copy_from(&(j3 * dy_dm));
    Some((jm, jx))
}

/// Apply a perturbation `(dw, dt)` on the left.
pub fn perturb(m: &Isometry3<f64>, d: &Vector6<f64>) -> Isometry3<f64> {
    let dr = UnitQuaternion::from_scaled_axis(Vector3::new(d[0], d[1], d[2]));
    Isometry3::from_parts(Translation3::new(d[3], d[4], d[5]), dr) * m
}

/// Tracks consistent with a motion: each track triangulated from its four views (linear,
/// [`triangulate_views`]) and kept when its largest image residual is at most
/// `threshold_px`; returns `(index, point)` pairs (guided re-selection after a
/// refinement, when the motion is better than the RANSAC model that chose the first
/// inliers).
pub fn consistent_tracks(
    rig: &StereoRig,
    m: &Isometry3<f64>,
    obs: &[RigTrack],
    threshold_px: f64,
) -> Vec<(usize, Point3<f64>)> {
    let cams = four_cameras(rig, m);
    obs.iter()
        .enumerate()
        .filter_map(|(i, o)| {
            let (x, worst) = track_error(rig, m, &cams, o)?;
            (worst <= threshold_px).then_some((i, x))
        })
        .collect()
}

/// The four cameras of a motion: left and right before, left and right after (first
/// left camera frame).
pub fn four_cameras(rig: &StereoRig, m: &Isometry3<f64>) -> [ProjectiveCamera; 4] {
    [
        ProjectiveCamera::from_pose(&rig.left, &Isometry3::identity()),
        ProjectiveCamera::from_pose(&rig.right, &rig.right_from_left),
        ProjectiveCamera::from_pose(&rig.left, m),
        ProjectiveCamera::from_pose(&rig.right, &(rig.right_from_left * m)),
    ]
}

/// A track's point triangulated linearly from its four views under motion `m` (cameras
/// from [`four_cameras`]) and its largest image residual, pixels (a RANSAC score that
/// does not trust either stereo pair's depth alone).
pub fn track_error(
    rig: &StereoRig,
    m: &Isometry3<f64>,
    cams: &[ProjectiveCamera; 4],
    obs: &RigTrack,
) -> Option<(Point3<f64>, f64)> {
    let x = dehomogenise3(&triangulate_views(cams, obs).ok()?)?;
    let r = track_residuals(rig, m, &x, obs)?;
    Some((x, (0..4).map(|j| r[2 * j].hypot(r[2 * j + 1])).fold(0.0, f64::max)))
}

/// Huber weights of the four 2D residuals of a track.
fn weights(r: &[f64; 8], k: f64) -> [f64; 4] {
    let mut w = [1.0; 4];
    for (i, wi) in w.iter_mut().enumerate() {
        let e = r[2 * i].hypot(r[2 * i + 1]);
        if e > k {
            *wi = k / e;
        }
    }
    w
}

/// Robust cost: the Huber loss of each 2D residual (squared pixels).
fn robust_cost(rig: &StereoRig, m: &Isometry3<f64>, pts: &[Point3<f64>], obs: &[RigTrack], k: f64) -> f64 {
    let mut c = 0.0;
    for (x, o) in pts.iter().zip(obs) {
        let Some(r) = track_residuals(rig, m, x, o) else { return f64::INFINITY };
        for i in 0..4 {
            let e = r[2 * i].hypot(r[2 * i + 1]);
            c += if e <= k { e * e } else { 2.0 * k * e - k * k };
        }
    }
    c
}

/// One track's weighted normal blocks at `(m, x)`: `U` (motion), `A` (point, undamped),
/// `B` (cross), gradients `g_m`, `g_x`. `None` when the point is behind a camera.
struct TrackNormal {
    u: Matrix6<f64>,
    a: Matrix3<f64>,
    bb: SMatrix<f64, 6, 3>,
    gm: Vector6<f64>,
    gx: Vector3<f64>,
}

fn track_normal(
    rig: &StereoRig,
    m: &Isometry3<f64>,
    x: &Point3<f64>,
    o: &RigTrack,
    k: f64,
) -> Option<TrackNormal> {
    let r = track_residuals(rig, m, x, o)?;
    let (jm, jx) = track_jacobians(rig, m, x)?;
    let w = weights(&r, k);
    let mut t = TrackNormal {
        u: Matrix6::zeros(),
        a: Matrix3::zeros(),
        bb: SMatrix::<f64, 6, 3>::zeros(),
        gm: Vector6::zeros(),
        gx: Vector3::zeros(),
    };
    for row in 0..8 {
        let wi = w[row / 2];
        let jmr = jm.row(row).transpose();
        let jxr = jx.row(row).transpose();
        t.u += wi * jmr * jmr.transpose();
        t.a += wi * jxr * jxr.transpose();
        t.bb += wi * jmr * jxr.transpose();
        t.gm += wi * jmr * r[row];
        t.gx += wi * jxr * r[row];
    }
    Some(t)
}

/// The normal equations at `(m, pts)` for the point-Schur back end of [`crate::lm`] (the
/// bundle adjustment's, `bundle/normal.rs`): the motion block and gradient, per point its
/// 3x3 block, gradient and its 6x3 block of `W`. `None` when a point is behind a camera.
fn normal_equations(
    rig: &StereoRig,
    m: &Isometry3<f64>,
    pts: &[Point3<f64>],
    obs: &[RigTrack],
    k: f64,
) -> Option<Normal> {
    let mut u = Matrix6::zeros();
    let mut gc = Vector6::zeros();
    let mut v = Vec::with_capacity(pts.len());
    let mut gp = Vec::with_capacity(pts.len());
    let mut w = DMatrix::zeros(6, 3 * pts.len());
    for (i, (x, o)) in pts.iter().zip(obs).enumerate() {
        let t = track_normal(rig, m, x, o, k)?;
        u += t.u;
        gc += t.gm;
        v.push(t.a);
        gp.push(t.gx);
        w.fixed_view_mut::<6, 3>(0, 3 * i).copy_from(&t.bb);
    }
    let u = DMatrix::from_column_slice(6, 6, u.as_slice());
    let gc = DVector::from_column_slice(gc.as_slice());
    Some(Normal::from_blocks(u, gc, v, gp, w))
}

/// Refine the motion and the points (module docs) from a start.
///
/// `points[i]` is the start of track `obs[i]`'s point (first left camera frame).
///
/// Errors: invalid options; [`GeometryError::NotEnoughData`] with fewer than 4 tracks or
/// mismatched lengths; [`GeometryError::Degenerate`] when the start puts a point behind
/// a camera, a point is unusable at the optimum (its 3x3 normal block singular: in
/// practice a point that crept towards infinity) or the normal equations are singular
/// (no parallax at all). [`refine_rig_motion_dropping`] leaves such tracks out instead.
pub fn refine_rig_motion(
    rig: &StereoRig,
    obs: &[RigTrack],
    start: &Isometry3<f64>,
    points: &[Point3<f64>],
    options: &RigMotionOptions,
) -> Result<RigMotionEstimate> {
    check_inputs(obs, points, options)?;
    let (m, pts, iterations) = optimise(rig, obs, start, points, options)?;
    finish(rig, obs, m, pts, options.huber_px, iterations)
}

/// Most rounds of [`refine_rig_motion_dropping`] that leave tracks out.
const MAX_DROP_ROUNDS: usize = 5;

/// [`refine_rig_motion`], but a track whose point is unusable, at the start (behind a
/// camera) or at the optimum (behind a camera, or its normal block singular: a point at
/// numerical infinity), is left out as an outlier and the rest re-fitted from where the
/// last fit ended (at most 5 rounds), instead of failing the whole motion for one point.
/// Returns the estimate and the indices (into `obs`) of the tracks it kept, in order:
/// `estimate.points[j]` belongs to `obs[kept[j]]`.
///
/// Errors: as [`refine_rig_motion`] when fewer than 4 tracks remain, the normal
/// equations are singular or tracks still drop after the last round.
pub fn refine_rig_motion_dropping(
    rig: &StereoRig,
    obs: &[RigTrack],
    start: &Isometry3<f64>,
    points: &[Point3<f64>],
    options: &RigMotionOptions,
) -> Result<(RigMotionEstimate, Vec<usize>)> {
    check_inputs(obs, points, options)?;
    let k = options.huber_px;
    let mut kept: Vec<usize> = (0..obs.len()).collect();
    let mut m = *start;
    let mut pts = points.to_vec();
    let mut optimised = false;
    let mut iterations = 0;
    for _ in 0..=MAX_DROP_ROUNDS {
        let o: Vec<RigTrack> = kept.iter().map(|&i| obs[i]).collect();
        let bad = unusable_tracks(rig, &m, &pts, &o, k);
        if bad.is_empty() {
            if optimised {
                let est = finish(rig, &o, m, pts, k, iterations)?;
                return Ok((est, kept));
            }
            let (m1, p1, it) = optimise(rig, &o, &m, &pts, options)?;
            (m, pts, optimised, iterations) = (m1, p1, true, iterations + it);
            continue;
        }
        let mut j = 0;
        kept.retain(|_| {
            j += 1;
            !bad.contains(&(j - 1))
        });
        let mut j = 0;
        pts.retain(|_| {
            j += 1;
            !bad.contains(&(j - 1))
        });
        if kept.len() < 4 {
            return Err(GeometryError::NotEnoughData {
                what: "rig motion tracks (after leaving out unusable points)",
                needed: 4,
                got: kept.len(),
            });
        }
        optimised = false;
    }
    Err(GeometryError::Degenerate(format!(
        "rig motion: points still unusable after {MAX_DROP_ROUNDS} rounds of leaving them out"
    )))
}

fn check_inputs(obs: &[RigTrack], points: &[Point3<f64>], options: &RigMotionOptions) -> Result<()> {
    options.validate()?;
    if obs.len() < 4 || points.len() != obs.len() {
        return Err(GeometryError::NotEnoughData {
            what: "rig motion tracks (with a start point each)",
            needed: 4,
            got: obs.len().min(points.len()),
        });
    }
    Ok(())
}

/// Indices of the tracks whose point is unusable at `(m, pts)`: behind a camera, or its
/// (undamped) 3x3 normal block singular.
fn unusable_tracks(
    rig: &StereoRig,
    m: &Isometry3<f64>,
    pts: &[Point3<f64>],
    obs: &[RigTrack],
    k: f64,
) -> Vec<usize> {
    pts.iter()
        .zip(obs)
        .enumerate()
        .filter(|(_, (x, o))| track_normal(rig, m, x, o, k).and_then(|t| t.a.try_inverse()).is_none())
        .map(|(i, _)| i)
        .collect()
}

/// The rig motion as a [`lm::LeastSquares`] problem: state the motion and the points,
/// the point-Schur back end, the cost half the Huber loss of [`robust_cost`].
struct Motion<'a> {
    rig: &'a StereoRig,
    obs: &'a [RigTrack],
    k: f64,
}

type MotionState = (Isometry3<f64>, Vec<Point3<f64>>);

impl lm::LeastSquares for Motion<'_> {
    type State = MotionState;
    type Normal = Normal;
    type Eval = f64;
    type Error = GeometryError;

    fn linearise(&mut self, (m, pts): &MotionState) -> Result<Option<Normal>> {
        Ok(normal_equations(self.rig, m, pts, self.obs, self.k))
    }

    fn retract(
        &self,
        (m, pts): &MotionState,
        (dm, dp): &(DVector<f64>, Vec<Vector3<f64>>),
    ) -> Result<Option<(MotionState, f64)>> {
        let dm = Vector6::from_column_slice(dm.as_slice());
        let pts_new: Vec<Point3<f64>> = pts.iter().zip(dp).map(|(x, d)| x + d).collect();
        let step_sq = dm.norm_squared() + dp.iter().map(|d| d.norm_squared()).sum::<f64>();
        Ok(Some(((perturb(m, &dm), pts_new), step_sq)))
    }

    fn evaluate(&self, (m, pts): &MotionState) -> Option<f64> {
        let c = 0.5 * robust_cost(self.rig, m, pts, self.obs, self.k);
        c.is_finite().then_some(c)
    }

    fn state_norm(&self, _state: &MotionState) -> f64 {
        0.0
    }
}

/// The function tolerance of the rig motion's Levenberg-Marquardt: a relative decrease of
/// 1e-12 (the cost to rounding at thousands of residuals).
const FUNCTION_TOLERANCE: f64 = 1e-12;

/// Levenberg-Marquardt ([`crate::lm`], point-Schur back end) from a start: the motion, the
/// points and the iterations run.
fn optimise(
    rig: &StereoRig,
    obs: &[RigTrack],
    start: &Isometry3<f64>,
    points: &[Point3<f64>],
    options: &RigMotionOptions,
) -> Result<(Isometry3<f64>, Vec<Point3<f64>>, usize)> {
    let k = options.huber_px;
    let cost = 0.5 * robust_cost(rig, start, points, obs, k);
    if !cost.is_finite() {
        return Err(GeometryError::Degenerate("a start point is behind a camera".into()));
    }
    let lm_options = lm::LmOptions {
        max_iterations: options.max_iterations,
        function_tolerance: FUNCTION_TOLERANCE,
        parameter_tolerance: 0.0,
    };
    let out = lm::run(&mut Motion { rig, obs, k }, (*start, points.to_vec()), cost, &lm_options)?;
    let (m, pts) = out.state;
    Ok((m, pts, out.iterations))
}

/// The estimate at an optimum `(m, pts)`: covariance, centre, noise.
fn finish(
    rig: &StereoRig,
    obs: &[RigTrack],
    m: Isometry3<f64>,
    pts: Vec<Point3<f64>>,
    k: f64,
    iterations: usize,
) -> Result<RigMotionEstimate> {
    let s = normal_equations(rig, &m, &pts, obs, k).and_then(|n| n.reduced_undamped()).ok_or_else(|| {
        GeometryError::Degenerate(
            "a point behind a camera or at infinity (singular normal block) at the optimum".into(),
        )
    })?;
    let s_inv = Matrix6::from_column_slice(s.as_slice())
        .try_inverse()
        .ok_or_else(|| GeometryError::Degenerate("rig motion not determined (no parallax)".into()))?;
    let n_obs = 8 * obs.len();
    let dof = n_obs.saturating_sub(6 + 3 * obs.len()).max(1) as f64;
    let mut weighted = 0.0;
    let mut plain = 0.0;
    for (x, o) in pts.iter().zip(obs) {
        if let Some(r) = track_residuals(rig, &m, x, o) {
            let w = weights(&r, k);
            for row in 0..8 {
                weighted += w[row / 2] * r[row] * r[row];
                plain += r[row] * r[row];
            }
        }
    }
    let sigma2 = weighted / dof;
    let covariance = s_inv * sigma2;
    let rt = m.rotation.to_rotation_matrix().into_inner().transpose();
    let c_tt = covariance.fixed_view::<3, 3>(3, 3).into_owned();
    Ok(RigMotionEstimate {
        cam2_from_cam1: m,
        covariance,
        centre_displacement: -(rt * m.translation.vector),
        centre_covariance: rt * c_tt * rt.transpose(),
        points: pts,
        rms_px: (plain / n_obs as f64).sqrt(),
        sigma_px: sigma2.sqrt(),
        iterations,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn rig() -> StereoRig {
        StereoRig {
            left: Intrinsics { fx: 700.0, fy: 720.0, skew: 0.5, cx: 390.0, cy: 284.0 },
            right: Intrinsics { fx: 705.0, fy: 716.0, skew: 0.0, cx: 380.0, cy: 290.0 },
            right_from_left: Isometry3::from_parts(
                Translation3::new(-1.0, 0.01, 0.02),
                UnitQuaternion::from_euler_angles(0.01, -0.02, 0.005),
            ),
        }
    }

    /// Tracks of random points 3-20 baselines in front, seen before and after `m`;
    /// optional Gaussian noise (pixels).
    fn problem(seed: u64, m: &Isometry3<f64>, n: usize, noise: f64) -> (Vec<RigTrack>, Vec<Point3<f64>>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let r = rig();
        let (mut obs, mut pts) = (Vec::new(), Vec::new());
        while obs.len() < n {
            let x = Point3::new(
                rng.random_range(-3.0..3.0),
                rng.random_range(-2.0..2.0),
                rng.random_range(3.0..20.0),
            );
            let Some(res) = track_residuals(&r, m, &x, &[Point2::origin(); 4]) else { continue };
            let mut t = [Point2::origin(); 4];
            for i in 0..4 {
                let mut g = || -> f64 {
                    let u1: f64 = rng.random_range(1e-12..1.0);
                    let u2: f64 = rng.random();
                    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
                };
                let (nx, ny) = (noise * g(), noise * g());
                t[i] = Point2::new(res[2 * i] + nx, res[2 * i + 1] + ny);
            }
            obs.push(t);
            pts.push(x);
        }
        (obs, pts)
    }

    fn motion(yaw: f64, pitch: f64, t: Vector3<f64>) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::from(t),
            UnitQuaternion::from_euler_angles(pitch, yaw, 0.3 * pitch),
        )
    }

    #[test]
    fn jacobians_match_central_differences() {
        let r = rig();
        let m = motion(0.05, -0.02, Vector3::new(0.1, -0.05, -0.4));
        let (obs, pts) = problem(3, &m, 5, 0.0);
        let h = 1e-6;
        for (x, o) in pts.iter().zip(&obs) {
            let (jm, jx) = track_jacobians(&r, &m, x).unwrap();
            for j in 0..6 {
                let mut d = Vector6::zeros();
                d[j] = h;
                let p = track_residuals(&r, &perturb(&m, &d), x, o).unwrap();
                d[j] = -h;
                let q = track_residuals(&r, &perturb(&m, &d), x, o).unwrap();
                for row in 0..8 {
                    let fd = (p[row] - q[row]) / (2.0 * h);
                    // Central differences: error O(h^2) times third derivatives (~1e-3 px here).
                    assert!(
                        (fd - jm[(row, j)]).abs() < 1e-5 * (1.0 + fd.abs()),
                        "m {row} {j}: {fd} vs {}",
                        jm[(row, j)]
                    );
                }
            }
            for j in 0..3 {
                let mut e = Vector3::zeros();
                e[j] = h;
                let p = track_residuals(&r, &m, &(x + e), o).unwrap();
                let q = track_residuals(&r, &m, &(x - e), o).unwrap();
                for row in 0..8 {
                    let fd = (p[row] - q[row]) / (2.0 * h);
                    assert!((fd - jx[(row, j)]).abs() < 1e-5 * (1.0 + fd.abs()), "x {row} {j}");
                }
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        /// Noise-free: from a perturbed start (motion and points), the motion to 1e-9 (the
        /// cost reaches its rounding floor; well conditioned with 40 points).
        #[test]
        fn noise_free_recovery(seed in 0u64..1000, yaw in -0.3..0.3f64, pitch in -0.05..0.05f64,
                               tx in -0.5..0.5f64, tz in -0.5..0.5f64) {
            let m = motion(yaw, pitch, Vector3::new(tx, 0.02, tz));
            let (obs, pts) = problem(seed, &m, 40, 0.0);
            let start = perturb(&m, &Vector6::new(0.01, -0.01, 0.005, 0.03, -0.02, 0.02));
            let noisy: Vec<Point3<f64>> = pts.iter().enumerate().map(|(i, p)| p + Vector3::new(0.01, -0.02, 0.05) * ((i % 3) as f64 - 1.0)).collect();
            let est = refine_rig_motion(&rig(), &obs, &start, &noisy, &RigMotionOptions::default()).unwrap();
            let err = est.cam2_from_cam1.inverse() * m;
            prop_assert!(err.translation.vector.norm() < 1e-9 && err.rotation.angle() < 1e-9, "{err:?}");
            prop_assert!(est.rms_px < 1e-7);
            let c = -(m.rotation.inverse() * m.translation.vector);
            prop_assert!((est.centre_displacement - c).norm() < 1e-9);
        }
    }

    /// At 1 px the motion error is within a few of its own standard deviations (the
    /// covariance is the Gauss-Newton one; 4 sigma for a 6-dof chi-square bound).
    #[test]
    fn noisy_covariance_is_consistent() {
        let m = motion(0.01, 0.0, Vector3::new(0.02, 0.0, -0.4));
        let mut chi = Vec::new();
        for seed in 0..20 {
            let (obs, pts) = problem(seed, &m, 100, 1.0);
            let est = refine_rig_motion(&rig(), &obs, &m, &pts, &RigMotionOptions::default()).unwrap();
            let dc = est.centre_displacement - (-(m.rotation.inverse() * m.translation.vector));
            let inv = est.centre_covariance.try_inverse().unwrap();
            chi.push((dc.transpose() * inv * dc)[(0, 0)]);
            assert!((est.sigma_px - 1.0).abs() < 0.2, "{}", est.sigma_px);
        }
        let mean = chi.iter().sum::<f64>() / chi.len() as f64;
        // Mean of a chi-square with 3 dof is 3; 20 samples: within [1.5, 5] comfortably.
        assert!((1.5..5.0).contains(&mean), "mean chi2 {mean}");
    }

    /// Re-selection keeps every exact track and drops a corrupted one.
    #[test]
    fn consistent_tracks_select_exact_ones() {
        let m = motion(0.1, 0.01, Vector3::new(0.2, 0.0, -0.5));
        let (mut obs, pts) = problem(4, &m, 30, 0.0);
        obs[7][2].x += 10.0;
        let kept = consistent_tracks(&rig(), &m, &obs, 1e-6);
        assert_eq!(kept.len(), 29);
        assert!(kept.iter().all(|(i, x)| *i != 7 && (x - pts[*i]).norm() < 1e-8));
    }

    /// A point at numerical infinity (its normal block underflows to singular, as a point
    /// that crept outwards does): the strict refinement fails the whole motion, the
    /// dropping one leaves that track out and recovers the noise-free motion (to 1e-9, as
    /// `noise_free_recovery`); so does a start point behind the camera.
    #[test]
    fn unusable_points_are_dropped() {
        let m = motion(0.1, 0.01, Vector3::new(0.2, 0.0, -0.5));
        let (obs, mut pts) = problem(5, &m, 30, 0.0);
        pts[4] = Point3::new(0.0, 0.0, 1e120);
        pts[9].z = -2.0;
        let o = RigMotionOptions::default();
        assert!(matches!(refine_rig_motion(&rig(), &obs, &m, &pts, &o), Err(GeometryError::Degenerate(_))));
        let start = perturb(&m, &Vector6::new(0.01, -0.01, 0.005, 0.03, -0.02, 0.02));
        let (est, kept) = refine_rig_motion_dropping(&rig(), &obs, &start, &pts, &o).unwrap();
        assert_eq!(kept.len(), 28);
        assert!(!kept.contains(&4) && !kept.contains(&9));
        assert_eq!(est.points.len(), kept.len());
        let err = est.cam2_from_cam1.inverse() * m;
        assert!(err.translation.vector.norm() < 1e-9 && err.rotation.angle() < 1e-9, "{err:?}");
        assert!(est.covariance.iter().all(|x| x.is_finite()));
        // Too few usable tracks left: an error, not a panic.
        let mut few = pts[..5].to_vec();
        few[0].z = -1.0;
        few[1].z = -1.0;
        assert!(refine_rig_motion_dropping(&rig(), &obs[..5], &m, &few, &o).is_err());
    }

    #[test]
    fn bad_inputs_are_errors() {
        let m = motion(0.0, 0.0, Vector3::new(0.0, 0.0, -0.4));
        let (obs, pts) = problem(1, &m, 3, 0.0);
        assert!(matches!(
            refine_rig_motion(&rig(), &obs, &m, &pts, &RigMotionOptions::default()),
            Err(GeometryError::NotEnoughData { .. })
        ));
        let (obs, mut pts) = problem(1, &m, 10, 0.0);
        pts[0].z = -1.0;
        assert!(matches!(
            refine_rig_motion(&rig(), &obs, &m, &pts, &RigMotionOptions::default()),
            Err(GeometryError::Degenerate(_))
        ));
        assert!(RigMotionOptions { huber_px: 0.0, ..RigMotionOptions::default() }.validate().is_err());
    }
}
