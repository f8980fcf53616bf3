//! Progress on stderr for long steps (reading a folder's images or a recording,
//! tracking a folder's views, the self-calibration of `calibrate`, a live head's motions
//! and captures in `run`): a bar over views, a spinner for a step of unknown length. Drawn only when stderr is a terminal (indicatif
//! hides them otherwise), so scripts, pipes and `--json` consumers see nothing; cleared
//! when the step ends or its function returns early with an error, so the results print
//! as before. No degrees of freedom, no units but views.

use std::time::Duration;

use headalign_platform::{
    Encoders, ImagingHead, Odometry, PlatformError, StereoCapture, StereoHead, StereoImages, Vehicle,
};
use indicatif::{ProgressBar, ProgressFinish, ProgressStyle};

/// A bar over `total` views, named `what`.
pub fn views(what: &str, total: usize) -> ProgressBar {
    let bar = ProgressBar::new(total as u64).with_finish(ProgressFinish::AndClear);
    if let Ok(style) = ProgressStyle::with_template("{prefix} [{wide_bar}] {pos}/{len} views {msg} {elapsed}")
    {
        bar.set_style(style.progress_chars("=> "));
    }
    bar.set_prefix(what.to_string());
    bar
}

/// A spinner with a message, ticking on its own while a step runs.
pub fn spinner(message: String) -> ProgressBar {
    let spin = ProgressBar::new_spinner().with_finish(ProgressFinish::AndClear);
    if let Ok(style) = ProgressStyle::with_template("{spinner} {msg} {elapsed}") {
        spin.set_style(style);
    }
    spin.set_message(message);
    spin.enable_steady_tick(Duration::from_millis(200));
    spin
}

/// A head (and base) whose every motion and capture is named on a spinner: a live run
/// waits on motors and cameras for minutes, and the spinner says what it waits for. Every
/// call is passed on unchanged (also the vehicle's odometry, which sessions record).
pub struct Narrated<'a, H> {
    head: &'a mut H,
    spin: ProgressBar,
    captures: usize,
}

impl<'a, H> Narrated<'a, H> {
    /// Narrate `head`'s calls under the name `what`.
    pub fn new(head: &'a mut H, what: &str) -> Self {
        Self { head, spin: spinner(format!("{what}: starting")), captures: 0 }
    }

    fn say(&self, doing: String) {
        self.spin.set_message(doing);
    }
}

impl<H: StereoHead> StereoHead for Narrated<'_, H> {
    fn image_size(&self) -> [u32; 2] {
        self.head.image_size()
    }

    fn read_encoders(&mut self) -> Result<Encoders, PlatformError> {
        self.head.read_encoders()
    }

    fn move_to(&mut self, target: &Encoders) -> Result<(), PlatformError> {
        self.say(format!(
            "moving the head to pan {:.2}, elevation {:.2}, verge {:.2} / {:.2} deg",
            target.pan, target.elevation, target.verge_left, target.verge_right
        ));
        self.head.move_to(target)
    }

    fn capture(&mut self) -> Result<StereoCapture, PlatformError> {
        self.captures += 1;
        self.say(format!("capture {}", self.captures));
        self.head.capture()
    }
}

impl<H: ImagingHead> ImagingHead for Narrated<'_, H> {
    fn capture_images(&mut self) -> Result<StereoImages, PlatformError> {
        self.captures += 1;
        self.say(format!("capture {} (both images)", self.captures));
        self.head.capture_images()
    }
}

impl<H: Vehicle> Vehicle for Narrated<'_, H> {
    fn drive(&mut self, distance_m: f64) -> Result<(), PlatformError> {
        self.say(format!("driving {distance_m:.2} m"));
        self.head.drive(distance_m)
    }

    fn steer_to(&mut self, encoder_deg: f64) -> Result<(), PlatformError> {
        self.say(format!("steering to {encoder_deg:.1} deg"));
        self.head.steer_to(encoder_deg)
    }

    fn read_steering(&mut self) -> Result<f64, PlatformError> {
        self.head.read_steering()
    }

    fn steer_by(&mut self, delta_deg: f64) -> Result<(), PlatformError> {
        self.say(format!("steering by {delta_deg:.1} deg"));
        self.head.steer_by(delta_deg)
    }

    fn last_odometry(&self) -> Option<Odometry> {
        self.head.last_odometry()
    }
}

/// Print a warning of a procedure on stderr as it arises (`warning: ...`).
pub fn warn(text: &str) {
    eprintln!("warning: {text}");
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A base that records what it was asked and reports odometry.
    #[derive(Default)]
    struct Base {
        driven: f64,
        steering: f64,
    }

    impl Vehicle for Base {
        fn drive(&mut self, distance_m: f64) -> Result<(), PlatformError> {
            self.driven += distance_m;
            Ok(())
        }
        fn steer_to(&mut self, encoder_deg: f64) -> Result<(), PlatformError> {
            self.steering = encoder_deg;
            Ok(())
        }
        fn read_steering(&mut self) -> Result<f64, PlatformError> {
            Ok(self.steering)
        }
        fn last_odometry(&self) -> Option<Odometry> {
            Some(Odometry { distance_m: self.driven, heading_deg: Some(1.5) })
        }
    }

    /// The narration passes every call and answer through unchanged, the odometry (which
    /// sessions record) included.
    #[test]
    fn narrated_calls_reach_the_base() {
        let mut base = Base::default();
        let mut n = Narrated::new(&mut base, "test");
        n.drive(0.25).unwrap();
        n.steer_by(4.0).unwrap();
        n.steer_by(-1.5).unwrap();
        assert_eq!(n.read_steering().unwrap(), 2.5);
        assert_eq!(n.last_odometry(), Some(Odometry { distance_m: 0.25, heading_deg: Some(1.5) }));
        drop(n);
        assert_eq!((base.driven, base.steering), (0.25, 2.5));
    }
}
