//! The data of the rig bundle adjustment: what it is given and what it returns (module
//! docs of [`crate::bundle`], sections What it computes, Parameters and degrees of freedom,
//! Gauge).
//!
//! # What it holds
//!
//! - [`RigState`]: everything estimated. The intrinsics `K_L, K_R` (pixels) and the lens
//!   distortion of both cameras (OpenCV `plumb_bob`, dimensionless coefficients on
//!   normalised coordinates); the rig's `right_from_left` (left camera in the right
//!   camera's frame; the length of its translation is the scale gauge, so every length
//!   of the solution is in that unit); the [`Motions`] of the views; the scene points in
//!   the reference frame, the left camera of view 0 (x right, y down, z forward).
//! - [`Motions`]: `Free`, one rigid pose per view (6 dof for each view `k >= 1` not among
//!   [`BundleOptions::gauge_views`]), or
//!   `Joints`, a chain of revolute axes (4 dof per line) with the angles of every joint in
//!   every view (radians; one dof each for views `k >= 1` when the angle prior is on, held
//!   at the commanded values otherwise). A jointed view's pose is the product of
//!   exponentials, root first: `Rot(axis_0, theta_k0) * Rot(axis_1, theta_k1) * ...`.
//! - [`BundleObservation`]: one observed pixel (the crate's convention: `(0, 0)` at the
//!   centre of the top-left pixel) of one point, in one camera ([`Side`]) of one view.
//! - [`BundleOptions`]: which parameters are free (skew, square pixels, principal point,
//!   distortion, joint angles), the robust loss, the angle prior, the noise and
//!   covariance model, the measurement window, the stopping rules;
//!   [`BundleOptions::validate`] checks their ranges.
//! - [`BundleResult`] and [`BundleReport`]: the refined state, the summary of the run
//!   (RMS of the unweighted residual norms in pixels, iterations, why it stopped, the
//!   noise sigma used) and the covariance of the camera parameters.
//!   [`BundleResult::perturbed`] and [`BundleResult::tangent_offset`] map between states
//!   and the covariance's tangent coordinates (the retraction of `layout.rs`), so callers
//!   can propagate the covariance to derived quantities by finite differences.
//!
//! # Pitfalls
//!
//! - The gauge is part of the data: `Free` needs `ref_from_cam[0]` at the identity (and
//!   a held view in [`BundleOptions::gauge_views`] for every further group of views that
//!   shares no point with view 0's) and
//!   `Joints` a zero row 0 of the angles and of the commanded angles; both are checked
//!   when the problem is set up, not repaired.
//! - The sign of a joint angle goes with the direction of its axis: keep the initial axes'
//!   directions consistent with the commanded angles (the updates never flip an axis).
//! - `BundleOptions::default()` (Huber at 2 px, zero skew, a 0.05 deg reading-difference
//!   prior, tolerances `1e-12`, 100 iterations) is what every caller gets for the options
//!   it does not set: changing a default changes their results.

use nalgebra::{DVector, Isometry3, Point2, Point3};

use super::covariance::{Covariance, CovarianceModel};
use super::layout::{Layout, Param, local, retract};
use super::prior::AnglePrior;
use super::robust::RobustLoss;
use super::solver::chi2_of;
use crate::camera::Intrinsics;
use crate::distortion::{Distortion, DistortionTerms};
use crate::so3::{Line, rotation_about_line};
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
pub(super) fn joint_pose(axes: &[Line], angles: &[f64]) -> Isometry3<f64> {
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

impl RigState {
    /// The lens of the camera `side`.
    pub fn distortion(&self, side: Side) -> &Distortion {
        match side {
            Side::Left => &self.left_distortion,
            Side::Right => &self.right_distortion,
        }
    }
}

/// Options of [`bundle_adjust`].
///
/// [`bundle_adjust`]: super::bundle_adjust
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
    /// Estimate each camera's distortion coefficients `distortion_terms` in the model of
    /// the state's [`Distortion::kind`] (default off: the state's distortion, usually zero,
    /// is held).
    pub estimate_distortion: bool,
    /// Which coefficients `estimate_distortion` frees (default
    /// [`DistortionTerms::Radial2`]: `k1, k2`; the others are held at the state's values).
    pub distortion_terms: DistortionTerms,
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
    ///
    /// [`truncated_mean_shift`]: super::truncated_mean_shift
    pub measurement_window: Option<[f64; 4]>,
    /// Relative cost decrease below which the iteration stops.
    pub function_tolerance: f64,
    /// Relative step size below which the iteration stops.
    pub parameter_tolerance: f64,
    /// Views held at their start pose besides view 0 (only with [`Motions::Free`];
    /// default none): the gauge of each group of views that shares no point with the
    /// others (the disconnected segments of a sequence), whose points then live in the
    /// frame of their group's held view. Without one, such a group could move rigidly at
    /// no cost and the reduced camera system would be singular. Held views have no
    /// `view{k}` parameters.
    pub gauge_views: Vec<usize>,
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
            distortion_terms: DistortionTerms::Radial2,
            angle_prior_sigma: Some(0.05_f64.to_radians()),
            angle_prior: AnglePrior::ReadingDifferences,
            noise_sigma_px: None,
            covariance_model: CovarianceModel::Gaussian,
            measurement_window: None,
            function_tolerance: 1e-12,
            parameter_tolerance: 1e-12,
            gauge_views: Vec::new(),
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

/// Output of [`bundle_adjust`].
///
/// [`bundle_adjust`]: super::bundle_adjust
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
    ///
    /// [`angle_prior_chi2`]: super::angle_prior_chi2
    pub fn chi2(&self, noise_px: f64, options: &BundleOptions) -> f64 {
        chi2_of(self.report.final_rms_px, self.report.observations, &self.state.motions, noise_px, options)
    }

    /// The parameters of the covariance's names.
    fn params(&self) -> Result<Vec<Param>> {
        self.covariance
            .names
            .iter()
            .map(|n| {
                Param::parse(n, &self.state)
                    .ok_or_else(|| GeometryError::InvalidOption(format!("unknown parameter {n}")))
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
