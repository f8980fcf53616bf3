//! headalign-vision: the image half of headalign (`docs/architecture.md#the-crates`). It knows images,
//! not heads: grey images and their I/O, Gaussian pyramids, correlation, corners,
//! descriptors and matching.
//!
//! Conventions: pixel `(x, y)` is column `x`, row `y`; `(0, 0)` is the centre of the
//! top-left pixel (the same convention as the observation files,
//! `docs/conventions.md#pixels-and-intrinsics`).
//!
//! Main entry points:
//! - [`Pyramid`], [`gaussian_blur`]: Gaussian pyramids (8-bit level 0, [`FloatImage`] above);
//! - [`register_translation`] (whole-image shift, paper sections 5-6) and [`locate_patch`]
//!   (where did the patch around a point go), both by coarse-to-fine ZNCC;
//! - [`detect_and_describe`]: FAST-9 corners ranked by Harris, spread over a grid, with
//!   256-bit BRIEF descriptors;
//! - [`match_descriptors`], [`match_epipolar`], [`match_predicted`]: Hamming matching,
//!   free or guided by a fundamental matrix or a predicting map;
//! - [`refine_point_against_patch`]: sub-pixel Lucas-Kanade alignment of a point against a
//!   reference patch under a local affine map (one physical point across images);
//! - [`draw::Canvas`]: annotated images (features, lines, fixation points).

pub mod correlation;
pub mod draw;
pub mod error;
pub mod features;
pub mod image;
pub mod matching;
pub mod pyramid;
pub mod refine;
#[cfg(test)]
mod test_util;

pub use correlation::{
    PatchMatch, PatchSearchOptions, Registration, RegistrationOptions, locate_patch,
    locate_patch_in_pyramids, register_pyramids, register_translation, zncc,
};
pub use error::VisionError;
pub use features::{Descriptor, FeatureOptions, Features, Keypoint, detect_and_describe};
pub use image::GrayImage;
pub use matching::{
    Match, MatchOptions, match_descriptors, match_epipolar, match_homography, match_predicted,
};
pub use pyramid::{FloatImage, Pyramid, gaussian_blur};
pub use refine::{PatchRefineOptions, RefineFailure, Refinement, refine_point_against_patch};
