//! Image mode on the command line (`demo --images`, `run --head-cmd`, `replay`): the
//! library's image-mode procedure and robot stages ([`headalign::image_mode`]) run
//! through a recording head, so that every captured view is recorded to a session folder
//! as it is captured (format: the `headalign_io::session` module documentation), with the
//! results in `report.json`, the annotated images of the paper's Figure 6 and a
//! `report.html` with the numbers; and the lens flags ([`LensArgs`]).
//!
//! [`procedure`] maps the flags to the library's options and its stages to the session's
//! stage names: the demo runs it on the simulator, `run --head-cmd` on a driver, `replay`
//! on a recorded session; the same code on the same images gives the same numbers. A
//! planar or far scene takes the planar route: no robot stages, no `figure6.png` (it
//! draws the general route's calibration), the report's `route`, `scene`, `planar` and
//! `checks` members (the same members on both routes: [`headalign_io::report::schema::Procedure`]) and
//! a `report.html` of the planar route's numbers
//! ([`headalign_io::report::html::write_session_report`]).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use headalign::calibrate::{LensChoice, lens_terms};
use headalign::image_mode::{
    self, ImageModeOptions, ImageRun, ImageStagesOptions, RobotRun, Stage, tracked_estimation,
};
use headalign::procedure::{RouteOutcome, VergeTiltOutcome};
use headalign::robot::stages::{RobotPlan, StageHooks};
use headalign::verge_tilt::EstimationOptions;
use headalign_geometry::distortion::DistortionTerms;
use headalign_io::session::{
    RecordingHead, STAGE_ROTATION_PROBE, STAGE_VERGE_TILT, STAGE_VERGING, SessionInfo, SessionWriter,
    default_session_dir,
};
use headalign_platform::{Encoders, ImagingHead, Vehicle};
use headalign_sim::{Scenario, SimulatedRobot};
use serde_json::{Value, json};

use headalign_io::report::{html as report_html, schema};

/// The procedure name in `session.json` for image mode.
pub const PROCEDURE: &str = "verge-tilt-images";

/// The procedure name in `session.json` for image mode followed by robot stages (the
/// stages and their settings in `session.json`'s `stages`).
pub const PROCEDURE_ROBOT: &str = "robot-images";

/// `--lens` and `--lens-terms` of the image procedures (`demo --images`, `run`, `align`):
/// the lens model the estimation frees in both cameras (`EstimationOptions::lens`); `None`
/// where not given.
#[derive(clap::Args, Debug, Clone, Copy, Default)]
pub struct LensArgs {
    /// Lens model estimated for both cameras: `pinhole`, `radtan`, `equidistant` or `auto`
    /// (model and terms chosen by BIC, reported; the default).
    // `demo --images` defaults to auto only when the scenario's renderer has a lens.
    #[arg(long, value_parser = crate::flags::parse_lens)]
    pub lens: Option<LensChoice>,
    /// Lens coefficients estimated: `radial` (k1 k2), `4` or `5` (as `calibrate --lens-terms`).
    #[arg(long, value_parser = crate::flags::parse_terms)]
    pub lens_terms: Option<DistortionTerms>,
}

impl LensArgs {
    /// The pinhole, given (observation files and point sessions).
    pub fn pinhole() -> Self {
        Self { lens: Some(LensChoice::Pinhole), lens_terms: None }
    }

    /// The model estimated: `--lens`, or `auto`.
    pub fn choice(&self) -> LensChoice {
        self.lens.unwrap_or(LensChoice::Auto)
    }

    /// These flags over `under` (each flag not given takes `under`'s).
    pub fn over(self, under: Self) -> Self {
        Self { lens: self.lens.or(under.lens), lens_terms: self.lens_terms.or(under.lens_terms) }
    }

    /// An error when lens terms are asked of the pinhole (nothing would be estimated: the
    /// flag would be ignored).
    pub fn validate(&self) -> Result<()> {
        crate::flags::check_lens_terms(self.choice(), self.lens_terms)
    }

    /// The lens a session recorded (`session.json`'s `lens`, `lens_terms`; the pinhole when
    /// absent); an unknown name is an error naming it.
    pub fn of_session(info: &SessionInfo) -> Result<Self> {
        let lens = match &info.lens {
            None => LensChoice::Pinhole,
            Some(name) => LensChoice::parse(name)
                .with_context(|| format!("session.json: unknown lens model '{name}'"))?,
        };
        Ok(Self { lens: Some(lens), lens_terms: info.lens_terms })
    }

    /// Record this lens in a session description (nothing for the pinhole).
    pub fn record(&self, info: &mut SessionInfo) {
        if self.choice() != LensChoice::Pinhole {
            info.lens = Some(self.choice().name().to_string());
            info.lens_terms = self.lens_terms;
        }
    }

    /// The estimation options with this lens (`auto` without `--lens-terms` chooses the
    /// terms too: [`lens_terms`]).
    pub fn apply(&self, estimation: EstimationOptions) -> EstimationOptions {
        let lens = self.choice();
        EstimationOptions { lens, lens_terms: lens_terms(lens, self.lens_terms), ..estimation }
    }
}

/// The estimation choices of an image procedure: the seed (recorded: a replay reproduces
/// the run) and the lens.
#[derive(Debug, Clone, Copy, Default)]
pub struct Estimation {
    /// Seed of the estimation's random choices.
    pub seed: u64,
    /// The lens model.
    pub lens: LensArgs,
}

/// Where sessions go when the user names none: `./headalign-sessions/<UTC time>`.
pub const DEFAULT_SESSION_BASE: &str = "headalign-sessions";

/// Where to record: a named folder, the default location, or nowhere.
#[derive(Debug, Clone)]
pub enum SessionTarget {
    /// This folder (must not hold a session yet).
    Dir(PathBuf),
    /// `./headalign-sessions/<UTC time>`.
    Default,
    /// No recording (simulated runs only).
    None,
}

impl SessionTarget {
    /// The folder to record into, if any.
    pub fn resolve(&self) -> Option<PathBuf> {
        match self {
            SessionTarget::Dir(d) => Some(d.clone()),
            SessionTarget::Default => Some(default_session_dir(Path::new(DEFAULT_SESSION_BASE))),
            SessionTarget::None => None,
        }
    }
}

/// Called before each stage with the stage's name, its planned captures `(name, target)`
/// and the name of unplanned captures.
pub type OnStage<'a, H> = dyn FnMut(&mut H, &str, Vec<(String, Encoders)>, &str) + 'a;

/// The library's image-mode procedure ([`image_mode::run`]) with the estimation choices
/// of the command line; `on_stage` gets each stage's name in the session format and the
/// name of its unplanned captures (verging's, `probe`, `check`).
pub fn procedure<H: ImagingHead>(
    head: &mut H,
    rotation_deg: f64,
    auto_rotation: bool,
    estimation: Estimation,
    on_stage: &mut OnStage<'_, H>,
) -> (ImageRun, Result<RouteOutcome>) {
    let options = ImageModeOptions {
        rotation_deg,
        auto_rotation,
        // The session records the seed: a replay reproduces this run bit for bit (and
        // `align --images`, which uses the default seed, too when the run did).
        estimation: estimation.lens.apply(tracked_estimation(estimation.seed)),
        ..ImageModeOptions::default()
    };
    let (run, outcome) = image_mode::run(head, &options, &mut |h, stage, plan| {
        let (name, other) = match stage {
            Stage::Verging => (STAGE_VERGING, STAGE_VERGING),
            Stage::RotationProbe => (STAGE_ROTATION_PROBE, "probe"),
            Stage::VergeTilt => (STAGE_VERGE_TILT, "check"),
        };
        on_stage(h, name, plan, other);
    });
    (run, outcome.map_err(anyhow::Error::from))
}

/// Run [`procedure`] on `head`, recording into `session` (if any): `report.json` holds
/// `report(outcome)` or the failure, `figure6.png` and `aligned.png` the annotated images.
/// A failure's message ends with where the session is.
pub fn recorded<H: ImagingHead>(
    head: &mut H,
    session: Option<(PathBuf, SessionInfo)>,
    rotation_deg: f64,
    auto_rotation: bool,
    estimation: Estimation,
    report: &mut dyn FnMut(&mut H, &ImageRun, &RouteOutcome) -> Result<Value>,
) -> Result<(ImageRun, RouteOutcome, Value)> {
    let Some((dir, info)) = session else {
        let (run, outcome) = procedure(head, rotation_deg, auto_rotation, estimation, &mut |_, _, _, _| {});
        let outcome = outcome?;
        let json = report(head, &run, &outcome)?;
        return Ok((run, outcome, json));
    };
    let writer = SessionWriter::create(&dir, &info).context("session")?;
    let mut rec = RecordingHead::new(head, writer);
    let (run, outcome) =
        procedure(&mut rec, rotation_deg, auto_rotation, estimation, &mut |h, stage, plan, other| {
            h.set_stage(stage, plan, other)
        });
    let writer = rec.into_writer();
    let result = outcome.and_then(|o| {
        let json = report(head, &run, &o)?;
        Ok((o, json))
    });
    finish(&writer, run, result)
}

/// The library's robot stages on images ([`image_mode::robot_stages`], default options)
/// with warnings printed as they arise; `on_stage(head, name)` before each stage.
pub fn robot_stages<H: ImagingHead + Vehicle>(
    head: &mut H,
    plan: &RobotPlan,
    outcome: &VergeTiltOutcome,
    on_stage: &mut dyn FnMut(&mut H, &str),
) -> Result<RobotRun> {
    let mut warn = crate::progress::warn;
    let hooks = StageHooks { stage: on_stage, warn: &mut warn };
    Ok(image_mode::robot_stages(head, plan, outcome, &ImageStagesOptions::default(), hooks)?)
}

/// The report of [`recorded_robot`]: the JSON of the run from the head, the captures,
/// the route's outcome and the robot stages' results (`None` on the planar route, which
/// runs none).
pub type RobotReport<'a, H> =
    dyn FnMut(&mut H, &ImageRun, &RouteOutcome, Option<&RobotRun>) -> Result<Value> + 'a;

/// [`recorded`] followed by the robot stages of `plan` on the same (recording) head, for
/// a head that is also a vehicle; `report` also sees the robot stages' results.
pub fn recorded_robot<H: ImagingHead + Vehicle>(
    head: &mut H,
    session: Option<(PathBuf, SessionInfo)>,
    rotation_deg: f64,
    auto_rotation: bool,
    estimation: Estimation,
    plan: &RobotPlan,
    report: &mut RobotReport<'_, H>,
) -> Result<(ImageRun, RouteOutcome, Value)> {
    let Some((dir, info)) = session else {
        let (run, outcome) = procedure(head, rotation_deg, auto_rotation, estimation, &mut |_, _, _, _| {});
        let outcome = outcome?;
        let robot = match &outcome {
            RouteOutcome::General(o, _) => Some(robot_stages(head, plan, o, &mut |_, _| {})?),
            RouteOutcome::Planar(_) => None,
        };
        let json = report(head, &run, &outcome, robot.as_ref())?;
        return Ok((run, outcome, json));
    };
    let writer = SessionWriter::create(&dir, &info).context("session")?;
    let mut rec = RecordingHead::new(head, writer);
    let (run, outcome) =
        procedure(&mut rec, rotation_deg, auto_rotation, estimation, &mut |h, stage, plan, other| {
            h.set_stage(stage, plan, other)
        });
    let robot = outcome.and_then(|o| {
        let r = match &o {
            RouteOutcome::General(g, _) => {
                Some(robot_stages(&mut rec, plan, g, &mut |h, stage| h.set_stage(stage, Vec::new(), stage))?)
            }
            RouteOutcome::Planar(_) => None,
        };
        Ok((o, r))
    });
    let writer = rec.into_writer();
    let result = robot.and_then(|(o, r)| {
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
    result: Result<(RouteOutcome, Value)>,
) -> Result<(ImageRun, RouteOutcome, Value)> {
    let result = result.and_then(|(route, mut json)| {
        if let Some(m) = json.as_object_mut() {
            m.insert("session".into(), json!(writer.dir().display().to_string()));
        }
        if let Some(files) = report_html::write_session_report(writer.dir(), &run, &route, &json)?
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
            writer.write_report(&json).context("session")?;
            Ok((run, o, json))
        }
        Err(e) => Err(failed_in_session(writer, e)),
    }
}

/// A failure of a recorded run: `report.json` says so (best effort: the error itself is
/// what the user must see) and the error, its cause first, ends with where the captured
/// views are kept.
pub fn failed_in_session(writer: &SessionWriter, e: anyhow::Error) -> anyhow::Error {
    let cause = one_line(&e);
    let _ = writer.write_report(&json!({"status": "failed", "error": cause}));
    anyhow::anyhow!(
        "{cause} (session with {} view(s) kept in {}; report.json has the whole error)",
        writer.views(),
        writer.dir().display()
    )
}

/// An error and its causes on one line, joined by ": ", leaving out a cause whose text
/// the message before it already ends with (errors that print their source).
pub fn one_line(e: &anyhow::Error) -> String {
    let mut parts: Vec<String> = Vec::new();
    for c in e.chain() {
        let text = c.to_string();
        if parts.last().is_some_and(|p| p.ends_with(&text)) {
            continue;
        }
        parts.push(text);
    }
    parts.join(": ")
}

/// The session description of an image-mode run.
pub fn session_info(
    rotation_deg: f64,
    auto_rotation: bool,
    image_size: [u32; 2],
    head: Value,
    lens: &LensArgs,
) -> SessionInfo {
    let mut info = SessionInfo::new(PROCEDURE, rotation_deg, EstimationOptions::default().seed, image_size);
    info.auto_rotation = auto_rotation;
    info.head = head;
    lens.record(&mut info);
    info
}

/// One line on the estimated lenses of an `estimate` JSON member (`None` without a lens):
/// each camera's coefficients with their sigmas, and the `auto` choice.
pub fn lens_line(estimate: &Value) -> Option<String> {
    let lens = estimate.get("lens")?;
    let model = lens["estimation"]["model"].as_str().unwrap_or("?");
    let side = |name: &str| -> String {
        let names = match lens["model"][usize::from(name == "right")].as_str() {
            Some("equidistant") => ["k1", "k2", "k3", "k4", ""],
            _ => ["k1", "k2", "p1", "p2", "k3"],
        };
        let values = lens[name].as_array().cloned().unwrap_or_default();
        let parts: Vec<String> = names
            .iter()
            .zip(&values)
            .filter_map(|(n, v)| {
                let sigma = lens["sigma"][format!("{name}.{n}")].as_f64()?;
                Some(format!("{n} {:.4} +- {sigma:.4}", v.as_f64().unwrap_or(f64::NAN)))
            })
            .collect();
        format!("{name} {}", parts.join(", "))
    };
    let terms: Vec<&str> = lens["estimation"]["terms"]
        .as_array()
        .map_or_else(Vec::new, |t| t.iter().filter_map(Value::as_str).collect());
    let mut line = format!(
        "lens {}: {}; {}",
        [model].iter().chain(&terms).copied().collect::<Vec<_>>().join(" "),
        side("left"),
        side("right")
    );
    let selection = &lens["estimation"]["selection"];
    if let Some(reason) = selection["reason"].as_str() {
        line += &format!(" (auto: {reason})");
    }
    for f in selection["failed"].as_array().into_iter().flatten() {
        let (name, why) = (f["candidate"].as_str().unwrap_or("?"), f["reason"].as_str().unwrap_or(""));
        line += &format!("; lens candidate {name} left out: {why}");
    }
    Some(line)
}

/// The run's JSON `v` judged: `Ok` when its `verdict` did not fail, otherwise an error of
/// one line (the failure, where the report is). Called after the results are printed, so
/// that a failed check still shows them and exits non-zero.
pub fn fail_on_verdict(v: &Value) -> Result<()> {
    let Some(failure) = v["verdict"]["failure"].as_str() else { return Ok(()) };
    match v["session"].as_str() {
        Some(dir) => bail!("{failure} (report: {dir}/report.json)"),
        None => bail!("{failure}"),
    }
}

/// The lines every command prints about a report's judgement: each of its `warnings`
/// (`warning: ...`) and the verdict of the check after the move.
pub fn judgement_lines(v: &Value) -> Vec<String> {
    let mut lines: Vec<String> = v["warnings"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(Value::as_str)
        .map(|w| format!("warning: {w}"))
        .collect();
    let verdict = &v["verdict"];
    let f = |x: &Value| x.as_f64().unwrap_or(f64::NAN);
    match verdict["status"].as_str() {
        Some("passed") => {
            let worst = verdict["components"].as_array().into_iter().flatten().max_by(|a, b| {
                (f(&a["measured_deg"]).abs() / f(&a["bound_deg"]))
                    .total_cmp(&(f(&b["measured_deg"]).abs() / f(&b["bound_deg"])))
            });
            lines.push(format!(
                "check after the move ({}): passed, every error within {} reported sigmas{}",
                verdict["check"].as_str().unwrap_or("?"),
                f(&verdict["sigmas_allowed"]),
                worst.map_or(String::new(), |c| format!(
                    " (largest: {} {:+.3} deg, bound {:.3})",
                    c["name"].as_str().unwrap_or("?"),
                    f(&c["measured_deg"]),
                    f(&c["bound_deg"])
                ))
            ));
        }
        Some("failed") => lines.push(format!("FAILED: {}", verdict["failure"].as_str().unwrap_or("?"))),
        Some(other) => lines.push(format!("check after the move: {other}")),
        None => {}
    }
    lines
}

/// Run verging, the verge/tilt procedure and then the robot stages of `plan` on rendered
/// images of the simulated robot (the demo), recording to `session`; the JSON has the
/// estimate against the simulator's truth, and with robot stages their results, the
/// front end's report per robot capture and the pan and steering errors (`errors`
/// `pan_err_deg`, `steer_err_deg`, as in point mode).
pub fn run(
    scenario: &Scenario,
    auto_rotation: bool,
    session: &SessionTarget,
    plan: &RobotPlan,
    lens: &LensArgs,
) -> Result<Value> {
    let t0 = Instant::now();
    let mut robot = SimulatedRobot::new(scenario.clone()).map_err(|e| anyhow::anyhow!("simulator: {e}"))?;
    let start = robot.head().encoders();
    let before = robot.head().alignment_errors(&start);
    let pan_before = robot.pan_err_deg(&start);
    let steer_before = robot.steer_err_deg(robot.steering_encoder_deg());
    let description = json!({"kind": "simulator", "scenario": serde_json::to_value(scenario)?});
    let session = session.resolve().map(|dir| {
        let mut info =
            session_info(scenario.rotation_deg, auto_rotation, scenario.image_size, description, lens);
        if plan.drives() {
            info.procedure = PROCEDURE_ROBOT.to_string();
            info.stages = serde_json::to_value(plan).ok();
        }
        (dir, info)
    });
    let estimation = Estimation { seed: EstimationOptions::default().seed, lens: *lens };
    let (_, _, json) = recorded_robot(
        &mut robot,
        session,
        scenario.rotation_deg,
        auto_rotation,
        estimation,
        plan,
        &mut |robot, run, route, robot_run| {
            let total = t0.elapsed().as_secs_f64();
            let procedure =
                schema::with_robot(schema::procedure_report(run, route, total)?, plan, robot_run)?;
            let before = crate::truth::before(&before, pan_before, steer_before);
            let stages = robot_run.map(|r| &r.outcomes);
            let report = crate::truth::demo_images_report(robot, scenario, route, procedure, stages, before)?;
            Ok(serde_json::to_value(&report)?)
        },
    )?;
    Ok(json)
}
