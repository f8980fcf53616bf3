//! Invariant lines of a rotation (paper section 3.1-3.2 steps 5-7,
//! `docs/how-it-works.md#invariant-lines-and-the-fixation-point`).
//!
//! A rigid motion `D` rotating by `theta` about an axis has eigenvalues `1, 1, e^{+-i theta}`.
//! The complex-conjugate eigenvectors `V, conj(V)` of `D` (or of any projective
//! `H ~ H_PE^-1 D H_PE`) span the line at infinity perpendicular to the axis; `Re(V)` and
//! `Im(V)` are two real points on it. Projected by a camera `P` they give two image points
//! whose join is the image of that line (for a pan rotation: the horizon). The lines of two
//! rotations meet at the vanishing point of the direction perpendicular to both axes:
//! fixating it aligns the camera. This needs no calibration.
//!
//! Eigenvectors come from faer's general eigen-decomposition (complex pairs to ~1e-15);
//! the complex pair is the eigenvalue pair with the largest imaginary part. Pitfall: with
//! noise an estimated `H` may have no complex pair at all (rotation too small for the
//! noise): that is an error, not a guess. Results are homogeneous: image lines `l` with
//! `l . x = 0`, unit norm; points unit norm.

use faer::Mat;
use nalgebra::{Matrix3x4, Matrix4, Vector3, Vector4};

use crate::{GeometryError, Result};

/// Two real points `(Re V, Im V)` spanning the invariant line at infinity of `h`
/// (each unit norm).
pub fn invariant_points(h: &Matrix4<f64>) -> Result<(Vector4<f64>, Vector4<f64>)> {
    if h.iter().any(|v| !v.is_finite()) {
        return Err(GeometryError::InvalidEstimate("homography is not finite".into()));
    }
    let m = Mat::<f64>::from_fn(4, 4, |i, j| h[(i, j)]);
    let eig =
        m.eigen().map_err(|e| GeometryError::Numerical(format!("eigen-decomposition failed: {e:?}")))?;
    let s = eig.S();
    let u = eig.U();
    let vals = s.column_vector();
    let mut best = None;
    let mut best_im = 0.0;
    for i in 0..4 {
        let im = vals[i].im;
        if im > best_im {
            best_im = im;
            best = Some(i);
        }
    }
    let scale = (0..4).map(|i| vals[i].norm()).fold(0.0, f64::max);
    let i = match best {
        Some(i) if best_im > 1e-12 * scale => i,
        _ => {
            return Err(GeometryError::InvalidEstimate(
                "homography has no complex eigenvalue pair: not a measurable rotation".into(),
            ));
        }
    };
    let re = Vector4::from_fn(|r, _| u[(r, i)].re);
    let im = Vector4::from_fn(|r, _| u[(r, i)].im);
    let (nr, ni) = (re.norm(), im.norm());
    if nr < 1e-12 || ni < 1e-12 {
        return Err(GeometryError::Numerical("degenerate complex eigenvector".into()));
    }
    Ok((re / nr, im / ni))
}

/// The image of the invariant line at infinity of `h` in a camera `p` (unit norm).
pub fn invariant_image_line(h: &Matrix4<f64>, p: &Matrix3x4<f64>) -> Result<Vector3<f64>> {
    let (a, b) = invariant_points(h)?;
    let l = (p * a).cross(&(p * b));
    let n = l.norm();
    if !n.is_finite() || n <= 0.0 {
        return Err(GeometryError::Degenerate("invariant line projects to a point".into()));
    }
    Ok(l / n)
}

/// Intersection of two image lines (homogeneous, unit norm). Errors if they are parallel
/// in the projective sense (identical).
pub fn intersect_lines(a: &Vector3<f64>, b: &Vector3<f64>) -> Result<Vector3<f64>> {
    let x = a.cross(b);
    let n = x.norm();
    if n < 1e-12 * a.norm() * b.norm() {
        return Err(GeometryError::Degenerate("the two invariant lines coincide".into()));
    }
    Ok(x / n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;
    use crate::selfcal::euclidean_upgrade;
    use crate::so3::{Line, rotation_about_line};
    use nalgebra::{Point3, Unit};
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(128))]
        /// The invariant line of a rotation about axis `a`, seen by `K [I|0]`, is the
        /// vanishing line `K^-T a`; the two lines of two rotations meet at `K (a1 x a2)`.
        /// Tolerance 1e-9: eigenvectors of a 4x4 to ~1e-15, amplified by the conditioning
        /// of the projective frame (entries O(1)) and small rotation angles.
        #[test]
        fn lines_match_vanishing_lines(ax in -0.3..0.3f64, az in -0.3..0.3f64, angle in 0.03..0.5f64, px in -0.5..0.5f64, pz in -0.5..0.5f64, pl in -0.3..0.3f64) {
            let k = Intrinsics { fx: 700.0, fy: 720.0, skew: 0.0, cx: 390.0, cy: 284.0 };
            let kn = Intrinsics { fx: 0.9, fy: 0.95, skew: 0.0, cx: 0.01, cy: -0.02 };
            let plane = Vector4::new(pl, 0.1, -pl, 1.0);
            let h_pe = euclidean_upgrade(&kn, &plane).unwrap();
            let inv = h_pe.try_inverse().unwrap();
            let a1 = Unit::new_normalize(Vector3::new(ax, -1.0, az));
            let a2 = Unit::new_normalize(Vector3::new(1.0, az, ax));
            let h1 = inv * rotation_about_line(&Line::new(a1, Point3::new(px, 0.1, pz)), angle).to_homogeneous() * h_pe;
            let h2 = inv * rotation_about_line(&Line::new(a2, Point3::new(0.0, px, pz)), -angle).to_homogeneous() * h_pe;
            // The projective camera whose Euclidean counterpart is K [I|0]: K kn^-1 ... in
            // conditioned coordinates the left camera is [I|0] and its calibration is kn.
            let p = Matrix3x4::identity();
            let l1 = invariant_image_line(&h1, &p).unwrap();
            let expected1 = (kn.inverse_matrix().transpose() * a1.into_inner()).normalize();
            prop_assert!(l1.cross(&expected1).norm() < 1e-9);
            let l2 = invariant_image_line(&h2, &p).unwrap();
            let x = intersect_lines(&l1, &l2).unwrap();
            let expected = (kn.matrix() * a1.cross(&a2)).normalize();
            prop_assert!(x.cross(&expected).norm() < 1e-9);
            let _ = k;
        }
    }

    #[test]
    fn identity_has_no_invariant_line() {
        assert!(invariant_points(&Matrix4::identity()).is_err());
        let mut bad = Matrix4::identity();
        bad[(0, 0)] = f64::NAN;
        assert!(invariant_points(&bad).is_err());
        let l = Vector3::new(1.0, 2.0, 3.0);
        assert!(intersect_lines(&l, &(l * 2.0)).is_err());
    }
}
