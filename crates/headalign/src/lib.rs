//! # headalign
//!
//! Self-alignment and self-calibration of an active stereo camera head from images alone
//! (paper: "Active Visual Alignment of a Mobile Stereo Camera Platform"; conventions:
//! `docs/conventions.md`). This crate holds the procedures; it sees the head only through the
//! [`headalign_platform::StereoHead`] trait and does its mathematics in
//! `headalign-geometry`.
//!
//! - [`observations`]: the stereo [`observations::View`] every procedure consumes.
//! - [`verge_tilt`]: the verge/tilt estimation core (F, frame, 3D homographies, linear
//!   self-calibration, rig bundle adjustment).
//! - [`alignment`]: exact aligned encoder readings from the calibrated head, measurement of
//!   cameras by resection.
//! - [`rig`]: the kernel both calibration routes share (lens models and their choice,
//!   known lenses, checks of the fit against the data).
//! - [`calibrate`]: self-calibration of a stereo rig from general rig motions (one
//!   general motion with constraints, or two rotations about different axes).
//! - [`procedure`]: the verge/tilt procedure over any `StereoHead`; [`plan`]: the views it
//!   captures.
//! - [`check`]: the targetless health check of a given stereo calibration (rotation
//!   change with sigmas, depth error, verdict).
//! - [`calibration`]: a calibrated stereo pair ([`calibration::StereoCalibration`]) with
//!   its rectification.
//! - [`image_mode`]: the procedure on images through the front end (verging first) and the
//!   robot stages on images, over any `ImagingHead`.
//! - [`robot`]: the robot stages (pan, steering, floor) and their driver ([`robot::stages`]),
//!   pan alignment without calibration
//!   by fixating a drive's epipole ([`robot::pan_fixation`]) and one-motion alignment
//!   ([`robot::one_motion`]).
//! - [`fixation`]: verging and fixating with no calibration; [`tracking`]: the tracker;
//!   [`timing`]: the seconds a calibration spends per stage.
//! - [`facing_plane`]: the route facing a plane or a scene too far for stereo depth.
//!
//! Aligning a simulated head (`headalign-sim`; any [`StereoHead`] will do): the verge/tilt
//! procedure captures views at small elevation, pan and vergence turns, self-calibrates the
//! cameras from them and returns the encoder readings at which the head is aligned, each
//! with its sigma (degrees).
//!
//! ```
//! use headalign::procedure::{VergeTiltOptions, VergeTiltRun};
//! use headalign_sim::{Scenario, SimulatedHead};
//!
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! // Unknown encoder zeros and mounting errors, 1 px image noise, 10 % outliers.
//! let mut head = SimulatedHead::new(Scenario { points: 80, ..Scenario::default() })?;
//! let outcome = VergeTiltRun::default().run(&mut head, &VergeTiltOptions::default())?;
//! let (aligned, sigma) = (outcome.solution.aligned_encoders, outcome.sigmas);
//! println!("elevation {:.3} +- {:.3} deg", aligned.elevation, sigma.elevation_deg);
//! // The simulator knows the truth.
//! let truth = head.aligned_encoders();
//! assert!((aligned.elevation - truth.elevation).abs() < 4.0 * sigma.elevation_deg);
//! assert!((aligned.verge_left - truth.verge_left).abs() < 4.0 * sigma.verge_left_deg);
//! # Ok(())
//! # }
//! ```
//!
//! Files and devices (sessions, recordings, observation files, calibration files, a head
//! behind a driver process, folders of stereo images) are the `headalign-io` crate's; this
//! crate reads and writes no file format.
//!
//! The crate's examples teach the rest: `align_simulated` (the above with the errors
//! printed) and `custom_head` (implementing [`StereoHead`] for your own head);
//! `cargo run --release -p headalign --example NAME`. Self-calibration from a folder of
//! stereo images with [`calibrate`] is `headalign-io`'s example `calibrate_folder`.

pub mod alignment;
pub mod calibrate;
pub mod calibration;
pub mod check;
pub mod error;
pub mod facing_plane;
pub mod fixation;
pub mod image_mode;
pub mod observations;
pub mod plan;
pub mod procedure;
pub mod rig;
pub mod robot;
pub mod timing;
pub mod tracking;
pub mod verge_tilt;

pub use error::AlignError;
pub use headalign_platform::{Encoders, Joint, StereoCapture, StereoHead, Vehicle};
