//! Point-mode sessions (`headalign demo --session DIR` without `--images`): the verge/tilt
//! stage's captures are recorded as they happen (`NN-name/view.json` with the tracked
//! points in its `capture` member, no images; `events.jsonl`), the views so far as an
//! observation session (`observations.json`, format `headalign-observations/1`, readable
//! by `align --observations`) and the demo's JSON as `report.json`. The robot stages
//! that follow are recorded too ([`robot_stages`]: their captures in folders named by
//! stage, drives and steering as events, the stage plan in `session.json` `stages`), and
//! `replay` re-runs the verge/tilt stage and then those stages.

use std::path::PathBuf;

use anyhow::{Context, Result};
use headalign::procedure::{
    AutoRotation, RouteOutcome, VergeTiltOptions, VergeTiltOutcome, VergeTiltRun, capture_plan,
    resolve_rotation,
};
use headalign_io::observations::session_to_json;
use headalign_io::session::{
    RecordingHead, STAGE_ROTATION_PROBE, STAGE_VERGE_TILT, SessionInfo, SessionWriter,
};
use headalign_platform::{StereoHead, Vehicle};

use headalign::robot::stages::{RobotOutcomes, RobotPlan, StageHooks, run_robot_stages};

/// The procedure name in `session.json` for point mode.
pub const PROCEDURE: &str = "verge-tilt-points";

/// Run the verge/tilt procedure on `head`, recording into `session` if given (the view
/// folders are named by [`capture_plan`]; with the auto mode its probes are recorded first,
/// in stage `rotation-probe`). On failure the session keeps the views and the message says
/// where. A planar or far scene takes the planar route ([`VergeTiltRun::run_detecting`]).
pub fn verge_tilt<H: StereoHead>(
    run: &mut VergeTiltRun,
    head: &mut H,
    options: &VergeTiltOptions,
    session: Option<(PathBuf, SessionInfo)>,
) -> Result<(RouteOutcome, Option<SessionWriter>)> {
    let Some((dir, info)) = session else {
        return Ok((run.run_detecting(head, options).context("verge/tilt procedure")?, None));
    };
    let writer = SessionWriter::create(&dir, &info).context("session")?;
    let mut rec = RecordingHead::new(head, writer);
    let outcome = (|| {
        rec.set_stage(STAGE_ROTATION_PROBE, Vec::new(), "probe");
        let options = resolve_rotation(&mut rec, options).context("choosing the rotations")?;
        // Not recorded: a replay re-runs `run`, which makes no such read.
        let plan = capture_plan(&rec.inner().read_encoders()?, &options);
        rec.set_stage(STAGE_VERGE_TILT, plan, "check");
        run.run_detecting(&mut rec, &options).context("verge/tilt procedure")
    })();
    let writer = rec.into_writer();
    let observations = dir.join("observations.json");
    let saved = session_to_json(&run.views)
        .map_err(anyhow::Error::from)
        .and_then(|text| std::fs::write(&observations, text).map_err(anyhow::Error::from))
        .with_context(|| format!("cannot write {}", observations.display()));
    match outcome.and_then(|o| saved.map(|()| o)) {
        Ok(o) => Ok((o, Some(writer))),
        Err(e) => Err(crate::images::failed_in_session(&writer, e)),
    }
}

/// The session description of a point-mode run.
pub fn session_info(
    options: &VergeTiltOptions,
    image_size: [u32; 2],
    head: serde_json::Value,
) -> SessionInfo {
    let mut info = SessionInfo::new(PROCEDURE, options.rotation_deg, options.estimation.seed, image_size);
    info.auto_rotation = options.auto_rotation.is_some();
    info.head = head;
    info
}

/// The options a point-mode session was recorded with.
pub fn options(info: &SessionInfo) -> VergeTiltOptions {
    VergeTiltOptions {
        rotation_deg: info.rotation_deg,
        verge_rotation_deg: info.rotation_deg,
        auto_rotation: info.auto_rotation.then(AutoRotation::default),
        estimation: headalign::verge_tilt::EstimationOptions {
            seed: info.estimation_seed,
            ..headalign::verge_tilt::EstimationOptions::default()
        },
        ..VergeTiltOptions::default()
    }
}

/// The robot stages of `plan` on `robot` after the verge/tilt stage, recorded into
/// `writer` when the run has a session (each stage's captures under its name, drives and
/// steering as events); a failure writes `report.json` and says where the session is.
pub fn robot_stages<R: StereoHead + Vehicle>(
    robot: &mut R,
    plan: &RobotPlan,
    outcome: &VergeTiltOutcome,
    writer: Option<SessionWriter>,
) -> Result<(RobotOutcomes, Option<SessionWriter>)> {
    let (calib, verge) = (&outcome.calibration, &outcome.verge_axes);
    let perturbations = outcome.axis_perturbations();
    let axes = Some(&perturbations);
    let mut warn = crate::progress::warn;
    let Some(writer) = writer else {
        let hooks = StageHooks { stage: &mut |_, _| {}, warn: &mut warn };
        return Ok((run_robot_stages(robot, plan, calib, verge, axes, hooks)?, None));
    };
    let mut rec = RecordingHead::new(robot, writer);
    let hooks = StageHooks {
        stage: &mut |h: &mut RecordingHead<'_, R>, stage| h.set_stage(stage, Vec::new(), stage),
        warn: &mut warn,
    };
    let result = run_robot_stages(&mut rec, plan, calib, verge, axes, hooks).map_err(anyhow::Error::from);
    let writer = rec.into_writer();
    match result {
        Ok(r) => Ok((r, Some(writer))),
        Err(e) => Err(crate::images::failed_in_session(&writer, e)),
    }
}
