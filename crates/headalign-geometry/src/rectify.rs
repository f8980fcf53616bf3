//! Stereo rectification of a calibrated pair: the rotations and new projection matrices
//! that make epipolar lines horizontal rows, in the form OpenCV (`stereoRectify`: `R1`,
//! `R2`, `P1`, `P2`, `Q`) and ROS `camera_info` (`R`, `P`) expect.
//!
//! Algorithm: Fusiello, Trucco & Verri, "A compact algorithm for rectification of stereo
//! pairs" (MVA 2000), with the symmetric choice of the new optical axis:
//! - new x axis `r1`: the baseline, from the left camera centre to the right one;
//! - new y axis `r2 = z x r1` normalised, `z` the mean of the two optical axes, so that
//!   both cameras turn by about the same amount;
//! - new z axis `r3 = r1 x r2`.
//!
//! Both rectified cameras share the orientation `rect_from_left = [r1; r2; r3]`
//! (`R1`), `R2 = rect_from_left * left_from_right`, and one focal length `f` (the mean of
//! the four focal lengths: no image is shrunk or stretched much) and one principal row
//! `cy` (the mean of the rows where the two image centres land), so that a scene point
//! has the same row in both rectified images. Each camera keeps its own principal column
//! (where its image centre lands), so disparities stay small; `Q` accounts for it.
//!
//! Degrees of freedom: none are estimated; this is a closed-form function of `K_L`, `K_R`
//! and `right_from_left` (6 + 5 + 5 dof in). Units: pixels for `f, cx, cy`; the baseline
//! and the last column of `P2` carry the translation's unit (metres if the rig is metric,
//! baselines if the calibration is only up to scale).
//!
//! Pitfalls: a zero baseline (pure rotation between the cameras) cannot be rectified (an
//! error); the mean optical axis must not be parallel to the baseline (cameras looking
//! along the baseline, also an error). Lens distortion is not modelled here.

use nalgebra::{Isometry3, Matrix3, Matrix3x4, Matrix4, Vector3};

use crate::camera::Intrinsics;
use crate::{GeometryError, Result};

/// A rectified stereo pair in OpenCV's and ROS's conventions.
#[derive(Debug, Clone, PartialEq)]
pub struct Rectification {
    /// `R1`: rotation from the left camera frame to the rectified left frame.
    pub rect_from_left: Matrix3<f64>,
    /// `R2`: rotation from the right camera frame to the rectified right frame.
    pub rect_from_right: Matrix3<f64>,
    /// `P1 = K1' [I | 0]` in the rectified left frame.
    pub p_left: Matrix3x4<f64>,
    /// `P2 = K2' [I | (-B, 0, 0)]` in the rectified left frame's axes.
    pub p_right: Matrix3x4<f64>,
    /// `Q`: reprojection of `(x, y, disparity, 1)` to homogeneous 3D points in the
    /// rectified left frame (disparity = `x_left - x_right`).
    pub q: Matrix4<f64>,
    /// Baseline length, in the unit of the input translation.
    pub baseline: f64,
}

/// Rectify a calibrated pair (see the module documentation). `right_from_left` maps points
/// in the left camera frame to the right one.
pub fn rectify_stereo(
    left: &Intrinsics,
    right: &Intrinsics,
    right_from_left: &Isometry3<f64>,
    image_size: [u32; 2],
) -> Result<Rectification> {
    let left_from_right = right_from_left.inverse();
    let r_lr = left_from_right.rotation.to_rotation_matrix().into_inner();
    // Right camera centre in the left frame: the baseline vector.
    let b = left_from_right.translation.vector;
    let baseline = b.norm();
    if !baseline.is_finite() || baseline < 1e-12 {
        return Err(GeometryError::Degenerate("stereo baseline is zero: cannot rectify".into()));
    }
    let r1 = b / baseline;
    let z = Vector3::z() + r_lr * Vector3::z();
    let r2 = z.cross(&r1);
    if r2.norm() < 1e-9 * z.norm() {
        return Err(GeometryError::Degenerate("cameras look along the baseline: cannot rectify".into()));
    }
    let r2 = r2.normalize();
    let r3 = r1.cross(&r2);
    let rect_from_left = Matrix3::from_rows(&[r1.transpose(), r2.transpose(), r3.transpose()]);
    let rect_from_right = rect_from_left * r_lr;

    let f = (left.fx + left.fy + right.fx + right.fy) / 4.0;
    if !f.is_finite() || f <= 0.0 {
        return Err(GeometryError::InvalidEstimate("focal lengths must be positive".into()));
    }
    // Where each image centre lands in its rectified image (before choosing cx, cy):
    // direction in the rectified frame, then normalised coordinates times f.
    let [w, h] = image_size;
    let centre = Vector3::new((f64::from(w) - 1.0) / 2.0, (f64::from(h) - 1.0) / 2.0, 1.0);
    let land = |k: &Intrinsics, rect_from_cam: &Matrix3<f64>| -> Result<(f64, f64)> {
        let d = rect_from_cam * (k.inverse_matrix() * centre);
        if d.z <= 1e-9 * d.norm() {
            return Err(GeometryError::Degenerate(
                "an image centre looks behind the rectified camera: rotation too large".into(),
            ));
        }
        Ok((f * d.x / d.z, f * d.y / d.z))
    };
    let (xl, yl) = land(left, &rect_from_left)?;
    let (xr, yr) = land(right, &rect_from_right)?;
    let cy = centre.y - (yl + yr) / 2.0;
    let (cx1, cx2) = (centre.x - xl, centre.x - xr);
    let k1 = Matrix3::new(f, 0.0, cx1, 0.0, f, cy, 0.0, 0.0, 1.0);
    let k2 = Matrix3::new(f, 0.0, cx2, 0.0, f, cy, 0.0, 0.0, 1.0);
    let mut p_left = Matrix3x4::zeros();
    p_left.fixed_view_mut::<3, 3>(0, 0).copy_from(&k1);
    let mut p_right = Matrix3x4::zeros();
    p_right.fixed_view_mut::<3, 3>(0, 0).copy_from(&k2);
    // K2 [I | (-B, 0, 0)]: last column -f B in x.
    p_right[(0, 3)] = -f * baseline;
    // OpenCV's Q with Tx = -B: [[1,0,0,-cx1],[0,1,0,-cy],[0,0,0,f],[0,0,-1/Tx,(cx1-cx2)/Tx]].
    let tx = -baseline;
    let q = Matrix4::new(
        1.0,
        0.0,
        0.0,
        -cx1,
        0.0,
        1.0,
        0.0,
        -cy,
        0.0,
        0.0,
        0.0,
        f,
        0.0,
        0.0,
        -1.0 / tx,
        (cx1 - cx2) / tx,
    );
    Ok(Rectification { rect_from_left, rect_from_right, p_left, p_right, q, baseline })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point3, Translation3, UnitQuaternion, Vector4};
    use proptest::prelude::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_rig(seed: u64) -> (Intrinsics, Intrinsics, Isometry3<f64>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut k = || {
            let mut k = Intrinsics::new(
                rng.random_range(500.0..900.0),
                rng.random_range(500.0..900.0),
                rng.random_range(350.0..420.0),
                rng.random_range(260.0..310.0),
            );
            k.skew = rng.random_range(-1.0..1.0);
            k
        };
        let (kl, kr) = (k(), k());
        let rot = UnitQuaternion::from_euler_angles(
            rng.random_range(-0.05..0.05),
            rng.random_range(-0.2..0.2),
            rng.random_range(-0.05..0.05),
        );
        let t = Vector3::new(
            -rng.random_range(0.1..0.4),
            rng.random_range(-0.02..0.02),
            rng.random_range(-0.02..0.02),
        );
        (kl, kr, Isometry3::from_parts(Translation3::from(t), rot))
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(128))]

        #[test]
        fn rectified_rows_agree_and_match_the_cameras(seed in 0u64..1_000_000) {
            let (kl, kr, right_from_left) = random_rig(seed);
            let r = rectify_stereo(&kl, &kr, &right_from_left, [768, 576]).unwrap();
            // Rotations are rotations.
            for m in [r.rect_from_left, r.rect_from_right] {
                prop_assert!((m * m.transpose() - Matrix3::identity()).norm() < 1e-12);
                prop_assert!((m.determinant() - 1.0).abs() < 1e-12);
            }
            let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 1);
            for _ in 0..10 {
                let x_left = Point3::new(rng.random_range(-2.0..2.0), rng.random_range(-1.0..1.0), rng.random_range(1.5..8.0));
                // Rectified pixels via P1, P2 on the point in the rectified left frame.
                let x_rect = r.rect_from_left * x_left.coords;
                let h = Vector4::new(x_rect.x, x_rect.y, x_rect.z, 1.0);
                let (a, b) = (r.p_left * h, r.p_right * h);
                let (ul, vl, ur, vr) = (a.x / a.z, a.y / a.z, b.x / b.z, b.y / b.z);
                // Same row: 1e-9 px (exact arithmetic on pixel values ~1e3).
                prop_assert!((vl - vr).abs() < 1e-9, "{vl} vs {vr}");
                // The rectified pixel is the original pixel mapped by K' R K^-1 (each camera).
                let pl = kl.matrix() * x_left.coords;
                let hl = r.p_left.fixed_view::<3, 3>(0, 0) * r.rect_from_left * kl.inverse_matrix() * pl;
                prop_assert!((hl.x / hl.z - ul).abs() < 1e-8 && (hl.y / hl.z - vl).abs() < 1e-8);
                let x_right = right_from_left * x_left;
                let pr = kr.matrix() * x_right.coords;
                let hr = r.p_right.fixed_view::<3, 3>(0, 0) * r.rect_from_right * kr.inverse_matrix() * pr;
                prop_assert!((hr.x / hr.z - ur).abs() < 1e-8 && (hr.y / hr.z - vr).abs() < 1e-8);
                // Q reprojects (u, v, disparity) to the point in the rectified left frame.
                let q = r.q * Vector4::new(ul, vl, ul - ur, 1.0);
                let back = q.xyz() / q.w;
                prop_assert!((back - x_rect).norm() < 1e-9 * x_rect.norm(), "{}", (back - x_rect).norm());
            }
        }
    }

    #[test]
    fn degenerate_rigs_are_errors() {
        let k = Intrinsics::new(700.0, 700.0, 384.0, 288.0);
        assert!(rectify_stereo(&k, &k, &Isometry3::identity(), [768, 576]).is_err());
        // Looking along the baseline.
        let along = Isometry3::translation(0.0, 0.0, -0.3);
        assert!(rectify_stereo(&k, &k, &along, [768, 576]).is_err());
    }
}
