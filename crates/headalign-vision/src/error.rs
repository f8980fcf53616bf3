//! Typed errors of the vision crate. Every error about a file names the file.

use std::path::PathBuf;

/// What can go wrong in the vision crate.
#[derive(Debug, thiserror::Error)]
pub enum VisionError {
    /// A file could not be read or decoded.
    #[error("cannot read image '{path}': {why}")]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        why: String,
    },
    /// A file could not be written.
    #[error("cannot write image '{path}': {why}")]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        why: String,
    },
    /// An image with no pixels, or a buffer that does not match its size.
    #[error("invalid image: {0}")]
    InvalidImage(String),
    /// Input that is well formed but not usable (mismatched sizes, a patch leaving the image).
    #[error("invalid input: {0}")]
    InvalidInput(String),
    /// An options struct failed its `validate()`.
    #[error("invalid options: {0}")]
    InvalidOptions(String),
    /// Zero-mean normalised cross-correlation is undefined: a window has (almost) no
    /// intensity variance, e.g. a blank wall, a lens cap or a saturated image.
    #[error("textureless input: {0} (ZNCC needs intensity variance; point the camera at texture)")]
    Textureless(String),
}
