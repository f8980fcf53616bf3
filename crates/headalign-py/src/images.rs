//! numpy images in and out: a list of `(left, right)` arrays checked and copied into the
//! library's stereo views, and `read_image` (a PNG or JPEG file as a `uint8` array, by
//! the library's own decoder, so that tests and scripts need neither OpenCV nor PIL).
//!
//! The rules (each broken one is a `ValueError` naming the view and the image): an image
//! is a numpy array of dtype `uint8` with two dimensions `(height, width)` (a trailing
//! axis of length 1 is accepted and dropped); the left and right images of a pair have the
//! same size; every pair has the size of the first (one rig, one camera mode). Colour
//! arrays are refused with the conversion to use (`lib.rs`, pitfalls). Views are named
//! `view00`, `view01`, ... in list order, with zero encoder readings (a fixed rig moved
//! as a whole, as a folder of stereo pairs is read).
//!
//! Pitfalls: arrays of any strides are accepted (a slice, a transposed view): they are
//! copied row by row into the library's contiguous buffer while the GIL is held, so the
//! estimation that follows (without the GIL) never touches Python memory.

use headalign_platform::{Encoders, GrayImage, StereoImages};
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray2, PyArrayDyn, PyArrayMethods, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::errors::value_error;

/// One image of view `view` (`side`: `left` or `right`) as the library's grey image.
fn gray_image(array: &Bound<'_, PyAny>, view: usize, side: &str) -> PyResult<GrayImage> {
    let what = format!("view {view}: the {side} image");
    let Ok(untyped) = array.cast::<PyUntypedArray>() else {
        let type_name = array.get_type().name().map(|n| n.to_string()).unwrap_or_default();
        return Err(value_error(format!("{what} is a {type_name}, not a numpy array")));
    };
    let dtype = untyped.dtype();
    let dtype_name = dtype.str().map(|s| s.to_string()).unwrap_or_default();
    let shape = untyped.shape().to_vec();
    let shape_text = shape.iter().map(|n| n.to_string()).collect::<Vec<_>>().join("x");
    let Ok(bytes) = array.cast::<PyArrayDyn<u8>>() else {
        return Err(value_error(format!(
            "{what} has dtype {dtype_name}; headalign reads 8-bit grey images (numpy uint8): convert it first, e.g. (img * 255).round().astype(numpy.uint8) for floats in 0..1"
        )));
    };
    let (height, width) = match shape.as_slice() {
        [h, w] | [h, w, 1] => (*h, *w),
        [_, _, c] => {
            return Err(value_error(format!(
                "{what} is {shape_text} ({c} channels); headalign reads grey images (height x width): convert it first, e.g. cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) for OpenCV's BGR"
            )));
        }
        _ => {
            return Err(value_error(format!(
                "{what} has shape {shape_text}; an image is a 2-D array (height x width)"
            )));
        }
    };
    let readonly = bytes.try_readonly().map_err(|e| value_error(format!("{what}: {e}")))?;
    let view2 = readonly.as_array();
    let data: Vec<u8> = view2.iter().copied().collect();
    let (w, h) = (u32::try_from(width), u32::try_from(height));
    let (Ok(w), Ok(h)) = (w, h) else {
        return Err(value_error(format!("{what} is {shape_text}: too large")));
    };
    GrayImage::new(w, h, data).map_err(|e| value_error(format!("{what}: {e}")))
}

/// The named stereo views of a list of `(left, right)` arrays (module docs).
pub fn stereo_views(pairs: &Bound<'_, PyAny>) -> PyResult<Vec<(String, StereoImages)>> {
    let mut views: Vec<(String, StereoImages)> = Vec::new();
    for (i, item) in pairs.try_iter()?.enumerate() {
        let item = item?;
        let pair: Vec<Bound<'_, PyAny>> = item
            .try_iter()
            .and_then(|it| it.collect::<PyResult<Vec<_>>>())
            .map_err(|_| value_error(format!("view {i}: expected a (left, right) pair of images")))?;
        let [left, right] = pair.as_slice() else {
            return Err(value_error(format!(
                "view {i}: expected a (left, right) pair of images, got {} items",
                pair.len()
            )));
        };
        let (left, right) = (gray_image(left, i, "left")?, gray_image(right, i, "right")?);
        let images = StereoImages::new(Encoders::default(), left, right)
            .map_err(|e| value_error(format!("view {i}: {e}")))?;
        if let Some((_, first)) = views.first()
            && first.image_size() != images.image_size()
        {
            let ([w0, h0], [w, h]) = (first.image_size(), images.image_size());
            return Err(value_error(format!(
                "view {i}: the images are {w}x{h} but the first pair's are {w0}x{h0} (one rig, one image size)"
            )));
        }
        views.push((format!("view{i:02}"), images));
    }
    if views.is_empty() {
        return Err(value_error("no views: give a list of (left, right) image pairs"));
    }
    Ok(views)
}

/// An image as a `(height, width)` `uint8` array.
pub fn to_numpy<'py>(py: Python<'py>, image: &GrayImage) -> PyResult<Bound<'py, PyArray2<u8>>> {
    let shape = (image.height() as usize, image.width() as usize);
    let array = Array2::from_shape_vec(shape, image.pixels().to_vec())
        .map_err(|e| value_error(format!("image buffer: {e}")))?;
    Ok(array.into_pyarray(py))
}

/// Read a PNG or JPEG file as a grey `uint8` array of shape `(height, width)` (colour
/// files are converted to luma, 16-bit ones scaled to 8 bits, as `calibrate` reads them).
#[pyfunction]
pub fn read_image<'py>(py: Python<'py>, path: std::path::PathBuf) -> PyResult<Bound<'py, PyArray2<u8>>> {
    let image = py
        .detach(|| GrayImage::load(&path))
        .map_err(|e| value_error(format!("'{}': {e}", path.display())))?;
    to_numpy(py, &image)
}
