//! The `headalign` command-line tool: subcommands, output formatting, nothing else (the
//! algorithms live in the `headalign` library).
//!
//! - `headalign demo`: the verge/tilt procedure on the simulated head, estimate vs truth.
//! - `headalign align --observations FILE`: the estimation on an observation session.
//! - `headalign simulate --out FILE`: record an observation session from the simulator.
//! - `headalign experiment <name>`: Monte-Carlo experiments ([`experiment`]).
//! - `headalign replay DIR`: re-run a recorded session offline ([`replay`]).
//! - `headalign run --head-cmd CMD`: the image procedure on a driver process ([`headcmd`]).
//! - `headalign calibrate DIR`: self-calibration from rig motions ([`calibrate`]).

mod calibrate;
mod experiment;
mod headcmd;
mod images;
mod points;
mod replay;
mod report_html;
mod stages;

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};
use headalign::alignment::{VergeAxes, measure_cameras, solve_alignment, verge_axes_from_motion};
use headalign::estimate::{EstimationOptions, RigCalibration, ViewRole, classify_views, estimate_rig};
use headalign::export::StereoCalibration;
use headalign::observations::{View, read_session, session_to_json};
use headalign::procedure::{AutoRotation, VergeTiltOptions, VergeTiltRun, alignment_sigmas, capture_plan};
use headalign_geometry::bootstrap::BootstrapOptions;
use headalign_geometry::camera::Intrinsics;
use headalign_geometry::so3::Line;
use headalign_platform::{Joint, StereoHead};
use headalign_sim::{Scenario, SimulatedHead, SimulatedRobot, calibration_errors};
use serde_json::{Value, json};

/// Print a line to stdout, ignoring write errors (a closed pipe, as in `headalign demo |
/// head`, is not a failure of the command and must not panic).
macro_rules! say {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stdout(), $($arg)*);
    }};
}

#[derive(Parser)]
#[command(
    name = "headalign",
    version,
    about = "Self-alignment and self-calibration of an active stereo camera head"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the verge/tilt procedure and the robot stages on the simulated robot (points or,
    /// with --images, rendered images) and compare with the truth.
    Demo(DemoArgs),
    /// Estimate calibration, axes and aligned readings from an observation session.
    Align(AlignArgs),
    /// Record an observation session (initial, elevation, pan, verge views) from the simulator.
    Simulate(SimulateArgs),
    /// Run a Monte-Carlo experiment (CSV, PNG/SVG plots, Markdown summary).
    Experiment(experiment::ExperimentArgs),
    /// Re-run a recorded session offline (same procedure, recorded images: same result).
    Replay(replay::ReplayArgs),
    /// Verge, calibrate and align a head driven through the JSON-lines protocol
    /// (docs/head-protocol.md), recording the session.
    Run(headcmd::RunArgs),
    /// Self-calibrate a stereo rig from a folder of views related by rigid motions of the
    /// whole rig (head rotations, robot drives, a hand-held rig).
    Calibrate(calibrate::CalibrateArgs),
}

#[derive(Args, Clone)]
struct ScenarioArgs {
    /// Random seed of the scenario (head errors, scene, noise).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Image noise, pixels (standard deviation per coordinate).
    #[arg(long)]
    noise: Option<f64>,
    /// Number of scene points seen by both cameras in the initial view.
    #[arg(long)]
    points: Option<usize>,
    /// Fraction of observations replaced by outliers (0 to <1).
    #[arg(long)]
    outliers: Option<f64>,
    /// Rotation of the elevation, pan and vergence moves, degrees.
    #[arg(long)]
    rotation: Option<f64>,
    /// Scenario file (TOML) overriding the defaults; flags override the file.
    #[arg(long, conflicts_with = "scene")]
    scenario: Option<PathBuf>,
    /// A scene preset instead of the default room (`Scenario::preset`): `default`,
    /// `paper` (points 0.6-1.5 m, the paper's ~1 m lab) or `robot` (6 panels about 1 m
    /// ahead), as `experiment --scene`; flags override it.
    #[arg(long)]
    scene: Option<String>,
}

impl ScenarioArgs {
    fn scenario(&self) -> Result<Scenario> {
        let mut s = match &self.scenario {
            Some(path) => {
                let text = std::fs::read_to_string(path)
                    .with_context(|| format!("cannot read {}", path.display()))?;
                Scenario::from_toml_str(&text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?
            }
            None => match &self.scene {
                Some(name) => Scenario::preset(name).map_err(|e| anyhow::anyhow!("--scene: {e}"))?,
                None => Scenario::default(),
            },
        };
        s.seed = self.seed;
        if let Some(v) = self.noise {
            s.noise_px = v;
        }
        if let Some(v) = self.points {
            s.points = v;
        }
        if let Some(v) = self.outliers {
            s.outlier_fraction = v;
        }
        if let Some(v) = self.rotation {
            s.rotation_deg = v;
        }
        s.validate()?;
        Ok(s)
    }
}

#[derive(Args)]
struct DemoArgs {
    #[command(flatten)]
    scenario: ScenarioArgs,
    /// Stages to run, in order, comma separated: verge-tilt, pan, steering, pan-fixate,
    /// one-motion (drive and tilt at once: pan and elevation; pan, steering and one-motion
    /// need the verge-tilt calibration; pan-fixate, the calibration-free
    /// route, fixates the epipole and needs a straight wheel; a stage may repeat). Default: pan first
    /// (coarse: the drive is derotated, so a bent wheel is tolerated, and it turns the
    /// head to the near scene for steering), steering, then pan again with the wheel
    /// straight (exact wherever the pan axis stands). Measured, seeds 1-20, 1 px, RMS
    /// pan / steer: this order 0.48 / 0.38 deg (0.41 / 0.20 at 60 deg pan zeros);
    /// pan,steering 0.37 / 0.38 but 1.72 deg pan with the rear axle 0.3 m behind the pan
    /// axis (0.58 with this order); steering,pan 0.53 / 0.26 (0.48 / 0.54).
    #[arg(long, default_value = "verge-tilt,pan,steering,pan")]
    stages: String,
    /// one-motion stage: level the elevation with the measured drive direction instead of
    /// the calibrated pan axis (the paper's one-motion elevation; less precise here).
    #[arg(long)]
    horizon_from_drive: bool,
    /// Largest initial pan error (pan zero offset), degrees (the paper used 20 and 60).
    #[arg(long)]
    pan_zero_max: Option<f64>,
    /// Largest steering zero offset, degrees.
    #[arg(long)]
    steer_zero_max: Option<f64>,
    /// Forward drive of the pan stage, metres.
    #[arg(long)]
    drive: Option<f64>,
    /// Drive per steering setting of the steering stage, metres (default 0.3; 0.2 with
    /// --images).
    #[arg(long)]
    steer_drive: Option<f64>,
    /// Steering settings of the steering stage relative to the start reading, degrees,
    /// comma separated (default -20,20,30).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    steer_settings: Option<Vec<f64>>,
    /// Tall textured panels about 1 m in front of the robot (the paper's near scene).
    /// Default: when the pan or steering stage runs and the scenario has none, 6; else
    /// the scenario's (0 by default: the verge/tilt-only scene is the plain room).
    #[arg(long)]
    near_panels: Option<usize>,
    /// Print one JSON object instead of the table.
    #[arg(long)]
    json: bool,
    /// Run on rendered images with the vision front end (verging, features, matching)
    /// instead of the simulator's point correspondences.
    #[arg(long)]
    images: bool,
    /// Record the session here (every captured view as it is captured, report.json;
    /// format in `headalign::session`). With --images the default is
    /// ./headalign-sessions/<UTC time> (and figure6.png, aligned.png are added); in point
    /// mode only this records (the verge/tilt stage, and observations.json). `--save` is an
    /// older name.
    #[arg(long, alias = "save", conflicts_with = "no_session")]
    session: Option<PathBuf>,
    /// With --images: record nothing (the simulated run can be repeated from its seed).
    #[arg(long, requires = "images")]
    no_session: bool,
    /// Let the verge/tilt procedure choose its elevation/pan rotations: up to 10 deg each
    /// way plus pan and elevation turned together (diagonal views), as far as the scene
    /// stays in view (probed first), and the vergence move likewise. Not the default: the
    /// README's tables are the paper's 3 deg protocol, and on images the probes cost time.
    /// Measured over 100 seeds (point mode): focal length 0.33 % RMS at 3 px (1.13 % with
    /// 10 deg single-joint views alone), alignment 0.05 deg RMS at 1 px.
    #[arg(long)]
    auto_rotation: bool,
    /// Widen the verge/tilt sigmas to a bootstrap over point tracks with this many
    /// replicates (`EstimationOptions::bootstrap`, at least 3; 30 is a sigma to about
    /// 13 %): for near scenes at a few pixels of noise, where the linearised sigmas are
    /// too small. Off by default (about one more adjustment per replicate). Point mode;
    /// for recorded images, `align --images DIR --bootstrap N`.
    #[arg(long, value_parser = parse_replicates, conflicts_with = "images")]
    bootstrap: Option<BootstrapOptions>,
}

/// Parse a bootstrap replicate count (`--bootstrap`), validated as
/// [`EstimationOptions::validate`] does.
fn parse_replicates(v: &str) -> Result<BootstrapOptions, String> {
    let replicates = v.trim().parse::<usize>().map_err(|e| format!("'{v}': {e}"))?;
    let b = BootstrapOptions { replicates, ..BootstrapOptions::default() };
    EstimationOptions { bootstrap: Some(b), ..EstimationOptions::default() }
        .validate()
        .map_err(|e| e.to_string())?;
    Ok(b)
}

#[derive(Args)]
struct AlignArgs {
    /// Observation session (JSON, format headalign-observations/1).
    #[arg(long, required_unless_present = "images", conflicts_with = "images")]
    observations: Option<PathBuf>,
    /// A recorded image session instead (folders NN-name/ with left.png, right.png and
    /// view.json, as `demo --images --session DIR` writes): the image front end finds the
    /// correspondences in its verge/tilt views (verging captures are skipped). `replay DIR`
    /// re-runs the whole recorded procedure instead.
    #[arg(long)]
    images: Option<PathBuf>,
    /// Print one JSON object instead of the table.
    #[arg(long)]
    json: bool,
    /// Write the calibration files here: calibration.json, opencv_stereo.yaml (OpenCV
    /// FileStorage), left.yaml and right.yaml (ROS camera_info), camchain.yaml (Kalibr),
    /// head.json (axes with sigmas) and alignment.json (aligned readings with sigmas), and
    /// report.html (the numbers; with --images also figure6.png, the annotated first view).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Baseline length in metres, to write the rig translation in metres (without it the
    /// translation is in baselines: self-calibration fixes no scale).
    #[arg(long)]
    baseline_m: Option<f64>,
    /// Widen the sigmas to a bootstrap over point tracks with this many replicates (as
    /// `demo --bootstrap`; off by default).
    #[arg(long, value_parser = parse_replicates)]
    bootstrap: Option<BootstrapOptions>,
}

#[derive(Args)]
struct SimulateArgs {
    #[command(flatten)]
    scenario: ScenarioArgs,
    /// Output file (an observation session), or with --images the session folder.
    #[arg(long)]
    out: PathBuf,
    /// Record rendered images (an image session folder for `calibrate`) instead of point
    /// observations.
    #[arg(long)]
    images: bool,
    /// With --images: `rotations` (initial, elevation, pan) or `general` (one general
    /// motion of the whole rig: 25 deg about the vertical with 0.3 m along it).
    #[arg(long, default_value = "rotations", requires = "images")]
    motion: String,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Demo(a) => demo(&a),
        Command::Align(a) => align(&a),
        Command::Simulate(a) => simulate(&a),
        Command::Experiment(a) => experiment::run(&a),
        Command::Replay(a) => replay::run(&a),
        Command::Run(a) => headcmd::run(&a),
        Command::Calibrate(a) => calibrate::run(&a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // One line naming the problem (the chain joined by ": ", repeated causes left
            // out; a cause that spans lines, e.g. a third-party parser's message, is folded
            // onto one).
            let msg = images::one_line(&e);
            let one_line: Vec<&str> = msg.lines().map(str::trim).filter(|l| !l.is_empty()).collect();
            eprintln!("error: {}", one_line.join(" "));
            ExitCode::FAILURE
        }
    }
}

fn k_json(k: &Intrinsics) -> Value {
    json!([[k.fx, k.skew, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]])
}

fn sigma(calib: &RigCalibration, name: &str) -> Option<f64> {
    calib.bundle.covariance.sigma(name)
}

fn camera_json(calib: &RigCalibration, side: &str, k: &Intrinsics) -> Value {
    let s = |p: &str| sigma(calib, &format!("{side}.{p}"));
    json!({
        "K": k_json(k),
        "fx": k.fx, "fy": k.fy, "skew": k.skew, "cx": k.cx, "cy": k.cy,
        "sigma": {"fx": s("fx"), "fy": s("fy"), "cx": s("cx"), "cy": s("cy")},
    })
}

fn axis_json(line: &Line, calib: &RigCalibration, index: usize) -> Value {
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
}

fn verge_json(line: &Option<Line>) -> Value {
    match line {
        Some(l) => {
            json!({"direction": [l.direction.x, l.direction.y, l.direction.z], "point_baselines": [l.point.x, l.point.y, l.point.z]})
        }
        None => Value::Null,
    }
}

fn encoders_json(e: &headalign_platform::Encoders) -> Value {
    json!({"pan": e.pan, "elevation": e.elevation, "verge_left": e.verge_left, "verge_right": e.verge_right})
}

/// The robot stages and their settings from the demo's flags.
fn robot_plan(args: &DemoArgs, scenario: &Scenario) -> Result<stages::RobotPlan> {
    Ok(stages::RobotPlan {
        stages: stages::RobotPlan::parse_stages(&args.stages)?,
        drive_m: scenario.drive_m,
        horizon_from_drive: args.horizon_from_drive,
        // On images a shorter steering drive: see `stages::IMAGE_STEER_DRIVE_M`.
        steer_drive_m: args.steer_drive.or(args.images.then_some(stages::IMAGE_STEER_DRIVE_M)),
        steer_settings_deg: args.steer_settings.clone(),
        baseline_m: scenario.baseline_m,
        // On images a wider planarity limit: see `stages::IMAGE_PLANARITY_CHI2_MAX`.
        planarity_chi2_max: args.images.then_some(stages::IMAGE_PLANARITY_CHI2_MAX),
    })
}

fn demo(args: &DemoArgs) -> Result<()> {
    let mut scenario = args.scenario.scenario()?;
    if let Some(v) = args.pan_zero_max {
        scenario.pan_zero_max_deg = v;
    }
    if let Some(v) = args.steer_zero_max {
        scenario.steer_zero_max_deg = v;
    }
    if let Some(v) = args.drive {
        scenario.drive_m = v;
    }
    let rplan = robot_plan(args, &scenario)?;
    if rplan.drives() {
        match args.near_panels {
            Some(n) => scenario.near_panels = n,
            None if scenario.near_panels == 0 => scenario.near_panels = Scenario::ROBOT_NEAR_PANELS,
            None => {}
        }
    } else if let Some(n) = args.near_panels {
        scenario.near_panels = n;
    }
    scenario.validate()?;
    if !rplan.stages.iter().any(|s| s == "verge-tilt") {
        anyhow::bail!(
            "the robot stages need the calibration of the verge-tilt stage (list it first in --stages)"
        );
    }
    if args.images {
        return demo_images(args, &scenario, &rplan);
    }
    let stages = &rplan.stages;
    let t0 = Instant::now();
    let mut robot = SimulatedRobot::new(scenario.clone()).map_err(|e| anyhow::anyhow!("simulator: {e}"))?;
    let start = robot.head().encoders();
    let before = robot.head().alignment_errors(&start);
    let pan_before = robot.pan_err_deg(&start);
    let steer_before = robot.steer_err_deg(robot.steering_encoder_deg());
    let options = VergeTiltOptions {
        rotation_deg: scenario.rotation_deg,
        verge_rotation_deg: scenario.rotation_deg,
        estimation: EstimationOptions {
            seed: scenario.seed,
            bootstrap: args.bootstrap,
            ..EstimationOptions::default()
        },
        auto_rotation: args.auto_rotation.then(AutoRotation::default),
        ..VergeTiltOptions::default()
    };
    let mut run = VergeTiltRun::default();
    let session = args.session.as_ref().map(|dir| {
        let head = json!({"kind": "simulator", "scenario": serde_json::to_value(&scenario).ok()});
        let mut info = points::session_info(&options, robot.head().image_size(), head);
        // The robot stages are recorded too (their captures after the verge/tilt views);
        // `replay` runs them from `stages`.
        info.stages = rplan.drives().then(|| serde_json::to_value(&rplan).ok()).flatten();
        (dir.clone(), info)
    });
    let (outcome, writer) = points::verge_tilt(&mut run, robot.head_mut(), &options, session)?;
    let (robot_out, writer) = points::robot_stages(&mut robot, &rplan, &outcome, writer)?;
    let stages::RobotOutcomes {
        pan: pan_outcomes,
        pan_fixate: fixate_outcomes,
        one_motion: one_motion_outcomes,
        steering: steer_outcome,
    } = robot_out;
    let total = t0.elapsed().as_secs_f64();
    let final_enc = robot.head().encoders();
    let pan_after =
        (!pan_outcomes.is_empty() || !fixate_outcomes.is_empty() || !one_motion_outcomes.is_empty())
            .then(|| robot.pan_err_deg(&final_enc));
    let steer_after = steer_outcome.as_ref().map(|_| robot.steer_err_deg(robot.steering_encoder_deg()));
    let head = robot.head();
    let after = head.alignment_errors(&head.encoders());
    let st = &outcome.calibration.bundle.state;
    let truth = head.truth().clone();
    let cal = calibration_errors(&truth.left, &truth.right, &st.left, &st.right);
    let recon =
        head.recon_err_pct(&outcome.calibration.reference_encoders, &outcome.calibration.points()).ok();
    let true_aligned = head.aligned_encoders();
    // What no joint can remove: the right camera's elevation error at the true aligned
    // readings (its mounting relative to the left camera).
    let unavoidable_r = head.alignment_errors(&true_aligned).elev_err_r_deg;
    let report = &outcome.calibration.report;
    if args.json || writer.is_some() {
        let mut errors_j = images::errors_json(&after, unavoidable_r, &cal, recon);
        errors_j.insert("pan_err_deg".into(), json!(pan_after));
        errors_j.insert("steer_err_deg".into(), json!(steer_after));
        let mut before_j = images::before_json(&before);
        before_j.insert("pan_err_deg".into(), json!(pan_before));
        before_j.insert("steer_err_deg".into(), json!(steer_before));
        let out = json!({
            "scenario": serde_json::to_value(&scenario)?,
            "errors": errors_j,
            "before": before_j,
            "pan": serde_json::to_value(&pan_outcomes)?,
            "pan_fixate": serde_json::to_value(&fixate_outcomes)?,
            "one_motion": serde_json::to_value(&one_motion_outcomes)?,
            "steering": serde_json::to_value(&steer_outcome)?,
            "stages": stages,
            "estimate": {
                "left": camera_json(&outcome.calibration, "left", &st.left),
                "right": camera_json(&outcome.calibration, "right", &st.right),
                "aligned_encoders": encoders_json(&outcome.solution.aligned_encoders),
                "aligned_sigma_deg": serde_json::to_value(outcome.sigmas)?,
                "predicted_elev_err_r_deg": outcome.solution.predicted_elev_err_r_deg,
                "roll_left_deg": outcome.solution.roll_left_deg, "roll_right_deg": outcome.solution.roll_right_deg,
                "checks": serde_json::to_value(&outcome.checks)?,
            },
            "truth": {
                "left": {"K": k_json(&truth.left)}, "right": {"K": k_json(&truth.right)},
                "aligned_encoders": encoders_json(&true_aligned),
                "steer_zero_deg": robot.truth().steer_zero_deg,
                "wheelbase_m": robot.truth().wheelbase_m,
            },
            "report": serde_json::to_value(report)?,
            "timings": {"estimation_s": outcome.estimation_seconds, "total_s": total},
            "rotations": {"auto": args.auto_rotation, "rotation_deg": outcome.rotation_deg, "diagonal_rotation_deg": outcome.diagonal_rotation_deg, "verge_rotation_deg": outcome.verge_rotation_deg},
        });
        if let Some(w) = &writer {
            w.write_report(&out).context("session")?;
        }
        if args.json {
            say!("{}", serde_json::to_string_pretty(&out)?);
            return Ok(());
        }
    }
    say!(
        "headalign demo: simulated head '{}' (seed {}, noise {} px, {} points, {:.0} % outliers, {} deg rotations{})",
        "yorick",
        scenario.seed,
        scenario.noise_px,
        scenario.points,
        100.0 * scenario.outlier_fraction,
        outcome.rotation_deg,
        if outcome.diagonal_rotation_deg != 0.0 {
            format!(" and {} deg diagonals", outcome.diagonal_rotation_deg)
        } else {
            String::new()
        }
    );
    say!();
    say!("{:<22} {:>12} {:>12} {:>10}", "calibration", "estimate", "truth", "sigma");
    let rows: [(&str, f64, f64, Option<f64>); 8] = [
        ("left fx (px)", st.left.fx, truth.left.fx, sigma(&outcome.calibration, "left.fx")),
        ("left fy (px)", st.left.fy, truth.left.fy, sigma(&outcome.calibration, "left.fy")),
        ("left cx (px)", st.left.cx, truth.left.cx, sigma(&outcome.calibration, "left.cx")),
        ("left cy (px)", st.left.cy, truth.left.cy, sigma(&outcome.calibration, "left.cy")),
        ("right fx (px)", st.right.fx, truth.right.fx, sigma(&outcome.calibration, "right.fx")),
        ("right fy (px)", st.right.fy, truth.right.fy, sigma(&outcome.calibration, "right.fy")),
        ("right cx (px)", st.right.cx, truth.right.cx, sigma(&outcome.calibration, "right.cx")),
        ("right cy (px)", st.right.cy, truth.right.cy, sigma(&outcome.calibration, "right.cy")),
    ];
    for (name, e, t, s) in rows {
        say!(
            "{:<22} {:>12.2} {:>12.2} {:>10}",
            name,
            e,
            t,
            s.map(|v| format!("{v:.2}")).unwrap_or_else(|| "-".into())
        );
    }
    say!();
    say!("{:<22} {:>12} {:>12} {:>10}", "aligned reading (deg)", "estimate", "truth", "sigma");
    let sig = outcome.sigmas;
    let a = outcome.solution.aligned_encoders;
    for (name, e, t, s) in [
        ("elevation", a.elevation, true_aligned.elevation, sig.elevation_deg),
        ("verge left", a.verge_left, true_aligned.verge_left, sig.verge_left_deg),
        ("verge right", a.verge_right, true_aligned.verge_right, sig.verge_right_deg),
    ] {
        say!("{:<22} {:>12.3} {:>12.3} {:>10.3}", name, e, t, s);
    }
    say!();
    say!("{:<22} {:>12} {:>12}", "alignment error (deg)", "before", "after");
    for (name, b, x) in [
        ("verge left", before.verge_err_l_deg, after.verge_err_l_deg),
        ("verge right", before.verge_err_r_deg, after.verge_err_r_deg),
        ("elevation left", before.elev_err_l_deg, after.elev_err_l_deg),
        ("elevation right", before.elev_err_r_deg, after.elev_err_r_deg),
    ] {
        say!("{:<22} {:>12.3} {:>12.3}", name, b, x);
    }
    say!(
        "  (right elevation: {:.3} deg of it cannot be removed by any joint (true mounting); predicted from the calibration: {:.3} deg)",
        unavoidable_r,
        outcome.solution.predicted_elev_err_r_deg
    );
    say!();
    say!(
        "f_err {:.3} %   aspect_err {:.3} %   pp_err {:.3} %   recon_err {}",
        cal.f_err_pct,
        cal.aspect_err_pct,
        cal.pp_err_pct,
        recon.map(|r| format!("{r:.2} %")).unwrap_or_else(|| "-".into())
    );
    say!(
        "stereo inliers {}/{}, bundle: {} points, {} observations, RMS {:.3} -> {:.3} px, sigma {:.3} px",
        report.stereo_inliers,
        report.stereo_matches,
        report.bundle_points,
        report.bundle_observations,
        report.initial_rms_px,
        report.final_rms_px,
        report.sigma_px
    );
    if let Some(p) = &report.depth_profile {
        say!(
            "depth scale: mean distance {:.1} baselines (sigma {:.1} %), sigmas widened by up to x{:.3} over its 95 % interval",
            p.log_depth.exp(),
            100.0 * p.sigma_log_depth,
            p.max_widening
        );
    }
    if let Some(b) = &report.bootstrap {
        say!("{}", bootstrap_line(b));
    }
    for d in &report.dropped_views {
        eprintln!(
            "warning: view '{}' was left out of the estimate (its capture is kept): {}",
            d.view, d.reason
        );
    }
    say!("checks after moving: {}", outcome.checks.len());
    if !pan_outcomes.is_empty() {
        say!();
    }
    for (i, s) in one_motion_outcomes.iter().flat_map(|p| &p.steps).enumerate() {
        let e = &s.estimate;
        say!(
            "one motion {}: pan {:+.3} deg, elevation {:+.3} deg, verge {:+.3} / {:+.3} deg; tilt {:+.3} deg, robot turn {:+.3} deg, verge check {:+.3} / {:+.3} deg, {} tracks",
            i + 1,
            e.pan_correction_deg,
            e.elevation_correction_deg,
            e.verge_correction_deg[0].unwrap_or(f64::NAN),
            e.verge_correction_deg[1].unwrap_or(f64::NAN),
            e.tilt_deg,
            e.turn_deg,
            e.verge_check_deg[0],
            e.verge_check_deg[1],
            s.inliers
        );
    }
    for (i, s) in fixate_outcomes.iter().flat_map(|p| &p.steps).enumerate() {
        say!(
            "pan fixation drive {}: epipole {}, alpha {:.0} px, pan move {:+.3} deg, median flow {:.1} px",
            i + 1,
            s.epipole_px.map_or("at infinity".to_string(), |e| format!("({:.1}, {:.1}) px", e[0], e[1])),
            s.alpha_px,
            s.pan_move_deg,
            s.median_flow_px
        );
    }
    for (i, s) in pan_outcomes.iter().flat_map(|p| &p.steps).enumerate() {
        {
            say!(
                "pan drive {}: image {:+.3} (sigma {:.3}), stereo {:+.3} (sigma {:.3}) -> correction {:+.3} deg (sigma {:.3}, {:.3} of it from the calibration); turn {:+.3} deg, median flow {:.1} px, elevation check {:+.3} deg",
                i + 1,
                s.pan_image_deg,
                s.sigma_image_deg,
                s.pan_stereo_deg,
                s.sigma_stereo_deg,
                s.pan_correction_deg,
                s.sigma_deg,
                s.sigma_calibration_deg,
                s.turn_deg,
                s.median_flow_px,
                s.elevation_check_deg
            );
        }
    }
    if let Some(after) = pan_after {
        say!("pan error (deg): before {:+.3}, after {:+.3}", pan_before, after);
    }
    if let Some(s) = &steer_outcome {
        say!(
            "steering: zero {:+.3} deg (truth {:+.3}), wheelbase {:.3} m (truth {:.3}), pan check {:+.3} deg; steer error before {:+.3}, after {:+.3} deg",
            s.steer_zero_deg,
            robot.truth().steer_zero_deg,
            s.wheelbase_m,
            robot.truth().wheelbase_m,
            s.pan_check_deg,
            steer_before,
            steer_after.unwrap_or(f64::NAN)
        );
    }
    say!("time: estimation {:.1} ms, total {:.1} ms", 1e3 * outcome.estimation_seconds, 1e3 * total);
    Ok(())
}

fn demo_images(args: &DemoArgs, scenario: &Scenario, plan: &stages::RobotPlan) -> Result<()> {
    let target = match (&args.session, args.no_session) {
        (Some(d), _) => images::SessionTarget::Dir(d.clone()),
        (None, true) => images::SessionTarget::None,
        (None, false) => images::SessionTarget::Default,
    };
    let v = images::run(scenario, args.auto_rotation, &target, plan)?;
    if args.json {
        say!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    let v = &v;
    say!(
        "headalign demo --images: simulated head 'yorick' (seed {}), rendered {}x{} images, vision front end",
        scenario.seed,
        scenario.image_size[0],
        scenario.image_size[1]
    );
    let steps = v["images"]["verging"]["steps"].as_array().map_or(0, Vec::len);
    say!(
        "verging: {} registration(s), overlap {:.0} %",
        steps,
        100.0 * v["images"]["verging"]["overlap_fraction"].as_f64().unwrap_or(f64::NAN)
    );
    if let Some(t) = v["images"]["tracking"].as_array() {
        for (name, t) in v["images"]["views"].as_array().into_iter().flatten().zip(t) {
            say!(
                "  view {:<12} stereo matches {:>5}, tracked left/right {:>5} {:>5}",
                name.as_str().unwrap_or("?"),
                t["stereo_matches"],
                t["observations"][0],
                t["observations"][1]
            );
        }
    }
    say!();
    say!("{:<22} {:>12} {:>12}", "alignment error (deg)", "before", "after");
    for (name, key) in [
        ("verge left", "verge_err_l_deg"),
        ("verge right", "verge_err_r_deg"),
        ("elevation left", "elev_err_l_deg"),
        ("elevation right", "elev_err_r_deg"),
    ] {
        say!(
            "{:<22} {:>12.3} {:>12.3}",
            name,
            v["before"][key].as_f64().unwrap_or(f64::NAN),
            v["errors"][key].as_f64().unwrap_or(f64::NAN)
        );
    }
    say!(
        "  (right elevation: {:.3} deg of it cannot be removed by any joint)",
        v["errors"]["elev_err_r_unavoidable_deg"].as_f64().unwrap_or(f64::NAN)
    );
    say!(
        "f_err {:.3} %   aspect_err {:.3} %   pp_err {:.3} %",
        v["errors"]["f_err_pct"].as_f64().unwrap_or(f64::NAN),
        v["errors"]["aspect_err_pct"].as_f64().unwrap_or(f64::NAN),
        v["errors"]["pp_err_pct"].as_f64().unwrap_or(f64::NAN)
    );
    say!("time: total {:.2} s", v["timings"]["total_s"].as_f64().unwrap_or(f64::NAN));
    if let Some(dir) = v["session"].as_str() {
        say!("session (views, report.json, figure6.png, aligned.png): {dir}");
    }
    Ok(())
}

fn align(args: &AlignArgs) -> Result<()> {
    let mut recorded = None;
    let views = match (&args.observations, &args.images) {
        (Some(file), _) => read_session(file)?,
        (None, Some(dir)) => {
            // The verge/tilt views (verging captures are recorded too, but the rig is not
            // rigid there).
            let r: Vec<_> = headalign::session::read_image_session(dir)?
                .into_iter()
                .filter(headalign::session::RecordedView::is_verge_tilt)
                .collect();
            let views =
                headalign::session::track_session(&r, &headalign::frontend::FrontEndOptions::default())?;
            recorded = Some(r);
            views
        }
        (None, None) => bail!("give --observations FILE or --images DIR"),
    };
    // Errors past reading name the session too.
    let session = args
        .observations
        .as_ref()
        .or(args.images.as_ref())
        .map_or(String::new(), |p| p.display().to_string());
    let in_session = || format!("session {session}");
    let t0 = Instant::now();
    let roles = classify_views(&views).with_context(in_session)?;
    let rig: Vec<View> = views
        .iter()
        .zip(&roles)
        .filter(|(_, r)| !matches!(r, ViewRole::Verge))
        .map(|(v, _)| v.clone())
        .collect();
    let estimation = EstimationOptions { bootstrap: args.bootstrap, ..EstimationOptions::default() };
    let calib = estimate_rig(&rig, &estimation).with_context(in_session)?;
    let state = &calib.bundle.state;
    let reference = views[0].capture.encoders;
    // Vergence axes from the first view where a vergence moved, if any.
    let mut verge = VergeAxes::default();
    if let Some((v, _)) = views.iter().zip(&roles).find(|(_, r)| matches!(r, ViewRole::Verge)) {
        let d = |j: Joint| (v.capture.encoders.get(j) - reference.get(j)).to_radians();
        let chain = headalign::alignment::head_motion(state, d(Joint::Pan), d(Joint::Elevation))
            .with_context(|| format!("session {session}: head model"))?;
        let measured =
            measure_cameras(&calib, &v.capture, &chain, &(chain * state.right_from_left.inverse()))
                .with_context(in_session)?;
        verge = verge_axes_from_motion(state, &reference, &v.capture.encoders, &measured)
            .with_context(in_session)?;
    }
    let solution = solve_alignment(state, &verge, &reference).with_context(in_session)?;
    let sig = alignment_sigmas(&calib, &verge, &reference).with_context(in_session)?;
    let seconds = t0.elapsed().as_secs_f64();
    let (pan, elev) = headalign::estimate::axes_of(state).context("axes")?;
    let axes = json!({
        "frame": "left camera of the first view; points in baselines",
        "pan": axis_json(&pan, &calib, 0),
        "elevation": axis_json(&elev, &calib, 1),
        "verge_left": verge_json(&verge.left),
        "verge_right": verge_json(&verge.right),
    });
    let mut written = Vec::new();
    if let Some(dir) = &args.out {
        let stereo = StereoCalibration::from_rig(&calib, views[0].capture.image_size, args.baseline_m)?;
        written = stereo.write_all(dir)?;
        let extra = [
            ("head.json", json!({"format": "headalign-head/1", "axes": axes})),
            (
                "alignment.json",
                json!({
                    "format": "headalign-alignment/1",
                    "reference_encoders": encoders_json(&reference),
                    "aligned_encoders": encoders_json(&solution.aligned_encoders),
                    "aligned_sigma_deg": serde_json::to_value(sig)?,
                    "verge_axes_measured": solution.verge_axes_measured,
                    "predicted_elev_err_r_deg": solution.predicted_elev_err_r_deg,
                    "roll_left_deg": solution.roll_left_deg, "roll_right_deg": solution.roll_right_deg,
                }),
            ),
        ];
        for (name, value) in extra {
            let path = dir.join(name);
            std::fs::write(&path, serde_json::to_string_pretty(&value)? + "\n")
                .with_context(|| format!("cannot write {}", path.display()))?;
            written.push(path);
        }
        let results = report_html::AlignmentResults {
            calibration: &calib,
            image_size: views[0].capture.image_size,
            baseline_m: args.baseline_m,
            verge_axes: &verge,
            reference,
            solution: &solution,
            sigmas: &sig,
        };
        let source = args.observations.as_ref().or(args.images.as_ref());
        written.extend(report_html::write_align_report(dir, source, &views, recorded.as_deref(), &results)?);
    }
    if args.json {
        let out = json!({
            "left": camera_json(&calib, "left", &state.left),
            "right": camera_json(&calib, "right", &state.right),
            "fixation_px": {"left": solution.fixation_px_left, "right": solution.fixation_px_right},
            "invariant_lines": serde_json::to_value(solution.invariant_lines)?,
            "axes": axes,
            "files": written.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
            "aligned_encoders": encoders_json(&solution.aligned_encoders),
            "aligned_sigma_deg": serde_json::to_value(sig)?,
            "verge_axes_measured": solution.verge_axes_measured,
            "predicted_elev_err_r_deg": solution.predicted_elev_err_r_deg,
            "roll_left_deg": solution.roll_left_deg, "roll_right_deg": solution.roll_right_deg,
            "report": serde_json::to_value(&calib.report)?,
            "seconds": seconds,
        });
        say!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(());
    }
    let show_k = |name: &str, k: &Intrinsics| {
        say!(
            "{name} K = [[{:.2}, {:.3}, {:.2}], [0, {:.2}, {:.2}], [0, 0, 1]]",
            k.fx,
            k.skew,
            k.cx,
            k.fy,
            k.cy
        );
    };
    show_k("left ", &state.left);
    show_k("right", &state.right);
    say!(
        "fixation point: left ({:.2}, {:.2}) px, right ({:.2}, {:.2}) px",
        solution.fixation_px_left[0],
        solution.fixation_px_left[1],
        solution.fixation_px_right[0],
        solution.fixation_px_right[1]
    );
    let d = |l: &Line| format!("({:+.4}, {:+.4}, {:+.4})", l.direction.x, l.direction.y, l.direction.z);
    say!("pan axis direction {}   elevation axis direction {}", d(&pan), d(&elev));
    let a = solution.aligned_encoders;
    say!(
        "aligned readings: elevation {:.3} +- {:.3} deg, verge_left {:.3} +- {:.3} deg, verge_right {:.3} +- {:.3} deg",
        a.elevation,
        sig.elevation_deg,
        a.verge_left,
        sig.verge_left_deg,
        a.verge_right,
        sig.verge_right_deg
    );
    if let Some(b) = &calib.report.bootstrap {
        say!("{}", bootstrap_line(b));
    }
    if !solution.verge_axes_measured {
        say!("note: no view moved the vergence joints; their axes were assumed nominal");
    }
    for p in &written {
        say!("wrote {}", p.display());
    }
    Ok(())
}

/// One line on what the bootstrap of the covariance did.
fn bootstrap_line(b: &headalign::estimate::BootstrapReport) -> String {
    format!(
        "bootstrap: {} replicates ({} failed), sigmas widened by up to x{:.3} (median bootstrap / linearised {:.3})",
        b.replicates, b.failed, b.max_widening, b.median_ratio
    )
}

fn simulate(args: &SimulateArgs) -> Result<()> {
    let scenario = args.scenario.scenario()?;
    if args.images {
        return calibrate::simulate_to_disk(&scenario, &args.motion, &args.out);
    }
    let mut head = SimulatedHead::new(scenario.clone()).map_err(|e| anyhow::anyhow!("simulator: {e}"))?;
    let e0 = head.read_encoders()?;
    let options = VergeTiltOptions {
        rotation_deg: scenario.rotation_deg,
        verge_rotation_deg: scenario.rotation_deg,
        ..VergeTiltOptions::default()
    };
    let mut views = Vec::new();
    for (name, enc) in capture_plan(&e0, &options) {
        head.move_to(&enc)?;
        views.push(View { name, capture: head.capture()? });
    }
    let text = session_to_json(&views)?;
    if args.out.exists() && args.out.is_dir() {
        bail!("{} is a directory", args.out.display());
    }
    std::fs::write(&args.out, text).with_context(|| format!("cannot write {}", args.out.display()))?;
    eprintln!("wrote {} views to {}", views.len(), args.out.display());
    Ok(())
}
