//! The Python extension module `headalign._headalign` (PyO3, rust-numpy): the library's
//! stereo self-calibration ([`headalign::calibrate::calibrate_views`]), verge/tilt
//! alignment ([`headalign::procedure::align_session_detecting`]) and calibration check
//! ([`headalign::check::check_views`]) called in process, with
//! numpy arrays in and out; the Python package `headalign` (`python/headalign/`) wraps it
//! with keyword arguments, type stubs and a progress bar. No subprocess, no temporary
//! files. The API and its conventions are in docs/python.md.
//!
//! What it computes: nothing of its own. It converts (numpy `uint8` images to the
//! library's [`headalign_platform::GrayImage`], the library's results to `float64`
//! arrays), reads paths with the readers the CLI uses ([`headalign_io::folder`],
//! [`headalign_io::recordings`], [`headalign_io::session`],
//! [`headalign_io::observations`], [`headalign_io::import`]) and writes files with
//! [`headalign_io::export::CalibrationFiles`].
//!
//! Conventions (OpenCV's, so that `cv2.stereoRectify(K1, D1, K2, D2, size, R, T)` takes
//! the arrays as they are): `K` is 3x3 in pixels; `D` is the lens model's coefficients in
//! OpenCV's order (`plumb_bob`: `k1 k2 p1 p2 k3`; `fisheye`: `k1 k2 k3 k4`, for
//! `cv2.fisheye`); `R, T` map a point from the left camera's frame to the right one's
//! (`x_right = R x_left + T`, as `cv2.stereoCalibrate` returns them), `T` in baselines
//! unless the baseline length is given; `image_size` is `(width, height)`.
//!
//! Errors: bad input (dtype, shape, sizes, options, unreadable paths) raises `ValueError`
//! with the library's or the CLI's one-line message; a failed estimation raises
//! `RuntimeError`; writing files raises `OSError`. No `unwrap` on a data path: a panic
//! would reach Python as PyO3's `PanicException`, never abort the interpreter.
//!
//! Pitfalls: long calls release the GIL ([`Python::detach`]); the progress callback takes
//! it back for each report (a few per view), and an exception it raises is printed as
//! unraisable and does not stop the estimation. Colour (3-D) arrays are refused, not
//! converted: whether they are RGB or BGR (OpenCV) cannot be told from the array, and the
//! grey levels would differ.

use pyo3::prelude::*;

mod alignment;
mod calibration;
mod check;
mod errors;
mod images;
mod progress;

/// The module `headalign._headalign`.
#[pymodule]
#[pyo3(name = "_headalign")]
fn headalign_module(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<calibration::Calibration>()?;
    m.add_class::<alignment::Alignment>()?;
    m.add_class::<check::Check>()?;
    m.add_function(wrap_pyfunction!(calibration::calibrate, m)?)?;
    m.add_function(wrap_pyfunction!(alignment::align, m)?)?;
    m.add_function(wrap_pyfunction!(check::check, m)?)?;
    m.add_function(wrap_pyfunction!(check::read_calibration, m)?)?;
    m.add_function(wrap_pyfunction!(images::read_image, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
