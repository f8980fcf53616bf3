//! `check(views, calibration)` and `read_calibration(path)`: the targetless health check
//! of a given stereo calibration ([`headalign::check::check_views`], as `headalign check`
//! runs it, without `--full`) and the calibration files it reads
//! ([`headalign_io::import::read_calibration`]: headalign's JSON, an OpenCV stereo YAML, a
//! Kalibr camchain).
//!
//! What it computes: the library's (docs/check.md): the right camera's rotation change
//! since the calibration (pitch, yaw, roll about its x, y, z axes, degrees, with sigmas),
//! the depth error it causes, the vertical disparity and Sampson error of the given and the
//! refitted calibration, and a verdict (`good`, `can-improve`, `recalibrate`), with the
//! given calibration turned by the refit (`updated`) when the refit validates.
//!
//! Inputs: `views` as for `calibrate` (a path or a list of `(left, right)` `uint8`
//! arrays, `images.rs`); `calibration` a `Calibration` or a path of a calibration file.
//! A file without an image size (OpenCV's sample) takes the views'; one with another size
//! than the views' is a `ValueError`, as in the CLI.
//!
//! Pitfall: the depth error needs the baseline in metres: a calibration in baselines (a
//! self-calibration without `baseline_m`) needs `baseline_m` here.

use std::path::PathBuf;

use headalign::calibration::StereoCalibration;
use headalign::check::{CheckError, CheckOptions, CheckReport, check_views};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::calibration::{Calibration, Source};
use crate::errors::{align_error, value_error};
use crate::progress::Progress;

/// The Python exception of a check error: a bad option or calibration is `ValueError`,
/// too few matches `RuntimeError`, the front end's errors as the library's.
fn check_error(e: CheckError) -> PyErr {
    match e {
        CheckError::InvalidOption(_) | CheckError::Calibration(_) => PyValueError::new_err(e.to_string()),
        CheckError::TooFewMatches { .. } => PyRuntimeError::new_err(e.to_string()),
        CheckError::Align(e) => align_error(e),
    }
}

/// The result of `check` (module docs).
#[pyclass(module = "headalign", name = "CheckReport", frozen)]
pub struct Check {
    report: CheckReport,
    updated: Option<Py<Calibration>>,
}

/// Pitch, yaw and roll as a dict, degrees.
fn angles<'py>(py: Python<'py>, a: &headalign::check::Angles) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("pitch", a.pitch)?;
    d.set_item("yaw", a.yaw)?;
    d.set_item("roll", a.roll)?;
    Ok(d)
}

#[pymethods]
impl Check {
    /// `good`, `can-improve` or `recalibrate`.
    #[getter]
    fn verdict(&self) -> &'static str {
        self.report.verdict.name()
    }

    /// Whether the data can tell (a `good` that is not conclusive: check more pairs).
    #[getter]
    fn conclusive(&self) -> bool {
        self.report.conclusive
    }

    /// The right camera's rotation change since the calibration, degrees: `pitch`,
    /// `yaw`, `roll` about its x, y, z axes.
    #[getter]
    fn rotation_change_deg<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        angles(py, &self.report.rotation_change_deg)
    }

    /// The sigmas of `rotation_change_deg`, degrees.
    #[getter]
    fn rotation_change_sigma_deg<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        angles(py, &self.report.rotation_change_sigma_deg)
    }

    /// The given calibration with the refitted rotation, or `None` (`update_refused`
    /// says why).
    #[getter]
    fn updated(&self, py: Python<'_>) -> Option<Py<Calibration>> {
        self.updated.as_ref().map(|c| c.clone_ref(py))
    }

    /// Why no update is offered (`None` when one is).
    #[getter]
    fn update_refused(&self) -> Option<String> {
        self.report.update_refused.clone()
    }

    /// The whole report as a dict (the JSON of `headalign check --json`).
    #[getter]
    fn report<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let text = serde_json::to_string(&self.report).map_err(|e| value_error(format!("report: {e}")))?;
        py.import("json")?.call_method1("loads", (text,))
    }

    fn __repr__(&self) -> String {
        let (r, s) = (&self.report.rotation_change_deg, &self.report.rotation_change_sigma_deg);
        format!(
            "CheckReport(verdict='{}', conclusive={}, pitch={:.3}+-{:.3}, yaw={:.3}+-{:.3}, roll={:.3}+-{:.3} deg)",
            self.report.verdict.name(),
            if self.report.conclusive { "True" } else { "False" },
            r.pitch,
            s.pitch,
            r.yaw,
            s.yaw,
            r.roll,
            s.roll
        )
    }
}

/// A calibration file as a `Calibration` (module docs).
#[pyfunction]
pub fn read_calibration(py: Python<'_>, path: PathBuf) -> PyResult<Calibration> {
    let stereo = py.detach(|| headalign_io::import::read_calibration(&path)).map_err(align_error)?;
    Ok(Calibration::from_file(stereo))
}

/// The given calibration with the views' image size (module docs).
fn with_image_size(mut given: StereoCalibration, image_size: [u32; 2]) -> PyResult<StereoCalibration> {
    if given.image_size == [0, 0] {
        given.image_size = image_size;
    } else if given.image_size != image_size {
        return Err(value_error(format!(
            "the calibration is of {}x{} images, the views are {}x{}",
            given.image_size[0], given.image_size[1], image_size[0], image_size[1]
        )));
    }
    Ok(given)
}

/// Check a calibration against views (the Python wrapper `headalign.check` documents the
/// arguments).
#[pyfunction]
#[pyo3(signature = (views, calibration, baseline_m, corners, seed, significance, depth_limit_pct, progress))]
#[allow(clippy::too_many_arguments)] // one per keyword argument of the Python API
pub fn check(
    py: Python<'_>,
    views: &Bound<'_, PyAny>,
    calibration: &Bound<'_, PyAny>,
    baseline_m: Option<f64>,
    corners: Option<usize>,
    seed: u64,
    significance: f64,
    depth_limit_pct: f64,
    progress: Option<Py<PyAny>>,
) -> PyResult<Check> {
    let mut options = CheckOptions {
        baseline_m,
        significance_sigmas: significance,
        depth_limit_pct,
        ..CheckOptions::default()
    };
    if let Some(c) = corners {
        options.front_end.features.max_features = c;
    }
    options.ransac.seed = seed;
    options.validate().map_err(check_error)?;
    let given = match calibration.cast::<Calibration>() {
        Ok(c) => c.get().stereo().clone(),
        Err(_) => {
            let path: PathBuf = calibration.extract().map_err(|_| {
                value_error("calibration must be a Calibration or the path of a calibration file")
            })?;
            headalign_io::import::read_calibration(&path).map_err(align_error)?
        }
    };
    let source = Source::of(views)?;
    let progress = Progress::new(progress);
    let report = py.detach(|| {
        let views = source.read(1)?;
        let Some(size) = views.image_size() else { return Err(value_error("no views")) };
        let given = with_image_size(given, size)?;
        progress.report("solving", &format!("checking {} pairs", views.count()), 0, 0);
        let report = check_views(views.stereo_views(), &given, &options).map_err(check_error);
        progress.report("solved", "", 0, 0);
        report
    })?;
    let updated = match &report.updated {
        Some(u) => Some(Py::new(py, Calibration::from_file(u.clone()))?),
        None => None,
    };
    Ok(Check { report, updated })
}
