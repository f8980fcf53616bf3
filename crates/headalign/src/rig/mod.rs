//! The kernel both self-calibration routes share, the verge/tilt route
//! ([`crate::verge_tilt`]) and the free-motion calibration ([`crate::calibrate`]): the
//! lens model and its automatic choice ([`lens_choice`]), known lenses removed from the
//! observations (`known_lens`: [`undistort_views`], [`read_opencv_lenses`]), and the checks of a rig bundle adjustment's fit against
//! the data: structure in its residuals ([`residuals`]) and its residuals against the
//! localisation noise measured from the images ([`image_noise`]); the left-right matches
//! of a capture (`stereo`).
//!
//! Each file's docs state what it computes, its degrees of freedom, units and pitfalls.
//! Nothing here depends on either route: both build on it (`docs/architecture.md`).

pub mod image_noise;
mod known_lens;
pub mod lens_choice;
pub mod residuals;
pub(crate) mod stereo;

/// Minimum iterations of the final adjustment (robust IRLS converges linearly).
pub const FINAL_ITERATIONS: usize = 300;

pub use image_noise::{ImageNoiseCheck, MeasuredVariances};
pub use known_lens::{LensModel, opencv_matrix, read_opencv_lenses, scalar, undistort_views};
pub use lens_choice::{FailedCandidate, LensCandidate, LensChoice, LensSelection, LensSpec, lens_terms};
