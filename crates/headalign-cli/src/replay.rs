//! `headalign replay DIR`: re-run a recorded session offline. The session's head is played
//! back ([`headalign_io::session::ReplayHead`]: recorded readings, recorded images, moves
//! checked against the recorded ones) under the same procedure that recorded it, so the
//! result is the recorded run's, bit for bit. A recording that stopped early (its run
//! failed) replays up to where it stopped and fails there, naming the event.
//!
//! A recording of a head run (a ROS 2 bag with joint states) has no events: its still
//! views are played back as a head ([`headalign_io::recordings::PlaybackHead`]) under the
//! image procedure with the rotation given on the command line, which `run` used too.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use headalign_io::runs;
use headalign_io::session::{ReplayHead, read_session_info};
use serde_json::Value;

use crate::{calibrate, images, points};
use headalign::procedure::{RouteOutcome, VergeTiltRun};
use headalign_io::report::schema;

/// Default of `--rotation` (a recording's), degrees: `run`'s.
const DEFAULT_ROTATION_DEG: f64 = 3.0;

/// Default of `--move-tolerance` (a recording's), degrees.
const DEFAULT_MOVE_TOLERANCE_DEG: f64 = 0.1;

/// Arguments of `headalign replay`.
#[derive(Args)]
pub struct ReplayArgs {
    /// The session folder (as `demo --images` or `run --head-cmd` recorded it), or a
    /// ROS 2 bag of a head run.
    pub dir: PathBuf,
    /// Print one JSON object instead of the summary.
    #[arg(long)]
    pub json: bool,
    /// A recording: the rotation of the recorded run's moves, degrees (as `run --rotation`).
    #[arg(long, default_value_t = DEFAULT_ROTATION_DEG)]
    pub rotation: f64,
    /// A recording: the recorded run chose its rotations (as `run --auto-rotation`).
    #[arg(long)]
    pub auto_rotation: bool,
    /// A recording: how far a recorded still view may be from a move's target, degrees.
    #[arg(long, default_value_t = DEFAULT_MOVE_TOLERANCE_DEG)]
    pub move_tolerance: f64,
    /// How a recording is read (bags, EuRoC folders).
    #[command(flatten)]
    pub recording: crate::recording::RecordingArgs,
    /// Lens model estimated: `pinhole`, `radtan`, `equidistant` or `auto` (default: the
    /// session's own, auto for a recording).
    #[arg(long, value_parser = crate::flags::parse_lens)]
    pub lens: Option<headalign::calibrate::LensChoice>,
    /// Lens coefficients estimated: `radial`, `4` or `5` (default: the session's own).
    #[arg(long, value_parser = crate::flags::parse_terms)]
    pub lens_terms: Option<headalign_geometry::distortion::DistortionTerms>,
}

impl ReplayArgs {
    /// The lens of the replay: the flags over the recorded one (`recorded`).
    fn lens(&self, recorded: images::LensArgs) -> Result<images::LensArgs> {
        let lens = images::LensArgs { lens: self.lens, lens_terms: self.lens_terms }.over(recorded);
        lens.validate()?;
        Ok(lens)
    }
}

/// `replay RECORDING`: the image procedure on the recording's still views.
fn replay_recording(args: &ReplayArgs) -> Result<()> {
    let t0 = Instant::now();
    if !(args.rotation.is_finite() && args.rotation > 0.0 && args.rotation < 90.0) {
        bail!("--rotation must be in (0, 90) degrees, got {}", args.rotation);
    }
    let mut head = crate::recording::playback_head(&args.dir, &args.recording, args.move_tolerance)?;
    let seed = images::Estimation {
        seed: headalign::verge_tilt::EstimationOptions::default().seed,
        lens: args.lens(images::LensArgs::default())?,
    };
    let (run, outcome) = runs::image_procedure(
        &mut head,
        &seed.image_mode(args.rotation, args.auto_rotation),
        &mut |_, _, _, _| {},
    );
    let outcome = outcome.with_context(|| format!("replay of '{}'", args.dir.display()))?;
    let report = schema::ReplayReport {
        schema: schema::REPLAY,
        procedure: schema::procedure_report(&run, &outcome, t0.elapsed().as_secs_f64())?,
        replayed: args.dir.display().to_string(),
        unplayed_events: None,
        still_views: Some(head.views().len()),
        still_views_used: Some(head.position() + 1),
    };
    let v = serde_json::to_value(&report)?;
    if args.json {
        say!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        say!("replayed {} ({} views)", args.dir.display(), run.run.views.len());
        print_summary(&v);
    }
    images::fail_on_verdict(&v)
}

/// Run `headalign replay`.
pub fn run(args: &ReplayArgs) -> Result<()> {
    if headalign_io::recordings::detect(&args.dir).is_some() {
        return replay_recording(args);
    }
    args.recording.only_for_recordings(&args.dir, "a recorded session", false)?;
    crate::flags::refuse(
        &[
            ("--rotation", args.rotation != DEFAULT_ROTATION_DEG),
            ("--auto-rotation", args.auto_rotation),
            ("--move-tolerance", args.move_tolerance != DEFAULT_MOVE_TOLERANCE_DEG),
        ],
        &format!(
            "a recording of a head run; the session '{}' replays its own recorded moves",
            args.dir.display()
        ),
    )?;
    let t0 = Instant::now();
    let info = read_session_info(&args.dir)?;
    let mut head = ReplayHead::open(&args.dir)?;
    let context = || format!("replay of '{}'", args.dir.display());
    let estimation = images::Estimation {
        seed: info.estimation_seed,
        lens: args.lens(images::LensArgs::of_session(&info)?)?,
    };
    // The verge/tilt part of an image session, as recorded (seed and rotation choice).
    let verge_tilt = |head: &mut ReplayHead| {
        let options = estimation.image_mode(info.rotation_deg, info.auto_rotation);
        runs::image_procedure(head, &options, &mut |_, _, _, _| {})
    };
    let (p, views) = if info.procedure == runs::PROCEDURE_IMAGES {
        let (run, outcome) = verge_tilt(&mut head);
        let outcome = outcome.with_context(context)?;
        (schema::procedure_report(&run, &outcome, t0.elapsed().as_secs_f64())?, run.run.views.len())
    } else if info.procedure == runs::PROCEDURE_ROBOT {
        let plan = info.robot_plan(&args.dir)?.with_context(|| {
            format!(
                "'{}' names no stages for procedure '{}'",
                args.dir.join("session.json").display(),
                info.procedure
            )
        })?;
        let (run, outcome) = verge_tilt(&mut head);
        let outcome = outcome.with_context(context)?;
        let robot = match &outcome {
            RouteOutcome::General(o, _) => {
                let warn = &mut crate::progress::warn;
                Some(runs::robot_stages(&mut head, &plan, o, &mut |_, _| {}, warn).with_context(context)?)
            }
            RouteOutcome::Planar(_) => None,
        };
        let p = schema::procedure_report(&run, &outcome, t0.elapsed().as_secs_f64())?;
        let views = run.run.views.len() + robot.as_ref().map_or(0, |r| r.tracking.len());
        (schema::with_robot(p, &plan, robot.as_ref())?, views)
    } else if info.procedure == runs::PROCEDURE_POINTS {
        let mut run = VergeTiltRun::default();
        let route = run.run_detecting(&mut head, &points::options(&info)).with_context(context)?;
        let names = run.views.iter().map(|v| v.name.clone()).collect();
        let total = t0.elapsed().as_secs_f64();
        let mut p = schema::Procedure::new("points", &route, names, info.auto_rotation, total)?;
        // The robot stages recorded after the verge/tilt stage (sessions that have them).
        if let (RouteOutcome::General(outcome, _), Some(plan)) = (&route, info.robot_plan(&args.dir)?) {
            let (robot, _) =
                runs::robot_stages_points(&mut head, &plan, outcome, None, &mut crate::progress::warn)
                    .with_context(context)?;
            p = p.with_robot(&plan.stages, Some(&robot));
            p.timings.total_s = t0.elapsed().as_secs_f64();
        }
        (p, run.views.len())
    } else if info.procedure == runs::PROCEDURE_CALIBRATE {
        // A calibration session (`simulate --images`): no head calls to play back; the
        // result is `calibrate --json` with the recorded constraints.
        let v = calibrate::replay(&args.dir, &info).with_context(context)?;
        let n = v["report"]["views"].as_array().map_or(0, Vec::len);
        if args.json {
            say!("{}", serde_json::to_string_pretty(&v)?);
        } else {
            say!("replayed {} ({n} views): calibrate {}", args.dir.display(), v["constraints"]);
            say!(
                "left fx {} fy {}, right fx {} fy {}",
                v["left"]["fx"],
                v["left"]["fy"],
                v["right"]["fx"],
                v["right"]["fy"]
            );
        }
        return Ok(());
    } else {
        bail!(
            "'{}': cannot replay procedure '{}' (this version replays '{}', '{}', '{}' and '{}')",
            args.dir.join("session.json").display(),
            info.procedure,
            runs::PROCEDURE_IMAGES,
            runs::PROCEDURE_ROBOT,
            runs::PROCEDURE_POINTS,
            runs::PROCEDURE_CALIBRATE
        );
    };
    finish_replay(args, p, &head, views)
}

/// Print a replay's result (`views` views replayed) with where it came from.
fn finish_replay(
    args: &ReplayArgs,
    procedure: schema::Procedure,
    head: &ReplayHead,
    views: usize,
) -> Result<()> {
    let report = schema::ReplayReport {
        schema: schema::REPLAY,
        procedure,
        replayed: args.dir.display().to_string(),
        unplayed_events: Some(head.remaining()),
        still_views: None,
        still_views_used: None,
    };
    let v = serde_json::to_value(&report)?;
    if args.json {
        say!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        say!("replayed {} ({views} views)", args.dir.display());
        print_summary(&v);
        if let Some(line) = crate::stages::summary_line(&v) {
            say!("{line}");
        }
    }
    images::fail_on_verdict(&v)
}

/// The human-readable summary of an image-mode run without truth (`replay`, `run`).
pub fn print_summary(v: &Value) {
    for line in crate::facing_plane::summary_lines(v) {
        say!("{line}");
    }
    let e = &v["estimate"];
    let f = |x: &Value| x.as_f64().unwrap_or(f64::NAN);
    for side in ["left", "right"] {
        say!(
            "{side:<5} fx {:.2}  fy {:.2}  cx {:.2}  cy {:.2} px",
            f(&e[side]["fx"]),
            f(&e[side]["fy"]),
            f(&e[side]["cx"]),
            f(&e[side]["cy"])
        );
    }
    if let Some(line) = images::lens_line(e) {
        say!("{line}");
    }
    let a = &e["aligned_encoders"];
    let s = &e["aligned_sigma_deg"];
    say!(
        "aligned readings: elevation {:.3} +- {:.3} deg, verge_left {:.3} +- {:.3} deg, verge_right {:.3} +- {:.3} deg",
        f(&a["elevation"]),
        f(&s["elevation_deg"]),
        f(&a["verge_left"]),
        f(&s["verge_left_deg"]),
        f(&a["verge_right"]),
        f(&s["verge_right_deg"])
    );
    say!("checks after moving: {}", v["checks"].as_array().map_or(0, Vec::len));
    for line in images::judgement_lines(v) {
        say!("{line}");
    }
    if let Some(dir) = v["session"].as_str() {
        say!("session ({}): {dir}", crate::facing_plane::session_files(v));
    }
}
