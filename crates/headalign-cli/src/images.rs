//! Image mode on the command line (`demo --images`, `run --head-cmd`, `replay`): the lens
//! flags ([`LensArgs`]), the estimation choices ([`Estimation`], mapped to the library's
//! [`ImageModeOptions`]), where a session goes ([`SessionTarget`]), the lines every
//! command prints about a run's judgement, and the demo on rendered images ([`run`]). The
//! runs themselves are recorded by [`headalign_io::runs`] (every captured view written to
//! a session folder as it is captured, `report.json`, the annotated images and
//! `report.html`); a planar or far scene takes the planar route there: no robot stages, no
//! `figure6.png`, the same report members on both routes
//! ([`headalign_io::report::schema::Procedure`]).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Result, bail};
use headalign::calibrate::{LensChoice, lens_terms};
use headalign::image_mode::{ImageModeOptions, tracked_estimation};
use headalign::robot::stages::RobotPlan;
use headalign::verge_tilt::EstimationOptions;
use headalign_geometry::distortion::DistortionTerms;
use headalign_io::report::schema;
use headalign_io::runs;
use headalign_io::session::{SessionInfo, default_session_dir};
use headalign_sim::{Scenario, SimulatedRobot};
use serde_json::{Value, json};

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
        Ok(Self { lens: Some(info.lens_choice()?), lens_terms: info.lens_terms })
    }

    /// Record this lens in a session description (nothing for the pinhole).
    pub fn record(&self, info: &mut SessionInfo) {
        info.set_lens(self.choice(), self.lens_terms);
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

impl Estimation {
    /// The library's image-mode options with these estimation choices.
    pub fn image_mode(&self, rotation_deg: f64, auto_rotation: bool) -> ImageModeOptions {
        ImageModeOptions {
            rotation_deg,
            auto_rotation,
            // The session records the seed: a replay reproduces this run bit for bit (and
            // `align --images`, which uses the default seed, too when the run did).
            estimation: self.lens.apply(tracked_estimation(self.seed)),
            ..ImageModeOptions::default()
        }
    }
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

/// The session description of an image-mode run.
pub fn session_info(
    rotation_deg: f64,
    auto_rotation: bool,
    image_size: [u32; 2],
    head: Value,
    lens: &LensArgs,
) -> SessionInfo {
    let mut info =
        SessionInfo::new(runs::PROCEDURE_IMAGES, rotation_deg, EstimationOptions::default().seed, image_size);
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
            info.procedure = runs::PROCEDURE_ROBOT.to_string();
            info.stages = serde_json::to_value(plan).ok();
        }
        (dir, info)
    });
    let estimation = Estimation { seed: EstimationOptions::default().seed, lens: *lens };
    let (_, _, json) = runs::recorded_robot(
        &mut robot,
        session,
        &estimation.image_mode(scenario.rotation_deg, auto_rotation),
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
        &mut crate::progress::warn,
    )?;
    Ok(json)
}
