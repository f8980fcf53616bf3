//! `headalign demo`: the verge/tilt procedure and the robot stages on the simulated robot,
//! estimate against the simulator's truth. Point mode ([`run_points`]) runs on the
//! simulator's tracked points (exact track ids, Gaussian pixel noise); image mode
//! ([`run_images`], `--images`) renders the views and runs the vision front end
//! ([`crate::images::run`]). Output: a table of estimate, truth and sigma (the
//! calibration in pixels, the aligned readings and alignment errors in degrees, the
//! calibration errors in percent), or one JSON object (`--json`,
//! [`headalign_io::report::schema::DemoReport`]: the same members on every route), which a recorded
//! session also keeps as `report.json`. The stages and their settings are a [`RobotPlan`]
//! ([`headalign::robot::stages`]); `verge-tilt` must be among them, since every robot stage uses its
//! calibration.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use headalign::procedure::{AutoRotation, RouteOutcome, VergeTiltOptions, VergeTiltOutcome, VergeTiltRun};
use headalign::verge_tilt::EstimationOptions;
use headalign_geometry::bootstrap::BootstrapOptions;
use headalign_io::session::SessionInfo;
use headalign_platform::{Encoders, StereoHead};
use headalign_sim::{
    AlignmentErrors, CalibrationErrors, HeadTruth, Scenario, SimulatedRobot, calibration_errors,
};
use serde_json::json;

use crate::align::{bootstrap_line, sigma};
use crate::flags::ScenarioArgs;
use crate::stages;
use crate::{images, points};
use headalign::robot::stages::{RobotOutcomes, RobotPlan};
use headalign_io::report::schema;

/// Arguments of `headalign demo`.
#[derive(Args)]
pub struct DemoArgs {
    #[command(flatten)]
    scenario: ScenarioArgs,
    /// Stages to run in order, comma separated: verge-tilt (required), pan, steering,
    /// pan-fixate, one-motion; a stage may repeat.
    // Names: `headalign::robot::stages::STAGES`. The default's first pan is coarse (derotated drive, a bent
    // wheel tolerated), the second exact once steering has straightened the wheel.
    #[arg(long, default_value = "verge-tilt,pan,steering,pan")]
    stages: String,
    /// one-motion stage: level the elevation with the drive's own direction instead of
    /// the calibrated pan axis.
    #[arg(long)]
    horizon_from_drive: bool,
    /// Largest initial pan error (pan zero offset), degrees.
    #[arg(long)]
    pan_zero_max: Option<f64>,
    /// Tilt of the pan axis from the floor's normal, degrees (default 2; direction drawn
    /// per seed).
    #[arg(long)]
    pan_tilt: Option<f64>,
    /// Largest steering zero offset, degrees.
    #[arg(long)]
    steer_zero_max: Option<f64>,
    /// Forward drive of the pan stage, metres.
    #[arg(long)]
    drive: Option<f64>,
    /// Drive per steering setting of the steering stage, metres (default 0.3; 0.2 with
    /// --images).
    // The 0.2 m image default is `headalign::robot::stages::IMAGE_STEER_DRIVE_M` (see `robot_plan`).
    #[arg(long)]
    steer_drive: Option<f64>,
    /// Steering settings of the steering stage relative to the start reading, degrees,
    /// comma separated (default -20,20,30,-30).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    steer_settings: Option<Vec<f64>>,
    /// Tall textured panels about 1 m in front of the robot. Default: 6 when a robot
    /// stage drives and the scenario has none, else the scenario's.
    // `Scenario::ROBOT_NEAR_PANELS`, applied in `demo` when `RobotPlan::drives`.
    #[arg(long)]
    near_panels: Option<usize>,
    /// Print one JSON object instead of the table.
    #[arg(long)]
    json: bool,
    /// Run on rendered images with the vision front end instead of the simulator's point
    /// correspondences.
    #[arg(long)]
    images: bool,
    /// Record the session here. With --images the default is
    /// `./headalign-sessions/<UTC time>`; in point mode only this flag records.
    // Format: `headalign_io::session`. `--save` is a hidden alias. Point mode records the
    // verge/tilt stage and observations.json; --images adds figure6.png and aligned.png.
    #[arg(long, alias = "save", conflicts_with = "no_session")]
    pub session: Option<PathBuf>,
    /// With --images: record nothing.
    #[arg(long, requires = "images")]
    no_session: bool,
    /// Let the verge/tilt procedure choose its rotations (up to 10 deg, diagonal views
    /// included) as far as the scene stays in view.
    // `AutoRotation::default`; the rotations are probed first.
    #[arg(long)]
    auto_rotation: bool,
    /// Widen the verge/tilt sigmas to a bootstrap over point tracks with this many
    /// replicates (at least 3; off by default; point mode only).
    // `EstimationOptions::bootstrap`; each replicate costs about one more adjustment.
    #[arg(long, value_parser = headalign_eval::parse_replicates, conflicts_with = "images")]
    bootstrap: Option<BootstrapOptions>,
    /// With --images: the lens model estimated (recorded in the session; default auto when
    /// the scenario draws a lens, else pinhole).
    #[command(flatten)]
    lens: images::LensArgs,
}

/// The robot stages and their settings from the demo's flags.
fn robot_plan(args: &DemoArgs, scenario: &Scenario) -> Result<RobotPlan> {
    let stages = stages::parse_stages(&args.stages)?;
    stages::refuse_unused_flags(
        &stages,
        &[
            ("--drive", args.drive.is_some()),
            ("--steer-drive", args.steer_drive.is_some()),
            ("--steer-settings", args.steer_settings.is_some()),
            ("--horizon-from-drive", args.horizon_from_drive),
        ],
    )?;
    if args.images {
        // The plan of `run --stages` too (`RobotPlan::images`).
        let settings = args.steer_settings.clone();
        let mut plan =
            RobotPlan::images(stages, scenario.drive_m, args.steer_drive, settings, scenario.baseline_m);
        plan.horizon_from_drive = args.horizon_from_drive;
        return Ok(plan);
    }
    Ok(RobotPlan {
        stages,
        drive_m: scenario.drive_m,
        horizon_from_drive: args.horizon_from_drive,
        steer_drive_m: args.steer_drive,
        steer_settings_deg: args.steer_settings.clone(),
        baseline_m: scenario.baseline_m,
        planarity_chi2_max: None,
    })
}

/// Run `headalign demo`: the scenario and the stage plan from the flags, then point mode
/// ([`run_points`]) or image mode ([`run_images`]).
pub fn run(args: &DemoArgs) -> Result<()> {
    let (scenario, rplan) = scenario_and_plan(args)?;
    if args.images {
        args.scenario.refuse_point_mode_flags()?;
        return run_images(args, &scenario, &rplan);
    }
    if let Some(lens) = args.lens.lens.filter(|l| *l != headalign::calibrate::LensChoice::Pinhole) {
        anyhow::bail!("--lens {} needs --images (point mode: align --observations --lens)", lens.name());
    }
    if args.lens.lens_terms.is_some() {
        anyhow::bail!("--lens-terms needs --images (point mode: align --observations --lens)");
    }
    run_points(args, &scenario, &rplan)
}

/// The scenario (the scenario flags, then the demo's robot flags) and the stage plan;
/// fails when the stages leave out the verge/tilt calibration.
fn scenario_and_plan(args: &DemoArgs) -> Result<(Scenario, RobotPlan)> {
    let mut scenario = args.scenario.scenario()?;
    if let Some(v) = args.pan_zero_max {
        scenario.pan_zero_max_deg = v;
    }
    if let Some(v) = args.steer_zero_max {
        scenario.steer_zero_max_deg = v;
    }
    if let Some(v) = args.pan_tilt {
        scenario.pan_tilt_deg = v;
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
    Ok((scenario, rplan))
}

/// The verge/tilt procedure's options from the scenario and the flags.
fn verge_tilt_options(args: &DemoArgs, scenario: &Scenario) -> VergeTiltOptions {
    VergeTiltOptions {
        rotation_deg: scenario.rotation_deg,
        verge_rotation_deg: scenario.rotation_deg,
        estimation: EstimationOptions {
            seed: scenario.seed,
            bootstrap: args.bootstrap,
            ..EstimationOptions::default()
        },
        auto_rotation: args.auto_rotation.then(AutoRotation::default),
        ..VergeTiltOptions::default()
    }
}

/// Where and how a point-mode run records (`--session DIR`), if it does.
fn point_session(
    args: &DemoArgs,
    scenario: &Scenario,
    options: &VergeTiltOptions,
    rplan: &RobotPlan,
    robot: &SimulatedRobot,
) -> Option<(PathBuf, SessionInfo)> {
    args.session.as_ref().map(|dir| {
        let head = json!({"kind": "simulator", "scenario": serde_json::to_value(scenario).ok()});
        let mut info = points::session_info(options, robot.head().image_size(), head);
        // The robot stages are recorded too (their captures after the verge/tilt views);
        // `replay` runs them from `stages`.
        info.stages = rplan.drives().then(|| serde_json::to_value(rplan).ok()).flatten();
        (dir.clone(), info)
    })
}

/// The simulated robot's errors before any stage ran.
struct Before {
    /// Alignment errors at the start readings.
    errors: AlignmentErrors,
    /// Pan error at the start readings, degrees.
    pan_deg: f64,
    /// Steering error at the start reading, degrees.
    steer_deg: f64,
}

impl Before {
    fn read(robot: &SimulatedRobot) -> Self {
        let start = robot.head().encoders();
        let errors = robot.head().alignment_errors(&start);
        let pan_deg = robot.pan_err_deg(&start);
        let steer_deg = robot.steer_err_deg(robot.steering_encoder_deg());
        Self { errors, pan_deg, steer_deg }
    }
}

/// The run judged against the simulator's truth after the last stage.
struct After {
    /// Alignment errors at the final readings.
    errors: AlignmentErrors,
    /// Pan error, degrees, if a stage moved the pan joint.
    pan_deg: Option<f64>,
    /// Steering error, degrees, if the steering stage ran.
    steer_deg: Option<f64>,
    /// The true head.
    truth: HeadTruth,
    /// The calibration's errors against the truth.
    cal: CalibrationErrors,
    /// Reconstruction error, percent of distance (`None` if it cannot be computed).
    recon: Option<f64>,
    /// The true aligned readings.
    true_aligned: Encoders,
    /// What no joint can remove: the right camera's elevation error at the true aligned
    /// readings (its mounting relative to the left camera), degrees.
    unavoidable_r: f64,
    /// The true steering zero, degrees.
    steer_zero_deg: f64,
    /// The true wheelbase, metres.
    wheelbase_m: f64,
    /// The true angle of the pan axis from the floor's normal, degrees.
    pan_tilt_deg: f64,
}

impl After {
    fn read(robot: &SimulatedRobot, outcome: &VergeTiltOutcome, stages: &RobotOutcomes) -> Self {
        let final_enc = robot.head().encoders();
        let pan_deg = stages.panned().then(|| robot.pan_err_deg(&final_enc));
        let steer_deg = stages.steering.as_ref().map(|_| robot.steer_err_deg(robot.steering_encoder_deg()));
        let head = robot.head();
        let errors = head.alignment_errors(&head.encoders());
        let st = &outcome.calibration.bundle.state;
        let truth = head.truth().clone();
        let cal = calibration_errors(&truth.left, &truth.right, &st.left, &st.right);
        let recon =
            head.recon_err_pct(&outcome.calibration.reference_encoders, &outcome.calibration.points()).ok();
        let true_aligned = head.aligned_encoders();
        let unavoidable_r = head.alignment_errors(&true_aligned).elev_err_r_deg;
        Self {
            errors,
            pan_deg,
            steer_deg,
            truth,
            cal,
            recon,
            true_aligned,
            unavoidable_r,
            steer_zero_deg: robot.truth().steer_zero_deg,
            wheelbase_m: robot.truth().wheelbase_m,
            pan_tilt_deg: robot.truth().pan_tilt_deg(),
        }
    }
}

/// Point mode: the verge/tilt procedure and the robot stages on the simulated robot's
/// point correspondences, printed as a table or one JSON object (also the session's
/// `report.json` when recording).
fn run_points(args: &DemoArgs, scenario: &Scenario, rplan: &RobotPlan) -> Result<()> {
    let t0 = Instant::now();
    let mut robot = SimulatedRobot::new(scenario.clone()).map_err(|e| anyhow::anyhow!("simulator: {e}"))?;
    let before = Before::read(&robot);
    let options = verge_tilt_options(args, scenario);
    let mut run = VergeTiltRun::default();
    let session = point_session(args, scenario, &options, rplan, &robot);
    let (route, writer) =
        headalign_io::runs::verge_tilt_points(&mut run, robot.head_mut(), &options, session)?;
    // The robot stages need the general route's 3D reconstruction.
    let (robot_out, writer) = match &route {
        RouteOutcome::General(outcome, _) => {
            let (r, w) = headalign_io::runs::robot_stages_points(
                &mut robot,
                rplan,
                outcome,
                writer,
                &mut crate::progress::warn,
            )?;
            (Some(r), w)
        }
        RouteOutcome::Planar(_) => (None, writer),
    };
    let total = t0.elapsed().as_secs_f64();
    if args.json || writer.is_some() {
        let views = run.views.iter().map(|v| v.name.clone()).collect();
        let run = PointRun {
            scenario,
            stages: &rplan.stages,
            route: &route,
            robot: robot_out.as_ref(),
            views,
            total,
        };
        let mut report = points_report(args, &run, &before, &robot)?;
        report.procedure.session = writer.as_ref().map(|w| w.dir().display().to_string());
        let out = serde_json::to_value(&report)?;
        if let Some(w) = &writer {
            w.write_report(&out).context("session")?;
        }
        if args.json {
            say!("{}", serde_json::to_string_pretty(&out)?);
            return images::fail_on_verdict(&out);
        }
    }
    let (outcome, scene) = match route {
        RouteOutcome::General(outcome, scene) => (*outcome, scene),
        RouteOutcome::Planar(p) => {
            crate::facing_plane::report(robot.head(), &p)?;
            let verdict = json!({"verdict": schema::verdict_json(&p.verdict)?});
            images::judgement_lines(&verdict).iter().for_each(|l| say!("{l}"));
            return images::fail_on_verdict(&verdict);
        }
    };
    let robot_out = robot_out.unwrap_or_default();
    let after = After::read(&robot, &outcome, &robot_out);
    say!("{}", headalign_io::report::html::scene_line(&scene));
    print_calibration(scenario, &outcome, &after);
    print_errors(&outcome, &before, &after);
    print_robot_stages(&robot_out, &before, &after);
    say!("time: estimation {:.1} ms, total {:.1} ms", 1e3 * outcome.estimation_seconds, 1e3 * total);
    let verdict = json!({"verdict": schema::verdict_json(&outcome.verdict)?});
    for line in images::judgement_lines(&verdict) {
        say!("{line}");
    }
    images::fail_on_verdict(&verdict)
}

/// What a point-mode run produced, for its JSON.
struct PointRun<'a> {
    scenario: &'a Scenario,
    stages: &'a [String],
    route: &'a RouteOutcome,
    /// The robot stages' outcomes (`None` on the planar route, which runs none).
    robot: Option<&'a RobotOutcomes>,
    /// The verge/tilt views' names.
    views: Vec<String>,
    /// Wall time of the whole run, seconds.
    total: f64,
}

/// The JSON of a point-mode run on either route (`--json`, and `report.json` of a
/// session): [`schema::DemoReport`].
fn points_report(
    args: &DemoArgs,
    run: &PointRun<'_>,
    before: &Before,
    robot: &SimulatedRobot,
) -> Result<schema::DemoReport> {
    let procedure =
        schema::Procedure::new("points", run.route, run.views.clone(), args.auto_rotation, run.total)?
            .with_robot(run.stages, run.robot);
    let truth = crate::truth::truth(robot, run.scenario)?;
    let errors = match run.route {
        RouteOutcome::General(outcome, _) => {
            let a = After::read(robot, outcome, run.robot.unwrap_or(&RobotOutcomes::default()));
            crate::truth::errors(&a.errors, a.unavoidable_r, &a.cal, a.recon, a.pan_deg, a.steer_deg)
        }
        RouteOutcome::Planar(p) => {
            let head = robot.head();
            let (t, c) = (head.truth(), &p.calibration);
            let cal = calibration_errors(&t.left, &t.right, &c.left.intrinsics, &c.right.intrinsics);
            let unavoidable_r = head.alignment_errors(&truth.aligned_encoders).elev_err_r_deg;
            let after = head.alignment_errors(&head.encoders());
            // No 3D reconstruction on a plane, and no robot stage moved the pan or steering.
            crate::truth::errors(&after, unavoidable_r, &cal, None, None, None)
        }
    };
    let aligned = procedure.estimate.aligned_encoders;
    Ok(schema::DemoReport {
        schema: schema::DEMO,
        procedure,
        scenario: serde_json::to_value(run.scenario)?,
        errors,
        before: crate::truth::before(&before.errors, before.pan_deg, before.steer_deg),
        aligned_reading_errors_deg: schema::ReadingErrors::new(&aligned, &truth.aligned_encoders),
        truth,
    })
}

/// The point-mode table's heading, the calibration against the truth and the aligned
/// readings.
fn print_calibration(scenario: &Scenario, outcome: &VergeTiltOutcome, after: &After) {
    let st = &outcome.calibration.bundle.state;
    let truth = &after.truth;
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
    let true_aligned = &after.true_aligned;
    for (name, e, t, s) in [
        ("elevation", a.elevation, true_aligned.elevation, sig.elevation_deg),
        ("verge left", a.verge_left, true_aligned.verge_left, sig.verge_left_deg),
        ("verge right", a.verge_right, true_aligned.verge_right, sig.verge_right_deg),
    ] {
        say!("{:<22} {:>12.3} {:>12.3} {:>10.3}", name, e, t, s);
    }
}

/// The point-mode table's alignment errors before and after, the calibration's errors,
/// the estimate's report and the checks.
fn print_errors(outcome: &VergeTiltOutcome, before: &Before, after: &After) {
    let report = &outcome.calibration.report;
    let cal = &after.cal;
    say!();
    say!("{:<22} {:>12} {:>12}", "alignment error (deg)", "before", "after");
    let (b, x) = (&before.errors, &after.errors);
    for (name, b, x) in [
        ("verge left", b.verge_err_l_deg, x.verge_err_l_deg),
        ("verge right", b.verge_err_r_deg, x.verge_err_r_deg),
        ("elevation left", b.elev_err_l_deg, x.elev_err_l_deg),
        ("elevation right", b.elev_err_r_deg, x.elev_err_r_deg),
    ] {
        say!("{:<22} {:>12.3} {:>12.3}", name, b, x);
    }
    say!(
        "  (right elevation: {:.3} deg of it cannot be removed by any joint (true mounting); predicted from the calibration: {:.3} deg)",
        after.unavoidable_r,
        outcome.solution.predicted_elev_err_r_deg
    );
    say!();
    say!(
        "f_err {:.3} %   aspect_err {:.3} %   pp_err {:.3} %   recon_err {}",
        cal.f_err_pct,
        cal.aspect_err_pct,
        cal.pp_err_pct,
        after.recon.map(|r| format!("{r:.2} %")).unwrap_or_else(|| "-".into())
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
    for d in &report.views_without_homography {
        eprintln!("note: view '{}' was used without a 3D homography (no linear start): {}", d.view, d.reason);
    }
    say!("checks after moving: {}", outcome.checks.len());
}

/// The point-mode table's robot stages: each one-motion step, fixation drive and pan
/// drive, then the pan and steering errors before and after.
fn print_robot_stages(stages: &RobotOutcomes, before: &Before, after: &After) {
    if !stages.pan.is_empty() {
        say!();
    }
    for (i, s) in stages.one_motion.iter().flat_map(|p| &p.steps).enumerate() {
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
    for (i, s) in stages.pan_fixate.iter().flat_map(|p| &p.steps).enumerate() {
        say!(
            "pan fixation drive {}: epipole {}, alpha {:.0} px, pan move {:+.3} deg, median flow {:.1} px",
            i + 1,
            s.epipole_px.map_or("at infinity".to_string(), |e| format!("({:.1}, {:.1}) px", e[0], e[1])),
            s.alpha_px,
            s.pan_move_deg,
            s.median_flow_px
        );
    }
    for (i, s) in stages.pan.iter().flat_map(|p| &p.steps).enumerate() {
        say!(
            "pan drive {}: image {:+.3} (sigma {:.3}), stereo {:+.3} (sigma {:.3}) -> correction {:+.3} deg (sigma {:.3}, {:.3} of it from the calibration); turn {:+.3} deg, median flow {:.1} px, elevation check {:+.3} deg; pan axis {:.2} +- {:.2} deg from the floor normal (truth {:.2}), planarity chi-square {:.1} ({:.2} dof)",
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
            s.elevation_check_deg,
            s.floor.pan_tilt_deg,
            s.floor.sigma_pan_tilt_deg,
            after.pan_tilt_deg,
            s.planarity_chi2,
            s.planarity_dof
        );
    }
    if let Some(pan_after) = after.pan_deg {
        say!("pan error (deg): before {:+.3}, after {:+.3}", before.pan_deg, pan_after);
    }
    if let Some(s) = &stages.steering {
        say!(
            "steering: zero {:+.3} deg (truth {:+.3}), wheelbase {:.3} m (truth {:.3}), pan axis {:.3} +- {:.3} deg from the floor normal (truth {:.3}), pan check {:+.3} deg; steer error before {:+.3}, after {:+.3} deg",
            s.steer_zero_deg,
            after.steer_zero_deg,
            s.wheelbase_m,
            after.wheelbase_m,
            s.floor.pan_tilt_deg,
            s.floor.sigma_pan_tilt_deg,
            after.pan_tilt_deg,
            s.pan_check_deg,
            before.steer_deg,
            after.steer_deg.unwrap_or(f64::NAN)
        );
    }
}

/// Image mode: the procedure on rendered images ([`crate::images::run`]), printed as a
/// table or one JSON object.
fn run_images(args: &DemoArgs, scenario: &Scenario, plan: &RobotPlan) -> Result<()> {
    let target = match (&args.session, args.no_session) {
        (Some(d), _) => images::SessionTarget::Dir(d.clone()),
        (None, true) => images::SessionTarget::None,
        (None, false) => images::SessionTarget::Default,
    };
    // The lens: the flags, else auto when the renderer draws a lens, else the pinhole.
    let drawn = if scenario.render.distortion.is_zero() {
        headalign::calibrate::LensChoice::Pinhole
    } else {
        headalign::calibrate::LensChoice::Auto
    };
    let lens = args.lens.over(images::LensArgs { lens: Some(drawn), lens_terms: None });
    lens.validate()?;
    let v = images::run(scenario, args.auto_rotation, &target, plan, &lens)?;
    if args.json {
        say!("{}", serde_json::to_string_pretty(&v)?);
        return images::fail_on_verdict(&v);
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
    for line in crate::facing_plane::summary_lines(v) {
        say!("{line}");
    }
    if let Some(line) = stages::summary_line(v) {
        say!("{line}");
    }
    if let Some(e) = v.get("aligned_reading_errors_deg") {
        let f = |k: &str| e[k].as_f64().unwrap_or(f64::NAN);
        say!(
            "aligned reading errors (deg): elevation {:+.4}, verge_left {:+.4}, verge_right {:+.4}",
            f("elevation"),
            f("verge_left"),
            f("verge_right")
        );
    }
    if let Some(line) = images::lens_line(&v["estimate"]) {
        say!("{line}");
    }
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
    for line in images::judgement_lines(v) {
        say!("{line}");
    }
    if let Some(dir) = v["session"].as_str() {
        say!("session ({}): {dir}", crate::facing_plane::session_files(v));
    }
    images::fail_on_verdict(v)
}
