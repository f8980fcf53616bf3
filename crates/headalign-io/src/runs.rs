//! Recorded runs: the library's procedures run through a [`RecordingHead`], so that every
//! captured view is written to a session folder as it is captured (format: the
//! [`crate::session`] module documentation), with the results in `report.json` and, in
//! image mode, the annotated images and `report.html` ([`crate::report::html`]).
//!
//! - Image mode ([`headalign::image_mode`]): [`image_procedure`] maps the procedure's
//!   stages to the session's stage names; [`recorded`] runs it into a session,
//!   [`recorded_robot`] follows it with the robot stages of a plan. `demo --images` runs
//!   them on the simulator, `run --head-cmd` on a driver, `replay` on a recorded session;
//!   the same code on the same images gives the same numbers.
//! - Point mode: [`verge_tilt_points`] records the verge/tilt stage's captures (the
//!   tracked points, no images) and `observations.json`; [`robot_stages_points`] the robot
//!   stages that follow.
//!
//! - Calibration sessions: [`write_calibration_session`] writes rendered views for
//!   `calibrate` (`simulate --images`).
//!
//! A failure keeps the session: `report.json` says `{"status": "failed", "error": ...}`
//! and the error ([`RunError::InSession`]), its cause first, ends with where the captured
//! views are kept. Nothing is estimated here: the procedures are the library's.

use std::path::PathBuf;

use headalign::AlignError;
use headalign::image_mode::{self, ImageModeOptions, ImageRun, ImageStagesOptions, RobotRun, Stage};
use headalign::procedure::{
    RouteOutcome, VergeTiltOptions, VergeTiltOutcome, VergeTiltRun, capture_plan, resolve_rotation,
};
use headalign::robot::stages::{RobotOutcomes, RobotPlan, StageHooks, run_robot_stages};
use headalign_platform::{Encoders, ImagingHead, StereoHead, StereoImages, Vehicle};
use serde_json::{Value, json};
use thiserror::Error;

use crate::observations::session_to_json;
use crate::report::ReportError;
use crate::session::{
    RecordingHead, STAGE_ROTATION_PROBE, STAGE_VERGE_TILT, STAGE_VERGING, SessionInfo, SessionWriter,
    ViewLabel,
};

/// The procedure name in `session.json` for image mode.
pub const PROCEDURE_IMAGES: &str = "verge-tilt-images";

/// The procedure name in `session.json` for image mode followed by robot stages (the
/// stages and their settings in `session.json`'s `stages`).
pub const PROCEDURE_ROBOT: &str = "robot-images";

/// The procedure name in `session.json` for point mode.
pub const PROCEDURE_POINTS: &str = "verge-tilt-points";

/// The procedure name in `session.json` of a calibration session (`simulate --images`):
/// views for `calibrate`; `replay` runs `calibrate` on it with the constraints in
/// `session.json`'s `head.calibrate`.
pub const PROCEDURE_CALIBRATE: &str = "calibrate-images";

/// The stage name of the views of a calibration session.
pub const STAGE_CALIBRATE: &str = "calibrate";

/// A recorded run that failed.
#[derive(Debug, Error)]
pub enum RunError {
    /// A procedure's error.
    #[error(transparent)]
    Align(#[from] AlignError),
    /// A head's error.
    #[error(transparent)]
    Platform(#[from] headalign_platform::PlatformError),
    /// A step failed; `what` names it (`session`, `verge/tilt procedure`).
    #[error("{what}")]
    Step {
        /// The step.
        what: &'static str,
        /// Why.
        #[source]
        source: AlignError,
    },
    /// A file that cannot be written.
    #[error("cannot write {}", path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// The report of the run.
    #[error(transparent)]
    Report(#[from] ReportError),
    /// A failure of a recorded run: its cause on one line, and where the views are kept.
    #[error("{cause} (session with {views} view(s) kept in {}; report.json has the whole error)", dir.display())]
    InSession {
        /// The failure and its causes, on one line ([`one_line`]).
        cause: String,
        /// Views captured.
        views: usize,
        /// The session folder.
        dir: PathBuf,
    },
}

/// `source` as the step `what` failed.
fn step(what: &'static str) -> impl FnOnce(AlignError) -> RunError {
    move |source| RunError::Step { what, source }
}

/// A session to record into: its folder and description.
pub type Session = Option<(PathBuf, SessionInfo)>;

/// Called before each stage with the stage's name, its planned captures `(name, target)`
/// and the name of unplanned captures.
pub type OnStage<'a, H> = dyn FnMut(&mut H, &str, Vec<(String, Encoders)>, &str) + 'a;

/// The library's image-mode procedure ([`image_mode::run`]) with `options`; `on_stage`
/// gets each stage's name in the session format and the name of its unplanned captures
/// (verging's, `probe`, `check`).
pub fn image_procedure<H: ImagingHead>(
    head: &mut H,
    options: &ImageModeOptions,
    on_stage: &mut OnStage<'_, H>,
) -> (ImageRun, Result<RouteOutcome, AlignError>) {
    image_mode::run(head, options, &mut |h, stage, plan| {
        let (name, other) = match stage {
            Stage::Verging => (STAGE_VERGING, STAGE_VERGING),
            Stage::RotationProbe => (STAGE_ROTATION_PROBE, "probe"),
            Stage::VergeTilt => (STAGE_VERGE_TILT, "check"),
        };
        on_stage(h, name, plan, other);
    })
}

/// The report of a recorded image-mode run: the JSON of the run from the head, the
/// captures and the route's outcome.
pub type Report<'a, H> = dyn FnMut(&mut H, &ImageRun, &RouteOutcome) -> Result<Value, ReportError> + 'a;

/// Run [`image_procedure`] on `head`, recording into `session` (if any): `report.json`
/// holds `report(outcome)` or the failure, `figure6.png` and `aligned.png` the annotated
/// images. A failure's message ends with where the session is.
pub fn recorded<H: ImagingHead>(
    head: &mut H,
    session: Session,
    options: &ImageModeOptions,
    report: &mut Report<'_, H>,
) -> Result<(ImageRun, RouteOutcome, Value), RunError> {
    let Some((dir, info)) = session else {
        let (run, outcome) = image_procedure(head, options, &mut |_, _, _, _| {});
        let outcome = outcome?;
        let json = report(head, &run, &outcome)?;
        return Ok((run, outcome, json));
    };
    let writer = SessionWriter::create(&dir, &info).map_err(step("session"))?;
    let mut rec = RecordingHead::new(head, writer);
    let (run, outcome) =
        image_procedure(&mut rec, options, &mut |h, stage, plan, other| h.set_stage(stage, plan, other));
    let writer = rec.into_writer();
    let result = outcome.map_err(RunError::from).and_then(|o| {
        let json = report(head, &run, &o)?;
        Ok((o, json))
    });
    finish(&writer, run, result)
}

/// The library's robot stages on images ([`image_mode::robot_stages`], default options);
/// `on_stage(head, name)` before each stage, `warn` with each warning as it arises.
pub fn robot_stages<H: ImagingHead + Vehicle>(
    head: &mut H,
    plan: &RobotPlan,
    outcome: &VergeTiltOutcome,
    on_stage: &mut dyn FnMut(&mut H, &str),
    warn: &mut dyn FnMut(&str),
) -> Result<RobotRun, AlignError> {
    let hooks = StageHooks { stage: on_stage, warn };
    image_mode::robot_stages(head, plan, outcome, &ImageStagesOptions::default(), hooks)
}

/// The report of [`recorded_robot`]: the JSON of the run from the head, the captures,
/// the route's outcome and the robot stages' results (`None` on the planar route, which
/// runs none).
pub type RobotReport<'a, H> =
    dyn FnMut(&mut H, &ImageRun, &RouteOutcome, Option<&RobotRun>) -> Result<Value, ReportError> + 'a;

/// [`recorded`] followed by the robot stages of `plan` on the same (recording) head, for
/// a head that is also a vehicle; `report` also sees the robot stages' results, `warn`
/// gets their warnings.
pub fn recorded_robot<H: ImagingHead + Vehicle>(
    head: &mut H,
    session: Session,
    options: &ImageModeOptions,
    plan: &RobotPlan,
    report: &mut RobotReport<'_, H>,
    warn: &mut dyn FnMut(&str),
) -> Result<(ImageRun, RouteOutcome, Value), RunError> {
    let Some((dir, info)) = session else {
        let (run, outcome) = image_procedure(head, options, &mut |_, _, _, _| {});
        let outcome = outcome?;
        let robot = match &outcome {
            RouteOutcome::General(o, _) => Some(robot_stages(head, plan, o, &mut |_, _| {}, warn)?),
            RouteOutcome::Planar(_) => None,
        };
        let json = report(head, &run, &outcome, robot.as_ref())?;
        return Ok((run, outcome, json));
    };
    let writer = SessionWriter::create(&dir, &info).map_err(step("session"))?;
    let mut rec = RecordingHead::new(head, writer);
    let (run, outcome) =
        image_procedure(&mut rec, options, &mut |h, stage, plan, other| h.set_stage(stage, plan, other));
    let robot = outcome.and_then(|o| {
        let r = match &o {
            RouteOutcome::General(g, _) => Some(robot_stages(
                &mut rec,
                plan,
                g,
                &mut |h, stage| h.set_stage(stage, Vec::new(), stage),
                warn,
            )?),
            RouteOutcome::Planar(_) => None,
        };
        Ok((o, r))
    });
    let writer = rec.into_writer();
    let result = robot.map_err(RunError::from).and_then(|(o, r)| {
        let json = report(head, &run, &o, r.as_ref())?;
        Ok((o, json))
    });
    finish(&writer, run, result)
}

/// The end of a recorded run: on success the session path in the JSON, the annotated
/// images, `report.html` and `report.json`; on failure `report.json` says so and the
/// error names where the session is.
fn finish(
    writer: &SessionWriter,
    run: ImageRun,
    result: Result<(RouteOutcome, Value), RunError>,
) -> Result<(ImageRun, RouteOutcome, Value), RunError> {
    let result = result.and_then(|(route, mut json)| {
        if let Some(m) = json.as_object_mut() {
            m.insert("session".into(), json!(writer.dir().display().to_string()));
        }
        if let Some(files) = crate::report::html::write_session_report(writer.dir(), &run, &route, &json)?
            && let Some(m) = json.as_object_mut()
        {
            m.insert(
                "files".into(),
                json!(files.iter().map(|p| p.display().to_string()).collect::<Vec<_>>()),
            );
        }
        Ok((route, json))
    });
    match result {
        Ok((o, json)) => {
            writer.write_report(&json).map_err(step("session"))?;
            Ok((run, o, json))
        }
        Err(e) => Err(failed_in_session(writer, &e)),
    }
}

/// A failure of a recorded run: `report.json` says so (best effort: the error itself is
/// what the user must see) and the error, its cause first, ends with where the captured
/// views are kept.
pub fn failed_in_session(writer: &SessionWriter, e: &(dyn std::error::Error + 'static)) -> RunError {
    let cause = one_line(e);
    let _ = writer.write_report(&json!({"status": "failed", "error": cause}));
    RunError::InSession { cause, views: writer.views(), dir: writer.dir().to_path_buf() }
}

/// An error and its causes on one line, joined by ": ", leaving out a cause whose text
/// the message before it already ends with (errors that print their source).
pub fn one_line(e: &(dyn std::error::Error + 'static)) -> String {
    let mut parts: Vec<String> = Vec::new();
    let mut next = Some(e);
    while let Some(c) = next {
        let text = c.to_string();
        if !parts.last().is_some_and(|p| p.ends_with(&text)) {
            parts.push(text);
        }
        next = c.source();
    }
    parts.join(": ")
}

/// Write named stereo views as a calibration session ([`PROCEDURE_CALIBRATE`], stage
/// [`STAGE_CALIBRATE`]) with the one session writer (`session.json`, `NN-name/left.png`,
/// `right.png`, `view.json`, `events.jsonl`); refuses a folder that already holds a session.
pub fn write_calibration_session(
    dir: &std::path::Path,
    views: &[(String, StereoImages)],
    info: &SessionInfo,
) -> Result<SessionWriter, AlignError> {
    let mut writer = SessionWriter::create(dir, info)?;
    for (name, pair) in views {
        let label = ViewLabel { name, stage: STAGE_CALIBRATE, commanded: None, vehicle: None };
        writer.write_view(&label, pair.encoders, Some(pair), None)?;
    }
    Ok(writer)
}

/// Run the verge/tilt procedure on `head` in point mode, recording into `session` if
/// given (the view folders are named by [`capture_plan`]; with the auto mode its probes
/// are recorded first, in stage `rotation-probe`), and the views as `observations.json`.
/// On failure the session keeps the views and the message says where. A planar or far
/// scene takes the planar route ([`VergeTiltRun::run_detecting`]).
pub fn verge_tilt_points<H: StereoHead>(
    run: &mut VergeTiltRun,
    head: &mut H,
    options: &VergeTiltOptions,
    session: Session,
) -> Result<(RouteOutcome, Option<SessionWriter>), RunError> {
    let Some((dir, info)) = session else {
        let route = run.run_detecting(head, options).map_err(step("verge/tilt procedure"))?;
        return Ok((route, None));
    };
    let writer = SessionWriter::create(&dir, &info).map_err(step("session"))?;
    let mut rec = RecordingHead::new(head, writer);
    let outcome = (|| {
        rec.set_stage(STAGE_ROTATION_PROBE, Vec::new(), "probe");
        let options = resolve_rotation(&mut rec, options).map_err(step("choosing the rotations"))?;
        // Not recorded: a replay re-runs `run`, which makes no such read.
        let plan = capture_plan(&rec.inner().read_encoders()?, &options);
        rec.set_stage(STAGE_VERGE_TILT, plan, "check");
        run.run_detecting(&mut rec, &options).map_err(step("verge/tilt procedure"))
    })();
    let writer = rec.into_writer();
    let observations = dir.join("observations.json");
    let saved = session_to_json(&run.views)
        .map_err(|e| -> Box<dyn std::error::Error + Send + Sync> { Box::new(e) })
        .and_then(|text| std::fs::write(&observations, text).map_err(Into::into))
        .map_err(|source| RunError::Write { path: observations.clone(), source });
    match outcome.and_then(|o| saved.map(|()| o)) {
        Ok(o) => Ok((o, Some(writer))),
        Err(e) => Err(failed_in_session(&writer, &e)),
    }
}

/// The robot stages of `plan` on `robot` after a point-mode verge/tilt stage, recorded
/// into `writer` when the run has a session (each stage's captures under its name, drives
/// and steering as events); `warn` gets their warnings. A failure writes `report.json` and
/// says where the session is.
pub fn robot_stages_points<R: StereoHead + Vehicle>(
    robot: &mut R,
    plan: &RobotPlan,
    outcome: &VergeTiltOutcome,
    writer: Option<SessionWriter>,
    warn: &mut dyn FnMut(&str),
) -> Result<(RobotOutcomes, Option<SessionWriter>), RunError> {
    let (calib, verge) = (&outcome.calibration, &outcome.verge_axes);
    let perturbations = outcome.axis_perturbations();
    let axes = Some(&perturbations);
    let Some(writer) = writer else {
        let hooks = StageHooks { stage: &mut |_, _| {}, warn };
        return Ok((run_robot_stages(robot, plan, calib, verge, axes, hooks)?, None));
    };
    let mut rec = RecordingHead::new(robot, writer);
    let hooks = StageHooks {
        stage: &mut |h: &mut RecordingHead<'_, R>, stage| h.set_stage(stage, Vec::new(), stage),
        warn,
    };
    let result = run_robot_stages(&mut rec, plan, calib, verge, axes, hooks);
    let writer = rec.into_writer();
    match result {
        Ok(r) => Ok((r, Some(writer))),
        Err(e) => Err(failed_in_session(&writer, &e)),
    }
}
