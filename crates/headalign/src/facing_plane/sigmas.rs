//! Step 6 of the planar route ([`super`] module docs): the sigmas of the aligned readings.
//!
//! Each camera's covariance (intrinsics in pixels, axis directions as tangent components
//! in radians, [`super::CameraPlanar::parameter_names`]) is propagated to the aligned
//! joint changes (elevation, left and right vergence; degrees) by central differences of
//! [`solve_alignment_axes`] at [`PROPAGATION_STEP_SIGMAS`] of each parameter's standard
//! deviation, as the general route's [`crate::procedure::alignment_sigmas`]; the two
//! cameras are estimated separately, so their contributions add. Pitfalls: linear; a
//! difference that fails on either side contributes nothing.

use headalign_geometry::plane::tangent_basis;
use headalign_platform::Encoders;
use nalgebra::{DMatrix, Unit};

use super::{CameraPlanar, PlanarCalibration};
use crate::alignment::{AlignmentSigmas, CameraAxes, PROPAGATION_STEP_SIGMAS, solve_alignment_axes};
use crate::error::AlignError;

/// Camera `c`'s axes with parameter `i` ([`CameraPlanar::parameter_names`]) moved by `h`.
fn moved(c: &CameraPlanar, i: usize, h: f64) -> CameraAxes {
    let mut axes = c.axes();
    let name = c.parameter_names[i].as_str();
    match name {
        "fx" => axes.intrinsics.fx += h,
        "fy" => axes.intrinsics.fy += h,
        "cx" => axes.intrinsics.cx += h,
        "cy" => axes.intrinsics.cy += h,
        _ => {
            let tangent = |a: &mut Unit<nalgebra::Vector3<f64>>| {
                let (b1, b2) = tangent_basis(a);
                let b = if name.ends_with("dir0") { b1 } else { b2 };
                *a = Unit::new_normalize(a.into_inner() + b * h);
            };
            if name.starts_with("pan.") {
                tangent(&mut axes.pan);
            } else if name.starts_with("elevation.") {
                tangent(&mut axes.elevation);
            } else if let Some(v) = axes.verge.as_mut() {
                tangent(v);
            }
        }
    }
    axes
}

/// The aligned deltas (elevation, left vergence, right vergence), degrees.
fn deltas(left: &CameraAxes, right: &CameraAxes, reference: &Encoders) -> Option<[f64; 3]> {
    let s = solve_alignment_axes(left, right, reference).ok()?;
    Some([s.delta_elevation_deg, s.delta_verge_left_deg, s.delta_verge_right_deg])
}

/// Propagate both cameras' covariances to the aligned readings (module docs).
pub fn alignment_sigmas(calib: &PlanarCalibration) -> Result<AlignmentSigmas, AlignError> {
    let reference = calib.reference_encoders;
    let mut cov = DMatrix::<f64>::zeros(3, 3);
    for (is_left, cam) in [(true, &calib.left), (false, &calib.right)] {
        let n = cam.parameter_names.len();
        let mut jac = DMatrix::<f64>::zeros(3, n);
        for i in 0..n {
            let sigma = cam.covariance[(i, i)].max(0.0).sqrt();
            if !(sigma > 0.0 && sigma.is_finite()) {
                continue;
            }
            let h = PROPAGATION_STEP_SIGMAS * sigma;
            let eval = |step: f64| {
                let m = moved(cam, i, step);
                if is_left {
                    deltas(&m, &calib.right.axes(), &reference)
                } else {
                    deltas(&calib.left.axes(), &m, &reference)
                }
            };
            if let (Some(p), Some(q)) = (eval(h), eval(-h)) {
                for r in 0..3 {
                    jac[(r, i)] = (p[r] - q[r]) / (2.0 * h);
                }
            }
        }
        cov += &jac * &cam.covariance * jac.transpose();
    }
    Ok(AlignmentSigmas {
        elevation_deg: cov[(0, 0)].max(0.0).sqrt(),
        verge_left_deg: cov[(1, 1)].max(0.0).sqrt(),
        verge_right_deg: cov[(2, 2)].max(0.0).sqrt(),
    })
}
