//! The cost of self-calibration from a sequence against its length: the curve for 25,
//! 50, 100 and 200 views of 752x480 (issue 32, item 1: linear, 200 views in at most 60 s
//! on 2 cores).
//!
//! The recording: the simulator renders a rig (752x480, EuRoC-like focal lengths of about
//! 458 px, 0.11 m baseline, no lens distortion) carried through its textured room: per
//! view 2 deg further about the vertical, the pitch swinging by +-6 deg and the height by
//! +-0.15 m, so that every view overlaps only its neighbours (the field of view is 78 deg
//! wide; after 200 views the rig has turned 400 deg). The 200 views are rendered once
//! into `$CARGO_TARGET_TMPDIR/sequence-752x480/` (stereo pairs `leftNNN.png`, reused by
//! later runs), and the folders `sequence-752x480-N/` hold the first `N` of them (hard
//! links), so that `headalign calibrate FOLDER` repeats each measurement.
//!
//! What is timed, per length: exactly what `headalign calibrate FOLDER` does after
//! reading the PNG files (which is not timed) for more than 20 views: the front end
//! through the views in order ([`track_views`]: corners, stereo matching, linking to the
//! previous view, patch refinement) and the sequence chain ([`calibrate_tracked`]:
//! keyframes, view graph, F, 3D homographies, starts, adjustments, report) at the default
//! 1500 corners per image. The command would also re-detect at 3000 corners if the result
//! were weak: the table says whether it is. Wall time, and the process's CPU time over
//! the same span (user + system, all threads: the corner detection runs on every core), from
//! `/proc/self/stat` (Linux; "n/a" elsewhere).
//!
//! `cargo bench -p headalign --bench sequence` (add `-- --views 25,50` for other
//! lengths). Rendering the 200 views takes a few minutes the first time.

use std::path::{Path, PathBuf};
use std::time::Instant;

use headalign::calibrate::{CalibrateOptions, calibrate_tracked, track_views, weak_data};
use headalign::tracking::FrontEndOptions;
use headalign_platform::{GrayImage, StereoImages};

#[path = "shared/rendered_path.rs"]
mod rendered_path;
use rendered_path::{Error, render, scenario};

/// Views of the longest sequence rendered.
const RENDERED: usize = 200;

/// The first `n` views of the rendered sequence, as a folder of their own (hard links)
/// and in memory.
fn views(all: &Path, n: usize) -> Result<(PathBuf, Vec<(String, StereoImages)>), Error> {
    let name = format!("{}-{n}", all.file_name().and_then(|s| s.to_str()).unwrap_or("sequence"));
    let dir = all.with_file_name(name);
    std::fs::create_dir_all(&dir)?;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let mut images = Vec::new();
        for side in ["left", "right"] {
            let file = format!("{side}{i:03}.png");
            if !dir.join(&file).exists() {
                std::fs::hard_link(all.join(&file), dir.join(&file))?;
            }
            images.push(GrayImage::load(&dir.join(&file))?);
        }
        let right = images.pop().ok_or("no image")?;
        let left = images.pop().ok_or("no image")?;
        out.push((format!("left{i:03}"), StereoImages::new(Default::default(), left, right)?));
    }
    Ok((dir, out))
}

/// CPU time (user + system, all threads) of this process so far, seconds (Linux).
fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command name (which may hold spaces) start after the last ')'.
    let rest = stat.get(stat.rfind(')')? + 2..)?;
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let (utime, stime): (f64, f64) = (fields.get(11)?.parse().ok()?, fields.get(12)?.parse().ok()?);
    // Linux reports these in clock ticks of USER_HZ, 100 per second on every architecture
    // it supports.
    Some((utime + stime) / 100.0)
}

fn main() -> Result<(), Error> {
    let mut lengths = vec![25, 50, 100, 200];
    let args: Vec<String> = std::env::args().collect();
    if let Some(i) = args.iter().position(|a| a == "--views") {
        let list = args.get(i + 1).ok_or("--views needs a list such as 25,50")?;
        lengths = list.split(',').map(str::parse).collect::<Result<_, _>>()?;
    }
    if lengths.iter().any(|&n| n == 0 || n > RENDERED) {
        return Err(format!("lengths must be in 1..={RENDERED}").into());
    }
    let all = Path::new(env!("CARGO_TARGET_TMPDIR")).join("sequence-752x480");
    render(&all, RENDERED, 3)?;
    let options = CalibrateOptions::default();
    println!(
        "views  keyframes  segments  wall s  cpu s  front end wall s  calibration wall s  wall ms/view  f err %  weak  folder"
    );
    let cpu_text =
        |a: Option<f64>, b: Option<f64>| b.zip(a).map_or("n/a".to_string(), |(b, a)| format!("{:.1}", b - a));
    for n in lengths {
        let (dir, images) = views(&all, n)?;
        let (wall0, cpu0) = (Instant::now(), cpu_seconds());
        let tracked = track_views(&images, &FrontEndOptions::default(), &options)?;
        let front = wall0.elapsed().as_secs_f64();
        let cal = calibrate_tracked(tracked, None, &options)?;
        let wall = wall0.elapsed().as_secs_f64();
        let cpu = cpu_text(cpu0, cpu_seconds());
        let truth = scenario().left;
        let f_err = 100.0 * (cal.bundle.state.left.fx - truth.fx) / truth.fx;
        let (keyframes, segments) = cal
            .report
            .sequence
            .as_ref()
            .map_or((cal.report.views.len(), 1), |s| (s.keyframes, s.segments.len()));
        println!(
            "{n:5}  {keyframes:9}  {segments:8}  {wall:6.1}  {cpu:>5}  {front:16.1}  {:18.1}  {:12.0}  {f_err:+7.2}  {:>4}  {}",
            wall - front,
            1000.0 * wall / n as f64,
            if weak_data(&cal.report, &options) { "yes" } else { "no" },
            dir.display()
        );
    }
    Ok(())
}
