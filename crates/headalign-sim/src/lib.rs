//! # headalign-sim
//!
//! A simulated stereo pan-tilt-verge head with ground truth, for tests, the demo and the
//! experiments (`docs/conventions.md#frames`,
//! `docs/conventions.md#the-default-scenario-yorick`). It implements the platform trait
//! [`headalign_platform::StereoHead`]; the alignment procedures see it only through that
//! trait. The ground truth ([`HeadTruth`], the scene points, the error metrics) is for the
//! simulator itself and for experiments that score the procedures.
//!
//! Modules:
//! - [`scenario`]: every parameter of a simulation ([`Scenario`], default "yorick"),
//!   validation and TOML loading.
//! - [`kinematics`]: the true head geometry (axes as lines in the robot frame, zero
//!   offsets, camera mounting) drawn from the seed, and the product-of-exponentials
//!   forward kinematics.
//! - [`quad`]: the planar rectangle the room's surfaces are made of.
//! - [`scene`]: a seeded room of 3D points (walls, floor, ceiling, boxes) with track ids.
//! - [`head`]: [`SimulatedHead`], noisy point captures with outliers, rendered stereo
//!   images.
//! - [`texture`]: baked, mip-mapped textures of the room's surfaces (photographs from the
//!   shared data folder plus procedural detail; procedural only if the folder is missing).
//! - [`render`]: ray-cast renderer of the textured room with radial distortion,
//!   supersampling, blur and sensor noise ([`RenderOptions`]).
//! - [`rigmotion`]: the general rigid motion of the whole rig that `simulate --motion
//!   general` records, and why it is chosen so.
//! - [`robot`]: [`SimulatedRobot`], a tricycle AGV carrying the head ([`headalign_platform::Vehicle`]).
//! - [`metrics`]: ground-truth error metrics (alignment, calibration, reconstruction,
//!   axes).
//! - [`driver`]: the simulated robot behind the JSON-lines head protocol (the server of
//!   the example driver `headalign-sim-driver`), its truth written to a file at the end.
//!
//! Frames: the world is the robot frame, origin on the pan axis at the ground, x right,
//! y down (gravity +y), z forward; cameras are x right, y down, z forward. Angles in the
//! public API are degrees (as encoders are); inside, radians. Lengths are metres.

pub mod driver;
pub mod head;
pub mod kinematics;
pub mod metrics;
pub mod quad;
pub mod render;
pub mod rigmotion;
pub mod robot;
pub mod scenario;
pub mod scene;
pub mod texture;

pub use head::SimulatedHead;
pub use kinematics::HeadTruth;
pub use metrics::{AlignmentErrors, AxisErrors, CalibrationErrors, ReconErrors, calibration_errors};
pub use render::RenderOptions;
pub use robot::{RobotTruth, SimulatedRobot};
pub use scenario::{Scenario, SceneKind};
pub use texture::{TextureReport, TexturedScene};

use thiserror::Error;

/// Failures of the simulator.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum SimError {
    /// One or more scenario parameters make no sense; the message names every one.
    #[error("invalid scenario: {0}")]
    InvalidScenario(String),
    /// A scenario file could not be parsed or written.
    #[error("scenario TOML: {0}")]
    Toml(String),
    /// The scene could not be built as asked (e.g. nothing visible in the initial view).
    #[error("scene: {0}")]
    Scene(String),
    /// An image could not be rendered (bad camera, non-invertible distortion).
    #[error("render: {0}")]
    Render(String),
    /// A metric could not be computed from the given data.
    #[error("metric: {0}")]
    Metric(String),
}
