//! Self-calibrate a stereo rig from a folder of stereo views with `headalign::calibrate`
//! (the folder read by `headalign_io::folder`).
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
//! The folder is read by [`read_folder`], by the rules `headalign calibrate DIR` reads it
//! with: stereo pairs `left*.png` / `right*.png` (or `.jpg`, `.jpeg`; any case), the right
//! file named as the left one with `left` replaced by `right`, taken in name order, or an
//! image session (`headalign_io::folder` documents the rules). Without an argument the example first records such a folder from the simulator (three views: an
//! initial one, then 5 deg of elevation and 5 deg of pan) into a temporary folder, so it
//! runs out of the box and can print the true intrinsics beside the estimate. The
//! `headalign calibrate DIR` command does the same with more options (known lenses,
//! distortion, constraints, output files).
//!
//! `cargo run --release -p headalign-io --example calibrate_folder [-- DIR]` (about 10 s,
//! most of it rendering the simulated images).

use std::path::PathBuf;

use headalign::calibrate::{CalibrateOptions, calibrate_rig};
use headalign::observations::View;
use headalign::tracking::{FrontEndOptions, Tracker};
use headalign_geometry::camera::Intrinsics;
use headalign_io::folder::{FolderOptions, read_folder};
use headalign_platform::{ImagingHead, Joint, StereoHead};
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
    let pairs = read_folder(&dir, &FolderOptions::default(), &mut |_, _| ())?;

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
