//! Pan alignment without calibration: fixate the epipole of a forward drive (paper
//! section 4, "simply fixate on the epipole itself", with the section 5 fixation loop).
//!
//! What it does: drive forward and back, find the epipole `e` of the left images (the
//! focus of expansion; 2-point RANSAC on flow lines and LM, [`translation_from_flow`],
//! with a guessed `K` whose only role is to parametrise `e`: the flow-line residual is in
//! pixels, so `e` does not depend on the guess), then pan by `atan((u_e - u_0) / alpha)`
//! towards the target column `u_0` (default the image centre). `alpha` starts
//! overestimated (1.5 image widths), so the first move undershoots (section 5), and is
//! re-estimated after each move from the epipole's shift: with `a`, `b` the offsets before
//! and after a pan of `theta` (`T = tan theta`), `b / alpha = tan(atan(a / alpha) - theta)`
//! gives `T alpha^2 + (b - a) alpha + a b T = 0`, the root nearest `(a - b) / T`. The sign
//! of the pan joint (which way a positive reading turns the image) is learnt the same way.
//! It stops when `|u_e - u_0| <= tolerance_px` (one degree of freedom: only the column
//! is fixated; the row of `e` is the elevation check).
//!
//! Units: pixels for image quantities, degrees for joint moves.
//!
//! Pitfalls: it aligns the left camera's optical axis (not the mean of both) to the
//! direction of travel, up to the angle between the optical axis and the target column
//! (`(c_x - u_0) / f_x`, about 0.5 deg for a principal point 6 px off centre); it needs a
//! straight wheel (no rotation is removed: a turn during the drive shifts `e`), and a
//! drive long enough for the scene depth ([`AlignError::DriveTooShort`]).

use std::collections::HashMap;

use headalign_geometry::camera::Intrinsics;
use headalign_geometry::translation::{TranslationOptions, translation_from_flow};
use headalign_platform::{Encoders, Joint, StereoHead, Vehicle};
use serde::Serialize;

use crate::error::{AlignError, StepContext};

/// Shift of the epipole below which a move does not update `alpha`, pixels.
const MIN_SHIFT_PX: f64 = 20.0;

/// Options of [`align_pan_by_fixation`].
#[derive(Debug, Clone, PartialEq)]
pub struct PanFixationOptions {
    /// Forward drive, metres. Default 0.10.
    pub drive_m: f64,
    /// Target column, pixels. Default `None`: the image centre `(w - 1) / 2`.
    pub target_u_px: Option<f64>,
    /// Starting focal length guess, as a multiple of the image width (overestimated on
    /// purpose). Default 1.5.
    pub focal_guess_widths: f64,
    /// Stop when the epipole is this close to the target column, pixels. Default 1.
    pub tolerance_px: f64,
    /// Most drives. Default 6.
    pub max_drives: usize,
    /// Largest single pan move, degrees (an epipole near infinity asks for 90). Default 30.
    pub max_move_deg: f64,
    /// Smallest median flow accepted, pixels. Default 2.
    pub min_flow_px: f64,
    /// Epipole estimation. Default [`TranslationOptions::default`].
    pub translation: TranslationOptions,
}

impl Default for PanFixationOptions {
    fn default() -> Self {
        Self {
            drive_m: 0.10,
            target_u_px: None,
            focal_guess_widths: 1.5,
            tolerance_px: 1.0,
            max_drives: 6,
            max_move_deg: 30.0,
            min_flow_px: 2.0,
            translation: TranslationOptions::default(),
        }
    }
}

impl PanFixationOptions {
    /// Check the options.
    pub fn validate(&self) -> Result<(), AlignError> {
        let pos = |v: f64| v.is_finite() && v > 0.0;
        if !(pos(self.drive_m)
            && pos(self.focal_guess_widths)
            && pos(self.tolerance_px)
            && pos(self.max_move_deg)
            && self.max_move_deg < 90.0
            && self.min_flow_px >= 0.0
            && self.max_drives > 0
            && self.target_u_px.is_none_or(f64::is_finite))
        {
            return Err(AlignError::InvalidOption(format!("pan fixation options out of range: {self:?}")));
        }
        self.translation.validate().step("pan fixation options")
    }
}

/// One drive of the fixation loop.
#[derive(Debug, Clone, Serialize)]
pub struct PanFixationStep {
    /// Epipole (column, row), pixels; `None` when it lies at infinity.
    pub epipole_px: Option<[f64; 2]>,
    /// Focal length in use for the next move, pixels.
    pub alpha_px: f64,
    /// Pan move made after this drive, degrees (0 on the last).
    pub pan_move_deg: f64,
    /// Median flow, pixels.
    pub median_flow_px: f64,
}

/// Result of [`align_pan_by_fixation`].
#[derive(Debug, Clone, Serialize)]
pub struct PanFixationOutcome {
    /// Every drive.
    pub steps: Vec<PanFixationStep>,
    /// Whether the epipole reached the target column within the tolerance.
    pub converged: bool,
    /// Head readings at the end.
    pub final_encoders: Encoders,
}

/// The positive root of `T a^2 + (b - a) alpha + a b T = 0` nearest `(a - b) / T`
/// (module docs); `None` when the move told nothing.
fn alpha_from_shift(a: f64, b: f64, t: f64) -> Option<f64> {
    if t.abs() < 1e-12 || (a - b).abs() < 1e-9 {
        return None;
    }
    let disc = (b - a).powi(2) - 4.0 * t * t * a * b;
    let linear = (a - b) / t;
    let roots = if disc >= 0.0 {
        let s = disc.sqrt();
        vec![((a - b) + s) / (2.0 * t), ((a - b) - s) / (2.0 * t)]
    } else {
        vec![linear]
    };
    roots
        .into_iter()
        .filter(|r| r.is_finite() && r.abs() > 0.0)
        .min_by(|p, q| (p - linear).abs().total_cmp(&(q - linear).abs()))
}

/// Fixate the epipole of a forward drive with the pan joint (module docs).
pub fn align_pan_by_fixation<R: StereoHead + Vehicle>(
    robot: &mut R,
    options: &PanFixationOptions,
) -> Result<PanFixationOutcome, AlignError> {
    options.validate()?;
    let [w, h] = robot.image_size();
    let (w, h) = (f64::from(w), f64::from(h));
    let u0 = options.target_u_px.unwrap_or((w - 1.0) / 2.0);
    let guess = options.focal_guess_widths * w;
    let k = Intrinsics { fx: guess, fy: guess, skew: 0.0, cx: u0, cy: (h - 1.0) / 2.0 };
    // Signed focal length: positive when a positive pan move shifts the epipole to
    // smaller columns (learnt from the first move).
    let mut alpha = guess;
    let mut steps: Vec<PanFixationStep> = Vec::new();
    let mut last: Option<(f64, f64)> = None; // (offset before the move, tan of the move)
    // Moves are made from the last commanded readings (read once), not from fresh noisy
    // reads: those would move the other joints by their read noise at every step.
    let mut commanded = robot.read_encoders()?;
    for _ in 0..options.max_drives {
        let before = robot.capture()?;
        robot.drive(options.drive_m)?;
        let after = robot.capture()?;
        robot.drive(-options.drive_m)?;
        let la: HashMap<u64, _> = after.left.iter().map(|o| (o.track, o.pixel)).collect();
        let flow: Vec<_> =
            before.left.iter().filter_map(|o| la.get(&o.track).map(|p| (o.pixel, *p))).collect();
        let est = translation_from_flow(&k, &flow, &options.translation).step("pan fixation epipole")?;
        if est.median_flow_px < options.min_flow_px {
            return Err(AlignError::DriveTooShort {
                median_flow_px: est.median_flow_px,
                min_flow_px: options.min_flow_px,
            });
        }
        let e = est.epipole;
        let finite = e.z.abs() > 1e-12 * e.norm();
        let offset = if finite { e.x / e.z - u0 } else { f64::INFINITY.copysign(e.x * e.z.signum()) };
        // Small moves measure alpha poorly (the epipole's own noise over a shift of a
        // few pixels): update only on shifts of at least `MIN_SHIFT_PX` or to learn the
        // sign (the first move of an overestimated alpha).
        if let (Some((a, t)), true) = (last, finite)
            && let Some(new) = alpha_from_shift(a, offset, t)
            && ((a - offset).abs() >= MIN_SHIFT_PX || new.signum() != alpha.signum())
        {
            alpha = new;
        }
        let epipole_px = finite.then(|| [e.x / e.z, e.y / e.z]);
        if finite && offset.abs() <= options.tolerance_px {
            steps.push(PanFixationStep {
                epipole_px,
                alpha_px: alpha,
                pan_move_deg: 0.0,
                median_flow_px: est.median_flow_px,
            });
            return Ok(PanFixationOutcome { steps, converged: true, final_encoders: robot.read_encoders()? });
        }
        let max = options.max_move_deg.to_radians();
        let theta =
            if finite { (offset / alpha).atan().clamp(-max, max) } else { max.copysign(offset * alpha) };
        commanded = commanded.moved(Joint::Pan, theta.to_degrees());
        robot.move_to(&commanded)?;
        last = finite.then_some((offset, theta.tan()));
        steps.push(PanFixationStep {
            epipole_px,
            alpha_px: alpha,
            pan_move_deg: theta.to_degrees(),
            median_flow_px: est.median_flow_px,
        });
    }
    Ok(PanFixationOutcome { steps, converged: false, final_encoders: robot.read_encoders()? })
}

#[cfg(test)]
mod tests {
    use super::*;
    use headalign_sim::{Scenario, SimulatedRobot};

    /// The focal length from one move, exact for any sign convention.
    #[test]
    fn alpha_from_shift_is_exact() {
        for alpha in [-900.0, -700.0, 650.0, 1200.0] {
            for (phi, theta) in [(0.3f64, 0.1f64), (-0.2, -0.25), (0.05, 0.4)] {
                let a = alpha * phi.tan();
                let b = alpha * (phi - theta).tan();
                let got = alpha_from_shift(a, b, theta.tan()).unwrap();
                assert!((got - alpha).abs() < 1e-9 * alpha.abs(), "{alpha} {phi} {theta}: {got}");
            }
        }
        assert!(alpha_from_shift(3.0, 3.0, 0.1).is_none());
    }

    /// Noise-free, straight wheel, no calibration: the direction of travel ends within
    /// the tolerance (1 px) of the target column in the left camera (checked with the
    /// true camera; 1.05 px allows for the epipole's rounding).
    #[test]
    fn fixating_the_epipole_aligns_the_left_camera() {
        for seed in [1u64, 2, 5] {
            let s = Scenario {
                seed,
                noise_px: 0.0,
                outlier_fraction: 0.0,
                near_panels: Scenario::ROBOT_NEAR_PANELS,
                ..Scenario::default()
            };
            let mut robot = SimulatedRobot::new(s).unwrap();
            let zero = robot.truth().steer_zero_deg;
            robot.steer_to(zero).unwrap();
            let out = align_pan_by_fixation(&mut robot, &PanFixationOptions::default()).unwrap();
            assert!(out.converged, "seed {seed}: {out:?}");
            let enc = robot.head().encoders();
            let (robot_from_left, _) = robot.head().world_from_cameras(&enc);
            let travel = robot_from_left.inverse().rotation * nalgebra::Vector3::z();
            let k = robot.head().truth().left;
            let u = k.fx * travel.x / travel.z + k.skew * travel.y / travel.z + k.cx;
            assert!(travel.z > 0.0 && (u - 383.5).abs() < 1.05, "seed {seed}: column {u}: {out:?}");
        }
    }
}
