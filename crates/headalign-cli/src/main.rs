//! The `headalign` command-line tool: a dispatcher (parse the flags, call one function per
//! subcommand, map its error to one line and the exit code). Each subcommand's file maps
//! its flags to the library's options, calls the library and prints; the procedures live
//! in the `headalign` library, the experiments in `headalign-eval`.
//!
//! - `headalign demo`: the verge/tilt procedure on the simulated head, estimate vs truth
//!   ([`demo`]).
//! - `headalign align --observations FILE`: the estimation on an observation session ([`align`]).
//! - `headalign simulate --out FILE`: record an observation session from the simulator ([`simulate`]).
//! - `headalign experiment <name>`: Monte-Carlo experiments (the `headalign-eval` crate).
//! - `headalign replay DIR`: re-run a recorded session offline ([`replay`]).
//! - `headalign run --head-cmd CMD`: the image procedure and the robot stages on a driver
//!   process ([`headcmd`]).
//! - `headalign calibrate DIR`: self-calibration from rig motions ([`calibrate`]).
//! - `headalign check SOURCE --calibration FILE`: the targetless health check of a stereo
//!   calibration ([`check`]).

mod align;
mod calibrate;
mod check;
mod demo;
mod facing_plane;
mod flags;
mod headcmd;
mod images;
mod points;
mod progress;
mod recording;
mod replay;
mod report_html;
mod schema;
mod simulate;
mod stages;

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Parser, Subcommand};

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
    /// Run the verge/tilt procedure and the robot stages on the simulated robot and
    /// compare with the truth.
    Demo(demo::DemoArgs),
    /// Estimate calibration, axes and aligned readings from an observation session.
    Align(align::AlignArgs),
    /// Record an observation session (initial, elevation, pan, verge views) from the simulator.
    Simulate(simulate::SimulateArgs),
    /// Run a Monte-Carlo experiment (CSV, PNG/SVG plots, Markdown summary).
    Experiment(headalign_eval::ExperimentArgs),
    /// Re-run a recorded session offline (same procedure, recorded images: same result).
    Replay(replay::ReplayArgs),
    /// Verge, calibrate and align a head driven through the JSON-lines head protocol, then
    /// run the robot stages on its base (--stages), recording the session.
    Run(headcmd::RunArgs),
    /// Self-calibrate a stereo rig from views related by rigid motions of the whole rig.
    Calibrate(calibrate::CalibrateArgs),
    /// Check a stereo calibration against natural stereo pairs: rotation change with sigmas,
    /// depth error, verdict good / can-improve / recalibrate (recalibrate: a change significant
    /// at 5 sigma causing more than 1 % depth error at 5 m).
    Check(check::CheckArgs),
}

/// Longest error message printed, characters: 300 with the `error: ` before it (the
/// rest goes to a report file).
const MAX_ERROR_LINE: usize = 293;

/// The folder a command writes its results to, when the user named one (`--out`,
/// `--session`): where a long error's full text goes.
fn report_dir(command: &Command) -> Option<PathBuf> {
    match command {
        Command::Calibrate(a) => a.out.clone(),
        Command::Check(a) => a.update.clone(),
        Command::Align(a) => a.out.clone(),
        Command::Run(a) => a.session.clone(),
        Command::Demo(a) => a.session.clone(),
        _ => None,
    }
}

/// An error's line, at most [`MAX_ERROR_LINE`] characters: a longer one is cut at a word
/// and ends with the file its full text was written to (`error.txt` in `dir` when that
/// folder exists, otherwise a file in the temporary folder), or with where a recorded
/// run's session is (its `report.json` has the whole error); the cut keeps the start,
/// where the failed step and its most likely cause stand.
fn error_line(msg: &str, dir: Option<&Path>) -> String {
    if msg.chars().count() <= MAX_ERROR_LINE {
        return msg.to_string();
    }
    // A recorded run's failure ends with where its session is, whose report.json holds
    // the whole error (`images::failed_in_session`): that end is kept.
    let session = msg.rfind(" (session with ").filter(|&i| msg.len() - i <= MAX_ERROR_LINE / 2);
    let tail = if let Some(i) = session {
        format!(" ...{}", &msg[i..])
    } else {
        let path = match dir.filter(|d| d.is_dir()) {
            Some(d) => d.join("error.txt"),
            None => std::env::temp_dir().join(format!("headalign-error-{}.txt", std::process::id())),
        };
        match std::fs::write(&path, format!("{msg}\n")) {
            Ok(()) => format!(" ... (full message: {})", path.display()),
            Err(_) => " ...".to_string(),
        }
    };
    let room = MAX_ERROR_LINE.saturating_sub(tail.chars().count()).max(80);
    let mut cut: String = msg.chars().take(room).collect();
    if let Some(i) = cut.rfind(' ').filter(|&i| i > room / 2) {
        cut.truncate(i);
    }
    format!("{}{tail}", cut.trim_end_matches([' ', ':', ',', ';']))
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let dir = report_dir(&cli.command);
    let result = match cli.command {
        Command::Demo(a) => demo::run(&a),
        Command::Align(a) => align::run(&a),
        Command::Simulate(a) => simulate::run(&a),
        Command::Experiment(a) => headalign_eval::run(&a),
        Command::Replay(a) => replay::run(&a),
        Command::Run(a) => headcmd::run(&a),
        Command::Calibrate(a) => calibrate::run(&a),
        Command::Check(a) => check::run(&a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // One line naming the problem (the chain joined by ": ", repeated causes left
            // out; a cause that spans lines, e.g. a third-party parser's message, is folded
            // onto one).
            let msg = images::one_line(&e);
            let one_line: Vec<&str> = msg.lines().map(str::trim).filter(|l| !l.is_empty()).collect();
            let line = error_line(&one_line.join(" "), dir.as_deref());
            eprintln!("error: {line}");
            ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod error_line_tests {
    use super::*;

    /// A short message stays as it is; a long one is cut at a word to at most
    /// [`MAX_ERROR_LINE`] characters, names the file, and the file holds the whole text.
    #[test]
    fn long_messages_are_cut_and_kept() {
        assert_eq!(error_line("short: cause", None), "short: cause");
        let dir = std::env::temp_dir().join(format!("headalign-error-line-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let long = format!("step: the likely cause first; {}", "detail ".repeat(100));
        let line = error_line(&long, Some(&dir));
        assert!(line.chars().count() <= MAX_ERROR_LINE, "{line}");
        assert!(line.starts_with("step: the likely cause first") && line.contains("error.txt"), "{line}");
        let full = std::fs::read_to_string(dir.join("error.txt")).unwrap_or_default();
        assert_eq!(full.trim_end(), long.trim_end());
        std::fs::remove_dir_all(&dir).ok();
    }
}
