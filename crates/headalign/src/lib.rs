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

pub mod alignment;
pub mod calibrate;
pub mod error;
pub mod estimate;
pub mod export;
pub mod frontend;
pub mod imaging;
pub mod observations;
pub mod procedure;
pub mod robot;
pub mod session;

pub use error::AlignError;
pub use headalign_platform::{Encoders, Joint, StereoCapture, StereoHead, Vehicle};

/// Polish with the geometry crate's small Levenberg-Marquardt (30 iterations).
pub(crate) fn lm_polish<S, const N: usize>(
    start: S,
    start_cost: f64,
    normal: impl Fn(&S) -> Option<(nalgebra::SMatrix<f64, N, N>, nalgebra::SVector<f64, N>)>,
    retract: impl Fn(&S, &nalgebra::SVector<f64, N>) -> Option<S>,
    cost: impl Fn(&S) -> f64,
) -> S {
    headalign_geometry::lm::minimise(start, start_cost, 30, normal, retract, cost).0
}
