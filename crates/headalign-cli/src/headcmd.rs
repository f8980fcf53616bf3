//! `headalign run --head-cmd CMD`: verging, then the verge/tilt procedure on images, on a
//! head behind a driver process that speaks the JSON-lines head protocol
//! (`docs/head-protocol.md`; [`headalign_io::process_head::ProcessHead`]), then the robot
//! stages of `--stages` (pan, steering, ...: [`headalign::robot::stages`]) when the driver has a base.
//! Every capture is recorded to the session folder before it is processed (always: a real
//! head's captures cannot be made again); `report.json` gets the results. A timeout, a
//! driver that exits or a malformed answer stops the run with one line naming the request
//! and the session folder, which keeps every view captured so far. Stages that drive
//! need a driver with a base: without one the run stops before any request but `hello`.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Args;
use headalign::robot::PanOptions;
use headalign_io::process_head::{ProcessHead, ProcessHeadOptions};
use headalign_io::runs;
use headalign_platform::StereoHead;
use serde_json::json;

use crate::{images, replay, stages};
use headalign::robot::stages::RobotPlan;
use headalign_io::report::schema;

/// Arguments of `headalign run`.
#[derive(Args)]
pub struct RunArgs {
    /// The driver's command line, e.g. "my_head_driver --port /dev/ttyUSB0" (words split
    /// on white space; quotes group words).
    #[arg(long)]
    pub head_cmd: String,
    /// Longest wait for one answer of the driver, seconds.
    #[arg(long, default_value_t = 30.0)]
    pub head_timeout: f64,
    /// Record the session here (default `./headalign-sessions/<UTC time>`).
    #[arg(long)]
    pub session: Option<PathBuf>,
    /// Rotation of the procedure's moves, degrees.
    #[arg(long, default_value_t = 3.0)]
    pub rotation: f64,
    /// Let the procedure choose its elevation/pan rotations as far as the scene stays in
    /// view; `--rotation` is then only the vergence move.
    // `AutoRotation::default`: up to 10 deg each way, plus pan and elevation together.
    #[arg(long)]
    pub auto_rotation: bool,
    /// Stages to run in order, comma separated: verge-tilt (first), then pan, steering,
    /// pan-fixate, one-motion (these drive: the driver needs a base).
    // Names: `headalign::robot::stages::STAGES`; `demo`'s default is verge-tilt,pan,steering,pan.
    #[arg(long, default_value = "verge-tilt")]
    pub stages: String,
    /// Forward drive of the pan, pan-fixate and one-motion stages, metres.
    // `PanOptions::default().drive_m`, the demo's `Scenario::drive_m`.
    #[arg(long)]
    pub drive: Option<f64>,
    /// Drive per steering setting of the steering stage, metres (default 0.2).
    // `headalign::robot::stages::IMAGE_STEER_DRIVE_M`.
    #[arg(long)]
    pub steer_drive: Option<f64>,
    /// Steering settings of the steering stage relative to the start reading, degrees,
    /// comma separated (default -20,20,30,-30).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub steer_settings: Option<Vec<f64>>,
    /// Stereo baseline in metres, to give the wheelbase in metres (default 0.25).
    // `SteeringOptions::default().baseline_m`, the simulated head's.
    #[arg(long)]
    pub baseline_m: Option<f64>,
    /// Print one JSON object instead of the summary.
    #[arg(long)]
    pub json: bool,
    /// The lens model estimated (recorded in the session).
    #[command(flatten)]
    pub lens: images::LensArgs,
    /// Only check --calibration: capture a few views beside the current position, return
    /// the head there, and print the check (as `headalign check`; nothing recorded).
    #[arg(long, requires = "calibration")]
    pub check_only: bool,
    /// The calibration --check-only checks (any format `headalign check` reads).
    #[arg(long, requires = "check_only")]
    pub calibration: Option<PathBuf>,
}

/// `--check-only`: the live check ([`headalign::check::live`]) of `--calibration`.
fn check_only(args: &RunArgs, head: &mut ProcessHead, calibration: &std::path::Path) -> Result<()> {
    let mut given = headalign_io::import::read_calibration(calibration)?;
    if given.image_size == [0, 0] {
        given.image_size = head.image_size();
    } else if given.image_size != head.image_size() {
        bail!(
            "{} is a calibration of {:?} images, the head's are {:?}",
            calibration.display(),
            given.image_size,
            head.image_size()
        );
    }
    let options = headalign::check::live::LiveCheckOptions::default();
    let live = headalign::check::live::check_live_head(head, &given, &options).context("live check")?;
    if args.json {
        say!("{}", serde_json::to_string_pretty(&live)?);
    } else {
        crate::check::print_text(&live.report, &[]);
        let returned = if live.returned { "returned to its start" } else { "NOT at its start" };
        say!("head '{}': {} views, {returned} ({:?})", args.head_cmd, options.moves_deg.len(), live.end);
    }
    if !live.returned {
        bail!("the head did not return to its start readings {:?} (now {:?})", live.start, live.end);
    }
    Ok(())
}

/// The stage plan of `run`'s flags; fails when the verge/tilt stage is not first.
fn plan(args: &RunArgs) -> Result<RobotPlan> {
    let stages = stages::parse_stages(&args.stages)?;
    if stages.first().map(String::as_str) != Some("verge-tilt") {
        bail!("--stages must start with verge-tilt: every robot stage uses its calibration");
    }
    stages::refuse_unused_flags(
        &stages,
        &[
            ("--drive", args.drive.is_some()),
            ("--steer-drive", args.steer_drive.is_some()),
            ("--steer-settings", args.steer_settings.is_some()),
        ],
    )?;
    let drive_m = args.drive.unwrap_or(PanOptions::default().drive_m);
    let baseline_m = args.baseline_m.unwrap_or(headalign::robot::SteeringOptions::default().baseline_m);
    for (name, v) in
        [("--drive", Some(drive_m)), ("--steer-drive", args.steer_drive), ("--baseline-m", Some(baseline_m))]
    {
        if let Some(v) = v
            && !(v.is_finite() && v > 0.0)
        {
            bail!("{name} must be a positive number of metres, got {v}");
        }
    }
    let settings = args.steer_settings.clone();
    Ok(RobotPlan::images(stages, drive_m, args.steer_drive, settings, baseline_m))
}

/// Run `headalign run`.
pub fn run(args: &RunArgs) -> Result<()> {
    let t0 = Instant::now();
    args.lens.validate()?;
    if !(args.head_timeout.is_finite() && args.head_timeout > 0.0 && args.head_timeout < 1e6) {
        bail!("--head-timeout must be a positive number of seconds, got {}", args.head_timeout);
    }
    if !(args.rotation.is_finite() && args.rotation > 0.0 && args.rotation < 90.0) {
        bail!("--rotation must be in (0, 90) degrees, got {}", args.rotation);
    }
    let plan = plan(args)?;
    let options = ProcessHeadOptions { timeout: Duration::from_secs_f64(args.head_timeout) };
    let mut head = ProcessHead::spawn(&args.head_cmd, options).context("head")?;
    if let Some(calibration) = args.calibration.as_deref().filter(|_| args.check_only) {
        return check_only(args, &mut head, calibration);
    }
    if plan.drives() && !head.has_base() {
        let driving: Vec<&str> =
            plan.stages.iter().map(String::as_str).filter(|s| *s != "verge-tilt").collect();
        let name = if head.name().is_empty() { args.head_cmd.as_str() } else { head.name() };
        bail!(
            "stage(s) {} drive the robot, but the head driver '{name}' has no base (its 'hello' answer lists no \"base\" capability): run --stages verge-tilt, or use a driver of a head on a base",
            driving.join(", ")
        );
    }
    let target = match &args.session {
        Some(d) => images::SessionTarget::Dir(d.clone()),
        None => images::SessionTarget::Default,
    };
    let description = json!({"kind": "process", "command": head.command(), "name": head.name()});
    let session = target.resolve().map(|d| {
        let mut info = images::session_info(
            args.rotation,
            args.auto_rotation,
            head.image_size(),
            description,
            &args.lens,
        );
        if plan.drives() {
            info.procedure = headalign_io::runs::PROCEDURE_ROBOT.to_string();
            info.stages = serde_json::to_value(&plan).ok();
        }
        (d, info)
    });
    let seed = images::Estimation {
        seed: headalign::verge_tilt::EstimationOptions::default().seed,
        lens: args.lens,
    };
    let mut head = crate::progress::Narrated::new(&mut head, "run");
    let options = seed.image_mode(args.rotation, args.auto_rotation);
    let (run, _, v) = if plan.drives() {
        runs::recorded_robot(
            &mut head,
            session,
            &options,
            &plan,
            &mut |_, run, route, robot| {
                let p = schema::procedure_report(run, route, t0.elapsed().as_secs_f64())?;
                Ok(serde_json::to_value(schema::RunReport::new(schema::with_robot(p, &plan, robot)?))?)
            },
            &mut crate::progress::warn,
        )?
    } else {
        runs::recorded(&mut head, session, &options, &mut |_, run, route| {
            let p = schema::procedure_report(run, route, t0.elapsed().as_secs_f64())?;
            Ok(serde_json::to_value(schema::RunReport::new(schema::with_robot(p, &plan, None)?))?)
        })?
    };
    drop(head); // the spinner goes before the results print
    if args.json {
        say!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        say!("head '{}' ({} views)", args.head_cmd, run.run.views.len());
        replay::print_summary(&v);
        if let Some(line) = stages::summary_line(&v) {
            say!("{line}");
        }
    }
    images::fail_on_verdict(&v)
}
