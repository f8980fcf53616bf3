//! Rig bundle adjustment: maximum-likelihood refinement of a calibrated stereo rig, its
//! motions and the scene points on reprojection error (`docs/how-it-works.md#the-rig-bundle-adjustment`).
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
//! - `left.{k1,k2}`, `right.{k1,k2}` (only with `estimate_distortion`; the parameters of
//!   `BundleOptions::distortion_terms` in the camera's lens model: `k1 k2 p1 p2 k3` of
//!   the radial-tangential, `k1..k4` of the equidistant, `xi alpha` of the double sphere;
//!   [`Distortion`], dimensionless), additive update. The projection is the lens model's
//!   (`crate::lens`, the table): `K m(X)` with `m` its image-plane point, `None` outside
//!   its validity region (for the pinhole-plane models `Z <= 0`; the double sphere
//!   projects rays beyond 90 deg); the parameters not estimated are held at their given
//!   values (a known lens model is used as given, estimated or not). Pitfall: with small
//!   rotations `k1` correlates with the focal length and the principal point (a barrel
//!   lens looks like a shorter focal length towards the image edges); the covariance
//!   shows it.
//! - `rig.rot0..2`: left-multiplicative rotation update of `right_from_left`,
//!   `R <- exp(w) R`; `rig.tdir0..1`: the *direction* of its translation on the unit
//!   sphere (tangent-plane update, `t <- |t| normalize(t/|t| + B d)`), its length is held
//!   fixed (scale gauge).
//! - [`Motions::Free`]: `view{k}.rot0..2`, `view{k}.trans0..2` for `k >= 1` (but the
//!   held [`BundleOptions::gauge_views`]), the left-multiplicative update
//!   `ref_from_cam <- (exp(w), v) * ref_from_cam` (6 dof).
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
//! `|right_from_left.translation|` constant. Views that share no point with view 0's
//! group (the disconnected segments of a sequence, `Free` only) need a gauge of their
//! own: [`BundleOptions::gauge_views`] holds one view per further group at its start pose
//! (the identity, with the group's points in that view's frame); the groups then share
//! only the intrinsics and the rig. Everything else is observable given two
//! rotations about different axes: a caller that wants a different scale (a known
//! baseline) rescales before or after.
//!
//! # Algorithm
//!
//! The project's one Levenberg-Marquardt ([`crate::lm`], whose damping policy follows),
//! with the point-Schur back end of `normal.rs`. Marquardt's diagonal scaling (diagonal clamped to
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
//! (`cargo bench -p headalign-geometry --bench bundle`, 80 -> 52 ms). Above 8 views (a
//! sequence's keyframes) that dense product costs `c^2 n` with both the camera
//! parameters `c` and the points `n` growing with the views: `W` is then kept per point
//! over its own rows, `S` formed point by point (`n k^2`, `k` a point's rows) and
//! factored by a profile Cholesky with the per-view parameters first and the shared ones
//! last (linear in the views along a sequence; `sparse.rs`). The dense path stays for
//! few views, so their results are bit for bit what they were.
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
//! Measured once (2400 adjustments of the experiments' scene at 3 px; no command reproduces it): the
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
//!
//! # Files
//!
//! The module is one directory, split by concern; each file opens with its own `//!` block
//! (what it computes, degrees of freedom, units, the algorithm, pitfalls) and ends with the
//! tests of what it holds (`state.rs` and `normal.rs` are exercised by the solver's and the
//! covariance's tests). Every public item is re-exported here, so its path is
//! `bundle::Item` whichever file holds it.
//!
//! - `state.rs` (the problem's data): [`Side`], [`BundleObservation`], [`Motions`],
//!   [`RigState`], [`BundleOptions`], [`BundleReport`], [`BundleResult`].
//! - `layout.rs` (the problem's parametrisation): which camera parameters are free, their
//!   order and names, the retraction of a tangent step and its inverse, the homogeneous
//!   point update.
//! - `residual.rs` (the problem's residuals): [`residual_pixels`], [`residual_pixels_at`]
//!   and the analytic linearisation of one observation.
//! - `prior.rs` (the problem's priors): [`AnglePrior`], [`angle_prior_residuals`],
//!   [`angle_prior_chi2`], the prior rows of the normal equations.
//! - `problem.rs` (the problem as the solver sees it): the checked, normalised start state,
//!   the observations used, the cost with the measurement window applied.
//! - `robust.rs` (the robust loss): [`RobustLoss`], the IRLS weights, the measurement
//!   window's [`truncated_mean_shift`].
//! - `normal.rs` (the solver's linear algebra): normal equations, reduced camera system
//!   (Schur complement over the points), Marquardt damping, the damped solve: the
//!   point-Schur back end of [`crate::lm`].
//! - `sparse.rs` (the linear algebra of many views): the per-point structure of `W`, the
//!   point-by-point Schur complement, the profile Cholesky of the reduced system.
//! - `solver.rs` (the solver): the adjustment as a [`crate::lm`] problem and the entry
//!   points [`bundle_adjust`], [`bundle_adjust_with_checkpoint`] ([`BundleCheckpoint`]),
//!   [`bundle_adjust_at_depth_scale`], [`bundle_adjust_holding`].
//! - `covariance.rs` (the covariance): [`Covariance`], [`CovarianceModel`], the covariance
//!   at the solution, [`clustered_covariance`], the depth scale [`log_depth_scale`].
//! - `synthetic.rs` ([`synthetic`], also at the crate root): seeded rig problems with known
//!   truth for tests, benchmarks and experiments.
//! - `test_support.rs`: fixtures shared by the tests (test builds only).
//!
//! [`Distortion`]: crate::distortion::Distortion
//! [`so3::exp`]: crate::so3::exp
//! [`GeometryError::Degenerate`]: crate::GeometryError::Degenerate

mod covariance;
mod layout;
mod normal;
mod prior;
mod problem;
mod residual;
mod robust;
mod solver;
mod sparse;
mod state;
pub mod synthetic;
#[cfg(test)]
mod test_support;

pub use covariance::{Covariance, CovarianceModel, clustered_covariance, log_depth_scale};
pub use layout::tangent_basis;
pub(crate) use normal::Normal;
pub use prior::{AnglePrior, angle_prior_chi2, angle_prior_residuals};
pub use residual::{residual_pixels, residual_pixels_at};
pub use robust::{RobustLoss, truncated_mean_shift};
pub use solver::{
    BundleCheckpoint, bundle_adjust, bundle_adjust_at_depth_scale, bundle_adjust_holding,
    bundle_adjust_with_checkpoint,
};
pub use state::{BundleObservation, BundleOptions, BundleReport, BundleResult, Motions, RigState, Side};

/// `a > b`, false if either is NaN.
fn gt(a: f64, b: f64) -> bool {
    a > b
}
