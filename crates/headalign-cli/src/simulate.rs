//! `headalign simulate --out FILE`: an observation session (initial, elevation, pan and
//! verge views, the simulator's tracked points) recorded from the simulator; with
//! `--images` a rendered image session for `calibrate` ([`crate::calibrate::simulate_to_disk`]).

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;
use headalign::observations::View;
use headalign::procedure::{VergeTiltOptions, capture_plan};
use headalign_io::observations::session_to_json;
use headalign_platform::StereoHead;
use headalign_sim::SimulatedHead;

use crate::flags::ScenarioArgs;

#[derive(Args)]
pub struct SimulateArgs {
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
    /// motion of the whole rig).
    // `general`: `headalign_sim::rigmotion::general_rig_motion`.
    #[arg(long, default_value = "rotations", requires = "images")]
    motion: String,
}

/// `headalign simulate`.
pub fn run(args: &SimulateArgs) -> Result<()> {
    let scenario = args.scenario.scenario()?;
    if args.images {
        args.scenario.refuse_point_mode_flags()?;
        return crate::calibrate::simulate_to_disk(&scenario, &args.motion, &args.out);
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
