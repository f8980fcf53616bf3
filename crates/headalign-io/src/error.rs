//! The error of the readers and writers that report in their own words ([`FileError`]):
//! one line naming the file and the problem, printed as it is, with no category before it.
//! The formats that the library's procedures also reach (sessions, recordings, observation
//! and calibration files) report with [`headalign::AlignError`] instead, whose message
//! names its category (`images: ...`, `recording: ...`).

use headalign::AlignError;
use thiserror::Error;

/// A file or folder that cannot be read or written as asked.
#[derive(Debug, Error)]
pub enum FileError {
    /// The file and the problem, one line.
    #[error("{0}")]
    File(String),
    /// An error of a format read on the way (an image session's, for instance).
    #[error(transparent)]
    Align(#[from] AlignError),
}
