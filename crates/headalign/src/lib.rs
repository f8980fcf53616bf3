//! # headalign
//!
//! Self-alignment and self-calibration of an active stereo camera head from images alone
//! (paper: "Active Visual Alignment of a Mobile Stereo Camera Platform"; conventions:
//! `docs/conventions.md`). This crate holds the procedures; it sees the head only through the
//! [`headalign_platform::StereoHead`] trait and does its mathematics in
//! `headalign-geometry`.
//!
//! - [`observations`]: observation sessions on disk (bring your own correspondences).
//! - [`verge_tilt`]: the verge/tilt estimation core (F, frame, 3D homographies, linear
//!   self-calibration, rig bundle adjustment).
//! - [`alignment`]: exact aligned encoder readings from the calibrated head, measurement of
//!   cameras by resection.
//! - [`calibrate`]: self-calibration of a stereo rig from general rig motions (one
//!   general motion with constraints, or two rotations about different axes).
//! - [`procedure`]: the verge/tilt procedure over any `StereoHead`.
//! - [`image_mode`]: the procedure on images through the front end (verging first) and the
//!   robot stages on images, over any `ImagingHead`.
//! - [`session`]: sessions on disk (recording head, replay head, the format).
//! - [`recordings`]: ROS 2 bags (MCAP) and EuRoC folders read as sessions.
//! - [`process_head`]: a head behind a driver process (JSON lines, `docs/head-protocol.md`).
//! - [`robot`]: the robot stages (pan, steering, floor) and their driver ([`robot::stages`]), pan alignment without calibration
//!   by fixating a drive's epipole ([`robot::pan_fixation`]) and one-motion alignment
//!   ([`robot::one_motion`]).
//! - [`fixation`]: verging and fixating with no calibration; [`tracking`]: the tracker.
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
//! The crate's examples teach the rest: `align_simulated` (the above with the errors
//! printed), `custom_head` (implementing [`StereoHead`] for your own head) and
//! `calibrate_folder` (self-calibration from a folder of stereo images with
//! [`calibrate`]); `cargo run --release -p headalign --example NAME`.

pub mod alignment;
pub mod calibrate;
pub mod error;
pub mod export;
pub mod facing_plane;
pub mod fixation;
pub mod image_mode;
pub mod observations;
pub mod procedure;
pub mod process_head;
pub mod recordings;
pub mod robot;
pub mod session;
pub mod tracking;
pub mod verge_tilt;

pub use error::AlignError;
pub use headalign_platform::{Encoders, Joint, StereoCapture, StereoHead, Vehicle};
