//! Robot stages: pan alignment from a forward drive (paper section 4,
//! `docs/how-it-works.md#4-pan`) and steering-wheel zeroing (paper section 7,
//! `docs/how-it-works.md#5-steering`), in point mode, generic
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
//! point of the calibrated pan axis) and rotated back about the floor normal by half the
//! measured heading change (the heading is the rotation's component along the normal; the
//! chord of an arc makes half the turn angle with the tangent; exact for the rear-axle
//! line, so this assumes the pan axis stands over it, and is a no-op when the wheel is
//! straight: hence the demo's pan, steering, pan order). The pan correction is the signed
//! angle about the pan axis from the head's forward direction (mean of the optical axes)
//! to that direction, both projected onto the plane perpendicular to the pan axis (the
//! simulator's `pan_err` metric).
//!
//! **Floor normal** ([`floor`]): the robot moves on a plane whose normal `n` need not be
//! the pan axis (a real robot's stands 1-3 deg off). Each stage fits `n` (2 dof) to its
//! drives: a turn's rotation lies along `n`, every drive's translation is perpendicular
//! to it; a Gaussian prior of [`FLOOR_TILT_PRIOR_DEG`] (5 deg) per component around the
//! calibrated pan axis keeps what the drives leave free (a straight drive determines only
//! `n`'s tilt along its travel direction). The pan stage fits it per drive, the steering
//! stage to all its turns (which fix it to about 0.2 deg). The pan axis' tilt from `n` is
//! reported with its sigma (the fit's and the calibration's, propagated as below):
//! [`PanStep::floor`], [`SteeringOutcome::floor`].
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
//! (a past measurement, seeds 1-30): the rotation error of the rig
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
//! two axes perpendicular to the fitted floor normal (radians) and the centre's
//! displacement along it (baselines), is tested by its chi-square against its covariance
//! (the motion's, by central differences through the motion's perturbation, plus the
//! calibration's as above, the normal held) on `3 - h` degrees of freedom, `h` the drive's
//! leverage in the normal's fit (about 1 for a straight drive, 0.5 for each of four
//! turns); above the quantile at those degrees of freedom with the tail probability of
//! `planarity_chi2_max` at 3 dof ([`planarity_limit`]; default the 99.999 % quantile, a
//! false alarm rate of 1e-5 per drive) is [`AlignError::NotPlanar`]. So is a normal fitted
//! beyond its prior's quantile at that rate (23 deg from the pan axis in point mode): a
//! pitching robot's straight drive is best fitted by a floor perpendicular to its pitch
//! axis. The former fixed limits (1 deg off-axis rotation; screw axis 10 deg, pitch 0.2)
//! both failed planar drives (3 of 260 experiment trials) and missed smaller real tilts;
//! the test about the pan axis itself failed every drive of a robot whose pan axis stands
//! 1-3 deg off the floor's normal (chi-square 170-6700). The angle of `d` out of the
//! plane perpendicular to the pan axis is reported as an elevation check (it includes the
//! pan axis' tilt along the travel direction).
//!
//! **Steering**: drives at `settings_deg` relative to the current steering reading; each
//! gives the motion `cam1_from_cam2` (the robot's motion in a robot-fixed frame): a turn
//! below `min_turn_deg` is [`AlignError::TurnTooSmall`]; the planarity test above names
//! a motion that is not planar. One drive failing it while the others pass is left out
//! as an outlier when three remain and they all pass (`SteeringOutcome::dropped_turns`):
//! at 3 px, seed 170's fourth drive has chi-square 43.5 with the axes held as exact and
//! 42.8 with their uncertainty propagated, on the same drives (against 25.9; without
//! [`crate::verge_tilt::EstimationOptions::image_border`] its first drive, far points only,
//! 42.7 / 42.8; an earlier reading of 30.0 with the uncertainty came from a second run
//! whose pan stage had left the head elsewhere, so different drives); a robot that really
//! pitches or rolls fails every drive. The turning centres (planar motion about the
//! floor normal fitted to the turns kept) give the steering zero, wheelbase and forward
//! direction ([`steering_from_turns`], in the floor's plane); the wheel is then set
//! straight. The zero's sigma: each drive's motion covariance
//! (independent drives) through its centre and the floor normal refitted, plus the
//! calibration's (every drive and the normal refitted under each perturbed calibration),
//! by central differences (96 % coverage over 100
//! trials at 1 px). A zero whose sigma exceeds `max_sigma_zero_deg` (default 10 deg)
//! is [`AlignError::SteeringUndetermined`], before the wheel is commanded: at 3 px with
//! exact readings, seed 170's first drive is left out and the other three (24-57 tracks
//! each) give -87 +- 64 deg.
//!
//! Degenerate drives: a median flow below `min_flow_px` is [`AlignError::DriveTooShort`].
//! Every drive is followed by the reverse drive, so the robot ends where it started.
//!
//! [`StereoHead`]: headalign_platform::StereoHead
//! [`Vehicle`]: headalign_platform::Vehicle
//! [`RigCalibration`]: crate::verge_tilt::RigCalibration
//! [`AxisPerturbations`]: crate::procedure::AxisPerturbations
//! [`PROPAGATION_STEP_SIGMAS`]: crate::procedure::PROPAGATION_STEP_SIGMAS
//! [`refine_rig_motion`]: headalign_geometry::rigmotion::refine_rig_motion
//! [`steering_from_turns`]: headalign_geometry::steering::steering_from_turns
//! [`translation_from_flow`]: headalign_geometry::translation::translation_from_flow
//!
//! Code layout: `rig` (the rig at a stage's readings and its check), `drive` (the rigid
//! motion of a drive), `floor` (the floor normal's fit and the planarity limit),
//! `propagation` (the covariance propagations and the planarity test), `pan` (the pan stage, [`pan_step`] a pipeline of named steps), `steering` (the
//! steering stage).

mod drive;
pub mod floor;
pub mod one_motion;
mod pan;
pub mod pan_fixation;
mod propagation;
mod rig;
pub mod stages;
mod steering;
#[cfg(test)]
mod tests;

use headalign_geometry::ransac::RansacOptions;
use headalign_geometry::translation::TranslationOptions;
use headalign_platform::Encoders;
use serde::Serialize;

pub(crate) use drive::drive_motion;
pub use floor::{FLOOR_TILT_PRIOR_DEG, FloorNormal, planarity_limit};
pub use pan::{align_pan, pan_step};
pub(crate) use pan::{angle_about, head_forward};
pub use rig::{RIG_MISFIT_FLOOR_PX, RIG_MISFIT_SIGMAS, RigCheck, predicted_rig, stereo_fundamental};
pub(crate) use rig::{check_rig, rig_at};
pub use steering::zero_steering;

use crate::error::{AlignError, StepContext};
use crate::verge_tilt::ENCODER_SIGMA_DEG;

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
    /// Planarity test: largest chi-square at 3 degrees of freedom of a drive's rotation
    /// about the two axes perpendicular to the fitted floor normal and its translation
    /// along it, against their covariance (the motion's and the calibration's); the test
    /// uses the quantile of the same tail probability at the degrees of freedom the
    /// normal's fit leaves ([`planarity_limit`]); more is [`AlignError::NotPlanar`] (the
    /// robot pitched or rolled). Default [`PLANARITY_CHI2_MAX`], the 99.999 % quantile: a
    /// false alarm rate of 1e-5 per drive when the covariance is right.
    pub planarity_chi2_max: f64,
    /// Standard deviation of each joint's encoder reading, degrees (the noise of the
    /// readings the drive's rig is predicted at; 0: exact). It enters the calibration
    /// part of the covariance (`calibration_covariance`, module docs): a reading 0.01 deg off turns
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
/// [`crate::verge_tilt::EstimationOptions::scaled_for_noise`] scales alike), else 1. A
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
    /// Heading change measured during the drive (about the fitted floor normal), degrees.
    pub turn_deg: f64,
    /// Rotation about axes perpendicular to the fitted floor normal (planarity check),
    /// degrees.
    pub off_axis_deg: f64,
    /// Chi-square of the drive's rotation about axes perpendicular to the fitted floor
    /// normal and its translation along it, against their covariance (planarity test).
    pub planarity_chi2: f64,
    /// Its degrees of freedom: 3 less the drive's leverage in the floor normal's fit
    /// ([`floor`] module docs; about 2 for a straight drive).
    pub planarity_dof: f64,
    /// The floor normal fitted to this drive and the pan axis' tilt from it.
    pub floor: FloorNormal,
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
    /// The floor normal of the last drive and the pan axis' tilt from it (each drive
    /// fits its own: `steps[k].floor`).
    pub floor: Option<FloorNormal>,
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
    /// limit at 3 dof of the rotation about axes perpendicular to the fitted floor normal
    /// and the translation along it, against the motion's and the calibration's
    /// covariance (applied at the drive's degrees of freedom, [`planarity_limit`]).
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
    /// Angle of the screw axis from the fitted floor normal, degrees.
    pub axis_from_floor_deg: f64,
    /// Chi-square of the planarity test about the fitted floor normal (options).
    pub planarity_chi2: f64,
    /// Its degrees of freedom: 3 less the drive's leverage in the floor normal's fit.
    pub planarity_dof: f64,
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
    /// The floor normal fitted to the drives kept (their turns' axes) and the pan axis'
    /// tilt from it.
    pub floor: FloorNormal,
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
