//! Projective homographies of 3D space, `Y ~ H X`.
//!
//! What it computes: a 4x4 matrix `H` defined up to scale (15 degrees of freedom) mapping
//! homogeneous points of one projective reconstruction onto another — for a stereo head,
//! the reconstruction of the initial view onto that of a moved view, with the same rig
//! cameras `P_L`, `P_R` in both (`H ~ H_PE^-1 D H_PE`,
//! `docs/how-it-works.md#the-3d-homography-of-a-rotation`).
//!
//! Algorithms (Hartley & Zisserman 2nd ed.):
//! - [`Homography3::dlt`]: the DLT of section 4.1 (Algorithm 4.2, normalised DLT)
//!   transposed to P^3 (section 4.9 / exercise; 3 independent equations per point,
//!   `y_w (H x)_i - y_i (H x)_w = 0`, i = 0..2), so 5 points in general position are a
//!   minimal set. Each point set is conditioned (dehomogenised, centroid to 0, mean
//!   distance sqrt 3), the null vector comes from an SVD, conditioning is undone.
//! - [`symmetric_transfer_error`]: the symmetric transfer error of section 4.2.2
//!   over four images: `H x` projected by `P_L`, `P_R` into the moved view and `H^-1 y`
//!   into the initial view; RMS of the four image distances, in pixels.
//! - [`Homography3Estimator`]: RANSAC (section 4.7) with 5-point samples.
//! - [`refine_transfer`]: Levenberg-Marquardt (appendix A6) over the 16 entries of `H`
//!   (scale fixed by renormalising to unit Frobenius norm after each step; the damping
//!   handles the scale direction of the normal equations) on the summed squared forward
//!   and backward transfer distances, analytic Jacobian.
//!
//! Units: residuals and thresholds in pixels.
//!
//! Pitfalls handled: points at (or numerically near) infinity cannot be conditioned and
//! are an error in the DLT; four coplanar points among five (or any configuration whose
//! DLT null space has dimension > 1) is [`GeometryError::Degenerate`]; a singular `H`
//! is an error; a projection at infinity gives an infinite transfer error (an outlier),
//! not a panic. Scaling `H` cannot change the sign of its determinant (`det(l H) = l^4
//! det H`), so an `H` with negative determinant is not conjugate to a rigid motion
//! ([`Homography3::normalized_det`] reports it).

use nalgebra::{DMatrix, Matrix4, Point2, SMatrix, SVector, Vector3, Vector4};

use crate::camera::ProjectiveCamera;
use crate::linear::smallest_right_singular_vectors;
use crate::ransac::Estimator;
use crate::{GeometryError, Result};

/// A 3D projective homography, `Y ~ H X`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Homography3(pub Matrix4<f64>);

/// Conditioning of a point set: dehomogenise, centroid to 0, mean distance sqrt 3.
fn conditioning(points: &[Vector4<f64>]) -> Result<(Matrix4<f64>, Vec<Vector3<f64>>)> {
    let mut e = Vec::with_capacity(points.len());
    for p in points {
        if !p.iter().all(|v| v.is_finite()) || p.w.abs() <= 1e-10 * p.xyz().norm() || p.w == 0.0 {
            return Err(GeometryError::Degenerate("point at infinity (or non-finite) in 3D DLT".into()));
        }
        e.push(p.xyz() / p.w);
    }
    let n = e.len() as f64;
    let c = e.iter().sum::<Vector3<f64>>() / n;
    let mean = e.iter().map(|p| (p - c).norm()).sum::<f64>() / n;
    if !mean.is_finite() || mean <= 1e-12 * (1.0 + c.norm()) {
        return Err(GeometryError::Degenerate("all 3D points coincide".into()));
    }
    let s = 3f64.sqrt() / mean;
    let mut t = Matrix4::identity() * s;
    t[(3, 3)] = 1.0;
    t.fixed_view_mut::<3, 1>(0, 3).copy_from(&(-c * s));
    let cond = e.iter().map(|p| (p - c) * s).collect();
    Ok((t, cond))
}

impl Homography3 {
    /// Conditioned DLT from `>= 5` pairs `y_i ~ H x_i` (see the module documentation).
    ///
    /// Errors: fewer than 5 pairs or mismatched lengths, points at infinity, coincident
    /// points, degenerate configurations (null space of dimension > 1, e.g. four of five
    /// points coplanar), singular result, SVD failure.
    pub fn dlt(x: &[Vector4<f64>], y: &[Vector4<f64>]) -> Result<Self> {
        if x.len() != y.len() {
            return Err(GeometryError::InvalidOption(format!(
                "{} x points but {} y points",
                x.len(),
                y.len()
            )));
        }
        if x.len() < 5 {
            return Err(GeometryError::NotEnoughData {
                what: "3D homography pairs",
                needed: 5,
                got: x.len(),
            });
        }
        let (tx, xc) = conditioning(x)?;
        let (ty, yc) = conditioning(y)?;
        let mut a = DMatrix::zeros(3 * x.len(), 16);
        for (k, (xi, yi)) in xc.iter().zip(&yc).enumerate() {
            let xh = [xi.x, xi.y, xi.z, 1.0];
            for i in 0..3 {
                let row = 3 * k + i;
                for j in 0..4 {
                    // y_w (H x)_i - y_i (H x)_w with y_w = 1.
                    a[(row, 4 * i + j)] = xh[j];
                    a[(row, 12 + j)] = -yi[i] * xh[j];
                }
            }
        }
        let (v, sv) = smallest_right_singular_vectors(&a, 1)?;
        // Entries of the conditioned system are O(1): a second (near) null vector below
        // 1e-8 of the largest singular value means the solution is not unique.
        if sv[14].is_nan() || sv[14] <= 1e-8 * sv[0] {
            return Err(GeometryError::Degenerate(
                "3D DLT null space has dimension > 1 (e.g. four coplanar points)".into(),
            ));
        }
        let hc = Matrix4::from_row_slice(v[0].as_slice());
        let ty_inv =
            ty.try_inverse().ok_or_else(|| GeometryError::Numerical("singular conditioning".into()))?;
        let h = ty_inv * hc * tx;
        let n = h.norm();
        let h = h / n;
        let sv_h = h
            .try_svd(false, false, f64::EPSILON, crate::linear::SVD_MAX_ITER)
            .ok_or_else(|| GeometryError::Numerical("SVD of H did not converge".into()))?
            .singular_values;
        if sv_h[3].is_nan() || sv_h[3] <= 1e-12 * sv_h[0] {
            return Err(GeometryError::Degenerate("3D homography is singular".into()));
        }
        Ok(Self(h))
    }

    /// The inverse matrix (exact inverse, `H * H^-1 = I`). Errors if `H` is singular.
    pub fn inverse(&self) -> Result<Self> {
        let n = self.0.norm();
        let d = self.0.determinant();
        if !d.is_finite() || !n.is_finite() || d.abs() <= 1e-14 * n.powi(4) {
            return Err(GeometryError::Degenerate("3D homography is singular".into()));
        }
        self.0
            .try_inverse()
            .map(Self)
            .ok_or_else(|| GeometryError::Degenerate("3D homography is singular".into()))
    }

    /// Scaled to determinant +1, with the sign making the trace non-negative.
    ///
    /// Errors with [`GeometryError::InvalidEstimate`] when `det H <= 0` (no scale can fix
    /// the sign: not conjugate to a rigid motion), or non-finite entries.
    pub fn normalized_det(&self) -> Result<Self> {
        let d = self.0.determinant();
        if !d.is_finite() {
            return Err(GeometryError::Numerical("non-finite determinant".into()));
        }
        if d <= 0.0 {
            return Err(GeometryError::InvalidEstimate(format!(
                "det H = {d:e} <= 0: not conjugate to a rigid motion"
            )));
        }
        let mut h = self.0 * d.powf(-0.25);
        if h.trace() < 0.0 {
            h = -h;
        }
        Ok(Self(h))
    }

    /// `H x`.
    pub fn transform(&self, x: &Vector4<f64>) -> Vector4<f64> {
        self.0 * x
    }
}

/// Correspondence of one scene point over two stereo views (four images).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Quadruplet {
    /// Projective point triangulated in the initial view from `(left0, right0)`.
    pub x: Vector4<f64>,
    /// Projective point triangulated in the moved view from `(left1, right1)`.
    pub y: Vector4<f64>,
    /// Left pixel, initial view.
    pub left0: Point2<f64>,
    /// Right pixel, initial view.
    pub right0: Point2<f64>,
    /// Left pixel, moved view.
    pub left1: Point2<f64>,
    /// Right pixel, moved view.
    pub right1: Point2<f64>,
}

/// `H` with its inverse (both used by the symmetric transfer error).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TransferModel {
    /// `Y ~ H X`.
    pub h: Homography3,
    /// `H^-1`.
    pub h_inv: Homography3,
}

impl TransferModel {
    /// Model from `H`, computing the inverse.
    pub fn new(h: Homography3) -> Result<Self> {
        Ok(Self { h_inv: h.inverse()?, h })
    }
}

fn dist(p: &ProjectiveCamera, x: &Vector4<f64>, px: &Point2<f64>) -> Option<f64> {
    let q = p.project(x)?;
    let d = (q - px).norm_squared();
    d.is_finite().then_some(d)
}

/// Symmetric transfer error over four images, pixels: `sqrt((d1^2 + d2^2 + d3^2 +
/// d4^2) / 4)` with `d1, d2` the distances of `P_L H x`, `P_R H x` to `left1`, `right1`
/// and `d3, d4` those of `P_L H^-1 y`, `P_R H^-1 y` to `left0`, `right0`; +infinity if a
/// projection is at infinity.
pub fn symmetric_transfer_error(
    model: &TransferModel,
    p_left: &ProjectiveCamera,
    p_right: &ProjectiveCamera,
    q: &Quadruplet,
) -> f64 {
    let hx = model.h.transform(&q.x);
    let hy = model.h_inv.transform(&q.y);
    let parts = [
        dist(p_left, &hx, &q.left1),
        dist(p_right, &hx, &q.right1),
        dist(p_left, &hy, &q.left0),
        dist(p_right, &hy, &q.right0),
    ];
    let mut s = 0.0;
    for p in parts {
        match p {
            Some(d) => s += d,
            None => return f64::INFINITY,
        }
    }
    (s / 4.0).sqrt()
}

/// RANSAC estimator of a 3D homography from quadruplets: 5-point DLT samples, DLT on all
/// inliers as polish, symmetric transfer error residual (pixels).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Homography3Estimator {
    /// Left camera of the rig (both views).
    pub p_left: ProjectiveCamera,
    /// Right camera of the rig (both views).
    pub p_right: ProjectiveCamera,
}

fn fit_indices(data: &[Quadruplet], idx: &[usize]) -> Option<TransferModel> {
    let x: Vec<_> = idx.iter().map(|&i| data[i].x).collect();
    let y: Vec<_> = idx.iter().map(|&i| data[i].y).collect();
    TransferModel::new(Homography3::dlt(&x, &y).ok()?).ok()
}

impl Estimator for Homography3Estimator {
    type Datum = Quadruplet;
    type Model = TransferModel;

    fn sample_size(&self) -> usize {
        5
    }

    fn fit_minimal(&self, data: &[Quadruplet], sample: &[usize]) -> Vec<TransferModel> {
        fit_indices(data, sample).into_iter().collect()
    }

    fn fit_inliers(&self, data: &[Quadruplet], inliers: &[usize]) -> Option<TransferModel> {
        fit_indices(data, inliers)
    }

    fn residual(&self, model: &TransferModel, q: &Quadruplet) -> f64 {
        symmetric_transfer_error(model, &self.p_left, &self.p_right, q)
    }
}

/// Pixel residual `proj(P z) - px` and its Jacobian with respect to `z` (2 x 4).
fn proj_residual(
    p: &ProjectiveCamera,
    z: &Vector4<f64>,
    px: &Point2<f64>,
) -> Option<([f64; 2], SMatrix<f64, 2, 4>)> {
    let h = p.0 * z;
    if h.z.abs() < 1e-300 || !h.iter().all(|v| v.is_finite()) {
        return None;
    }
    let iw = 1.0 / h.z;
    let u = h.x * iw;
    let v = h.y * iw;
    let mut j = SMatrix::<f64, 2, 4>::zeros();
    for c in 0..4 {
        j[(0, c)] = (p.0[(0, c)] - u * p.0[(2, c)]) * iw;
        j[(1, c)] = (p.0[(1, c)] - v * p.0[(2, c)]) * iw;
    }
    Some(([u - px.x, v - px.y], j))
}

/// The 8 transfer residuals of a quadruplet (forward left, forward right, backward left,
/// backward right; x then y) and their Jacobian with respect to the 16 entries of `H`
/// (row-major). `None` when a projection is at infinity.
fn transfer_residuals(
    h: &Matrix4<f64>,
    h_inv: &Matrix4<f64>,
    pl: &ProjectiveCamera,
    pr: &ProjectiveCamera,
    q: &Quadruplet,
) -> Option<(SVector<f64, 8>, SMatrix<f64, 8, 16>)> {
    let hx = h * q.x;
    let gy = h_inv * q.y;
    let mut r = SVector::<f64, 8>::zeros();
    let mut j = SMatrix::<f64, 8, 16>::zeros();
    // Forward: d(H x)/dH_ab = e_a x_b.
    for (k, (p, px)) in [(pl, &q.left1), (pr, &q.right1)].into_iter().enumerate() {
        let (res, jz) = proj_residual(p, &hx, px)?;
        for i in 0..2 {
            r[2 * k + i] = res[i];
            for a in 0..4 {
                for b in 0..4 {
                    j[(2 * k + i, 4 * a + b)] = jz[(i, a)] * q.x[b];
                }
            }
        }
    }
    // Backward: d(H^-1 y) = -H^-1 dH H^-1 y, so d/dH_ab = -H^-1 e_a (H^-1 y)_b.
    for (k, (p, px)) in [(pl, &q.left0), (pr, &q.right0)].into_iter().enumerate() {
        let (res, jz) = proj_residual(p, &gy, px)?;
        let jzg = jz * h_inv; // 2 x 4
        for i in 0..2 {
            r[4 + 2 * k + i] = res[i];
            for a in 0..4 {
                for b in 0..4 {
                    j[(4 + 2 * k + i, 4 * a + b)] = -jzg[(i, a)] * gy[b];
                }
            }
        }
    }
    Some((r, j))
}

fn transfer_cost(
    h: &Matrix4<f64>,
    pl: &ProjectiveCamera,
    pr: &ProjectiveCamera,
    quads: &[Quadruplet],
) -> f64 {
    let Some(h_inv) = h.try_inverse() else { return f64::INFINITY };
    let mut c = 0.0;
    for q in quads {
        match transfer_residuals(h, &h_inv, pl, pr, q) {
            Some((r, _)) => c += r.norm_squared(),
            None => return f64::INFINITY,
        }
    }
    c
}

/// Levenberg-Marquardt refinement of `H` on the summed squared forward and backward
/// transfer distances (pixels^2) over `quads` (at least 5). Never increases the cost.
pub fn refine_transfer(
    model: &TransferModel,
    p_left: &ProjectiveCamera,
    p_right: &ProjectiveCamera,
    quads: &[Quadruplet],
) -> Result<TransferModel> {
    if quads.len() < 5 {
        return Err(GeometryError::NotEnoughData {
            what: "quadruplets to refine H",
            needed: 5,
            got: quads.len(),
        });
    }
    let n0 = model.h.0.norm();
    if !n0.is_finite() || n0 == 0.0 {
        return Err(GeometryError::Degenerate("H vanishes".into()));
    }
    let h = model.h.0 / n0;
    let cost = transfer_cost(&h, p_left, p_right, quads);
    if !cost.is_finite() {
        return Err(GeometryError::Numerical("transfer cost is not finite at the start".into()));
    }
    let normal = |h: &Matrix4<f64>| {
        let h_inv = h.try_inverse()?;
        let mut jtj = SMatrix::<f64, 16, 16>::zeros();
        let mut jtr = SVector::<f64, 16>::zeros();
        for q in quads {
            if let Some((r, j)) = transfer_residuals(h, &h_inv, p_left, p_right, q) {
                jtj += j.transpose() * j;
                jtr += j.transpose() * r;
            }
        }
        Some((jtj, jtr))
    };
    let retract = |h: &Matrix4<f64>, d: &SVector<f64, 16>| {
        let cand = h + Matrix4::from_row_slice(d.as_slice());
        Some(cand / cand.norm())
    };
    let (h, _) =
        crate::lm::minimise(h, cost, 100, normal, retract, |h| transfer_cost(h, p_left, p_right, quads));
    TransferModel::new(Homography3(h))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fundamental::tests::random_scene;
    use crate::ransac::{RansacOptions, ransac};
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};
    use proptest::prelude::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Random well-conditioned 3D homography keeping points with z in [1, 6] finite.
    fn random_h(rng: &mut ChaCha8Rng) -> Matrix4<f64> {
        let mut h = Matrix4::identity();
        for i in 0..3 {
            for j in 0..4 {
                h[(i, j)] += rng.random_range(-0.4..0.4);
            }
        }
        for j in 0..3 {
            h[(3, j)] = rng.random_range(-0.05..0.05);
        }
        h
    }

    fn random_points(rng: &mut ChaCha8Rng, n: usize) -> Vec<Vector4<f64>> {
        (0..n)
            .map(|_| {
                let w: f64 = rng.random_range(0.5..2.0);
                Vector4::new(
                    rng.random_range(-2.0..2.0) * w,
                    rng.random_range(-2.0..2.0) * w,
                    rng.random_range(1.0..6.0) * w,
                    w,
                )
            })
            .collect()
    }

    fn same_up_to_scale(a: &Matrix4<f64>, b: &Matrix4<f64>) -> f64 {
        let a = a / a.norm();
        let b = b / b.norm();
        (a - b).norm().min((a + b).norm())
    }

    /// Quadruplets of a rigid motion of a random scene seen by a random rig.
    fn motion_quads(
        seed: u64,
        n: usize,
        sigma: f64,
    ) -> (ProjectiveCamera, ProjectiveCamera, Matrix4<f64>, Vec<Quadruplet>) {
        let s = random_scene(seed, n, 0.0);
        let (pl, pr) = (s.p_left(), s.p_right());
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xabcdef);
        let d = Isometry3::from_parts(
            Translation3::new(
                rng.random_range(-0.1..0.1),
                rng.random_range(-0.1..0.1),
                rng.random_range(-0.1..0.1),
            ),
            UnitQuaternion::from_euler_angles(
                rng.random_range(-0.05..0.05),
                rng.random_range(-0.05..0.05),
                rng.random_range(-0.05..0.05),
            ),
        )
        .to_homogeneous();
        let mut noise =
            || Point2::new(rng.random_range(-sigma..=sigma), rng.random_range(-sigma..=sigma)).coords;
        let quads = s
            .points
            .iter()
            .map(|p| {
                let x = p.to_homogeneous();
                let y = d * x;
                let (l0, r0) = (pl.project(&x).unwrap() + noise(), pr.project(&x).unwrap() + noise());
                let (l1, r1) = (pl.project(&y).unwrap() + noise(), pr.project(&y).unwrap() + noise());
                let xt = crate::triangulation::triangulate_linear(&pl, &pr, &l0, &r0).unwrap();
                let yt = crate::triangulation::triangulate_linear(&pl, &pr, &l1, &r1).unwrap();
                Quadruplet { x: xt, y: yt, left0: l0, right0: r0, left1: l1, right1: r1 }
            })
            .collect();
        (pl, pr, d, quads)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(128))]

        #[test]
        fn dlt_noise_free(seed in 0u64..1_000_000, n in 5usize..30) {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let h = random_h(&mut rng);
            let x = random_points(&mut rng, n);
            let y: Vec<_> = x.iter().map(|p| h * p * rng.random_range(0.5..2.0)).collect();
            let est = Homography3::dlt(&x, &y);
            prop_assume!(est.is_ok()); // random 5-point sets are in general position almost surely
            let est = est.unwrap();
            // 1e-8: conditioned 3n x 16 SVD with O(1) entries, then undoing the
            // conditioning (scales ~1-3); minimal sets can be poorly conditioned.
            prop_assert!(same_up_to_scale(&est.0, &h) < 1e-8, "{}", same_up_to_scale(&est.0, &h));
            let inv = est.inverse().unwrap();
            prop_assert!((est.0 * inv.0 - Matrix4::identity()).norm() < 1e-10);
        }

        #[test]
        fn normalized_det_of_rigid_conjugate(seed in 0u64..1_000_000, scale in -5.0..5.0f64) {
            prop_assume!(scale.abs() > 0.1);
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let g = random_h(&mut rng);
            prop_assume!(g.determinant().abs() > 1e-3);
            let d = Isometry3::from_parts(
                Translation3::new(0.1, -0.2, 0.05),
                UnitQuaternion::from_euler_angles(rng.random_range(-1.0..1.0), 0.3, -0.2),
            ).to_homogeneous();
            let h = g.try_inverse().unwrap() * d * g * scale;
            let n = Homography3(h).normalized_det().unwrap();
            // 1e-10: a 4x4 determinant and product with entries O(1) (conditioned g).
            prop_assert!((n.0.determinant() - 1.0).abs() < 1e-10);
            prop_assert!(n.0.trace() >= 0.0);
            // Eigenvalues of a rigid motion: trace = 2 + 1 + 2 cos(theta) > 0 here.
            let expected = g.try_inverse().unwrap() * d * g;
            prop_assert!((n.0 - expected).norm() < 1e-9 * expected.norm());
        }

        #[test]
        fn transfer_error_zero_for_exact_motion(seed in 0u64..1_000_000) {
            let (pl, pr, d, quads) = motion_quads(seed, 12, 0.0);
            let m = TransferModel::new(Homography3(d)).unwrap();
            for q in &quads {
                // 1e-7 px: triangulation of exact pixels, projected back.
                prop_assert!(symmetric_transfer_error(&m, &pl, &pr, q) < 1e-7);
            }
            let x: Vec<_> = quads.iter().map(|q| q.x).collect();
            let y: Vec<_> = quads.iter().map(|q| q.y).collect();
            let h = Homography3::dlt(&x, &y).unwrap();
            prop_assert!(same_up_to_scale(&h.0, &d) < 1e-8);
        }
    }

    #[test]
    fn ransac_with_outliers() {
        let (pl, pr, d, mut quads) = motion_quads(4, 150, 0.3);
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let n_out = 30;
        for q in quads.iter_mut().take(n_out) {
            q.left1 += nalgebra::Vector2::new(rng.random_range(20.0..60.0), rng.random_range(-60.0..-20.0));
            q.right1 += nalgebra::Vector2::new(rng.random_range(20.0..60.0), rng.random_range(-60.0..-20.0));
            q.y = crate::triangulation::triangulate_linear(&pl, &pr, &q.left1, &q.right1).unwrap();
        }
        let est = Homography3Estimator { p_left: pl, p_right: pr };
        let opts = RansacOptions { threshold: 2.0, ..Default::default() };
        let rep = ransac(&est, &quads, &opts).unwrap();
        assert!(rep.inliers.iter().all(|&i| i >= n_out), "an outlier was accepted");
        assert!(rep.inliers.len() >= 115, "{} inliers", rep.inliers.len());
        let inl: Vec<_> = rep.inliers.iter().map(|&i| quads[i]).collect();
        let refined = refine_transfer(&rep.model, &pl, &pr, &inl).unwrap();
        let c0 = transfer_cost(&(rep.model.h.0 / rep.model.h.0.norm()), &pl, &pr, &inl);
        let c1 = transfer_cost(&refined.h.0, &pl, &pr, &inl);
        assert!(c1 <= c0, "{c1} > {c0}");
        // Uniform noise of +-0.3 px: the refined H is close to the true motion.
        assert!(same_up_to_scale(&refined.h.0, &d) < 1e-2, "{}", same_up_to_scale(&refined.h.0, &d));
    }

    #[test]
    fn transfer_jacobian_matches_finite_differences() {
        let (pl, pr, d, quads) = motion_quads(9, 5, 0.5);
        let h = d + Matrix4::from_fn(|i, j| 0.01 * ((i * 4 + j) as f64).sin());
        let h_inv = h.try_inverse().unwrap();
        for q in &quads {
            let (_, j) = transfer_residuals(&h, &h_inv, &pl, &pr, q).unwrap();
            for k in 0..16 {
                let step = 1e-6;
                let mut e = Matrix4::zeros();
                e[(k / 4, k % 4)] = step;
                let (hp, hm) = (h + e, h - e);
                let rp = transfer_residuals(&hp, &hp.try_inverse().unwrap(), &pl, &pr, q).unwrap().0;
                let rm = transfer_residuals(&hm, &hm.try_inverse().unwrap(), &pl, &pr, q).unwrap().0;
                let fd = (rp - rm) / (2.0 * step);
                for i in 0..8 {
                    // Central differences: O(h^2) truncation, ~1e-16 * |r| / h rounding.
                    assert!(
                        (fd[i] - j[(i, k)]).abs() < 1e-5 * (1.0 + j[(i, k)].abs()),
                        "{i},{k}: {} vs {}",
                        fd[i],
                        j[(i, k)]
                    );
                }
            }
        }
    }

    #[test]
    fn degenerate_inputs_give_errors() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let x = random_points(&mut rng, 5);
        assert!(matches!(Homography3::dlt(&x[..4], &x[..4]), Err(GeometryError::NotEnoughData { .. })));
        assert!(Homography3::dlt(&x, &x[..4]).is_err());
        // Four coplanar points (z = 2) among five.
        let mut cop = x.clone();
        for p in cop.iter_mut().take(4) {
            p.z = 2.0 * p.w;
        }
        assert!(matches!(Homography3::dlt(&cop, &cop), Err(GeometryError::Degenerate(_))));
        // A point at infinity.
        let mut inf = x.clone();
        inf[0].w = 0.0;
        assert!(Homography3::dlt(&inf, &x).is_err());
        assert!(Homography3(Matrix4::zeros()).inverse().is_err());
        let mut neg = Matrix4::identity();
        neg[(0, 0)] = -1.0;
        assert!(matches!(Homography3(neg).normalized_det(), Err(GeometryError::InvalidEstimate(_))));
        // Projection at infinity: infinite transfer error, no panic.
        let m = TransferModel::new(Homography3(Matrix4::identity())).unwrap();
        let pl = ProjectiveCamera::canonical();
        let q = Quadruplet {
            x: Vector4::new(1.0, 0.0, 0.0, 0.0),
            y: Vector4::new(0.0, 0.0, 1.0, 1.0),
            left0: Point2::origin(),
            right0: Point2::origin(),
            left1: Point2::origin(),
            right1: Point2::origin(),
        };
        assert!(symmetric_transfer_error(&m, &pl, &pl, &q).is_infinite());
    }
}
