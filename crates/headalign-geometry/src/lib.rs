//! # headalign-geometry
//!
//! The mathematics of headalign, with no knowledge of images, heads or I/O.
//!
//! Conventions (`docs/conventions.md#frames`): camera frames are x right, y down, z forward;
//! pixel coordinates have (0, 0) at the centre of the top-left pixel; the projective
//! frame of a stereo rig is that of the left camera, `P_L = [I | 0]`. Angles inside this
//! crate are radians; residuals and thresholds are pixels unless a function says
//! otherwise. Everything is `f64`.
//!
//! Modules, in the order the alignment procedure uses them:
//! - [`camera`]: intrinsics `K`, projective 3x4 cameras, rigid poses.
//! - [`distortion`]: a camera's lens (model and parameters), undistortion of pixels.
//! - [`lens`]: the lens models as a table (pinhole, radial-tangential `plumb_bob`, equidistant `fisheye`, double sphere `ds`): projection with Jacobians, unprojection, names.
//! - [`so3`]: rotation exponential/logarithm safe at zero angle, screw axes.
//! - [`ransac`]: the `Estimator` trait and one generic, seeded, adaptive RANSAC.
//! - `linear` (inside the crate): the null space of a homogeneous system by SVD, Hartley normalisation.
//! - [`fundamental`]: normalised 8-point and 7-point F, Sampson refinement.
//! - [`triangulation`]: optimal correction of a match, then linear triangulation.
//! - [`frame`]: a well-conditioned (quasi-Euclidean) projective frame from F.
//! - [`essential`]: calibrated relative pose (5 dof) by Sampson ML from several starts.
//! - [`homography2d`]: plane homographies (4-point DLT), a robust prefilter for rotations.
//! - [`homography3d`]: 4x4 projective homographies of 3D space, 5-point DLT,
//!   symmetric transfer error over four images.
//! - [`selfcal`]: plane at infinity from two motions, linear self-calibration of `K`,
//!   Euclidean upgrade, decomposition of the right camera.
//! - [`registration`]: 3D point-set registration (Kabsch/Umeyama), 3-point rigid RANSAC
//!   solver for homographies in a quasi-Euclidean frame.
//! - [`resection`]: pose of a calibrated camera from 3D-2D correspondences.
//! - [`rigmotion`]: maximum-likelihood rigid motion of a calibrated stereo rig between
//!   two stereo views (robot drives).
//! - [`invariant`]: invariant lines at infinity of a motion from its complex eigenvectors.
//! - [`plane`]: the plane-induced homography, the invariant line of a homography, the
//!   projection of a plane point through a chain of rotations about lines (the planar
//!   route, paper section 3.3) with its Jacobians.
//! - [`lm`]: a small dense Levenberg-Marquardt shared by the refinements.
//! - [`rectify`]: stereo rectification of a calibrated pair (OpenCV / ROS conventions).
//! - [`bundle`]: the rig bundle adjustment (maximum likelihood, Schur complement,
//!   robust loss, covariance).
//! - [`bootstrap`]: the bundle adjustment's spread over resampled point tracks.
//! - [`synthetic`] (`bundle::synthetic`): seeded rig problems with known truth for tests,
//!   benches, experiments.

pub mod bootstrap;
pub mod bundle;
pub mod camera;
pub mod distortion;
pub mod error;
pub mod essential;
pub mod frame;
pub mod fundamental;
pub mod homography2d;
pub mod homography3d;
pub mod invariant;
pub mod lens;
mod linear;
pub mod lm;
pub mod plane;
pub mod ransac;
pub mod rectify;
pub mod registration;
pub mod resection;
pub mod rigmotion;
pub mod selfcal;
pub mod so3;
pub mod steering;
pub mod translation;
pub mod triangulation;

pub use bundle::synthetic;
pub use error::GeometryError;

/// Result alias of this crate.
pub type Result<T> = std::result::Result<T, GeometryError>;
