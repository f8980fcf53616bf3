//! Robot stages: pan alignment from a forward drive (paper section 4, DESIGN.md section 2
//! step 6) and steering-wheel zeroing (paper section 7, step 8), in point mode, generic
//! over the platform traits ([`StereoHead`] + [`Vehicle`]).
//!
//! Both use the calibrated rig of the verge/tilt stage ([`RigCalibration`] and the
//! vergence axes) to triangulate the stereo matches of a view at any encoder readings
//! (cameras predicted by the calibrated kinematics), in the current left camera frame,
//! in stereo-baseline units.
//!
//! **Rigid motion of a drive** (both stages): triangulate before and after; RANSAC over
//! 3-point rigid fits (Umeyama) of `Y = R X + t` (`cam2_from_cam1`), each track scored by
//! its linear triangulation from all four views under the model and the largest of its
//! four reprojection errors (pixels; a score that trusts neither stereo pair's depth
//! alone); then the maximum-likelihood motion ([`refine_rig_motion`]: motion and points
//! on the reprojection error in all four images, Huber, covariance) and a guided
//! re-selection of the tracks with it (twice); finally a maximum-likelihood pass (as the
//! verge/tilt estimator's): the noise estimated from the median residual, the tracks
//! within 3.5 of it kept, plain least squares (a wrong track inside the RANSAC threshold
//! otherwise biased even noise-free drives, 0.006 deg of pan on demo seed 1). The
//! camera centre moved by `c = -R^T t` (first camera frame) with covariance from that
//! adjustment.
//!
//! **Rig check** (every stage, [`RigCheck`]): the rig predicted at the stage's readings
//! is tested against the stage's own stereo pairs before any drive is registered: each
//! stereo match triangulated from its two pixels, the larger of its two reprojection
//! errors, median over the matches, against [`RIG_MISFIT_SIGMAS`] times the
//! calibration's noise estimate. A rig that misfits (a vergence axis measured badly from
//! the 3 deg vergence move, so the cameras predicted at vergence readings far from it
//! turn wrongly: at 3 px one robot trial in 300 had the rig 1.9 deg off, a median misfit
//! of 13 px, and its drive registration found 3 consistent tracks) is re-fitted to the
//! pairs in its vertical components, which the vertical disparities determine (rotations
//! about the right camera's x and z axes, the baseline's y component), and the stage goes
//! on with that correction, applied also to every perturbed rig of the uncertainty
//! propagation below (which still describes the predicted rig: conservative for the
//! corrected one); a rig that still misfits is [`AlignError::RigMisfit`].
//!
//! **Pan** (per drive): two estimates of the displacement direction:
//! - *image*: left-left matches, the second image derotated by the measured `R`
//!   (`K R^T K^-1`), matches kept only within `guide_px` of the flow the reconstruction
//!   predicts, then [`translation_from_flow`] (epipole by 2-point RANSAC on flow lines,
//!   LM on the sphere, re-selection at 3.5 robust sigmas, `t = K^-1 e`);
//! - *stereo*: `c` of the maximum-likelihood motion.
//!
//! Each is turned into the displacement of the pan axis (`d = (R^T - I) o + c`, `o` a
//! point of the calibrated pan axis) and rotated back by half the measured heading change
//! (the chord of an arc makes half the turn angle with the tangent; exact for the
//! rear-axle line, so this assumes the pan axis stands over it, and is a no-op when the
//! wheel is straight: hence the demo's pan, steering, pan order). The pan correction is
//! the signed angle about the pan axis from the head's forward direction (mean of the
//! optical axes, projected) to that direction.
//!
//! **Uncertainty of the pan**: two parts. (1) The verge/tilt calibration's (both `K`s,
//! the rig, the pan and elevation axes; [`RigCalibration`]'s bundle covariance): the
//! whole computation after the data selections (rig at the readings, the least-squares
//! motion refit from the solution, the derotated flow and the epipole refit, the two
//! angles) is re-run at each calibration parameter moved by +-[`PROPAGATION_STEP_SIGMAS`]
//! of its sigma, and central differences give the 2x2 covariance of the two estimates
//! `J C J^T`. It dominates at 1 px (about 0.3 deg, mostly the left principal point: the
//! travel direction is measured in the left camera frame) and is common to both
//! estimates.
//! (2) The image noise, in two parts: the drive motion's (its 6x6 maximum-likelihood
//! covariance, moved through both estimates by central differences along its Cholesky
//! factor: the image estimate depends on the motion's rotation through the derotation
//! of the flow, where a rotation error `dw` shifts the epipole by about `dw Z / d`,
//! depth over drive, and both depend on it through the half turn and the pan axis'
//! offset; this term was missing: the image estimate's sigma was the flow's alone, 0.17
//! deg at 1 px on seed 4 where the motion adds 0.18 deg, correlated 0.9 with the
//! stereo estimate's 0.21 deg, so the combination trusted the image estimate too much),
//! and the flow's given the motion (the epipole's LM covariance, image estimate only).
//! The estimates are combined with the weights that minimise the variance under the sum
//! of (1) and (2) (clamped to a convex combination); the flow and the motion share the
//! left images, whose correlation is not modelled, so the stated sigma takes the bound
//! valid for any correlation of those two, `(sqrt(w^T C_m w) + w_i s_flow)^2`, plus
//! `w^T C_cal w`. Measured 95 % coverage in `experiment coverage` (robot group). The drive
//! is repeated (`iterations`) after correcting, as the paper suggests.
//!
//! **The vergence axes' uncertainty** (given [`AxisPerturbations`],
//! [`crate::procedure::VergeTiltOutcome::axis_perturbations`]): the rig predicted at a
//! drive's readings turns each camera about its vergence axis from the reference, and the
//! axes come from resections of the vergence view, not from the bundle. Part (1) then
//! moves the axes with each calibration parameter (re-derived with the scene points
//! following and the poses re-resected) and adds the resected poses' own noise (modes of a
//! parametric bootstrap of the robust resection: at 3 px its Huber loss and 5 px outlier
//! gate spread the poses 1.4x beyond the least-squares covariance). Measured at 3 px
//! (the removed `examples/planarity_chi2.rs`, `RIGCHI=1`, seeds 1-30): the rotation error of the rig
//! at the readings has a chi-square mean (3 expected) of 9.7 with the axes held as exact,
//! 3.5 with their uncertainty (2.9 at the reference readings). Without
//! `AxisPerturbations` the axes are held (the former behaviour).
//!
//! **The readings' noise** (`encoder_sigma_deg` of [`PanOptions`] and
//! [`SteeringOptions`], default the calibration prior's 0.01 deg): the rig is predicted
//! at the drive's readings, so part (1) also moves each joint's reading (its difference
//! from the reference reading: two reads) and adds those modes; the corrected pan is the
//! pan reading plus the correction, so that read's noise adds to the pan's sigma. With
//! noise-free images and readings at 0.01 deg the rig's error from the readings alone
//! failed the planarity test in 12 of 20 `fig5-pan-tilt` trials before it was counted
//! (the rest of the fix: [`crate::alignment::verge_axes_from_motion`] ignores the
//! unmoved joints' jitter).
//!
//! **Planarity** (both stages): the out-of-plane part of a drive, its rotation about the
//! two axes perpendicular to the pan axis (radians) and the centre's displacement along
//! it (baselines), is tested by its chi-square (3 dof) against its covariance (the
//! motion's, by central differences through the motion's perturbation, plus the
//! calibration's as above); above `planarity_chi2_max` (default the 99.999 % quantile,
//! a false alarm rate of 1e-5 per drive) is [`AlignError::NotPlanar`]. The former fixed
//! limits (1 deg off-axis rotation; screw axis 10 deg, pitch 0.2) both failed planar
//! drives (3 of 260 experiment trials) and missed smaller real tilts. The angle of `d`
//! out of the plane perpendicular to the pan axis is reported as an elevation check.
//!
//! **Steering**: drives at `settings_deg` relative to the current steering reading; each
//! gives the motion `cam1_from_cam2` (the robot's motion in a robot-fixed frame): a turn
//! below `min_turn_deg` is [`AlignError::TurnTooSmall`]; the planarity test above names
//! a motion that is not planar. One drive failing it while the others pass is left out
//! as an outlier when three remain and they all pass (`SteeringOutcome::dropped_turns`):
//! at 3 px, seed 170's fourth drive has chi-square 43.5 with the axes held as exact and
//! 42.8 with their uncertainty propagated, on the same drives (against 25.9; without
//! [`crate::estimate::EstimationOptions::image_border`] its first drive, far points only,
//! 42.7 / 42.8; an earlier reading of 30.0 with the uncertainty came from a second run
//! whose pan stage had left the head elsewhere, so different drives); a robot that really
//! pitches or rolls fails every drive. The turning centres
//! (planar motion about the pan axis) give the steering zero, wheelbase and forward
//! direction ([`steering_from_turns`]); the wheel is then set straight. The zero's sigma: each drive's motion covariance
//! (independent drives) through its centre, plus the calibration's (every drive refitted
//! under each perturbed calibration), by central differences (96 % coverage over 100
//! trials at 1 px). A zero whose sigma exceeds `max_sigma_zero_deg` (default 10 deg)
//! is [`AlignError::SteeringUndetermined`], before the wheel is commanded: at 3 px with
//! exact readings, seed 170's first drive is left out and the other three (24-57 tracks
//! each) give -87 +- 64 deg.
//!
//! Degenerate drives: a median flow below `min_flow_px` is [`AlignError::DriveTooShort`].
//! Every drive is followed by the reverse drive, so the robot ends where it started.

use std::collections::HashMap;

use headalign_geometry::camera::{Intrinsics, ProjectiveCamera, dehomogenise3};
use headalign_geometry::essential::refine_relative_pose;
use headalign_geometry::ransac::{Estimator, RansacOptions, ransac};
use headalign_geometry::registration::similarity_fit;
use headalign_geometry::rigmotion::{
    RigMotionEstimate, RigMotionOptions, RigTrack, StereoRig, consistent_tracks, four_cameras, perturb,
    refine_rig_motion, refine_rig_motion_dropping, track_error, track_residuals,
};
use headalign_geometry::so3::screw_from_isometry;
use headalign_geometry::steering::{SteeringSolution, Turn, steering_from_turns};
use headalign_geometry::translation::{
    FlowMatch, TranslationOptions, derotate, refit_translation, translation_from_flow,
};
use headalign_geometry::triangulation::triangulate_linear;
use headalign_platform::{Encoders, Joint, StereoCapture, StereoHead, Vehicle};
use nalgebra::{
    DMatrix, DVector, Isometry3, Matrix2, Matrix3, Matrix6, Point2, Point3, SMatrix, SVector, Translation3,
    Unit, UnitQuaternion, Vector2, Vector3, Vector6,
};
use serde::Serialize;

use crate::alignment::VergeAxes;
use crate::error::{AlignError, StepContext};
use crate::estimate::{ENCODER_SIGMA_DEG, RigCalibration};
use crate::procedure::{AxisPerturbations, PROPAGATION_STEP_SIGMAS, predicted_poses};

/// The 99.999 % quantile of a chi-square with 3 degrees of freedom: the default
/// planarity limit, a false alarm rate of 1e-5 per drive (a demo run tests 8 drives; at
/// the 99.9 % quantile, 16.27, one of 260 `fig5-pan-tilt` trials failed, chi-square
/// 17.6, as that rate predicts; a 0.3 deg pitch gives chi-square values in the
/// thousands even at 1 px).
pub const PLANARITY_CHI2_MAX: f64 = 25.902;

/// Fewest samples of a drive registration's RANSAC (the robot stages' default
/// `registration`; the generic default is 50). At 50, a steering drive of `experiment
/// coverage`'s seed 222 at 1 px kept a wrong motion with 39 tracks (0.07 baselines out of
/// the plane, within its own inflated covariance) where 80 fit the true one, and the
/// steering zero's sigma came out 6 times the median; over `fig5-pan-tilt --only 1,3
/// --seed 201 --trials 120` the RMS steering error at 1 px fell from 0.39 to 0.25 deg
/// with 200 (3 px: 1.01 and 1.08 deg, within their sampling noise), sigmas above 4 times
/// the median from 11 to 8 of 120, for 40 % more CPU time in those trials.
pub const DRIVE_MIN_ITERATIONS: usize = 200;

/// Options of [`align_pan`].
#[derive(Debug, Clone, PartialEq)]
pub struct PanOptions {
    /// Forward drive, metres. Default 0.10 (the paper's).
    pub drive_m: f64,
    /// Drives (each after correcting the last). Default 2.
    pub iterations: usize,
    /// Epipole estimation. Default [`TranslationOptions::default`] (3 px threshold).
    pub translation: TranslationOptions,
    /// Registration RANSAC (threshold: reprojection pixels). Default threshold 4 px, at
    /// least [`DRIVE_MIN_ITERATIONS`] samples.
    pub registration: RansacOptions,
    /// Flow matches farther than this from the reconstruction's prediction are dropped,
    /// pixels. Default 6.
    pub guide_px: f64,
    /// Smallest median flow accepted, pixels. Default 2.
    pub min_flow_px: f64,
    /// Derotate and guide the image matches with the stereo motion's rotation. Default
    /// true: the maximum-likelihood motion locates a 0.10 m drive's turn to about
    /// 0.02 deg at 1 px, and a wheel 1 deg off turns the robot by 0.17 deg, which shifts
    /// the image by 2 px, a third of the flow of a far scene (false assumes a pure
    /// translation, as the paper, which needs a straight wheel).
    pub use_stereo_rotation: bool,
    /// Planarity test: largest chi-square (3 degrees of freedom) of a drive's rotation
    /// about the two axes perpendicular to the pan axis and its translation along it,
    /// against their covariance (the motion's and the calibration's); more is
    /// [`AlignError::NotPlanar`] (the robot pitched or rolled, or the pan axis is not
    /// perpendicular to the ground). Default [`PLANARITY_CHI2_MAX`], the 99.999 %
    /// quantile: a false alarm rate of 1e-5 per drive when the covariance is right.
    pub planarity_chi2_max: f64,
    /// Standard deviation of each joint's encoder reading, degrees (the noise of the
    /// readings the drive's rig is predicted at; 0: exact). It enters the calibration
    /// part of the covariance (`calibration_covariance`): a reading 0.01 deg off turns
    /// the predicted stereo rig by that much, which the planarity test otherwise sees as
    /// the robot tilting (noise-free images with readings at 0.01 deg failed 12 of 20
    /// `fig5-pan-tilt` trials). Default [`ENCODER_SIGMA_DEG`], the noise the
    /// calibration's angle prior assumes.
    pub encoder_sigma_deg: f64,
    /// Multiply the pixel thresholds (`registration`, `translation`'s RANSAC, `guide_px`)
    /// by the calibration's noise estimate when it exceeds 1 px ([`threshold_scale`]):
    /// the defaults are for about 1 px of noise (at 3 px the 4 px registration threshold
    /// kept 5 of 125 tracks of a drive). Default true.
    pub scale_to_noise: bool,
}

impl Default for PanOptions {
    fn default() -> Self {
        Self {
            drive_m: 0.10,
            iterations: 2,
            translation: TranslationOptions::default(),
            registration: RansacOptions {
                threshold: 4.0,
                min_iterations: DRIVE_MIN_ITERATIONS,
                ..RansacOptions::default()
            },
            guide_px: 6.0,
            min_flow_px: 2.0,
            use_stereo_rotation: true,
            planarity_chi2_max: PLANARITY_CHI2_MAX,
            encoder_sigma_deg: ENCODER_SIGMA_DEG,
            scale_to_noise: true,
        }
    }
}

/// Factor of a robot stage's pixel thresholds for the calibration's noise estimate
/// `sigma_px` (pixels): `max(1, sigma_px)` when `scale` (the defaults are for about 1 px
/// of noise, as the verge/tilt estimator's, which
/// [`crate::estimate::EstimationOptions::scaled_for_noise`] scales alike), else 1. A
/// non-finite estimate counts as 1 px.
pub fn threshold_scale(scale: bool, sigma_px: f64) -> f64 {
    if scale && sigma_px.is_finite() { sigma_px.max(1.0) } else { 1.0 }
}

impl PanOptions {
    /// These options with the pixel thresholds scaled for the calibration's noise
    /// estimate `sigma_px` ([`PanOptions::scale_to_noise`]).
    pub fn scaled_to_noise(&self, sigma_px: f64) -> PanOptions {
        let k = threshold_scale(self.scale_to_noise, sigma_px);
        let mut o = self.clone();
        o.registration.threshold *= k;
        o.translation.ransac.threshold *= k;
        o.guide_px *= k;
        o
    }

    /// Check the options.
    pub fn validate(&self) -> Result<(), AlignError> {
        let bad = |m: String| Err(AlignError::InvalidOption(m));
        if !(self.drive_m.is_finite() && self.drive_m > 0.0) {
            return bad(format!("drive_m must be positive, got {}", self.drive_m));
        }
        if self.iterations == 0 {
            return bad("iterations must be at least 1".into());
        }
        if self.planarity_chi2_max.is_nan() || self.planarity_chi2_max <= 0.0 {
            return bad(format!("planarity_chi2_max must be positive, got {}", self.planarity_chi2_max));
        }
        check_encoder_sigma(self.encoder_sigma_deg)?;
        if !(self.guide_px > 0.0 && self.min_flow_px >= 0.0) {
            return bad(format!(
                "guide_px must be > 0 and min_flow_px >= 0, got {} {}",
                self.guide_px, self.min_flow_px
            ));
        }
        self.translation.validate().step("pan options")?;
        self.registration.validate().step("pan options")
    }
}

/// One drive of the pan stage.
#[derive(Debug, Clone, Serialize)]
pub struct PanStep {
    /// Head readings during the drive.
    pub encoders: Encoders,
    /// Pan correction from the image epipole, degrees.
    pub pan_image_deg: f64,
    /// Its standard deviation from the image noise (the drive motion's, through the
    /// derotation, and the flow's), degrees.
    pub sigma_image_deg: f64,
    /// Pan correction from the stereo reconstruction's motion, degrees.
    pub pan_stereo_deg: f64,
    /// Its standard deviation from the image noise (the drive motion's), degrees.
    pub sigma_stereo_deg: f64,
    /// Combined correction applied, degrees.
    pub pan_correction_deg: f64,
    /// Weight of the image estimate in the combination (the stereo one has `1 - w`).
    pub weight_image: f64,
    /// Standard deviation of the combined correction due to the verge/tilt calibration's
    /// uncertainty and the noise of the readings the rig is predicted at (no image noise of
    /// the drive), degrees (NaN if it could not be propagated).
    pub sigma_calibration_deg: f64,
    /// Standard deviation of the combined correction: calibration and image noise
    /// (module docs) and the pan reading's noise ([`PanOptions::encoder_sigma_deg`]: the
    /// corrected pan is that reading plus the correction), degrees.
    pub sigma_deg: f64,
    /// Heading change measured during the drive, degrees.
    pub turn_deg: f64,
    /// Rotation about axes perpendicular to the pan axis (planarity check), degrees.
    pub off_axis_deg: f64,
    /// Chi-square (3 degrees of freedom) of the drive's out-of-plane rotation and
    /// translation against their covariance (planarity test).
    pub planarity_chi2: f64,
    /// Angle of the travel direction out of the plane perpendicular to the pan axis
    /// (elevation check), degrees.
    pub elevation_check_deg: f64,
    /// Median flow of the guided matches, pixels.
    pub median_flow_px: f64,
    /// Flow inliers / registration inliers.
    pub inliers: [usize; 2],
    /// The predicted stereo rig checked against this drive's captures (and corrected if
    /// it misfit them).
    pub rig_check: RigCheck,
}

/// Result of [`align_pan`].
#[derive(Debug, Clone, Serialize)]
pub struct PanOutcome {
    /// Every drive.
    pub steps: Vec<PanStep>,
    /// Head readings at the end (aligned pan).
    pub final_encoders: Encoders,
}

/// Options of [`zero_steering`].
#[derive(Debug, Clone, PartialEq)]
pub struct SteeringOptions {
    /// Drive per steering setting, metres. Default 0.3.
    pub drive_m: f64,
    /// Steering settings relative to the current reading, degrees (known differences).
    /// Default `[-20, 20, 30, -30]` (three suffice; a fourth halves the RMS steering
    /// error at 60 deg pan zeros, measured 0.44 -> 0.20 deg over seeds 1-20).
    pub settings_deg: Vec<f64>,
    /// Smallest turn whose axis is trusted, degrees. Default 2.
    pub min_turn_deg: f64,
    /// Planarity test of each drive, as [`PanOptions::planarity_chi2_max`]: chi-square
    /// (3 dof) of the rotation about axes perpendicular to the pan axis and the
    /// translation along it, against the motion's and the calibration's covariance.
    /// Default [`PLANARITY_CHI2_MAX`] (false alarm rate 1e-5 per drive).
    pub planarity_chi2_max: f64,
    /// Wheelbase in metres if known (then converted with `baseline_m`). Default none.
    pub wheelbase_m: Option<f64>,
    /// Stereo baseline, metres, to express lengths in metres. Default 0.25.
    pub baseline_m: f64,
    /// Registration RANSAC (threshold: reprojection pixels). Default threshold 4 px, at
    /// least [`DRIVE_MIN_ITERATIONS`] samples.
    pub registration: RansacOptions,
    /// Standard deviation of each joint's encoder reading, degrees, as
    /// [`PanOptions::encoder_sigma_deg`]. Default [`ENCODER_SIGMA_DEG`].
    pub encoder_sigma_deg: f64,
    /// Multiply the registration threshold by the calibration's noise estimate when it
    /// exceeds 1 px, as [`PanOptions::scale_to_noise`]. Default true.
    pub scale_to_noise: bool,
    /// Largest standard deviation of the steering zero accepted, degrees: above it the
    /// stage is [`AlignError::SteeringUndetermined`] and the wheel is not commanded.
    /// Default 10 (the largest of 860 experiment trials, 3 px included, was 7.6; three
    /// drives of 24-57 tracks each at 3 px gave 64).
    pub max_sigma_zero_deg: f64,
}

impl Default for SteeringOptions {
    fn default() -> Self {
        Self {
            drive_m: 0.3,
            settings_deg: vec![-20.0, 20.0, 30.0, -30.0],
            min_turn_deg: 2.0,
            planarity_chi2_max: PLANARITY_CHI2_MAX,
            wheelbase_m: None,
            baseline_m: 0.25,
            registration: RansacOptions {
                threshold: 4.0,
                min_iterations: DRIVE_MIN_ITERATIONS,
                ..RansacOptions::default()
            },
            encoder_sigma_deg: ENCODER_SIGMA_DEG,
            scale_to_noise: true,
            max_sigma_zero_deg: 10.0,
        }
    }
}

/// `encoder_sigma_deg` of [`PanOptions`] and [`SteeringOptions`]: finite, >= 0.
fn check_encoder_sigma(sigma_deg: f64) -> Result<(), AlignError> {
    if sigma_deg.is_finite() && sigma_deg >= 0.0 {
        Ok(())
    } else {
        Err(AlignError::InvalidOption(format!("encoder_sigma_deg must be finite and >= 0, got {sigma_deg}")))
    }
}

impl SteeringOptions {
    /// These options with the registration threshold scaled for the calibration's noise
    /// estimate `sigma_px` ([`SteeringOptions::scale_to_noise`]).
    pub fn scaled_to_noise(&self, sigma_px: f64) -> SteeringOptions {
        let mut o = self.clone();
        o.registration.threshold *= threshold_scale(self.scale_to_noise, sigma_px);
        o
    }

    /// Check the options.
    pub fn validate(&self) -> Result<(), AlignError> {
        let bad = |m: String| Err(AlignError::InvalidOption(m));
        if !(self.drive_m.is_finite() && self.drive_m > 0.0 && self.baseline_m > 0.0) {
            return bad(format!(
                "drive_m and baseline_m must be positive, got {} {}",
                self.drive_m, self.baseline_m
            ));
        }
        if let Some(l) = self.wheelbase_m
            && !(l.is_finite() && l > 0.0)
        {
            return bad(format!("wheelbase_m must be positive, got {l}"));
        }
        let needed = if self.wheelbase_m.is_some() { 2 } else { 3 };
        if self.settings_deg.len() < needed || self.settings_deg.iter().any(|s| !s.is_finite()) {
            return bad(format!(
                "need at least {needed} finite steering settings, got {:?}",
                self.settings_deg
            ));
        }
        if !(self.min_turn_deg >= 0.0 && self.planarity_chi2_max > 0.0 && self.max_sigma_zero_deg > 0.0) {
            return bad(format!(
                "min_turn_deg >= 0, planarity_chi2_max > 0 and max_sigma_zero_deg > 0 required, got {} {} {}",
                self.min_turn_deg, self.planarity_chi2_max, self.max_sigma_zero_deg
            ));
        }
        check_encoder_sigma(self.encoder_sigma_deg)?;
        self.registration.validate().step("steering options")
    }
}

/// One steering drive.
#[derive(Debug, Clone, Serialize)]
pub struct TurnStep {
    /// Steering encoder reading, degrees.
    pub steer_encoder_deg: f64,
    /// Turn angle, degrees (signed about the pan axis).
    pub turn_deg: f64,
    /// Angle of the screw axis from the pan axis, degrees.
    pub axis_tilt_deg: f64,
    /// Chi-square (3 dof) of the planarity test (options).
    pub planarity_chi2: f64,
    /// Registration inliers.
    pub inliers: usize,
    /// Turning centre, left camera frame at the stage's start, stereo baselines.
    pub centre: [f64; 3],
}

/// Result of [`zero_steering`].
#[derive(Debug, Clone, Serialize)]
pub struct SteeringOutcome {
    /// Every drive.
    pub turns: Vec<TurnStep>,
    /// Estimated steering zero (encoder reading of a straight wheel), degrees.
    pub steer_zero_deg: f64,
    /// Its standard deviation: the drives' noise and the calibration's uncertainty
    /// (module docs), degrees (NaN if it could not be propagated).
    pub sigma_steer_zero_deg: f64,
    /// Estimated wheelbase, metres (via the baseline).
    pub wheelbase_m: f64,
    /// Pan correction implied by the forward direction found here (a check on the pan
    /// stage), degrees.
    pub pan_check_deg: f64,
    /// RMS distance of the centres from the axle line, metres.
    pub across_rms_m: f64,
    /// Indices into `turns` of drives left out: one drive failing the planarity test
    /// while the rest pass (an outlier drive; module docs). Empty normally.
    pub dropped_turns: Vec<usize>,
    /// The predicted stereo rig checked against the first drive's captures (and
    /// corrected if it misfit them).
    pub rig_check: RigCheck,
}

/// The calibrated stereo cameras at readings `enc`, in the current left camera frame,
/// plus `ref_from_left` (to move calibrated axes into that frame).
#[derive(Clone)]
pub(crate) struct Rig {
    k_left: Intrinsics,
    p_left: ProjectiveCamera,
    p_right: ProjectiveCamera,
    pub(crate) ref_from_left: Isometry3<f64>,
    pub(crate) left_from_right: Isometry3<f64>,
    stereo: StereoRig,
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
/// 3 px (the removed `examples/planarity_chi2.rs`, readings with 0.01 deg of noise) the median misfit
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
/// (`calibration_covariance`), the readings taken as exact. The covariance is `None` if
/// the propagation failed.
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
/// scenes: [`crate::frontend::TrackingHead::with_stereo_prior`]).
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

fn by_track(obs: &[headalign_platform::TrackObservation]) -> HashMap<u64, Point2<f64>> {
    obs.iter().map(|o| (o.track, o.pixel)).collect()
}

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
    before: HashMap<u64, Point3<f64>>,
    pub(crate) inliers: usize,
    /// The maximum-likelihood refinement (covariance of the centre's displacement).
    ml: RigMotionEstimate,
    /// The tracks of that refinement (same order as `ml.points`).
    tracks: Vec<RigTrack>,
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
const LEAST_SQUARES_HUBER_PX: f64 = 1e9;

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
    Ok(PanOutcome { steps, final_encoders: robot.read_encoders()? })
}

/// The pan axis (direction, a point) in the left camera frame of `rig`.
fn pan_axis_in(calib: &RigCalibration, rig: &Rig) -> Result<(Vector3<f64>, Vector3<f64>), AlignError> {
    let axis = calib.pan_axis().ok_or_else(|| AlignError::MissingMotion("pan axis".into()))?;
    let axis = axis.transformed(&rig.ref_from_left.inverse());
    Ok((axis.direction.into_inner(), axis.point.coords))
}

/// The two pan estimates of a drive (module docs) from its measured motion and image
/// direction: `(a_img, a_st, f_img, f_st)`, angles in radians from the head's forward
/// direction about `up`, and the two travel directions of the pan axis.
fn pan_geometry(
    rig: &Rig,
    up: &Vector3<f64>,
    o: &Vector3<f64>,
    motion: &Isometry3<f64>,
    c: &Vector3<f64>,
    direction: &Vector3<f64>,
    use_stereo_rotation: bool,
) -> (f64, f64, Vector3<f64>, Vector3<f64>) {
    let (r, heading) = if use_stereo_rotation {
        let w = motion.rotation.inverse().scaled_axis();
        (motion.rotation.to_rotation_matrix().into_inner(), w.dot(up))
    } else {
        (Matrix3::identity(), 0.0)
    };
    let half_back = UnitQuaternion::from_axis_angle(&Unit::new_normalize(*up), -0.5 * heading);
    let forward_of = |c: &Vector3<f64>| half_back * ((r.transpose() - Matrix3::identity()) * o + c);
    let f_img = forward_of(&(direction * c.norm()));
    let f_st = forward_of(c);
    let h = head_forward(rig);
    (angle_about(up, &h, &f_img), angle_about(up, &h, &f_st), f_img, f_st)
}

/// An orthonormal pair perpendicular to `up`.
fn perpendicular_basis(up: &Vector3<f64>) -> [Vector3<f64>; 2] {
    let helper = if up.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
    let e1 = up.cross(&helper).normalize();
    [e1, up.cross(&e1).normalize()]
}

/// The out-of-plane part of a drive `cam2_from_cam1` (zero for a motion on the plane
/// perpendicular to `up`): its rotation vector's components along `basis` (radians) and
/// the centre's displacement along `up` (baselines).
fn out_of_plane(motion: &Isometry3<f64>, up: &Vector3<f64>, basis: &[Vector3<f64>; 2]) -> Vector3<f64> {
    let w = motion.rotation.inverse().scaled_axis();
    let c = -(motion.rotation.inverse() * motion.translation.vector);
    Vector3::new(w.dot(&basis[0]), w.dot(&basis[1]), c.dot(up))
}

/// Covariance of [`out_of_plane`] from the motion's own covariance (left perturbation,
/// rotation first; Jacobian by central differences, step 1e-6: the map is smooth and
/// O(1) in these units).
fn out_of_plane_covariance(
    ml: &RigMotionEstimate,
    up: &Vector3<f64>,
    basis: &[Vector3<f64>; 2],
) -> Matrix3<f64> {
    let h = 1e-6;
    let mut j = SMatrix::<f64, 3, 6>::zeros();
    for k in 0..6 {
        let mut d = Vector6::zeros();
        d[k] = h;
        let p = out_of_plane(&perturb(&ml.cam2_from_cam1, &d), up, basis);
        d[k] = -h;
        let m = out_of_plane(&perturb(&ml.cam2_from_cam1, &d), up, basis);
        j.set_column(k, &((p - m) / (2.0 * h)));
    }
    j * ml.covariance * j.transpose()
}

/// Variance floor added to the out-of-plane covariance's diagonal (radians squared /
/// baselines squared): rounding of noise-free data, far below any real tilt (1e-6 rad is
/// 0.00006 deg).
const PLANARITY_FLOOR: f64 = 1e-12;

/// Chi-square of the out-of-plane part `v` with covariance `cov` (plus the floor).
fn planarity_chi2(v: &Vector3<f64>, cov: &Matrix3<f64>) -> f64 {
    let c = cov + Matrix3::identity() * PLANARITY_FLOOR;
    c.try_inverse().map_or(f64::INFINITY, |inv| (v.transpose() * inv * v)[(0, 0)])
}

/// Covariance (2x2) of the two pan estimates `q(motion)` from a drive motion's own
/// covariance ([`RigMotionEstimate::covariance`], left perturbation, rotation first):
/// `q` is evaluated at the motion moved by `+-` [`PROPAGATION_STEP_SIGMAS`] times each
/// column of the covariance's Cholesky factor `L` (`C = L L^T`), and the central
/// differences `D` (per unit of each column) give `D D^T` (exact for a linear `q`; the
/// factor keeps the strong rotation-translation correlations of a short drive). `None`
/// if `q` fails or the covariance is not positive definite.
fn motion_covariance(
    ml: &RigMotionEstimate,
    q: impl Fn(&Isometry3<f64>) -> Option<Vector2<f64>>,
) -> Option<Matrix2<f64>> {
    let l = ml.covariance.cholesky()?.l();
    let mut out = Matrix2::zeros();
    for k in 0..6 {
        let step: Vector6<f64> = l.column(k) * PROPAGATION_STEP_SIGMAS;
        let plus = q(&perturb(&ml.cam2_from_cam1, &step))?;
        let minus = q(&perturb(&ml.cam2_from_cam1, &(-step)))?;
        let d = (plus - minus) / (2.0 * PROPAGATION_STEP_SIGMAS);
        out += d * d.transpose();
    }
    Some(out)
}

/// Calibration parameters that move the rig or the head axes (the bundle's per-view
/// angles and poses do not enter the robot stages), with a usable standard deviation.
fn calibration_parameters(calib: &RigCalibration) -> Vec<usize> {
    let cov = &calib.bundle.covariance;
    (0..cov.names.len())
        .filter(|&i| {
            let v = cov.matrix[(i, i)];
            !cov.names[i].starts_with("view") && v.is_finite() && v > 0.0
        })
        .collect()
}

/// Encoder readings a quantity is computed at, with the standard deviation of each
/// joint's reading noise (degrees; 0: the readings taken as exact).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Readings {
    pub(crate) enc: Encoders,
    pub(crate) sigma_deg: f64,
}

impl Readings {
    /// The readings taken as exact.
    pub(crate) fn exact(enc: Encoders) -> Self {
        Self { enc, sigma_deg: 0.0 }
    }
}

/// Covariance of a quantity `q(calibration, vergence axes, readings)` (`n_out` values)
/// from the verge/tilt calibration's covariance, given `axes` ([`AxisPerturbations`]) the
/// vergence axes' own, and the noise of the encoder `readings` the quantity is computed
/// at: `J C J^T`, `J` by central differences of `q` along each parameter, step
/// [`PROPAGATION_STEP_SIGMAS`] of its standard deviation (as
/// [`crate::procedure::alignment_sigmas`]).
///
/// Without `axes`: the parameters of [`calibration_parameters`], the axes held as given
/// (the stereo rig predicted at other vergence readings then counts no error of the
/// axes). With `axes`: every parameter with a step in `axes.calibration` (the per-view
/// ones too: they move the scene points the axis views were resected against), the
/// axes moved with the calibration, plus the resected poses' noise modes (unit
/// variance, independent of the calibration) with the calibration held. The readings'
/// noise: the rig is predicted from each joint's reading minus the calibration's
/// reference reading, two independent reads, so each joint's reading is moved by `+-`
/// [`PROPAGATION_STEP_SIGMAS`] `sqrt(2) sigma`, independent of the other joints and of
/// the calibration (whose angle priors hold the differences of the calibration views'
/// readings, not the reference reading's own error).
/// `None` if `q` fails at a perturbed calibration.
pub(crate) fn calibration_covariance_dyn(
    calib: &RigCalibration,
    verge: &VergeAxes,
    axes: Option<&AxisPerturbations>,
    readings: &Readings,
    n_out: usize,
    mut q: impl FnMut(&RigCalibration, &VergeAxes, &Encoders) -> Option<DVector<f64>>,
) -> Option<DMatrix<f64>> {
    let cov = &calib.bundle.covariance;
    let n = cov.names.len();
    let enc = &readings.enc;
    let axes = axes.filter(|a| a.calibration.len() == n);
    let idx: Vec<usize> = match axes {
        Some(a) => (0..n).filter(|&i| a.calibration[i].is_some()).collect(),
        None => calibration_parameters(calib),
    };
    let mut scratch = calib.clone();
    let mut jac = DMatrix::<f64>::zeros(n_out, idx.len());
    for (col, &i) in idx.iter().enumerate() {
        let h = AxisPerturbations::calibration_step(cov, i);
        let (plus_axes, minus_axes) = match axes.and_then(|a| a.calibration[i].as_ref()) {
            Some(st) => (st.plus, st.minus),
            None => (*verge, *verge),
        };
        let mut delta = DVector::zeros(n);
        delta[i] = h;
        scratch.bundle.state = calib.bundle.perturbed(&delta).ok()?;
        let plus = q(&scratch, &plus_axes, enc)?;
        delta[i] = -h;
        scratch.bundle.state = calib.bundle.perturbed(&delta).ok()?;
        let minus = q(&scratch, &minus_axes, enc)?;
        if plus.len() != n_out || minus.len() != n_out {
            return None;
        }
        jac.set_column(col, &((plus - minus) / (2.0 * h)));
    }
    let sub = cov.matrix.select_rows(idx.iter()).select_columns(idx.iter());
    let mut out = &jac * sub * jac.transpose();
    // Unit-variance modes at +-PROPAGATION_STEP_SIGMAS: the difference over twice the
    // step is the change per unit of the mode.
    let mut add_mode = |d: DVector<f64>| {
        if d.len() != n_out {
            return None;
        }
        let d = d / (2.0 * PROPAGATION_STEP_SIGMAS);
        out += &d * d.transpose();
        Some(())
    };
    if let Some(a) = axes {
        // The resected poses' noise.
        for st in &a.pose {
            add_mode(q(calib, &st.plus, enc)? - q(calib, &st.minus, enc)?)?;
        }
    }
    if readings.sigma_deg > 0.0 {
        let half = PROPAGATION_STEP_SIGMAS * std::f64::consts::SQRT_2 * readings.sigma_deg;
        for joint in Joint::ALL {
            let (mut plus, mut minus) = (*enc, *enc);
            *plus.get_mut(joint) += half;
            *minus.get_mut(joint) -= half;
            add_mode(q(calib, verge, &plus)? - q(calib, verge, &minus)?)?;
        }
    }
    Some(out)
}

/// [`calibration_covariance_dyn`] for a fixed-size quantity.
pub(crate) fn calibration_covariance<const N: usize>(
    calib: &RigCalibration,
    verge: &VergeAxes,
    axes: Option<&AxisPerturbations>,
    readings: &Readings,
    mut q: impl FnMut(&RigCalibration, &VergeAxes, &Encoders) -> Option<SVector<f64, N>>,
) -> Option<SMatrix<f64, N, N>> {
    let c = calibration_covariance_dyn(calib, verge, axes, readings, N, |cp, va, e| {
        q(cp, va, e).map(|v| DVector::from_column_slice(v.as_slice()))
    })?;
    Some(SMatrix::<f64, N, N>::from_fn(|r, k| c[(r, k)]))
}

/// Options of the least-squares refits under a perturbed calibration (warm start).
fn refit_options() -> RigMotionOptions {
    RigMotionOptions { huber_px: LEAST_SQUARES_HUBER_PX, max_iterations: 10 }
}

/// One pan measurement from the captures before and after a forward drive.
pub fn pan_step(
    calib: &RigCalibration,
    verge: &VergeAxes,
    axes: Option<&AxisPerturbations>,
    before: &StereoCapture,
    after: &StereoCapture,
    options: &PanOptions,
) -> Result<PanStep, AlignError> {
    let options = &options.scaled_to_noise(calib.report.sigma_px);
    let enc = before.encoders;
    let (rig, correction, rig_check) =
        check_rig(rig_at(calib, verge, &enc)?, &[before, after], calib.report.sigma_px, &enc)?;
    let (up, o) = pan_axis_in(calib, &rig)?;
    let motion = drive_motion(&rig, before, after, &options.registration)?;
    let use_rot = options.use_stereo_rotation;
    let r = if use_rot {
        motion.cam2_from_cam1.rotation.to_rotation_matrix().into_inner()
    } else {
        Matrix3::identity()
    };
    let c = motion.ml.centre_displacement;
    let w = motion.cam2_from_cam1.rotation.inverse().scaled_axis();
    let heading_stereo = w.dot(&up);
    let off_axis = (w - up * heading_stereo).norm().to_degrees();

    // Image estimate on guided, derotated left-left matches.
    let k = rig.k_left;
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
    let dir = image.direction.into_inner();
    let (a_img, a_st, f_img, f_st) = pan_geometry(&rig, &up, &o, &motion.cam2_from_cam1, &c, &dir, use_rot);

    // Data variances of the two estimates (first order).
    let grad = |f: &Vector3<f64>| {
        let fh = f - up * up.dot(f);
        up.cross(&fh) / fh.norm_squared().max(1e-300)
    };
    let g_img = grad(&f_img);
    let var_img = c.norm_squared() * (g_img.transpose() * image.covariance * g_img)[(0, 0)];
    let g_st = grad(&f_st);
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
        let (ai, as_, _, _) = pan_geometry(&rig, &up, &o, m, &c_p, &dir_p, use_rot);
        Some(Vector2::new(ai, as_))
    };
    let c_motion = motion_covariance(&motion.ml, angles_at).unwrap_or_else(|| {
        // Not propagated (a refit failed): the centre's part alone, on the stereo estimate.
        Matrix2::new(0.0, 0.0, 0.0, var_centre)
    });

    // Calibration covariance of both estimates and of the out-of-plane part: the whole
    // computation after the data selections, re-run under each perturbed calibration.
    let basis = perpendicular_basis(&up);
    let v = out_of_plane(&motion.cam2_from_cam1, &up, &basis);
    let iterations = options.translation.max_iterations;
    let readings = Readings { enc, sigma_deg: options.encoder_sigma_deg };
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
        let (ai, as_, _, _) = pan_geometry(&rig_p, &up_p, &o_p, &m_p, &c_p, &dir_p, use_rot);
        // Out-of-plane part about the perturbed axis, in the nominal basis moved with it.
        let q = UnitQuaternion::rotation_between(&up, &up_p).unwrap_or_else(UnitQuaternion::identity);
        let v_p = out_of_plane(&m_p, &up_p, &[q * basis[0], q * basis[1]]);
        Some(SVector::<f64, 5>::from([ai, as_, v_p.x, v_p.y, v_p.z]))
    });
    let cal = cal.unwrap_or_else(|| SMatrix::<f64, 5, 5>::from_diagonal_element(f64::NAN));

    let v_cov = out_of_plane_covariance(&motion.ml, &up, &basis) + cal.fixed_view::<3, 3>(2, 2);
    let chi2 = planarity_chi2(&v, &v_cov);
    if chi2 > options.planarity_chi2_max {
        return Err(AlignError::NotPlanar(format!(
            "pan drive: the robot rotated {off_axis:.3} deg about an axis perpendicular to the pan axis and moved {:.4} baselines along it; chi-square {chi2:.1} (3 dof) above {}",
            v.z, options.planarity_chi2_max
        )));
    }

    // Combination: weights minimising the variance of `w_i a_img + w_s a_st` under the
    // calibration covariance, the motion's (both estimates, correlated) and the flow's
    // (image estimate), the last two taken as uncorrelated (clamped to [0, 1]: a convex
    // combination). Its stated variance is the calibration part plus a bound on the data
    // part valid for any correlation of the motion's and the flow's errors (both use the
    // left images): `(sqrt(w^T C_m w) + w_i s_flow)^2`.
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
    let fc = f_st.normalize();
    Ok(PanStep {
        encoders: enc,
        pan_image_deg: a_img.to_degrees(),
        sigma_image_deg: var_i_all.sqrt().to_degrees(),
        pan_stereo_deg: a_st.to_degrees(),
        sigma_stereo_deg: var_s_all.sqrt().to_degrees(),
        pan_correction_deg: combined.to_degrees(),
        weight_image: w_i,
        sigma_calibration_deg: var_cal.sqrt().to_degrees(),
        sigma_deg: (var_cal + data_sd * data_sd).sqrt().to_degrees().hypot(options.encoder_sigma_deg),
        turn_deg: heading_stereo.to_degrees(),
        off_axis_deg: off_axis,
        planarity_chi2: chi2,
        elevation_check_deg: fc.dot(&up).clamp(-1.0, 1.0).asin().to_degrees(),
        median_flow_px: image.median_flow_px,
        inliers: [image.inliers.len(), motion.inliers],
        rig_check,
    })
}

/// The turning centre of a drive `m = cam1_from_cam2` seen as a planar motion about
/// `up`: rotation about `up` by the measured angle's component along it; centre from the
/// horizontal translation (`(I - R + u u^T) p = t_perp`). The free 3D screw axis is too
/// noisy in direction (depth noise of the stereo points) to place the centre well.
fn turn_centre(m: &Isometry3<f64>, up: &Unit<Vector3<f64>>) -> Option<Point3<f64>> {
    let u = up.into_inner();
    let phi = m.rotation.scaled_axis().dot(&u);
    let r_planar = UnitQuaternion::from_axis_angle(up, phi).to_rotation_matrix().into_inner();
    let t = m.translation.vector;
    let t_perp = t - u * u.dot(&t);
    let a = Matrix3::identity() - r_planar + u * u.transpose();
    a.try_inverse().map(|inv| Point3::from(inv * t_perp))
}

/// Steering zero (degrees) from the drives' motions `cam2_from_cam1` under `up`.
fn steer_zero_of(
    up: &Unit<Vector3<f64>>,
    motions: &[Isometry3<f64>],
    settings: &[f64],
    hint: &Vector3<f64>,
    wheelbase: Option<f64>,
) -> Option<f64> {
    let turns: Option<Vec<Turn>> = motions
        .iter()
        .zip(settings)
        .map(|(m, s)| Some(Turn { steer_encoder_deg: *s, centre: turn_centre(&m.inverse(), up)? }))
        .collect();
    steering_from_turns(up, &turns?, hint, wheelbase).ok().map(|s| s.steer_zero_deg)
}

/// Fewest steering drives a solution keeps after leaving one out (three determine the
/// zero, the wheelbase and the forward direction).
const MIN_STEERING_DRIVES: usize = 3;

/// What the steering solution of a set of drives needs besides the drives.
struct SteeringContext<'a> {
    calib: &'a RigCalibration,
    verge: &'a VergeAxes,
    axes: Option<&'a AxisPerturbations>,
    readings: Readings,
    up: &'a Unit<Vector3<f64>>,
    wheelbase: Option<f64>,
    /// The correction of the predicted rig ([`check_rig`]), applied to every perturbed one.
    correction: Option<Isometry3<f64>>,
}

/// The steering solution of a set of drives, the zero's variance (degrees squared) and
/// each drive's planarity chi-square.
struct SteeringFit {
    solution: SteeringSolution,
    var_zero: f64,
    chi2: Vec<f64>,
}

/// Solve the steering from `motions` (drives at `settings`, centres `turns`) and
/// propagate (module docs).
fn steering_fit(
    ctx: &SteeringContext,
    motions: &[DriveMotion],
    settings: &[f64],
    turns: &[Turn],
) -> Result<SteeringFit, AlignError> {
    let (calib, verge, up, wheelbase) = (ctx.calib, ctx.verge, ctx.up, ctx.wheelbase);
    let hint: Vector3<f64> = motions.iter().map(|m| m.cam2_from_cam1.inverse().translation.vector).sum();
    let sol = steering_from_turns(up, turns, &hint, wheelbase).step("steering zero")?;
    // Uncertainty: every drive's motion covariance (independent drives) and the
    // calibration's (each drive refitted under each perturbed calibration), propagated by
    // central differences to the out-of-plane parts and the steering zero.
    let basis = perpendicular_basis(up);
    let nominal: Vec<Isometry3<f64>> = motions.iter().map(|m| m.cam2_from_cam1).collect();
    let n = motions.len();
    let cal =
        calibration_covariance_dyn(calib, verge, ctx.axes, &ctx.readings, 3 * n + 1, |cp, verge_p, enc_p| {
            let rig_p = rig_at(cp, verge_p, enc_p).ok()?.corrected(ctx.correction.as_ref());
            let up_p = cp.pan_axis()?.transformed(&rig_p.ref_from_left.inverse()).direction;
            let q = UnitQuaternion::rotation_between(up, &up_p).unwrap_or_else(UnitQuaternion::identity);
            let basis_p = [q * basis[0], q * basis[1]];
            let mut out = DVector::zeros(3 * n + 1);
            let mut refits = Vec::with_capacity(n);
            for (k, d) in motions.iter().enumerate() {
                let ml = refine_rig_motion(
                    &rig_p.stereo,
                    &d.tracks,
                    &d.cam2_from_cam1,
                    &d.ml.points,
                    &refit_options(),
                )
                .ok()?;
                out.fixed_rows_mut::<3>(3 * k).copy_from(&out_of_plane(&ml.cam2_from_cam1, &up_p, &basis_p));
                refits.push(ml.cam2_from_cam1);
            }
            out[3 * n] = steer_zero_of(&up_p, &refits, settings, &hint, wheelbase)?;
            Some(out)
        })
        .unwrap_or_else(|| DMatrix::from_element(3 * n + 1, 3 * n + 1, f64::NAN));
    let mut var_zero = cal[(3 * n, 3 * n)];
    let mut chi2s = Vec::with_capacity(n);
    for (k, d) in motions.iter().enumerate() {
        let v = out_of_plane(&d.cam2_from_cam1, up, &basis);
        let v_cov = out_of_plane_covariance(&d.ml, up, &basis) + cal.fixed_view::<3, 3>(3 * k, 3 * k);
        chi2s.push(planarity_chi2(&v, &v_cov));
        // The drive's own noise, through its centre to the zero.
        let h = 1e-6;
        let mut j = SMatrix::<f64, 1, 6>::zeros();
        for p in 0..6 {
            let mut delta = Vector6::zeros();
            let mut at = |sign: f64| {
                delta[p] = sign * h;
                let mut ms = nominal.clone();
                ms[k] = perturb(&nominal[k], &delta);
                steer_zero_of(up, &ms, settings, &hint, wheelbase)
            };
            match (at(1.0), at(-1.0)) {
                (Some(a), Some(b)) => j[p] = (a - b) / (2.0 * h),
                _ => j[p] = f64::NAN,
            }
        }
        var_zero += (j * d.ml.covariance * j.transpose())[(0, 0)];
    }
    Ok(SteeringFit { solution: sol, var_zero, chi2: chi2s })
}

/// Find the steering zero from drives at known steering differences and straighten the
/// wheel (module docs).
pub fn zero_steering<R: StereoHead + Vehicle>(
    robot: &mut R,
    calib: &RigCalibration,
    verge: &VergeAxes,
    axes: Option<&AxisPerturbations>,
    options: &SteeringOptions,
) -> Result<SteeringOutcome, AlignError> {
    options.validate()?;
    let options = &options.scaled_to_noise(calib.report.sigma_px);
    let enc = robot.read_encoders()?;
    let predicted = rig_at(calib, verge, &enc)?;
    let pan_axis = calib.pan_axis().ok_or_else(|| AlignError::MissingMotion("pan axis".into()))?;
    // The vergence readings do not change during the stage, so neither does the rig: it
    // is checked on the first drive's captures ([`check_rig`]; its correction, if any,
    // leaves `ref_from_left` and so `up` as predicted).
    let up = pan_axis.transformed(&predicted.ref_from_left.inverse()).direction;
    let mut checked: Option<(Rig, Option<Isometry3<f64>>, RigCheck)> = None;
    let s0 = robot.read_steering()?;
    let mut turns = Vec::new();
    let mut steps = Vec::new();
    let mut motions = Vec::new();
    let mut settings = Vec::new();
    for s in &options.settings_deg {
        robot.steer_to(s0 + s)?;
        let before = robot.capture()?;
        robot.drive(options.drive_m)?;
        let after = robot.capture()?;
        robot.drive(-options.drive_m)?;
        let (rig, _, _) = match &checked {
            Some(c) => c,
            None => {
                checked.insert(check_rig(predicted.clone(), &[&before, &after], calib.report.sigma_px, &enc)?)
            }
        };
        let motion = drive_motion(rig, &before, &after, &options.registration)?;
        let m = motion.cam2_from_cam1.inverse();
        let angle = m.rotation.angle().to_degrees();
        if angle < options.min_turn_deg {
            return Err(AlignError::TurnTooSmall { angle_deg: angle, min_deg: options.min_turn_deg });
        }
        let screw = screw_from_isometry(&m, options.min_turn_deg.to_radians())
            .ok_or(AlignError::TurnTooSmall { angle_deg: angle, min_deg: options.min_turn_deg })?
            .oriented_along(&up);
        let tilt = screw.axis.direction.angle(&up).to_degrees();
        let centre = turn_centre(&m, &up)
            .ok_or(AlignError::TurnTooSmall { angle_deg: angle, min_deg: options.min_turn_deg })?;
        turns.push(Turn { steer_encoder_deg: s0 + s, centre });
        steps.push(TurnStep {
            steer_encoder_deg: s0 + s,
            turn_deg: screw.angle.to_degrees(),
            axis_tilt_deg: tilt,
            planarity_chi2: f64::NAN,
            inliers: motion.inliers,
            centre: [centre.x, centre.y, centre.z],
        });
        settings.push(s0 + s);
        motions.push(motion);
    }
    let scale = options.baseline_m;
    let wheelbase = options.wheelbase_m.map(|l| l / scale);
    let (rig, correction, rig_check) =
        checked.ok_or_else(|| AlignError::InvalidOption("steering: no steering settings".into()))?;
    let readings = Readings { enc, sigma_deg: options.encoder_sigma_deg };
    let ctx = SteeringContext { calib, verge, axes, readings, up: &up, wheelbase, correction };
    let mut fit = steering_fit(&ctx, &motions, &settings, &turns)?;
    for (step, chi2) in steps.iter_mut().zip(&fit.chi2) {
        step.planarity_chi2 = *chi2;
    }
    // A drive that fails the planarity test while the others pass is an outlier (one
    // drive's reconstruction, e.g. a view of far points only, under the rig predicted
    // at the readings); it is left out when enough drives remain and the rest then pass.
    // A robot that really pitches or rolls, or a pan axis off perpendicular, shows in
    // every drive.
    let failing: Vec<usize> =
        (0..steps.len()).filter(|&k| fit.chi2[k] > options.planarity_chi2_max).collect();
    let mut dropped = Vec::new();
    if let [k] = failing[..]
        && steps.len() > MIN_STEERING_DRIVES
    {
        let m2: Vec<DriveMotion> =
            motions.iter().enumerate().filter(|(i, _)| *i != k).map(|(_, m)| m.clone()).collect();
        let s2: Vec<f64> = settings.iter().enumerate().filter(|(i, _)| *i != k).map(|(_, x)| *x).collect();
        let t2: Vec<Turn> = turns.iter().enumerate().filter(|(i, _)| *i != k).map(|(_, x)| *x).collect();
        let refit = steering_fit(&ctx, &m2, &s2, &t2)?;
        if !refit.chi2.iter().any(|c| *c > options.planarity_chi2_max) {
            dropped.push(k);
            fit = refit;
        }
    }
    if dropped.is_empty()
        && let Some(&k) = failing.first()
    {
        return Err(AlignError::NotPlanar(format!(
            "steering {:+.1} deg: screw axis {:.2} deg from the pan axis; chi-square {:.1} (3 dof) above {} ({} of {} drives failed the test)",
            settings[k],
            steps[k].axis_tilt_deg,
            fit.chi2[k],
            options.planarity_chi2_max,
            failing.len(),
            steps.len()
        )));
    }
    let sol = fit.solution;
    let sigma_zero = fit.var_zero.sqrt();
    // A NaN sigma (not propagated) passes: the zero itself may be well determined.
    if sigma_zero > options.max_sigma_zero_deg {
        return Err(AlignError::SteeringUndetermined {
            zero_deg: sol.steer_zero_deg,
            sigma_deg: sigma_zero,
            max_sigma_deg: options.max_sigma_zero_deg,
            drives: steps.len() - dropped.len(),
            dropped_turns: dropped,
        });
    }
    robot.steer_to(sol.steer_zero_deg)?;
    let pan_check = angle_about(&up, &head_forward(&rig), &sol.forward);
    Ok(SteeringOutcome {
        turns: steps,
        dropped_turns: dropped,
        steer_zero_deg: sol.steer_zero_deg,
        sigma_steer_zero_deg: sigma_zero,
        wheelbase_m: sol.wheelbase * scale,
        pan_check_deg: pan_check.to_degrees(),
        across_rms_m: sol.across_rms * scale,
        rig_check,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimate::EstimationOptions;
    use crate::procedure::{VergeTiltOptions, VergeTiltRun};
    use headalign_sim::{Scenario, SimulatedRobot};

    /// A simulated robot for `s` and its verge/tilt calibration (estimation seed = the
    /// scenario's seed), as every test here starts.
    fn calibrated_robot(s: Scenario) -> (SimulatedRobot, crate::procedure::VergeTiltOutcome) {
        let opts = VergeTiltOptions {
            estimation: EstimationOptions { seed: s.seed, ..EstimationOptions::default() },
            ..VergeTiltOptions::default()
        };
        let mut robot = SimulatedRobot::new(s).unwrap();
        let vt = VergeTiltRun::default().run(robot.head_mut(), &opts).unwrap();
        (robot, vt)
    }

    /// A robot-scene simulated robot at `noise` px and its verge/tilt calibration as the
    /// experiments run it (noise-scaled estimation options, 3 deg vergence rotations), with
    /// the depth-scale profile `depth_profile` (the default's:
    /// `EstimationOptions::default().depth_profile`).
    fn experiment_robot(
        seed: u64,
        noise: f64,
        depth_profile: Option<crate::estimate::DepthProfile>,
        image_border: bool,
    ) -> (SimulatedRobot, crate::procedure::VergeTiltOutcome, Scenario) {
        let s = Scenario {
            seed,
            noise_px: noise,
            near_panels: Scenario::ROBOT_NEAR_PANELS,
            ..Scenario::default()
        };
        let opts = VergeTiltOptions {
            verge_rotation_deg: 3.0,
            estimation: EstimationOptions {
                depth_profile,
                image_border,
                ..EstimationOptions::scaled_for_noise(noise, seed)
            },
            ..VergeTiltOptions::default()
        };
        let mut robot = SimulatedRobot::new(s.clone()).unwrap();
        let vt = VergeTiltRun::default().run(robot.head_mut(), &opts).unwrap();
        (robot, vt, s)
    }

    /// Every option the stages check is rejected when out of range, by a named
    /// [`AlignError::InvalidOption`]; the defaults pass.
    #[test]
    fn robot_options_validate() {
        assert!(PanOptions::default().validate().is_ok());
        assert!(SteeringOptions::default().validate().is_ok());
        let pans = [
            PanOptions { drive_m: f64::NAN, ..PanOptions::default() },
            PanOptions { drive_m: 0.0, ..PanOptions::default() },
            PanOptions { iterations: 0, ..PanOptions::default() },
            PanOptions { planarity_chi2_max: f64::NAN, ..PanOptions::default() },
            PanOptions { encoder_sigma_deg: -0.1, ..PanOptions::default() },
            PanOptions { guide_px: 0.0, ..PanOptions::default() },
        ];
        for o in &pans {
            assert!(matches!(o.validate(), Err(AlignError::InvalidOption(_))), "{o:?}");
        }
        let steerings = [
            SteeringOptions { drive_m: f64::INFINITY, ..SteeringOptions::default() },
            SteeringOptions { baseline_m: 0.0, ..SteeringOptions::default() },
            SteeringOptions { settings_deg: vec![-20.0, 20.0], ..SteeringOptions::default() },
            SteeringOptions { settings_deg: vec![-20.0, f64::NAN, 20.0], ..SteeringOptions::default() },
            SteeringOptions { min_turn_deg: -1.0, ..SteeringOptions::default() },
            SteeringOptions { planarity_chi2_max: 0.0, ..SteeringOptions::default() },
            SteeringOptions { max_sigma_zero_deg: 0.0, ..SteeringOptions::default() },
            SteeringOptions { max_sigma_zero_deg: f64::NAN, ..SteeringOptions::default() },
            SteeringOptions { encoder_sigma_deg: f64::NAN, ..SteeringOptions::default() },
            SteeringOptions { wheelbase_m: Some(-0.5), ..SteeringOptions::default() },
        ];
        for o in &steerings {
            assert!(matches!(o.validate(), Err(AlignError::InvalidOption(_))), "{o:?}");
        }
        // Two settings suffice with a known wheelbase.
        let known = SteeringOptions {
            settings_deg: vec![-20.0, 20.0],
            wheelbase_m: Some(0.5),
            ..SteeringOptions::default()
        };
        assert!(known.validate().is_ok());
    }

    /// Noise-free end to end: steering zero then pan, both exact to 1e-9 deg (rounding
    /// through triangulation, two least-squares fits and the epipole; before the
    /// maximum-likelihood passes a wrong track inside the RANSAC threshold left 0.006
    /// deg on demo seed 1) with sigmas near zero; and the named degenerate cases.
    #[test]
    fn noise_free_steering_and_pan_and_degenerate_cases() {
        let s = Scenario { seed: 1, noise_px: 0.0, outlier_fraction: 0.0, ..Scenario::default() };
        let (mut robot, vt) = calibrated_robot(s);
        let (cal, verge) = (&vt.calibration, &vt.verge_axes);
        let axes = vt.axis_perturbations();
        // The simulated readings are exact.
        let steering = SteeringOptions { encoder_sigma_deg: 0.0, ..SteeringOptions::default() };
        let st = zero_steering(&mut robot, cal, verge, Some(&axes), &steering).unwrap();
        let now = robot.steering_encoder_deg();
        assert!(robot.steer_err_deg(now).abs() < 1e-9, "{st:?}");
        assert!(st.sigma_steer_zero_deg < 1e-4, "{st:?}");
        let exact = PanOptions { encoder_sigma_deg: 0.0, ..PanOptions::default() };
        let pan = align_pan(&mut robot, cal, verge, Some(&axes), &exact).unwrap();
        let enc = robot.head().encoders();
        assert!(robot.pan_err_deg(&enc).abs() < 1e-9, "{pan:?}");
        assert!(pan.steps.iter().all(|s| s.sigma_deg < 1e-4 && s.planarity_chi2 < 1.0), "{pan:?}");

        let short = PanOptions { drive_m: 0.002, ..PanOptions::default() };
        assert!(matches!(
            align_pan(&mut robot, cal, verge, Some(&axes), &short),
            Err(AlignError::DriveTooShort { .. })
        ));
        let small = SteeringOptions { settings_deg: vec![0.3, 0.6, 0.9], ..SteeringOptions::default() };
        assert!(matches!(
            zero_steering(&mut robot, cal, verge, Some(&axes), &small),
            Err(AlignError::TurnTooSmall { .. })
        ));
    }

    /// The calibration propagation against the covariance itself: for quantities that are
    /// calibration parameters (the left camera's fx and cx, linear in the tangent step)
    /// the central differences must return the covariance block exactly (1e-9 relative:
    /// rounding); and a quantity that no calibration parameter moves gets zero.
    #[test]
    fn calibration_covariance_matches_the_covariance_block() {
        let s = Scenario { seed: 3, noise_px: 1.0, ..Scenario::default() };
        let (_, vt) = calibrated_robot(s);
        let cal = &vt.calibration;
        let c = calibration_covariance(
            cal,
            &vt.verge_axes,
            None,
            &Readings::exact(vt.final_encoders),
            |cp, _, _| {
                let k = cp.bundle.state.left;
                Some(SVector::<f64, 3>::new(k.fx, k.cx, 1.0))
            },
        )
        .unwrap();
        let cov = &cal.bundle.covariance;
        let (i, j) = (cov.index("left.fx").unwrap(), cov.index("left.cx").unwrap());
        let expect = [[cov.matrix[(i, i)], cov.matrix[(i, j)]], [cov.matrix[(j, i)], cov.matrix[(j, j)]]];
        for r in 0..2 {
            for k in 0..2 {
                let tol = 1e-9 * (expect[r][r] * expect[k][k]).sqrt();
                assert!(
                    (c[(r, k)] - expect[r][k]).abs() <= tol,
                    "{r} {k}: {} vs {}",
                    c[(r, k)],
                    expect[r][k]
                );
            }
        }
        assert!(c[(2, 2)] == 0.0 && c[(0, 2)] == 0.0);
        assert!(expect[1][1] > 0.0);
    }

    /// The readings' noise: for quantities linear in the readings and independent of the
    /// calibration (the pan reading; the sum of the elevation and left vergence readings)
    /// the modes give exactly `2 sigma^2` per joint (the reading and the reference
    /// reading), uncorrelated across joints (1e-9 relative: rounding); a quantity the
    /// readings do not move gets zero; and the rig predicted at the readings turns by the
    /// vergence readings' noise (its rotation's variance, radians, `2 sigma^2` per
    /// vergence joint, the calibration noise-free; 1 % for the rotations' nonlinearity).
    #[test]
    fn reading_noise_adds_each_joints_variance() {
        let s = Scenario { seed: 3, noise_px: 0.0, ..Scenario::default() };
        let (_, vt) = calibrated_robot(s);
        let cal = &vt.calibration;
        let sigma = 0.01;
        let readings = Readings { enc: vt.final_encoders, sigma_deg: sigma };
        let c = calibration_covariance(cal, &vt.verge_axes, None, &readings, |_, _, e| {
            Some(SVector::<f64, 3>::new(
                e.get(Joint::Pan),
                e.get(Joint::Elevation) + e.get(Joint::VergeLeft),
                1.0,
            ))
        })
        .unwrap();
        let var = 2.0 * sigma * sigma;
        let expect = [[var, 0.0], [0.0, 2.0 * var]];
        for r in 0..2 {
            for k in 0..2 {
                assert!((c[(r, k)] - expect[r][k]).abs() <= 1e-9 * var, "{r} {k}: {}", c[(r, k)]);
            }
        }
        assert!(c[(2, 2)] == 0.0);
        let nominal = rig_at(cal, &vt.verge_axes, &vt.final_encoders).unwrap().stereo.right_from_left;
        let rot = calibration_covariance(cal, &vt.verge_axes, None, &readings, |cp, va, e| {
            let d = rig_at(cp, va, e).ok()?.stereo.right_from_left * nominal.inverse();
            Some(d.rotation.scaled_axis())
        })
        .unwrap();
        let s_rad = sigma.to_radians();
        let expect = 4.0 * s_rad * s_rad;
        assert!((rot.trace() - expect).abs() <= 0.01 * expect, "{} vs {expect}", rot.trace());
    }

    /// The vergence axes' pose part of the rig predicted at other readings against a
    /// Monte-Carlo: seed 2 at 3 px in the robot scene (the experiments' verge/tilt
    /// options), the axis sources' captures re-drawn 100 times (every calibration point
    /// the capture observes, projected at the estimate, plus 3 px Gaussian noise: the
    /// model the bootstrap draws from), resected by [`crate::alignment::measure_cameras`]
    /// and turned into axes, the calibration held; the spread of the predicted rig's
    /// rotation at the stage's final readings against [`predicted_rig`]'s covariance with
    /// only the pose modes of [`AxisPerturbations`]. Measured: Monte-Carlo / predicted
    /// standard deviation 0.89 here (at c46cdb3 and with the 0.1-sigma difference step
    /// alike; 1.10 when this test was written, on an earlier calibration). Exact pixels
    /// of the true scene, as a first version drew (they add the calibration's fixed
    /// misfit through the Huber weights), gave 1.10
    /// with the image border not modelled and 1.07-1.30 over seeds 1-8
    /// (the removed `examples/axis_mc.rs`); with `EstimationOptions::min_camera_observations` 2 the
    /// calibration differs and it was 1.22 (exact pixels 1.33). The least-squares pose
    /// covariance gave 1.40 (1.29-1.51).
    /// Tolerance [0.8, 1.3]: 100 draws know a standard deviation to 7 %, the bootstrap's
    /// 200 to 5 %, and it keeps out the least-squares value.
    #[test]
    fn axis_pose_part_matches_monte_carlo_at_3px() {
        use crate::alignment::{measure_cameras, verge_axes_from_motion};
        use crate::procedure::AxisMeasurement;
        use rand::{RngExt, SeedableRng};
        let noise = 3.0;
        let (_, vt, _) = experiment_robot(
            2,
            noise,
            EstimationOptions::default().depth_profile,
            EstimationOptions::default().image_border,
        );
        let cal = &vt.calibration;
        let r0 = cal.reference_encoders;
        let enc = vt.final_encoders;
        let all = vt.axis_perturbations();
        let pose_only = AxisPerturbations { calibration: vec![None; all.calibration.len()], pose: all.pose };
        let (rig, cov) = predicted_rig(cal, &vt.verge_axes, Some(&pose_only), &enc).unwrap();
        let predicted = cov.unwrap().fixed_view::<3, 3>(0, 0).trace().sqrt();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let points: std::collections::HashMap<u64, nalgebra::Point3<f64>> =
            cal.points().into_iter().collect();
        let mut samples: Vec<Vector3<f64>> = Vec::new();
        for _ in 0..100 {
            let mut redraw = |src: &Option<AxisMeasurement>| -> VergeAxes {
                let Some(src) = src else { return vt.verge_axes };
                // The model the bootstrap draws from: every calibration point the capture
                // observes, projected at the estimate, plus noise.
                let mut c = src.capture.clone();
                let st = &cal.bundle.state;
                for (obs, k, pose) in [
                    (&mut c.left, &st.left, &src.measured.ref_from_left),
                    (&mut c.right, &st.right, &src.measured.ref_from_right),
                ] {
                    obs.retain_mut(|o| {
                        let Some(p) =
                            points.get(&o.track).and_then(|x| k.project(&pose.inverse_transform_point(x)))
                        else {
                            return false;
                        };
                        o.pixel.x = p.x + noise * rng.sample::<f64, _>(rand_distr::StandardNormal);
                        o.pixel.y = p.y + noise * rng.sample::<f64, _>(rand_distr::StandardNormal);
                        true
                    });
                }
                let m = measure_cameras(cal, &c, &src.measured.ref_from_left, &src.measured.ref_from_right)
                    .unwrap();
                verge_axes_from_motion(&cal.bundle.state, &r0, &c.encoders, &m).unwrap()
            };
            let axes = VergeAxes {
                left: redraw(&vt.axis_sources.left).left,
                right: redraw(&vt.axis_sources.right).right,
            };
            let (p, _) = predicted_rig(cal, &axes, None, &enc).unwrap();
            samples.push((p.right_from_left * rig.right_from_left.inverse()).rotation.scaled_axis());
        }
        let n = samples.len() as f64;
        let mean: Vector3<f64> = samples.iter().sum::<Vector3<f64>>() / n;
        let mc = (samples.iter().map(|v| (v - mean).norm_squared()).sum::<f64>() / (n - 1.0)).sqrt();
        let ratio = mc / predicted;
        assert!((0.8..1.3).contains(&ratio), "Monte-Carlo {mc} vs predicted {predicted}: {ratio}");
    }

    /// The steering drives' planarity chi-squares of the robot experiment at `seed`, 3 px,
    /// with the vergence axes held as exact and with their uncertainty, on the same drives
    /// (the robot cloned after the pan stage: a second run whose pan stage used the axes'
    /// uncertainty would leave the head elsewhere and drive different drives).
    fn steering_chi2(seed: u64, image_border: bool) -> [Vec<f64>; 2] {
        let noise = 3.0;
        let (mut robot, vt, s) = experiment_robot(seed, noise, None, image_border);
        let perturbations = vt.axis_perturbations();
        // The stages scale their thresholds with the calibration's noise estimate.
        let pan =
            PanOptions { drive_m: s.drive_m, planarity_chi2_max: f64::INFINITY, ..PanOptions::default() };
        let st = SteeringOptions {
            baseline_m: s.baseline_m,
            planarity_chi2_max: f64::INFINITY,
            ..SteeringOptions::default()
        };
        align_pan(&mut robot, &vt.calibration, &vt.verge_axes, None, &pan).unwrap();
        [None, Some(&perturbations)].map(|axes| {
            let z = zero_steering(&mut robot.clone(), &vt.calibration, &vt.verge_axes, axes, &st).unwrap();
            z.turns.iter().map(|t| t.planarity_chi2).collect()
        })
    }

    /// Seeds 100-399 whose steering drives fail the planarity test with the axes held,
    /// printed with the chi-squares on the same drives with the axes' uncertainty (a
    /// diagnostic, not a test: `[IMAGE_BORDER=1] cargo test --release -p headalign --lib
    /// scan_steering_chi2 -- --ignored --nocapture`, about 3.5 min). Measured: with the
    /// image border modelled only seed 170 (fourth drive 43.5 held, 42.8 with the axes) and
    /// 216 (third, 28.5 / 28.4); without it only seed 170 (first drive 42.7 / 42.8).
    #[test]
    #[ignore]
    fn scan_steering_chi2() {
        for seed in 100..400 {
            let [held, with] = steering_chi2(seed, std::env::var("IMAGE_BORDER").is_ok_and(|v| v == "1"));
            if held.iter().any(|&c| c > 25.9) {
                eprintln!("SCAN seed {seed} held {held:.1?} with {with:.1?}");
            }
        }
    }

    /// The motion propagation against the covariance itself: for a quantity linear in the
    /// perturbation (two components of the tangent step) the Cholesky central differences
    /// return the covariance block exactly (1e-9 relative: rounding of the retraction at
    /// steps of 1e-3).
    #[test]
    fn motion_covariance_matches_the_covariance_block() {
        let a = nalgebra::Matrix6::<f64>::from_fn(|r, k| {
            ((r * 7 + k * 3) % 5) as f64 - 2.0 + if r == k { 6.0 } else { 0.0 }
        });
        let cov = (a * a.transpose()) * 1e-8;
        let m = Isometry3::new(Vector3::new(0.0, 0.0, 1.0), Vector3::new(0.0, 0.02, 0.0));
        let ml = RigMotionEstimate {
            cam2_from_cam1: m,
            covariance: cov,
            centre_displacement: Vector3::zeros(),
            centre_covariance: Matrix3::zeros(),
            points: Vec::new(),
            rms_px: 0.0,
            sigma_px: 0.0,
            iterations: 0,
        };
        // The tangent step of `perturb` recovered from the moved motion (left perturbation).
        let q = |p: &Isometry3<f64>| {
            let d = p * m.inverse();
            Some(Vector2::new(d.rotation.scaled_axis().y, d.translation.vector.z))
        };
        let c = motion_covariance(&ml, q).unwrap();
        let expect = Matrix2::new(cov[(1, 1)], cov[(1, 5)], cov[(5, 1)], cov[(5, 5)]);
        assert!((c - expect).norm() <= 1e-6 * expect.norm(), "{c} vs {expect}");
    }

    /// The data part of the pan sigma (motion and flow; the calibration exact: estimated
    /// noise-free on the same head): z-scores of repeated 1 px drives from one pose (RMS z
    /// 0.83 here). 40 drives: an RMS z of a calibrated sigma lies in [0.78, 1.21] with 95 %
    /// probability; the bound on the correlation of the motion's and the flow's errors may
    /// only make it smaller, hence [0.5, 1.3].
    #[test]
    fn pan_data_sigma_covers_repeated_drives() {
        let base = Scenario { seed: 4, near_panels: Scenario::ROBOT_NEAR_PANELS, ..Scenario::default() };
        let (exact, vt) = calibrated_robot(Scenario { noise_px: 0.0, ..base.clone() });
        let (cal, verge) = (&vt.calibration, &vt.verge_axes);
        let axes = vt.axis_perturbations();
        let mut robot = SimulatedRobot::new(Scenario { noise_px: 1.0, ..base }).unwrap();
        let enc = exact.head().encoders();
        robot.move_to(&enc).unwrap();
        // The simulated readings are exact: the data's sigma alone.
        let opt = PanOptions { encoder_sigma_deg: 0.0, ..PanOptions::default() };
        let mut z2 = Vec::new();
        for _ in 0..40 {
            let before = robot.capture().unwrap();
            robot.drive(opt.drive_m).unwrap();
            let after = robot.capture().unwrap();
            robot.drive(-opt.drive_m).unwrap();
            let step = pan_step(cal, verge, Some(&axes), &before, &after, &opt).unwrap();
            let err = robot.pan_err_deg(&enc.moved(Joint::Pan, step.pan_correction_deg));
            assert!(step.sigma_calibration_deg < 1e-3 * step.sigma_deg, "{step:?}");
            z2.push((err / step.sigma_deg).powi(2));
        }
        let rms_z = (z2.iter().sum::<f64>() / z2.len() as f64).sqrt();
        assert!((0.5..1.3).contains(&rms_z), "RMS z {rms_z}");
    }

    /// A robot on a ramp: every drive also pitches it about its own x axis (a motion
    /// that is not planar).
    struct Ramp {
        inner: SimulatedRobot,
        pitch_deg: f64,
    }

    impl StereoHead for Ramp {
        fn image_size(&self) -> [u32; 2] {
            self.inner.image_size()
        }
        fn read_encoders(&mut self) -> Result<Encoders, headalign_platform::PlatformError> {
            self.inner.read_encoders()
        }
        fn move_to(&mut self, target: &Encoders) -> Result<(), headalign_platform::PlatformError> {
            self.inner.move_to(target)
        }
        fn capture(&mut self) -> Result<StereoCapture, headalign_platform::PlatformError> {
            self.inner.capture()
        }
    }

    impl Vehicle for Ramp {
        fn drive(&mut self, d: f64) -> Result<(), headalign_platform::PlatformError> {
            self.inner.drive(d)?;
            let pitch = Isometry3::rotation(Vector3::x() * self.pitch_deg.to_radians() * d.signum());
            let pose = self.inner.head().world_from_robot() * pitch;
            self.inner.head_mut().set_world_from_robot(pose);
            Ok(())
        }
        fn steer_to(&mut self, e: f64) -> Result<(), headalign_platform::PlatformError> {
            self.inner.steer_to(e)
        }
        fn read_steering(&mut self) -> Result<f64, headalign_platform::PlatformError> {
            self.inner.read_steering()
        }
    }

    /// Non-planar drives are named, in both stages, by the chi-square test (noise-free,
    /// so only the pitch can trip it: 0.3 deg, below the former fixed 1 deg limit, and 3
    /// deg for the pan stage; 5 deg with a 10-15 deg turn for the steering stage); flat
    /// drives pass it with chi-square values near zero.
    #[test]
    fn non_planar_motion_is_named() {
        let s = Scenario {
            seed: 2,
            noise_px: 0.0,
            outlier_fraction: 0.0,
            near_panels: Scenario::ROBOT_NEAR_PANELS,
            ..Scenario::default()
        };
        let (mut robot, vt) = calibrated_robot(s);
        let (cal, verge) = (&vt.calibration, &vt.verge_axes);
        let axes = vt.axis_perturbations();
        // Planar: fine, and the pan stage reports its planarity check near zero.
        let flat = align_pan(&mut robot, cal, verge, Some(&axes), &PanOptions::default()).unwrap();
        assert!(flat.steps.iter().all(|s| s.off_axis_deg < 1e-6 && s.planarity_chi2 < 1.0), "{flat:?}");
        let mut ramp = Ramp { inner: robot, pitch_deg: 0.3 };
        assert!(matches!(
            align_pan(&mut ramp, cal, verge, Some(&axes), &PanOptions::default()),
            Err(AlignError::NotPlanar(_))
        ));
        ramp.pitch_deg = 3.0;
        assert!(matches!(
            align_pan(&mut ramp, cal, verge, Some(&axes), &PanOptions::default()),
            Err(AlignError::NotPlanar(_))
        ));
        ramp.pitch_deg = 5.0;
        assert!(matches!(
            zero_steering(&mut ramp, cal, verge, Some(&axes), &SteeringOptions::default()),
            Err(AlignError::NotPlanar(_))
        ));
    }

    /// The rig check (`check_rig`): a predicted rig that fits the capture is used as it
    /// is (no correction, the same rig); one turned 1.5 deg about the cameras' x axis
    /// (a vertical misalignment of about 18 px) is detected and re-fitted to the
    /// capture; a capture whose right pixels belong to other tracks fits no rig and is
    /// named.
    #[test]
    fn rig_check_corrects_a_misfitting_rig_and_names_a_hopeless_one() {
        let s = Scenario {
            seed: 1,
            noise_px: 1.0,
            near_panels: Scenario::ROBOT_NEAR_PANELS,
            ..Scenario::default()
        };
        let (mut robot, vt) = calibrated_robot(s);
        let cal = &vt.calibration;
        let enc = robot.read_encoders().unwrap();
        let cap = robot.capture().unwrap();
        let predicted = rig_at(cal, &vt.verge_axes, &enc).unwrap();
        let noise = cal.report.sigma_px;
        let (rig, correction, check) = check_rig(predicted.clone(), &[&cap], noise, &enc).unwrap();
        assert!(correction.is_none() && check.misfit_px <= check.bound_px, "{check:?}");
        assert_eq!(rig.stereo, predicted.stereo);
        assert!(check.matches > 100, "{check:?}");

        let tilt = Isometry3::rotation(Vector3::x() * 1.5f64.to_radians());
        let off = predicted.clone().corrected(Some(&tilt));
        let (fixed, correction, check) = check_rig(off, &[&cap], noise, &enc).unwrap();
        assert!(correction.is_some() && check.misfit_px > 4.0 * check.bound_px, "{check:?}");
        assert!(check.used_misfit_px <= check.bound_px, "{check:?}");
        // The re-fit undoes the tilt: measured 0.038 deg about x and 0.004 about z from the
        // predicted rig, which is itself off the truth by a few hundredths of a degree at
        // 1 px (the fit is to the data, not to the prediction); nothing about y, which the
        // check keeps (a five-parameter re-fit had drifted 0.36 deg there).
        let d = (fixed.stereo.right_from_left * predicted.stereo.right_from_left.inverse())
            .rotation
            .scaled_axis();
        assert!(d.norm().to_degrees() < 0.1, "{d:?}");
        assert!(d.y.to_degrees().abs() < 1e-3, "{d:?}");
        assert!(
            (fixed.stereo.right_from_left.translation.vector.norm()
                - predicted.stereo.right_from_left.translation.vector.norm())
            .abs()
                < 1e-12
        );

        let mut shuffled = cap.clone();
        let n = shuffled.right.len();
        let pixels: Vec<_> = shuffled.right.iter().map(|o| o.pixel).collect();
        for (i, o) in shuffled.right.iter_mut().enumerate() {
            o.pixel = pixels[(i + n / 2) % n];
        }
        let err = check_rig(predicted, &[&shuffled], noise, &enc).err();
        assert!(matches!(err, Some(AlignError::RigMisfit { .. })), "{err:?}");
        assert!(err.is_some_and(|e| e.to_string().contains("run the verge/tilt stage again")));
    }

    /// Seed 78 of `experiment coverage`'s robot group at 3 px (readings with 0.01 deg of
    /// noise) once had its right vergence axis 12 deg off (a 3 deg vergence move at 3 px),
    /// so the rig predicted at the aligned readings, 9 deg of right vergence away, was
    /// 1.9 deg off and misfitted the pan drive's captures by a median 13 px; the drive
    /// registration then found 3 consistent tracks and the pan stage failed. The estimate
    /// no longer errs so there (its points re-triangulated by support, session 19), so the
    /// test tilts that axis by 12 deg itself: the rig check must see the misfit, re-fit
    /// the rig and let the stage complete.
    #[test]
    fn a_misfitting_rig_is_corrected() {
        let s = Scenario {
            seed: 78,
            noise_px: 3.0,
            encoder_noise_deg: ENCODER_SIGMA_DEG,
            near_panels: Scenario::ROBOT_NEAR_PANELS,
            ..Scenario::default()
        };
        let opts = VergeTiltOptions {
            estimation: EstimationOptions::scaled_for_noise(3.0, 78),
            ..VergeTiltOptions::default()
        };
        let mut robot = SimulatedRobot::new(s).unwrap();
        let vt = VergeTiltRun::default().run(robot.head_mut(), &opts).unwrap();
        let axes = vt.axis_perturbations();
        let mut verge = vt.verge_axes;
        let right = verge.right.unwrap();
        let d = right.direction.into_inner();
        let about = nalgebra::Unit::new_normalize(d.cross(&nalgebra::Vector3::x()));
        let tilted = nalgebra::Rotation3::from_axis_angle(&about, 12f64.to_radians()) * d;
        verge.right =
            Some(headalign_geometry::so3::Line::new(nalgebra::Unit::new_normalize(tilted), right.point));
        let pan = PanOptions::default();
        let out = align_pan(&mut robot, &vt.calibration, &verge, Some(&axes), &pan).unwrap();
        let check = out.steps[0].rig_check;
        assert!(check.misfit_px > check.bound_px && check.correction_deg > 1.0, "{check:?}");
    }

    /// Seed 6 at 1 px in the robot's scene (pan zeros up to 40 deg) after the verge/tilt
    /// and pan stages, with the axes' perturbations.
    fn pan_aligned_seed_6() -> (SimulatedRobot, crate::procedure::VergeTiltOutcome, AxisPerturbations) {
        let s = Scenario {
            seed: 6,
            noise_px: 1.0,
            pan_zero_max_deg: 40.0,
            near_panels: Scenario::ROBOT_NEAR_PANELS,
            ..Scenario::default()
        };
        let (mut robot, vt) = calibrated_robot(s);
        let axes = vt.axis_perturbations();
        align_pan(&mut robot, &vt.calibration, &vt.verge_axes, Some(&axes), &PanOptions::default()).unwrap();
        (robot, vt, axes)
    }

    /// A steering zero whose sigma exceeds `max_sigma_zero_deg` is named, with the drives
    /// that determined it, and the wheel is not commanded to it. (Seed 170 at 3 px with
    /// exact readings once showed this with the default limit: 64 deg from three drives;
    /// since its points are re-triangulated by support it completes, 2.5 sigmas off, so
    /// the limit is lowered here instead.)
    #[test]
    fn an_undetermined_steering_zero_is_named() {
        let (mut robot, vt, axes) = pan_aligned_seed_6();
        let (cal, verge) = (&vt.calibration, &vt.verge_axes);
        let strict = SteeringOptions { max_sigma_zero_deg: 1e-3, ..SteeringOptions::default() };
        let err = zero_steering(&mut robot, cal, verge, Some(&axes), &strict).unwrap_err();
        match err {
            AlignError::SteeringUndetermined { zero_deg, sigma_deg, max_sigma_deg, drives, .. } => {
                assert!(sigma_deg > max_sigma_deg && max_sigma_deg == 1e-3, "{err}");
                assert!(drives >= 3, "{err}");
                assert!((robot.steering_encoder_deg() - zero_deg).abs() > 1e-6, "{err}");
            }
            e => panic!("expected SteeringUndetermined, got {e}"),
        }
    }

    /// At 1 px a planar robot passes the planarity tests of every drive (the false alarm
    /// rate is 1e-5 per drive when the covariances are right; the former fixed limits
    /// failed 3 of 260 experiment trials), and the stated sigmas are of the size of the
    /// errors (within 4 sigma: one seed, so only a gross inconsistency fails).
    #[test]
    fn noisy_planar_drives_pass_and_sigmas_are_plausible() {
        let (mut robot, vt, axes) = pan_aligned_seed_6();
        let (cal, verge) = (&vt.calibration, &vt.verge_axes);
        let st = zero_steering(&mut robot, cal, verge, Some(&axes), &SteeringOptions::default()).unwrap();
        let err = robot.steer_err_deg(robot.steering_encoder_deg());
        assert!(st.sigma_steer_zero_deg > 0.0 && err.abs() < 4.0 * st.sigma_steer_zero_deg, "{err} {st:?}");
        let pan = align_pan(&mut robot, cal, verge, Some(&axes), &PanOptions::default()).unwrap();
        let last = pan.steps.last().unwrap();
        let err = robot.pan_err_deg(&robot.head().encoders());
        assert!(last.sigma_calibration_deg > 0.0 && last.sigma_deg >= last.sigma_calibration_deg);
        assert!(err.abs() < 4.0 * last.sigma_deg, "{err} {last:?}");
    }
}
