//! Self-calibrate a stereo rig from a folder of stereo views with `headalign::calibrate`.
//!
//! Teaches the image route of the library: load stereo pairs, track features through them
//! with [`Tracker`] (the first view is the reference; a track id then names the same scene
//! point in every image), and hand the tracked views to [`calibrate_rig`], which finds
//! both cameras' intrinsics, the rig's relative pose and the motions between the views
//! from the images alone, each with its sigma. The views must be related by rigid motions
//! of the whole rig (head rotations about two different axes, robot drives, a hand-held
//! rig moved around) in a scene with depth: a flat target is a degenerate case, reported
//! as such.
//!
//! The folder holds stereo pairs `left*.png` / `right*.png` (or `.jpg`), the right file
//! named as the left one with `left` replaced by `right`, taken in name order. Without an
//! argument the example first records such a folder from the simulator (three views: an
//! initial one, then 5 deg of elevation and 5 deg of pan) into a temporary folder, so it
//! runs out of the box and can print the true intrinsics beside the estimate. The
//! `headalign calibrate DIR` command does the same with more options (known lenses,
//! distortion, constraints, output files).
//!
//! `cargo run --release -p headalign --example calibrate_folder [-- DIR]` (about 10 s,
//! most of it rendering the simulated images).

use std::path::{Path, PathBuf};

use headalign::calibrate::{CalibrateOptions, calibrate_rig};
use headalign::observations::View;
use headalign::tracking::{FrontEndOptions, Tracker};
use headalign_geometry::camera::Intrinsics;
use headalign_platform::{Encoders, GrayImage, ImagingHead, Joint, StereoHead, StereoImages};
use headalign_sim::{Scenario, SimulatedHead};

type Error = Box<dyn std::error::Error>;

fn main() -> Result<(), Error> {
    let (dir, truth) = match std::env::args_os().nth(1) {
        Some(arg) => (PathBuf::from(arg), None),
        None => {
            let (dir, truth) = record_simulated_folder()?;
            (dir, Some(truth))
        }
    };
    let pairs = read_pairs(&dir)?;

    // Track features through the views, in order.
    let mut tracker = Tracker::new(FrontEndOptions::default())?;
    let mut views = Vec::new();
    for (name, images) in &pairs {
        let (capture, _) = tracker.track(images, name)?;
        views.push(View { name: name.clone(), capture });
    }

    // Self-calibrate from the rig's motions.
    let cal = calibrate_rig(&views, &CalibrateOptions::default())?;

    let (state, cov) = (&cal.bundle.state, &cal.bundle.covariance);
    println!("{} views from {}", views.len(), dir.display());
    for (side, k, t) in
        [("left", &state.left, truth.map(|t| t[0])), ("right", &state.right, truth.map(|t| t[1]))]
    {
        let sigma =
            |p: &str| cov.sigma(&format!("{side}.{p}")).map_or("-".to_string(), |s| format!("{s:.2}"));
        println!(
            "{side:<5} fx {:8.2} +- {:5}  fy {:8.2} +- {:5}  cx {:7.2} +- {:5}  cy {:7.2} +- {:5}  skew {:+.3}",
            k.fx,
            sigma("fx"),
            k.fy,
            sigma("fy"),
            k.cx,
            sigma("cx"),
            k.cy,
            sigma("cy"),
            k.skew
        );
        if let Some(t) = t {
            println!(
                "{:<5} fx {:8.2}           fy {:8.2}           cx {:7.2}           cy {:7.2}   (truth)",
                "", t.fx, t.fy, t.cx, t.cy
            );
        }
    }
    let rig = &state.right_from_left;
    let t = rig.translation.vector.normalize();
    println!(
        "rig: right camera rotated {:.3} deg from the left, baseline direction ({:+.3}, {:+.3}, {:+.3}) in the right camera",
        rig.rotation.angle().to_degrees(),
        t.x,
        t.y,
        t.z
    );
    let r = &cal.report;
    for m in &r.motions {
        println!("motion to '{}': {:.2} deg, {} inliers", m.view, m.rotation_deg, m.inliers);
    }
    println!("final RMS {:.3} px over {} observations", r.final_rms_px, r.bundle_observations);
    for w in &r.warnings {
        println!("warning: {w}");
    }
    Ok(())
}

/// The stereo pairs of `dir` (module docs), named by the left file's stem.
fn read_pairs(dir: &Path) -> Result<Vec<(String, StereoImages)>, Error> {
    let entries =
        std::fs::read_dir(dir).map_err(|e| format!("cannot read folder '{}': {e}", dir.display()))?;
    let mut names: Vec<String> = entries
        .filter_map(Result::ok)
        .filter_map(|e| e.file_name().into_string().ok())
        .filter(|n| n.contains("left") && (n.ends_with(".png") || n.ends_with(".jpg")))
        .collect();
    names.sort();
    let load = |name: &str| {
        let path = dir.join(name);
        GrayImage::load(&path).map_err(|e| format!("'{}': {e}", path.display()))
    };
    let mut pairs = Vec::new();
    for name in names {
        let right = name.replacen("left", "right", 1);
        let images = StereoImages::new(Encoders::default(), load(&name)?, load(&right)?)?;
        let stem = name.rsplit_once('.').map_or(name.as_str(), |(stem, _)| stem);
        pairs.push((stem.to_string(), images));
    }
    if pairs.len() < 2 {
        let n = pairs.len();
        return Err(format!("'{}' holds {n} stereo pair(s) (left*.png + right*.png); calibration needs 2 or more views related by rig motions", dir.display()).into());
    }
    Ok(pairs)
}

/// Record three simulated views into a new temporary folder (module docs): the folder and
/// the true intrinsics `[left, right]`.
fn record_simulated_folder() -> Result<(PathBuf, [Intrinsics; 2]), Error> {
    let dir = std::env::temp_dir().join(format!("headalign-calibrate-folder-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let mut head = SimulatedHead::new(Scenario { seed: 2, ..Scenario::default() })?;
    let e0 = head.read_encoders()?;
    for (i, readings) in [e0, e0.moved(Joint::Elevation, 5.0), e0.moved(Joint::Pan, 5.0)].iter().enumerate() {
        head.move_to(readings)?;
        let pair = head.capture_images()?;
        pair.left.save(&dir.join(format!("left{i:02}.png")))?;
        pair.right.save(&dir.join(format!("right{i:02}.png")))?;
    }
    println!(
        "recorded 3 simulated stereo views into {} (give it as DIR to calibrate it again)",
        dir.display()
    );
    let truth = head.truth();
    Ok((dir, [truth.left, truth.right]))
}
