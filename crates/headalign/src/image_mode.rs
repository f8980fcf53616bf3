//! Image mode: the verge/tilt procedure on images through the vision front end (no
//! simulator-provided correspondences), on any [`ImagingHead`]: verging (paper section
//! 6, [`crate::fixation`]), then the captures, tracking, estimation, alignment and checks
//! of the point-mode procedure ([`VergeTiltRun::run_detecting`]: a planar or far scene
//! takes the planar route), and after it the robot stages on the robot's images
//! ([`robot_stages`]: the front end in its drive mode, stereo guided by the calibrated
//! rig, the tracks undistorted with the calibration's lenses).
//!
//! [`run`] is the one image-mode procedure: the command line runs it on the simulator
//! (`demo --images`), on a driver process (`run --head-cmd`) and on a recorded session
//! (`replay`); the same code on the same images gives the same numbers. It names each
//! stage to a callback before the stage's captures ([`Stage`]), so that a recording head
//! wrapped around the head by the caller files them (this module knows no session format).
//!
//! Options: [`ImageModeOptions`] (rotations and the estimation, by default
//! [`tracked_estimation`]) and [`ImageStagesOptions`] (the robot stages' corner count).
//! [`judgement`] gives the verdict of the check after the move and the model-fit checks
//! against the noise the front end measured; [`figure6`] draws the paper's Figure 6.
//!
//! Pitfall: the robot stages' geometry is pinhole, so their captures pass through
//! [`procedure::pinhole_capture`] (unchanged for a pinhole calibration).

use headalign_geometry::bundle::{BundleOptions, CovarianceModel};
use headalign_platform::{
    Encoders, ImagingHead, Odometry, PlatformError, StereoCapture, StereoHead, StereoImages, Vehicle,
};
use headalign_vision::draw::{BLUE, Canvas, GREEN, MAGENTA, RED, YELLOW};

use crate::alignment::AlignmentSolution;
use crate::calibrate::image_noise::MeasuredVariances;
use crate::error::AlignError;
use crate::fixation::{VergingOptions, VergingReport, verge_to_common_view};
use crate::observations::View;
use crate::procedure::{
    self, AutoRotation, CheckVerdict, RouteOutcome, VergeTiltOptions, VergeTiltOutcome, VergeTiltRun,
    capture_plan, resolve_rotation,
};
use crate::robot::stages::{RobotOutcomes, RobotPlan, StageHooks, run_robot_stages};
use crate::robot::stereo_fundamental;
use crate::tracking::{FrontEndOptions, TrackingHead, TrackingMode, ViewTracking, tracked_view_name};
use crate::verge_tilt::{EstimationOptions, ModelFit, RigCalibration, model_fit, observation_view_names};

/// A stage of [`run`], named to its callback before the stage's captures.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Verging to a common view (no planned captures).
    Verging,
    /// Probing the rotations (`auto_rotation` only; no planned captures).
    RotationProbe,
    /// The verge/tilt captures (planned: [`capture_plan`]; then the check view).
    VergeTilt,
}

/// The options of [`run`].
#[derive(Debug, Clone)]
pub struct ImageModeOptions {
    /// Rotation of the elevation, pan and vergence moves, degrees. Default: the
    /// procedure's ([`VergeTiltOptions::default`], 3 deg).
    pub rotation_deg: f64,
    /// Choose the elevation/pan rotations by probing first ([`resolve_rotation`] with
    /// [`AutoRotation::default`]). Default off.
    pub auto_rotation: bool,
    /// The estimation. Default [`tracked_estimation`] with the default seed.
    pub estimation: EstimationOptions,
    /// Verging. Default [`VergingOptions::default`].
    pub verging: VergingOptions,
}

impl Default for ImageModeOptions {
    fn default() -> Self {
        Self {
            rotation_deg: VergeTiltOptions::default().rotation_deg,
            auto_rotation: false,
            estimation: tracked_estimation(EstimationOptions::default().seed),
            verging: VergingOptions::default(),
        }
    }
}

impl ImageModeOptions {
    /// An error for a rotation that is not a positive finite angle, or bad estimation
    /// options.
    pub fn validate(&self) -> Result<(), AlignError> {
        if !(self.rotation_deg.is_finite() && self.rotation_deg > 0.0) {
            return Err(AlignError::InvalidOption(format!(
                "rotation must be a positive number of degrees, got {}",
                self.rotation_deg
            )));
        }
        self.estimation.validate()
    }

    /// The verge/tilt procedure's options.
    fn verge_tilt(&self) -> VergeTiltOptions {
        VergeTiltOptions {
            rotation_deg: self.rotation_deg,
            verge_rotation_deg: self.rotation_deg,
            estimation: self.estimation.clone(),
            auto_rotation: self.auto_rotation.then(AutoRotation::default),
            ..VergeTiltOptions::default()
        }
    }
}

/// What the image procedure captured and found, whether it succeeded or not.
#[derive(Default)]
pub struct ImageRun {
    /// The verging report (if verging finished).
    pub verging: Option<VergingReport>,
    /// The verge/tilt views (tracked observations), in capture order.
    pub run: VergeTiltRun,
    /// Their images.
    pub images: Vec<StereoImages>,
    /// The front end's report per view.
    pub tracking: Vec<ViewTracking>,
    /// The rotations were chosen by probing.
    pub auto_rotation: bool,
}

/// Called before each stage with the stage and its planned captures `(name, target)`.
pub type OnStage<'a, H> = dyn FnMut(&mut H, Stage, Vec<(String, Encoders)>) + 'a;

/// Verging, then the verge/tilt procedure on images through the front end, on any
/// imaging head. `on_stage` is called before each stage. With `auto_rotation` the
/// elevation/pan rotations are chosen first by probing ([`resolve_rotation`], default
/// [`AutoRotation`]: up to 10 deg each way plus diagonal views, while the tracker keeps
/// the reference view's tracks), in stage [`Stage::RotationProbe`] through a tracking
/// head of its own; the verge/tilt stage then starts a fresh tracker at its initial view,
/// so that an estimate from the recorded verge/tilt views sees the same tracks. The run
/// is returned with the outcome: what was captured survives a failure.
pub fn run<H: ImagingHead>(
    head: &mut H,
    options: &ImageModeOptions,
    on_stage: &mut OnStage<'_, H>,
) -> (ImageRun, Result<RouteOutcome, AlignError>) {
    let mut out = ImageRun { auto_rotation: options.auto_rotation, ..ImageRun::default() };
    on_stage(head, Stage::Verging, Vec::new());
    let verging = match verge_to_common_view(head, &options.verging) {
        Ok(v) => v,
        Err(e) => return (out, Err(e.in_step("verging"))),
    };
    let vt = options.verge_tilt();
    let vt = if options.auto_rotation {
        on_stage(head, Stage::RotationProbe, Vec::new());
        let resolved = TrackingHead::new(head, FrontEndOptions::default())
            .and_then(|mut probing| resolve_rotation(&mut probing, &vt))
            .map_err(|e| e.in_step("choosing the rotations"));
        match resolved {
            Ok(o) => o,
            Err(e) => {
                out.verging = Some(verging);
                return (out, Err(e));
            }
        }
    } else {
        vt
    };
    on_stage(head, Stage::VergeTilt, capture_plan(&verging.encoders, &vt));
    out.verging = Some(verging);
    let mut tracking_head = match TrackingHead::new(head, FrontEndOptions::default()) {
        Ok(t) => t,
        Err(e) => return (out, Err(e)),
    };
    let outcome = out
        .run
        .run_detecting(&mut tracking_head, &vt)
        .map_err(|e| e.in_step("verge/tilt procedure on images"));
    out.images = std::mem::take(&mut tracking_head.images);
    out.tracking = std::mem::take(&mut tracking_head.tracking);
    (out, outcome)
}

/// The estimation options of image mode: the default ones with the covariance clustered
/// by track ([`CovarianceModel::PointClustered`], the sandwich estimate from the
/// residuals themselves). Tracked corners are not i.i.d. Gaussian: their localisation
/// error differs from track to track (per-track RMS 0.20 / 0.35 / 0.58 px at the 10 / 50
/// / 90 % quantiles against the true cameras, seed 1, a past measurement), and
/// the Gaussian model spreads one `sigma_px` evenly. Measured (`bench/seeds.py 1 20
/// --images`, the same estimates): z-score RMS over the 13 reported quantities 1.39 ->
/// 1.32, 95 % coverage 85 -> 89 %; right focal lengths and the aligned readings stay
/// 1.3-1.5. Measured once more (no command reproduces it): no mean bias, no error
/// correlation between neighbouring tracks, coarser clusters do not help; tracks at depth
/// steps carry part of it, but leaving them out ([`crate::verge_tilt::DepthStepGate`])
/// did not improve the full pipeline on seeds 1-20 and cost focal accuracy, so it stays
/// off here.
pub fn tracked_estimation(seed: u64) -> EstimationOptions {
    let d = EstimationOptions::default();
    let bundle = BundleOptions { covariance_model: CovarianceModel::PointClustered, ..d.bundle.clone() };
    EstimationOptions { seed, bundle, ..d }
}

/// Corners per image in the robot stages (the verge/tilt stage uses the front end's
/// 1500). A forward drive's pan is sensitive to the drive's measured rotation (an error
/// `d` moves the epipole by about `d Z / D`: 15 d for a 0.10 m drive at 1.5 m), so the
/// rigid motion needs many tracks: seed 11 linked 63-69 tracks per drive with 1500
/// corners and ended 4.2 deg off; with 3000, 285-296 tracks and 0.26 deg (seed 20: 2.9
/// -> 0.7 deg).
pub const ROBOT_FEATURES: usize = 3000;

/// The options of [`robot_stages`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ImageStagesOptions {
    /// Corners per image. Default [`ROBOT_FEATURES`] (3000).
    pub max_features: usize,
}

impl Default for ImageStagesOptions {
    fn default() -> Self {
        Self { max_features: ROBOT_FEATURES }
    }
}

impl ImageStagesOptions {
    /// An error for no corners.
    pub fn validate(&self) -> Result<(), AlignError> {
        if self.max_features == 0 {
            return Err(AlignError::InvalidOption("robot stages: max_features must be at least 1".into()));
        }
        Ok(())
    }
}

/// What the robot stages of an image-mode run found, and the front end's report per
/// capture of theirs.
pub struct RobotRun {
    /// The stages' outcomes.
    pub outcomes: RobotOutcomes,
    /// The front end's report per robot-stage capture, in order.
    pub tracking: Vec<ViewTracking>,
}

/// The robot stages of `plan` on images: the front end in [`TrackingMode::Previous`] (the
/// captures before and after each drive share track ids) over `head`; `hooks` as in
/// [`run_robot_stages`] (its `stage` callback sees `head` itself).
pub fn robot_stages<H: ImagingHead + Vehicle>(
    head: &mut H,
    plan: &RobotPlan,
    outcome: &VergeTiltOutcome,
    options: &ImageStagesOptions,
    hooks: StageHooks<'_, H>,
) -> Result<RobotRun, AlignError> {
    options.validate()?;
    let mut front = FrontEndOptions { mode: TrackingMode::Previous, ..FrontEndOptions::default() };
    front.features.max_features = options.max_features;
    // Stereo matching guided by the calibrated rig: with parallel cameras and the near
    // scene 1 m away, disparities reach 200 px and free matching finds mostly wrong pairs.
    let (calib, verge) = (&outcome.calibration, &outcome.verge_axes);
    let prior = move |enc: &Encoders| stereo_fundamental(calib, verge, enc).ok();
    let mut tracking_head = TrackingHead::new(head, front)?.with_stereo_prior(Box::new(prior));
    // The stages' geometry is pinhole: they see the tracks undistorted with the
    // calibration's lenses (unchanged for a pinhole calibration).
    let mut undistorting = Undistorting { inner: &mut tracking_head, calib };
    let StageHooks { stage, warn } = hooks;
    let outcomes = run_robot_stages(
        &mut undistorting,
        plan,
        &outcome.calibration,
        &outcome.verge_axes,
        Some(&outcome.axis_perturbations()),
        StageHooks { stage: &mut |t, name| stage(t.inner.inner(), name), warn },
    )
    .map_err(|e| e.in_step("robot stages on images"))?;
    Ok(RobotRun { outcomes, tracking: std::mem::take(&mut tracking_head.tracking) })
}

/// A head whose captures are undistorted with a calibration's estimated lenses
/// ([`procedure::pinhole_capture`]; unchanged for a pinhole calibration), for the robot
/// stages, whose geometry is pinhole. Every other call goes to `inner`.
struct Undistorting<'a, H> {
    inner: &'a mut H,
    calib: &'a RigCalibration,
}

impl<H: StereoHead> StereoHead for Undistorting<'_, H> {
    fn image_size(&self) -> [u32; 2] {
        self.inner.image_size()
    }
    fn read_encoders(&mut self) -> Result<Encoders, PlatformError> {
        self.inner.read_encoders()
    }
    fn move_to(&mut self, target: &Encoders) -> Result<(), PlatformError> {
        self.inner.move_to(target)
    }
    fn capture(&mut self) -> Result<StereoCapture, PlatformError> {
        let capture = self.inner.capture()?;
        Ok(procedure::pinhole_capture(self.calib, &capture))
    }
}

impl<H: Vehicle> Vehicle for Undistorting<'_, H> {
    fn drive(&mut self, distance_m: f64) -> Result<(), PlatformError> {
        self.inner.drive(distance_m)
    }
    fn steer_to(&mut self, encoder_deg: f64) -> Result<(), PlatformError> {
        self.inner.steer_to(encoder_deg)
    }
    fn read_steering(&mut self) -> Result<f64, PlatformError> {
        self.inner.read_steering()
    }
    fn steer_by(&mut self, delta_deg: f64) -> Result<(), PlatformError> {
        self.inner.steer_by(delta_deg)
    }
    fn last_odometry(&self) -> Option<Odometry> {
        self.inner.last_odometry()
    }
}

/// The verdict of a route's check after the move ([`procedure::check_verdict`]) and, on
/// the general route, the estimate's model-fit checks against the noise the front end
/// measured in the rig views ([`crate::verge_tilt::model_fit`]).
pub fn judgement(run: &ImageRun, route: &RouteOutcome) -> (CheckVerdict, Option<ModelFit>) {
    match route {
        RouteOutcome::Planar(p) => (p.verdict.clone(), None),
        RouteOutcome::General(o, _) => {
            let names: Vec<String> = run.run.views.iter().map(|v| v.name.clone()).collect();
            let rig_views = names.iter().position(|n| n == "verge").unwrap_or(names.len());
            let rig: Vec<(String, String)> = names
                .iter()
                .take(rig_views)
                .enumerate()
                .map(|(i, n)| (n.clone(), tracked_view_name(i)))
                .collect();
            let keys = observation_view_names(&o.calibration, &rig);
            let measured: MeasuredVariances = run
                .tracking
                .iter()
                .enumerate()
                .map(|(i, t)| (tracked_view_name(i), t.localisation.clone()))
                .collect();
            let size = run.images.first().map_or([0, 0], StereoImages::image_size);
            let fit = model_fit(&o.calibration, &keys, &measured, size);
            let mut verdict = o.verdict.clone();
            verdict.judge_fit(&fit);
            (verdict, Some(fit))
        }
    }
}

/// The paper's Figure 6 on the reference view (stereo pair side by side): features used by
/// the adjustment (green; others red), the invariant lines of the pan (horizon, blue) and
/// elevation (yellow) rotations, and the fixation point (magenta). `view0` is the tracked
/// reference view, `first` its images.
pub fn figure6(
    first: &StereoImages,
    view0: &View,
    calib: &RigCalibration,
    solution: &AlignmentSolution,
) -> Canvas {
    let used: std::collections::HashSet<u64> =
        calib.observations.iter().filter(|o| o.view == 0).map(|o| calib.point_tracks[o.point]).collect();
    let lines = &solution.invariant_lines;
    let fixation = [solution.fixation_px_left, solution.fixation_px_right];
    let mut halves = Vec::new();
    for (k, (image, list)) in
        [(&first.left, &view0.capture.left), (&first.right, &view0.capture.right)].into_iter().enumerate()
    {
        let mut c = Canvas::from_gray(image);
        for o in list {
            let colour = if used.contains(&o.track) { GREEN } else { RED };
            c.circle([o.pixel.x, o.pixel.y], 3.0, colour, 1);
        }
        let (pan, elevation) = if k == 0 {
            (lines.pan_left, lines.elevation_left)
        } else {
            (lines.pan_right, lines.elevation_right)
        };
        c.image_line(pan, BLUE, 2);
        c.image_line(elevation, YELLOW, 2);
        c.circle(fixation[k], 12.0, MAGENTA, 2);
        c.cross(fixation[k], 18.0, MAGENTA, 2);
        halves.push(c);
    }
    Canvas::beside(&halves[0], &halves[1])
}

/// Caption of [`figure6`] (`figure6.png`) in the reports.
pub const FIGURE6_CAPTION: &str = "figure6.png: the first view (left | right) as the paper's Figure 6: features the bundle adjustment used (green) and not (red), the invariant lines of the pan (blue) and elevation (yellow) rotations, and the fixation point (magenta).";

#[cfg(test)]
mod tests {
    use super::*;

    /// The defaults validate, with the track-clustered covariance and 3000 robot-stage
    /// corners; a non-positive rotation or no corners is an error.
    #[test]
    fn options_have_documented_defaults_and_validate() {
        let o = ImageModeOptions::default();
        assert!(o.validate().is_ok());
        assert_eq!(o.estimation.bundle.covariance_model, CovarianceModel::PointClustered);
        assert_eq!(o.verge_tilt().verge_rotation_deg, o.rotation_deg);
        for bad in [0.0, -3.0, f64::NAN] {
            assert!(
                ImageModeOptions { rotation_deg: bad, ..ImageModeOptions::default() }.validate().is_err()
            );
        }
        assert_eq!(ImageStagesOptions::default().max_features, ROBOT_FEATURES);
        assert!(ImageStagesOptions { max_features: 0 }.validate().is_err());
    }

    /// A step's failure prints as `step: cause` through the error chain.
    #[test]
    fn a_failed_step_names_itself_first() {
        let e = AlignError::Images("no corners".into()).in_step("verging");
        let source = std::error::Error::source(&e).map(ToString::to_string);
        assert_eq!((e.to_string(), source.as_deref()), ("verging".into(), Some("images: no corners")));
    }
}
