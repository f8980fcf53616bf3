//! `headalign-sim-driver`: an example driver that speaks the headalign head protocol
//! (`docs/head-protocol.md`, JSON lines on stdin/stdout) in front of the simulated robot
//! of `headalign demo --images`. The server and what each flag does are
//! [`headalign_sim::driver`]'s; here the flags are parsed and a failure printed (a
//! `--die-at` crash exits with status 3).

use std::path::PathBuf;

use clap::Parser;
use headalign_sim::driver::{DriverError, DriverOptions, serve};

#[derive(Parser)]
#[command(name = "headalign-sim-driver", about = "Example head driver fronting the simulated robot")]
struct Args {
    /// Scenario seed (as `headalign demo --seed`).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Tall textured panels about 1 m ahead (default 6, as the demo's robot stages).
    // `Scenario::ROBOT_NEAR_PANELS`.
    #[arg(long)]
    near_panels: Option<usize>,
    /// A scenario file (TOML, as `headalign demo --scenario`); `--seed` and `--near-panels` apply over it.
    #[arg(long)]
    scenario: Option<PathBuf>,
    /// Answer as a version-1 driver of a head alone (no base: no drive, no steer).
    #[arg(long)]
    no_base: bool,
    /// At the end, write the robot's true alignment errors to this JSON file.
    #[arg(long)]
    truth: Option<PathBuf>,
    /// Folder for the captured PNGs (default: a temporary folder, removed at exit).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Exit with status 3 on receiving this request (1 = hello).
    #[arg(long)]
    die_at: Option<u64>,
    /// Answer this request with a line that is not JSON.
    #[arg(long)]
    garble_at: Option<u64>,
    /// Answer this request late, by --sleep-s seconds.
    #[arg(long)]
    sleep_at: Option<u64>,
    /// Delay of --sleep-at, seconds.
    #[arg(long, default_value_t = 60.0)]
    sleep_s: f64,
}

fn main() -> std::process::ExitCode {
    let a = Args::parse();
    let options = DriverOptions {
        seed: a.seed,
        near_panels: a.near_panels,
        scenario: a.scenario,
        no_base: a.no_base,
        truth: a.truth,
        out: a.out,
        die_at: a.die_at,
        garble_at: a.garble_at,
        sleep_at: a.sleep_at,
        sleep_s: a.sleep_s,
    };
    match serve(&options) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e @ DriverError::Crash { .. }) => {
            eprintln!("headalign-sim-driver: {e}");
            std::process::exit(3);
        }
        Err(e) => {
            eprintln!("headalign-sim-driver: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}
