//! # headalign
//!
//! Self-alignment and self-calibration of an active stereo camera head from images alone
//! (paper: "Active Visual Alignment of a Mobile Stereo Camera Platform"; design:
//! `DESIGN.md`). This crate holds the procedures; it sees the head only through the
//! [`headalign_platform::StereoHead`] trait and does its mathematics in
//! `headalign-geometry`.
//!
//! - [`observations`]: observation sessions on disk (bring your own correspondences).
//! - [`estimate`]: the verge/tilt estimation core (F, frame, 3D homographies, linear
//!   self-calibration, rig bundle adjustment).
//! - [`alignment`]: exact aligned encoder readings from the calibrated head, measurement of
//!   cameras by resection.
//! - [`calibrate`]: self-calibration of a stereo rig from general rig motions (one
//!   general motion with constraints, or two rotations about different axes).
//! - [`procedure`]: the verge/tilt procedure over any `StereoHead`.
//! - [`session`]: sessions on disk (recording head, replay head, the format).
//! - [`process_head`]: a head behind a driver process (JSON lines, `docs/head-protocol.md`).
//! - [`panfix`]: pan alignment without calibration, by fixating a drive's epipole.

pub mod alignment;
pub mod calibrate;
pub mod error;
pub mod estimate;
pub mod export;
pub mod frontend;
pub mod imaging;
pub mod observations;
pub mod onemotion;
pub mod panfix;
pub mod procedure;
pub mod process_head;
pub mod robot;
pub mod session;

pub use error::AlignError;
pub use headalign_platform::{Encoders, Joint, StereoCapture, StereoHead, Vehicle};
