//! headalign-vision: the image half of headalign (DESIGN.md section 3). It knows images,
//! not heads: grey images and their I/O, Gaussian pyramids, correlation, corners,
//! descriptors and matching.
//!
//! Conventions: pixel `(x, y)` is column `x`, row `y`; `(0, 0)` is the centre of the
//! top-left pixel (the same convention as the observation files, DESIGN.md section 6).

pub mod draw;
pub mod error;
pub mod image;

pub use error::VisionError;
pub use image::GrayImage;
