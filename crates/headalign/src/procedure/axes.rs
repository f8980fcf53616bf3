//! The vergence axes' measurement and its uncertainty ([`super`] module docs; paper
//! section 3.2 step 7, `docs/how-it-works.md#the-exact-alignment-solve`): where each axis came from
//! ([`AxisSources`]: the capture after a vergence move and the cameras resected from it),
//! the resected poses' covariance (6x6 in the tangent `ref_from_cam * Exp([w; t])`,
//! radians and scene units; least squares, [`resection_pose_covariance`], or a parametric
//! bootstrap of the robust resection, [`resection_pose_covariance_bootstrap`]), and the
//! axes re-derived under perturbations of the calibration and of those poses
//! ([`AxisPerturbations`], [`axis_perturbations`]), which the robot stages propagate.
//!
//! Under a calibration perturbation the scene points follow the cameras (one Gauss-Newton
//! re-triangulation each: their conditional mean, since the covariance has them
//! eliminated) and each axis pose is re-resected (one Gauss-Newton step over the
//! resection's inliers, chosen once at the estimate: a threshold re-applied per
//! perturbation would move observations in and out between the two sides of a central
//! difference). Steps: [`PROPAGATION_STEP_SIGMAS`] of each sigma; the re-triangulation's
//! derivatives by central differences at 1e-6; the resection's normal equations are the
//! resection's own ([`headalign_geometry::resection::normal_equations`], analytic). Residuals in pixels; the resection's
//! outlier threshold is `ResectionOptions::outlier_px` (5 px), its Huber loss 2 px.
//!
//! Pitfalls: a point near infinity has a nearly singular `J^T J`, and its Gauss-Newton
//! step may carry it through infinity to behind its cameras: it is held. The points' own
//! conditional noise (given the cameras) is not propagated into the resections. The
//! bootstrap is seeded (left camera `0x5eed_a215`, the right one adds 1).

use headalign_geometry::bundle::RigState;
use headalign_platform::Encoders;
use nalgebra::DVector;

use super::PROPAGATION_STEP_SIGMAS;
use super::sigmas::aligned_deltas;
use crate::alignment::{MeasuredCameras, VergeAxes, solve_alignment, verge_axes_from_motion};
use crate::verge_tilt::RigCalibration;

/// One measurement of the vergence axes: the capture after a vergence move and the
/// cameras resected from it.
#[derive(Debug, Clone)]
pub struct AxisMeasurement {
    /// The capture (its encoders give the joint turns).
    pub capture: headalign_platform::StereoCapture,
    /// Both cameras resected from it.
    pub measured: MeasuredCameras,
}

/// Where each vergence axis came from (`None`: not measured, nominal).
#[derive(Debug, Clone, Default)]
pub struct AxisSources {
    /// Source of the left vergence axis.
    pub left: Option<AxisMeasurement>,
    /// Source of the right vergence axis.
    pub right: Option<AxisMeasurement>,
}

/// The observations of `obs` that [`crate::alignment::measure_cameras`]' resection keeps:
/// tracks among `points` (the calibration's points seen three or more times,
/// [`RigCalibration::points`]) whose residual at `ref_from_cam` is within the resection's
/// outlier threshold (`ResectionOptions::outlier_px`), as (track, observed pixel). Chosen
/// once at the estimate and then held: a threshold re-applied under each finite-difference
/// perturbation would move observations in and out between the two sides of a difference.
pub(super) fn resection_inliers(
    k: &headalign_geometry::camera::Intrinsics,
    points: &std::collections::HashMap<u64, nalgebra::Point3<f64>>,
    obs: &[headalign_platform::TrackObservation],
    ref_from_cam: &nalgebra::Isometry3<f64>,
) -> Vec<(u64, nalgebra::Vector2<f64>)> {
    let outlier_px = headalign_geometry::resection::ResectionOptions::default().outlier_px;
    obs.iter()
        .filter(|o| {
            points
                .get(&o.track)
                .and_then(|x| project_into(k, ref_from_cam, x))
                .is_some_and(|p| (p - o.pixel.coords).norm() <= outlier_px)
        })
        .map(|o| (o.track, o.pixel.coords))
        .collect()
}

/// The pose-only noise estimate from a resection's inliers (pixels): the residuals' RMS at
/// `ref_from_cam` with 6 degrees of freedom taken out. Needs at least 4 inliers.
fn residual_sigma(
    k: &headalign_geometry::camera::Intrinsics,
    points: &std::collections::HashMap<u64, nalgebra::Point3<f64>>,
    inliers: &[(u64, nalgebra::Vector2<f64>)],
    ref_from_cam: &nalgebra::Isometry3<f64>,
) -> f64 {
    let dof = (2 * inliers.len() - 6) as f64;
    let sum: f64 = inliers
        .iter()
        .filter_map(|(t, px)| project_into(k, ref_from_cam, points.get(t)?).map(|p| (p - px).norm_squared()))
        .sum();
    (sum / dof).sqrt()
}

/// Pixel of `x` (reference frame) in the camera at `ref_from_cam`.
pub(super) fn project_into(
    k: &headalign_geometry::camera::Intrinsics,
    ref_from_cam: &nalgebra::Isometry3<f64>,
    x: &nalgebra::Point3<f64>,
) -> Option<nalgebra::Vector2<f64>> {
    k.project(&ref_from_cam.inverse_transform_point(x)).map(|p| p.coords)
}

/// Gauss-Newton normal equations `(J^T J, J^T r)` of a pose resected against `points` from
/// `inliers` (residual projected - observed, pixels), in the tangent `ref_from_cam *
/// Exp([w; t])`: the resection's own ([`headalign_geometry::resection::normal_equations`]
/// at `cam_from_ref`), whose left update `Exp(s) cam_from_ref` is `Exp([w; t])^-1`, `s =
/// -[w; t]` to first order, so `J` changes sign. `None` if a point is behind the camera.
fn resection_normal_equations(
    k: &headalign_geometry::camera::Intrinsics,
    points: &std::collections::HashMap<u64, nalgebra::Point3<f64>>,
    inliers: &[(u64, nalgebra::Vector2<f64>)],
    ref_from_cam: &nalgebra::Isometry3<f64>,
) -> Option<(nalgebra::Matrix6<f64>, nalgebra::Vector6<f64>)> {
    let pairs = inliers.iter().filter_map(|(t, px)| points.get(t).map(|x| (*x, nalgebra::Point2::from(*px))));
    let (jtj, jtr) = headalign_geometry::resection::normal_equations(k, &ref_from_cam.inverse(), pairs)?;
    Some((jtj, -jtr))
}

/// Covariance (6x6, tangent `ref_from_cam * Exp([w; t])`, radians and scene units) of a
/// camera pose resected from `obs` against `points` by [`crate::alignment::measure_cameras`]:
/// `sigma^2 (J^T J)^-1` over the observations it keeps (`resection_inliers`), `J` the
/// resection's analytic one. `sigma` is `noise_px` or, if `None`, the residuals' own estimate
/// `sqrt(sum r^2 / (2n - 6))`. `None` if fewer than 4 points or `J^T J` is singular.
pub fn resection_pose_covariance(
    k: &headalign_geometry::camera::Intrinsics,
    points: &std::collections::HashMap<u64, nalgebra::Point3<f64>>,
    obs: &[headalign_platform::TrackObservation],
    ref_from_cam: &nalgebra::Isometry3<f64>,
    noise_px: Option<f64>,
) -> Option<nalgebra::Matrix6<f64>> {
    let inliers = resection_inliers(k, points, obs, ref_from_cam);
    if inliers.len() < 4 {
        return None;
    }
    let sigma = noise_px.unwrap_or_else(|| residual_sigma(k, points, &inliers, ref_from_cam));
    let (jtj, _) = resection_normal_equations(k, points, &inliers, ref_from_cam)?;
    jtj.try_inverse().map(|inv| inv * (sigma * sigma))
}

/// Draws of [`resection_pose_covariance_bootstrap`]: the covariance of a 6-vector from
/// 200 draws knows each standard deviation to about 5 %.
pub const AXIS_BOOTSTRAP_DRAWS: usize = 200;
/// Seed of the bootstrap's noise (left camera; the right one adds 1).
const AXIS_BOOTSTRAP_SEED: u64 = 0x5eed_a215;

/// Covariance (6x6, tangent as [`resection_pose_covariance`]) of a camera pose resected
/// by [`crate::alignment::measure_cameras`], as the spread of its own robust resection
/// re-run on [`AXIS_BOOTSTRAP_DRAWS`] synthetic draws
/// ([`headalign_geometry::resection::resection_bootstrap`]: the exact pixels, at the
/// estimate, of every point the capture observes, plus Gaussian noise of `noise_px` or, if `None`,
/// the residuals' estimate as [`resection_pose_covariance`]). Unlike the least-squares
/// covariance it includes the resection's Huber loss (2 px) and its outlier re-selection
/// (5 px), which at 3 px noise widen the pose's spread about 1.4x (standard deviation;
/// 1.0x at 1 px; a past measurement; the test
/// `robot::tests::axis_pose_part_matches_monte_carlo_at_3px` checks this bootstrap).
/// `None` with fewer than 6 points or 20 successful
/// draws.
pub fn resection_pose_covariance_bootstrap(
    k: &headalign_geometry::camera::Intrinsics,
    points: &std::collections::HashMap<u64, nalgebra::Point3<f64>>,
    obs: &[headalign_platform::TrackObservation],
    ref_from_cam: &nalgebra::Isometry3<f64>,
    noise_px: Option<f64>,
    seed: u64,
) -> Option<nalgebra::Matrix6<f64>> {
    use headalign_geometry::resection::{ResectionOptions, resection_bootstrap};
    let inliers = resection_inliers(k, points, obs, ref_from_cam);
    if inliers.len() < 6 {
        return None;
    }
    let sigma = noise_px.unwrap_or_else(|| residual_sigma(k, points, &inliers, ref_from_cam));
    // Every observed point, as the resection sees them (its inliers at 3 px are only about
    // 75 % of the true matches: a draw from the inliers alone would re-select a subset of
    // a subset and spread 12 % wider).
    let xs: Vec<nalgebra::Point3<f64>> = obs.iter().filter_map(|o| points.get(&o.track).copied()).collect();
    let cam_from_ref = ref_from_cam.inverse();
    let draws = resection_bootstrap(
        k,
        &xs,
        &cam_from_ref,
        sigma,
        AXIS_BOOTSTRAP_DRAWS,
        seed,
        &ResectionOptions::default(),
    )
    .ok()?;
    if draws.len() < 20 {
        return None;
    }
    // Tangent of each draw: ref_from_cam_draw = ref_from_cam * Exp([w; t]).
    let ds: Vec<nalgebra::Vector6<f64>> = draws
        .iter()
        .map(|c| {
            let d = cam_from_ref * c.inverse();
            let w = d.rotation.scaled_axis();
            let t = d.translation.vector;
            nalgebra::Vector6::new(w.x, w.y, w.z, t.x, t.y, t.z)
        })
        .collect();
    let n = ds.len() as f64;
    let mean: nalgebra::Vector6<f64> = ds.iter().sum::<nalgebra::Vector6<f64>>() / n;
    Some(ds.iter().map(|d| (d - mean) * (d - mean).transpose()).sum::<nalgebra::Matrix6<f64>>() / (n - 1.0))
}

/// The points of `state` moved by one Gauss-Newton step each against their bundle
/// observations `by_point` (indices into `state.points`): to first order the points'
/// conditional mean given the perturbed camera parameters (the covariance has the points
/// eliminated; they follow the cameras). Points with fewer than 2 observations are held,
/// and so is a point whose step would leave one of its observations unprojectable.
pub(super) fn retriangulated(
    state: &RigState,
    by_point: &[Vec<&headalign_geometry::bundle::BundleObservation>],
) -> RigState {
    use headalign_geometry::bundle::residual_pixels_at;
    let mut out = state.clone();
    // Each view's pose once (the residuals' own, so the arithmetic is unchanged).
    let poses: Vec<nalgebra::Isometry3<f64>> =
        (0..state.motions.view_count()).map(|v| state.motions.ref_from_cam(v)).collect();
    let h = 1e-6;
    for (j, obs) in by_point.iter().enumerate() {
        if obs.len() < 2 || j >= out.points.len() {
            continue;
        }
        let x = state.points[j];
        let mut jtj = nalgebra::Matrix3::<f64>::zeros();
        let mut jtr = nalgebra::Vector3::<f64>::zeros();
        for o in obs {
            let Some(pose) = poses.get(o.view) else { continue };
            let Some(r) = residual_pixels_at(state, pose, &x, o) else { continue };
            let mut jm = nalgebra::Matrix2x3::<f64>::zeros();
            let mut ok = true;
            for c in 0..3 {
                let mut probe = x;
                probe[c] += h;
                let p = residual_pixels_at(state, pose, &probe, o);
                probe[c] -= 2.0 * h;
                let m = residual_pixels_at(state, pose, &probe, o);
                match (p, m) {
                    (Some(p), Some(m)) => jm.set_column(c, &((p - m) / (2.0 * h))),
                    _ => ok = false,
                }
            }
            if ok {
                jtj += jm.transpose() * jm;
                jtr += jm.transpose() * r;
            }
        }
        let Some(inv) = jtj.try_inverse() else { continue };
        let moved = x - inv * jtr;
        // A point near infinity has a nearly singular `J^T J`: its step may carry it
        // through infinity to behind its cameras, where nothing downstream can project it
        // (seed 72 at 3 px: one such point made every perturbation's re-resection fail and
        // the aligned sigmas collapse to the encoder prior's). Such a point is held: it
        // is seen along nearly the same ray either way.
        if obs.iter().all(|o| {
            poses.get(o.view).is_some_and(|pose| residual_pixels_at(state, pose, &moved, o).is_some())
        }) {
            out.points[j] = moved;
        }
    }
    out
}

/// One Gauss-Newton step of the resection of `ref_from_cam` against `points` over the
/// observations the resection kept at the estimate (`inliers`, [`resection_inliers`]): to
/// first order the pose [`crate::alignment::measure_cameras`] would return for these
/// intrinsics and points.
fn reresected(
    k: &headalign_geometry::camera::Intrinsics,
    points: &std::collections::HashMap<u64, nalgebra::Point3<f64>>,
    inliers: &[(u64, nalgebra::Vector2<f64>)],
    ref_from_cam: &nalgebra::Isometry3<f64>,
) -> Option<nalgebra::Isometry3<f64>> {
    let (jtj, jtr) = resection_normal_equations(k, points, inliers, ref_from_cam)?;
    let step = -(jtj.try_inverse()? * jtr);
    Some(ref_from_cam * tangent_step(&step))
}

/// `Exp([w; t])` as an isometry (rotation vector `w`, translation `t`).
pub(super) fn tangent_step(d: &nalgebra::Vector6<f64>) -> nalgebra::Isometry3<f64> {
    nalgebra::Isometry3::new(
        nalgebra::Vector3::new(d[3], d[4], d[5]),
        nalgebra::Vector3::new(d[0], d[1], d[2]),
    )
}

/// The vergence axes re-measured under perturbations, linearised: what
/// [`alignment_sigmas_measured`] differentiates.
///
/// [`alignment_sigmas_measured`]: super::alignment_sigmas_measured
pub(super) struct AxisFollow<'a> {
    calib: &'a RigCalibration,
    verge: &'a VergeAxes,
    sources: &'a AxisSources,
    reference: &'a Encoders,
    /// Every observation of the final adjustment, by point.
    pub(super) by_point: Vec<Vec<&'a headalign_geometry::bundle::BundleObservation>>,
    /// The resections' inliers at the estimate (`resection_inliers`), left then right.
    inliers: [Vec<(u64, nalgebra::Vector2<f64>)>; 2],
    /// The resected poses: left camera of the left source, right camera of the right one.
    pub(super) poses: [Option<nalgebra::Isometry3<f64>>; 2],
}

impl<'a> AxisFollow<'a> {
    /// Side `side`'s resection (0: the left camera of the left axis' source, 1: the right
    /// camera of the right one): its observations, its intrinsics in the calibration and
    /// its resected pose; `None` for an axis without a source or without a pose.
    pub(super) fn resected(
        &self,
        side: usize,
    ) -> Option<(
        &'a [headalign_platform::TrackObservation],
        &'a headalign_geometry::camera::Intrinsics,
        nalgebra::Isometry3<f64>,
    )> {
        let state = &self.calib.bundle.state;
        let (obs, k) = if side == 0 {
            (self.sources.left.as_ref().map(|s| s.capture.left.as_slice()), &state.left)
        } else {
            (self.sources.right.as_ref().map(|s| s.capture.right.as_slice()), &state.right)
        };
        Some((obs?, k, self.poses.get(side).copied().flatten()?))
    }

    pub(super) fn new(
        calib: &'a RigCalibration,
        verge: &'a VergeAxes,
        sources: &'a AxisSources,
        reference: &'a Encoders,
    ) -> Self {
        let mut by_point: Vec<Vec<&headalign_geometry::bundle::BundleObservation>> =
            vec![Vec::new(); calib.bundle.state.points.len()];
        for o in &calib.observations {
            if o.point < by_point.len() {
                by_point[o.point].push(o);
            }
        }
        let state = &calib.bundle.state;
        let points: std::collections::HashMap<u64, nalgebra::Point3<f64>> =
            calib.points().into_iter().collect();
        let poses = [
            sources.left.as_ref().map(|s| s.measured.ref_from_left),
            sources.right.as_ref().map(|s| s.measured.ref_from_right),
        ];
        let inliers = [
            match (&sources.left, poses[0]) {
                (Some(src), Some(p)) => resection_inliers(&state.left, &points, &src.capture.left, &p),
                _ => Vec::new(),
            },
            match (&sources.right, poses[1]) {
                (Some(src), Some(p)) => resection_inliers(&state.right, &points, &src.capture.right, &p),
                _ => Vec::new(),
            },
        ];
        Self { calib, verge, sources, reference, by_point, inliers, poses }
    }

    /// Aligned deltas with the calibration `state` and the axis-measuring poses `poses`
    /// (as [`Self::poses`]), the axes from [`Self::axes`].
    pub(super) fn deltas(
        &self,
        state: &RigState,
        poses: [Option<&nalgebra::Isometry3<f64>>; 2],
    ) -> Option<[f64; 3]> {
        let axes = self.axes(state, poses)?;
        solve_alignment(state, &axes, self.reference).ok().map(|s| aligned_deltas(&s))
    }

    /// The vergence axes with the calibration `state` and the axis-measuring poses `poses`
    /// (as [`Self::poses`]): each measured axis re-derived by [`verge_axes_from_motion`],
    /// an axis without a source held as given.
    fn axes(&self, state: &RigState, poses: [Option<&nalgebra::Isometry3<f64>>; 2]) -> Option<VergeAxes> {
        let axis = |src: &Option<AxisMeasurement>, pose: Option<&nalgebra::Isometry3<f64>>, is_left: bool| {
            let (Some(src), Some(pose)) = (src, pose) else {
                return Some(if is_left { self.verge.left } else { self.verge.right });
            };
            let mut m = src.measured;
            if is_left {
                m.ref_from_left = *pose;
            } else {
                m.ref_from_right = *pose;
            }
            let axes = verge_axes_from_motion(state, self.reference, &src.capture.encoders, &m).ok()?;
            Some(if is_left { axes.left } else { axes.right })
        };
        Some(VergeAxes {
            left: axis(&self.sources.left, poses[0], true)?,
            right: axis(&self.sources.right, poses[1], false)?,
        })
    }

    /// Aligned deltas under the calibration perturbation `delta` (the bundle's tangent):
    /// the points follow the cameras (one Gauss-Newton re-triangulation each, against all
    /// their adjustment observations) and each axis pose is re-resected (one Gauss-Newton
    /// step over its resection's inliers, held from the estimate).
    pub(super) fn followed(&self, delta: &DVector<f64>) -> Option<[f64; 3]> {
        let (st, axes) = self.followed_axes(delta)?;
        solve_alignment(&st, &axes, self.reference).ok().map(|s| aligned_deltas(&s))
    }

    /// The perturbed calibration state and the vergence axes re-derived under it, as
    /// [`Self::followed`].
    fn followed_axes(&self, delta: &DVector<f64>) -> Option<(RigState, VergeAxes)> {
        let st = retriangulated(&self.calib.bundle.perturbed(delta).ok()?, &self.by_point);
        let pts: std::collections::HashMap<u64, nalgebra::Point3<f64>> =
            self.calib.point_tracks.iter().copied().zip(st.points.iter().copied()).collect();
        let left = match self.poses[0] {
            Some(p) => Some(reresected(&st.left, &pts, &self.inliers[0], &p)?),
            None => None,
        };
        let right = match self.poses[1] {
            Some(p) => Some(reresected(&st.right, &pts, &self.inliers[1], &p)?),
            None => None,
        };
        let axes = self.axes(&st, [left.as_ref(), right.as_ref()])?;
        Some((st, axes))
    }
}

/// The vergence axes at `+` and `-` one finite-difference step of one source of
/// uncertainty ([`AxisPerturbations`]).
#[derive(Debug, Clone, Copy)]
pub struct AxisStep {
    /// The axes re-derived at `+` the step.
    pub plus: VergeAxes,
    /// ... and at `-` the step.
    pub minus: VergeAxes,
}

/// The vergence axes' uncertainty as finite-difference steps, for propagating it, with
/// its correlation to the calibration, into anything predicted at other vergence
/// readings (the robot stages' stereo rig at a drive's readings,
/// [`crate::robot::align_pan`], [`crate::robot::zero_steering`]). The axes are a function
/// of the calibration (the pan/elevation chain, the stereo pose, and the scene points the
/// axis views are resected against) and of the resected poses' own pixel noise
/// (independent: the axis views are not in the bundle); the same linearisation as
/// [`alignment_sigmas_measured`] (`AxisFollow`). Built by [`axis_perturbations`].
///
/// [`alignment_sigmas_measured`]: super::alignment_sigmas_measured
#[derive(Debug, Clone, Default)]
pub struct AxisPerturbations {
    /// One entry per parameter of the bundle covariance (its order): the axes with the
    /// calibration moved along that parameter by `+-` [`Self::calibration_step`] (the
    /// step [`crate::robot`]'s calibration propagation uses), the points following and
    /// the axis poses re-resected; `None` where the parameter has no positive variance;
    /// the axes held as given (both steps `verge`) where they cannot be re-derived, so the
    /// parameter still counts through the rest of a computation.
    pub calibration: Vec<Option<AxisStep>>,
    /// The resected poses' own noise: independent modes of unit variance (the columns
    /// `l` of the Cholesky factor of each pose's covariance), each the axes with that
    /// pose moved by `+-` [`PROPAGATION_STEP_SIGMAS`] `l` (the calibration held): the
    /// central difference of a quantity over one mode, divided by
    /// `2 PROPAGATION_STEP_SIGMAS`, is its change per unit of the mode.
    pub pose: Vec<AxisStep>,
}

impl AxisPerturbations {
    /// The calibration parameter's step ([`PROPAGATION_STEP_SIGMAS`] of its standard
    /// deviation), as used for [`Self::calibration`].
    pub fn calibration_step(cov: &headalign_geometry::bundle::Covariance, i: usize) -> f64 {
        PROPAGATION_STEP_SIGMAS * cov.matrix[(i, i)].max(0.0).sqrt()
    }
}

/// Build [`AxisPerturbations`] for the axes `verge` measured from `sources` (an axis
/// without a source is held as given: both steps equal it). `noise_px` as
/// [`alignment_sigmas_measured`] (`None`: estimated from the resection residuals).
///
/// [`alignment_sigmas_measured`]: super::alignment_sigmas_measured
pub fn axis_perturbations(
    calib: &RigCalibration,
    verge: &VergeAxes,
    sources: &AxisSources,
    reference: &Encoders,
    noise_px: Option<f64>,
) -> AxisPerturbations {
    let follow = AxisFollow::new(calib, verge, sources, reference);
    let cov = &calib.bundle.covariance;
    let n = cov.matrix.nrows();
    let calibration = (0..n)
        .map(|i| {
            let h = AxisPerturbations::calibration_step(cov, i);
            if h.is_nan() || h <= 0.0 {
                return None;
            }
            let mut delta = DVector::zeros(n);
            delta[i] = h;
            let plus = follow.followed_axes(&delta).map(|f| f.1);
            delta[i] = -h;
            let minus = follow.followed_axes(&delta).map(|f| f.1);
            Some(match (plus, minus) {
                (Some(plus), Some(minus)) => AxisStep { plus, minus },
                _ => AxisStep { plus: *verge, minus: *verge },
            })
        })
        .collect();
    let state = &calib.bundle.state;
    let points: std::collections::HashMap<u64, nalgebra::Point3<f64>> = calib.points().into_iter().collect();
    let mut pose = Vec::new();
    for side in 0..2 {
        let Some((obs, k, pose0)) = follow.resected(side) else { continue };
        let seed = AXIS_BOOTSTRAP_SEED + side as u64;
        let Some(pcov) = resection_pose_covariance_bootstrap(k, &points, obs, &pose0, noise_px, seed) else {
            continue;
        };
        let Some(chol) = pcov.cholesky() else { continue };
        let l = chol.l();
        for c in 0..6 {
            let step: nalgebra::Vector6<f64> = l.column(c) * PROPAGATION_STEP_SIGMAS;
            let eval = |d: &nalgebra::Vector6<f64>| {
                let moved = pose0 * tangent_step(d);
                let mut poses = [follow.poses[0].as_ref(), follow.poses[1].as_ref()];
                poses[side] = Some(&moved);
                follow.axes(state, poses)
            };
            if let (Some(plus), Some(minus)) = (eval(&step), eval(&-step)) {
                pose.push(AxisStep { plus, minus });
            }
        }
    }
    AxisPerturbations { calibration, pose }
}
