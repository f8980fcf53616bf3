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
}
