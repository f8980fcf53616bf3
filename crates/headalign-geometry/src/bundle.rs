//! Rig bundle adjustment: maximum-likelihood refinement of a calibrated stereo rig, its
//! motions and the scene points on reprojection error (DESIGN.md section 2, step 4).
//!
//! # What it computes
//!
//! A rigid stereo rig (left and right pinhole camera) is observed from views
//! `k = 0..V-1`. Every unknown lives in the **reference frame = left camera of view 0**
//! (x right, y down, z forward). A point `X` projects to
//!
//! - left image of view k: `K_L pi(cam_k_from_ref X)`,
//! - right image of view k: `K_R pi(right_from_left cam_k_from_ref X)`,
//!
//! with `pi(p) = (p.x / p.z, p.y / p.z)` and `cam_k_from_ref = ref_from_cam_k^-1`. The
//! residual of an observation is *projected pixel - observed pixel*, in pixels
//! ([`residual_pixels`]).
//!
//! # Parameters and degrees of freedom
//!
//! The "camera" (non-point) parameters, in this order (their names are those of
//! [`Covariance::names`]):
//!
//! - `left.{fx,fy,skew,cx,cy}`, `right.{..}`: intrinsics, up to 5 each.
//!   `zero_skew` holds the skew at 0 (it is set to 0 at the start), `square_pixels`
//!   ties `fy = fx` (both are set to their mean at the start; `fx` then moves both),
//!   `fix_principal_point` holds `cx, cy`. [`bundle_adjust_holding`] holds any named
//!   camera parameter at its start value (a profile-likelihood point; a held `fy` stays
//!   untied from `fx`).
//! - `left.{k1,k2}`, `right.{k1,k2}` (only with `estimate_distortion`): the radial
//!   coefficients of OpenCV's `plumb_bob` lens model ([`Distortion`], dimensionless, on
//!   normalised coordinates), additive update. The projection is then
//!   `K distort(pi(X))`; the other coefficients (`p1 p2 k3`) of
//!   [`RigState::left_distortion`] / `right_distortion` are held at their given values (a
//!   known lens model is used as given, estimated or not). Pitfall: with small rotations
//!   `k1` correlates with the focal length and the principal point (a barrel lens looks
//!   like a shorter focal length towards the image edges); the covariance shows it.
//! - `rig.rot0..2`: left-multiplicative rotation update of `right_from_left`,
//!   `R <- exp(w) R`; `rig.tdir0..1`: the *direction* of its translation on the unit
//!   sphere (tangent-plane update, `t <- |t| normalize(t/|t| + B d)`), its length is held
//!   fixed (scale gauge).
//! - [`Motions::Free`]: `view{k}.rot0..2`, `view{k}.trans0..2` for `k >= 1`, the
//!   left-multiplicative update `ref_from_cam <- (exp(w), v) * ref_from_cam` (6 dof).
//! - [`Motions::Joints`]: `axis{j}.dir0..1` (direction, tangent-plane update) and
//!   `axis{j}.pt0..1` (the foot point, moved in the plane perpendicular to the direction)
//!   for every axis (4 dof, a line), then `view{k}.angle{j}` for `k >= 1` when
//!   `angle_prior_sigma` is set (otherwise the angles are held at the commanded values).
//!   The pose of view k is the product of exponentials, root first:
//!   `ref_from_cam_k = Rot(axis_0, theta_k0) * Rot(axis_1, theta_k1) * ...`.
//!   The angles carry a Gaussian prior around the commanded ones (dimensionless
//!   residuals), weighted against the pixel residuals as if the pixel noise were
//!   `noise_sigma_px` (1 px when that is `None`); [`AnglePrior`] says how the commanded
//!   angles are in error. By default ([`AnglePrior::ReadingDifferences`]) they are
//!   differences of encoder readings, each read with independent noise `sigma`, all
//!   taken from view 0's reading: the errors `theta_kj - commanded_kj` of joint `j` over
//!   the `m` views `k >= 1` then have covariance `sigma^2 (I + 1 1^T)` (each its own
//!   reading's noise minus the shared reference reading's), whitened as
//!   `(I - beta 1 1^T) e / sigma` with `beta = (1 - 1/sqrt(m + 1)) / m`
//!   ([`angle_prior_residuals`]). Treating them as independent with variance `sigma^2`
//!   ([`AnglePrior::Independent`]) states each angle's error too small by `sqrt 2` and
//!   misses their correlation: with the simulator's readings at 0.01 deg the angles'
//!   sigmas are 0.0093 deg that way against 0.0118 deg (the right value, near
//!   `sqrt 2 * 0.01` where the images add little). The intrinsics hardly depend on it: a
//!   0.01 deg prior is nearly as good as exact angles for them (the focal length's bound
//!   at 3 px, one seed: 1.378 % with exact angles, 1.395 % with either model, 1.93 % with
//!   a 0.1 deg prior), and `experiment calibration --encoder-noise 0.01` gave the same
//!   ratios with both models to 0.02.
//! - Points: 3 each, eliminated by the Schur complement, never in the covariance. They
//!   are stored Euclidean but updated on the sphere of homogeneous 4-vectors
//!   (`h = (X, 1)/|(X, 1)|`, `h <- normalize(h + B d)`, `B` a Householder basis of the
//!   tangent space): depth along a ray then enters the disparity nearly linearly, and
//!   Gauss-Newton steps stay good for far points along the weakly observed
//!   plane-at-infinity direction of small-rotation self-calibration (with Euclidean point
//!   updates the same problem needed ~5x more iterations).
//!
//! # Gauge
//!
//! The reference frame is fixed by holding view 0 at the identity (for `Joints`, row 0 of
//! the angles is zero, so view 0 does not depend on the axes); the scale by holding
//! `|right_from_left.translation|` constant. Everything else is observable given two
//! rotations about different axes: a caller that wants a different scale (a known
//! baseline) rescales before or after.
//!
//! # Algorithm
//!
//! Levenberg-Marquardt with Marquardt's diagonal scaling (diagonal clamped to
//! `[1e-6, 1e32]`), steps accepted only if the robust cost decreases, so the returned
//! state is never worse than the initial one. The damping `lambda` (start 1e-3) follows
//! Nielsen's rule (H. B. Nielsen, "Damping parameter in Marquardt's method", IMM-REP
//! 1999-05; Madsen, Nielsen, Tingleff, "Methods for non-linear least squares problems",
//! 2004, section 3.2): after an accepted step with gain ratio `rho` (actual over predicted
//! decrease) `lambda *= max(1/3, 1 - (2 rho - 1)^3)`, after a rejected one
//! `lambda *= nu, nu *= 2` (`nu = 2` after each acceptance). The older rule (divide by 10
//! on acceptance, multiply by 10 on rejection) oscillated: measured over the adjustments
//! of `experiment fig5-verge-tilt`, 1.88 solves per linearisation, nearly every other step
//! rejected; with Nielsen's rule `fig5-verge-tilt --trials 100` ran 36.2 -> 27.3 s on the
//! same machine. Each iteration forms the normal equations
//! `J^T W J`, with one 3x3 block `V_p` per point, the dense camera block `U` and the
//! off-diagonal blocks `W_p`, reduces them to the camera system
//! `(U - sum_p W_p V_p^-1 W_p^T) dc = -g_c + sum_p W_p V_p^-1 g_p` (Schur complement over
//! the points), solves it by Cholesky and back-substitutes the points (Triggs, McLauchlan,
//! Hartley, Fitzgibbon, "Bundle adjustment - a modern synthesis", 2000, section 6;
//! Hartley & Zisserman, 2nd ed., appendix A6). Robust losses (Huber, Cauchy) act on the
//! norm of each 2D residual by iteratively reweighted least squares (weights
//! `rho'(s)/s` at the linearisation point); the reported RMS is of the unweighted
//! residuals (outliers included). IRLS converges linearly: with 10 % outliers expect
//! ~45 iterations to the default tolerances, against ~10 for plain least squares.
//! Cost per iteration: `U` is one dense product per (view, side) pair (all its
//! observations share the same camera-parameter columns) and `sum_p W_p V_p^-1 W_p^T`
//! one product `M M^T` with `M_p = W_p L_p^-T` (`V_p = L_p L_p^T`); with the residual-only
//! evaluation this took the adjustment 35 % faster than per-observation scatter
//! (`cargo bench -p headalign-geometry --bench bundle`, 80 -> 52 ms).
//!
//! Jacobians: projection w.r.t. intrinsics and the camera-frame point are analytic, as
//! are those w.r.t. the rig and free view poses (tangent updates via [`so3::exp`], safe
//! at zero). For the `Joints` model the derivative of each view's pose tangent w.r.t. the
//! axis and angle parameters is taken by **central differences of the small pose
//! function** (step 1e-6, one 6-vector per parameter per view per iteration) and chained
//! analytically with the pose Jacobian; its relative error is about 1e-10, which affects
//! only the convergence rate, not the minimum.
//!
//! Observations whose point is behind either camera at the initial state are left out,
//! then points with fewer than 2 remaining observations are left out (returned
//! unchanged, no error); a step that would bring any used point behind a camera is
//! rejected. Stopping: relative cost decrease below `function_tolerance`, step norm below
//! `parameter_tolerance * (|x| + parameter_tolerance)` (`|x|` over intrinsics, baseline
//! and used points), damping limit (no decrease possible: a minimum to rounding), or
//! `max_iterations`.
//!
//! # Measurement window
//!
//! A detector reports a feature only if its measured position lies in the image (or its
//! detection window), so an observation whose true position is within a few sigma of the
//! border was kept only if the noise did not push it out: its error has an inward mean.
//! With [`BundleOptions::measurement_window`] and `noise_sigma_px`, the residual of each
//! image axis is the *expected reported measurement* minus the observed pixel, where the
//! expectation is the projection plus the mean of a Gaussian of that sigma truncated to
//! the window ([`truncated_mean_shift`]), and its Jacobian row is scaled by that
//! expectation's derivative (the truncated variance over `sigma^2`). More than 6 sigma
//! inside the window nothing changes. [`residual_pixels`] stays the plain reprojection
//! error. The estimating equations are then unbiased at the border too
//! (moment matching: the expectation of each residual is zero at the truth; the exact
//! truncated likelihood differs only in the weight of the few border residuals).
//! Measured (the removed `examples/bias_mc.rs`, 2400 adjustments of the experiments' scene at 3 px): the
//! image border's truncation put the focal lengths +0.08 to +0.14 sigma higher, fy most
//! (the image is 576 px high); with the window they return to the untruncated values.
//!
//! # Covariance
//!
//! At the solution, with no damping and the final robust weights, the reduced camera
//! system `S` is formed with the prior weighted by `sigma^2`, and the covariance of the
//! camera parameters (tangent parametrisation above) is `sigma^2 S^-1`, the marginal
//! covariance with the points eliminated. `sigma` is `noise_sigma_px` or, if `None`, the
//! estimate `sigma^2 = sum w |r|^2 / (m - n)` with `m = 2 observations + priors`,
//! `n = parameters` for `RobustLoss::None`; with a robust loss the outliers would inflate
//! that sum, so the estimate is `median |r| / sqrt(2 ln 2) * sqrt(m / (m - n))` (the
//! median of the Rayleigh-distributed 2D residual norms). Points whose undamped block
//! `V_p` is not positive definite are omitted from the covariance (conservative), and so
//! are the observations of a point collapsed onto a camera centre (information above
//! `1e8` times the median point's, `MAX_POINT_INFORMATION_RATIO`): its terms would
//! swamp the camera parameters' in rounding and make `S` indefinite.
//!
//! With [`CovarianceModel::PointClustered`] the covariance is instead the cluster-robust
//! ("sandwich") estimate with each point's observations as one cluster:
//! `S^-1 (sum_p s_p s_p^T + sigma^2 P) S^-1 * 2n / (2n - c)`, where `s_p = g_p - W_p V_p^-1
//! h_p` is point `p`'s efficient score for the camera parameters (`g_p = sum J_c^T r`,
//! `h_p = sum J_p^T r` over its observations, zero at convergence; pixels), `P` the
//! angle priors' information (weighted by `sigma^2` as in `S`), `c` the camera
//! parameters and `2n` the residual components (the camera parameters' share of the
//! leverage; the points' share is already out of `s_p`, which sees only the residual
//! part the point did not absorb). Under i.i.d. Gaussian noise its expectation is
//! `sigma^2 S^-1`; it stays consistent when a point's errors are correlated across its
//! observations or differ in size between points (features tracked through images carry
//! the same localisation bias into every view of a track: White 1980, Liang and Zeger
//! 1986, the clustered form). It needs many more points than camera parameters (here
//! hundreds against 20-40). [`clustered_covariance`] computes the same sandwich with the
//! clusters given by the caller (points sharing a label form one cluster: an image region,
//! a surface), to test whether errors are correlated across points (diagnostics; coarse
//! clusters are few, and a sandwich over few clusters is noisy and biased low).
//! [`BundleResult::perturbed`] moves the
//! state by a tangent step so callers can propagate the covariance to any derived
//! quantity by finite differences.
//!
//! # Pitfalls
//!
//! - Gauge: if view 0 were not the identity or the baseline length were free, the reduced
//!   system would be singular; a perturbed start with a different baseline length converges
//!   to a *scaled* truth.
//! - An axis whose angle is zero in every view does not move anything and cannot be
//!   estimated: rejected with [`GeometryError::Degenerate`].
//! - The sign of an angle goes with the direction of its axis (`(-a, -theta)` is the same
//!   motion). The tangent updates never flip an axis, so keep the directions of the
//!   initial axes consistent with the commanded angles.
//! - Small rotations (3 deg) make the axis positions weakly determined: trust the
//!   covariance, not the point estimate alone.

use std::collections::BTreeMap;

use nalgebra::{
    DMatrix, DVector, Isometry3, Matrix2x3, Matrix3, Matrix3x2, Point2, Point3, Translation3, Unit,
    UnitQuaternion, Vector2, Vector3, Vector6,
};
use serde::{Deserialize, Serialize};

use crate::camera::Intrinsics;
use crate::distortion::Distortion;
use crate::so3::{self, Line, rotation_about_line};
use crate::{GeometryError, Result};

/// Which camera of the rig an observation is in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Side {
    /// The left camera (the reference camera of the rig).
    Left,
    /// The right camera.
    Right,
}

/// One image observation of a scene point.
#[derive(Clone, Copy, Debug)]
pub struct BundleObservation {
    /// Index into [`RigState::points`].
    pub point: usize,
    /// View index, `0..view_count`.
    pub view: usize,
    /// Camera of the rig.
    pub side: Side,
    /// Observed pixel.
    pub pixel: Point2<f64>,
}

/// How the views move relative to view 0.
#[derive(Clone, Debug)]
pub enum Motions {
    /// One free rigid pose per view; `ref_from_cam[0]` must be the identity.
    Free {
        /// Pose of each view's left camera in the reference frame.
        ref_from_cam: Vec<Isometry3<f64>>,
    },
    /// A chain of revolute joints, root first, given as lines in the reference frame at
    /// the reference configuration.
    Joints {
        /// Joint axes, root first.
        axes: Vec<Line>,
        /// `angles[k][j]`: angle of joint j in view k relative to view 0, radians; row 0
        /// all zeros.
        angles: Vec<Vec<f64>>,
        /// Commanded angles (same shape), the centres of the angle prior.
        commanded: Vec<Vec<f64>>,
    },
}

impl Motions {
    /// Pose of view `view`'s left camera in the reference frame (identity for an
    /// out-of-range view).
    pub fn ref_from_cam(&self, view: usize) -> Isometry3<f64> {
        match self {
            Motions::Free { ref_from_cam } => {
                ref_from_cam.get(view).copied().unwrap_or_else(Isometry3::identity)
            }
            Motions::Joints { axes, angles, .. } => match angles.get(view) {
                Some(row) => joint_pose(axes, row),
                None => Isometry3::identity(),
            },
        }
    }

    /// Number of views.
    pub fn view_count(&self) -> usize {
        match self {
            Motions::Free { ref_from_cam } => ref_from_cam.len(),
            Motions::Joints { angles, .. } => angles.len(),
        }
    }
}

/// Product of exponentials, root first.
fn joint_pose(axes: &[Line], angles: &[f64]) -> Isometry3<f64> {
    axes.iter().zip(angles).fold(Isometry3::identity(), |acc, (l, &a)| acc * rotation_about_line(l, a))
}

/// Everything the bundle adjustment estimates.
#[derive(Clone, Debug)]
pub struct RigState {
    /// Left intrinsics.
    pub left: Intrinsics,
    /// Right intrinsics.
    pub right: Intrinsics,
    /// Lens distortion of the left camera (zero: pinhole); `k1, k2` are estimated with
    /// [`BundleOptions::estimate_distortion`], everything else is held.
    pub left_distortion: Distortion,
    /// Lens distortion of the right camera.
    pub right_distortion: Distortion,
    /// Pose of the left camera in the right camera's frame.
    pub right_from_left: Isometry3<f64>,
    /// Motions of the rig.
    pub motions: Motions,
    /// Scene points in the reference frame.
    pub points: Vec<Point3<f64>>,
}

/// Robust loss on the norm of each 2D residual.
#[derive(Clone, Copy, Debug)]
pub enum RobustLoss {
    /// Plain least squares.
    None,
    /// Huber: quadratic below `scale_px`, linear above.
    Huber {
        /// Threshold, pixels.
        scale_px: f64,
    },
    /// Cauchy: `s^2/2 log(1 + r^2/s^2)`.
    Cauchy {
        /// Scale, pixels.
        scale_px: f64,
    },
}

/// The noise model behind the reported covariance (module docs, Covariance).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CovarianceModel {
    /// Independent isotropic Gaussian pixel errors of one `sigma`: `sigma^2 S^-1`.
    #[default]
    Gaussian,
    /// Cluster-robust (sandwich) estimate with each point's observations as one cluster:
    /// errors may be correlated within a point's observations and differ between points.
    PointClustered,
}

/// The error model of the commanded joint angles of [`Motions::Joints`] (module docs,
/// Parameters).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum AnglePrior {
    /// Each commanded angle is a difference of two encoder readings, the view's and view
    /// 0's, each with independent noise `angle_prior_sigma`: the angles of one joint share
    /// the reference reading's error (covariance `sigma^2 (I + 1 1^T)` over the views).
    #[default]
    ReadingDifferences,
    /// Each commanded angle has its own independent error of `angle_prior_sigma` (e.g.
    /// relative moves measured by a joint's own incremental sensor).
    Independent,
}

/// One row of the angle prior: a dimensionless residual and its derivative with respect
/// to each camera parameter it involves (`(parameter index, d residual / d parameter)`).
#[derive(Clone, Debug)]
struct PriorRow {
    entries: Vec<(usize, f64)>,
    residual: f64,
}

/// The whitened angle-prior residuals of one joint (module docs, Parameters): `errors`
/// are `theta_k - commanded_k` over the views `k >= 1` (radians), `sigma` the prior's
/// sigma (radians). Returns one dimensionless residual per error; their sum of squares is
/// the prior's chi-square `e^T C^-1 e` (`C = sigma^2 I` for [`AnglePrior::Independent`],
/// `sigma^2 (I + 1 1^T)` for [`AnglePrior::ReadingDifferences`]).
pub fn angle_prior_residuals(errors: &[f64], sigma: f64, model: AnglePrior) -> Vec<f64> {
    let beta = prior_beta(errors.len(), model);
    let sum: f64 = errors.iter().sum();
    errors.iter().map(|e| (e - beta * sum) / sigma).collect()
}

/// The prior's chi-square of a motion model under `options` (0 without a prior or for
/// [`Motions::Free`]): the sum of the squares of [`angle_prior_residuals`] over every joint.
pub fn angle_prior_chi2(motions: &Motions, options: &BundleOptions) -> f64 {
    let (Some(sigma), Motions::Joints { angles, commanded, .. }) = (options.angle_prior_sigma, motions)
    else {
        return 0.0;
    };
    let joints = angles.first().map_or(0, Vec::len);
    (0..joints)
        .map(|j| {
            let errors: Vec<f64> = angles
                .iter()
                .zip(commanded)
                .skip(1)
                .map(|(a, c)| a.get(j).copied().unwrap_or(0.0) - c.get(j).copied().unwrap_or(0.0))
                .collect();
            angle_prior_residuals(&errors, sigma, options.angle_prior).iter().map(|r| r * r).sum::<f64>()
        })
        .sum()
}

/// `beta` of the whitening `(I - beta 1 1^T)` of `m` reading differences (0 for
/// independent errors): `(I - beta 1 1^T)^2 = (I + 1 1^T)^-1` needs
/// `2 beta - m beta^2 = 1 / (m + 1)`, the root below `1 / m`.
fn prior_beta(m: usize, model: AnglePrior) -> f64 {
    match model {
        AnglePrior::Independent => 0.0,
        AnglePrior::ReadingDifferences if m == 0 => 0.0,
        AnglePrior::ReadingDifferences => (1.0 - 1.0 / ((m + 1) as f64).sqrt()) / m as f64,
    }
}

/// Options of [`bundle_adjust`].
#[derive(Clone, Debug)]
pub struct BundleOptions {
    /// Maximum number of Levenberg-Marquardt iterations (linearisations).
    pub max_iterations: usize,
    /// Robust loss.
    pub robust: RobustLoss,
    /// Hold the skews at zero.
    pub zero_skew: bool,
    /// Tie `fy = fx` in each camera.
    pub square_pixels: bool,
    /// Hold the principal points.
    pub fix_principal_point: bool,
    /// Estimate the radial distortion `k1, k2` of each camera (default off: the state's
    /// distortion, usually zero, is held).
    pub estimate_distortion: bool,
    /// Sigma of the prior on joint angles around the commanded ones, radians; `None` holds
    /// the angles at the commanded values. Under [`AnglePrior::ReadingDifferences`] (the
    /// default) it is the noise of one encoder reading.
    pub angle_prior_sigma: Option<f64>,
    /// How the commanded angles are in error (default [`AnglePrior::ReadingDifferences`]).
    pub angle_prior: AnglePrior,
    /// Pixel noise for the covariance; `None` estimates it from the residuals.
    pub noise_sigma_px: Option<f64>,
    /// How the covariance treats the residuals (module docs, Covariance). Default
    /// [`CovarianceModel::Gaussian`].
    pub covariance_model: CovarianceModel,
    /// The window `[x_min, y_min, x_max, y_max]` (pixels) outside which no measurement
    /// is reported: a detector keeps a feature only if its *measured* position is inside
    /// (for a whole image `[-0.5, -0.5, w - 0.5, h - 0.5]`), so near the border the
    /// reported measurements are pulled inward by the noise. With `noise_sigma_px` set,
    /// each residual is then taken against the expected measurement under that truncated
    /// Gaussian ([`truncated_mean_shift`]); without it, or with `None` (the default), against
    /// the projection. Module docs, Measurement window.
    pub measurement_window: Option<[f64; 4]>,
    /// Relative cost decrease below which the iteration stops.
    pub function_tolerance: f64,
    /// Relative step size below which the iteration stops.
    pub parameter_tolerance: f64,
}

impl Default for BundleOptions {
    fn default() -> Self {
        Self {
            max_iterations: 100,
            robust: RobustLoss::Huber { scale_px: 2.0 },
            zero_skew: true,
            square_pixels: false,
            fix_principal_point: false,
            estimate_distortion: false,
            angle_prior_sigma: Some(0.05_f64.to_radians()),
            angle_prior: AnglePrior::ReadingDifferences,
            noise_sigma_px: None,
            covariance_model: CovarianceModel::Gaussian,
            measurement_window: None,
            function_tolerance: 1e-12,
            parameter_tolerance: 1e-12,
        }
    }
}

impl BundleOptions {
    /// Check that every option is in range.
    pub fn validate(&self) -> Result<()> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        match self.robust {
            RobustLoss::None => {}
            RobustLoss::Huber { scale_px } | RobustLoss::Cauchy { scale_px } => {
                if !positive(scale_px) {
                    return Err(GeometryError::InvalidOption(format!(
                        "robust scale must be positive and finite, got {scale_px}"
                    )));
                }
            }
        }
        if let Some(s) = self.angle_prior_sigma
            && !positive(s)
        {
            return Err(GeometryError::InvalidOption(format!("angle_prior_sigma must be positive, got {s}")));
        }
        if let Some(s) = self.noise_sigma_px
            && !positive(s)
        {
            return Err(GeometryError::InvalidOption(format!("noise_sigma_px must be positive, got {s}")));
        }
        if let Some([x0, y0, x1, y1]) = self.measurement_window
            && !([x0, y0, x1, y1].iter().all(|v| v.is_finite()) && x0 < x1 && y0 < y1)
        {
            return Err(GeometryError::InvalidOption(format!(
                "measurement_window must be finite with min < max, got [{x0}, {y0}, {x1}, {y1}]"
            )));
        }
        for (name, v) in [
            ("function_tolerance", self.function_tolerance),
            ("parameter_tolerance", self.parameter_tolerance),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(GeometryError::InvalidOption(format!("{name} must be finite and >= 0, got {v}")));
            }
        }
        Ok(())
    }
}

/// Summary of a run.
#[derive(Clone, Debug)]
pub struct BundleReport {
    /// Linearisations performed.
    pub iterations: usize,
    /// RMS of the (unweighted) residual norms at the start, pixels.
    pub initial_rms_px: f64,
    /// RMS of the (unweighted) residual norms at the end, pixels.
    pub final_rms_px: f64,
    /// True if a tolerance (or the damping limit) stopped the iteration.
    pub converged: bool,
    /// Why the iteration stopped.
    pub termination: String,
    /// Observations used.
    pub observations: usize,
    /// Parameters estimated (camera parameters + 3 per used point).
    pub parameters: usize,
    /// Pixel noise used for the covariance (given or estimated).
    pub sigma_px: f64,
    /// Square root of the largest ratio, over the camera parameters, of the reported
    /// variance to the Gaussian model's `sigma^2 S^-1` (1 under
    /// [`CovarianceModel::Gaussian`]): how much the clustered covariance widened the
    /// sigmas.
    pub sigma_inflation: f64,
}

/// Marginal covariance of the camera (non-point) parameters.
#[derive(Clone, Debug)]
pub struct Covariance {
    /// Parameter names, in the order of the matrix.
    pub names: Vec<String>,
    /// Covariance matrix in the solver's tangent parametrisation.
    pub matrix: DMatrix<f64>,
}

impl Covariance {
    /// Index of a named parameter.
    pub fn index(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }

    /// Standard deviation of a named parameter.
    pub fn sigma(&self, name: &str) -> Option<f64> {
        let i = self.index(name)?;
        Some(self.matrix[(i, i)].max(0.0).sqrt())
    }
}

/// Output of [`bundle_adjust`].
#[derive(Clone, Debug)]
pub struct BundleResult {
    /// The refined state.
    pub state: RigState,
    /// Summary.
    pub report: BundleReport,
    /// Covariance of the camera parameters.
    pub covariance: Covariance,
}

impl BundleResult {
    /// The least-squares cost in chi-square units at pixel noise `noise_px`: the squared
    /// reprojection errors over `noise_px^2` plus the angle prior's chi-square
    /// ([`angle_prior_chi2`] under `options`), as the adjustment weighs them.
    pub fn chi2(&self, noise_px: f64, options: &BundleOptions) -> f64 {
        chi2_of(self.report.final_rms_px, self.report.observations, &self.state.motions, noise_px, options)
    }

    /// The parameters of the covariance's names.
    fn params(&self) -> Result<Vec<Param>> {
        self.covariance
            .names
            .iter()
            .map(|n| {
                Param::parse(n).ok_or_else(|| GeometryError::InvalidOption(format!("unknown parameter {n}")))
            })
            .collect()
    }

    /// The state moved by a tangent-space step `delta` over the non-point parameters (same
    /// order as `covariance.names`), points unchanged.
    /// Lets callers propagate the covariance to any derived quantity by finite differences.
    pub fn perturbed(&self, delta: &DVector<f64>) -> Result<RigState> {
        if delta.len() != self.covariance.names.len() {
            return Err(GeometryError::InvalidOption(format!(
                "delta has {} entries, the covariance {}",
                delta.len(),
                self.covariance.names.len()
            )));
        }
        let params = self.params()?;
        let layout = Layout::from_params(params, &self.state.motions)?;
        retract(&self.state, &layout, delta)
    }

    /// The tangent-space step from this result's state to `other` over the non-point
    /// parameters (same order as `covariance.names`): the inverse of
    /// [`BundleResult::perturbed`], `perturbed(tangent_offset(x)) == x` up to rounding
    /// for every state `x` of the same shape whose rotations differ by less than pi and
    /// whose directions lie in the same half-space. Lets callers take the spread of
    /// other solutions (bootstrap replicates) in the covariance's coordinates.
    pub fn tangent_offset(&self, other: &RigState) -> Result<DVector<f64>> {
        let params = self.params()?;
        local(&self.state, other, &params)
    }
}

/// The inverse of [`retract`]: the step over `params` that moves `from` to `to`.
fn local(from: &RigState, to: &RigState, params: &[Param]) -> Result<DVector<f64>> {
    let shape = || GeometryError::InvalidOption("the two states differ in shape".into());
    let line_offset = |a: &Line, b: &Line| -> Option<([f64; 2], [f64; 2])> {
        let d = a.direction.into_inner();
        let e = b.direction.into_inner();
        let basis = tangent_basis(&d);
        let along = d.dot(&e);
        if along <= 0.0 {
            return None;
        }
        let dir = basis.transpose() * e / along;
        // The point of `b` in the plane through `a.point` perpendicular to `d`.
        let s = (a.point - b.point).dot(&d) / along;
        let x = b.point + e * s;
        let pt = basis.transpose() * (x - a.point);
        Some(([dir[0], dir[1]], [pt[0], pt[1]]))
    };
    let t = from.right_from_left.translation.vector;
    let t_hat = t / t.norm();
    let u_hat = to.right_from_left.translation.vector.normalize();
    let along = t_hat.dot(&u_hat);
    let tdir = tangent_basis(&t_hat).transpose() * u_hat / along;
    let rig_rot = so3::log(
        &(to.right_from_left.rotation * from.right_from_left.rotation.inverse()).to_rotation_matrix(),
    );
    let mut out = DVector::zeros(params.len());
    for (o, p) in out.iter_mut().zip(params) {
        *o = match *p {
            Param::Intr(side, i) => {
                let (a, b) =
                    if side == Side::Left { (&from.left, &to.left) } else { (&from.right, &to.right) };
                let f = |k: &Intrinsics| [k.fx, k.fy, k.skew, k.cx, k.cy];
                f(b).get(i).copied().ok_or_else(shape)? - f(a).get(i).copied().ok_or_else(shape)?
            }
            Param::Dist(side, i) => {
                let (a, b) = if side == Side::Left {
                    (&from.left_distortion, &to.left_distortion)
                } else {
                    (&from.right_distortion, &to.right_distortion)
                };
                if i == 0 { b.k1 - a.k1 } else { b.k2 - a.k2 }
            }
            Param::RigRot(i) => rig_rot.get(i).copied().ok_or_else(shape)?,
            Param::RigTdir(i) if along > 0.0 => tdir.get(i).copied().ok_or_else(shape)?,
            Param::RigTdir(_) => return Err(shape()),
            Param::AxisDir(j, i) | Param::AxisPt(j, i) => {
                let (Motions::Joints { axes: a, .. }, Motions::Joints { axes: b, .. }) =
                    (&from.motions, &to.motions)
                else {
                    return Err(shape());
                };
                let (dir, pt) = line_offset(a.get(j).ok_or_else(shape)?, b.get(j).ok_or_else(shape)?)
                    .ok_or_else(shape)?;
                let v = if matches!(p, Param::AxisDir(..)) { dir } else { pt };
                v.get(i).copied().ok_or_else(shape)?
            }
            Param::Angle(k, j) => {
                let (Motions::Joints { angles: a, .. }, Motions::Joints { angles: b, .. }) =
                    (&from.motions, &to.motions)
                else {
                    return Err(shape());
                };
                let get = |m: &Vec<Vec<f64>>| m.get(k).and_then(|r| r.get(j)).copied().ok_or_else(shape);
                get(b)? - get(a)?
            }
            Param::ViewRot(k, i) | Param::ViewTrans(k, i) => {
                let (Motions::Free { ref_from_cam: a }, Motions::Free { ref_from_cam: b }) =
                    (&from.motions, &to.motions)
                else {
                    return Err(shape());
                };
                let step = b.get(k).ok_or_else(shape)? * a.get(k).ok_or_else(shape)?.inverse();
                let v = if matches!(p, Param::ViewRot(..)) {
                    so3::log(&step.rotation.to_rotation_matrix())
                } else {
                    step.translation.vector
                };
                v.get(i).copied().ok_or_else(shape)?
            }
        };
    }
    Ok(out)
}

/// Residual (projected - observed, pixels) of one observation; `None` if the point is
/// behind the camera or an index is out of range.
pub fn residual_pixels(state: &RigState, obs: &BundleObservation) -> Option<Vector2<f64>> {
    if obs.view >= state.motions.view_count() {
        return None;
    }
    let x = state.points.get(obs.point)?;
    residual_pixels_at(state, &state.motions.ref_from_cam(obs.view), x, obs)
}

/// [`residual_pixels`] of the point `point_in_ref` (in place of the state's point
/// `obs.point`) seen from the view pose `ref_from_cam` (the left camera of `obs.view`,
/// `state.motions.ref_from_cam(obs.view)`, computed once by a caller that evaluates many
/// observations or point positions in one view). Same arithmetic: the result is
/// bit-identical to [`residual_pixels`] for the state's own pose and point.
pub fn residual_pixels_at(
    state: &RigState,
    ref_from_cam: &Isometry3<f64>,
    point_in_ref: &Point3<f64>,
    obs: &BundleObservation,
) -> Option<Vector2<f64>> {
    let xc = ref_from_cam.inverse_transform_point(point_in_ref);
    let (k, d, xs) = match obs.side {
        Side::Left => (&state.left, &state.left_distortion, xc),
        Side::Right => (&state.right, &state.right_distortion, state.right_from_left * xc),
    };
    if d.is_zero() {
        return Some(k.project(&xs)? - obs.pixel);
    }
    if !gt(xs.z, 0.0) {
        return None;
    }
    let n = d.distort(&Vector2::new(xs.x / xs.z, xs.y / xs.z));
    Some(Vector2::new(k.fx * n.x + k.skew * n.y + k.cx - obs.pixel.x, k.fy * n.y + k.cy - obs.pixel.y))
}

// ---------------------------------------------------------------------------------------
// Parametrisation

const INTR_NAMES: [&str; 5] = ["fx", "fy", "skew", "cx", "cy"];
const DIST_NAMES: [&str; 2] = ["k1", "k2"];
const JOINT_FD_STEP: f64 = 1e-6;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Param {
    Intr(Side, usize),
    /// Radial distortion `k1` (0) or `k2` (1).
    Dist(Side, usize),
    RigRot(usize),
    RigTdir(usize),
    AxisDir(usize, usize),
    AxisPt(usize, usize),
    /// (view, axis)
    Angle(usize, usize),
    ViewRot(usize, usize),
    ViewTrans(usize, usize),
}

impl Param {
    fn name(&self) -> String {
        match *self {
            Param::Intr(side, i) => {
                let s = if side == Side::Left { "left" } else { "right" };
                format!("{s}.{}", INTR_NAMES.get(i).copied().unwrap_or("?"))
            }
            Param::Dist(side, i) => {
                let s = if side == Side::Left { "left" } else { "right" };
                format!("{s}.{}", DIST_NAMES.get(i).copied().unwrap_or("?"))
            }
            Param::RigRot(i) => format!("rig.rot{i}"),
            Param::RigTdir(i) => format!("rig.tdir{i}"),
            Param::AxisDir(j, i) => format!("axis{j}.dir{i}"),
            Param::AxisPt(j, i) => format!("axis{j}.pt{i}"),
            Param::Angle(k, j) => format!("view{k}.angle{j}"),
            Param::ViewRot(k, i) => format!("view{k}.rot{i}"),
            Param::ViewTrans(k, i) => format!("view{k}.trans{i}"),
        }
    }

    fn parse(name: &str) -> Option<Param> {
        let (head, tail) = name.split_once('.')?;
        let num = |prefix: &str| tail.strip_prefix(prefix).and_then(|s| s.parse::<usize>().ok());
        match head {
            "left" | "right" => {
                let side = if head == "left" { Side::Left } else { Side::Right };
                INTR_NAMES
                    .iter()
                    .position(|n| *n == tail)
                    .map(|i| Param::Intr(side, i))
                    .or_else(|| DIST_NAMES.iter().position(|n| *n == tail).map(|i| Param::Dist(side, i)))
            }
            "rig" => num("rot").map(Param::RigRot).or_else(|| num("tdir").map(Param::RigTdir)),
            _ => {
                if let Some(j) = head.strip_prefix("axis").and_then(|s| s.parse::<usize>().ok()) {
                    num("dir")
                        .map(|i| Param::AxisDir(j, i))
                        .or_else(|| num("pt").map(|i| Param::AxisPt(j, i)))
                } else if let Some(k) = head.strip_prefix("view").and_then(|s| s.parse::<usize>().ok()) {
                    num("angle")
                        .map(|j| Param::Angle(k, j))
                        .or_else(|| num("rot").map(|i| Param::ViewRot(k, i)))
                        .or_else(|| num("trans").map(|i| Param::ViewTrans(k, i)))
                } else {
                    None
                }
            }
        }
    }
}

/// Where each parameter sits in the camera-parameter vector.
#[derive(Clone, Debug)]
struct Layout {
    params: Vec<Param>,
    intr: [[Option<usize>; 5]; 2],
    dist: [[Option<usize>; 2]; 2],
    square: [bool; 2],
    rig_rot: [Option<usize>; 3],
    rig_tdir: [Option<usize>; 2],
    axis_dir: Vec<[Option<usize>; 2]>,
    axis_pt: Vec<[Option<usize>; 2]>,
    angle: Vec<Vec<Option<usize>>>,
    view_rot: Vec<[Option<usize>; 3]>,
    view_trans: Vec<[Option<usize>; 3]>,
}

fn side_index(s: Side) -> usize {
    match s {
        Side::Left => 0,
        Side::Right => 1,
    }
}

impl Layout {
    fn build(state: &RigState, options: &BundleOptions) -> Result<Self> {
        let mut p = Vec::new();
        for side in [Side::Left, Side::Right] {
            p.push(Param::Intr(side, 0));
            if !options.square_pixels {
                p.push(Param::Intr(side, 1));
            }
            if !options.zero_skew {
                p.push(Param::Intr(side, 2));
            }
            if !options.fix_principal_point {
                p.push(Param::Intr(side, 3));
                p.push(Param::Intr(side, 4));
            }
            if options.estimate_distortion {
                p.extend((0..2).map(|i| Param::Dist(side, i)));
            }
        }
        p.extend((0..3).map(Param::RigRot));
        p.extend((0..2).map(Param::RigTdir));
        let v = state.motions.view_count();
        match &state.motions {
            Motions::Free { .. } => {
                for k in 1..v {
                    p.extend((0..3).map(|i| Param::ViewRot(k, i)));
                    p.extend((0..3).map(|i| Param::ViewTrans(k, i)));
                }
            }
            Motions::Joints { axes, .. } => {
                for j in 0..axes.len() {
                    p.extend((0..2).map(|i| Param::AxisDir(j, i)));
                    p.extend((0..2).map(|i| Param::AxisPt(j, i)));
                }
                if options.angle_prior_sigma.is_some() {
                    for k in 1..v {
                        p.extend((0..axes.len()).map(|j| Param::Angle(k, j)));
                    }
                }
            }
        }
        Self::from_params(p, &state.motions)
    }

    fn from_params(params: Vec<Param>, motions: &Motions) -> Result<Self> {
        let n_views = motions.view_count();
        let n_axes = match motions {
            Motions::Joints { axes, .. } => axes.len(),
            Motions::Free { .. } => 0,
        };
        let free = matches!(motions, Motions::Free { .. });
        let mut l = Layout {
            params: Vec::new(),
            intr: [[None; 5]; 2],
            dist: [[None; 2]; 2],
            square: [false; 2],
            rig_rot: [None; 3],
            rig_tdir: [None; 2],
            axis_dir: vec![[None; 2]; n_axes],
            axis_pt: vec![[None; 2]; n_axes],
            angle: vec![vec![None; n_axes]; n_views],
            view_rot: vec![[None; 3]; n_views],
            view_trans: vec![[None; 3]; n_views],
        };
        let bad = |p: &Param| {
            GeometryError::InvalidOption(format!("parameter {} does not fit the state", p.name()))
        };
        for (idx, p) in params.iter().enumerate() {
            let slot: Option<&mut Option<usize>> = match *p {
                Param::Intr(s, i) => l.intr[side_index(s)].get_mut(i),
                Param::Dist(s, i) => l.dist[side_index(s)].get_mut(i),
                Param::RigRot(i) => l.rig_rot.get_mut(i),
                Param::RigTdir(i) => l.rig_tdir.get_mut(i),
                Param::AxisDir(j, i) => l.axis_dir.get_mut(j).and_then(|a| a.get_mut(i)),
                Param::AxisPt(j, i) => l.axis_pt.get_mut(j).and_then(|a| a.get_mut(i)),
                Param::Angle(k, j) if k >= 1 => l.angle.get_mut(k).and_then(|a| a.get_mut(j)),
                Param::ViewRot(k, i) if k >= 1 && free => l.view_rot.get_mut(k).and_then(|a| a.get_mut(i)),
                Param::ViewTrans(k, i) if k >= 1 && free => {
                    l.view_trans.get_mut(k).and_then(|a| a.get_mut(i))
                }
                _ => None,
            };
            match slot {
                Some(s) if s.is_none() => *s = Some(idx),
                _ => return Err(bad(p)),
            }
        }
        for s in 0..2 {
            l.square[s] = l.intr[s][0].is_some() && l.intr[s][1].is_none();
        }
        l.params = params;
        Ok(l)
    }

    fn len(&self) -> usize {
        self.params.len()
    }

    fn names(&self) -> Vec<String> {
        self.params.iter().map(Param::name).collect()
    }
}

/// Orthonormal basis (3x2) of the plane perpendicular to the unit vector `d`.
fn tangent_basis(d: &Vector3<f64>) -> Matrix3x2<f64> {
    let a = if d.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
    let b1 = (a - d * d.dot(&a)).normalize();
    let b2 = d.cross(&b1);
    Matrix3x2::from_columns(&[b1, b2])
}

fn quat_exp(w: &Vector3<f64>) -> UnitQuaternion<f64> {
    UnitQuaternion::from_rotation_matrix(&so3::exp(w))
}

fn comp<const N: usize>(idx: &[Option<usize>; N], delta: &DVector<f64>) -> [f64; N] {
    let mut out = [0.0; N];
    for (o, i) in out.iter_mut().zip(idx) {
        if let Some(i) = i {
            *o = delta.get(*i).copied().unwrap_or(0.0);
        }
    }
    out
}

fn retract_line(line: &Line, a: [f64; 2], b: [f64; 2]) -> Line {
    let d = line.direction.into_inner();
    let basis = tangent_basis(&d);
    let dir = Unit::new_normalize(d + basis * Vector2::new(a[0], a[1]));
    let pt = line.point + basis * Vector2::new(b[0], b[1]);
    Line::new(dir, pt)
}

/// The state moved by a step over the camera parameters (points unchanged).
fn retract(state: &RigState, layout: &Layout, delta: &DVector<f64>) -> Result<RigState> {
    let mut out = state.clone();
    for (s, k) in [(0, &mut out.left), (1, &mut out.right)] {
        let d = comp(&layout.intr[s], delta);
        k.fx += d[0];
        k.fy += d[1];
        k.skew += d[2];
        k.cx += d[3];
        k.cy += d[4];
        if layout.square[s] {
            k.fy = k.fx;
        }
    }
    for (s, d) in [(0, &mut out.left_distortion), (1, &mut out.right_distortion)] {
        let c = comp(&layout.dist[s], delta);
        d.k1 += c[0];
        d.k2 += c[1];
    }
    let w = comp(&layout.rig_rot, delta);
    let td = comp(&layout.rig_tdir, delta);
    let t = state.right_from_left.translation.vector;
    let n = t.norm();
    let t_hat = t / n;
    let t_new = (t_hat + tangent_basis(&t_hat) * Vector2::new(td[0], td[1])).normalize() * n;
    out.right_from_left = Isometry3::from_parts(
        Translation3::from(t_new),
        quat_exp(&Vector3::new(w[0], w[1], w[2])) * state.right_from_left.rotation,
    );
    match &mut out.motions {
        Motions::Free { ref_from_cam } => {
            for (k, pose) in ref_from_cam.iter_mut().enumerate() {
                let (Some(ri), Some(ti)) = (layout.view_rot.get(k), layout.view_trans.get(k)) else {
                    continue;
                };
                let w = comp(ri, delta);
                let v = comp(ti, delta);
                let step = Isometry3::from_parts(
                    Translation3::new(v[0], v[1], v[2]),
                    quat_exp(&Vector3::new(w[0], w[1], w[2])),
                );
                *pose = step * *pose;
            }
        }
        Motions::Joints { axes, angles, .. } => {
            for (j, axis) in axes.iter_mut().enumerate() {
                let (Some(di), Some(pi)) = (layout.axis_dir.get(j), layout.axis_pt.get(j)) else {
                    continue;
                };
                *axis = retract_line(axis, comp(di, delta), comp(pi, delta));
            }
            for (k, row) in angles.iter_mut().enumerate() {
                for (j, a) in row.iter_mut().enumerate() {
                    if let Some(Some(i)) = layout.angle.get(k).and_then(|r| r.get(j)) {
                        *a += delta.get(*i).copied().unwrap_or(0.0);
                    }
                }
            }
        }
    }
    Ok(out)
}

// ---------------------------------------------------------------------------------------
// Linearisation

/// Predictions farther than this many sigmas outside a measurement window get the shift
/// of this distance (the expectation's limit is the border itself; beyond it the ratio of
/// two vanishing probabilities is not computed).
const WINDOW_CLAMP_SIGMAS: f64 = 4.0;

/// Predictions farther than this many sigmas inside both borders of a window are not
/// shifted (the shift is below `7e-9` sigma there, and the test is all that most
/// observations cost).
const WINDOW_REACH_SIGMAS: f64 = 6.0;

/// The standard normal cumulative distribution `Phi(t) = erfc(-t / sqrt 2) / 2` (`libm`'s
/// `erfc`, accurate to rounding: the residual and its analytic derivative must agree).
fn normal_cdf(t: f64) -> f64 {
    0.5 * libm::erfc(-t / std::f64::consts::SQRT_2)
}

/// The standard normal density.
fn normal_pdf(t: f64) -> f64 {
    (-0.5 * t * t).exp() / (2.0 * std::f64::consts::PI).sqrt()
}

/// Shift of the expected measurement from the prediction `mu` when Gaussian noise of
/// `sigma` is added and only measurements in `[lo, hi]` are reported, and its derivative
/// with respect to `mu`: with `a = (lo - mu) / sigma`, `b = (hi - mu) / sigma` and
/// `Z = Phi(b) - Phi(a)`, `shift = sigma (phi(a) - phi(b)) / Z` and
/// `d shift / d mu = (a phi(a) - b phi(b)) / Z - (shift / sigma)^2` (so `1 + d shift / d mu`
/// is the truncated variance over `sigma^2`, in `(0, 1]`). `(0, 0)` more than
/// `WINDOW_REACH_SIGMAS` inside both borders; for a prediction more than
/// `WINDOW_CLAMP_SIGMAS` outside, the shift at that distance is held (derivative 0), so
/// the expected measurement follows the prediction there and such an observation still
/// pulls its point back towards the window.
#[inline]
pub fn truncated_mean_shift(mu: f64, lo: f64, hi: f64, sigma: f64) -> (f64, f64) {
    if !(gt(sigma, 0.0) && mu.is_finite() && lo < hi) {
        return (0.0, 0.0);
    }
    if mu - lo > WINDOW_REACH_SIGMAS * sigma && hi - mu > WINDOW_REACH_SIGMAS * sigma {
        return (0.0, 0.0);
    }
    let (lo_c, hi_c) = (lo - WINDOW_CLAMP_SIGMAS * sigma, hi + WINDOW_CLAMP_SIGMAS * sigma);
    let clamped = mu < lo_c || mu > hi_c;
    let m = mu.clamp(lo_c, hi_c);
    let a = (lo - m) / sigma;
    let b = (hi - m) / sigma;
    let z = normal_cdf(b) - normal_cdf(a);
    if !gt(z, 0.0) {
        return (0.0, 0.0);
    }
    let (pa, pb) = (normal_pdf(a), normal_pdf(b));
    let ratio = (pa - pb) / z;
    let slope = if clamped { 0.0 } else { (a * pa - b * pb) / z - ratio * ratio };
    (sigma * ratio, slope)
}

/// Per-view geometry and the pose-tangent Jacobian columns `(param index, d xi / d param)`.
struct ViewGeom {
    /// `cam_from_ref` rotation.
    rt: Matrix3<f64>,
    /// `ref_from_cam` translation.
    t: Vector3<f64>,
    cols: Vec<(usize, Vector6<f64>)>,
}

/// Left-multiplicative tangent `(w, v)` with `b = (exp(w), v) * a`.
fn pose_tangent(b: &Isometry3<f64>, a: &Isometry3<f64>) -> Vector6<f64> {
    let dr = b.rotation * a.rotation.inverse();
    let w = dr.scaled_axis();
    let v = b.translation.vector - dr * a.translation.vector;
    Vector6::new(w.x, w.y, w.z, v.x, v.y, v.z)
}

fn view_geoms(state: &RigState, layout: &Layout, with_jac: bool) -> Vec<ViewGeom> {
    let n_views = state.motions.view_count();
    let mut out = Vec::with_capacity(n_views);
    for k in 0..n_views {
        let pose = state.motions.ref_from_cam(k);
        let mut cols = Vec::new();
        if with_jac && k >= 1 {
            match &state.motions {
                Motions::Free { .. } => {
                    let ri = layout.view_rot.get(k).copied().unwrap_or([None; 3]);
                    let ti = layout.view_trans.get(k).copied().unwrap_or([None; 3]);
                    for (i, idx) in ri.iter().chain(ti.iter()).enumerate() {
                        if let Some(idx) = idx {
                            let mut g = Vector6::zeros();
                            g[i] = 1.0;
                            cols.push((*idx, g));
                        }
                    }
                }
                Motions::Joints { axes, angles, .. } => {
                    let row = angles.get(k).cloned().unwrap_or_default();
                    let h = JOINT_FD_STEP;
                    let fd = |f: &dyn Fn(f64) -> Isometry3<f64>| {
                        (pose_tangent(&f(h), &pose) - pose_tangent(&f(-h), &pose)) / (2.0 * h)
                    };
                    for j in 0..axes.len() {
                        let di = layout.axis_dir.get(j).copied().unwrap_or([None; 2]);
                        let pi = layout.axis_pt.get(j).copied().unwrap_or([None; 2]);
                        for c in 0..4 {
                            let idx = if c < 2 { di[c] } else { pi[c - 2] };
                            let Some(idx) = idx else { continue };
                            let g = fd(&|e| {
                                let mut a = [0.0; 2];
                                let mut b = [0.0; 2];
                                if c < 2 {
                                    a[c] = e;
                                } else {
                                    b[c - 2] = e;
                                }
                                let mut ax = axes.clone();
                                if let Some(l) = ax.get_mut(j) {
                                    *l = retract_line(l, a, b);
                                }
                                joint_pose(&ax, &row)
                            });
                            cols.push((idx, g));
                        }
                        if let Some(Some(idx)) = layout.angle.get(k).and_then(|r| r.get(j)) {
                            let g = fd(&|e| {
                                let mut r = row.clone();
                                if let Some(a) = r.get_mut(j) {
                                    *a += e;
                                }
                                joint_pose(axes, &r)
                            });
                            cols.push((*idx, g));
                        }
                    }
                }
            }
        }
        out.push(ViewGeom {
            rt: pose.rotation.to_rotation_matrix().into_inner().transpose(),
            t: pose.translation.vector,
            cols,
        });
    }
    out
}

/// Rig quantities shared by all observations.
struct RigGeom {
    r: Matrix3<f64>,
    t: Vector3<f64>,
    /// `|t| * tangent_basis(t/|t|)`.
    tdir: Matrix3x2<f64>,
}

fn rig_geom(state: &RigState) -> RigGeom {
    let t = state.right_from_left.translation.vector;
    let n = t.norm();
    RigGeom {
        r: state.right_from_left.rotation.to_rotation_matrix().into_inner(),
        t,
        tdir: tangent_basis(&(t / n)) * n,
    }
}

/// Residual and, if `cols` is given, the Jacobians of one observation: returns
/// `(residual, d residual / d point)` and fills `cols` with `(param index, column)`;
/// without `cols` the point Jacobian returned is zero (not computed).
#[allow(clippy::too_many_arguments)]
fn linearise_obs(
    state: &RigState,
    layout: &Layout,
    views: &[ViewGeom],
    rig: &RigGeom,
    obs: &BundleObservation,
    x: &Point3<f64>,
    cols: Option<&mut Vec<(usize, Vector2<f64>)>>,
) -> Option<(Vector2<f64>, Matrix2x3<f64>)> {
    let view = views.get(obs.view)?;
    let xc = view.rt * (x.coords - view.t);
    let (k, dist, xs, dxs) = match obs.side {
        Side::Left => (&state.left, &state.left_distortion, xc, Matrix3::identity()),
        Side::Right => (&state.right, &state.right_distortion, rig.r * xc + rig.t, rig.r),
    };
    if !gt(xs.z, 0.0) {
        return None;
    }
    let iz = 1.0 / xs.z;
    let (a, b, jproj) = if dist.is_zero() {
        // Pinhole: kept exactly as before distortion existed (bit-identical results).
        let a = xs.x * iz;
        let b = xs.y * iz;
        let jproj = Matrix2x3::new(
            k.fx * iz,
            k.skew * iz,
            -(k.fx * a + k.skew * b) * iz,
            0.0,
            k.fy * iz,
            -k.fy * b * iz,
        );
        (a, b, jproj)
    } else {
        // pixel = K2 distort(pi(xs)): d pixel / d xs = K2 J_dist d pi / d xs.
        let (n, jd) = dist.distort_with_jacobian(&Vector2::new(xs.x * iz, xs.y * iz));
        let k2 = nalgebra::Matrix2::new(k.fx, k.skew, 0.0, k.fy);
        let dpi = Matrix2x3::new(iz, 0.0, -xs.x * iz * iz, 0.0, iz, -xs.y * iz * iz);
        (n.x, n.y, k2 * jd * dpi)
    };
    let r = Vector2::new(k.fx * a + k.skew * b + k.cx - obs.pixel.x, k.fy * b + k.cy - obs.pixel.y);
    let Some(cols) = cols else {
        // The residual alone (cost evaluations): no Jacobian.
        return Some((r, Matrix2x3::zeros()));
    };
    let jpoint = jproj * dxs * view.rt;
    // Point Jacobian in the homogeneous tangent parametrisation (see `retract_point`):
    // h = (X, 1) / |(X, 1)|, d residual / d h = [jpoint, d/dw] / w, then times the basis.
    let h = point_homogeneous(x);
    let side_t = if obs.side == Side::Right { rig.t } else { Vector3::zeros() };
    let jw = jproj * (dxs * (-(view.rt * view.t)) + side_t);
    let mut j4 = nalgebra::Matrix2x4::zeros();
    j4.fixed_view_mut::<2, 3>(0, 0).copy_from(&jpoint);
    j4.set_column(3, &jw);
    let jhom = j4 * homogeneous_basis(&h) / h.w;
    cols.clear();
    let s = side_index(obs.side);
    let intr = &layout.intr[s];
    let dk = [
        if layout.square[s] { Vector2::new(a, b) } else { Vector2::new(a, 0.0) },
        Vector2::new(0.0, b),
        Vector2::new(b, 0.0),
        Vector2::new(1.0, 0.0),
        Vector2::new(0.0, 1.0),
    ];
    for (idx, d) in intr.iter().zip(dk) {
        if let Some(idx) = idx {
            cols.push((*idx, d));
        }
    }
    let didx = &layout.dist[s];
    if didx.iter().any(Option::is_some) {
        // d distort / d k1 = x r^2, d / d k2 = x r^4 (x the undistorted normalised point).
        let (u, v) = (xs.x * iz, xs.y * iz);
        let r2 = u * u + v * v;
        for (idx, m) in didx.iter().zip([r2, r2 * r2]) {
            if let Some(idx) = idx {
                cols.push((*idx, Vector2::new((k.fx * u + k.skew * v) * m, k.fy * v * m)));
            }
        }
    }
    if obs.side == Side::Right {
        let jrot = jproj * (-so3::skew(&(rig.r * xc)));
        for (i, idx) in layout.rig_rot.iter().enumerate() {
            if let Some(idx) = idx {
                cols.push((*idx, jrot.column(i).into_owned()));
            }
        }
        let jt = jproj * rig.tdir;
        for (i, idx) in layout.rig_tdir.iter().enumerate() {
            if let Some(idx) = idx {
                cols.push((*idx, jt.column(i).into_owned()));
            }
        }
    }
    if !view.cols.is_empty() {
        // d xc / d(w, v) = [R^T [X]x, -R^T]
        let jw = jpoint * so3::skew(&x.coords);
        for (idx, g) in &view.cols {
            let gw = Vector3::new(g[0], g[1], g[2]);
            let gv = Vector3::new(g[3], g[4], g[5]);
            cols.push((*idx, jw * gw - jpoint * gv));
        }
    }
    Some((r, jhom))
}

/// The unit homogeneous 4-vector `(X, 1) / |(X, 1)|` of a point (its `w` is positive).
fn point_homogeneous(x: &Point3<f64>) -> nalgebra::Vector4<f64> {
    nalgebra::Vector4::new(x.x, x.y, x.z, 1.0).normalize()
}

/// Orthonormal 4x3 basis of the tangent space of the unit sphere at `h` (`h.w > 0`): the
/// first three columns of the Householder reflection that maps `h` to `-e4`.
fn homogeneous_basis(h: &nalgebra::Vector4<f64>) -> nalgebra::Matrix4x3<f64> {
    let v = h + nalgebra::Vector4::w();
    let house = nalgebra::Matrix4::identity() - v * v.transpose() * (2.0 / v.norm_squared());
    house.fixed_view::<4, 3>(0, 0).into_owned()
}

/// A point moved by a homogeneous tangent step: `h <- normalize(h + B d)`, back to
/// Euclidean. Points are updated on the sphere of homogeneous 4-vectors (Triggs et al.
/// section 2.2) because depth along a ray is then nearly linear in the parameters (it
/// enters the disparity through `w`), which keeps Gauss-Newton steps good for far
/// points. `None` if the step would take the point to or through infinity.
fn retract_point(x: &Point3<f64>, d: &Vector3<f64>) -> Option<Point3<f64>> {
    let h = point_homogeneous(x);
    let h2 = (h + homogeneous_basis(&h) * d).normalize();
    if !gt(h2.w, 1e-12) {
        return None;
    }
    let p = Point3::new(h2.x / h2.w, h2.y / h2.w, h2.z / h2.w);
    p.coords.iter().all(|v| v.is_finite()).then_some(p)
}

/// `(rho(s), weight = rho'(s)/s)` for a squared residual norm `s2`.
fn robust(loss: RobustLoss, s2: f64) -> (f64, f64) {
    match loss {
        RobustLoss::None => (0.5 * s2, 1.0),
        RobustLoss::Huber { scale_px: k } => {
            let s = s2.sqrt();
            if s <= k { (0.5 * s2, 1.0) } else { (k * s - 0.5 * k * k, k / s) }
        }
        RobustLoss::Cauchy { scale_px: k } => {
            let q = s2 / (k * k);
            (0.5 * k * k * q.ln_1p(), 1.0 / (1.0 + q))
        }
    }
}

/// The problem after filtering: used observations and points.
struct Problem<'a> {
    layout: Layout,
    obs: Vec<BundleObservation>,
    /// Compact point index of each used observation.
    obs_point: Vec<usize>,
    /// Original index of each used point.
    points: Vec<usize>,
    options: &'a BundleOptions,
    /// Weight of the angle prior relative to pixels (`sigma_px^2`).
    prior_weight: f64,
    /// The depth-scale constraint `(target, tolerance)` of [`bundle_adjust_at_depth_scale`].
    depth: Option<(f64, f64)>,
}

struct Eval {
    cost: f64,
    sum_sq: f64,
}

struct Normal {
    u: DMatrix<f64>,
    gc: DVector<f64>,
    v: Vec<Matrix3<f64>>,
    gp: Vec<Vector3<f64>>,
    /// `W`, camera parameters x points: point `p`'s block is columns `3p..3p+3`.
    w: DMatrix<f64>,
    sum_wsq: f64,
    /// The depth-scale pseudo-residual: its Jacobian row over the points (compact order)
    /// and its value; its rank-one normal term is applied in [`solve`] (Sherman-Morrison).
    depth: Option<(Vec<Vector3<f64>>, f64)>,
}

impl Problem<'_> {
    /// [`linearise_obs`] with the measurement window applied (module docs, Measurement
    /// window): the residual against the expected measurement, each image axis's Jacobian
    /// row scaled by the derivative of that expectation.
    fn observe(
        &self,
        state: &RigState,
        views: &[ViewGeom],
        rig: &RigGeom,
        obs: &BundleObservation,
        x: &Point3<f64>,
        mut cols: Option<&mut Vec<(usize, Vector2<f64>)>>,
    ) -> Option<(Vector2<f64>, Matrix2x3<f64>)> {
        let (mut r, mut jp) = linearise_obs(state, &self.layout, views, rig, obs, x, cols.as_deref_mut())?;
        let (Some([x0, y0, x1, y1]), Some(sigma)) =
            (self.options.measurement_window, self.options.noise_sigma_px)
        else {
            return Some((r, jp));
        };
        for (axis, (lo, hi)) in [(x0, x1), (y0, y1)].into_iter().enumerate() {
            let predicted = r[axis] + obs.pixel[axis];
            let (shift, slope) = truncated_mean_shift(predicted, lo, hi, sigma);
            if shift == 0.0 && slope == 0.0 {
                continue;
            }
            r[axis] += shift;
            let scale = 1.0 + slope;
            for c in 0..3 {
                jp[(axis, c)] *= scale;
            }
            if let Some(cols) = cols.as_deref_mut() {
                for (_, j) in cols.iter_mut() {
                    j[axis] *= scale;
                }
            }
        }
        Some((r, jp))
    }
    fn prior_terms(&self, state: &RigState) -> Vec<PriorRow> {
        let mut out = Vec::new();
        let (Some(sigma), Motions::Joints { angles, commanded, .. }) =
            (self.options.angle_prior_sigma, &state.motions)
        else {
            return out;
        };
        let joints = self.layout.angle.iter().map(Vec::len).max().unwrap_or(0);
        for j in 0..joints {
            // The free angles of joint j: (parameter index, theta - commanded).
            let free: Vec<(usize, f64)> = self
                .layout
                .angle
                .iter()
                .enumerate()
                .filter_map(|(k, row)| {
                    let idx = (*row.get(j)?)?;
                    let a = angles.get(k).and_then(|r| r.get(j)).copied().unwrap_or(0.0);
                    let c = commanded.get(k).and_then(|r| r.get(j)).copied().unwrap_or(0.0);
                    Some((idx, a - c))
                })
                .collect();
            let errors: Vec<f64> = free.iter().map(|f| f.1).collect();
            let residuals = angle_prior_residuals(&errors, sigma, self.options.angle_prior);
            let beta = prior_beta(free.len(), self.options.angle_prior);
            for (i, residual) in residuals.into_iter().enumerate() {
                let entries = free
                    .iter()
                    .enumerate()
                    .map(|(l, f)| (f.0, (if i == l { 1.0 } else { 0.0 } - beta) / sigma))
                    .collect();
                out.push(PriorRow { entries, residual });
            }
        }
        out
    }

    fn evaluate(&self, state: &RigState) -> Option<Eval> {
        let views = view_geoms(state, &self.layout, false);
        let rig = rig_geom(state);
        let mut cost = 0.0;
        let mut sum_sq = 0.0;
        for (o, &p) in self.obs.iter().zip(&self.obs_point) {
            let x = state.points.get(*self.points.get(p)?)?;
            let (r, _) = self.observe(state, &views, &rig, o, x, None)?;
            let s2 = r.norm_squared();
            cost += robust(self.options.robust, s2).0;
            sum_sq += s2;
        }
        for row in self.prior_terms(state) {
            cost += 0.5 * self.prior_weight * row.residual * row.residual;
        }
        if let Some((target, tol)) = self.depth {
            let r = (log_depth_scale_of(state, &self.points)? - target) / tol;
            cost += 0.5 * r * r;
        }
        (cost.is_finite()).then_some(Eval { cost, sum_sq })
    }

    fn residual_norms(&self, state: &RigState) -> Option<Vec<f64>> {
        let views = view_geoms(state, &self.layout, false);
        let rig = rig_geom(state);
        let mut out = Vec::with_capacity(self.obs.len());
        for (o, &p) in self.obs.iter().zip(&self.obs_point) {
            let x = state.points.get(*self.points.get(p)?)?;
            out.push(self.observe(state, &views, &rig, o, x, None)?.0.norm());
        }
        Some(out)
    }

    /// Per point: the gradient of its observations' squared residuals with respect to the
    /// camera parameters (`sum w J_c^T r`) and to the point (`sum w J_p^T r`), pixels.
    fn point_scores(&self, state: &RigState) -> Option<Vec<(DVector<f64>, Vector3<f64>)>> {
        let nc = self.layout.len();
        let views = view_geoms(state, &self.layout, true);
        let rig = rig_geom(state);
        let mut out = vec![(DVector::zeros(nc), Vector3::zeros()); self.points.len()];
        let mut cols = Vec::with_capacity(32);
        for (o, &p) in self.obs.iter().zip(&self.obs_point) {
            let x = state.points.get(*self.points.get(p)?)?;
            let (r, jp) = self.observe(state, &views, &rig, o, x, Some(&mut cols))?;
            let wt = robust(self.options.robust, r.norm_squared()).1;
            let (gc, gp) = out.get_mut(p)?;
            *gp += jp.transpose() * r * wt;
            for &(a, ja) in &cols {
                gc[a] += wt * ja.dot(&r);
            }
        }
        Some(out)
    }

    fn normal_equations(&self, state: &RigState, prior_weight: f64) -> Option<Normal> {
        let nc = self.layout.len();
        let np = self.points.len();
        let views = view_geoms(state, &self.layout, true);
        let rig = rig_geom(state);
        let mut n = Normal {
            u: DMatrix::zeros(nc, nc),
            gc: DVector::zeros(nc),
            v: vec![Matrix3::zeros(); np],
            gp: vec![Vector3::zeros(); np],
            w: DMatrix::zeros(nc, 3 * np),
            sum_wsq: 0.0,
            depth: None,
        };
        if let Some((target, tol)) = self.depth {
            let r = (log_depth_scale_of(state, &self.points)? - target) / tol;
            let row = log_depth_scale_jacobian(state, &self.points)?;
            n.depth = Some((row.into_iter().map(|a| a / tol).collect(), r));
        }
        // Every observation of one (view, side) pair has the same camera-parameter
        // columns in the same order (they follow from the layout, the side and the view
        // alone), so the pair's weighted Jacobian rows are stacked densely over that list
        // and its share of `U` is one matrix product, scattered once at the end.
        let mut blocks: Vec<Option<CameraBlock>> = (0..2 * views.len()).map(|_| None).collect();
        let mut cols = Vec::with_capacity(32);
        for (o, &p) in self.obs.iter().zip(&self.obs_point) {
            let x = state.points.get(*self.points.get(p)?)?;
            let (r, jp) = self.observe(state, &views, &rig, o, x, Some(&mut cols))?;
            let s2 = r.norm_squared();
            let wt = robust(self.options.robust, s2).1;
            n.sum_wsq += wt * s2;
            let jpw = jp * wt;
            *n.v.get_mut(p)? += jp.transpose() * jpw;
            *n.gp.get_mut(p)? += jpw.transpose() * r;
            let block = blocks.get_mut(2 * o.view + side_index(o.side))?.get_or_insert_with(|| CameraBlock {
                idx: cols.iter().map(|c| c.0).collect(),
                rows: Vec::new(),
            });
            if !block.idx.iter().eq(cols.iter().map(|c| &c.0)) {
                return None;
            }
            let sw = wt.sqrt();
            block.rows.extend(cols.iter().map(|c| c.1.x * sw));
            block.rows.extend(cols.iter().map(|c| c.1.y * sw));
            for &(a, ja) in &cols {
                n.gc[a] += wt * ja.dot(&r);
                let wrow = ja.transpose() * jpw;
                for c in 0..3 {
                    n.w[(a, 3 * p + c)] += wrow[c];
                }
            }
        }
        for block in blocks.into_iter().flatten() {
            let k = block.idx.len();
            // The row-major rows of `sqrt(w) J` are the columns of its transpose.
            let jt = DMatrix::from_vec(k, block.rows.len() / k.max(1), block.rows);
            let h = &jt * jt.transpose();
            for (i, &a) in block.idx.iter().enumerate() {
                for (j, &b) in block.idx.iter().enumerate() {
                    n.u[(a, b)] += h[(i, j)];
                }
            }
        }
        for row in self.prior_terms(state) {
            for &(a, da) in &row.entries {
                n.gc[a] += prior_weight * row.residual * da;
                for &(b, db) in &row.entries {
                    n.u[(a, b)] += prior_weight * da * db;
                }
            }
        }
        Some(n)
    }
}

/// The camera-parameter Jacobian of the observations of one (view, side) pair: their
/// parameter indices in column order and the rows of `sqrt(w) J`, row-major (two per
/// observation).
struct CameraBlock {
    idx: Vec<usize>,
    rows: Vec<f64>,
}

/// `S` and the points' `L_p^-1` (see [`reduced_camera_system`]).
type ReducedSystem = (DMatrix<f64>, Vec<Option<Matrix3<f64>>>);

/// The reduced camera system `S = U - W V^-1 W^T` of `n` with every point block `V_p`
/// (and `U`'s diagonal) damped by `damp` of its diagonal, as one product `S = U - M M^T`
/// with `M_p = W_p L_p^-T` (`V_p = L_p L_p^T`). Per point its `L_p^-1`, or `None` for a
/// block that is not positive definite: such a point is left out when `skip_singular`,
/// otherwise the whole system is `None`.
fn reduced_camera_system(
    n: &Normal,
    damp: impl Fn(f64) -> f64,
    skip_singular: bool,
) -> Option<ReducedSystem> {
    let nc = n.u.nrows();
    let mut m = DMatrix::zeros(nc, n.w.ncols());
    let mut l_inv = Vec::with_capacity(n.v.len());
    for (p, v) in n.v.iter().enumerate() {
        let mut vd = *v;
        for i in 0..3 {
            vd[(i, i)] += damp(v[(i, i)]);
        }
        let li = vd.cholesky().and_then(|ch| ch.l().try_inverse());
        let Some(li) = li else {
            if skip_singular {
                l_inv.push(None);
                continue;
            }
            return None;
        };
        m.columns_mut(3 * p, 3).gemm(1.0, &n.w.columns(3 * p, 3), &li.transpose(), 0.0);
        l_inv.push(Some(li));
    }
    let mut s = n.u.clone();
    for i in 0..nc {
        s[(i, i)] += damp(n.u[(i, i)]);
    }
    s.gemm(-1.0, &m, &m.transpose(), 1.0);
    Some((0.5 * (&s + s.transpose()), l_inv))
}

/// Solve the damped normal equations by the Schur complement over the points; with a
/// depth-scale pseudo-residual `r_s` (Jacobian `a`, points only) the normal matrix gains
/// the dense rank-one term `a a^T` and the gradient `a r_s`, solved by Sherman-Morrison:
/// `x = y - z (a.y) / (1 + a.z)` with `N y = -g - a r_s`, `N z = a`.
fn solve(n: &Normal, lambda: f64) -> Option<(DVector<f64>, Vec<Vector3<f64>>)> {
    let rc = -&n.gc;
    let Some((a, r)) = &n.depth else {
        let rp: Vec<Vector3<f64>> = n.gp.iter().map(|g| -g).collect();
        return solve_rhs(n, lambda, &rc, &rp);
    };
    let rp: Vec<Vector3<f64>> = n.gp.iter().zip(a).map(|(g, ai)| -g - ai * *r).collect();
    let (yc, yp) = solve_rhs(n, lambda, &rc, &rp)?;
    let (zc, zp) = solve_rhs(n, lambda, &DVector::zeros(rc.len()), a)?;
    let ay: f64 = a.iter().zip(&yp).map(|(ai, y)| ai.dot(y)).sum();
    let az: f64 = a.iter().zip(&zp).map(|(ai, z)| ai.dot(z)).sum();
    let f = ay / (1.0 + az);
    let dc = yc - zc * f;
    let dp = yp.iter().zip(&zp).map(|(y, z)| y - z * f).collect();
    Some((dc, dp))
}

/// The decrease of the cost that the damped step `(dc, dp)` of [`solve`] predicts (the
/// local quadratic model, cost units): with `(N + lambda D) h = -g`,
/// `-g.h - h^T N h / 2 = (-g.h + lambda h^T D h) / 2`, where `g` includes the depth-scale
/// pseudo-residual's gradient and `D` is the clamped diagonal the damping uses.
fn predicted_decrease(n: &Normal, lambda: f64, dc: &DVector<f64>, dp: &[Vector3<f64>]) -> f64 {
    let mut g_h = n.gc.dot(dc);
    let mut h_d_h: f64 = (0..dc.len()).map(|i| damping_diagonal(n.u[(i, i)]) * dc[i] * dc[i]).sum();
    for (p, d) in dp.iter().enumerate() {
        let (Some(g), Some(v)) = (n.gp.get(p), n.v.get(p)) else { continue };
        let mut g = *g;
        if let Some(a) = n.depth.as_ref().and_then(|(a, r)| a.get(p).map(|a| a * *r)) {
            g += a;
        }
        g_h += g.dot(d);
        h_d_h += (0..3).map(|i| damping_diagonal(v[(i, i)]) * d[i] * d[i]).sum::<f64>();
    }
    0.5 * (lambda * h_d_h - g_h)
}

/// A diagonal entry of the normal matrix as the damping scales it: clamped to
/// `[1e-6, 1e32]` (Marquardt scaling, module docs).
fn damping_diagonal(d: f64) -> f64 {
    d.clamp(1e-6, 1e32)
}

/// Solve the damped normal equations `N_lambda (dc, dp) = (rc, rp)` (data and priors
/// only) by the Schur complement over the points.
fn solve_rhs(
    n: &Normal,
    lambda: f64,
    rc: &DVector<f64>,
    rp: &[Vector3<f64>],
) -> Option<(DVector<f64>, Vec<Vector3<f64>>)> {
    let (s, l_inv) = reduced_camera_system(n, |d| lambda * damping_diagonal(d), false)?;
    // V_p^-1 = L_p^-T L_p^-1.
    let v_inv: Vec<Matrix3<f64>> =
        l_inv.into_iter().map(|li| li.map(|li| li.transpose() * li)).collect::<Option<_>>()?;
    let mut b = rc.clone();
    for (p, (vi, g)) in v_inv.iter().zip(rp).enumerate() {
        b.gemv(-1.0, &n.w.columns(3 * p, 3), &(vi * g), 1.0);
    }
    let dc = s.cholesky()?.solve(&b);
    if !dc.iter().all(|v| v.is_finite()) {
        return None;
    }
    let dp = v_inv
        .iter()
        .zip(rp)
        .enumerate()
        .map(|(p, (vi, g))| vi * (g - n.w.columns(3 * p, 3).tr_mul(&dc)))
        .collect();
    Some((dc, dp))
}

/// `a > b`, false if either is NaN.
fn gt(a: f64, b: f64) -> bool {
    a > b
}

fn rms(sum_sq: f64, n: usize) -> f64 {
    if n == 0 { 0.0 } else { (sum_sq / n as f64).sqrt() }
}

// ---------------------------------------------------------------------------------------
// Validation

fn check_intrinsics(k: &Intrinsics, name: &str) -> Result<()> {
    if !k.is_finite() || !gt(k.fx, 0.0) || !gt(k.fy, 0.0) {
        return Err(GeometryError::InvalidEstimate(format!(
            "{name} intrinsics must be finite with positive focal lengths, got {k:?}"
        )));
    }
    Ok(())
}

fn iso_finite(p: &Isometry3<f64>) -> bool {
    p.translation.vector.iter().chain(p.rotation.coords.iter()).all(|v| v.is_finite())
}

/// Check the state and normalise it for the options (skew, square pixels, fixed angles,
/// unit axis directions).
fn prepare_state(initial: &RigState, options: &BundleOptions) -> Result<RigState> {
    let mut s = initial.clone();
    check_intrinsics(&s.left, "left")?;
    check_intrinsics(&s.right, "right")?;
    for d in [&s.left_distortion, &s.right_distortion] {
        d.validate()?;
    }
    for k in [&mut s.left, &mut s.right] {
        if options.zero_skew {
            k.skew = 0.0;
        }
        if options.square_pixels {
            let f = 0.5 * (k.fx + k.fy);
            k.fx = f;
            k.fy = f;
        }
    }
    let t = s.right_from_left.translation.vector;
    if !iso_finite(&s.right_from_left) || !gt(t.norm(), 1e-12) {
        return Err(GeometryError::Degenerate(
            "right_from_left must be finite with a non-zero baseline (it fixes the scale)".into(),
        ));
    }
    let v = s.motions.view_count();
    if v == 0 {
        return Err(GeometryError::NotEnoughData { what: "views", needed: 1, got: 0 });
    }
    match &mut s.motions {
        Motions::Free { ref_from_cam } => {
            if ref_from_cam.iter().any(|p| !iso_finite(p)) {
                return Err(GeometryError::Degenerate("a view pose is not finite".into()));
            }
            let p0 = ref_from_cam.first().copied().unwrap_or_else(Isometry3::identity);
            if p0.translation.vector.norm() > 1e-9 || p0.rotation.angle() > 1e-9 {
                return Err(GeometryError::Degenerate("view 0 pose must be the identity (gauge)".into()));
            }
            if let Some(p) = ref_from_cam.first_mut() {
                *p = Isometry3::identity();
            }
        }
        Motions::Joints { axes, angles, commanded } => {
            if axes.is_empty() {
                return Err(GeometryError::NotEnoughData { what: "joint axes", needed: 1, got: 0 });
            }
            if commanded.len() != angles.len() {
                return Err(GeometryError::Degenerate(format!(
                    "{} rows of angles but {} rows of commanded angles",
                    angles.len(),
                    commanded.len()
                )));
            }
            for (k, (a, c)) in angles.iter().zip(commanded.iter()).enumerate() {
                if a.len() != axes.len() || c.len() != axes.len() {
                    return Err(GeometryError::Degenerate(format!(
                        "view {k}: angle rows must have one entry per axis ({})",
                        axes.len()
                    )));
                }
                if a.iter().chain(c).any(|x| !x.is_finite()) {
                    return Err(GeometryError::Degenerate(format!("view {k}: angles must be finite")));
                }
                if k == 0 && a.iter().chain(c).any(|x| x.abs() > 1e-12) {
                    return Err(GeometryError::Degenerate("row 0 of the angles must be zero (gauge)".into()));
                }
            }
            if options.angle_prior_sigma.is_none() {
                angles.clone_from(commanded);
            }
            for (j, l) in axes.iter_mut().enumerate() {
                let d = l.direction.into_inner();
                if !d.iter().chain(l.point.coords.iter()).all(|x| x.is_finite()) || !gt(d.norm(), 1e-12) {
                    return Err(GeometryError::Degenerate(format!("axis {j} is not a finite line")));
                }
                *l = Line::new(Unit::new_normalize(d), l.point);
                let moved = angles.iter().zip(commanded.iter()).any(|(a, c)| {
                    a.get(j).is_some_and(|x| x.abs() > 1e-12) || c.get(j).is_some_and(|x| x.abs() > 1e-12)
                });
                if !moved {
                    return Err(GeometryError::Degenerate(format!(
                        "axis {j} has zero angle in every view: it is not observable"
                    )));
                }
            }
        }
    }
    Ok(s)
}

// ---------------------------------------------------------------------------------------
// The solver

/// The state normalised for the options ([`prepare_state`]) and the problem on it: the
/// observations in front of the cameras, of points seen at least twice.
fn problem<'a>(
    initial: &RigState,
    observations: &[BundleObservation],
    options: &'a BundleOptions,
) -> Result<(RigState, Problem<'a>)> {
    options.validate()?;
    if observations.is_empty() {
        return Err(GeometryError::NotEnoughData { what: "observations", needed: 1, got: 0 });
    }
    let state = prepare_state(initial, options)?;
    let n_views = state.motions.view_count();
    let mut per_view = vec![0usize; n_views];
    for (i, o) in observations.iter().enumerate() {
        if o.view >= n_views || o.point >= state.points.len() {
            return Err(GeometryError::Degenerate(format!(
                "observation {i} refers to view {} / point {} out of range",
                o.view, o.point
            )));
        }
        if !(o.pixel.x.is_finite() && o.pixel.y.is_finite()) {
            return Err(GeometryError::Degenerate(format!("observation {i} has a non-finite pixel")));
        }
        if let Some(c) = per_view.get_mut(o.view) {
            *c += 1;
        }
    }
    if let Some(k) = per_view.iter().position(|&c| c == 0) {
        return Err(GeometryError::Degenerate(format!("view {k} has no observations")));
    }
    let layout = Layout::build(&state, options)?;

    // Filter: in front of the cameras, points with >= 2 observations.
    let views0 = view_geoms(&state, &layout, false);
    let rig0 = rig_geom(&state);
    let mut kept: Vec<BundleObservation> = Vec::with_capacity(observations.len());
    let mut count = vec![0usize; state.points.len()];
    for o in observations {
        let Some(x) = state.points.get(o.point) else { continue };
        if !x.coords.iter().all(|v| v.is_finite()) {
            return Err(GeometryError::Degenerate(format!("point {} is not finite", o.point)));
        }
        if linearise_obs(&state, &layout, &views0, &rig0, o, x, None).is_some() {
            kept.push(*o);
            if let Some(c) = count.get_mut(o.point) {
                *c += 1;
            }
        }
    }
    let mut compact = vec![usize::MAX; state.points.len()];
    let mut points = Vec::new();
    for (i, &c) in count.iter().enumerate() {
        if c >= 2 {
            if let Some(slot) = compact.get_mut(i) {
                *slot = points.len();
            }
            points.push(i);
        }
    }
    kept.retain(|o| count.get(o.point).is_some_and(|&c| c >= 2));
    let obs_point: Vec<usize> = kept.iter().map(|o| compact.get(o.point).copied().unwrap_or(0)).collect();
    let mut per_view = vec![0usize; n_views];
    for o in &kept {
        if let Some(c) = per_view.get_mut(o.view) {
            *c += 1;
        }
    }
    if kept.is_empty() {
        return Err(GeometryError::NotEnoughData { what: "usable observations", needed: 2, got: 0 });
    }
    if let Some(k) = per_view.iter().position(|&c| c == 0) {
        return Err(GeometryError::Degenerate(format!(
            "view {k} has no usable observations (in front of the camera, point seen at least twice)"
        )));
    }

    let sigma_opt = options.noise_sigma_px.unwrap_or(1.0);
    let problem = Problem {
        layout,
        obs: kept,
        obs_point,
        points,
        options,
        prior_weight: sigma_opt * sigma_opt,
        depth: None,
    };
    Ok((state, problem))
}

/// Refine a rig state on the observations. See the module documentation.
pub fn bundle_adjust(
    initial: &RigState,
    observations: &[BundleObservation],
    options: &BundleOptions,
) -> Result<BundleResult> {
    adjust(initial, observations, options, None, None, &[])?.ok_or_else(never_abandoned)
}

/// What [`bundle_adjust_with_checkpoint`] shows its callback: the accepted state after
/// `iterations` iterations, not converged.
#[derive(Debug, Clone, Copy)]
pub struct BundleCheckpoint<'a> {
    /// The current (best so far) state.
    pub state: &'a RigState,
    /// Iterations done.
    pub iterations: usize,
    /// RMS reprojection error of the state over the used observations, pixels.
    pub rms_px: f64,
    /// Observations used.
    pub observations: usize,
}

impl BundleCheckpoint<'_> {
    /// [`BundleResult::chi2`] of the checkpoint's state (the same expression, so a caller
    /// comparing it with a finished result's compares like with like).
    pub fn chi2(&self, noise_px: f64, options: &BundleOptions) -> f64 {
        chi2_of(self.rms_px, self.observations, &self.state.motions, noise_px, options)
    }
}

/// The least-squares cost in chi-square units of `observations` residuals with RMS
/// `rms_px` at noise `noise_px`, plus the angle prior's chi-square under `options`
/// ([`BundleResult::chi2`], [`BundleCheckpoint::chi2`]).
fn chi2_of(
    rms_px: f64,
    observations: usize,
    motions: &Motions,
    noise_px: f64,
    options: &BundleOptions,
) -> f64 {
    rms_px.powi(2) * observations as f64 / (noise_px * noise_px) + angle_prior_chi2(motions, options)
}

/// [`bundle_adjust`] that, if still not converged after `at_iteration` iterations, asks
/// `keep_going` whether to continue; `Ok(None)` when it says no. The run that continues is
/// exactly [`bundle_adjust`]'s (the solver is deterministic and the check changes
/// nothing), so a caller that would give up on a hopeless start pays for the iterations up
/// to the check only, and one that goes on does not repeat them (what running a short
/// probe and then the full adjustment from the start would cost).
pub fn bundle_adjust_with_checkpoint(
    initial: &RigState,
    observations: &[BundleObservation],
    options: &BundleOptions,
    at_iteration: usize,
    keep_going: &mut dyn FnMut(&BundleCheckpoint<'_>) -> bool,
) -> Result<Option<BundleResult>> {
    adjust(initial, observations, options, None, Some((at_iteration, keep_going)), &[])
}

/// The error for a run without a checkpoint that came back abandoned (cannot happen: only
/// the checkpoint's callback abandons).
fn never_abandoned() -> GeometryError {
    GeometryError::Numerical("the adjustment was abandoned without a checkpoint".into())
}

/// [`bundle_adjust`] with the scene's depth scale held near `target`: the stiff
/// pseudo-residual `(s - target) / tolerance` (cost units; `s` of [`log_depth_scale`] over
/// the adjusted points) joins the cost, so the result is the profile-likelihood point at
/// that depth scale (`tolerance` small against `sigma_s / sigma_px`). The reported
/// covariance and noise are those of the data and priors alone (the linearisation at the
/// profile point, without the constraint), and `final_rms_px` is of the pixels alone.
pub fn bundle_adjust_at_depth_scale(
    initial: &RigState,
    observations: &[BundleObservation],
    options: &BundleOptions,
    target: f64,
    tolerance: f64,
) -> Result<BundleResult> {
    if !(target.is_finite() && tolerance.is_finite() && tolerance > 0.0) {
        return Err(GeometryError::InvalidOption(format!(
            "depth-scale target {target} / tolerance {tolerance} must be finite, tolerance > 0"
        )));
    }
    adjust(initial, observations, options, Some((target, tolerance)), None, &[])?.ok_or_else(never_abandoned)
}

/// [`bundle_adjust`] with the named camera parameters (covariance names, e.g.
/// `right.fx`) held at their values in `initial`: the profile-likelihood point at those
/// values. The covariance is over the parameters left free. A name that is unknown or
/// not adjusted under `options` is [`GeometryError::InvalidOption`].
pub fn bundle_adjust_holding(
    initial: &RigState,
    observations: &[BundleObservation],
    options: &BundleOptions,
    held: &[&str],
) -> Result<BundleResult> {
    let held: Vec<Param> = held
        .iter()
        .map(|n| Param::parse(n).ok_or_else(|| GeometryError::InvalidOption(format!("no parameter {n}"))))
        .collect::<Result<_>>()?;
    adjust(initial, observations, options, None, None, &held)?.ok_or_else(never_abandoned)
}

/// The scene's depth scale `s` of a state: `-ln` of the mean inverse distance (the log
/// harmonic-mean distance) from the reference left camera, in units of the baseline
/// length (the scale gauge, held by the adjustment), over the points that
/// [`bundle_adjust`] would adjust with these observations (seen at least twice, in front
/// of the cameras), and its standard
/// deviation from the linearisation at `state` with pixel noise `sigma_px` (data and
/// priors; points not eliminated: `sigma_px^2 a^T N^-1 a`). Why: with small rotations the
/// scene's distance in baselines is the badly determined direction of the rig (a
/// receding scene with shifted principal points fits nearly as well), and the camera
/// covariance varies along it.
pub fn log_depth_scale(
    state: &RigState,
    observations: &[BundleObservation],
    options: &BundleOptions,
    sigma_px: f64,
) -> Result<(f64, f64)> {
    let opts = BundleOptions { noise_sigma_px: Some(sigma_px), ..options.clone() };
    let (state, problem) = problem(state, observations, &opts)?;
    let numerical = |w: &str| GeometryError::Numerical(format!("depth scale: {w}"));
    let s = log_depth_scale_of(&state, &problem.points).ok_or_else(|| numerical("non-finite point"))?;
    let a = log_depth_scale_jacobian(&state, &problem.points).ok_or_else(|| numerical("non-finite point"))?;
    let n =
        problem.normal_equations(&state, problem.prior_weight).ok_or_else(|| numerical("linearisation"))?;
    let (_, z) = solve_rhs(&n, 0.0, &DVector::zeros(problem.layout.len()), &a)
        .ok_or_else(|| numerical("singular normal equations"))?;
    let q: f64 = a.iter().zip(&z).map(|(ai, zi)| ai.dot(zi)).sum();
    if !(q.is_finite() && q >= 0.0) {
        return Err(numerical("negative variance"));
    }
    Ok((s, sigma_px * q.sqrt()))
}

/// `s = -ln(mean 1/|X|)` over the given points (original indices): the log of their
/// harmonic-mean distance. Inverse distance, not log distance, is averaged because a far
/// point's inverse distance is bounded and nearly linear in its disparity while its log
/// distance is unbounded (measured at 3 px: the mean log distance had sigmas up to 570,
/// carried by a few points near infinity). `None` if any point is not finite or at the
/// origin, or there are none.
fn log_depth_scale_of(state: &RigState, points: &[usize]) -> Option<f64> {
    let mut sum = 0.0;
    for &i in points {
        let d = state.points.get(i)?.coords.norm();
        if !(d.is_finite() && d > 0.0) {
            return None;
        }
        sum += 1.0 / d;
    }
    let m = sum / points.len() as f64;
    (!points.is_empty() && m > 0.0).then(|| -m.ln())
}

/// Gradient of [`log_depth_scale_of`] with respect to each point's homogeneous tangent
/// step `d` of [`retract_point`] (compact order):
/// `X^T / (n m |X|^3) (B_xyz - X B_w) / h_w`, `m` the mean inverse distance.
fn log_depth_scale_jacobian(state: &RigState, points: &[usize]) -> Option<Vec<Vector3<f64>>> {
    let n = points.len() as f64;
    let mut m = 0.0;
    for &i in points {
        m += 1.0 / state.points.get(i)?.coords.norm();
    }
    m /= n;
    points
        .iter()
        .map(|&i| {
            let x = state.points.get(i)?;
            let h = point_homogeneous(x);
            let b = homogeneous_basis(&h);
            let dxdd = (b.fixed_view::<3, 3>(0, 0) - x.coords * b.fixed_view::<1, 3>(3, 0)) / h.w;
            let g = (dxdd.transpose() * x.coords) / (x.coords.norm().powi(3) * n * m);
            g.iter().all(|v| v.is_finite()).then_some(g)
        })
        .collect()
}

/// Nielsen's damping after a rejected step (or one that could not be solved): raise
/// `lambda` by `nu`, and double `nu` for the next rejection in a row.
fn reject(lambda: &mut f64, nu: &mut f64) {
    *lambda *= *nu;
    *nu *= 2.0;
}

/// The callback of [`bundle_adjust_with_checkpoint`] and the iteration count at which it
/// is asked.
type Checkpoint<'c> = (usize, &'c mut dyn FnMut(&BundleCheckpoint<'_>) -> bool);

fn adjust(
    initial: &RigState,
    observations: &[BundleObservation],
    options: &BundleOptions,
    depth: Option<(f64, f64)>,
    mut checkpoint: Option<Checkpoint<'_>>,
    held: &[Param],
) -> Result<Option<BundleResult>> {
    let (mut state, mut problem) = problem(initial, observations, options)?;
    problem.depth = depth;
    if let Some(p) = held.iter().find(|p| !problem.layout.params.contains(p)) {
        return Err(GeometryError::InvalidOption(format!("{} is not a free parameter here", p.name())));
    }
    if !held.is_empty() {
        let kept = problem.layout.params.iter().copied().filter(|p| !held.contains(p)).collect();
        // A held `fy` is not a tie `fy = fx`: the tie follows the options.
        let square = problem.layout.square;
        problem.layout = Layout::from_params(kept, &state.motions)?;
        problem.layout.square = square;
    }
    let nc = problem.layout.len();
    let n_params = nc + 3 * problem.points.len();
    let n_obs = problem.obs.len();

    let Some(first) = problem.evaluate(&state) else {
        return Err(GeometryError::Numerical("the initial cost is not finite".into()));
    };
    let initial_rms_px = rms(first.sum_sq, n_obs);
    let mut current = first;
    let mut lambda = 1e-3;
    // Nielsen's update (module docs, Algorithm): the factor a rejected step raises the
    // damping by, doubled at each rejection in a row.
    let mut nu = 2.0;
    let mut iterations = 0;
    let mut converged = false;
    let mut termination = String::from("maximum iterations reached");
    'outer: while iterations < options.max_iterations {
        if let Some((at, keep_going)) = checkpoint.as_mut()
            && iterations == *at
        {
            let seen = BundleCheckpoint {
                state: &state,
                iterations,
                rms_px: rms(current.sum_sq, n_obs),
                observations: n_obs,
            };
            if !keep_going(&seen) {
                return Ok(None);
            }
        }
        iterations += 1;
        let Some(normal) = problem.normal_equations(&state, problem.prior_weight) else {
            return Err(GeometryError::Numerical("linearisation failed at an accepted state".into()));
        };
        loop {
            if lambda > 1e16 {
                converged = true;
                termination = "no further decrease possible (damping limit): minimum to rounding".into();
                break 'outer;
            }
            let Some((dc, dp)) = solve(&normal, lambda) else {
                reject(&mut lambda, &mut nu);
                continue;
            };
            let predicted = predicted_decrease(&normal, lambda, &dc, &dp);
            let mut cand = retract(&state, &problem.layout, &dc)?;
            let mut step_sq = dc.norm_squared();
            for (&pi, d) in problem.points.iter().zip(&dp) {
                if let Some(x) = cand.points.get_mut(pi) {
                    // A far point whose step would cross infinity keeps its position for this
                    // step; rejecting the whole step for it stalls the solver from rough
                    // starts (the damping grows until no step moves anything).
                    if let Some(p) = retract_point(x, d) {
                        step_sq += (p - *x).norm_squared();
                        *x = p;
                    }
                }
            }
            let eval = problem.evaluate(&cand);
            match eval {
                Some(e) if e.cost < current.cost => {
                    let decrease = current.cost - e.cost;
                    let x_norm = x_norm(&state, &problem.points);
                    state = cand;
                    let old_cost = current.cost;
                    current = e;
                    // Nielsen: lower the damping by up to 3x where the quadratic model
                    // predicted the decrease well (gain ratio near 1), raise it where it
                    // did not (ratio near 0).
                    let gain = decrease / predicted;
                    let factor = if gain.is_finite() && predicted > 0.0 {
                        (1.0 - (2.0 * gain - 1.0).powi(3)).max(1.0 / 3.0)
                    } else {
                        1.0
                    };
                    lambda = (lambda * factor).max(1e-12);
                    nu = 2.0;
                    if decrease <= options.function_tolerance * old_cost {
                        converged = true;
                        termination = "function tolerance".into();
                        break 'outer;
                    }
                    if step_sq.sqrt() <= options.parameter_tolerance * (x_norm + options.parameter_tolerance)
                    {
                        converged = true;
                        termination = "parameter tolerance".into();
                        break 'outer;
                    }
                    if current.cost == 0.0 {
                        converged = true;
                        termination = "zero cost".into();
                        break 'outer;
                    }
                    break;
                }
                _ => reject(&mut lambda, &mut nu),
            }
        }
    }

    // Covariance at the solution.
    let m = 2 * n_obs + problem.prior_terms(&state).len();
    let sigma = match options.noise_sigma_px {
        Some(s) => s,
        None => {
            if m <= n_params {
                return Err(GeometryError::NotEnoughData {
                    what: "residuals beyond parameters to estimate the noise",
                    needed: n_params + 1,
                    got: m,
                });
            }
            let dof = m as f64 / (m - n_params) as f64;
            match options.robust {
                RobustLoss::None => {
                    let Some(n) = problem.normal_equations(&state, 1.0) else {
                        return Err(GeometryError::Numerical("linearisation failed at the solution".into()));
                    };
                    (n.sum_wsq / (m - n_params) as f64).sqrt()
                }
                RobustLoss::Huber { .. } | RobustLoss::Cauchy { .. } => {
                    // Outliers would inflate sum w r^2; use the median residual norm instead
                    // (Rayleigh: median = sigma sqrt(2 ln 2)), corrected for the fitted dof.
                    let Some(mut norms) = problem.residual_norms(&state) else {
                        return Err(GeometryError::Numerical("residuals failed at the solution".into()));
                    };
                    norms.sort_by(f64::total_cmp);
                    let med = norms.get(norms.len() / 2).copied().unwrap_or(0.0);
                    med / (2.0 * std::f64::consts::LN_2).sqrt() * dof.sqrt()
                }
            }
        }
    };
    let (covariance, sigma_inflation) = covariance(&problem, &state, sigma, options.covariance_model, None)?;
    Ok(Some(BundleResult {
        state,
        report: BundleReport {
            iterations,
            initial_rms_px,
            final_rms_px: rms(current.sum_sq, n_obs),
            converged,
            termination,
            observations: n_obs,
            parameters: n_params,
            sigma_px: sigma,
            sigma_inflation,
        },
        covariance,
    }))
}

fn x_norm(state: &RigState, points: &[usize]) -> f64 {
    let mut s = state.right_from_left.translation.vector.norm_squared();
    for k in [&state.left, &state.right] {
        s += k.fx * k.fx + k.fy * k.fy + k.skew * k.skew + k.cx * k.cx + k.cy * k.cy;
    }
    for &p in points {
        if let Some(x) = state.points.get(p) {
            s += x.coords.norm_squared();
        }
    }
    s.sqrt()
}

/// The cluster-robust covariance of the camera parameters of a converged `state` (module
/// docs, Covariance) with the points grouped into clusters: points with the same
/// `cluster_of_point` entry (indexed like `state.points`) form one cluster, whose errors may
/// be correlated across all their observations. With every point its own cluster this is
/// the covariance of [`CovarianceModel::PointClustered`]. `sigma_px` weights the angle
/// priors as in [`bundle_adjust`] (its reported `sigma_px`). For diagnostics: coarser
/// clusters (an image region, a surface) test whether errors are correlated across points.
pub fn clustered_covariance(
    state: &RigState,
    observations: &[BundleObservation],
    options: &BundleOptions,
    sigma_px: f64,
    cluster_of_point: &[usize],
) -> Result<Covariance> {
    if cluster_of_point.len() != state.points.len() {
        return Err(GeometryError::InvalidOption(format!(
            "{} cluster labels for {} points",
            cluster_of_point.len(),
            state.points.len()
        )));
    }
    if !(sigma_px.is_finite() && sigma_px > 0.0) {
        return Err(GeometryError::InvalidOption(format!("sigma_px must be positive, got {sigma_px}")));
    }
    let (state, problem) = problem(state, observations, options)?;
    let model = CovarianceModel::PointClustered;
    Ok(covariance(&problem, &state, sigma_px, model, Some(cluster_of_point))?.0)
}

/// A point whose information (trace of its `V_p`) exceeds this multiple of the median
/// point's. Information grows as the inverse square of depth, so such a point is about
/// `1e4` times nearer than the median one: a point collapsed onto a camera centre (a
/// wrong track "explained" at depth `1e-11` in a 3 px trial), which no lens sees. Its
/// `U` and `W V^-1 W^T` terms are then some `1e24` times the camera parameters'
/// information and cancel to rounding noise, so the reduced camera system is not
/// positive definite although every parameter is observable.
const MAX_POINT_INFORMATION_RATIO: f64 = 1e8;

/// Compact indices of the points whose information exceeds
/// [`MAX_POINT_INFORMATION_RATIO`] times the median point's.
fn overinformed_points(n: &Normal) -> Vec<usize> {
    let mut traces: Vec<f64> = n.v.iter().map(|v| v.trace()).collect();
    traces.sort_by(f64::total_cmp);
    let Some(&median) = traces.get(traces.len() / 2) else { return Vec::new() };
    let limit = MAX_POINT_INFORMATION_RATIO * median;
    n.v.iter().enumerate().filter(|(_, v)| gt(v.trace(), limit)).map(|(p, _)| p).collect()
}

/// The covariance of the camera parameters under `model` (module docs, Covariance) and
/// its [`BundleReport::sigma_inflation`]. Points collapsed onto a camera centre
/// ([`MAX_POINT_INFORMATION_RATIO`]) are left out of it.
/// `clusters`, under `PointClustered`: the cluster of each point (indexed like
/// `state.points`; `None`: each point its own).
fn covariance(
    problem: &Problem<'_>,
    state: &RigState,
    sigma: f64,
    model: CovarianceModel,
    clusters: Option<&[usize]>,
) -> Result<(Covariance, f64)> {
    let names = problem.layout.names();
    let Some(n) = problem.normal_equations(state, sigma * sigma) else {
        return Err(GeometryError::Numerical("linearisation failed at the solution".into()));
    };
    // A point collapsed onto a camera centre cannot be eliminated in floating point: the
    // covariance is that of the problem without its observations (the adjustment itself
    // keeps them).
    let excessive = overinformed_points(&n);
    if !excessive.is_empty() {
        let kept: Vec<BundleObservation> = problem
            .obs
            .iter()
            .zip(&problem.obs_point)
            .filter(|(_, p)| !excessive.contains(p))
            .map(|(o, _)| *o)
            .collect();
        let (_, mut reduced) = self::problem(state, &kept, problem.options)?;
        reduced.prior_weight = problem.prior_weight;
        reduced.depth = problem.depth;
        if !problem.layout.params.iter().all(|p| reduced.layout.params.contains(p)) {
            return Err(GeometryError::Numerical("a parameter lost every observation".into()));
        }
        // Parameters held by [`bundle_adjust_holding`] stay held.
        reduced.layout = problem.layout.clone();
        return covariance(&reduced, state, sigma, model, clusters);
    }
    // A point whose block is singular carries no usable information: left out.
    let Some((s, l_inv)) = reduced_camera_system(&n, |_| 0.0, true) else {
        return Err(GeometryError::Numerical("reduced camera system is not finite".into()));
    };
    // W_p V_p^-1 per point.
    let wv_of: Vec<Option<nalgebra::OMatrix<f64, nalgebra::Dyn, nalgebra::U3>>> = l_inv
        .iter()
        .enumerate()
        .map(|(p, li)| li.map(|li| n.w.columns(3 * p, 3) * (li.transpose() * li)))
        .collect();
    let Some(ch) = s.cholesky() else {
        return Err(GeometryError::Numerical(
            "reduced camera system is singular at the solution: a parameter is unobservable".into(),
        ));
    };
    let inv = ch.inverse();
    let gaussian = 0.5 * (&inv + inv.transpose()) * (sigma * sigma);
    if model == CovarianceModel::Gaussian {
        return Ok((Covariance { names, matrix: gaussian }, 1.0));
    }
    let Some(scores) = problem.point_scores(state) else {
        return Err(GeometryError::Numerical("linearisation failed at the solution".into()));
    };
    let nc = inv.nrows();
    // Sum of the efficient scores per cluster (compact point index -> cluster).
    let mut sums: BTreeMap<usize, DVector<f64>> = BTreeMap::new();
    for (i, ((gc, gp), wv)) in scores.iter().zip(&wv_of).enumerate() {
        let Some(wv) = wv else { continue };
        let cluster = match clusters {
            Some(c) => problem.points.get(i).and_then(|&p| c.get(p)).copied().unwrap_or(usize::MAX),
            None => i,
        };
        *sums.entry(cluster).or_insert_with(|| DVector::zeros(nc)) += gc - wv * gp;
    }
    let mut meat = DMatrix::zeros(nc, nc);
    for sp in sums.values() {
        meat.ger(1.0, sp, sp, 1.0);
    }
    // Camera parameters' share of the leverage: fitted residuals are that much smaller.
    let components = 2.0 * problem.obs.len() as f64;
    if components > nc as f64 {
        meat *= components / (components - nc as f64);
    }
    // The angle priors, as modelled: information sigma^2 P, so their meat is sigma^2 (sigma^2 P).
    let s2 = sigma * sigma;
    for row in problem.prior_terms(state) {
        for &(a, da) in &row.entries {
            for &(b, db) in &row.entries {
                meat[(a, b)] += s2 * s2 * da * db;
            }
        }
    }
    let sandwich = &inv * meat * &inv;
    let matrix = 0.5 * (&sandwich + sandwich.transpose());
    let inflation = (0..nc)
        .filter(|&i| gaussian[(i, i)] > 0.0)
        .map(|i| matrix[(i, i)] / gaussian[(i, i)])
        .fold(0.0_f64, f64::max)
        .sqrt();
    Ok((Covariance { names, matrix }, inflation))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::{Synth, gauss, perturb, synth};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn angle_between(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
        a.normalize().dot(&b.normalize()).clamp(-1.0, 1.0).acos()
    }

    fn axes(s: &RigState) -> Vec<Line> {
        match &s.motions {
            Motions::Joints { axes, .. } => axes.clone(),
            Motions::Free { .. } => Vec::new(),
        }
    }

    /// Largest relative difference over intrinsics, rig, motions and points.
    fn state_distance(a: &RigState, b: &RigState) -> f64 {
        let mut d: f64 = 0.0;
        for (ka, kb) in [(&a.left, &b.left), (&a.right, &b.right)] {
            for (x, y) in [(ka.fx, kb.fx), (ka.fy, kb.fy), (ka.cx, kb.cx), (ka.cy, kb.cy)] {
                d = d.max((x - y).abs() / y.abs());
            }
            d = d.max((ka.skew - kb.skew).abs() / kb.fx);
        }
        for (da, db) in [(&a.left_distortion, &b.left_distortion), (&a.right_distortion, &b.right_distortion)]
        {
            for (x, y) in da.to_opencv().iter().zip(db.to_opencv()) {
                d = d.max((x - y).abs());
            }
        }
        d = d.max(a.right_from_left.rotation.angle_to(&b.right_from_left.rotation));
        d = d.max(
            (a.right_from_left.translation.vector - b.right_from_left.translation.vector).norm()
                / b.right_from_left.translation.vector.norm(),
        );
        for k in 0..b.motions.view_count() {
            let (pa, pb) = (a.motions.ref_from_cam(k), b.motions.ref_from_cam(k));
            d = d.max(pa.rotation.angle_to(&pb.rotation));
            d = d.max((pa.translation.vector - pb.translation.vector).norm());
        }
        for (la, lb) in axes(a).iter().zip(axes(b).iter()) {
            d = d.max(angle_between(&la.direction, &lb.direction));
            d = d.max((la.point - lb.point).norm());
        }
        for (pa, pb) in a.points.iter().zip(&b.points) {
            d = d.max((pa - pb).norm() / pb.coords.norm());
        }
        d
    }

    #[test]
    fn synthetic_problem_has_the_expected_size() {
        let s = synth(1, 200, 0.0, 0.0, false);
        assert!(s.obs.len() > 1100, "{} observations", s.obs.len());
        assert!(s.obs.iter().all(|o| residual_pixels(&s.truth, o).unwrap().norm() < 1e-9));
    }

    /// Noise-free data have zero residual at the truth, the gauge (view 0, baseline length)
    /// is fixed, so the truth is the isolated minimum; LM ends in Gauss-Newton with zero
    /// residual, which converges quadratically to rounding level (~1e-12). 1e-8 leaves room
    /// for the conditioning of 3 deg rotations (which amplifies rounding by ~1e3-1e4).
    #[test]
    fn joints_noise_free_converges_to_truth() {
        let s = synth(2, 200, 0.0, 0.0, false);
        let start = perturb(&s.truth, 20);
        assert!(state_distance(&start, &s.truth) > 1e-3);
        let res = bundle_adjust(&start, &s.obs, &BundleOptions::default()).unwrap();
        let d = state_distance(&res.state, &s.truth);
        assert!(res.report.converged, "{:?}", res.report);
        assert!(res.report.final_rms_px < 1e-8, "{:?}", res.report);
        assert!(d < 1e-8, "distance to truth {d:e}, {:?}", res.report);
    }

    /// The checkpoint changes nothing when the callback goes on (the same state to the
    /// bit, the same report), shows the state a run capped at that many iterations ends
    /// with (same chi-square), and abandons when told to.
    #[test]
    fn a_checkpoint_that_goes_on_is_the_plain_run() {
        let s = synth(5, 120, 1.0, 0.0, false);
        let start = perturb(&s.truth, 20);
        let options =
            BundleOptions { noise_sigma_px: Some(1.0), robust: RobustLoss::None, ..Default::default() };
        let plain = bundle_adjust(&start, &s.obs, &options).unwrap();
        assert!(plain.report.converged && plain.report.iterations > 3, "{:?}", plain.report);
        let at = 2;
        let capped =
            bundle_adjust(&start, &s.obs, &BundleOptions { max_iterations: at, ..options.clone() }).unwrap();
        let mut seen = Vec::new();
        let mut go_on = |c: &BundleCheckpoint<'_>| {
            seen.push((c.iterations, c.chi2(1.0, &options), c.state.left.fx));
            true
        };
        let checked =
            bundle_adjust_with_checkpoint(&start, &s.obs, &options, at, &mut go_on).unwrap().unwrap();
        assert_eq!(seen, vec![(at, capped.chi2(1.0, &options), capped.state.left.fx)]);
        assert_eq!(format!("{:?}", checked.report), format!("{:?}", plain.report));
        assert_eq!(format!("{:?}", checked.state), format!("{:?}", plain.state));
        assert_eq!(checked.covariance.matrix, plain.covariance.matrix);
        let mut stop = |_: &BundleCheckpoint<'_>| false;
        assert!(bundle_adjust_with_checkpoint(&start, &s.obs, &options, at, &mut stop).unwrap().is_none());
        // A run that converges before the checkpoint never asks.
        let mut never = |_: &BundleCheckpoint<'_>| -> bool { panic!("asked after convergence") };
        let late = plain.report.iterations + 1;
        let done =
            bundle_adjust_with_checkpoint(&start, &s.obs, &options, late, &mut never).unwrap().unwrap();
        assert_eq!(done.report.iterations, plain.report.iterations);
    }

    #[test]
    fn free_noise_free_converges_to_truth() {
        let s = synth(3, 200, 0.0, 0.0, true);
        let start = perturb(&s.truth, 30);
        let res = bundle_adjust(&start, &s.obs, &BundleOptions::default()).unwrap();
        let d = state_distance(&res.state, &s.truth);
        assert!(res.report.converged, "{:?}", res.report);
        assert!(d < 1e-8, "distance to truth {d:e}, {:?}", res.report);
    }

    #[test]
    fn noisy_with_outliers_huber_is_accurate() {
        let s = synth(4, 200, 1.0, 0.10, false);
        let start = perturb(&s.truth, 40);
        let res = bundle_adjust(&start, &s.obs, &BundleOptions::default()).unwrap();
        eprintln!("{:?}", res.report);
        assert!(res.report.converged, "{:?}", res.report);
        for (side, est, tru) in
            [("left", &res.state.left, &s.truth.left), ("right", &res.state.right, &s.truth.right)]
        {
            for (n, e, t) in [("fx", est.fx, tru.fx), ("fy", est.fy, tru.fy)] {
                // One seed: within 4 of its own sigma (a 6e-5 chance for a calibrated
                // sigma), and that sigma about 1.4 % at 1 px with 200 points and 3 deg.
                let sd = res.covariance.sigma(&format!("{side}.{n}")).unwrap_or(f64::NAN);
                assert!((e - t).abs() < 4.0 * sd && sd / t < 0.02, "{side}.{n}: {e} vs {t}, sigma {sd}");
            }
        }
        for (le, lt) in axes(&res.state).iter().zip(axes(&s.truth).iter()) {
            let a = angle_between(&le.direction, &lt.direction).to_degrees();
            assert!(a < 0.5, "axis direction off by {a} deg");
        }
        // Never worse than the start; robust weights keep the inlier RMS near 1 px.
        assert!(res.report.final_rms_px < res.report.initial_rms_px);
        assert!((0.7..1.5).contains(&res.report.sigma_px), "{:?}", res.report);
    }

    #[test]
    fn cauchy_and_plain_losses_run() {
        let s = synth(5, 60, 0.5, 0.0, false);
        for robust in [RobustLoss::None, RobustLoss::Cauchy { scale_px: 3.0 }] {
            let opts = BundleOptions { robust, ..BundleOptions::default() };
            let res = bundle_adjust(&perturb(&s.truth, 50), &s.obs, &opts).unwrap();
            assert!(res.report.converged && res.report.final_rms_px < 1.0, "{:?}", res.report);
        }
    }

    /// Central differences of `residual_pixels` along camera parameter `i` / point coordinate.
    fn fd_check(state: &RigState, options: &BundleOptions, obs: &[BundleObservation]) {
        let layout = Layout::build(state, options).unwrap();
        let views = view_geoms(state, &layout, true);
        let rig = rig_geom(state);
        let mut cols = Vec::new();
        let h = 1e-6;
        let mut checked = 0;
        for o in obs {
            let x = state.points[o.point];
            let (r, jp) = linearise_obs(state, &layout, &views, &rig, o, &x, Some(&mut cols)).unwrap();
            assert!((r - residual_pixels(state, o).unwrap()).norm() < 1e-9);
            let mut dense = vec![Vector2::zeros(); layout.len()];
            for (i, c) in &cols {
                dense[*i] += c;
            }
            for (i, analytic) in dense.iter().enumerate() {
                let mut e = DVector::zeros(layout.len());
                e[i] = h;
                let plus = residual_pixels(&retract(state, &layout, &e).unwrap(), o).unwrap();
                let minus = residual_pixels(&retract(state, &layout, &(-e)).unwrap(), o).unwrap();
                let numeric = (plus - minus) / (2.0 * h);
                let err = (numeric - analytic).norm();
                assert!(
                    err < 1e-5 * (1.0 + numeric.norm()),
                    "{}: analytic {analytic:?} numeric {numeric:?}",
                    layout.params[i].name()
                );
                checked += 1;
            }
            for c in 0..3 {
                let mut sp = state.clone();
                let mut e = Vector3::zeros();
                e[c] = h;
                sp.points[o.point] = retract_point(&x, &e).unwrap();
                let plus = residual_pixels(&sp, o).unwrap();
                sp.points[o.point] = retract_point(&x, &(-e)).unwrap();
                let minus = residual_pixels(&sp, o).unwrap();
                let numeric = (plus - minus) / (2.0 * h);
                assert!((numeric - jp.column(c)).norm() < 1e-6 * (1.0 + numeric.norm()), "point {c}");
            }
        }
        assert!(checked > 0);
    }

    /// The truncated mean and its derivative against numerical integration and central
    /// differences, over predictions inside, at and outside a window's borders.
    #[test]
    fn truncated_mean_shift_matches_integration() {
        let (lo, hi, sigma) = (-0.5, 99.5, 3.0);
        for &mu in &[-12.0, -6.0, -2.0, -0.5, 0.0, 1.0, 3.0, 7.0, 20.0, 50.0, 93.0, 99.0, 101.0, 104.0, 111.0]
        {
            let (shift, slope) = truncated_mean_shift(mu, lo, hi, sigma);
            // Midpoint rule over the window: the truncated mean of the measurement.
            let steps = 200_000;
            let dx = (hi - lo) / steps as f64;
            let (mut w, mut wx) = (0.0, 0.0);
            for i in 0..steps {
                let x = lo + (i as f64 + 0.5) * dx;
                let p = normal_pdf((x - mu) / sigma);
                w += p;
                wx += p * x;
            }
            let numeric = wx / w - mu;
            // Outside the clamp the shift is held, not the expectation's.
            if (lo - mu) <= WINDOW_CLAMP_SIGMAS * sigma && (mu - hi) <= WINDOW_CLAMP_SIGMAS * sigma {
                // The midpoint rule's error over 0.0005 px steps is about 1e-8 relative.
                assert!(
                    (shift - numeric).abs() < 1e-5 * (1.0 + numeric.abs()),
                    "mu {mu}: {shift} vs {numeric}"
                );
                let h = 1e-4;
                let d = (truncated_mean_shift(mu + h, lo, hi, sigma).0
                    - truncated_mean_shift(mu - h, lo, hi, sigma).0)
                    / (2.0 * h);
                assert!((slope - d).abs() < 1e-4, "mu {mu}: slope {slope} vs {d}");
                assert!(
                    1.0 + slope > 0.0 && 1.0 + slope <= 1.0 + 1e-9,
                    "mu {mu}: variance ratio {}",
                    1.0 + slope
                );
            } else {
                assert_eq!(slope, 0.0);
            }
        }
        assert_eq!(truncated_mean_shift(50.0, lo, hi, sigma), (0.0, 0.0));
        assert!(
            (truncated_mean_shift(-0.5, lo, hi, sigma).0 - sigma * (2.0 / std::f64::consts::PI).sqrt()).abs()
                < 1e-6
        );
        assert!(
            (normal_cdf(1.959_963_985) - 0.975).abs() < 1e-7
                && (normal_cdf(-3.0) - 0.001_349_898).abs() < 1e-9
        );
    }

    /// The windowed residuals are unbiased estimating equations: on "mean data" (every
    /// observation at its expected reported measurement, the projection plus the
    /// truncated-Gaussian shift of a 3 px noise inside a window a few pixels within the
    /// points' spread) the windowed fit recovers the truth from a perturbed start to rounding,
    /// while the plain fit, which takes those shifts for geometry, does not.
    #[test]
    fn a_measurement_window_recovers_the_truth_from_mean_data() {
        let s = synth(2, 200, 0.0, 0.0, false);
        let window = [180.0, 70.0, 700.0, 506.0];
        let sigma = 3.0;
        let mut shifted = 0;
        let obs: Vec<BundleObservation> = s
            .obs
            .iter()
            .filter(|o| {
                o.pixel.x > window[0]
                    && o.pixel.x < window[2]
                    && o.pixel.y > window[1]
                    && o.pixel.y < window[3]
            })
            .map(|o| {
                let (dx, _) = truncated_mean_shift(o.pixel.x, window[0], window[2], sigma);
                let (dy, _) = truncated_mean_shift(o.pixel.y, window[1], window[3], sigma);
                if dx.abs() + dy.abs() > 0.1 {
                    shifted += 1;
                }
                BundleObservation { pixel: o.pixel + Vector2::new(dx, dy), ..*o }
            })
            .collect();
        assert!(shifted > 30, "{shifted} observations near a border");
        let start = perturb(&s.truth, 20);
        let opts = BundleOptions {
            noise_sigma_px: Some(sigma),
            measurement_window: Some(window),
            ..BundleOptions::default()
        };
        // Cameras, rig and axes (points seen fewer than twice inside the window keep their
        // start).
        let distance = |r: &BundleResult| {
            state_distance(&RigState { points: s.truth.points.clone(), ..r.state.clone() }, &s.truth)
        };
        let res = bundle_adjust(&start, &obs, &opts).unwrap();
        let d = distance(&res);
        assert!(res.report.final_rms_px < 1e-8 && d < 1e-7, "distance to truth {d:e}, {:?}", res.report);
        let plain = bundle_adjust(&start, &obs, &BundleOptions { measurement_window: None, ..opts }).unwrap();
        let dp = distance(&plain);
        assert!(dp > 1e-3, "plain fit distance {dp:e}");
    }

    /// With a measurement window the residuals and both Jacobians (camera parameters and
    /// point) still agree with central differences (a wide sigma so that most
    /// observations are near a border).
    #[test]
    fn windowed_jacobians_match_finite_differences() {
        let s = synth(3, 30, 0.0, 0.0, false);
        let options = BundleOptions {
            noise_sigma_px: Some(40.0),
            measurement_window: Some([150.0, 40.0, 700.0, 540.0]),
            ..BundleOptions::default()
        };
        let (state, problem) = problem(&s.truth, &s.obs, &options).unwrap();
        let residual = |st: &RigState, o: &BundleObservation, x: &Point3<f64>| {
            let views = view_geoms(st, &problem.layout, false);
            problem.observe(st, &views, &rig_geom(st), o, x, None).unwrap().0
        };
        let views = view_geoms(&state, &problem.layout, true);
        let rig = rig_geom(&state);
        let h = 1e-6;
        let mut shifted = 0;
        for o in problem.obs.iter().step_by(3) {
            let x = state.points[o.point];
            let mut cols = Vec::new();
            let (r, jp) = problem.observe(&state, &views, &rig, o, &x, Some(&mut cols)).unwrap();
            assert!((r - residual(&state, o, &x)).norm() < 1e-12);
            if (r - residual_pixels(&state, o).unwrap()).norm() > 0.1 {
                shifted += 1;
            }
            let mut dense = vec![Vector2::zeros(); problem.layout.len()];
            for (i, c) in &cols {
                dense[*i] += c;
            }
            for (i, analytic) in dense.iter().enumerate() {
                let mut e = DVector::zeros(problem.layout.len());
                e[i] = h;
                let plus = residual(&retract(&state, &problem.layout, &e).unwrap(), o, &x);
                let minus = residual(&retract(&state, &problem.layout, &(-e)).unwrap(), o, &x);
                let numeric = (plus - minus) / (2.0 * h);
                assert!(
                    (numeric - analytic).norm() < 1e-5 * (1.0 + numeric.norm()),
                    "{i}: {analytic:?} {numeric:?}"
                );
            }
            for c in 0..3 {
                let mut e = Vector3::zeros();
                e[c] = h;
                let plus = residual(&state, o, &retract_point(&x, &e).unwrap());
                let minus = residual(&state, o, &retract_point(&x, &(-e)).unwrap());
                let numeric = (plus - minus) / (2.0 * h);
                assert!((numeric - jp.column(c)).norm() < 1e-6 * (1.0 + numeric.norm()), "point {c}");
            }
        }
        assert!(shifted > 10, "only {shifted} observations near a border");
    }

    #[test]
    fn jacobians_match_finite_differences() {
        let pick = |s: &Synth| -> Vec<BundleObservation> {
            let mut out = Vec::new();
            for view in 0..3 {
                for side in [Side::Left, Side::Right] {
                    out.extend(s.obs.iter().filter(|o| o.view == view && o.side == side).take(2));
                }
            }
            out
        };
        let s = synth(6, 30, 0.0, 0.0, false);
        let st = perturb(&s.truth, 60);
        // Joints with free angles, skew and non-square pixels.
        let all = BundleOptions { zero_skew: false, ..BundleOptions::default() };
        let mut st_skew = st.clone();
        st_skew.left.skew = 1.5;
        st_skew.right.skew = -0.7;
        fd_check(&st_skew, &all, &pick(&s));
        // Square pixels and a fixed principal point.
        let mut sq = st.clone();
        for k in [&mut sq.left, &mut sq.right] {
            k.fy = k.fx;
        }
        let opts =
            BundleOptions { square_pixels: true, fix_principal_point: true, ..BundleOptions::default() };
        fd_check(&sq, &opts, &pick(&s));
        // Free model.
        let f = synth(7, 30, 0.0, 0.0, true);
        fd_check(&perturb(&f.truth, 70), &BundleOptions::default(), &pick(&f));
    }

    /// The synthetic problem re-observed through a barrel lens (`k1 = -0.2, k2 = 0.05` on
    /// the left, `-0.15, 0.03` on the right: up to ~6 % radial at the image corners),
    /// noise-free.
    fn distorted(seed: u64, n_points: usize, free: bool) -> Synth {
        let mut s = synth(seed, n_points, 0.0, 0.0, free);
        s.truth.left_distortion = Distortion::radial(-0.2, 0.05);
        s.truth.right_distortion = Distortion::radial(-0.15, 0.03);
        let truth = s.truth.clone();
        s.obs.retain_mut(|o| {
            let at = BundleObservation { pixel: Point2::origin(), ..*o };
            match residual_pixels(&truth, &at) {
                Some(r) => {
                    o.pixel = Point2::from(r);
                    true
                }
                None => false,
            }
        });
        s
    }

    #[test]
    fn distortion_jacobians_match_finite_differences() {
        let s = distorted(13, 30, false);
        let pick: Vec<_> = s.obs.iter().step_by(7).take(12).copied().collect();
        let opts = BundleOptions { estimate_distortion: true, zero_skew: false, ..BundleOptions::default() };
        let mut st = perturb(&s.truth, 130);
        st.left.skew = 1.5;
        fd_check(&st, &opts, &pick);
        // From the pinhole start (zero distortion takes the pinhole branch of the projection).
        st.left_distortion = Distortion::default();
        st.right_distortion = Distortion::default();
        fd_check(&st, &opts, &pick);
        // Tangential and k3 held but used; square pixels.
        let mut sq = perturb(&s.truth, 131);
        sq.left_distortion.p1 = 1e-3;
        sq.right_distortion.k3 = 0.01;
        for k in [&mut sq.left, &mut sq.right] {
            k.fy = k.fx;
        }
        let opts =
            BundleOptions { estimate_distortion: true, square_pixels: true, ..BundleOptions::default() };
        fd_check(&sq, &opts, &pick);
        let f = distorted(14, 30, true);
        let pick: Vec<_> = f.obs.iter().step_by(5).take(12).copied().collect();
        fd_check(
            &perturb(&f.truth, 140),
            &BundleOptions { estimate_distortion: true, ..BundleOptions::default() },
            &pick,
        );
    }

    /// Noise-free distorted data from a pinhole start (K ~1.5 % off, distortion zero): the
    /// truth is the isolated zero-residual minimum, so LM ends in Gauss-Newton at rounding
    /// level; 1e-8 as in `joints_noise_free_converges_to_truth` (k1, k2 absolute, order 0.1).
    #[test]
    fn distortion_noise_free_converges_to_truth() {
        for (seed, free) in [(15, false), (16, true)] {
            let s = distorted(seed, 200, free);
            let mut start = perturb(&s.truth, seed * 10);
            start.left_distortion = Distortion::default();
            start.right_distortion = Distortion::default();
            // Without distortion in the model the fit cannot reach zero residual.
            let pinhole = bundle_adjust(&start, &s.obs, &BundleOptions::default()).unwrap();
            assert!(pinhole.report.final_rms_px > 0.05, "{:?}", pinhole.report);
            let opts = BundleOptions { estimate_distortion: true, ..BundleOptions::default() };
            let res = bundle_adjust(&start, &s.obs, &opts).unwrap();
            let d = state_distance(&res.state, &s.truth);
            eprintln!(
                "free={free}: pinhole rms {:.3} px fx {:.2} (true {:.2}); with distortion rms {:.1e}, distance {d:.1e}",
                pinhole.report.final_rms_px, pinhole.state.left.fx, s.truth.left.fx, res.report.final_rms_px
            );
            assert!(res.report.converged, "{:?}", res.report);
            assert!(res.report.final_rms_px < 1e-8, "{:?}", res.report);
            assert!(d < 1e-8, "distance to truth {d:e}, {:?}", res.report);
            for n in ["left.k1", "left.k2", "right.k1", "right.k2"] {
                assert!(res.covariance.index(n).is_some(), "{n} missing");
            }
            // perturbed() understands the distortion names.
            let mut delta = DVector::zeros(res.covariance.names.len());
            delta[res.covariance.index("right.k2").unwrap_or(0)] = 0.01;
            let moved = res.perturbed(&delta).unwrap();
            assert!((moved.right_distortion.k2 - res.state.right_distortion.k2 - 0.01).abs() < 1e-15);
        }
    }

    /// With 0.5 px noise the covariance of k1 is positive and its error is within a few sigma.
    #[test]
    fn distortion_covariance_is_consistent() {
        let mut s = distorted(17, 150, false);
        let mut rng = ChaCha8Rng::seed_from_u64(170);
        for o in &mut s.obs {
            o.pixel += Vector2::new(gauss(&mut rng), gauss(&mut rng)) * 0.5;
        }
        let opts = BundleOptions { estimate_distortion: true, ..BundleOptions::default() };
        let res = bundle_adjust(&s.truth, &s.obs, &opts).unwrap();
        for (n, est, tru) in [
            ("left.k1", res.state.left_distortion.k1, s.truth.left_distortion.k1),
            ("right.k2", res.state.right_distortion.k2, s.truth.right_distortion.k2),
        ] {
            let sigma = res.covariance.sigma(n).unwrap();
            eprintln!("{n}: est {est:.5} true {tru:.5} sigma {sigma:.5}");
            // 5 sigma: one seed, a failure here is a real inconsistency, not bad luck.
            assert!(sigma > 0.0 && (est - tru).abs() < 5.0 * sigma, "{n}: {est} vs {tru}, sigma {sigma}");
        }
    }

    /// Commanded angles as differences of noisy readings ([`AnglePrior::ReadingDifferences`]):
    /// every view's reading of every joint, view 0's included, gets Gaussian noise `sigma`.
    fn scatter_readings(motions: &mut Motions, sigma: f64, rng: &mut ChaCha8Rng) {
        if let Motions::Joints { commanded, .. } = motions {
            let reference: Vec<f64> =
                (0..commanded.first().map_or(0, Vec::len)).map(|_| sigma * gauss(rng)).collect();
            for row in commanded.iter_mut().skip(1) {
                for (c, r0) in row.iter_mut().zip(&reference) {
                    *c += sigma * gauss(rng) - r0;
                }
            }
        }
    }

    /// The whitened prior residuals' chi-square is `e^T C^-1 e` with the model's `C`, on
    /// random error vectors of 1-6 views (to rounding: the whitening is exact).
    #[test]
    fn angle_prior_whitening_is_the_inverse_covariance() {
        let mut rng = ChaCha8Rng::seed_from_u64(5150);
        for trial in 0..200 {
            let m = 1 + trial % 6;
            let sigma = 1e-4 * (1.0 + (trial % 7) as f64);
            let e: Vec<f64> = (0..m).map(|_| sigma * gauss(&mut rng)).collect();
            let ev = DVector::from_vec(e.clone());
            for (model, c) in [
                (AnglePrior::Independent, DMatrix::identity(m, m) * (sigma * sigma)),
                (
                    AnglePrior::ReadingDifferences,
                    (DMatrix::identity(m, m) + DMatrix::from_element(m, m, 1.0)) * (sigma * sigma),
                ),
            ] {
                let chi2: f64 = angle_prior_residuals(&e, sigma, model).iter().map(|r| r * r).sum();
                let exact = (ev.transpose() * c.try_inverse().unwrap() * &ev)[(0, 0)];
                assert!((chi2 - exact).abs() <= 1e-12 * exact.max(1.0), "{model:?} m {m}: {chi2} vs {exact}");
            }
        }
        assert!(angle_prior_residuals(&[], 1e-3, AnglePrior::ReadingDifferences).is_empty());
    }

    /// The prior rows' analytic derivatives `(delta_il - beta) / sigma` (as
    /// `Problem::prior_terms` builds them) against central differences of the residuals
    /// (linear in the errors: equal up to the rounding of a 1e-7 rad step on errors of
    /// 1e-4 rad, 1e-6 relative).
    #[test]
    fn angle_prior_derivatives_match_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(5151);
        for m in 1..=6 {
            let sigma = 2e-4;
            let e: Vec<f64> = (0..m).map(|_| sigma * gauss(&mut rng)).collect();
            for model in [AnglePrior::Independent, AnglePrior::ReadingDifferences] {
                let beta = prior_beta(m, model);
                for l in 0..m {
                    let h = 1e-7;
                    let (mut plus, mut minus) = (e.clone(), e.clone());
                    plus[l] += h;
                    minus[l] -= h;
                    let rp = angle_prior_residuals(&plus, sigma, model);
                    let rm = angle_prior_residuals(&minus, sigma, model);
                    for i in 0..m {
                        let fd = (rp[i] - rm[i]) / (2.0 * h);
                        let analytic = (if i == l { 1.0 } else { 0.0 } - beta) / sigma;
                        assert!(
                            (fd - analytic).abs() <= 1e-6 * (1.0 / sigma),
                            "{model:?} m {m} d r{i}/d e{l}: {fd} vs {analytic}"
                        );
                    }
                }
            }
        }
    }

    /// Monte-Carlo spread of `left.fx` and `left.cx` against the mean predicted sigma of
    /// both covariance models, for errors built by `err(point, side, rng)`.
    fn spread_and_predictions(
        err: &mut dyn FnMut(usize, &BundleObservation, &mut ChaCha8Rng) -> Vector2<f64>,
        names: &[&str],
    ) -> Vec<(f64, f64, f64)> {
        let base = synth(8, 80, 0.0, 0.0, false);
        let trials = 40;
        let mut rng = ChaCha8Rng::seed_from_u64(801);
        let mut est = vec![Vec::new(); names.len()];
        let mut pred = vec![(0.0, 0.0); names.len()];
        let sigma_prior = BundleOptions::default().angle_prior_sigma.unwrap_or(1e-3);
        for trial in 0..trials {
            // Commanded angles from noisy readings, as the prior claims.
            let mut start = base.truth.clone();
            scatter_readings(&mut start.motions, sigma_prior, &mut rng);
            let obs: Vec<BundleObservation> = base
                .obs
                .iter()
                .map(|o| BundleObservation { pixel: o.pixel + err(trial, o, &mut rng), ..*o })
                .collect();
            let opts = BundleOptions {
                robust: RobustLoss::None,
                covariance_model: CovarianceModel::PointClustered,
                // Both error models below have 1 px per component in total; the prior is
                // weighted by it in the fit and in both covariances (as the estimator's
                // maximum-likelihood pass does with its noise estimate).
                noise_sigma_px: Some(1.0),
                ..BundleOptions::default()
            };
            let res = bundle_adjust(&start, &obs, &opts).unwrap();
            let gauss = bundle_adjust(
                &res.state,
                &obs,
                &BundleOptions { covariance_model: CovarianceModel::Gaussian, max_iterations: 1, ..opts },
            )
            .unwrap();
            assert!(res.report.sigma_inflation >= 1.0 - 0.5 && gauss.report.sigma_inflation == 1.0);
            for (i, n) in names.iter().enumerate() {
                let (l, r) = (&res.state.left, &res.state.right);
                est[i].push(match *n {
                    "left.fx" => l.fx,
                    "left.cx" => l.cx,
                    _ => r.fy,
                });
                pred[i].0 += gauss.covariance.sigma(n).unwrap() / trials as f64;
                pred[i].1 += res.covariance.sigma(n).unwrap() / trials as f64;
            }
        }
        est.iter()
            .zip(&pred)
            .map(|(v, p)| {
                let n = v.len() as f64;
                let mean = v.iter().sum::<f64>() / n;
                ((v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt(), p.0, p.1)
            })
            .collect()
    }

    /// The clustered covariance: with i.i.d. noise it agrees with the Gaussian one (the
    /// sandwich's expectation is `sigma^2 S^-1`); when every observation of a point in one
    /// camera carries the same offset (a tracked feature's localisation bias), the
    /// Gaussian sigmas are wrong (here 1.4-2.8x too large: the point absorbs most of a
    /// shared offset; measured empirical/clustered 0.83-1.09) and the clustered ones
    /// follow the spread. 40 trials:
    /// a sample standard deviation is within about 25 % of the truth (2 sigma), hence the
    /// 0.7-1.4 band; the correlated case must separate the models by more than that.
    #[test]
    fn clustered_covariance_follows_correlated_errors() {
        let names = ["left.fx", "left.cx", "right.fy"];
        let iid = spread_and_predictions(&mut |_, _, rng| Vector2::new(gauss(rng), gauss(rng)), &names);
        for ((emp, g, c), n) in iid.iter().zip(names) {
            eprintln!("iid {n}: empirical {emp:.4}, gaussian {g:.4}, clustered {c:.4}");
            assert!((0.85..1.18).contains(&(c / g)), "{n}: clustered {c} vs gaussian {g}");
            assert!((0.7..1.4).contains(&(emp / c)), "{n}: empirical {emp} vs clustered {c}");
        }
        // Offset per (point, side), shared by every view, plus 0.3 px i.i.d. noise.
        let mut offsets: std::collections::HashMap<(usize, usize, bool), Vector2<f64>> =
            std::collections::HashMap::new();
        let mut salt = ChaCha8Rng::seed_from_u64(802);
        let corr = spread_and_predictions(
            &mut |trial, o, rng| {
                let key = (trial, o.point, o.side == Side::Right);
                let b =
                    *offsets.entry(key).or_insert_with(|| Vector2::new(gauss(&mut salt), gauss(&mut salt)));
                0.95 * b + 0.3 * Vector2::new(gauss(rng), gauss(rng))
            },
            &names,
        );
        let mut separated = false;
        for ((emp, g, c), n) in corr.iter().zip(names) {
            eprintln!("correlated {n}: empirical {emp:.4}, gaussian {g:.4}, clustered {c:.4}");
            assert!((0.7..1.4).contains(&(emp / c)), "{n}: empirical {emp} vs clustered {c}");
            separated |= emp / g > 1.6 || g / emp > 1.6;
        }
        assert!(separated, "the correlated errors did not make the Gaussian sigmas wrong: {corr:?}");
    }

    /// [`clustered_covariance`]: with every point its own cluster it is the covariance of
    /// `PointClustered` (the same sums in the same order, at the state as re-normalised by
    /// the adjustment's set-up, which moves the axes' unit directions in the last bit; the
    /// covariance's conditioning amplifies that by up to ~1e4: measured 1.2e-12 relative,
    /// allowed 1e-10); merging
    /// points two by two, whose i.i.d. errors are independent, leaves its expectation
    /// unchanged (one draw, 120 clusters against 240 with 25 camera parameters: measured
    /// ratios 0.76-1.06; the variance of a sandwich term from ~100 effective clusters is
    /// within about 30 % at 2 sigma, hence the 0.55-1.45 band); bad labels and noise are
    /// errors.
    #[test]
    fn clustered_covariance_by_labels() {
        let mut s = synth(9, 240, 0.0, 0.0, false);
        let mut rng = ChaCha8Rng::seed_from_u64(803);
        for o in &mut s.obs {
            o.pixel += Vector2::new(gauss(&mut rng), gauss(&mut rng)) * 0.5;
        }
        let opts = BundleOptions {
            robust: RobustLoss::None,
            noise_sigma_px: Some(0.5),
            covariance_model: CovarianceModel::PointClustered,
            ..BundleOptions::default()
        };
        let res = bundle_adjust(&s.truth, &s.obs, &opts).unwrap();
        let n = res.state.points.len();
        let own: Vec<usize> = (0..n).collect();
        let same = clustered_covariance(&res.state, &s.obs, &opts, 0.5, &own).unwrap();
        assert_eq!(same.names, res.covariance.names);
        let scale = res.covariance.matrix.amax();
        let rel = (&same.matrix - &res.covariance.matrix).amax() / scale;
        assert!(rel <= 1e-10, "{rel:e}");
        let pairs: Vec<usize> = (0..n).map(|p| p / 2).collect();
        let merged = clustered_covariance(&res.state, &s.obs, &opts, 0.5, &pairs).unwrap();
        for (i, name) in res.covariance.names.iter().enumerate() {
            let ratio = merged.matrix[(i, i)] / res.covariance.matrix[(i, i)];
            eprintln!("{name}: merged / own variance {ratio:.3}");
            assert!((0.55..1.45).contains(&ratio), "{name}: variance ratio {ratio}");
        }
        assert!(clustered_covariance(&res.state, &s.obs, &opts, 0.5, &pairs[1..]).is_err());
        assert!(clustered_covariance(&res.state, &s.obs, &opts, f64::NAN, &pairs).is_err());
        assert!(clustered_covariance(&res.state, &s.obs, &opts, 0.0, &pairs).is_err());
    }

    #[test]
    fn covariance_predicts_the_spread() {
        let base = synth(8, 80, 0.0, 0.0, false);
        let opts = BundleOptions { robust: RobustLoss::None, ..BundleOptions::default() };
        let sigma_prior = opts.angle_prior_sigma.unwrap();
        let trials = 50;
        let mut fx = Vec::new();
        let mut predicted = Vec::new();
        let mut rng = ChaCha8Rng::seed_from_u64(800);
        for _ in 0..trials {
            let obs: Vec<BundleObservation> = base
                .obs
                .iter()
                .map(|o| BundleObservation {
                    pixel: o.pixel + Vector2::new(gauss(&mut rng), gauss(&mut rng)),
                    ..*o
                })
                .collect();
            // Commanded angles from noisy readings, as the prior claims.
            let mut start = base.truth.clone();
            scatter_readings(&mut start.motions, sigma_prior, &mut rng);
            let res = bundle_adjust(&start, &obs, &opts).unwrap();
            assert!(res.report.converged, "{:?}", res.report);
            fx.push(res.state.left.fx);
            predicted.push(res.covariance.sigma("left.fx").unwrap());
        }
        let n = trials as f64;
        let mean = fx.iter().sum::<f64>() / n;
        let std = (fx.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        let pred = predicted.iter().sum::<f64>() / n;
        let ratio = std / pred;
        eprintln!("fx: empirical std {std:.4}, predicted {pred:.4}, ratio {ratio:.3}");
        assert!((0.7..1.4).contains(&ratio), "empirical {std} predicted {pred}");
    }

    /// The depth scale's gradient over each point's homogeneous tangent step against
    /// central differences of `retract_point` (step 1e-6: truncation ~1e-12, rounding
    /// ~1e-10 relative to the entry).
    #[test]
    fn depth_scale_jacobian_matches_finite_differences() {
        let s = synth(11, 40, 0.0, 0.0, false);
        let points: Vec<usize> = (0..s.truth.points.len()).collect();
        let a = log_depth_scale_jacobian(&s.truth, &points).unwrap();
        let h = 1e-6;
        for i in [0, 7, 19, 39] {
            for k in 0..3 {
                let mut d = Vector3::zeros();
                d[k] = h;
                let mut plus = s.truth.clone();
                plus.points[i] = retract_point(&s.truth.points[i], &d).unwrap();
                let mut minus = s.truth.clone();
                minus.points[i] = retract_point(&s.truth.points[i], &-d).unwrap();
                let fd = (log_depth_scale_of(&plus, &points).unwrap()
                    - log_depth_scale_of(&minus, &points).unwrap())
                    / (2.0 * h);
                let scale = a[i].norm().max(1e-12);
                assert!((fd - a[i][k]).abs() < 1e-6 * scale, "point {i} dof {k}: fd {fd:e} vs {:e}", a[i][k]);
            }
        }
    }

    /// The profile at the estimate's own depth scale is the estimate (to the solver's
    /// tolerance), and at `s + 2 sigma_s` it holds `s` there and costs about 4 in chi-square
    /// if the depth scale were linear; measured 3.07 on this 80-point scene (sigma_s 0.21:
    /// the profile is flatter than its linearisation on the far side, which is why the
    /// estimate profiles it), so 1.5-6 is allowed.
    #[test]
    fn depth_scale_profile_holds_the_scale_and_costs_its_chi_square() {
        let base = synth(12, 80, 1.0, 0.0, false);
        let opts =
            BundleOptions { robust: RobustLoss::None, noise_sigma_px: Some(1.0), ..BundleOptions::default() };
        let est = bundle_adjust(&perturb(&base.truth, 120), &base.obs, &opts).unwrap();
        assert!(est.report.converged, "{:?}", est.report);
        let (s0, sig) = log_depth_scale(&est.state, &base.obs, &opts, 1.0).unwrap();
        assert!(sig > 0.0 && sig < 1.0, "sigma_s {sig}");
        let cost = |st: &RigState| {
            let (_, p) = problem(st, &base.obs, &opts).unwrap();
            p.evaluate(st).unwrap().cost
        };
        let tol = 1e-3 * sig;
        let same = bundle_adjust_at_depth_scale(&est.state, &base.obs, &opts, s0, tol).unwrap();
        assert!(
            state_distance(&same.state, &est.state) < 1e-6,
            "{}",
            state_distance(&same.state, &est.state)
        );
        let far = bundle_adjust_at_depth_scale(&est.state, &base.obs, &opts, s0 + 2.0 * sig, tol).unwrap();
        let (s1, _) = log_depth_scale(&far.state, &base.obs, &opts, 1.0).unwrap();
        assert!((s1 - s0 - 2.0 * sig).abs() < 1e-2 * sig, "held at {s1}, wanted {}", s0 + 2.0 * sig);
        let dchi2 = 2.0 * (cost(&far.state) - cost(&est.state));
        eprintln!("s {s0:.4} sigma_s {sig:.4}: chi-square rise at +2 sigma_s {dchi2:.3}");
        assert!((1.5..6.0).contains(&dchi2), "chi-square rise {dchi2}");
        // Its covariance is the unconstrained linearisation at the profile point.
        assert_eq!(far.covariance.names, est.covariance.names);
        assert!(bundle_adjust_at_depth_scale(&est.state, &base.obs, &opts, s0, 0.0).is_err());
    }

    /// Holding a camera parameter: at its own estimate the profile point is the estimate,
    /// and at `+-2 sigma` it stays there while everything else re-adjusts, the cost rising
    /// by about 4 in chi-square (exactly 4 for a linear model; measured 3.66-4.38 on this
    /// 80-point scene at 1 px, the model's curvature, so 2.5-6 is allowed),
    /// without the held parameter in the covariance. A held `fy` is not tied to `fx`;
    /// an unknown name, or one the options do not adjust, is an error.
    #[test]
    fn holding_a_parameter_gives_its_profile_likelihood() {
        let base = synth(12, 80, 1.0, 0.0, false);
        let opts =
            BundleOptions { robust: RobustLoss::None, noise_sigma_px: Some(1.0), ..BundleOptions::default() };
        let est = bundle_adjust(&perturb(&base.truth, 120), &base.obs, &opts).unwrap();
        assert!(est.report.converged, "{:?}", est.report);
        let same = bundle_adjust_holding(&est.state, &base.obs, &opts, &["right.fx"]).unwrap();
        assert!(
            state_distance(&same.state, &est.state) < 1e-6,
            "{}",
            state_distance(&same.state, &est.state)
        );
        assert!(same.covariance.index("right.fx").is_none() && same.covariance.index("right.fy").is_some());
        for name in ["right.fx", "left.fy"] {
            let sigma = est.covariance.sigma(name).unwrap();
            for sign in [-2.0, 2.0] {
                let mut start = est.state.clone();
                let held = match name {
                    "right.fx" => &mut start.right.fx,
                    _ => &mut start.left.fy,
                };
                *held += sign * sigma;
                let target = *held;
                let end = bundle_adjust_holding(&start, &base.obs, &opts, &[name]).unwrap();
                let got = if name == "right.fx" { end.state.right.fx } else { end.state.left.fy };
                assert_eq!(got, target, "{name} not held");
                let dchi2 = end.chi2(1.0, &opts) - est.chi2(1.0, &opts);
                eprintln!("{name} at {sign:+} sigma: chi-square rise {dchi2:.3}");
                assert!((2.5..6.0).contains(&dchi2), "{name} {sign}: chi-square rise {dchi2}");
            }
        }
        assert!(bundle_adjust_holding(&est.state, &base.obs, &opts, &["right.focal"]).is_err());
        // Distortion is not estimated under these options: nothing to hold.
        assert!(bundle_adjust_holding(&est.state, &base.obs, &opts, &["left.k1"]).is_err());
    }

    /// Regression (calibration experiment, 3 px, seed 53): a wrong track "explained" by a
    /// point at depth 1e-11 made the reduced camera system indefinite by rounding (its
    /// terms some 1e24 times the cameras' information) and failed the whole estimate.
    /// Such a point now leaves the covariance, which then equals the covariance without
    /// its observations (to 1e-9 relative: the same sums in the same order); kept, it
    /// makes this covariance differ from that by more than that (rounding noise).
    #[test]
    fn a_point_at_a_camera_centre_leaves_the_covariance() {
        let s = synth(13, 60, 0.5, 0.0, false);
        let mut state = s.truth.clone();
        state.points[0] = Point3::from(state.left.unproject(&Point2::new(400.0, 300.0)) * 1e-11);
        let others: Vec<BundleObservation> = s.obs.iter().copied().filter(|o| o.point != 0).collect();
        let mut all = others.clone();
        for view in 0..3 {
            for side in [Side::Left, Side::Right] {
                let o = BundleObservation { point: 0, view, side, pixel: Point2::origin() };
                if let Some(r) = residual_pixels(&state, &o).filter(|r| r.iter().all(|v| v.is_finite())) {
                    all.push(BundleObservation { pixel: Point2::from(r), ..o });
                }
            }
        }
        assert!(all.len() >= others.len() + 2, "the collapsed point needs two observations");
        let opts = BundleOptions::default();
        let own: Vec<usize> = (0..state.points.len()).collect();
        let with = clustered_covariance(&state, &all, &opts, 0.5, &own).unwrap();
        let without = clustered_covariance(&state, &others, &opts, 0.5, &own).unwrap();
        assert_eq!(with.names, without.names);
        let scale = without.matrix.abs().max();
        assert!((&with.matrix - &without.matrix).abs().max() <= 1e-9 * scale);
    }

    #[test]
    fn covariance_names_and_perturbed() {
        let s = synth(9, 60, 0.5, 0.0, false);
        let res = bundle_adjust(&s.truth, &s.obs, &BundleOptions::default()).unwrap();
        let names = &res.covariance.names;
        for n in ["left.fx", "left.fy", "left.cx", "left.cy", "right.fx", "rig.rot0", "rig.tdir1"] {
            assert!(res.covariance.index(n).is_some(), "{n} missing from {names:?}");
        }
        for n in ["axis0.dir0", "axis1.pt1", "view1.angle0", "view2.angle1"] {
            assert!(res.covariance.index(n).is_some(), "{n} missing from {names:?}");
        }
        assert!(res.covariance.index("left.skew").is_none());
        assert_eq!(res.covariance.matrix.nrows(), names.len());
        assert!(res.covariance.sigma("left.fx").unwrap() > 0.0);
        let same = res.perturbed(&DVector::zeros(names.len())).unwrap();
        assert!(state_distance(&same, &res.state) < 1e-14);
        let mut d = DVector::zeros(names.len());
        d[res.covariance.index("left.fx").unwrap()] = 1.0;
        d[res.covariance.index("view2.angle0").unwrap()] = 0.01;
        let moved = res.perturbed(&d).unwrap();
        assert!((moved.left.fx - res.state.left.fx - 1.0).abs() < 1e-12);
        let (Motions::Joints { angles: a, .. }, Motions::Joints { angles: b, .. }) =
            (&moved.motions, &res.state.motions)
        else {
            panic!("joints expected")
        };
        assert!((a[2][0] - b[2][0] - 0.01).abs() < 1e-15);
        assert!(res.perturbed(&DVector::zeros(3)).is_err());
        // Free model names.
        let f = synth(10, 40, 0.5, 0.0, true);
        let opts = BundleOptions { square_pixels: true, ..BundleOptions::default() };
        let res = bundle_adjust(&f.truth, &f.obs, &opts).unwrap();
        assert!(res.covariance.index("view2.trans2").is_some() && res.covariance.index("left.fy").is_none());
        let same = res.perturbed(&DVector::zeros(res.covariance.names.len())).unwrap();
        assert!(state_distance(&same, &res.state) < 1e-14);
        assert!((res.state.left.fx - res.state.left.fy).abs() < 1e-12);
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(32))]
        /// `tangent_offset` inverts `perturbed` over every kind of parameter (intrinsics,
        /// rig rotation and baseline direction, joint axes, angles; free view poses), for
        /// random steps of realistic size: to near machine precision.
        #[test]
        fn tangent_offset_inverts_perturbed(seed in 0u64..1000, scale in 1e-4f64..0.05, free in proptest::bool::ANY) {
            use rand_distr::{Distribution, StandardNormal};
            let s = synth(seed, 30, 0.5, 0.0, free);
            let res = bundle_adjust(&s.truth, &s.obs, &BundleOptions { max_iterations: 0, ..BundleOptions::default() }).unwrap();
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let n = res.covariance.names.len();
            let delta = DVector::from_fn(n, |i, _| {
                let z: f64 = StandardNormal.sample(&mut rng);
                // Pixels for the intrinsics, radians / baselines for the rest.
                if res.covariance.names[i].starts_with("left.") || res.covariance.names[i].starts_with("right.") { z * 1000.0 * scale } else { z * scale }
            });
            let moved = res.perturbed(&delta).unwrap();
            let back = res.tangent_offset(&moved).unwrap();
            let err = (&back - &delta).amax();
            proptest::prop_assert!(err < 1e-9 * (1.0 + delta.amax()), "offset error {err:e}");
            let same = res.tangent_offset(&res.state).unwrap();
            proptest::prop_assert!(same.amax() < 1e-15);
        }
    }

    #[test]
    fn error_paths() {
        let s = synth(11, 30, 0.0, 0.0, false);
        let opts = BundleOptions::default();
        let ba = |st: &RigState, obs: &[BundleObservation], o: &BundleOptions| bundle_adjust(st, obs, o);
        assert!(matches!(ba(&s.truth, &[], &opts), Err(GeometryError::NotEnoughData { .. })));
        // A view with no observations.
        let no_view2: Vec<_> = s.obs.iter().copied().filter(|o| o.view != 2).collect();
        assert!(ba(&s.truth, &no_view2, &opts).is_err());
        // NaN pixel.
        let mut nan = s.obs.clone();
        nan[3].pixel.x = f64::NAN;
        assert!(ba(&s.truth, &nan, &opts).is_err());
        // Out-of-range indices.
        let mut oob = s.obs.clone();
        oob[0].point = 10_000;
        assert!(ba(&s.truth, &oob, &opts).is_err());
        // Non-positive focal length.
        let mut bad = s.truth.clone();
        bad.right.fx = 0.0;
        assert!(ba(&bad, &s.obs, &opts).is_err());
        bad.right.fx = -700.0;
        assert!(ba(&bad, &s.obs, &opts).is_err());
        // Zero baseline.
        let mut bad = s.truth.clone();
        bad.right_from_left.translation.vector = Vector3::zeros();
        assert!(ba(&bad, &s.obs, &opts).is_err());
        // Unobservable axis: elevation never moves.
        let mut bad = s.truth.clone();
        if let Motions::Joints { angles, commanded, .. } = &mut bad.motions {
            for row in angles.iter_mut().chain(commanded.iter_mut()) {
                row[1] = 0.0;
            }
        }
        let only_pan = |o: &&BundleObservation| o.view != 1;
        let obs02: Vec<_> = s.obs.iter().filter(only_pan).copied().collect();
        assert!(matches!(ba(&bad, &obs02, &opts), Err(GeometryError::Degenerate(_))));
        // Bad angle shapes, non-zero row 0.
        let mut bad = s.truth.clone();
        if let Motions::Joints { angles, .. } = &mut bad.motions {
            angles[0][0] = 0.1;
        }
        assert!(ba(&bad, &s.obs, &opts).is_err());
        let mut bad = s.truth.clone();
        if let Motions::Joints { commanded, .. } = &mut bad.motions {
            commanded.pop();
        }
        assert!(ba(&bad, &s.obs, &opts).is_err());
        // Free model with a non-identity view 0.
        let f = synth(12, 30, 0.0, 0.0, true);
        let mut bad = f.truth.clone();
        if let Motions::Free { ref_from_cam } = &mut bad.motions {
            ref_from_cam[0].translation.vector.x = 0.1;
        }
        assert!(ba(&bad, &f.obs, &opts).is_err());
        // Bad options.
        for o in [
            BundleOptions { robust: RobustLoss::Huber { scale_px: 0.0 }, ..opts.clone() },
            BundleOptions { robust: RobustLoss::Cauchy { scale_px: f64::NAN }, ..opts.clone() },
            BundleOptions { angle_prior_sigma: Some(-1.0), ..opts.clone() },
            BundleOptions { noise_sigma_px: Some(0.0), ..opts.clone() },
            BundleOptions { function_tolerance: f64::INFINITY, ..opts.clone() },
        ] {
            assert!(o.validate().is_err());
            assert!(matches!(ba(&s.truth, &s.obs, &o), Err(GeometryError::InvalidOption(_))));
        }
        assert!(opts.validate().is_ok());
        // Points seen once are left out without error; behind-camera points too.
        let mut partial = s.obs.clone();
        let lone = s.truth.points.len();
        let mut st = s.truth.clone();
        st.points.push(Point3::new(0.0, 0.0, 3.0));
        st.points.push(Point3::new(0.0, 0.0, -3.0));
        partial.push(BundleObservation {
            point: lone,
            view: 0,
            side: Side::Left,
            pixel: Point2::new(390.0, 284.0),
        });
        for view in 0..3 {
            partial.push(BundleObservation {
                point: lone + 1,
                view,
                side: Side::Left,
                pixel: Point2::new(100.0, 100.0),
            });
        }
        let res = ba(&st, &partial, &opts).unwrap();
        assert_eq!(res.report.observations, s.obs.len());
        assert_eq!(res.state.points[lone], st.points[lone]);
        assert_eq!(res.state.points[lone + 1], st.points[lone + 1]);
        // Angles held fixed without a prior.
        let fixed = BundleOptions { angle_prior_sigma: None, ..opts.clone() };
        let res = ba(&s.truth, &s.obs, &fixed).unwrap();
        assert!(res.covariance.index("view1.angle1").is_none());
        // Residual helper: behind the camera and out of range.
        assert!(residual_pixels(&st, &partial[partial.len() - 1]).is_none());
        let mut o = s.obs[0];
        o.view = 7;
        assert!(residual_pixels(&s.truth, &o).is_none());
    }
}
