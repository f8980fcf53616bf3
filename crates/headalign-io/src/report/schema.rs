//! The JSON objects the commands print with `--json`, one typed struct per schema, each
//! built in one place: `headalign-demo/1` ([`DemoReport`]), `headalign-run/1`
//! ([`RunReport`]), `headalign-replay/1` ([`ReplayReport`]), `headalign-align/1`
//! ([`AlignReport`]), `headalign-calibrate/1` ([`CalibrateReport`]), and the file
//! `alignment.json` (`headalign-alignment/2`, [`AlignmentFile`]). docs/formats.md
//! ("JSON on stdout") documents every member: its type, unit, meaning and when it is null.
//!
//! Every member is a field, so every route of a command prints the same members: what a
//! route cannot give is an `Option` (`null`) or an empty list, never a missing member.
//! The members shared by `demo`, `run` and `replay` (the procedure's estimate, checks,
//! robot stages, timings) are one struct, [`Procedure`], flattened into each report; the
//! robot stages' members are [`RobotOutcomes`]' fields, flattened into it.
//!
//! Adding a member: add a field to the struct of its schema (shared by demo, run and
//! replay: [`Procedure`]; with the truth: [`DemoReport`]; the robot stages' outcome types
//! in `headalign::robot::stages` flow through as they are), fill it where that struct is built, add
//! a row to its table in docs/formats.md (the `json_schemas` integration test compares
//! the two), and bump the schema's version when a member changes meaning or goes.
//!
//! The demo's members against the simulator's truth ([`Truth`], [`Errors`], [`Before`],
//! [`ReadingErrors`]) are plain data: this crate does not depend on the simulator (its
//! truth is visible only to the simulator, the demo and the experiments), so the command
//! line fills them from `headalign_sim`.
//!
//! Pitfall: a schema's nested members that differ by route (`checks`, `planar`, `scene`,
//! `report`) are kept as the library's own serialisations ([`Value`]); the test compares
//! the top-level members and those of `errors` and `before`.

use headalign::alignment::{AlignmentSolution, InvariantLines, VergeAxes};
use headalign::calibrate::{DensityReport, KnownIntrinsicsRig, LensModel, MotionCalibration};
use headalign::calibration::TranslationUnit;
use headalign::facing_plane::SceneCheck;
use headalign::image_mode::{self as image_mode, ImageRun, RobotRun};
use headalign::procedure::CheckVerdict;
use headalign::procedure::{
    AlignmentSigmas, PlanarOutcome, PlanarSessionAlignment, RouteOutcome, SessionAlignment, VergeTiltOutcome,
};
use headalign::robot::stages::RobotPlan;
use headalign::verge_tilt::{ModelFit, RigCalibration};
use headalign_geometry::bundle::Covariance;
use headalign_geometry::camera::Intrinsics;
use headalign_geometry::distortion::Distortion;
use headalign_geometry::so3::Line;
use headalign_platform::Encoders;
use nalgebra::Isometry3;
use serde::Serialize;
use serde_json::{Value, json};

use headalign::robot::stages::RobotOutcomes;

/// Schema of `demo --json` (and a demo session's `report.json`).
pub const DEMO: &str = "headalign-demo/1";
/// Schema of `run --json` (and a run session's `report.json`).
pub const RUN: &str = "headalign-run/1";
/// Schema of `replay --json` on a head's session or recording.
pub const REPLAY: &str = "headalign-replay/1";
/// Schema of `align --json`.
pub const ALIGN: &str = "headalign-align/1";
/// Schema of `calibrate --json` (and of `replay --json` on a calibration session).
pub const CALIBRATE: &str = "headalign-calibrate/1";

/// What a route's robot stages say when they did not run (the planar route).
pub type SkipNote = Option<&'static str>;

/// A camera's intrinsics with their sigmas (pixels).
#[derive(Debug, Clone, Serialize)]
pub struct Camera {
    /// The camera matrix, row-major.
    #[serde(rename = "K")]
    pub k: [[f64; 3]; 3],
    pub fx: f64,
    pub fy: f64,
    pub skew: f64,
    pub cx: f64,
    pub cy: f64,
    /// 1-sigma of each estimated parameter; null when not estimated.
    pub sigma: CameraSigma,
}

/// The sigmas of a camera's intrinsics, pixels (null: not estimated or no covariance).
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct CameraSigma {
    pub fx: Option<f64>,
    pub fy: Option<f64>,
    pub cx: Option<f64>,
    pub cy: Option<f64>,
}

impl Camera {
    /// A camera from its intrinsics and a sigma per parameter name (`fx`, `fy`, `cx`, `cy`).
    pub fn new(k: &Intrinsics, sigma: impl Fn(&str) -> Option<f64>) -> Self {
        Self {
            k: [[k.fx, k.skew, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]],
            fx: k.fx,
            fy: k.fy,
            skew: k.skew,
            cx: k.cx,
            cy: k.cy,
            sigma: CameraSigma { fx: sigma("fx"), fy: sigma("fy"), cx: sigma("cx"), cy: sigma("cy") },
        }
    }
}

/// A point in each image, pixels.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct PixelPair {
    pub left: [f64; 2],
    pub right: [f64; 2],
}

/// The estimate every procedure reports (`estimate`), on either route.
#[derive(Debug, Clone, Serialize)]
pub struct Estimate {
    pub left: Camera,
    pub right: Camera,
    /// The aligned readings, degrees.
    pub aligned_encoders: Encoders,
    /// Their sigmas, degrees.
    pub aligned_sigma_deg: AlignmentSigmas,
    /// Where each camera's optical axis meets the fixation point, pixels.
    pub fixation_px: PixelPair,
    /// The readings the head ended at, degrees.
    pub final_encoders: Encoders,
    /// The right camera's elevation error no joint can remove, as calibrated, degrees.
    pub predicted_elev_err_r_deg: f64,
    pub roll_left_deg: f64,
    pub roll_right_deg: f64,
    /// The estimated lenses ([`lens_json`]); null for pinhole cameras.
    pub lens: Option<Value>,
}

/// The procedure's rotations, degrees.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Rotations {
    /// The rotations were chosen by probing (`--auto-rotation`).
    pub auto: bool,
    pub rotation_deg: f64,
    pub diagonal_rotation_deg: f64,
    pub verge_rotation_deg: f64,
}

/// Wall times, seconds.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Timings {
    /// The verge/tilt estimation.
    pub estimation_s: f64,
    /// The whole command.
    pub total_s: f64,
}

/// The members `demo`, `run` and `replay` share: what the procedure did and found, with
/// no truth.
#[derive(Debug, Clone, Serialize)]
pub struct Procedure {
    /// `points` (the simulator's or a session's tracked points) or `images`.
    pub mode: &'static str,
    /// `general` or `planar` (a planar or far scene, paper section 3.3).
    pub route: &'static str,
    /// The scene check that chose the route (`headalign::facing_plane::SceneCheck`).
    pub scene: Value,
    /// The planar route's calibration (`headalign::facing_plane::PlanarCalibration`); null on
    /// the general route.
    pub planar: Option<Value>,
    pub estimate: Estimate,
    /// The adjustment's report (`headalign::verge_tilt::EstimationReport`); null on the
    /// planar route.
    pub report: Option<Value>,
    /// The checks after the move (the general route's `CheckStep`s or the planar route's
    /// `PlanarCheck`s).
    pub checks: Value,
    /// Why the planar route's check after the move was not made; null otherwise.
    pub check_failure: Option<String>,
    /// The check after the move judged against the reported sigmas (and, on the general
    /// image route, the estimate's fit to the measured image noise):
    /// `headalign::procedure::CheckVerdict` and its one-line `failure` (null when it
    /// passed).
    pub verdict: Value,
    /// The estimate's residuals against the image noise the front end measured
    /// (`headalign::verge_tilt::ModelFit`); null in point mode and on the planar route.
    pub model_fit: Option<Value>,
    /// Warnings about the data or the model, each one line.
    pub warnings: Vec<String>,
    pub rotations: Rotations,
    pub timings: Timings,
    /// The verge/tilt views, in capture order.
    pub views: Vec<String>,
    /// Image mode: verging, the front end's report per view; null in point mode.
    pub images: Option<Value>,
    /// The stages asked for (`--stages`, or the session's).
    pub stages: Vec<String>,
    /// Why the robot stages did not run (the planar route); null otherwise.
    pub robot_stages: SkipNote,
    /// The robot stages' outcomes: `pan`, `pan_fixate`, `one_motion` (lists, empty when
    /// not run), `steering` (null when not run).
    #[serde(flatten)]
    pub robot: RobotOutcomes,
    /// Image mode: the front end's report per robot-stage capture; null otherwise.
    pub robot_tracking: Option<Value>,
    /// The session folder recorded; null when none.
    pub session: Option<String>,
    /// Files written besides the session's views (the calibration files of a run with a
    /// lens model).
    pub files: Vec<String>,
}

/// `run --json`: [`Procedure`].
#[derive(Debug, Clone, Serialize)]
pub struct RunReport {
    pub schema: &'static str,
    #[serde(flatten)]
    pub procedure: Procedure,
}

impl RunReport {
    pub fn new(procedure: Procedure) -> Self {
        Self { schema: RUN, procedure }
    }
}

/// `replay --json` of a head's session or recording: [`Procedure`] and where it came from.
#[derive(Debug, Clone, Serialize)]
pub struct ReplayReport {
    pub schema: &'static str,
    #[serde(flatten)]
    pub procedure: Procedure,
    /// The session or recording replayed.
    pub replayed: String,
    /// A session: recorded head calls left over (0 when the replay matched); null for a
    /// recording.
    pub unplayed_events: Option<usize>,
    /// A recording: its still views; null for a session.
    pub still_views: Option<usize>,
    /// A recording: the still views the procedure used; null for a session.
    pub still_views_used: Option<usize>,
}

/// Alignment errors against the simulator's truth, degrees (`headalign_sim::metrics`).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Errors {
    pub verge_err_l_deg: f64,
    pub verge_err_r_deg: f64,
    pub elev_err_l_deg: f64,
    pub elev_err_r_deg: f64,
    /// The right camera's elevation error at the true aligned readings (no joint removes it).
    pub elev_err_r_unavoidable_deg: f64,
    /// `elev_err_r_deg - elev_err_r_unavoidable_deg`.
    pub elev_err_r_excess_deg: f64,
    /// Null when no stage moved the pan joint.
    pub pan_err_deg: Option<f64>,
    /// Null when the steering stage did not run.
    pub steer_err_deg: Option<f64>,
    /// Calibration errors, percent.
    pub f_err_pct: f64,
    pub aspect_err_pct: f64,
    pub pp_err_pct: f64,
    /// Null where not computed (image mode, the planar route).
    pub recon_err_pct: Option<f64>,
}

/// The simulated robot's errors at the start, degrees.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Before {
    pub verge_err_l_deg: f64,
    pub verge_err_r_deg: f64,
    pub elev_err_l_deg: f64,
    pub elev_err_r_deg: f64,
    pub pan_err_deg: f64,
    pub steer_err_deg: f64,
}

/// Estimated minus true aligned readings, degrees.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct ReadingErrors {
    pub elevation: f64,
    pub verge_left: f64,
    pub verge_right: f64,
}

impl ReadingErrors {
    pub fn new(estimate: &Encoders, truth: &Encoders) -> Self {
        Self {
            elevation: estimate.elevation - truth.elevation,
            verge_left: estimate.verge_left - truth.verge_left,
            verge_right: estimate.verge_right - truth.verge_right,
        }
    }
}

/// The simulator's truth.
#[derive(Debug, Clone, Serialize)]
pub struct Truth {
    pub left: Camera,
    pub right: Camera,
    /// The rendered lens (`headalign_geometry::distortion::Distortion`).
    pub distortion: Value,
    pub aligned_encoders: Encoders,
    pub steer_zero_deg: f64,
    pub wheelbase_m: f64,
    /// The pan axis' tilt from the floor normal.
    pub pan_tilt_deg: f64,
}

/// `demo --json`: [`Procedure`] and the run against the simulator's truth.
#[derive(Debug, Clone, Serialize)]
pub struct DemoReport {
    pub schema: &'static str,
    #[serde(flatten)]
    pub procedure: Procedure,
    /// The scenario simulated (`headalign_sim::Scenario`).
    pub scenario: Value,
    pub truth: Truth,
    pub errors: Errors,
    pub before: Before,
    pub aligned_reading_errors_deg: ReadingErrors,
}

/// `align --json`, on either route.
#[derive(Debug, Clone, Serialize)]
pub struct AlignReport {
    pub schema: &'static str,
    /// `general` or `planar`.
    pub route: &'static str,
    pub scene: Value,
    /// The planar route's calibration; null on the general route.
    pub planar: Option<Value>,
    pub left: Camera,
    pub right: Camera,
    pub fixation_px: PixelPair,
    /// The fixation points' own sigmas (`[x, y]` per camera; not the readings': a
    /// reading turns the principal point onto the fixation point); null on the planar
    /// route.
    pub fixation_sigma_px: Option<PixelPair>,
    pub invariant_lines: InvariantLines,
    /// The head's axes (`head.json`'s); null on the planar route.
    pub axes: Option<Value>,
    pub aligned_encoders: Encoders,
    pub aligned_sigma_deg: AlignmentSigmas,
    pub verge_axes_measured: bool,
    pub predicted_elev_err_r_deg: f64,
    pub roll_left_deg: f64,
    pub roll_right_deg: f64,
    /// What the scene leaves undetermined (empty on the general route).
    pub undetermined: Vec<String>,
    /// The adjustment's report; null on the planar route.
    pub report: Option<Value>,
    /// The estimate's residuals against the image noise the front end measured
    /// (`headalign::verge_tilt::ModelFit`); null for observation files and the planar route.
    pub model_fit: Option<Value>,
    /// The estimated lenses; null for pinhole cameras.
    pub lens: Option<Value>,
    pub warnings: Vec<String>,
    pub files: Vec<String>,
    pub seconds: f64,
}

impl AlignReport {
    /// `align --json` on the general route: the session's alignment `a`, the scene check
    /// that chose the route, the head's axes ([`head_axes_json`]), the model-fit checks
    /// (image sessions), the warnings, the files written and the wall time (seconds).
    pub fn general(
        a: &SessionAlignment,
        scene: &SceneCheck,
        axes: Value,
        fit: Option<&ModelFit>,
        warnings: Vec<String>,
        files: Vec<String>,
        seconds: f64,
    ) -> Result<Self, serde_json::Error> {
        let (calib, solution) = (&a.calibration, &a.solution);
        let state = &calib.bundle.state;
        let s = |side: &'static str| move |p: &str| calib.bundle.covariance.sigma(&format!("{side}.{p}"));
        Ok(Self {
            schema: ALIGN,
            route: "general",
            scene: serde_json::to_value(scene)?,
            planar: None,
            left: Camera::new(&state.left, s("left")),
            right: Camera::new(&state.right, s("right")),
            fixation_px: PixelPair { left: solution.fixation_px_left, right: solution.fixation_px_right },
            fixation_sigma_px: Some(PixelPair {
                left: a.fixation_sigmas.left_px,
                right: a.fixation_sigmas.right_px,
            }),
            invariant_lines: solution.invariant_lines,
            axes: Some(axes),
            aligned_encoders: solution.aligned_encoders,
            aligned_sigma_deg: a.sigmas,
            verge_axes_measured: solution.verge_axes_measured,
            predicted_elev_err_r_deg: solution.predicted_elev_err_r_deg,
            roll_left_deg: solution.roll_left_deg,
            roll_right_deg: solution.roll_right_deg,
            undetermined: Vec::new(),
            report: Some(serde_json::to_value(&calib.report)?),
            lens: lens_json(calib),
            model_fit: fit.map(serde_json::to_value).transpose()?,
            warnings,
            files,
            seconds,
        })
    }

    /// `align --json` on the planar route (a planar or far scene): the session's planar
    /// alignment `p`, the warnings, the files written and the wall time (seconds).
    pub fn planar(
        p: &PlanarSessionAlignment,
        warnings: Vec<String>,
        files: Vec<String>,
        seconds: f64,
    ) -> Result<Self, serde_json::Error> {
        let (cal, sol) = (&p.calibration, &p.solution);
        Ok(Self {
            schema: ALIGN,
            route: "planar",
            scene: serde_json::to_value(&cal.scene)?,
            planar: Some(serde_json::to_value(cal)?),
            left: Camera::new(&cal.left.intrinsics, |n| cal.left.sigma(n)),
            right: Camera::new(&cal.right.intrinsics, |n| cal.right.sigma(n)),
            fixation_px: PixelPair { left: sol.fixation_px_left, right: sol.fixation_px_right },
            fixation_sigma_px: None,
            invariant_lines: sol.invariant_lines,
            axes: None,
            aligned_encoders: sol.aligned_encoders,
            aligned_sigma_deg: p.sigmas,
            verge_axes_measured: sol.verge_axes_measured,
            predicted_elev_err_r_deg: sol.predicted_elev_err_r_deg,
            roll_left_deg: sol.roll_left_deg,
            roll_right_deg: sol.roll_right_deg,
            undetermined: cal.undetermined.clone(),
            report: None,
            lens: None,
            model_fit: None,
            warnings,
            files,
            seconds,
        })
    }
}

/// The head's axes of `align` (`axes` of its JSON and of `head.json`): the pan and
/// elevation axes `pan`, `elev` of the calibration `calib` (direction, the point in
/// baselines, the direction's sigma in degrees) and the vergence axes where measured, in
/// the left camera frame of the first view.
pub fn head_axes_json(calib: &RigCalibration, pan: &Line, elev: &Line, verge: &VergeAxes) -> Value {
    let axis = |line: &Line, index: usize| {
        let c = &calib.bundle.covariance;
        let dir_sigma = match (c.sigma(&format!("axis{index}.dir0")), c.sigma(&format!("axis{index}.dir1"))) {
            (Some(a), Some(b)) => Some(a.hypot(b).to_degrees()),
            _ => None,
        };
        json!({
            "direction": [line.direction.x, line.direction.y, line.direction.z],
            "point_baselines": [line.point.x, line.point.y, line.point.z],
            "direction_sigma_deg": dir_sigma,
        })
    };
    let verge_json = |line: &Option<Line>| match line {
        Some(l) => {
            json!({"direction": [l.direction.x, l.direction.y, l.direction.z], "point_baselines": [l.point.x, l.point.y, l.point.z]})
        }
        None => Value::Null,
    };
    json!({
        "frame": "left camera of the first view; points in baselines",
        "pan": axis(pan, 0),
        "elevation": axis(elev, 1),
        "verge_left": verge_json(&verge.left),
        "verge_right": verge_json(&verge.right),
    })
}

/// The file `alignment.json` of `align --out`, on either route (its format lives in
/// `headalign-io`).
pub use crate::alignment_file::AlignmentFile;

/// A calibrated camera of `calibrate`, pixels.
#[derive(Debug, Clone, Serialize)]
pub struct CalibratedCamera {
    pub fx: f64,
    pub fy: f64,
    pub skew: f64,
    pub cx: f64,
    pub cy: f64,
    /// 1-sigma per parameter (`fx fy skew cx cy`); null when not estimated.
    pub sigma: CalibratedSigma,
}

/// The sigmas of a calibrated camera, pixels.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct CalibratedSigma {
    pub fx: Option<f64>,
    pub fy: Option<f64>,
    pub skew: Option<f64>,
    pub cx: Option<f64>,
    pub cy: Option<f64>,
}

impl CalibratedCamera {
    /// A camera from its intrinsics and a sigma per parameter name.
    pub fn new(k: &Intrinsics, sigma: impl Fn(&str) -> Option<f64>) -> Self {
        Self {
            fx: k.fx,
            fy: k.fy,
            skew: k.skew,
            cx: k.cx,
            cy: k.cy,
            sigma: CalibratedSigma {
                fx: sigma("fx"),
                fy: sigma("fy"),
                skew: sigma("skew"),
                cx: sigma("cx"),
                cy: sigma("cy"),
            },
        }
    }
}

/// The constraints `calibrate` imposed.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Constraints {
    pub zero_skew: bool,
    pub square_pixels: bool,
    pub fix_principal_point: bool,
}

/// `calibrate --json` (and `calibrate_report.json`), on either route.
#[derive(Debug, Clone, Serialize)]
pub struct CalibrateReport {
    pub schema: &'static str,
    /// `self-calibration` or `known intrinsics (no self-calibration)`.
    pub route: &'static str,
    /// The views given (of the rig used).
    pub views: Vec<String>,
    /// Views of other rigs left out, `"NAME: reason"`.
    pub skipped: Vec<String>,
    pub left: CalibratedCamera,
    pub right: CalibratedCamera,
    /// The rig (`rotation_deg`, `rotation_axis`, `translation_direction`).
    pub right_from_left: Value,
    /// Each camera's lens (`estimated`, `model`, `left`, `right`, `sigma`).
    pub distortion: Value,
    pub constraints: Constraints,
    /// `m` or `baselines`.
    pub translation_unit: &'static str,
    /// Self-calibration: the adjustment's report; null on the known-intrinsics route.
    pub report: Option<Value>,
    /// Self-calibration: the corner counts tried and the one kept; null otherwise.
    pub density: Option<Value>,
    /// Known intrinsics: the fundamental matrix of the undistorted views; null otherwise.
    pub fundamental_undistorted: Option<[[f64; 3]; 3]>,
    /// Known intrinsics: stereo matches, inliers and their RMS (px); null otherwise.
    pub stereo_matches: Option<usize>,
    pub stereo_inliers: Option<usize>,
    pub stereo_rms_px: Option<f64>,
    pub files: Vec<String>,
    pub seconds: f64,
}

impl CalibrateReport {
    /// The known-intrinsics route (`calibrate --intrinsics`): the views, the given lenses,
    /// the rig from the undistorted views' stereo matches, and the wall time (seconds).
    pub fn known_intrinsics(
        views: Vec<String>,
        lenses: &[LensModel; 2],
        rig: &KnownIntrinsicsRig,
        constraints: Constraints,
        unit: TranslationUnit,
        seconds: f64,
    ) -> Self {
        let f = rig.fundamental.0;
        let distortion = [lenses[0].distortion, lenses[1].distortion];
        Self {
            schema: CALIBRATE,
            route: "known intrinsics (no self-calibration)",
            views,
            skipped: Vec::new(),
            left: CalibratedCamera::new(&lenses[0].k, |_| None),
            right: CalibratedCamera::new(&lenses[1].k, |_| None),
            right_from_left: rig_json(&rig.right_from_left),
            distortion: distortion_json(&distortion, false, None),
            constraints,
            translation_unit: unit_name(unit),
            report: None,
            density: None,
            fundamental_undistorted: Some(std::array::from_fn(|r| std::array::from_fn(|c| f[(r, c)]))),
            stereo_matches: Some(rig.stereo_matches),
            stereo_inliers: Some(rig.stereo_inliers),
            stereo_rms_px: Some(rig.stereo_rms_px),
            files: Vec::new(),
            seconds,
        }
    }

    /// The self-calibration route: the calibration `cal` with each camera's lens
    /// (`distortion`, `lens_estimated` or given), the corner counts tried (`density`, none
    /// for tracked points) and the wall time (seconds).
    pub fn self_calibration(
        cal: &MotionCalibration,
        distortion: &[Distortion; 2],
        lens_estimated: bool,
        constraints: Constraints,
        unit: TranslationUnit,
        density: Option<&DensityReport>,
        seconds: f64,
    ) -> Result<Self, serde_json::Error> {
        let st = &cal.bundle.state;
        let c = &cal.bundle.covariance;
        let sigma = |side: &'static str| move |p: &str| c.sigma(&format!("{side}.{p}"));
        Ok(Self {
            schema: CALIBRATE,
            route: "self-calibration",
            views: cal.report.views.clone(),
            skipped: Vec::new(),
            left: CalibratedCamera::new(&st.left, sigma("left")),
            right: CalibratedCamera::new(&st.right, sigma("right")),
            right_from_left: rig_json(&st.right_from_left),
            distortion: distortion_json(distortion, lens_estimated, Some(c)),
            constraints,
            translation_unit: unit_name(unit),
            report: Some(serde_json::to_value(&cal.report)?),
            density: density.map(serde_json::to_value).transpose()?,
            fundamental_undistorted: None,
            stereo_matches: None,
            stereo_inliers: None,
            stereo_rms_px: None,
            files: Vec::new(),
            seconds,
        })
    }
}

impl Estimate {
    /// The general route's estimate.
    pub fn general(outcome: &VergeTiltOutcome) -> Self {
        let cal = &outcome.calibration;
        let (st, cov) = (&cal.bundle.state, &cal.bundle.covariance);
        let sigma = |side: &'static str| move |p: &str| cov.sigma(&format!("{side}.{p}"));
        Self::of(
            Camera::new(&st.left, sigma("left")),
            Camera::new(&st.right, sigma("right")),
            &outcome.solution,
            outcome.sigmas,
            outcome.final_encoders,
            lens_json(cal),
        )
    }

    /// The planar route's estimate (no lens: the planar route estimates pinhole cameras).
    pub fn planar(out: &PlanarOutcome) -> Self {
        let cal = &out.calibration;
        Self::of(
            Camera::new(&cal.left.intrinsics, |p| cal.left.sigma(p)),
            Camera::new(&cal.right.intrinsics, |p| cal.right.sigma(p)),
            &out.solution,
            out.sigmas,
            out.final_encoders,
            None,
        )
    }

    fn of(
        left: Camera,
        right: Camera,
        s: &AlignmentSolution,
        sigmas: AlignmentSigmas,
        final_encoders: Encoders,
        lens: Option<Value>,
    ) -> Self {
        Self {
            left,
            right,
            aligned_encoders: s.aligned_encoders,
            aligned_sigma_deg: sigmas,
            fixation_px: PixelPair { left: s.fixation_px_left, right: s.fixation_px_right },
            final_encoders,
            predicted_elev_err_r_deg: s.predicted_elev_err_r_deg,
            roll_left_deg: s.roll_left_deg,
            roll_right_deg: s.roll_right_deg,
            lens,
        }
    }
}

impl Procedure {
    /// The members of a verge/tilt run on either route, in `mode` (`points` or `images`),
    /// with its view names, whether it chose its rotations and the command's wall time
    /// (seconds); no robot stages yet (only `verge-tilt` in `stages`;
    /// [`Procedure::with_robot`] adds them), no image members, session or files.
    pub fn new(
        mode: &'static str,
        route: &RouteOutcome,
        views: Vec<String>,
        auto_rotation: bool,
        total_s: f64,
    ) -> Result<Self, serde_json::Error> {
        let (estimate, scene, planar, report, checks, check_failure, verdict, o) = match route {
            RouteOutcome::General(o, scene) => (
                Estimate::general(o),
                serde_json::to_value(scene)?,
                None,
                Some(serde_json::to_value(&o.calibration.report)?),
                serde_json::to_value(&o.checks)?,
                None,
                &o.verdict,
                (o.rotation_deg, o.diagonal_rotation_deg, o.verge_rotation_deg, o.estimation_seconds),
            ),
            RouteOutcome::Planar(p) => (
                Estimate::planar(p),
                serde_json::to_value(&p.calibration.scene)?,
                Some(serde_json::to_value(&p.calibration)?),
                None,
                serde_json::to_value(&p.checks)?,
                p.check_failure.clone(),
                &p.verdict,
                (p.rotation_deg, p.diagonal_rotation_deg, p.verge_rotation_deg, p.estimation_seconds),
            ),
        };
        let planar_route = matches!(route, RouteOutcome::Planar(_));
        Ok(Self {
            mode,
            route: if planar_route { "planar" } else { "general" },
            scene,
            planar,
            estimate,
            report,
            checks,
            check_failure,
            verdict: verdict_json(verdict)?,
            model_fit: None,
            warnings: Vec::new(),
            rotations: Rotations {
                auto: auto_rotation,
                rotation_deg: o.0,
                diagonal_rotation_deg: o.1,
                verge_rotation_deg: o.2,
            },
            timings: Timings { estimation_s: o.3, total_s },
            views,
            images: None,
            stages: vec![crate::session::STAGE_VERGE_TILT.to_string()],
            robot_stages: planar_route.then_some(ROBOT_STAGES_SKIPPED),
            robot: RobotOutcomes::default(),
            robot_tracking: None,
            session: None,
            files: Vec::new(),
        })
    }

    /// The stages asked for and, when they ran (the general route), their outcomes.
    pub fn with_robot(mut self, stages: &[String], robot: Option<&RobotOutcomes>) -> Self {
        self.stages = stages.to_vec();
        if let Some(r) = robot {
            self.robot = r.clone();
        }
        self
    }
}

/// The `verdict` member: the verdict and, when it failed, its one-line `failure`.
pub fn verdict_json(verdict: &CheckVerdict) -> Result<Value, serde_json::Error> {
    let mut v = serde_json::to_value(verdict)?;
    if let Some(m) = v.as_object_mut() {
        m.insert("failure".into(), json!(verdict.failure_line()));
    }
    Ok(v)
}

/// The estimated lenses of a calibration with their sigmas (`None` for a pinhole
/// estimate): `model` (ROS names, left and right), the coefficients in each model's
/// order (`k1 k2 p1 p2 k3` or `k1..k4`), `sigma` per estimated coefficient (`left.k1`
/// ...), and how they were estimated (`estimation`: first estimate, the auto choice).
pub fn lens_json(calib: &RigCalibration) -> Option<Value> {
    let lens = calib.report.lens.as_ref()?;
    let st = &calib.bundle.state;
    let cov = &calib.bundle.covariance;
    let mut sigma = serde_json::Map::new();
    for (side, d) in [("left", &st.left_distortion), ("right", &st.right_distortion)] {
        for name in d.kind.coefficient_names() {
            let key = format!("{side}.{name}");
            if let Some(s) = cov.sigma(&key) {
                sigma.insert(key, json!(s));
            }
        }
    }
    Some(json!({
        "model": [st.left_distortion.kind.ros_name(), st.right_distortion.kind.ros_name()],
        "left": st.left_distortion.coefficients(),
        "right": st.right_distortion.coefficients(),
        "sigma": sigma,
        "estimation": serde_json::to_value(lens).ok(),
    }))
}

/// The robot stages' entry of a planar-route report: why they did not run.
pub const ROBOT_STAGES_SKIPPED: &str = "skipped: they need the 3D reconstruction a plane does not give";
/// The report's name of a translation unit.
pub fn unit_name(unit: TranslationUnit) -> &'static str {
    match unit {
        TranslationUnit::Metres => "m",
        TranslationUnit::Baselines => "baselines",
    }
}

/// The `distortion` member: each camera's model and coefficients (in the model's order,
/// OpenCV's `D`), and the sigma of every estimated coefficient (none without a covariance `c`).
pub fn distortion_json(distortion: &[Distortion; 2], estimated: bool, c: Option<&Covariance>) -> Value {
    let mut sigma = serde_json::Map::new();
    for (side, d) in ["left", "right"].iter().zip(distortion) {
        for name in d.kind.coefficient_names() {
            let key = format!("{side}.{name}");
            if let Some(s) = c.and_then(|c| c.sigma(&key)) {
                sigma.insert(key, json!(s));
            }
        }
    }
    json!({
        "estimated": estimated,
        "model": [distortion[0].kind.ros_name(), distortion[1].kind.ros_name()],
        "left": distortion[0].coefficients(), "right": distortion[1].coefficients(),
        "sigma": sigma,
    })
}

pub fn rig_json(m: &Isometry3<f64>) -> Value {
    let (axis, angle) = m.rotation.axis_angle().map_or(([0.0; 3], 0.0), |(a, t)| ([a.x, a.y, a.z], t));
    let t = m.translation.vector;
    json!({"rotation_deg": angle.to_degrees(), "rotation_axis": axis, "translation_direction": [t.x / t.norm(), t.y / t.norm(), t.z / t.norm()]})
}

pub fn k_json(k: &Intrinsics) -> Value {
    json!({"fx": k.fx, "fy": k.fy, "skew": k.skew, "cx": k.cx, "cy": k.cy})
}

/// The file `alignment.json` of `align --out` on `route`: the reference and aligned
/// readings with their sigmas, the rolls and what the scene leaves `undetermined`.
pub fn alignment_file(
    route: &'static str,
    reference: Encoders,
    solution: &AlignmentSolution,
    sigmas: AlignmentSigmas,
    undetermined: &[String],
) -> AlignmentFile {
    AlignmentFile::new(route, reference, solution, sigmas, undetermined)
}

/// The members of an image-mode run on either route ([`Procedure`]): the
/// estimate, checks and timings, and the front end's report (`images`); no robot stages
/// ([`with_robot`] adds them).
pub fn procedure_report(
    run: &ImageRun,
    route: &RouteOutcome,
    total_s: f64,
) -> Result<Procedure, serde_json::Error> {
    let views = run.run.views.iter().map(|v| v.name.clone()).collect();
    let mut p = Procedure::new("images", route, views, run.auto_rotation, total_s)?;
    let (verdict, fit) = image_mode::judgement(run, route);
    p.verdict = verdict_json(&verdict)?;
    if let Some(fit) = &fit {
        p.warnings.extend(fit.warnings.iter().cloned());
        p.model_fit = Some(serde_json::to_value(fit)?);
    }
    p.images = Some(json!({
        "verging": serde_json::to_value(&run.verging)?,
        "tracking": serde_json::to_value(&run.tracking)?,
        "views": run.run.views.iter().map(|v| v.name.clone()).collect::<Vec<_>>(),
    }));
    Ok(p)
}

/// The stages of `plan` and, when they ran, their outcomes and the front end's report per
/// robot-stage capture (`robot_tracking`).
pub fn with_robot(
    p: Procedure,
    plan: &RobotPlan,
    robot: Option<&RobotRun>,
) -> Result<Procedure, serde_json::Error> {
    let mut p = p.with_robot(&plan.stages, robot.map(|r| &r.outcomes));
    if let Some(r) = robot {
        p.robot_tracking = Some(serde_json::to_value(&r.tracking)?);
    }
    Ok(p)
}
