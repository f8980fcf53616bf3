//! Known lens models for self-calibration from observations ([`super`] module docs, "Lens
//! distortion"): a camera's radial/tangential distortion, given with the intrinsics its
//! coefficients were estimated with, removed from every observation before the pinhole
//! chain runs ([`undistort_views`]), and read from an OpenCV FileStorage YAML file
//! ([`read_opencv_lenses`]).
//!
//! Degrees of freedom: none estimated here (the model is known; `k1, k2, p1, p2, k3` in
//! OpenCV's convention, normalised by the model's own `K`). Units: pixels in and out.
//!
//! Pitfalls: an observation outside the model's valid range (where the undistortion does
//! not converge, or gives a non-finite pixel) is dropped, not kept distorted. The model's
//! `K` normalises the pixels: coefficients are meaningless with another camera's `K`. The
//! YAML reader is a small parser of the FileStorage matrices it needs (`M1 D1 M2 D2`, or
//! `camera_matrix` and `distortion_coefficients`), not a general YAML parser.

use headalign_geometry::camera::Intrinsics;
use headalign_geometry::distortion::{Distortion, LensKind};
use headalign_platform::{StereoCapture, TrackObservation};

use crate::error::AlignError;
use crate::observations::View;

/// A camera's known lens: the intrinsics its distortion coefficients belong to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensModel {
    /// Intrinsics the coefficients were estimated with (they normalise the pixels).
    pub k: Intrinsics,
    /// The distortion.
    pub distortion: Distortion,
}

/// The views with every observation undistorted (`lenses[0]` left, `[1]` right); an
/// observation that cannot be undistorted (outside the lens model's valid range) is
/// dropped.
pub fn undistort_views(views: &[View], lenses: &[LensModel; 2]) -> Vec<View> {
    let fix = |list: &[TrackObservation], lens: &LensModel| -> Vec<TrackObservation> {
        list.iter()
            .filter_map(|o| {
                let pixel = lens.distortion.undistort_pixel(&lens.k, &o.pixel).ok()?;
                (pixel.x.is_finite() && pixel.y.is_finite())
                    .then_some(TrackObservation { track: o.track, pixel })
            })
            .collect()
    };
    views
        .iter()
        .map(|v| View {
            name: v.name.clone(),
            capture: StereoCapture {
                left: fix(&v.capture.left, &lenses[0]),
                right: fix(&v.capture.right, &lenses[1]),
                ..v.capture.clone()
            },
        })
        .collect()
}

/// Parse the numbers of an OpenCV FileStorage matrix `name: !!opencv-matrix ... data: [...]`
/// (or an inline `name: [ ... ]`), in the file's (row-major) order.
pub fn opencv_matrix(text: &str, name: &str) -> Option<Vec<f64>> {
    let key = format!("{name}:");
    let start = text.lines().scan(0usize, |pos, line| {
        let here = *pos;
        *pos += line.len() + 1;
        Some((here, line))
    });
    let (offset, _) = start.into_iter().find(|(_, line)| line.trim_start().starts_with(&key))?;
    let rest = &text[offset..];
    let open = rest.find('[')?;
    // The data must belong to this key: no other top-level key before the bracket.
    let before = &rest[key.len()..open];
    if before.lines().skip(1).any(|l| !l.starts_with(' ') && !l.trim().is_empty()) {
        return None;
    }
    let close = rest[open..].find(']')? + open;
    rest[open + 1..close].split(',').map(|v| v.trim().parse::<f64>().ok()).collect()
}

/// The value of a top-level scalar `name: value` (quotes and a trailing comment removed),
/// if present.
pub fn scalar(text: &str, name: &str) -> Option<String> {
    let key = format!("{name}:");
    let line = text.lines().find(|l| l.starts_with(&key))?;
    let value = line[key.len()..].split('#').next()?.trim().trim_matches(|c| c == '"' || c == '\'');
    (!value.is_empty()).then(|| value.to_string())
}

/// Both cameras' lens models from an OpenCV FileStorage YAML: `M1 D1 M2 D2` (OpenCV's
/// stereo sample and headalign's `opencv_stereo.yaml`), or a single camera's
/// `camera_matrix` and `distortion_coefficients` (used for both; a ROS `camera_info`).
/// The coefficients are radial-tangential unless a `distortion_model` key names the
/// equidistant model (`fisheye`, `equidistant`; per camera `distortion_model_1`/`_2`).
/// `origin` names the file in messages.
pub fn read_opencv_lenses(text: &str, origin: &str) -> Result<[LensModel; 2], AlignError> {
    let bad = |m: String| AlignError::InvalidOption(format!("{origin}: {m}"));
    // The model of `D1` / `D2` (or of the single camera's coefficients): the YAML's
    // `distortion_model[_1|_2]` key, radial-tangential (`plumb_bob`) when absent.
    let model = |keys: &[&str]| -> Result<LensKind, AlignError> {
        match keys.iter().find_map(|k| scalar(text, k)) {
            None => Ok(LensKind::RadialTangential),
            Some(name) => LensKind::parse(&name).ok_or_else(|| {
                bad(format!(
                    "distortion model '{name}' is not supported (plumb_bob/radtan or fisheye/equidistant)"
                ))
            }),
        }
    };
    let lens = |m: &str, d: &str| -> Result<Option<LensModel>, AlignError> {
        let (Some(mv), Some(dv)) = (opencv_matrix(text, m), opencv_matrix(text, d)) else {
            return Ok(None);
        };
        if mv.len() != 9 {
            return Err(bad(format!("{m} has {} numbers, a 3x3 matrix has 9", mv.len())));
        }
        let k = Intrinsics::from_matrix(&nalgebra::Matrix3::from_row_slice(&mv))
            .map_err(|e| bad(format!("{m}: {e}")))?;
        let keys: &[&str] = match d {
            "D1" => &["distortion_model_1", "distortion_model"],
            "D2" => &["distortion_model_2", "distortion_model"],
            _ => &["distortion_model"],
        };
        let distortion =
            Distortion::from_coefficients(model(keys)?, &dv).map_err(|e| bad(format!("{d}: {e}")))?;
        Ok(Some(LensModel { k, distortion }))
    };
    if let (Some(l), Some(r)) = (lens("M1", "D1")?, lens("M2", "D2")?) {
        return Ok([l, r]);
    }
    if let Some(one) = lens("camera_matrix", "distortion_coefficients")? {
        return Ok([one, one]);
    }
    Err(bad("no lens found: expected M1, D1, M2, D2 or camera_matrix and distortion_coefficients (OpenCV FileStorage matrices)".into()))
}
