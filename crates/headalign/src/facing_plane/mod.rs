//! The planar route: alignment facing a plane or a scene too far for stereo depth (paper
//! section 3.3, issue 34), from the verge/tilt procedure's views.
//!
//! When every stereo match lies on one plane (a wall, a door) or the scene is so far away
//! that the baseline sees no depth, stereo gives no projective structure and the general
//! route ([`crate::verge_tilt`]) has nothing to build 3D homographies from. Each camera's
//! own views are then related by 3x3 homographies, and those still hold the head's axes
//! (paper section 3.3): a rotation's homography leaves the image of the line at infinity
//! perpendicular to its axis fixed. The route, each camera on its own:
//! 1. **detection** ([`detect_scene`]): the reference view's stereo matches against one
//!    homography and against `F` at the same threshold;
//! 2. **homographies** (`start.rs`): per rotated view, a robust 3x3 homography between
//!    the reference image and the view's image of this camera (RANSAC on transfer error);
//! 3. **start** (`start.rs`): `K` by rotating-camera self-calibration from those
//!    homographies taken as infinite homographies `K R K^-1` (Hartley; the solver the
//!    general route's starts use), each single-joint rotation `R = (K^-1 H K)^T`, its
//!    axis from the rotation's logarithm and the commanded angle's sign, the plane
//!    fronto-parallel at 3 m, the axes through the camera centre;
//! 4. **maximum likelihood** (`refine.rs`): unknowns `fx, fy, cx, cy` (zero skew), each
//!    moved joint's axis (2 dof of direction, 2 of the axis' offset from the camera
//!    centre), every rotation angle (the commanded encoder difference as a prior of
//!    [`PlanarOptions::angle_prior_sigma_deg`]), the plane `m = n / d` (3) and each
//!    point's 2 dof on it; residuals in pixels, model and analytic Jacobians in
//!    [`headalign_geometry::plane`]; Levenberg-Marquardt with a Schur complement over
//!    the points; covariance from the normal equations;
//! 5. **profile** (`profile.rs`, [`PlanarOptions::normal_profile_z`]): the covariance
//!    widened to the largest of its linearisations at the estimate and at the camera
//!    re-adjusted with the plane's normal held one sigma either side (the normal is the
//!    ill-determined direction of a wall a few metres away), only where the data
//!    determine a plane: it moves some view by [`FAR_PARALLAX_PX`] and the camera
//!    re-adjusted with the plane at infinity (`m = 0`) costs more than the chi-square
//!    bound at 5 % ([`PlaneTest`]; at 1 px the far scene's fitted plane is noise that
//!    moves the views by a pixel or two);
//! 6. **alignment**: [`crate::alignment::solve_alignment_axes`] from each camera's axes
//!    and intrinsics (alignment needs no baseline); sigmas by [`alignment_sigmas`].
//!
//! What a plane cannot give is not reported as a number: the distances (the plane's, the
//! axes' offsets, the baseline: a gauge, fixed by a unit-variance prior on the offsets
//! and on `m` that no observable quantity feels), the rig's translation, the plane's
//! normal when the scene is far (its sigma then exceeds [`NORMAL_UNDETERMINED_DEG`], the
//! plane moves no view by [`FAR_PARALLAX_PX`], or the plane at infinity explains the data
//! ([`PlaneTest`]): [`CameraPlanar::plane_normal`] is `None` and the scene is reported
//! `far`).
//!
//! Degrees of freedom per camera: 4, plus 4 per moved joint, 1 per (view, moved joint), 3
//! and 2 per point, less the one gauge. Pitfalls: a far scene that is not at infinity is
//! fitted as one plane, and the depth spread about it is unmodelled (noise-free seed 1 of
//! the room at 240-960 baselines: 0.012 deg of elevation error; at 800-3200 baselines, the
//! `far` preset, 0.0004 deg); the two cameras are estimated separately (their rotation angles are
//! the same joints' but are not tied), which loses a little precision and keeps each
//! problem small.

mod check;
mod detect;
mod profile;
mod refine;
mod sigmas;
mod start;
#[cfg(test)]
mod tests;

use headalign_geometry::bundle::Side;
use headalign_geometry::camera::Intrinsics;
use headalign_geometry::ransac::RansacOptions;
use headalign_geometry::so3::Line;
use headalign_platform::{Encoders, Joint};
use nalgebra::{DMatrix, Unit, Vector3};
use serde::Serialize;

pub use check::{CameraCheck, MIN_CHECK_TRACKS, PlanarCheck, UNCHECKED, check_alignment};
pub use detect::{SceneCheck, SceneKind, detect_scene};
pub use profile::{PLANE_TEST_Z, PlaneTest, chi_square_quantile};
pub use sigmas::alignment_sigmas;

use crate::alignment::CameraAxes;
use crate::error::AlignError;
use crate::observations::View;
use crate::verge_tilt::ENCODER_SIGMA_DEG;

/// Plane normal sigma beyond which the plane counts as undetermined (the scene acts as
/// the plane at infinity), degrees.
pub const NORMAL_UNDETERMINED_DEG: f64 = 10.0;

/// Below this largest displacement (pixels) that the plane's distance adds to the infinite
/// homographies of a camera's views, `f |t| |m|`, the plane is taken as at infinity: its
/// normal is reported undetermined and the scene `far` (a wall 4 m away turned 3 deg
/// about the pan axis, 0.13 m off the camera, adds about 1.2 px; the `far` preset
/// under 0.1 px).
pub const FAR_PARALLAX_PX: f64 = 0.5;

/// The homographies' RANSAC threshold is at least this many transfer-error sigmas
/// (`sqrt 2` times the pixel noise the detection estimated): a noise-only match lies
/// beyond it with probability `exp(-8)`.
pub const HOMOGRAPHY_SIGMAS: f64 = 4.0;

/// Options of [`estimate_planar`].
#[derive(Debug, Clone)]
pub struct PlanarOptions {
    /// RANSAC of each camera's image homographies; threshold on the transfer error in
    /// pixels (default 3 px, raised to [`HOMOGRAPHY_SIGMAS`] sigmas of the noise the
    /// detection measured; the plane and the far scene leave no parallax beyond 0.3 px).
    pub homography: RansacOptions,
    /// Standard deviation of the prior on each rotation angle, degrees (default
    /// [`ENCODER_SIGMA_DEG`], as the general route).
    pub angle_prior_sigma_deg: f64,
    /// After the first adjustment, observations farther than this many robust standard
    /// deviations from their prediction are dropped (default 4: a 2D residual's squared
    /// norm beyond 16 sigma^2 has probability exp(-8) under Gaussian noise).
    pub reselect_sigmas: f64,
    /// Fewest tracks a rotated view must share with the reference view (default 12).
    pub min_tracks: usize,
    /// Levenberg-Marquardt iterations per pass (default 100).
    pub max_iterations: usize,
    /// Pixel noise (per coordinate) that weights the covariance, pixels; `None` (default):
    /// the fit's own estimate from its residuals. Experiments set it to the simulated
    /// noise on exact observations to get the Cramér-Rao bound at the truth.
    pub covariance_sigma_px: Option<f64>,
    /// The covariance's profile over the plane normal (`profile.rs`): the ends lie this
    /// many sigmas of the normal's direction either side (default `Some(1.0)`, as the
    /// general route's depth-scale profile); `None`: the linearised covariance at the
    /// estimate.
    pub normal_profile_z: Option<f64>,
}

impl Default for PlanarOptions {
    fn default() -> Self {
        Self {
            homography: RansacOptions { threshold: 3.0, ..RansacOptions::default() },
            angle_prior_sigma_deg: ENCODER_SIGMA_DEG,
            reselect_sigmas: 4.0,
            min_tracks: 12,
            max_iterations: 100,
            covariance_sigma_px: None,
            normal_profile_z: Some(1.0),
        }
    }
}

impl PlanarOptions {
    /// Check every option (field docs).
    pub fn validate(&self) -> Result<(), AlignError> {
        self.homography
            .validate()
            .map_err(|e| AlignError::Observations(format!("planar homography: {e}")))?;
        let bad = |what: &str| Err(AlignError::Observations(format!("planar options: {what}")));
        if !(self.angle_prior_sigma_deg.is_finite() && self.angle_prior_sigma_deg > 0.0) {
            return bad("angle_prior_sigma_deg must be positive");
        }
        if !(self.reselect_sigmas.is_finite() && self.reselect_sigmas > 1.0) {
            return bad("reselect_sigmas must exceed 1");
        }
        if self.covariance_sigma_px.is_some_and(|s| !(s.is_finite() && s > 0.0)) {
            return bad("covariance_sigma_px must be positive");
        }
        if self.normal_profile_z.is_some_and(|z| !(z.is_finite() && z > 0.0)) {
            return bad("normal_profile_z must be positive");
        }
        if self.min_tracks < 4 || self.max_iterations == 0 {
            return bad("min_tracks must be at least 4 and max_iterations positive");
        }
        Ok(())
    }
}

/// One camera's planar calibration, in its own reference frame.
#[derive(Debug, Clone, Serialize)]
pub struct CameraPlanar {
    /// Which camera.
    #[serde(skip)]
    pub side: Side,
    /// Intrinsics (zero skew).
    pub intrinsics: Intrinsics,
    /// Pan axis direction, directed like its encoder (camera frame of the reference view).
    pub pan: [f64; 3],
    /// Elevation axis direction.
    pub elevation: [f64; 3],
    /// This camera's vergence axis direction, if a view turned it.
    pub verge: Option<[f64; 3]>,
    /// The plane's unit normal (camera frame, towards the camera), `None` when the data
    /// cannot tell it (far scene: module docs).
    pub plane_normal: Option<[f64; 3]>,
    /// Sigma of the plane normal's direction, degrees.
    pub plane_normal_sigma_deg: f64,
    /// The largest displacement the plane's distance adds to the infinite homography of a
    /// view, pixels ([`FAR_PARALLAX_PX`]).
    pub plane_parallax_px: f64,
    /// Covariance of [`CameraPlanar::parameter_names`] (pixels, radians).
    #[serde(skip)]
    pub covariance: DMatrix<f64>,
    /// Names of the covariance's rows: `fx, fy, cx, cy`, then per axis its two tangent
    /// components (`pan.dir0`, `pan.dir1`, ...) in the basis of
    /// [`headalign_geometry::plane::tangent_basis`].
    pub parameter_names: Vec<String>,
    /// Estimated pixel noise (per coordinate), pixels.
    pub sigma_px: f64,
    /// RMS residual of the final fit, pixels.
    pub rms_px: f64,
    /// Largest sigma ratio the profile over the plane normal applied (1: none;
    /// [`PlanarOptions::normal_profile_z`]).
    pub profile_widening: f64,
    /// The fitted plane against the plane at infinity ([`PlaneTest`]): a plane it does not
    /// reject is neither profiled nor reported.
    pub plane_test: PlaneTest,
    /// Observations in the final fit.
    pub observations: usize,
    /// Points in the final fit.
    pub points: usize,
    /// Each moved joint's estimated line (pan, elevation, vergence order; camera frame of
    /// the reference view, points in the scale gauge of the module docs), for the check
    /// after the move ([`check_alignment`]); not reported: its points are no distances.
    #[serde(skip)]
    pub joint_lines: Vec<(Joint, Line)>,
    /// The plane `m = n / d` in the same gauge (only `p m^T` products are observable).
    #[serde(skip)]
    pub plane_m: [f64; 3],
}

impl CameraPlanar {
    /// The axes and intrinsics alignment needs.
    pub fn axes(&self) -> CameraAxes {
        let u = |a: [f64; 3]| Unit::new_normalize(Vector3::from(a));
        CameraAxes {
            intrinsics: self.intrinsics,
            pan: u(self.pan),
            elevation: u(self.elevation),
            verge: self.verge.map(u),
        }
    }

    /// Sigma of a named parameter (pixels or radians), if present.
    pub fn sigma(&self, name: &str) -> Option<f64> {
        let i = self.parameter_names.iter().position(|n| n == name)?;
        Some(self.covariance[(i, i)].max(0.0).sqrt())
    }
}

/// The planar route's result.
#[derive(Debug, Clone, Serialize)]
pub struct PlanarCalibration {
    /// Left camera.
    pub left: CameraPlanar,
    /// Right camera.
    pub right: CameraPlanar,
    /// The scene check that chose the route, refined by the estimate (`far` when neither
    /// camera determines the plane's normal).
    pub scene: SceneCheck,
    /// What the planar route cannot determine, by name (reported, never a number).
    pub undetermined: Vec<String>,
    /// Encoder readings of the reference view.
    pub reference_encoders: Encoders,
    /// Views left out, with the reason.
    pub dropped_views: Vec<String>,
}

/// The quantities a plane never determines (module docs).
pub const UNDETERMINED: [&str; 4] = [
    "plane distance (scale gauge)",
    "axis offsets from the camera centres (scale gauge)",
    "rig translation and baseline",
    "rig rotation between the cameras (the cameras are estimated separately)",
];

/// Run the planar route (module docs) on the procedure's views (the first is the
/// reference; rig, diagonal and vergence views are all used). `scene` is the detection's
/// result, carried into the report.
pub fn estimate_planar(
    views: &[View],
    scene: SceneCheck,
    options: &PlanarOptions,
) -> Result<PlanarCalibration, AlignError> {
    options.validate()?;
    let first = views.first().ok_or_else(|| AlignError::Observations("no views".into()))?;
    // The homographies' threshold grows with the noise the detection measured: a fixed
    // 3 px on the one-sided transfer error (noise sqrt 2 sigma a coordinate) keeps only
    // 40 % of the matches at 2 px, and those whose noise happens to agree with the
    // homography: a biased sample (2-4 deg of error at 2 px before this rule).
    let mut options = options.clone();
    if scene.sigma_px.is_finite() {
        options.homography.threshold =
            options.homography.threshold.max(HOMOGRAPHY_SIGMAS * std::f64::consts::SQRT_2 * scene.sigma_px);
    }
    let options = &options;
    let mut dropped = Vec::new();
    let left = calibrate_camera(views, Side::Left, options, &mut dropped)?;
    let right = calibrate_camera(views, Side::Right, options, &mut dropped)?;
    let mut scene = scene;
    let mut undetermined: Vec<String> = UNDETERMINED.iter().map(|s| s.to_string()).collect();
    if left.plane_normal.is_none() && right.plane_normal.is_none() {
        scene.kind = SceneKind::Far;
        scene.why.push_str(&format!(
            "; the plane's distance moves the images by at most {:.2} / {:.2} px (left / right), its normal's sigma is {:.1} / {:.1} deg and the plane at infinity raises the cost by {:.1} / {:.1} (5 % bounds {:.1} / {:.1}): the scene acts as the plane at infinity",
            left.plane_parallax_px,
            right.plane_parallax_px,
            left.plane_normal_sigma_deg,
            right.plane_normal_sigma_deg,
            left.plane_test.rise,
            right.plane_test.rise,
            left.plane_test.threshold,
            right.plane_test.threshold
        ));
        undetermined.push("plane normal (far scene)".into());
    } else {
        scene.kind = SceneKind::Planar;
        scene.why.push_str(&format!(
            "; the plane's distance moves the images by up to {:.2} / {:.2} px (left / right)",
            left.plane_parallax_px, right.plane_parallax_px
        ));
    }
    Ok(PlanarCalibration {
        left,
        right,
        scene,
        undetermined,
        reference_encoders: first.capture.encoders,
        dropped_views: dropped,
    })
}

/// The joints that move camera `side` (pan, elevation, its vergence).
fn camera_joints(side: Side) -> [Joint; 3] {
    match side {
        Side::Left => [Joint::Pan, Joint::Elevation, Joint::VergeLeft],
        Side::Right => [Joint::Pan, Joint::Elevation, Joint::VergeRight],
    }
}

/// Steps 2-4 of the module docs for one camera.
fn calibrate_camera(
    views: &[View],
    side: Side,
    options: &PlanarOptions,
    dropped: &mut Vec<String>,
) -> Result<CameraPlanar, AlignError> {
    let data = start::camera_data(views, side, options, dropped)?;
    let problem = start::initial_problem(&data, side)?;
    let fit = refine::maximum_likelihood(problem, options)?;
    Ok(fit.into_camera(side))
}
