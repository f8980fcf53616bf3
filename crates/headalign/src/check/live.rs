//! The check of a live head (`headalign run --check-only`): a few stereo views captured at
//! and beside the head's current position, [`super::check_views`] on them, and the head
//! returned to where it was.
//!
//! # What it does
//!
//! 1. Reads the start readings.
//! 2. For each offset of [`LiveCheckOptions::moves_deg`] (pan and elevation, degrees,
//!    relative to the start; the default `(0, 0), (+3, 0), (-3, 0)`) moves there and
//!    captures a stereo pair. Pan and elevation turn both cameras together: the rig (its
//!    `right_from_left`, which the vergences set) is the same in every view, as the check
//!    assumes, while each view sees a different part of the scene.
//! 3. Moves back to the start readings (commanded exactly as read; also after a failed
//!    capture, before the error is returned) and reads the final readings.
//! 4. Checks the given calibration on the views ([`super::check_views`]: its module docs
//!    give the method, units and verdict).
//!
//! No degrees of freedom are estimated here. Units: degrees for the moves and readings.
//!
//! # Pitfalls
//!
//! - A head with reading noise returns to its commanded start, not to a reading equal to
//!   the start's to the last digit: [`LiveCheck::returned`] compares within
//!   [`LiveCheckOptions::return_tolerance_deg`].
//! - A move that leaves the scene (a blank wall beside the start) gives a pair with few
//!   matches; the check pools the pairs, so the others still count.

use headalign_platform::{Encoders, ImagingHead, Joint, PlatformError, StereoImages};
use serde::Serialize;

use super::{CheckError, CheckOptions, CheckReport, check_views};
use crate::AlignError;
use crate::calibrate::views::StereoViews;
use crate::calibration::StereoCalibration;

/// The options of [`check_live_head`].
#[derive(Debug, Clone)]
pub struct LiveCheckOptions {
    /// The check. Default [`CheckOptions::default`].
    pub check: CheckOptions,
    /// The views' `(pan, elevation)` offsets from the start, degrees. Default `(0, 0),
    /// (3, 0), (-3, 0)`.
    pub moves_deg: Vec<[f64; 2]>,
    /// The largest difference of a final reading from its start reading that counts as
    /// returned, degrees. Default 1e-6 (a head that reads what it was commanded).
    pub return_tolerance_deg: f64,
}

impl Default for LiveCheckOptions {
    fn default() -> Self {
        Self {
            check: CheckOptions::default(),
            moves_deg: vec![[0.0, 0.0], [3.0, 0.0], [-3.0, 0.0]],
            return_tolerance_deg: 1e-6,
        }
    }
}

impl LiveCheckOptions {
    /// An error naming the first bad option.
    pub fn validate(&self) -> Result<(), CheckError> {
        self.check.validate()?;
        if self.moves_deg.is_empty() {
            return Err(CheckError::InvalidOption("the live check needs at least one view".into()));
        }
        if let Some(m) = self.moves_deg.iter().find(|m| !m.iter().all(|v| v.is_finite() && v.abs() <= 90.0)) {
            return Err(CheckError::InvalidOption(format!("a move must be within +-90 deg, got {m:?}")));
        }
        let t = self.return_tolerance_deg;
        if !(t.is_finite() && t >= 0.0) {
            return Err(CheckError::InvalidOption(format!("the return tolerance must be >= 0, got {t}")));
        }
        Ok(())
    }
}

/// What [`check_live_head`] found.
#[derive(Debug, Clone, Serialize)]
pub struct LiveCheck {
    /// The check of the captured views.
    pub report: CheckReport,
    /// The readings before the first move.
    pub start: Encoders,
    /// The readings after the return.
    pub end: Encoders,
    /// Whether every final reading is within the tolerance of its start reading.
    pub returned: bool,
}

/// Capture the views of `options` on `head`, return it to its start, and check `given`
/// on the views (module docs).
pub fn check_live_head<H: ImagingHead + ?Sized>(
    head: &mut H,
    given: &StereoCalibration,
    options: &LiveCheckOptions,
) -> Result<LiveCheck, CheckError> {
    options.validate()?;
    let device = |e: PlatformError, what: &str| CheckError::Align(AlignError::from(e).in_step(what));
    let start = head.read_encoders().map_err(|e| device(e, "reading the start position"))?;
    let captured = capture_views(head, &start, &options.moves_deg);
    // Back to the start whatever happened, then the capture's error if any.
    let back = head.move_to(&start).map_err(|e| device(e, "returning to the start position"));
    let views = captured?;
    back?;
    let end = head.read_encoders().map_err(|e| device(e, "reading the final position"))?;
    let returned =
        Joint::ALL.iter().all(|&j| (end.get(j) - start.get(j)).abs() <= options.return_tolerance_deg);
    let report = check_views(StereoViews::Images(&views), given, &options.check)?;
    Ok(LiveCheck { report, start, end, returned })
}

/// One named pair per `(pan, elevation)` offset from `start`.
fn capture_views<H: ImagingHead + ?Sized>(
    head: &mut H,
    start: &Encoders,
    moves: &[[f64; 2]],
) -> Result<Vec<(String, StereoImages)>, CheckError> {
    moves
        .iter()
        .map(|&[pan, elevation]| {
            let target = start.moved(Joint::Pan, pan).moved(Joint::Elevation, elevation);
            let name = format!("pan{pan:+}-elevation{elevation:+}");
            let step =
                |e: PlatformError| CheckError::Align(AlignError::from(e).in_step(&format!("view {name}")));
            head.move_to(&target).map_err(step)?;
            let images = head.capture_images().map_err(step)?;
            Ok((name, images))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use headalign_platform::{StereoCapture, StereoHead};

    use super::*;
    use crate::calibration::{IntrinsicSigmas, TranslationUnit};

    /// A head that moves exactly and whose second capture fails.
    struct Flaky {
        at: Encoders,
        captures: usize,
    }

    impl StereoHead for Flaky {
        fn image_size(&self) -> [u32; 2] {
            [64, 48]
        }
        fn read_encoders(&mut self) -> Result<Encoders, PlatformError> {
            Ok(self.at)
        }
        fn move_to(&mut self, target: &Encoders) -> Result<(), PlatformError> {
            self.at = *target;
            Ok(())
        }
        fn capture(&mut self) -> Result<StereoCapture, PlatformError> {
            Err(PlatformError::Device("no point mode".into()))
        }
    }

    impl ImagingHead for Flaky {
        fn capture_images(&mut self) -> Result<StereoImages, PlatformError> {
            self.captures += 1;
            if self.captures == 2 {
                return Err(PlatformError::Device("camera unplugged".into()));
            }
            let image = headalign_vision::GrayImage::new(64, 48, vec![0; 64 * 48])
                .map_err(|e| PlatformError::Device(e.to_string()))?;
            StereoImages::new(self.at, image.clone(), image)
        }
    }

    /// A failed capture is reported with its view, after the head went back to its start.
    #[test]
    fn a_failed_capture_still_returns_the_head() {
        let start = Encoders { pan: 1.5, elevation: -2.0, verge_left: 3.0, verge_right: -3.0 };
        let mut head = Flaky { at: start, captures: 0 };
        let k = headalign_geometry::camera::Intrinsics::new(50.0, 50.0, 32.0, 24.0);
        let given = StereoCalibration {
            image_size: [64, 48],
            left: k,
            right: k,
            sigmas: [IntrinsicSigmas::default(); 2],
            right_from_left: nalgebra::Isometry3::translation(-0.1, 0.0, 0.0),
            unit: TranslationUnit::Metres,
            distortion: Default::default(),
        };
        let e = check_live_head(&mut head, &given, &LiveCheckOptions::default()).unwrap_err();
        // The step names the view; the device's words are its cause.
        let mut text = e.to_string();
        let mut cause = std::error::Error::source(&e);
        while let Some(c) = cause {
            text.push_str(&format!(": {c}"));
            cause = c.source();
        }
        assert!(text.contains("pan+3") && text.contains("camera unplugged"), "{text}");
        assert_eq!(head.at, start);
    }

    #[test]
    fn bad_options_are_errors() {
        let none = LiveCheckOptions { moves_deg: Vec::new(), ..LiveCheckOptions::default() };
        assert!(none.validate().is_err());
        let far = LiveCheckOptions { moves_deg: vec![[120.0, 0.0]], ..LiveCheckOptions::default() };
        assert!(far.validate().is_err());
        assert!(LiveCheckOptions::default().validate().is_ok());
    }
}
