//! `calibrate(views, ...)`: the stereo self-calibration of views related by rigid motions
//! of the whole rig ([`headalign::calibrate::calibrate_views`], as `headalign calibrate
//! DIR` runs it: the same options for the same arguments, so the same numbers), and the
//! `Calibration` it returns, in OpenCV's conventions (`lib.rs`).
//!
//! Inputs: a path (a folder of stereo pairs or an image session: [`headalign_io::folder`];
//! a point session: [`headalign_io::session`]; a ROS 2 bag or an EuRoC folder:
//! [`headalign_io::recordings`]), or a list of `(left, right)` `uint8` arrays
//! (`images.rs`). Degrees of freedom, units and the estimation are the library's
//! (`headalign::calibrate`, docs/how-it-works.md): per camera `fx fy cx cy` (the skew
//! held at zero unless `free_skew`) and the lens coefficients, the rig's rotation and
//! translation direction; residuals in pixels. The translation is a unit vector (in
//! baselines) unless `baseline_m` scales it to metres.
//!
//! Outputs: `K1 D1 K2 D2 R T` (`float64`), the lens model (headalign's short name and
//! OpenCV's), the sigma of every estimated parameter by name and their covariance (in the
//! solver's tangent parametrisation: rotations as rotation vectors, radians), the
//! warnings, the library's report as a dict, and `write(dir)` (every file format of
//! [`headalign_io::export::CalibrationFiles`]).
//!
//! Pitfalls: `D` of a pinhole estimate is OpenCV's `plumb_bob` with five zeros (what
//! `cv2` takes for "no distortion"); the double sphere has no OpenCV model (`lens_model`
//! is `None`, `D` its `xi alpha`, and `write` leaves the OpenCV and ROS files out).

use std::path::{Path, PathBuf};

use headalign::calibrate::{
    CalibrateOptions, CalibrateViewsOptions, Density, LensChoice, StereoViews, ViewsCalibration,
    calibrate_views, lens_terms,
};
use headalign::calibration::StereoCalibration;
use headalign::observations::View;
use headalign::tracking::FrontEndOptions;
use headalign_geometry::distortion::{Distortion, DistortionTerms, LensKind};
use headalign_io::export::CalibrationFiles as _;
use headalign_io::folder::FolderOptions;
use headalign_io::recordings::RecordingOptions;
use headalign_platform::StereoImages;
use nalgebra::DMatrix;
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray1, PyArray2};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::errors::{align_error, file_error, value_error};
use crate::images::stereo_views;
use crate::progress::Progress;

/// A calibrated stereo pair in OpenCV's conventions (module docs).
#[pyclass(module = "headalign", name = "Calibration", frozen)]
pub struct Calibration {
    stereo: StereoCalibration,
    /// headalign's name of the lens model (`pinhole`, `radtan`, `equidistant`, `ds`).
    lens: String,
    /// The sigma of each estimated parameter, by name.
    sigmas: Vec<(String, f64)>,
    covariance_names: Vec<String>,
    covariance: DMatrix<f64>,
    warnings: Vec<String>,
    /// The library's report (`null` when there is none).
    report: serde_json::Value,
}

/// A nalgebra matrix as a `float64` numpy array of its shape.
fn matrix<'py>(py: Python<'py>, m: &DMatrix<f64>) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let rows: Vec<f64> = (0..m.nrows()).flat_map(|r| (0..m.ncols()).map(move |c| m[(r, c)])).collect();
    let array = Array2::from_shape_vec((m.nrows(), m.ncols()), rows)
        .map_err(|e| value_error(format!("matrix: {e}")))?;
    Ok(array.into_pyarray(py))
}

/// `D` of one camera in OpenCV's order (module docs, pitfalls).
fn opencv_distortion(d: &Distortion) -> Vec<f64> {
    match d.kind {
        LensKind::Pinhole => vec![0.0; 5],
        _ => d.coefficients(),
    }
}

/// The intrinsics' sigmas a calibration carries (`left.fx`, ...), where known.
fn file_sigmas(stereo: &StereoCalibration) -> Vec<(String, f64)> {
    let mut out = Vec::new();
    for (side, s) in ["left", "right"].iter().zip(&stereo.sigmas) {
        for (name, v) in [("fx", s.fx), ("fy", s.fy), ("cx", s.cx), ("cy", s.cy), ("skew", s.skew)] {
            if let Some(v) = v {
                out.push((format!("{side}.{name}"), v));
            }
        }
    }
    out
}

impl Calibration {
    /// From the library's stereo calibration; `lens` is headalign's model name.
    pub fn new(
        stereo: StereoCalibration,
        lens: String,
        covariance: Option<&headalign_geometry::bundle::Covariance>,
        warnings: Vec<String>,
        report: serde_json::Value,
    ) -> Self {
        let (covariance_names, covariance) = match covariance {
            Some(c) => (c.names.clone(), c.matrix.clone()),
            None => (Vec::new(), DMatrix::zeros(0, 0)),
        };
        let sigmas = if covariance_names.is_empty() {
            file_sigmas(&stereo)
        } else {
            let diagonal = covariance.diagonal();
            covariance_names
                .iter()
                .zip(diagonal.iter())
                .map(|(n, v)| (n.clone(), v.max(0.0).sqrt()))
                .collect()
        };
        Self { stereo, lens, sigmas, covariance_names, covariance, warnings, report }
    }

    /// A calibration read from a file: its lens named by its model (`pinhole` when every
    /// coefficient is zero), its intrinsics' sigmas where the file has them (headalign's
    /// JSON), no covariance, warnings or report.
    pub fn from_file(stereo: StereoCalibration) -> Self {
        let zero = stereo.distortion.iter().all(|d| d.coefficients().iter().all(|&c| c == 0.0));
        let lens = if zero { "pinhole" } else { stereo.distortion[0].kind.kalibr_name() };
        Self::new(stereo, lens.to_string(), None, Vec::new(), serde_json::Value::Null)
    }

    /// The library's stereo calibration.
    pub fn stereo(&self) -> &StereoCalibration {
        &self.stereo
    }
}

#[pymethods]
impl Calibration {
    /// Left camera matrix, 3x3, pixels.
    #[getter(K1)]
    fn k1<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        matrix(py, &DMatrix::from_iterator(3, 3, self.stereo.left.matrix().iter().copied()))
    }

    /// Right camera matrix, 3x3, pixels.
    #[getter(K2)]
    fn k2<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        matrix(py, &DMatrix::from_iterator(3, 3, self.stereo.right.matrix().iter().copied()))
    }

    /// Left lens coefficients in OpenCV's order (`plumb_bob`: k1 k2 p1 p2 k3; `fisheye`:
    /// k1 k2 k3 k4).
    #[getter(D1)]
    fn d1<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        opencv_distortion(&self.stereo.distortion[0]).into_pyarray(py)
    }

    /// Right lens coefficients, as `D1`.
    #[getter(D2)]
    fn d2<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        opencv_distortion(&self.stereo.distortion[1]).into_pyarray(py)
    }

    /// Rotation from the left camera's frame to the right one's, 3x3.
    #[getter(R)]
    fn r<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let r = self.stereo.right_from_left.rotation.to_rotation_matrix();
        matrix(py, &DMatrix::from_iterator(3, 3, r.matrix().iter().copied()))
    }

    /// Translation from the left camera's frame to the right one's, 3x1 (baselines, or
    /// metres with `baseline_m`: `translation_unit`).
    #[getter(T)]
    fn t<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let t = self.stereo.right_from_left.translation.vector;
        matrix(py, &DMatrix::from_column_slice(3, 1, t.as_slice()))
    }

    /// `(width, height)`, pixels.
    #[getter]
    fn image_size(&self) -> (u32, u32) {
        (self.stereo.image_size[0], self.stereo.image_size[1])
    }

    /// headalign's name of the lens model: `pinhole`, `radtan`, `equidistant` or `ds`.
    #[getter]
    fn lens(&self) -> &str {
        &self.lens
    }

    /// OpenCV's name of the lens model: `plumb_bob` (also for the pinhole, with zero
    /// coefficients) or `fisheye`; `None` for the double sphere.
    #[getter]
    fn lens_model(&self) -> Option<&'static str> {
        match self.stereo.distortion[0].kind {
            LensKind::Pinhole => Some("plumb_bob"),
            kind => kind.model().names().opencv,
        }
    }

    /// `baselines`, or `m` with `baseline_m`: the unit of `T`.
    #[getter]
    fn translation_unit(&self) -> &'static str {
        self.stereo.unit.name()
    }

    /// The standard deviation of every estimated parameter, by name (`left.fx`,
    /// `right.k1`, ...; pixels for the intrinsics, radians for rotations); of a file, the
    /// intrinsics' sigmas it holds.
    #[getter]
    fn sigmas<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for (name, sigma) in &self.sigmas {
            d.set_item(name, sigma)?;
        }
        Ok(d)
    }

    /// The covariance of the parameters named by `covariance_names`, in that order.
    #[getter]
    fn covariance<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        matrix(py, &self.covariance)
    }

    /// The names of the rows and columns of `covariance`.
    #[getter]
    fn covariance_names(&self) -> Vec<String> {
        self.covariance_names.clone()
    }

    /// What the estimate's checks found doubtful, one line each.
    #[getter]
    fn warnings(&self) -> Vec<String> {
        self.warnings.clone()
    }

    /// The library's report (views used, tracks, residuals, lens choice, ...) as a dict,
    /// or `None`.
    #[getter]
    fn report<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let text = serde_json::to_string(&self.report).map_err(|e| value_error(format!("report: {e}")))?;
        py.import("json")?.call_method1("loads", (text,))
    }

    /// Write every calibration file into `dir` (created if missing): `calibration.json`,
    /// `opencv_stereo.yaml`, `left.yaml` and `right.yaml` (ROS `camera_info`),
    /// `camchain.yaml` (Kalibr). Returns the paths written.
    fn write(&self, py: Python<'_>, dir: PathBuf) -> PyResult<Vec<PathBuf>> {
        py.detach(|| self.stereo.write_all(&dir)).map_err(align_error)
    }

    fn __repr__(&self) -> String {
        let (l, r) = (&self.stereo.left, &self.stereo.right);
        format!(
            "Calibration(image_size=({}, {}), lens='{}', left fx={:.2} fy={:.2}, right fx={:.2} fy={:.2}, {} warning(s))",
            self.stereo.image_size[0],
            self.stereo.image_size[1],
            self.lens,
            l.fx,
            l.fy,
            r.fx,
            r.fy,
            self.warnings.len()
        )
    }
}

/// The options of `calibrate`, as the CLI's flags of the same names set them.
pub struct CalibrateArgs {
    /// `pinhole`, `radtan`, `equidistant`, `ds` or `auto`.
    pub lens: String,
    /// `radial`, `4` or `5` (`None`: the model's default; all terms for `auto`).
    pub lens_terms: Option<String>,
    /// Estimate the skews.
    pub free_skew: bool,
    /// `fx = fy` in both cameras.
    pub square_pixels: bool,
    /// Principal points held at the image centre.
    pub fix_principal_point: bool,
    /// Corners per image, no retry (`None`: 1500, then 3000 if weak).
    pub corners: Option<usize>,
    /// Seed of the robust estimators.
    pub seed: u64,
    /// Read every N-th pair of a folder or recording.
    pub every: usize,
}

impl CalibrateArgs {
    /// The library's options (the CLI's `calibrate::options` and `views_options` for the
    /// same flags); a bad option is a `ValueError` with the CLI's message.
    fn options(&self) -> PyResult<CalibrateViewsOptions> {
        let lens = LensChoice::parse(&self.lens).ok_or_else(|| {
            value_error(format!(
                "unknown lens model '{}': pinhole, radtan, equidistant, ds or auto",
                self.lens
            ))
        })?;
        let terms =
            match &self.lens_terms {
                None => None,
                Some(t) => Some(DistortionTerms::parse(t).ok_or_else(|| {
                    value_error(format!("unknown lens terms '{t}': radial (k1 k2), 4 or 5"))
                })?),
            };
        if lens == LensChoice::Pinhole && terms.is_some() {
            return Err(value_error(
                "lens_terms needs a lens model to estimate (lens='radtan', 'equidistant' or 'auto')",
            ));
        }
        if lens == LensChoice::Model(LensKind::Equidistant) && terms == Some(DistortionTerms::Full5) {
            return Err(value_error(
                "lens_terms '5' adds the radial-tangential k3; the equidistant model has four coefficients (lens_terms='4')",
            ));
        }
        let mut calibrate = CalibrateOptions {
            zero_skew: !self.free_skew,
            square_pixels: self.square_pixels,
            fix_principal_point: self.fix_principal_point,
            lens,
            lens_terms: lens_terms(lens, terms),
            ..CalibrateOptions::default()
        };
        calibrate.estimation.seed = self.seed;
        let density = self.corners.map_or_else(Density::default, Density::fixed);
        let mut front_end = FrontEndOptions::default();
        front_end.features.max_features = density.corners;
        let options = CalibrateViewsOptions {
            calibrate,
            front_end,
            density,
            automatic_density: self.corners.is_none(),
            lenses: None,
        };
        options.validate().map_err(align_error)?;
        if self.every == 0 {
            return Err(value_error("every must be at least 1"));
        }
        Ok(options)
    }
}

/// What `calibrate` and `check` are given: images in memory, or a path.
pub enum Source {
    /// Named stereo views from numpy arrays.
    Images(Vec<(String, StereoImages)>),
    /// A folder, session or recording.
    Path(PathBuf),
}

impl Source {
    /// `views` of the Python API: a path (`str` or `os.PathLike`), or a list of pairs.
    pub fn of(views: &Bound<'_, PyAny>) -> PyResult<Self> {
        match views.extract::<PathBuf>() {
            Ok(path) => Ok(Source::Path(path)),
            Err(_) => Ok(Source::Images(stereo_views(views)?)),
        }
    }

    /// The views, a path read as `headalign calibrate DIR` reads it (every `every`-th
    /// pair); call without the GIL.
    pub fn read(self, every: usize) -> PyResult<Views> {
        match self {
            Source::Images(images) => Ok(Views::Images(images)),
            Source::Path(path) => read_path(&path, every),
        }
    }
}

/// The views of a [`Source`].
pub enum Views {
    /// Stereo images, to be tracked.
    Images(Vec<(String, StereoImages)>),
    /// A point session's tracked points.
    Tracked(Vec<View>),
}

impl Views {
    /// The library's view of them.
    pub fn stereo_views(&self) -> StereoViews<'_> {
        match self {
            Views::Images(images) => StereoViews::Images(images),
            Views::Tracked(tracked) => StereoViews::Tracked(tracked),
        }
    }

    /// Image size of the first view (`None`: no views).
    pub fn image_size(&self) -> Option<[u32; 2]> {
        match self {
            Views::Images(images) => images.first().map(|(_, v)| v.image_size()),
            Views::Tracked(tracked) => tracked.first().map(|v| v.capture.image_size),
        }
    }

    /// How many views.
    pub fn count(&self) -> usize {
        match self {
            Views::Images(images) => images.len(),
            Views::Tracked(tracked) => tracked.len(),
        }
    }
}

/// Read `path` (module docs) with every `every`-th pair.
fn read_path(path: &Path, every: usize) -> PyResult<Views> {
    if headalign_io::recordings::detect(path).is_some() {
        let options = RecordingOptions { every, ..RecordingOptions::default() };
        let rec = headalign_io::recordings::read_recording(path, &options).map_err(align_error)?;
        return Ok(Views::Images(rec.views.into_iter().map(|v| (v.name, v.images)).collect()));
    }
    if headalign_io::session::is_point_session(path) {
        let views = headalign_io::session::read_point_session(path).map_err(align_error)?;
        return Ok(Views::Tracked(views.into_iter().map(|r| r.view).collect()));
    }
    let views = headalign_io::folder::read_folder(path, &FolderOptions { every }, &mut |_, _| {})
        .map_err(file_error)?;
    Ok(Views::Images(views))
}

/// Run the library on `source` without the GIL.
fn run(
    py: Python<'_>,
    source: Source,
    options: &CalibrateViewsOptions,
    every: usize,
    progress: &Progress,
) -> PyResult<ViewsCalibration> {
    py.detach(|| {
        let views = source.read(every)?;
        calibrate_views(views.stereo_views(), options, &mut |p| progress.views(p)).map_err(align_error)
    })
}

/// Self-calibrate a stereo rig from views related by rigid motions of the whole rig
/// (the Python wrapper `headalign.calibrate` documents the arguments).
#[pyfunction]
#[pyo3(signature = (views, lens, lens_terms, free_skew, square_pixels, fix_principal_point, corners, seed, baseline_m, every, progress))]
#[allow(clippy::too_many_arguments)] // one per keyword argument of the Python API
pub fn calibrate(
    py: Python<'_>,
    views: &Bound<'_, PyAny>,
    lens: String,
    lens_terms: Option<String>,
    free_skew: bool,
    square_pixels: bool,
    fix_principal_point: bool,
    corners: Option<usize>,
    seed: u64,
    baseline_m: Option<f64>,
    every: usize,
    progress: Option<Py<PyAny>>,
) -> PyResult<Calibration> {
    let args = CalibrateArgs {
        lens,
        lens_terms,
        free_skew,
        square_pixels,
        fix_principal_point,
        corners,
        seed,
        every,
    };
    let options = args.options()?;
    if let Some(b) = baseline_m
        && !(b.is_finite() && b > 0.0)
    {
        return Err(value_error(format!("baseline must be positive, got {b}")));
    }
    let source = Source::of(views)?;
    let r = run(py, source, &options, args.every, &Progress::new(progress))?;
    let cal = r.calibration;
    let state = &cal.bundle.state;
    let mut stereo =
        StereoCalibration::from_bundle(&cal.bundle, r.image_size, baseline_m).map_err(align_error)?;
    stereo.distortion = [state.left_distortion, state.right_distortion];
    let lens_name = match (options.calibrate.lens, &cal.report.lens_selection) {
        (LensChoice::Pinhole, _) => "pinhole",
        (LensChoice::Auto, Some(sel)) if sel.spec.kind.is_none() => "pinhole",
        _ => stereo.distortion[0].kind.kalibr_name(),
    };
    let report = serde_json::to_value(&cal.report).map_err(|e| value_error(format!("report: {e}")))?;
    Ok(Calibration::new(
        stereo,
        lens_name.to_string(),
        Some(&cal.bundle.covariance),
        cal.report.warnings.clone(),
        report,
    ))
}
