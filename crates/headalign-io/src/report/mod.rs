//! The reports of a run: the JSON objects the commands print with `--json` ([`schema`],
//! one typed struct per schema, documented member by member in docs/formats.md) and the
//! self-contained `report.html` page with the run's annotated images ([`html`]). Nothing is
//! estimated here: both render what a procedure of the `headalign` crate returned.
//!
//! [`write_align_files`] writes the files of `align --out` (the calibration files,
//! `head.json`, `alignment.json`, `report.html`).
//!
//! Errors: [`ReportError`], one line naming the step or file (`report: calibration: ...`,
//! `cannot write FILE: ...`).

pub mod html;
pub mod schema;

use std::path::{Path, PathBuf};

use headalign::AlignError;
use headalign::calibration::StereoCalibration;
use headalign::observations::View;
use headalign::procedure::SessionAlignment;
use headalign_vision::VisionError;
use serde_json::{Value, json};
use thiserror::Error;

use crate::export::CalibrationFiles as _;
use crate::session::RecordedView;

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

/// `align --out DIR` on the general route: the calibration files of the session's
/// alignment `a` (translation in metres with `baseline_m`, else in baselines), `head.json`
/// (the head's `axes`, [`schema::head_axes_json`]), `alignment.json` and `report.html`
/// ([`html::write_align_report`]: `source` is the session read, `views` the tracked views,
/// `recorded` the images of an image session); the paths written, in order.
pub fn write_align_files(
    dir: &Path,
    a: &SessionAlignment,
    views: &[View],
    recorded: Option<&[RecordedView]>,
    axes: &Value,
    baseline_m: Option<f64>,
    source: Option<&PathBuf>,
) -> Result<Vec<PathBuf>, ReportError> {
    let (calib, solution, sig) = (&a.calibration, &a.solution, a.sigmas);
    let image_size = views.first().map_or([0, 0], |v| v.capture.image_size);
    let stereo = StereoCalibration::from_rig(calib, image_size, baseline_m)?;
    let mut written = stereo.write_all(dir)?;
    let extra = [
        ("head.json", json!({"format": "headalign-head/1", "axes": axes})),
        (
            "alignment.json",
            serde_json::to_value(schema::alignment_file("general", a.reference, solution, sig, &[]))?,
        ),
    ];
    for (name, value) in extra {
        let path = dir.join(name);
        std::fs::write(&path, serde_json::to_string_pretty(&value)? + "\n")
            .map_err(|source| ReportError::Write { path: path.clone(), source })?;
        written.push(path);
    }
    let results = html::AlignmentResults {
        calibration: calib,
        image_size,
        baseline_m,
        verge_axes: &a.verge_axes,
        reference: a.reference,
        solution,
        sigmas: &sig,
    };
    written.extend(html::write_align_report(dir, source, views, recorded, &results)?);
    Ok(written)
}
