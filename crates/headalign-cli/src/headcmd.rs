//! `headalign run --head-cmd CMD`: verging, then the verge/tilt procedure on images, on a
//! head behind a driver process that speaks the JSON-lines head protocol
//! (`docs/head-protocol.md`; [`headalign::process_head::ProcessHead`]). Every capture is
//! recorded to the session folder before it is processed (always: a real head's captures
//! cannot be made again); `report.json` gets the results. A timeout, a driver that exits
//! or a malformed answer stops the run with one line naming the request and the session
//! folder, which keeps every view captured so far.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Args;
use headalign::process_head::{ProcessHead, ProcessHeadOptions};
use headalign_platform::StereoHead;
use serde_json::json;

use crate::{images, replay};

/// Print a line to stdout, ignoring write errors (a closed pipe is not a failure).
macro_rules! say {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stdout(), $($arg)*);
    }};
}

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
    /// Print one JSON object instead of the summary.
    #[arg(long)]
    pub json: bool,
}

/// Run `headalign run`.
pub fn run(args: &RunArgs) -> Result<()> {
    let t0 = Instant::now();
    if !(args.head_timeout.is_finite() && args.head_timeout > 0.0 && args.head_timeout < 1e6) {
        bail!("--head-timeout must be a positive number of seconds, got {}", args.head_timeout);
    }
    if !(args.rotation.is_finite() && args.rotation > 0.0 && args.rotation < 90.0) {
        bail!("--rotation must be in (0, 90) degrees, got {}", args.rotation);
    }
    let options = ProcessHeadOptions { timeout: Duration::from_secs_f64(args.head_timeout) };
    let mut head = ProcessHead::spawn(&args.head_cmd, options).context("head")?;
    let target = match &args.session {
        Some(d) => images::SessionTarget::Dir(d.clone()),
        None => images::SessionTarget::Default,
    };
    let description = json!({"kind": "process", "command": head.command(), "name": head.name()});
    let session = target.resolve().map(|d| {
        (d, images::session_info(args.rotation, args.auto_rotation, head.image_size(), description))
    });
    let seed = headalign::estimate::EstimationOptions::default().seed;
    let (run, _, v) = images::recorded(
        &mut head,
        session,
        args.rotation,
        args.auto_rotation,
        seed,
        &mut |_, run, outcome| images::run_json(run, outcome, t0.elapsed().as_secs_f64()),
    )?;
    if args.json {
        say!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        say!("head '{}' ({} views)", args.head_cmd, run.run.views.len());
        replay::print_summary(&v);
    }
    Ok(())
}
