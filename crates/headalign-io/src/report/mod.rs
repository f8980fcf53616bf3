//! The reports of a run: the JSON objects the commands print with `--json` ([`schema`],
//! one typed struct per schema, documented member by member in docs/formats.md) and the
//! self-contained `report.html` page with the run's annotated images ([`html`]). Nothing is
//! estimated here: both render what a procedure of the `headalign` crate returned.
//!
//! Errors: [`ReportError`], one line naming the step or file (`report: calibration: ...`,
//! `cannot write FILE: ...`).

pub mod html;
pub mod schema;

use std::path::PathBuf;

use headalign::AlignError;
use headalign_vision::VisionError;
use thiserror::Error;

/// A report that cannot be built or written.
#[derive(Debug, Error)]
pub enum ReportError {
    /// A step of the report failed; `what` names it (`report: calibration`).
    #[error("{what}")]
    Step {
        /// The step.
        what: &'static str,
        /// Why.
        #[source]
        source: AlignError,
    },
    /// The calibration holds no head axes (it is not a verge/tilt calibration).
    #[error("report: head axes")]
    HeadAxes,
    /// A file that cannot be written.
    #[error("cannot write {}", path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// An annotated image that cannot be written.
    #[error(transparent)]
    Image(#[from] VisionError),
    /// A format written on the way (the calibration files).
    #[error(transparent)]
    Align(#[from] AlignError),
    /// A member that cannot be serialised.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
}
