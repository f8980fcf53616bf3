//! `align(session)`: the verge/tilt alignment of a recorded head run
//! ([`headalign::procedure::align_session_detecting`], as `headalign align` runs it): the
//! encoder readings that align both optical axes with the direction perpendicular to the
//! pan and elevation axes (paper section 3.2; docs/how-it-works.md), their sigmas, and the
//! head's calibration.
//!
//! Inputs, told apart as the CLI's `--observations` and `--images` are: a file is an
//! observation session (`headalign-observations/1`, [`headalign_io::observations`]); a
//! folder is a point or image session ([`headalign_io::session`]: its verge/tilt views,
//! the verging captures and robot stages left out), a ROS 2 bag or an EuRoC folder of a
//! head run (its still views from the verge/tilt start, [`headalign_io::recordings`]).
//! Images are tracked by the default front end. The lens model is the caller's, else the
//! one a recorded session names (`session.json`), else `auto` for images and the pinhole
//! for tracked points, as in the CLI.
//!
//! Outputs: the route (`general`: the head's full calibration; `planar`: a planar or far
//! scene, where each camera is calibrated from its own plane homographies and the rig's
//! translation and the axes' positions are undetermined), the aligned readings and the
//! reference readings (degrees), their sigmas (degrees), the fixation points (pixels, in
//! the reference view's images) with their sigmas (general route), both camera matrices,
//! the calibration (general route, as `calibrate` returns it) and the warnings.
//!
//! Pitfall: without a view that moved a vergence joint the vergence readings rest on
//! nominal axes: `verge_axes_measured` is false and the warning says what that assumes.

use std::path::{Path, PathBuf};

use headalign::alignment::NOMINAL_VERGE_WARNING;
use headalign::calibrate::{LensChoice, lens_terms};
use headalign::calibration::StereoCalibration;
use headalign::observations::View;
use headalign::procedure::{SessionRoute, align_session_detecting};
use headalign::tracking::FrontEndOptions;
use headalign::verge_tilt::EstimationOptions;
use headalign_geometry::camera::Intrinsics;
use headalign_geometry::distortion::DistortionTerms;
use headalign_io::recordings::RecordingOptions;
use headalign_io::session::RecordedView;
use headalign_platform::Encoders;
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray2};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::calibration::Calibration;
use crate::errors::{align_error, align_error_in, value_error};
use crate::progress::Progress;

/// The verge/tilt alignment of a head (module docs).
#[pyclass(module = "headalign", name = "Alignment", frozen)]
pub struct Alignment {
    route: &'static str,
    reference: Encoders,
    aligned: Encoders,
    /// Sigmas of the aligned elevation, left and right vergence readings, degrees.
    sigmas_deg: [f64; 3],
    fixation_px: [[f64; 2]; 2],
    fixation_sigma_px: Option<[[f64; 2]; 2]>,
    verge_axes_measured: bool,
    cameras: [Intrinsics; 2],
    calibration: Option<Py<Calibration>>,
    undetermined: Vec<String>,
    warnings: Vec<String>,
}

/// Encoder readings as a dict of degrees.
fn readings<'py>(py: Python<'py>, e: &Encoders) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("pan", e.pan)?;
    d.set_item("elevation", e.elevation)?;
    d.set_item("verge_left", e.verge_left)?;
    d.set_item("verge_right", e.verge_right)?;
    Ok(d)
}

/// A camera matrix as a 3x3 `float64` array.
fn camera_matrix<'py>(py: Python<'py>, k: &Intrinsics) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let m = k.matrix();
    let rows: Vec<f64> = (0..3).flat_map(|r| (0..3).map(move |c| m[(r, c)])).collect();
    let array = Array2::from_shape_vec((3, 3), rows).map_err(|e| value_error(format!("matrix: {e}")))?;
    Ok(array.into_pyarray(py))
}

#[pymethods]
impl Alignment {
    /// `general` (full calibration) or `planar` (a planar or far scene).
    #[getter]
    fn route(&self) -> &'static str {
        self.route
    }

    /// The readings of the reference (first) view, degrees: `pan`, `elevation`,
    /// `verge_left`, `verge_right`.
    #[getter]
    fn reference<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        readings(py, &self.reference)
    }

    /// The aligned readings, degrees (pan as in the reference view).
    #[getter]
    fn aligned_readings<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        readings(py, &self.aligned)
    }

    /// The sigmas of the aligned readings, degrees: `elevation`, `verge_left`,
    /// `verge_right`.
    #[getter]
    fn sigmas<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for (name, s) in ["elevation", "verge_left", "verge_right"].iter().zip(self.sigmas_deg) {
            d.set_item(name, s)?;
        }
        Ok(d)
    }

    /// Where each camera must look, pixels in the reference view: `(left (x, y), right
    /// (x, y))`.
    #[getter]
    fn fixation_px(&self) -> ((f64, f64), (f64, f64)) {
        let [l, r] = self.fixation_px;
        ((l[0], l[1]), (r[0], r[1]))
    }

    /// The sigmas of `fixation_px`, pixels (general route; `None` on the planar one).
    #[getter]
    fn fixation_sigma_px(&self) -> Option<((f64, f64), (f64, f64))> {
        self.fixation_sigma_px.map(|[l, r]| ((l[0], l[1]), (r[0], r[1])))
    }

    /// False if no view moved a vergence joint (nominal vergence axes; a warning says so).
    #[getter]
    fn verge_axes_measured(&self) -> bool {
        self.verge_axes_measured
    }

    /// Left camera matrix, 3x3, pixels.
    #[getter(K1)]
    fn k1<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        camera_matrix(py, &self.cameras[0])
    }

    /// Right camera matrix, 3x3, pixels.
    #[getter(K2)]
    fn k2<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        camera_matrix(py, &self.cameras[1])
    }

    /// The head's stereo calibration (general route), as `calibrate` returns it; `None` on
    /// the planar route.
    #[getter]
    fn calibration(&self, py: Python<'_>) -> Option<Py<Calibration>> {
        self.calibration.as_ref().map(|c| c.clone_ref(py))
    }

    /// What the planar route cannot determine, one line each (empty on the general route).
    #[getter]
    fn undetermined(&self) -> Vec<String> {
        self.undetermined.clone()
    }

    /// What is doubtful about the result, one line each.
    #[getter]
    fn warnings(&self) -> Vec<String> {
        self.warnings.clone()
    }

    fn __repr__(&self) -> String {
        let (a, s) = (&self.aligned, self.sigmas_deg);
        format!(
            "Alignment(route='{}', elevation={:.3}+-{:.3}, verge_left={:.3}+-{:.3}, verge_right={:.3}+-{:.3} deg, {} warning(s))",
            self.route,
            a.elevation,
            s[0],
            a.verge_left,
            s[1],
            a.verge_right,
            s[2],
            self.warnings.len()
        )
    }
}

/// The lens of the estimate: `lens` and `terms` over a recorded session's own (the
/// pinhole for sessions without one and for observation files; `auto` for a
/// recording's or a folder's images without a `session.json`), as the CLI's
/// `AlignArgs::lens`.
fn lens_of(path: &Path, lens: Option<&str>, terms: Option<&str>) -> PyResult<(LensChoice, DistortionTerms)> {
    let given = match lens {
        None => None,
        Some(name) => Some(LensChoice::parse(name).ok_or_else(|| {
            value_error(format!("unknown lens model '{name}': pinhole, radtan, equidistant, ds or auto"))
        })?),
    };
    let given_terms = match terms {
        None => None,
        Some(t) => Some(
            DistortionTerms::parse(t)
                .ok_or_else(|| value_error(format!("unknown lens terms '{t}': radial (k1 k2), 4 or 5")))?,
        ),
    };
    let (recorded, recorded_terms) = if path.join("session.json").is_file() {
        let info = headalign_io::session::read_session_info(path).map_err(align_error)?;
        let lens = match &info.lens {
            None => LensChoice::Pinhole,
            Some(name) => LensChoice::parse(name)
                .ok_or_else(|| value_error(format!("session.json: unknown lens model '{name}'")))?,
        };
        (lens, info.lens_terms)
    } else if path.is_file() && headalign_io::recordings::detect(path).is_none() {
        (LensChoice::Pinhole, None)
    } else {
        (LensChoice::Auto, None)
    };
    let choice = given.unwrap_or(recorded);
    let terms = given_terms.or(recorded_terms);
    if choice == LensChoice::Pinhole && terms.is_some() {
        return Err(value_error(
            "lens_terms needs a lens model to estimate (lens='radtan', 'equidistant' or 'auto')",
        ));
    }
    Ok((choice, lens_terms(choice, terms)))
}

/// The views `align` estimates from (module docs), tracked when they are images.
fn read_views(path: &Path, progress: &Progress) -> PyResult<Vec<View>> {
    use headalign_io::session::{estimation_views, read_image_session, read_point_session};
    let recorded = headalign_io::recordings::detect(path).is_some();
    if !recorded && path.is_file() {
        return headalign_io::observations::read_session(path).map_err(align_error);
    }
    if !recorded && !path.is_dir() {
        return Err(value_error(format!(
            "'{}' is neither an observation file nor a session folder",
            path.display()
        )));
    }
    if headalign_io::session::is_point_session(path) {
        let r = estimation_views(read_point_session(path).map_err(align_error)?, |v| v.stage.as_deref());
        return Ok(r.into_iter().map(|v| v.view).collect());
    }
    let r: Vec<RecordedView> = if recorded {
        let rec = headalign_io::recordings::read_recording(path, &RecordingOptions::default())
            .map_err(align_error)?;
        let still = headalign_io::recordings::still_views(rec.views);
        headalign_io::recordings::verge_tilt_views(still).map_err(align_error)?
    } else {
        estimation_views(read_image_session(path).map_err(align_error)?, |v| v.stage.as_deref())
    };
    progress.report("tracking", &format!("tracking {} views", r.len()), 0, 0);
    let (views, _) = headalign_io::session::track_session_reporting(&r, &FrontEndOptions::default())
        .map_err(align_error)?;
    Ok(views)
}

/// Align a head from a recorded session (the Python wrapper `headalign.align` documents
/// the arguments).
#[pyfunction]
#[pyo3(signature = (session, lens, lens_terms, baseline_m, progress))]
pub fn align(
    py: Python<'_>,
    session: PathBuf,
    lens: Option<String>,
    lens_terms: Option<String>,
    baseline_m: Option<f64>,
    progress: Option<Py<PyAny>>,
) -> PyResult<Alignment> {
    let (lens, lens_terms) = lens_of(&session, lens.as_deref(), lens_terms.as_deref())?;
    if let Some(b) = baseline_m
        && !(b.is_finite() && b > 0.0)
    {
        return Err(value_error(format!("baseline must be positive, got {b}")));
    }
    let progress = Progress::new(progress);
    let estimation = EstimationOptions { lens, lens_terms, ..EstimationOptions::default() };
    let (route, image_size) = py.detach(|| {
        let views = read_views(&session, &progress)?;
        let image_size = views.first().map_or([0, 0], |v| v.capture.image_size);
        progress.report("solving", &format!("alignment of {} views", views.len()), 0, 0);
        let route = align_session_detecting(&views, &estimation)
            .map_err(|e| align_error_in(e, &format!("session {}", session.display())));
        progress.report("solved", "", 0, 0);
        Ok::<_, PyErr>((route?, image_size))
    })?;
    let mut warnings = Vec::new();
    let alignment = match route {
        SessionRoute::General(a, _scene) => {
            let stereo =
                StereoCalibration::from_rig(&a.calibration, image_size, baseline_m).map_err(align_error)?;
            let st = &a.calibration.bundle.state;
            let report = serde_json::to_value(&a.calibration.report)
                .map_err(|e| value_error(format!("report: {e}")))?;
            let lens_name =
                if lens == LensChoice::Pinhole { "pinhole" } else { st.left_distortion.kind.kalibr_name() };
            let cal = Calibration::new(
                stereo,
                lens_name.to_string(),
                Some(&a.calibration.bundle.covariance),
                Vec::new(),
                report,
            );
            let s = &a.sigmas;
            Alignment {
                route: "general",
                reference: a.reference,
                aligned: a.solution.aligned_encoders,
                sigmas_deg: [s.elevation_deg, s.verge_left_deg, s.verge_right_deg],
                fixation_px: [a.solution.fixation_px_left, a.solution.fixation_px_right],
                fixation_sigma_px: Some([a.fixation_sigmas.left_px, a.fixation_sigmas.right_px]),
                verge_axes_measured: a.solution.verge_axes_measured,
                cameras: [st.left, st.right],
                calibration: Some(Py::new(py, cal)?),
                undetermined: Vec::new(),
                warnings: Vec::new(),
            }
        }
        SessionRoute::Planar(p) => {
            warnings.push(
                "the rig's translation and the axes' positions are undetermined on a plane: no calibration"
                    .to_string(),
            );
            let s = &p.sigmas;
            Alignment {
                route: "planar",
                reference: p.reference,
                aligned: p.solution.aligned_encoders,
                sigmas_deg: [s.elevation_deg, s.verge_left_deg, s.verge_right_deg],
                fixation_px: [p.solution.fixation_px_left, p.solution.fixation_px_right],
                fixation_sigma_px: None,
                verge_axes_measured: p.solution.verge_axes_measured,
                cameras: [p.calibration.left.intrinsics, p.calibration.right.intrinsics],
                calibration: None,
                undetermined: p.calibration.undetermined.clone(),
                warnings: Vec::new(),
            }
        }
    };
    if !alignment.verge_axes_measured {
        warnings.push(NOMINAL_VERGE_WARNING.to_string());
    }
    Ok(Alignment { warnings, ..alignment })
}
