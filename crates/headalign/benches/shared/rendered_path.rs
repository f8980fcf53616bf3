//! The rendered rig path shared by the `sequence` and `calibrate` benchmarks: a rig of
//! 752x480 (EuRoC-like focal lengths of about 458 px, 0.11 m baseline, no lens distortion)
//! carried through the simulator's textured room, per view 2 deg further about the
//! vertical, the pitch swinging by +-6 deg and the height by +-0.15 m (the `sequence`
//! benchmark's module docs). No degrees of freedom are estimated here; angles in degrees,
//! lengths in metres. Pitfall: the files are rendered once and reused by later runs, so a
//! change of the path or the scenario needs a fresh directory.

use std::path::Path;
use std::time::Instant;

use headalign_geometry::camera::Intrinsics;
use headalign_platform::ImagingHead;
use headalign_sim::rigmotion::screw_motion;
use headalign_sim::{Scenario, SimulatedHead};
use nalgebra::Vector3;

/// A benchmark's error.
pub type Error = Box<dyn std::error::Error + Send + Sync>;

/// The simulated rig.
pub fn scenario() -> Scenario {
    Scenario {
        seed: 7,
        image_size: [752, 480],
        left: Intrinsics::new(458.0, 457.0, 367.0, 248.0),
        right: Intrinsics::new(457.0, 456.0, 380.0, 255.0),
        baseline_m: 0.11,
        ..Scenario::default()
    }
}

/// The rig's pose at view `i`, robot frame.
pub fn pose(i: usize) -> nalgebra::Isometry3<f64> {
    let t = i as f64;
    let turn = screw_motion(-Vector3::y(), 2.0 * t, 0.15 * (std::f64::consts::TAU * t / 60.0).sin());
    let tilt = screw_motion(Vector3::x(), 6.0 * (std::f64::consts::TAU * t / 40.0).sin(), 0.0);
    turn * tilt
}

/// Render the first `n` views into `dir` as `leftNN.png` / `rightNN.png` with `digits`
/// digits, unless the last one is there already; progress on stderr every 20 views.
pub fn render(dir: &Path, n: usize, digits: usize) -> Result<(), Error> {
    let name = |side: &str, i: usize| dir.join(format!("{side}{i:0digits$}.png"));
    if n == 0 || name("right", n - 1).exists() {
        return Ok(());
    }
    std::fs::create_dir_all(dir)?;
    let mut head = SimulatedHead::new(scenario())?;
    let t = Instant::now();
    for i in 0..n {
        head.set_world_from_robot(pose(i));
        let pair = head.capture_images()?;
        pair.left.save(&name("left", i))?;
        pair.right.save(&name("right", i))?;
        if i % 20 == 19 {
            eprintln!("rendered {} views ({:.0} s)", i + 1, t.elapsed().as_secs_f64());
        }
    }
    Ok(())
}
