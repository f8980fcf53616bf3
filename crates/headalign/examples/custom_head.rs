//! Implement `headalign::StereoHead` for your own head, and align it.
//!
//! Teaches the seam between the procedures and the hardware: the four methods of
//! [`StereoHead`], what each must do, and how errors travel. `MyHead` is a thin wrapper
//! that forwards to an inner head (here the simulator; on a real head, the driver of the
//! motors and the cameras' feature tracker). It adds what a real driver has to add: joint
//! limits, refusing non-finite commands with an error rather than a panic, and a log of
//! the calls. Then the verge/tilt procedure runs on it, unaware of what is underneath.
//!
//! A head whose cameras deliver only images implements
//! [`headalign_platform::ImagingHead`] (`capture_images`) and is wrapped in
//! [`headalign::tracking::TrackingHead`], which finds and tracks the features and provides
//! `capture`. A head behind another process speaks the JSON-lines protocol of
//! `docs/head-protocol.md` (`headalign_io::process_head` in the `headalign-io` crate).
//!
//! `cargo run --release -p headalign --example custom_head` (about a second).

use headalign::procedure::{VergeTiltOptions, VergeTiltRun};
use headalign::{Encoders, Joint, StereoCapture, StereoHead};
use headalign_platform::PlatformError;
use headalign_sim::{Scenario, SimulatedHead};

/// Your head. Here it forwards to a simulated head; replace `inner` by your driver.
struct MyHead {
    inner: SimulatedHead,
    /// Each joint's reachable readings, degrees.
    range_deg: [f64; 2],
    /// Calls, for the log.
    moves: usize,
    captures: usize,
}

impl StereoHead for MyHead {
    /// Image size `[width, height]` in pixels, the same for both cameras and for the whole
    /// run.
    fn image_size(&self) -> [u32; 2] {
        self.inner.image_size()
    }

    /// The joints' current readings in degrees, as the encoders report them (not the last
    /// command): the procedure trusts them, not what it asked for.
    fn read_encoders(&mut self) -> Result<Encoders, PlatformError> {
        self.inner.read_encoders()
    }

    /// Move all four joints to absolute readings (degrees) and return only when they are
    /// there. What the head cannot do is an error, never a panic: the procedure stops with
    /// it and the views captured so far stay available (`VergeTiltRun::views`).
    fn move_to(&mut self, target: &Encoders) -> Result<(), PlatformError> {
        if !target.is_finite() {
            return Err(PlatformError::InvalidCommand(format!("non-finite readings {target:?}")));
        }
        let [min_deg, max_deg] = self.range_deg;
        for joint in Joint::ALL {
            let target_deg = target.get(joint);
            if !(min_deg..=max_deg).contains(&target_deg) {
                return Err(PlatformError::OutOfRange { joint, target_deg, min_deg, max_deg });
            }
        }
        self.moves += 1;
        println!(
            "move {:>2}: pan {:+7.3} elevation {:+7.3} verge {:+7.3} {:+7.3}",
            self.moves, target.pan, target.elevation, target.verge_left, target.verge_right
        );
        self.inner.move_to(target)
    }

    /// Capture a stereo view at the current position: the readings at capture time and
    /// the tracked points of each image. A track id must name the same scene point in both
    /// images and in every view; pixels have (0, 0) at the centre of the top-left pixel.
    fn capture(&mut self) -> Result<StereoCapture, PlatformError> {
        let capture = self.inner.capture()?;
        self.captures += 1;
        println!(
            "capture {}: {} left, {} right points",
            self.captures,
            capture.left.len(),
            capture.right.len()
        );
        Ok(capture)
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let inner = SimulatedHead::new(Scenario { seed: 7, ..Scenario::default() })?;
    let mut head = MyHead { inner, range_deg: [-45.0, 45.0], moves: 0, captures: 0 };

    // The same call as for any head.
    let outcome = VergeTiltRun::default().run(&mut head, &VergeTiltOptions::default())?;
    let (aligned, sigma) = (outcome.solution.aligned_encoders, outcome.sigmas);
    println!(
        "\naligned readings (deg): elevation {:.3} +- {:.3}, verge left {:.3} +- {:.3}, verge right {:.3} +- {:.3}",
        aligned.elevation,
        sigma.elevation_deg,
        aligned.verge_left,
        sigma.verge_left_deg,
        aligned.verge_right,
        sigma.verge_right_deg
    );

    // Only the simulator knows the truth: the errors left after the procedure.
    let after = head.inner.alignment_errors(&head.inner.encoders());
    println!(
        "true alignment errors now (deg): verge left {:+.3}, verge right {:+.3}, elevation left {:+.3}",
        after.verge_err_l_deg, after.verge_err_r_deg, after.elev_err_l_deg
    );

    // A command outside the range is an error the caller sees, not a panic.
    let too_far = Encoders { elevation: 90.0, ..aligned };
    if let Err(e) = head.move_to(&too_far) {
        println!("refused: {e}");
    }
    Ok(())
}
