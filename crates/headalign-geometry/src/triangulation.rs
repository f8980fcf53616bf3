//! Triangulation of matched pixels into homogeneous 3D points.
//!
//! What it computes:
//! - [`optimal_correction`]: the pair `(x̂_l, x̂_r)` closest to a measured match (sum of
//!   squared pixel distances, the maximum-likelihood correction under isotropic Gaussian
//!   noise) that satisfies `x̂_r^T F x̂_l = 0` exactly. Lindstrom, "Triangulation made
//!   easy" (CVPR 2010): the correction is along the constraint's normals with a common
//!   multiplier, found by solving the (exact) quadratic in that multiplier; we iterate
//!   his scheme to a fixed point (at most 10 rounds, usually 2 as in `niter2`), which
//!   satisfies the first-order optimality conditions. Equivalent to Hartley-Sturm's
//!   polynomial method (Hartley & Zisserman 2nd ed., section 12.5, Algorithm 12.1) without
//!   its degree-6 polynomial.
//! - [`triangulate_linear`] / [`triangulate_views`]: the homogeneous DLT (H&Z section
//!   12.2): two rows `x p3^T - p1^T`, `y p3^T - p2^T` per view, each scaled to unit norm,
//!   null vector by SVD. Works for any projective cameras (not only `K[R|t]`), e.g.
//!   `P_L = K0 [I|0]`, `P_R = K0 [M | e]`.
//! - [`triangulate_optimal`]: correction, then the linear method (exact intersection of
//!   the corrected rays).
//!
//! Degrees of freedom: a 3D point has 3; results are unit-norm homogeneous 4-vectors
//! with `w >= 0` (projective: points at infinity, `w = 0`, are allowed).
//!
//! Units: pixels for all image quantities.
//!
//! Pitfalls handled: the linear system is only 4 x 4 (thin SVD is fine); degenerate
//! geometry (the two rays coincide, the point lies on the baseline, cameras identical)
//! shows as a second vanishing singular value and is an error; a match at the epipoles
//! (vanishing constraint gradient) cannot be corrected and is an error unless it already
//! satisfies the constraint.

use nalgebra::{DMatrix, Matrix2, Point2, Vector2, Vector3, Vector4};

use crate::camera::ProjectiveCamera;
use crate::fundamental::FundamentalMatrix;
use crate::linear::SVD_MAX_ITER;
use crate::{GeometryError, Result};

/// Maximum rounds of Lindstrom's iteration.
const CORRECTION_MAX_ITER: usize = 10;

/// Optimal correction of a match `(left, right)` to satisfy `x_r^T F x_l = 0` (see the
/// module documentation). Pixels in, pixels out.
pub fn optimal_correction(
    f: &FundamentalMatrix,
    left: &Point2<f64>,
    right: &Point2<f64>,
) -> Result<(Point2<f64>, Point2<f64>)> {
    let fm = &f.0;
    if !fm.iter().all(|v| v.is_finite())
        || !left.coords.iter().chain(right.coords.iter()).all(|v| v.is_finite())
    {
        return Err(GeometryError::Numerical("non-finite input to optimal correction".into()));
    }
    // Lindstrom's notation with x = right, x' = left, E = F: constraint x^T E x' = 0.
    let xl = Vector3::new(left.x, left.y, 1.0);
    let xr = Vector3::new(right.x, right.y, 1.0);
    let e2: Matrix2<f64> = fm.fixed_view::<2, 2>(0, 0).into_owned(); // S F S^T
    let c0 = xr.dot(&(fm * xl));
    // Normals at the measured points: n_r = S F x_l, n_l = S F^T x_r.
    let n0_r: Vector2<f64> = (fm * xl).xy();
    let n0_l: Vector2<f64> = (fm.transpose() * xr).xy();
    let scale = (n0_r.norm_squared() + n0_l.norm_squared()).sqrt();
    if c0 == 0.0 {
        return Ok((*left, *right));
    }
    let mut hat_l = xl;
    let mut hat_r = xr;
    let mut prev = f64::INFINITY;
    for _ in 0..CORRECTION_MAX_ITER {
        // Normals at the current estimate; the correction from the *measured* points is
        // lambda times them: x̂_r = x_r - S^T lambda n_r, x̂_l = x_l - S^T lambda n_l.
        let n_r: Vector2<f64> = (fm * hat_l).xy();
        let n_l: Vector2<f64> = (fm.transpose() * hat_r).xy();
        // Constraint (exact): c0 - lambda (n_r . n0_r + n_l . n0_l) + lambda^2 n_r^T E2 n_l = 0.
        let a = n_r.dot(&(e2 * n_l));
        let b = 0.5 * (n_r.dot(&n0_r) + n_l.dot(&n0_l));
        let disc = (b * b - a * c0).max(0.0);
        let denom = b + b.signum() * disc.sqrt();
        if denom == 0.0 || !denom.is_finite() {
            return Err(GeometryError::Degenerate(format!(
                "match at the epipoles: constraint gradient vanishes (|grad| = {scale:e})"
            )));
        }
        let lambda = c0 / denom; // the root of smaller magnitude
        let dl = n_l * lambda;
        let dr = n_r * lambda;
        hat_l = Vector3::new(xl.x - dl.x, xl.y - dl.y, 1.0);
        hat_r = Vector3::new(xr.x - dr.x, xr.y - dr.y, 1.0);
        let cost = dl.norm_squared() + dr.norm_squared();
        if (prev - cost).abs() <= 1e-15 * cost.max(1e-300) {
            break;
        }
        prev = cost;
    }
    Ok((Point2::new(hat_l.x, hat_l.y), Point2::new(hat_r.x, hat_r.y)))
}

/// Null vector of a DLT system with unit-norm rows; errors when the null space is not
/// one-dimensional (to 1e-10 relative).
fn dlt_point(rows: &[nalgebra::RowVector4<f64>]) -> Result<Vector4<f64>> {
    let m = rows.len();
    let mut a = DMatrix::zeros(m.max(4), 4);
    for (i, r) in rows.iter().enumerate() {
        let n = r.norm();
        if !n.is_finite() || n == 0.0 {
            return Err(GeometryError::Degenerate("zero or non-finite triangulation row".into()));
        }
        a.row_mut(i).copy_from(&(r / n));
    }
    let svd = a
        .try_svd(false, true, f64::EPSILON, SVD_MAX_ITER)
        .ok_or_else(|| GeometryError::Numerical("SVD did not converge in triangulation".into()))?;
    let v_t = svd.v_t.ok_or_else(|| GeometryError::Numerical("SVD without V".into()))?;
    let s = svd.singular_values;
    if s[2].is_nan() || s[2] <= 1e-10 * s[0] {
        return Err(GeometryError::Degenerate(
            "rays do not determine a point (coincident rays or cameras)".into(),
        ));
    }
    let mut x = Vector4::new(v_t[(3, 0)], v_t[(3, 1)], v_t[(3, 2)], v_t[(3, 3)]);
    x /= x.norm();
    if x.w < 0.0 {
        x = -x;
    }
    Ok(x)
}

fn rows_for(p: &ProjectiveCamera, x: &Point2<f64>) -> [nalgebra::RowVector4<f64>; 2] {
    let p = &p.0;
    [p.row(2) * x.x - p.row(0), p.row(2) * x.y - p.row(1)]
}

/// Linear (DLT) triangulation from two views: unit-norm homogeneous point, `w >= 0`.
pub fn triangulate_linear(
    p_left: &ProjectiveCamera,
    p_right: &ProjectiveCamera,
    left: &Point2<f64>,
    right: &Point2<f64>,
) -> Result<Vector4<f64>> {
    let [a, b] = rows_for(p_left, left);
    let [c, d] = rows_for(p_right, right);
    dlt_point(&[a, b, c, d])
}

/// Optimal correction with `F` (which must be the fundamental matrix of the two cameras),
/// then linear triangulation of the corrected pair.
pub fn triangulate_optimal(
    f: &FundamentalMatrix,
    p_left: &ProjectiveCamera,
    p_right: &ProjectiveCamera,
    left: &Point2<f64>,
    right: &Point2<f64>,
) -> Result<Vector4<f64>> {
    let (l, r) = optimal_correction(f, left, right)?;
    triangulate_linear(p_left, p_right, &l, &r)
}

/// Linear (DLT) triangulation from `n >= 2` views.
pub fn triangulate_views(cameras: &[ProjectiveCamera], pixels: &[Point2<f64>]) -> Result<Vector4<f64>> {
    if cameras.len() != pixels.len() {
        return Err(GeometryError::InvalidOption(format!(
            "{} cameras but {} pixels",
            cameras.len(),
            pixels.len()
        )));
    }
    if cameras.len() < 2 {
        return Err(GeometryError::NotEnoughData {
            what: "views to triangulate",
            needed: 2,
            got: cameras.len(),
        });
    }
    let rows: Vec<_> = cameras.iter().zip(pixels).flat_map(|(p, x)| rows_for(p, x)).collect();
    dlt_point(&rows)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fundamental::tests::random_scene;
    use nalgebra::Matrix3x4;
    use proptest::prelude::*;

    fn reproj(p: &ProjectiveCamera, x: &Vector4<f64>, px: &Point2<f64>) -> f64 {
        (p.project(x).unwrap() - px).norm()
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(128))]

        #[test]
        fn linear_noise_free_recovers_points(seed in 0u64..1_000_000) {
            let s = random_scene(seed, 10, 0.0);
            let (pl, pr) = (s.p_left(), s.p_right());
            for (x, (l, r)) in s.points.iter().zip(&s.pairs) {
                let h = triangulate_linear(&pl, &pr, l, r).unwrap();
                prop_assert!((h.norm() - 1.0).abs() < 1e-14 && h.w >= 0.0);
                let p = h.xyz() / h.w;
                // 1e-9 relative: 4x4 SVD with unit rows, condition ~ depth / baseline.
                prop_assert!((p - x.coords).norm() < 1e-9 * x.coords.norm(), "{}", (p - x.coords).norm());
            }
        }

        #[test]
        fn projective_cameras_work(seed in 0u64..1_000_000) {
            // P_L = K0 [I | 0], P_R = K0 [M | e]: a projective frame, not K[R|t].
            let s = random_scene(seed, 10, 0.0);
            let h = nalgebra::Matrix4::new(
                1.0, 0.1, 0.0, 0.2,
                0.0, 1.2, -0.1, 0.0,
                0.05, 0.0, 0.9, 0.1,
                0.01, -0.02, 0.03, 1.0,
            );
            let h_inv = h.try_inverse().unwrap();
            // Cameras P H^-1 and points H X give the same images.
            let pl = ProjectiveCamera(s.p_left().0 * h_inv);
            let pr = ProjectiveCamera(s.p_right().0 * h_inv);
            for (x, (l, r)) in s.points.iter().zip(&s.pairs) {
                let y = triangulate_linear(&pl, &pr, l, r).unwrap();
                let truth = h * x.to_homogeneous();
                let truth = truth / truth.norm() * truth.w.signum();
                // 1e-9: as above, plus the conditioning of H (~2).
                prop_assert!((y - truth).norm() < 1e-9, "{}", (y - truth).norm());
            }
        }

        #[test]
        fn correction_satisfies_constraint_and_is_optimal(seed in 0u64..1_000_000) {
            let s = random_scene(seed, 10, 1.0);
            let clean = random_scene(seed, 10, 0.0);
            let f = crate::fundamental::FundamentalMatrix(clean.f_true());
            for ((l, r), (lt, rt)) in s.pairs.iter().zip(&clean.pairs) {
                let (cl, cr) = optimal_correction(&f, l, r).unwrap();
                // 1e-9 px: the quadratic in lambda is exact, rounding in pixel units.
                prop_assert!(f.sampson_distance(&cl, &cr) < 1e-9, "{}", f.sampson_distance(&cl, &cr));
                let cost = (cl - l).norm_squared() + (cr - r).norm_squared();
                // The noise-free pair satisfies the constraint: the optimum is no farther.
                let truth_cost = (lt - l).norm_squared() + (rt - r).norm_squared();
                prop_assert!(cost <= truth_cost + 1e-9);
                // First-order: cost ~ Sampson error to within a few percent for 1 px noise.
                let sd = f.sampson_distance(l, r).powi(2);
                prop_assert!((cost - sd).abs() <= 0.05 * sd + 1e-12, "{cost} vs {sd}");
                // KKT: corrections parallel to the constraint normals with one multiplier.
                let xl = Vector3::new(cl.x, cl.y, 1.0);
                let xr = Vector3::new(cr.x, cr.y, 1.0);
                let nl = (f.0.transpose() * xr).xy();
                let nr = (f.0 * xl).xy();
                let dl = l - cl;
                let dr = r - cr;
                let lam = (dl.dot(&nl) + dr.dot(&nr)) / (nl.norm_squared() + nr.norm_squared());
                prop_assert!((dl - nl * lam).norm() < 1e-6 * (1.0 + dl.norm()));
                prop_assert!((dr - nr * lam).norm() < 1e-6 * (1.0 + dr.norm()));
            }
        }

        #[test]
        fn optimal_triangulation_noisy_is_sensible(seed in 0u64..1_000_000) {
            let s = random_scene(seed, 10, 0.5);
            let clean = random_scene(seed, 10, 0.0);
            let f = crate::fundamental::FundamentalMatrix(clean.f_true());
            let (pl, pr) = (s.p_left(), s.p_right());
            for (l, r) in &s.pairs {
                let x = triangulate_optimal(&f, &pl, &pr, l, r).unwrap();
                // Reprojection of the optimal point: a few sigma at most.
                let e = (reproj(&pl, &x, l).powi(2) + reproj(&pr, &x, r).powi(2)).sqrt();
                prop_assert!(e < 5.0, "{e}");
                // The corrected pair is reprojected exactly.
                let (cl, cr) = optimal_correction(&f, l, r).unwrap();
                prop_assert!(reproj(&pl, &x, &cl) < 1e-6 && reproj(&pr, &x, &cr) < 1e-6);
            }
        }

        #[test]
        fn n_views_match_two_views(seed in 0u64..1_000_000) {
            let s = random_scene(seed, 5, 0.0);
            let (pl, pr) = (s.p_left(), s.p_right());
            for (x, (l, r)) in s.points.iter().zip(&s.pairs) {
                let y = triangulate_views(&[pl, pr, pl], &[*l, *r, *l]).unwrap();
                prop_assert!((y.xyz() / y.w - x.coords).norm() < 1e-9 * x.coords.norm());
            }
        }
    }

    #[test]
    fn degenerate_inputs_give_errors() {
        let s = random_scene(1, 3, 0.0);
        let pl = s.p_left();
        let (l, _) = s.pairs[0];
        // Same camera twice: the rays coincide.
        assert!(triangulate_linear(&pl, &pl, &l, &l).is_err());
        assert!(triangulate_views(&[pl], &[l]).is_err());
        assert!(triangulate_views(&[pl, pl], &[l]).is_err());
        let zero = ProjectiveCamera(Matrix3x4::zeros());
        assert!(triangulate_linear(&zero, &pl, &l, &l).is_err());
        let f = crate::fundamental::FundamentalMatrix(s.f_true());
        assert!(optimal_correction(&f, &Point2::new(f64::NAN, 0.0), &l).is_err());
        // At both epipoles the gradient vanishes; a match there satisfies the constraint.
        let (el, er) = f.epipoles().unwrap();
        let pel = Point2::new(el.x / el.z, el.y / el.z);
        let per = Point2::new(er.x / er.z, er.y / er.z);
        let out = optimal_correction(&f, &pel, &per);
        assert!(out.is_ok() || matches!(out, Err(GeometryError::Degenerate(_))));
    }
}
