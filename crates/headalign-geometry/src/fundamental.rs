//! The fundamental matrix of a stereo pair.
//!
//! What it computes: `F` (3x3, rank 2, defined up to scale: 7 degrees of freedom) with the
//! convention `x_right^T F x_left = 0` — the left image is the first. Stored with
//! Frobenius norm 1.
//!
//! Algorithms (Hartley & Zisserman 2nd ed.):
//! - [`FundamentalMatrix::eight_point`]: normalised 8-point algorithm, section 11.2,
//!   Algorithm 11.1: Hartley normalisation of each image (centroid at the origin, mean
//!   distance sqrt 2), linear solution, rank 2 enforced by zeroing the smallest singular
//!   value, denormalisation.
//! - [`FundamentalMatrix::seven_point`]: section 11.1.2: the 2-dimensional null space
//!   `a F1 + (1 - a) F2` and the real roots of the cubic `det = 0`. The null space of the
//!   7 x 9 system is the last two columns of `Q` in a Householder QR with column pivoting
//!   of its transpose (Golub & Van Loan, 4th ed., algorithm 5.4.1), on stack arrays: like
//!   an SVD it is backward stable (an exact orthonormal null basis of a matrix within
//!   ~eps of the system, so the basis is off by ~eps / (sigma_7 / sigma_1), the same
//!   bound), at a fraction of the cost; the normal matrix `A^T A` is never formed (it
//!   would square the condition number).
//! - [`FundamentalMatrix::sampson_distance`]: first-order geometric error, section 11.4.3
//!   (eq. 11.9); reported in pixels as the square root of the Sampson error.
//! - [`FundamentalMatrix::refine_sampson`]: Levenberg-Marquardt (appendix A6) on the sum
//!   of squared Sampson distances, over the minimal parametrisation
//!   `F = U diag(1, s, 0) V^T` with `U, V` in SO(3) updated by right-multiplied rotation
//!   exponentials (3 + 3 + 1 = 7 dof, Bartoli & Sturm 2004), analytic Jacobian.
//! - [`estimate_fundamental`]: RANSAC (7-point samples, 8-point polish, Sampson residual,
//!   section 11.6, Algorithm 11.4) with the DEGENSAC plane test of Chum, Werner & Matas
//!   (CVPR 2005; see [`FundamentalEstimator`]), then guided Sampson refinement on the
//!   inliers until the inlier set is stable.
//! - [`homography_compatible_with_f`]: the plane homography defined by `F` and three
//!   matches (H&Z result 13.6).
//!
//! Units: Sampson distances and RANSAC thresholds are pixels.
//!
//! Pitfalls handled: coordinates are normalised before every linear solve (without it the
//! 8-point matrix has a condition number of ~1e8 for pixel coordinates); nalgebra's SVD is
//! thin, so the 8-point system is padded with zero rows to square (8 pairs) or first
//! reduced to its 9 x 9 `R` factor by QR (more pairs: same right singular vectors, and we
//! never form `A^T A`); SVDs use `try_svd` with an
//! iteration limit and fail with a typed error; coincident points (zero spread) and
//! rank-deficient solutions are errors. The 7-point rank test reads the pivoted `R`'s
//! diagonal (`|r_66| <= 1e-10 |r_00|`: null space of dimension > 2) instead of singular
//! values: without the pivoting the diagonal does not reveal the rank, and even with it
//! `|r_66|` only brackets `sigma_7` within a modest factor (pathological matrices aside),
//! so samples at the edge of the 1e-10 test may be judged differently from an SVD; an
//! undetected near-degenerate sample only yields candidates that score badly. The
//! DEGENSAC test takes the right epipole of each 7-point `F` from the largest cross
//! product of two of its columns rather than an SVD (as accurate for a rank-2 `F`). Scenes
//! of walls and floors are dominated by planes: without the plane test, RANSAC often
//! returns an `F` fitted to one plane that misses a tenth of the off-plane inliers.

use nalgebra::{DMatrix, DVector, Matrix3, Point2, SMatrix, SVector, Vector3};

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::linear::{SVD_MAX_ITER, normalising_transform_2d, smallest_right_singular_vectors};
use crate::ransac::{Estimator, RansacOptions, RansacReport, ransac};
use crate::so3;
use crate::{GeometryError, Result};

fn apply(t: &Matrix3<f64>, p: &Point2<f64>) -> Vector3<f64> {
    t * Vector3::new(p.x, p.y, 1.0)
}

/// The rows `x_r^T F x_l = 0` of the linear system in the 9 entries of `F` (row-major),
/// in normalised coordinates, with the two normalising transforms.
fn epipolar_system(
    pairs: &[(Point2<f64>, Point2<f64>)],
) -> Result<(DMatrix<f64>, Matrix3<f64>, Matrix3<f64>)> {
    let tl = normalising_transform_2d(pairs.iter().map(|p| &p.0))?;
    let tr = normalising_transform_2d(pairs.iter().map(|p| &p.1))?;
    let mut a = DMatrix::zeros(pairs.len(), 9);
    for (i, (l, r)) in pairs.iter().enumerate() {
        let xl = apply(&tl, l);
        let xr = apply(&tr, r);
        for j in 0..3 {
            for k in 0..3 {
                a[(i, 3 * j + k)] = xr[j] * xl[k];
            }
        }
    }
    Ok((a, tl, tr))
}

fn mat_from_vec9(v: &DVector<f64>) -> Matrix3<f64> {
    Matrix3::from_row_slice(v.as_slice())
}

/// Scale to Frobenius norm 1 with a deterministic sign (largest-magnitude entry positive).
fn normalise_scale(f: &Matrix3<f64>) -> Result<Matrix3<f64>> {
    let n = f.norm();
    if !n.is_finite() || n <= 0.0 {
        return Err(GeometryError::Degenerate("fundamental matrix vanishes".into()));
    }
    let imax = f.iamax_full();
    let sign = if f[imax] < 0.0 { -1.0 } else { 1.0 };
    Ok(f * (sign / n))
}

/// Real roots of `c[3] x^3 + c[2] x^2 + c[1] x + c[0]`, with a Newton polish; handles a
/// vanishing leading coefficient by falling back to the quadratic/linear case.
fn real_roots_cubic(c: [f64; 4]) -> Vec<f64> {
    let scale = c.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if scale == 0.0 || !scale.is_finite() {
        return vec![];
    }
    let [c0, c1, c2, c3] = c.map(|v| v / scale);
    let mut roots = Vec::new();
    if c3.abs() < 1e-12 {
        if c2.abs() < 1e-12 {
            if c1.abs() > 1e-12 {
                roots.push(-c0 / c1);
            }
        } else {
            let disc = c1 * c1 - 4.0 * c2 * c0;
            if disc >= 0.0 {
                let q = -0.5 * (c1 + c1.signum() * disc.sqrt());
                if q != 0.0 {
                    roots.push(q / c2);
                    roots.push(c0 / q);
                } else {
                    roots.push(0.0);
                }
            }
        }
    } else {
        // Depressed cubic t^3 + p t + q with x = t - b/3.
        let (b, cc, d) = (c2 / c3, c1 / c3, c0 / c3);
        let p = cc - b * b / 3.0;
        let q = 2.0 * b * b * b / 27.0 - b * cc / 3.0 + d;
        let disc = q * q / 4.0 + p * p * p / 27.0;
        if disc > 0.0 {
            let sq = disc.sqrt();
            let u = (-q / 2.0 + sq).cbrt();
            let v = (-q / 2.0 - sq).cbrt();
            roots.push(u + v - b / 3.0);
        } else if p.abs() < 1e-300 {
            roots.push(-b / 3.0);
        } else {
            let r = (-p / 3.0).sqrt();
            let phi = ((3.0 * q) / (2.0 * p * r)).clamp(-1.0, 1.0).acos() / 3.0;
            for k in 0..3 {
                let t = 2.0 * r * (phi - 2.0 * std::f64::consts::PI * k as f64 / 3.0).cos();
                roots.push(t - b / 3.0);
            }
        }
    }
    // Newton polish on the scaled polynomial.
    for x in &mut roots {
        for _ in 0..3 {
            let f = ((c3 * *x + c2) * *x + c1) * *x + c0;
            let df = (3.0 * c3 * *x + 2.0 * c2) * *x + c1;
            if df.abs() > 1e-300 {
                let nx = *x - f / df;
                if nx.is_finite() {
                    *x = nx;
                }
            }
        }
    }
    roots
}

/// Rank tolerance of the 7-point system: `|r_66| <= RANK_TOL_7 |r_00|` in the pivoted QR
/// of its transpose means a null space of dimension > 2.
const RANK_TOL_7: f64 = 1e-10;

/// Orthonormal basis of the null space of the 7 x 9 system `A` (rows `a`), by Householder
/// QR with column pivoting of `A^T` (Golub & Van Loan, 4th ed., algorithm 5.4.1): `A^T P =
/// Q R` with `Q = H_0 ... H_6`, and the last two columns of `Q` are orthogonal to every row
/// of `A`. All on the stack.
///
/// Errors if the pivoted `R` has `|r_66| <= RANK_TOL_7 |r_00|` (null space of dimension > 2)
/// or an entry is not finite.
fn null_space_7x9(mut a: [[f64; 9]; 7]) -> Result<[[f64; 9]; 2]> {
    if !a.iter().flatten().all(|v| v.is_finite()) {
        return Err(GeometryError::Numerical("non-finite entry in a linear system".into()));
    }
    // Householder vectors (entries k..9 of row k) and their 2 / |v|^2.
    let mut betas = [0.0f64; 7];
    let mut r_diag = [0.0f64; 7];
    for k in 0..7 {
        let tail_norm2 = |row: &[f64; 9]| row[k..].iter().map(|v| v * v).sum::<f64>();
        let mut p = k;
        let mut p_norm2 = tail_norm2(&a[k]);
        for (i, row) in a.iter().enumerate().skip(k + 1) {
            let n2 = tail_norm2(row);
            if n2 > p_norm2 {
                (p, p_norm2) = (i, n2);
            }
        }
        a.swap(k, p);
        let norm = p_norm2.sqrt();
        if norm == 0.0 {
            break; // rank k: r_kk.. stay zero, caught below
        }
        let alpha = if a[k][k] > 0.0 { -norm } else { norm };
        r_diag[k] = alpha;
        a[k][k] -= alpha;
        let vv: f64 = a[k][k..].iter().map(|v| v * v).sum();
        betas[k] = 2.0 / vv;
        let (head, tail) = a.split_at_mut(k + 1);
        let v = &head[k];
        for row in tail.iter_mut() {
            let s = betas[k] * (k..9).map(|j| v[j] * row[j]).sum::<f64>();
            for j in k..9 {
                row[j] -= s * v[j];
            }
        }
    }
    if r_diag[6].is_nan() || r_diag[6].abs() <= RANK_TOL_7 * r_diag[0].abs() {
        return Err(GeometryError::Degenerate("7-point system has a null space of dimension > 2".into()));
    }
    // Q e_7 and Q e_8: apply H_6, ..., H_0 to the unit vectors.
    let mut out = [[0.0f64; 9]; 2];
    out[0][7] = 1.0;
    out[1][8] = 1.0;
    for x in &mut out {
        for k in (0..7).rev() {
            let v = &a[k];
            let s = betas[k] * (k..9).map(|j| v[j] * x[j]).sum::<f64>();
            for j in k..9 {
                x[j] -= s * v[j];
            }
        }
    }
    Ok(out)
}

/// A fundamental matrix, `x_right^T F x_left = 0`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FundamentalMatrix(pub Matrix3<f64>);

impl FundamentalMatrix {
    /// Normalised 8-point algorithm (H&Z Algorithm 11.1) from `>= 8` pairs
    /// `(left, right)` in pixels. Rank 2 is enforced, the result has Frobenius norm 1.
    ///
    /// Errors: fewer than 8 pairs, coincident points, a null space of dimension > 1
    /// (degenerate configuration), SVD failure.
    pub fn eight_point(pairs: &[(Point2<f64>, Point2<f64>)]) -> Result<Self> {
        if pairs.len() < 8 {
            return Err(GeometryError::NotEnoughData { what: "8-point pairs", needed: 8, got: pairs.len() });
        }
        let (a, tl, tr) = epipolar_system(pairs)?;
        let (v, sv) = smallest_right_singular_vectors(&a, 2)?;
        // Second-smallest singular value ~0: the solution is not unique.
        if sv[7] <= 1e-10 * sv[0] {
            return Err(GeometryError::Degenerate("8-point system has a null space of dimension > 1".into()));
        }
        let fn_ = enforce_rank2(&mat_from_vec9(&v[0]))?;
        // Rank 2 is enforced in normalised coordinates: a Frobenius projection in pixel
        // coordinates would weight the entries badly. Denormalisation then leaves
        // sigma_3 ~ 1e-12 from rounding.
        let f = tr.transpose() * fn_ * tl;
        Ok(Self(normalise_scale(&f)?))
    }

    /// 7-point algorithm (H&Z section 11.1.2) from exactly 7 pairs, solved in normalised
    /// coordinates: one or three real solutions (each rank 2, Frobenius norm 1).
    ///
    /// Errors: not exactly 7 pairs, coincident points, a null space of dimension > 2
    /// (`|r_66| <= 1e-10 |r_00|` in the pivoted QR, see the module documentation),
    /// non-finite coordinates.
    pub fn seven_point(pairs: &[(Point2<f64>, Point2<f64>)]) -> Result<Vec<Self>> {
        let Ok(pairs) = <&[(Point2<f64>, Point2<f64>); 7]>::try_from(pairs) else {
            return Err(GeometryError::NotEnoughData {
                what: "7-point pairs (exactly 7)",
                needed: 7,
                got: pairs.len(),
            });
        };
        Self::seven_point_fixed(pairs)
    }

    /// [`Self::seven_point`] on a fixed-size sample: stack arithmetic only, apart from the
    /// returned vector.
    fn seven_point_fixed(pairs: &[(Point2<f64>, Point2<f64>); 7]) -> Result<Vec<Self>> {
        let tl = normalising_transform_2d(pairs.iter().map(|p| &p.0))?;
        let tr = normalising_transform_2d(pairs.iter().map(|p| &p.1))?;
        let rows = pairs.map(|(l, r)| {
            let (xl, xr) = (apply(&tl, &l), apply(&tr, &r));
            std::array::from_fn(|i| xr[i / 3] * xl[i % 3])
        });
        let [n1, n2] = null_space_7x9(rows)?;
        let f1 = Matrix3::from_row_slice(&n1);
        let f2 = Matrix3::from_row_slice(&n2);
        // det(x A + B) with A = F1 - F2, B = F2 (so x F1 + (1 - x) F2) is a cubic in x:
        // c0 = det B, c3 = det A, and c1, c2 from the values at x = 1 and x = -1.
        let am = f1 - f2;
        let c0 = f2.determinant();
        let c3 = am.determinant();
        let d1 = f1.determinant();
        let dm1 = (f2 - am).determinant();
        let c2 = 0.5 * (d1 + dm1) - c0;
        let c1 = 0.5 * (d1 - dm1) - c3;
        let cmax = [c0, c1, c2, c3].iter().fold(0.0f64, |m, v| m.max(v.abs()));
        // Root at infinity (c3 ~ 0): A itself is singular.
        let at_infinity = (c3.abs() < 1e-12 * cmax).then_some(am);
        let out: Vec<Self> = real_roots_cubic([c0, c1, c2, c3])
            .into_iter()
            .map(|x| am * x + f2)
            .chain(at_infinity)
            .filter_map(|fn_| normalise_scale(&(tr.transpose() * fn_ * tl)).ok().map(Self))
            .collect();
        if out.is_empty() {
            return Err(GeometryError::Degenerate("7-point cubic has no usable real root".into()));
        }
        Ok(out)
    }

    /// Algebraic residual `x_r^T F x_l`.
    pub fn algebraic(&self, left: &Point2<f64>, right: &Point2<f64>) -> f64 {
        let xl = Vector3::new(left.x, left.y, 1.0);
        let xr = Vector3::new(right.x, right.y, 1.0);
        xr.dot(&(self.0 * xl))
    }

    /// Sampson distance in pixels: `|x_r^T F x_l| / sqrt((F x_l)_1^2 + (F x_l)_2^2 +
    /// (F^T x_r)_1^2 + (F^T x_r)_2^2)`, the square root of the Sampson error (H&Z eq.
    /// 11.9). Zero for an exact match with a vanishing gradient, +infinity if only the
    /// gradient vanishes.
    #[inline]
    pub fn sampson_distance(&self, left: &Point2<f64>, right: &Point2<f64>) -> f64 {
        let xl = Vector3::new(left.x, left.y, 1.0);
        let xr = Vector3::new(right.x, right.y, 1.0);
        let fx = self.0 * xl;
        let ftx = self.0.transpose() * xr;
        let e = xr.dot(&fx);
        let den = fx.x * fx.x + fx.y * fx.y + ftx.x * ftx.x + ftx.y * ftx.y;
        if den > 0.0 {
            e.abs() / den.sqrt()
        } else if e == 0.0 {
            0.0
        } else {
            f64::INFINITY
        }
    }

    /// The epipoles `(e_left, e_right)` with `F e_left = 0` and `F^T e_right = 0`, unit
    /// norm, sign chosen so that the largest-magnitude component is positive. Errors if `F` does not have rank 2 (to 1e-10 relative).
    pub fn epipoles(&self) -> Result<(Vector3<f64>, Vector3<f64>)> {
        let svd = self
            .0
            .try_svd(true, true, f64::EPSILON, SVD_MAX_ITER)
            .ok_or_else(|| GeometryError::Numerical("SVD of F did not converge".into()))?;
        let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
            return Err(GeometryError::Numerical("SVD of F without U or V".into()));
        };
        let s = svd.singular_values;
        if s[1].is_nan() || s[1] <= 1e-10 * s[0] {
            return Err(GeometryError::Degenerate("F has rank < 2".into()));
        }
        let canon = |v: Vector3<f64>| {
            let v = v.normalize();
            if v[v.iamax()] < 0.0 { -v } else { v }
        };
        Ok((canon(v_t.row(2).transpose()), canon(u.column(2).into_owned())))
    }

    /// Levenberg-Marquardt refinement of the sum of squared Sampson distances over the
    /// 7-dof parametrisation `F = U diag(1, s, 0) V^T` (see the module documentation).
    /// The input is first projected to rank 2 (a no-op for every `F` this module
    /// returns); from there the cost never increases. Needs `>= 7` pairs.
    pub fn refine_sampson(&self, pairs: &[(Point2<f64>, Point2<f64>)]) -> Result<Self> {
        if pairs.len() < 7 {
            return Err(GeometryError::NotEnoughData {
                what: "Sampson refinement pairs",
                needed: 7,
                got: pairs.len(),
            });
        }
        let tl = normalising_transform_2d(pairs.iter().map(|p| &p.0))?;
        let tr = normalising_transform_2d(pairs.iter().map(|p| &p.1))?;
        let p = Rank2Param::from_matrix(&self.0, tl, tr)?;
        let cost = sampson_cost(&p.matrix(), pairs);
        if !cost.is_finite() {
            return Err(GeometryError::Numerical("Sampson cost is not finite at the start".into()));
        }
        let normal = |p: &Rank2Param| {
            let mut jtj = SMatrix::<f64, 7, 7>::zeros();
            let mut jtr = SVector::<f64, 7>::zeros();
            for (l, r) in pairs {
                if let Some((res, j)) = p.residual_and_jacobian(l, r) {
                    jtj += j * j.transpose();
                    jtr += j * res;
                }
            }
            Some((jtj, jtr))
        };
        let (p, _) = crate::lm::minimise(
            p,
            cost,
            100,
            normal,
            |p, d| Some(p.updated(d)),
            |p| sampson_cost(&p.matrix(), pairs),
        );
        Ok(Self(normalise_scale(&p.matrix())?))
    }
}

fn enforce_rank2(f: &Matrix3<f64>) -> Result<Matrix3<f64>> {
    let svd = f
        .try_svd(true, true, f64::EPSILON, SVD_MAX_ITER)
        .ok_or_else(|| GeometryError::Numerical("SVD of F did not converge".into()))?;
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(GeometryError::Numerical("SVD of F without U or V".into()));
    };
    let s = svd.singular_values;
    Ok(u * Matrix3::from_diagonal(&Vector3::new(s[0], s[1], 0.0)) * v_t)
}

/// Sum of squared Sampson distances (pixels^2).
pub(crate) fn sampson_cost(f: &Matrix3<f64>, pairs: &[(Point2<f64>, Point2<f64>)]) -> f64 {
    let fm = FundamentalMatrix(*f);
    pairs.iter().map(|(l, r)| fm.sampson_distance(l, r).powi(2)).sum()
}

/// `F = T_r^T U diag(1, s, 0) V^T T_l` with `U, V` rotations and `T_l, T_r` fixed
/// Hartley normalisations of the data: the parameters live in normalised coordinates
/// (well scaled), the cost stays in pixels.
#[derive(Debug, Clone, Copy)]
struct Rank2Param {
    u: Matrix3<f64>,
    v: Matrix3<f64>,
    s: f64,
    tl: Matrix3<f64>,
    tr: Matrix3<f64>,
}

impl Rank2Param {
    fn from_matrix(f: &Matrix3<f64>, tl: Matrix3<f64>, tr: Matrix3<f64>) -> Result<Self> {
        let (Some(tl_inv), Some(tr_inv)) = (tl.try_inverse(), tr.try_inverse()) else {
            return Err(GeometryError::Degenerate("singular normalising transform".into()));
        };
        let g = tr_inv.transpose() * f * tl_inv;
        let svd = g
            .try_svd(true, true, f64::EPSILON, SVD_MAX_ITER)
            .ok_or_else(|| GeometryError::Numerical("SVD of F did not converge".into()))?;
        let (Some(mut u), Some(v_t)) = (svd.u, svd.v_t) else {
            return Err(GeometryError::Numerical("SVD of F without U or V".into()));
        };
        let sv = svd.singular_values;
        if sv[1].is_nan() || sv[1] <= 1e-12 * sv[0] {
            return Err(GeometryError::Degenerate("F has rank < 2".into()));
        }
        let mut v = v_t.transpose();
        // The third singular value is dropped, so the third columns' signs are free.
        if u.determinant() < 0.0 {
            u.column_mut(2).neg_mut();
        }
        if v.determinant() < 0.0 {
            v.column_mut(2).neg_mut();
        }
        Ok(Self { u, v, s: sv[1] / sv[0], tl, tr })
    }

    fn d(&self) -> Matrix3<f64> {
        Matrix3::from_diagonal(&Vector3::new(1.0, self.s, 0.0))
    }

    fn matrix(&self) -> Matrix3<f64> {
        self.tr.transpose() * self.u * self.d() * self.v.transpose() * self.tl
    }

    /// Parameters: `delta = (a, b, ds)`, `U <- U exp([a]x)`, `V <- V exp([b]x)`, `s <- s + ds`.
    fn updated(&self, delta: &SVector<f64, 7>) -> Self {
        let a = Vector3::new(delta[0], delta[1], delta[2]);
        let b = Vector3::new(delta[3], delta[4], delta[5]);
        Self {
            u: self.u * so3::exp(&a).into_inner(),
            v: self.v * so3::exp(&b).into_inner(),
            s: self.s + delta[6],
            tl: self.tl,
            tr: self.tr,
        }
    }

    /// Derivatives of `F` with respect to the 7 parameters at zero update.
    fn d_f(&self) -> [Matrix3<f64>; 7] {
        let d = self.d();
        let vt = self.v.transpose() * self.tl;
        let u = self.tr.transpose() * self.u;
        let mut out = [Matrix3::zeros(); 7];
        for k in 0..3 {
            let ek = so3::skew(&Vector3::ith(k, 1.0));
            out[k] = u * ek * d * vt;
            // V exp([b]x) transposed = exp(-[b]x) V^T.
            out[3 + k] = -(u * d * ek * vt);
        }
        out[6] = u * Matrix3::from_diagonal(&Vector3::new(0.0, 1.0, 0.0)) * vt;
        out
    }

    /// Signed Sampson residual and its gradient with respect to the 7 parameters; `None`
    /// where the residual is not differentiable (vanishing gradient of the constraint).
    fn residual_and_jacobian(&self, l: &Point2<f64>, r: &Point2<f64>) -> Option<(f64, SVector<f64, 7>)> {
        let f = self.matrix();
        let (res, g) = sampson_residual_grad(&f, l, r)?;
        let df = self.d_f();
        let mut j = SVector::<f64, 7>::zeros();
        for k in 0..7 {
            j[k] = g.component_mul(&df[k]).sum();
        }
        Some((res, j))
    }
}

/// Signed Sampson residual `e / sqrt(den)` and its gradient with respect to the 9
/// entries of `F`.
fn sampson_residual_grad(f: &Matrix3<f64>, l: &Point2<f64>, r: &Point2<f64>) -> Option<(f64, Matrix3<f64>)> {
    let xl = Vector3::new(l.x, l.y, 1.0);
    let xr = Vector3::new(r.x, r.y, 1.0);
    let fx = f * xl;
    let ftx = f.transpose() * xr;
    let e = xr.dot(&fx);
    let den = fx.x * fx.x + fx.y * fx.y + ftx.x * ftx.x + ftx.y * ftx.y;
    if den.is_nan() || den <= 0.0 || den.is_infinite() {
        return None;
    }
    let sd = den.sqrt();
    // de/dF = xr xl^T; dden/dF_jk = 2 (F xl)_j xl_k [j<2] + 2 (F^T xr)_k xr_j [k<2].
    let de = xr * xl.transpose();
    let mut dden = Matrix3::zeros();
    for j in 0..3 {
        for k in 0..3 {
            let mut v = 0.0;
            if j < 2 {
                v += 2.0 * fx[j] * xl[k];
            }
            if k < 2 {
                v += 2.0 * ftx[k] * xr[j];
            }
            dden[(j, k)] = v;
        }
    }
    let g = de / sd - dden * (0.5 * e / (den * sd));
    Some((e / sd, g))
}

/// RANSAC estimator of `F`: datum `(left, right)` pixels, 7-point minimal solver with the
/// DEGENSAC plane test, 8-point polish, Sampson distance residual (pixels).
///
/// Scenes of walls and floors are dominated by planes. A 7-point sample with five or more
/// points on one plane fits a whole family of `F` (all those compatible with the plane's
/// homography), so plain RANSAC settles on one that explains the plane and misses up to a
/// tenth of the off-plane inliers; local optimisation cannot leave that basin. For each
/// 7-point solution the sample is tested for a plane (Chum, Werner & Matas, "Two-view
/// geometry estimation unaffected by a dominant plane", CVPR 2005): the homography
/// compatible with `F` and three sample points (H&Z result 13.6) for five triplets that
/// any five of seven points contain; if it maps five or more sample points within
/// [`Self::plane_threshold_px`], the plane-and-parallax solution `F = [e']x H` is added,
/// with the epipole `e'` from the parallax lines of off-plane matches (a small seeded
/// 2-point search over the data).
#[derive(Debug, Clone, Copy)]
pub struct FundamentalEstimator {
    /// Transfer error (pixels) under which a sample point lies on a plane; also the
    /// Sampson distance that scores an epipole in the parallax search. Default 3 px.
    pub plane_threshold_px: f64,
}

impl Default for FundamentalEstimator {
    fn default() -> Self {
        Self { plane_threshold_px: 3.0 }
    }
}

/// Triplets of a 7-point sample such that any five of the seven points contain one of them.
const DEGENSAC_TRIPLETS: [[usize; 3]; 5] = [[0, 1, 2], [3, 4, 5], [0, 1, 6], [3, 4, 6], [2, 5, 6]];
/// Sample points on one plane that make a 7-point sample plane-degenerate.
const DEGENERATE_ON_PLANE: usize = 5;
/// Two-point epipole hypotheses tried by the plane-and-parallax search.
const PARALLAX_SAMPLES: usize = 24;

fn homogeneous(p: &Point2<f64>) -> Vector3<f64> {
    Vector3::new(p.x, p.y, 1.0)
}

/// The plane homography compatible with `F` (right epipole `e_right`, `F^T e_right = 0`)
/// that maps three given matches exactly (H&Z result 13.6):
/// `H = A - e' (M^-1 b)^T`, `A = [e']x F`, `M` the stacked left points and
/// `b_i = (x'_i x A x_i) . (x'_i x e') / |x'_i x e'|^2`. `None` if the three left points
/// are collinear or a right point coincides with the epipole.
pub fn homography_compatible_with_f(
    f: &FundamentalMatrix,
    e_right: &Vector3<f64>,
    matches: &[(Point2<f64>, Point2<f64>); 3],
) -> Option<Matrix3<f64>> {
    let a = e_right.cross_matrix() * f.0;
    let mut m = Matrix3::zeros();
    let mut b = Vector3::zeros();
    for (i, (l, r)) in matches.iter().enumerate() {
        let (x, xp) = (homogeneous(l), homogeneous(r));
        let v = xp.cross(e_right);
        let vv = v.norm_squared();
        if vv <= 1e-24 * xp.norm_squared() * e_right.norm_squared() {
            return None;
        }
        b[i] = xp.cross(&(a * x)).dot(&v) / vv;
        m.set_row(i, &x.transpose());
    }
    let h = a - e_right * (m.try_inverse()? * b).transpose();
    h.iter().all(|v| v.is_finite()).then_some(h)
}

/// Matches as four coordinate arrays, so that counting Sampson inliers vectorises.
struct SoaMatches {
    lx: Vec<f64>,
    ly: Vec<f64>,
    rx: Vec<f64>,
    ry: Vec<f64>,
}

impl SoaMatches {
    fn gather(data: &[(Point2<f64>, Point2<f64>)], indices: &[usize]) -> Self {
        let coordinate =
            |c: fn(&(Point2<f64>, Point2<f64>)) -> f64| indices.iter().map(|&i| c(&data[i])).collect();
        Self {
            lx: coordinate(|d| d.0.x),
            ly: coordinate(|d| d.0.y),
            rx: coordinate(|d| d.1.x),
            ry: coordinate(|d| d.1.y),
        }
    }

    /// Number of matches with [`FundamentalMatrix::sampson_distance`] `<= tol`: the same
    /// operations in the same order (nalgebra's `F x`, `F^T x'` and dot products sum left
    /// to right), branch-free, so the count is the same bit for bit.
    fn within_sampson(&self, f: &FundamentalMatrix, tol: f64) -> usize {
        let m = &f.0;
        let (f00, f01, f02, f10, f11, f12, f20, f21, f22) = (
            m[(0, 0)],
            m[(0, 1)],
            m[(0, 2)],
            m[(1, 0)],
            m[(1, 1)],
            m[(1, 2)],
            m[(2, 0)],
            m[(2, 1)],
            m[(2, 2)],
        );
        let zero_is_within = 0.0 <= tol;
        let mut count = 0;
        for (((&x, &y), &u), &v) in self.lx.iter().zip(&self.ly).zip(&self.rx).zip(&self.ry) {
            let (fx0, fx1, fx2) = (f00 * x + f01 * y + f02, f10 * x + f11 * y + f12, f20 * x + f21 * y + f22);
            let (ftx0, ftx1) = (f00 * u + f10 * v + f20, f01 * u + f11 * v + f21);
            let e = u * fx0 + v * fx1 + fx2;
            let den = fx0 * fx0 + fx1 * fx1 + ftx0 * ftx0 + ftx1 * ftx1;
            let within = if den > 0.0 { e.abs() / den.sqrt() <= tol } else { e == 0.0 && zero_is_within };
            count += usize::from(within);
        }
        count
    }
}

/// Transfer error `|H a - b|` in pixels (as [`crate::homography2d::Homography2::transfer_error`]).
#[inline]
fn transfer_error(h: &Matrix3<f64>, a: &Point2<f64>, b: &Point2<f64>) -> f64 {
    crate::homography2d::Homography2(*h).transfer_error(a, b)
}

/// The right epipole `e'` (`F^T e' = 0`, unit norm, sign free) of a rank-2 `F` as the
/// largest of the three cross products of two columns of `F` (each orthogonal to both
/// columns, so to the column space when `F` has rank 2). The largest one is at least
/// `sigma_1 sigma_2 / sqrt 3` (the squared cross products sum to the sum of squared 2x2
/// minors, `sigma_1^2 sigma_2^2 + O(sigma_3)`), so its direction is as accurate as the
/// SVD's null vector, `O(sigma_3 / sigma_2)`. `None` if `F` is close to rank 1 (largest
/// cross product `<= 1e-10 |F|^2`, i.e. `sigma_2 <~ 1e-10 sigma_1`) or not finite.
fn right_epipole_by_cross(f: &FundamentalMatrix) -> Option<Vector3<f64>> {
    let (c0, c1, c2) = (f.0.column(0), f.0.column(1), f.0.column(2));
    let e = [c0.cross(&c1), c1.cross(&c2), c2.cross(&c0)]
        .into_iter()
        .max_by(|a, b| a.norm_squared().total_cmp(&b.norm_squared()))?;
    let n = e.norm();
    (n > 1e-10 * f.0.norm_squared()).then(|| e / n)
}

impl FundamentalEstimator {
    /// The sample points on one plane if at least [`DEGENERATE_ON_PLANE`] of them are: by
    /// the homographies compatible with each 7-point solution `F` (DEGENSAC), or, when the
    /// 7-point system itself is degenerate (all seven exactly on a plane), by a DLT
    /// homography through all seven.
    fn plane_of_sample(
        &self,
        models: &[FundamentalMatrix],
        data: &[(Point2<f64>, Point2<f64>)],
        sample: &[usize],
    ) -> Option<Vec<usize>> {
        let tol = self.plane_threshold_px;
        let on_plane = |h: &Matrix3<f64>, i: usize| transfer_error(h, &data[i].0, &data[i].1) <= tol;
        let on =
            |h: &Matrix3<f64>| -> Vec<usize> { sample.iter().copied().filter(|&i| on_plane(h, i)).collect() };
        if models.is_empty() {
            let pairs: Vec<_> = sample.iter().map(|&i| data[i]).collect();
            let h = crate::homography2d::Homography2::dlt(&pairs).ok()?;
            let on = on(&h.0);
            return (on.len() == sample.len()).then_some(on);
        }
        // A triplet's homography fails as soon as more than `sample.len() - 5` points miss.
        let misses_allowed = sample.len().saturating_sub(DEGENERATE_ON_PLANE);
        let enough = |h: &Matrix3<f64>| {
            let mut misses = 0;
            for &i in sample {
                if !on_plane(h, i) {
                    misses += 1;
                    if misses > misses_allowed {
                        return false;
                    }
                }
            }
            true
        };
        models.iter().find_map(|f| {
            let e_right = right_epipole_by_cross(f)?;
            DEGENSAC_TRIPLETS.iter().find_map(|t| {
                let h = homography_compatible_with_f(f, &e_right, &t.map(|k| data[sample[k]]))?;
                enough(&h).then(|| on(&h))
            })
        })
    }

    /// The plane-and-parallax `F = [e']x H` for the plane through the matches `on_plane`,
    /// the epipole `e'` from the parallax lines of matches clearly off the plane (the best
    /// supported of a few seeded 2-point hypotheses), or `None` if there are too few.
    fn plane_and_parallax(
        &self,
        on_plane: &[usize],
        data: &[(Point2<f64>, Point2<f64>)],
        sample: &[usize],
    ) -> Option<FundamentalMatrix> {
        let tol = self.plane_threshold_px;
        let plane: Vec<_> = on_plane.iter().map(|&i| data[i]).collect();
        let h = crate::homography2d::Homography2::dlt(&plane).ok()?;
        let off: Vec<usize> =
            (0..data.len()).filter(|&i| h.transfer_error(&data[i].0, &data[i].1) > 2.0 * tol).collect();
        if off.len() < 2 {
            return None;
        }
        // Seeded by the sample itself: the same sample always gives the same model.
        let seed = sample
            .iter()
            .fold(0xcbf2_9ce4_8422_2325_u64, |acc, &i| (acc ^ i as u64).wrapping_mul(0x100_0000_01b3));
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let parallax = |i: usize| (h.0 * homogeneous(&data[i].0)).cross(&homogeneous(&data[i].1));
        let off_points = SoaMatches::gather(data, &off);
        let mut best: Option<(FundamentalMatrix, usize)> = None;
        for _ in 0..PARALLAX_SAMPLES {
            let i = off[rng.random_range(0..off.len())];
            let j = off[rng.random_range(0..off.len())];
            if i == j {
                continue;
            }
            let e = parallax(i).cross(&parallax(j));
            let Ok(fm) = normalise_scale(&(e.cross_matrix() * h.0)) else { continue };
            let fm = FundamentalMatrix(fm);
            let support = off_points.within_sampson(&fm, tol);
            if best.as_ref().is_none_or(|(_, s)| support > *s) {
                best = Some((fm, support));
            }
        }
        best.map(|(fm, _)| fm)
    }
}

impl Estimator for FundamentalEstimator {
    type Datum = (Point2<f64>, Point2<f64>);
    type Model = FundamentalMatrix;

    fn sample_size(&self) -> usize {
        7
    }

    fn fit_minimal(&self, data: &[Self::Datum], sample: &[usize]) -> Vec<FundamentalMatrix> {
        let Ok(sample7) = <&[usize; 7]>::try_from(sample) else { return Vec::new() };
        let pairs = sample7.map(|i| data[i]);
        let mut models = FundamentalMatrix::seven_point_fixed(&pairs).unwrap_or_default();
        // One plane-and-parallax model per degenerate sample (the plane is the sample's,
        // whichever 7-point root revealed it).
        if let Some(extra) = self
            .plane_of_sample(&models, data, sample)
            .and_then(|on_plane| self.plane_and_parallax(&on_plane, data, sample))
        {
            models.push(extra);
        }
        models
    }

    fn fit_inliers(&self, data: &[Self::Datum], inliers: &[usize]) -> Option<FundamentalMatrix> {
        let pairs: Vec<_> = inliers.iter().map(|&i| data[i]).collect();
        FundamentalMatrix::eight_point(&pairs).ok()
    }

    fn residual(&self, model: &FundamentalMatrix, datum: &Self::Datum) -> f64 {
        model.sampson_distance(&datum.0, &datum.1)
    }
}

/// Robust `F`: RANSAC with [`FundamentalEstimator`], then guided refinement: rounds of
/// [`FundamentalMatrix::refine_sampson`] on the inliers and re-selection (Sampson distance
/// <= threshold), each kept only if it lowers the MSAC score over all pairs, until the
/// inlier set is stable.
pub fn estimate_fundamental(
    pairs: &[(Point2<f64>, Point2<f64>)],
    options: &RansacOptions,
) -> Result<RansacReport<FundamentalMatrix>> {
    let estimator = FundamentalEstimator { plane_threshold_px: options.threshold };
    let report = ransac(&estimator, pairs, options)?;
    let t = options.threshold;
    let msac = |f: &FundamentalMatrix| -> f64 {
        pairs.iter().map(|(l, r)| f.sampson_distance(l, r).min(t).powi(2)).sum()
    };
    let select = |f: &FundamentalMatrix| -> Vec<usize> {
        (0..pairs.len()).filter(|&i| f.sampson_distance(&pairs[i].0, &pairs[i].1) <= t).collect()
    };
    // Guided refinement: refine on the inliers, re-select, repeat while the MSAC cost
    // falls and the set changes. RANSAC's minimal models can stop short of the full
    // inlier set by some ten percent with a wide depth range; the refined model recovers it.
    let (mut model, mut cost, mut inliers) = (report.model, msac(&report.model), report.inliers.clone());
    for _ in 0..GUIDED_ROUNDS {
        let inlier_pairs: Vec<_> = inliers.iter().map(|&i| pairs[i]).collect();
        let Ok(refined) = model.refine_sampson(&inlier_pairs) else { break };
        let refined_cost = msac(&refined);
        if refined_cost >= cost {
            break;
        }
        let next = select(&refined);
        (model, cost) = (refined, refined_cost);
        if next == inliers || next.len() < 7 {
            break;
        }
        inliers = next;
    }
    let inliers = select(&model);
    if inliers.len() < 7 {
        return Ok(report);
    }
    let k = inliers.len();
    let sum_sq: f64 = inliers.iter().map(|&i| model.sampson_distance(&pairs[i].0, &pairs[i].1).powi(2)).sum();
    Ok(RansacReport {
        model,
        inlier_ratio: k as f64 / pairs.len() as f64,
        rms_inlier_residual: (sum_sq / k as f64).sqrt(),
        inliers,
        iterations: report.iterations,
    })
}

/// Maximum refine / re-select rounds of [`estimate_fundamental`].
const GUIDED_ROUNDS: usize = 10;

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::camera::{Intrinsics, ProjectiveCamera};
    use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion};
    use proptest::prelude::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, Normal};

    /// A random stereo rig and scene with ground truth.
    pub(crate) struct Scene {
        pub k_l: Intrinsics,
        pub k_r: Intrinsics,
        pub right_from_left: Isometry3<f64>,
        pub points: Vec<Point3<f64>>,
        pub pairs: Vec<(Point2<f64>, Point2<f64>)>,
    }

    impl Scene {
        pub fn p_left(&self) -> ProjectiveCamera {
            ProjectiveCamera::from_pose(&self.k_l, &Isometry3::identity())
        }
        pub fn p_right(&self) -> ProjectiveCamera {
            ProjectiveCamera::from_pose(&self.k_r, &self.right_from_left)
        }
        /// True F = K_r^-T [t]x R K_l^-1.
        pub fn f_true(&self) -> Matrix3<f64> {
            let r = self.right_from_left.rotation.to_rotation_matrix().into_inner();
            let t = self.right_from_left.translation.vector;
            let f = self.k_r.inverse_matrix().transpose() * so3::skew(&t) * r * self.k_l.inverse_matrix();
            normalise_scale(&f).unwrap()
        }
    }

    pub(crate) fn random_intrinsics(rng: &mut ChaCha8Rng) -> Intrinsics {
        Intrinsics {
            fx: rng.random_range(500.0..1200.0),
            fy: rng.random_range(500.0..1200.0),
            skew: rng.random_range(-2.0..2.0),
            cx: rng.random_range(300.0..450.0),
            cy: rng.random_range(230.0..330.0),
        }
    }

    /// Random rig (baseline 0.1-0.5 m, small relative rotation) and `n` points 1.5-6 m in
    /// front of both cameras, pixels with Gaussian noise `sigma`.
    pub(crate) fn random_scene(seed: u64, n: usize, sigma: f64) -> Scene {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let k_l = random_intrinsics(&mut rng);
        let k_r = random_intrinsics(&mut rng);
        let rot = UnitQuaternion::from_euler_angles(
            rng.random_range(-0.1..0.1),
            rng.random_range(-0.3..0.3),
            rng.random_range(-0.1..0.1),
        );
        let base = Vector3::new(
            -rng.random_range(0.1..0.5),
            rng.random_range(-0.05..0.05),
            rng.random_range(-0.05..0.05),
        );
        let right_from_left = Isometry3::from_parts(Translation3::from(base), rot);
        let normal = Normal::new(0.0, sigma.max(1e-300)).unwrap();
        let mut points = Vec::new();
        let mut pairs = Vec::new();
        while points.len() < n {
            let p = Point3::new(
                rng.random_range(-2.0..2.0),
                rng.random_range(-1.5..1.5),
                rng.random_range(1.5..6.0),
            );
            let pr = right_from_left * p;
            if pr.z < 0.5 {
                continue;
            }
            let mut l = k_l.project(&p).unwrap();
            let mut r = k_r.project(&pr).unwrap();
            if sigma > 0.0 {
                l += nalgebra::Vector2::new(normal.sample(&mut rng), normal.sample(&mut rng));
                r += nalgebra::Vector2::new(normal.sample(&mut rng), normal.sample(&mut rng));
            }
            points.push(p);
            pairs.push((l, r));
        }
        Scene { k_l, k_r, right_from_left, points, pairs }
    }

    fn same_up_to_sign(a: &Matrix3<f64>, b: &Matrix3<f64>) -> f64 {
        (a - b).norm().min((a + b).norm())
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(128))]

        #[test]
        fn eight_point_noise_free(seed in 0u64..1_000_000, n in 8usize..60) {
            let s = random_scene(seed, n, 0.0);
            let f = FundamentalMatrix::eight_point(&s.pairs).unwrap();
            // 1e-6: F has entries spanning ~1e-6..1 in pixel units; the normalised
            // solve is accurate to ~1e-12 relative, amplified by the denormalisation.
            prop_assert!(same_up_to_sign(&f.0, &s.f_true()) < 1e-6, "{}", same_up_to_sign(&f.0, &s.f_true()));
            prop_assert!((f.0.norm() - 1.0).abs() < 1e-12);
            prop_assert!(f.0.determinant().abs() < 1e-15);
            for (l, r) in &s.pairs {
                // 1e-7 px: exact data, rounding in pixel units of ~1e3.
                prop_assert!(f.sampson_distance(l, r) < 1e-7);
            }
        }

        #[test]
        fn seven_point_contains_truth(seed in 0u64..1_000_000) {
            let s = random_scene(seed, 7, 0.0);
            let sols = FundamentalMatrix::seven_point(&s.pairs).unwrap();
            prop_assert!(sols.len() == 1 || sols.len() == 3 || sols.len() == 2);
            let best = sols.iter().map(|f| same_up_to_sign(&f.0, &s.f_true())).fold(f64::INFINITY, f64::min);
            // 1e-5: the 7-point cubic root is polished by Newton; conditioning of
            // random 7-point sets varies, some are close to degenerate.
            prop_assert!(best < 1e-5, "{best}");
            for f in &sols {
                prop_assert!(f.0.determinant().abs() < 1e-10);
                for (l, r) in &s.pairs {
                    prop_assert!(f.sampson_distance(l, r) < 1e-6);
                }
            }
        }

        #[test]
        fn seven_point_null_space_satisfies_the_epipolar_constraint(seed in 0u64..1_000_000) {
            let s = random_scene(seed, 7, 0.0);
            let pairs: [(Point2<f64>, Point2<f64>); 7] = std::array::from_fn(|k| s.pairs[k]);
            let tl = normalising_transform_2d(pairs.iter().map(|p| &p.0)).unwrap();
            let tr = normalising_transform_2d(pairs.iter().map(|p| &p.1)).unwrap();
            let rows: [[f64; 9]; 7] = pairs.map(|(l, r)| {
                let (xl, xr) = (apply(&tl, &l), apply(&tr, &r));
                std::array::from_fn(|i| xr[i / 3] * xl[i % 3])
            });
            let [n1, n2] = null_space_7x9(rows).unwrap();
            let dot = |a: &[f64; 9], b: &[f64; 9]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
            let eps = f64::EPSILON;
            // Householder QR is backward stable: the basis is orthonormal to ~eps and exactly
            // null for A + E with |E| <~ c m n eps |A| (Higham, ASNA 2nd ed., thm 19.4); 7
            // reflections of length <= 9: 64 eps covers the constant (measured over seeds
            // 0..5000: orthonormality within 5 eps, |a_i . n| within 1.7 eps |A|).
            prop_assert!((dot(&n1, &n1) - 1.0).abs() < 64.0 * eps && (dot(&n2, &n2) - 1.0).abs() < 64.0 * eps);
            prop_assert!(dot(&n1, &n2).abs() < 64.0 * eps);
            let a_norm = rows.iter().flatten().map(|v| v * v).sum::<f64>().sqrt();
            for row in &rows {
                for n in [&n1, &n2] {
                    prop_assert!(dot(row, n).abs() < 64.0 * eps * a_norm, "{:e} vs |A| {a_norm:e}", dot(row, n));
                }
            }
            // In pixels, |x_r^T F x_l| is bounded by the null space's backward error and by
            // the denormalisation F = T_r^T G T_l / |.|, whose rounding is amplified by the
            // cancellation in T x (the elementwise condition |x_r|^T |T_r|^T |G| |T_l| |x_l|,
            // ~1e3 times |x_r^T F x_l|'s natural scale for Hartley transforms of pixels);
            // measured over seeds 0..5000: at most 0.92 eps (cond + backward), 64 is margin.
            let (tl_inv, tr_inv) = (tl.try_inverse().unwrap(), tr.try_inverse().unwrap());
            for f in FundamentalMatrix::seven_point(&s.pairs).unwrap() {
                let g = tr_inv.transpose() * f.0 * tl_inv;
                for (l, r) in &pairs {
                    let (xl, xr) = (homogeneous(l), homogeneous(r));
                    let cond = xr.abs().dot(&(tr.abs().transpose() * g.abs() * tl.abs() * xl.abs()));
                    let backward = g.norm() * a_norm;
                    let tol = 64.0 * eps * (cond + backward);
                    let e = f.algebraic(l, r);
                    prop_assert!(e.abs() < tol, "{e:e} >= {tol:e} (cond {cond:e})");
                }
            }
        }

        #[test]
        fn soa_sampson_count_matches_sampson_distance(seed in 0u64..1_000_000) {
            let s = random_scene(seed, 300, 2.0);
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let mut pairs = s.pairs.clone();
            for pair in pairs.iter_mut().take(100) {
                pair.1 = Point2::new(rng.random_range(0.0..768.0), rng.random_range(0.0..576.0));
            }
            let all: Vec<usize> = (0..pairs.len()).collect();
            let soa = SoaMatches::gather(&pairs, &all);
            let f = FundamentalMatrix(s.f_true());
            // Thresholds at the data's own distances: ties must fall the same way, so the
            // arithmetic has to be identical, not just close.
            for tol in [0.5, 2.0, f.sampson_distance(&pairs[7].0, &pairs[7].1)] {
                let slow = pairs.iter().filter(|(l, r)| f.sampson_distance(l, r) <= tol).count();
                prop_assert_eq!(soa.within_sampson(&f, tol), slow);
            }
            for (k, (l, r)) in pairs.iter().enumerate().take(20) {
                let one = SoaMatches::gather(&pairs, &[k]);
                let d = f.sampson_distance(l, r);
                prop_assert_eq!(one.within_sampson(&f, d), 1);
                prop_assert_eq!(one.within_sampson(&f, d * (1.0 - f64::EPSILON)), 0);
            }
        }

        #[test]
        fn epipoles_are_null_vectors(seed in 0u64..1_000_000) {
            let s = random_scene(seed, 20, 0.0);
            let f = FundamentalMatrix::eight_point(&s.pairs).unwrap();
            let (el, er) = f.epipoles().unwrap();
            // An SVD's singular vector is accurate to eps over the relative gap
            // sigma_2 / sigma_1 (Davis-Kahan), so |F e| (|F| = 1) is bounded by eps / gap:
            // the tolerance is 16 times that (measured over seeds 0..300000: at most 1.5).
            let sv = f.0.singular_values();
            let gap = (sv.sum() - sv.min() - sv.max()) / sv.max();
            let svd_error = f64::EPSILON / gap;
            prop_assert!((f.0 * el).norm() < 16.0 * svd_error, "{} at gap {gap:e}", (f.0 * el).norm());
            prop_assert!(
                (f.0.transpose() * er).norm() < 16.0 * svd_error,
                "{} at gap {gap:e}",
                (f.0.transpose() * er).norm()
            );
            // The left epipole is the image of the right camera centre in the left camera.
            // It is as accurate as F over the gap (sin-theta theorem): |F - F_true| (both of
            // norm 1, same sign) plus the SVD's own error, over the gap, twice that
            // (measured over seeds 0..300000: at most 0.67 of the bound without the 2).
            let c_r = s.p_right().centre().unwrap();
            let e_true = s.p_left().0 * c_r;
            let f_true = s.f_true().normalize();
            let f_true = if f_true.dot(&f.0) < 0.0 { -f_true } else { f_true };
            let f_error = (f.0.normalize() - f_true).norm();
            let angle = el.cross(&e_true.normalize()).norm();
            prop_assert!(angle < 2.0 * (f_error + svd_error) / gap, "{angle:e} at gap {gap:e}");
        }

        #[test]
        fn refine_sampson_does_not_increase_cost(seed in 0u64..1_000_000) {
            let s = random_scene(seed, 40, 1.0);
            let f0 = FundamentalMatrix::eight_point(&s.pairs).unwrap();
            let f1 = f0.refine_sampson(&s.pairs).unwrap();
            let c0 = sampson_cost(&f0.0, &s.pairs);
            let c1 = sampson_cost(&f1.0, &s.pairs);
            prop_assert!(c1 <= c0, "{c1} > {c0}");
            prop_assert!(f1.0.determinant().abs() < 1e-14);
            // With sigma = 1 px the Sampson RMS should be near sigma * sqrt((2n - 7) / (2n))... < 2 px.
            prop_assert!((c1 / s.pairs.len() as f64).sqrt() < 2.0);
        }
    }

    #[test]
    fn refine_sampson_reaches_truth_on_exact_data_from_perturbed_start() {
        let s = random_scene(11, 30, 0.0);
        let truth = s.f_true();
        let tl = normalising_transform_2d(s.pairs.iter().map(|p| &p.0)).unwrap();
        let tr = normalising_transform_2d(s.pairs.iter().map(|p| &p.1)).unwrap();
        let p = Rank2Param::from_matrix(&truth, tl, tr).unwrap();
        let start =
            p.updated(&SVector::<f64, 7>::from_column_slice(&[1e-3, -2e-3, 1e-3, 2e-3, 1e-3, -1e-3, 1e-3]));
        let f = FundamentalMatrix(start.matrix()).refine_sampson(&s.pairs).unwrap();
        // 1e-7: LM on exact data converges to the truth; residual rounding in pixels.
        assert!(same_up_to_sign(&f.0, &truth) < 1e-7, "{}", same_up_to_sign(&f.0, &truth));
        assert!(sampson_cost(&f.0, &s.pairs) < 1e-14);
    }

    #[test]
    fn sampson_jacobian_matches_finite_differences() {
        let s = random_scene(5, 10, 1.0);
        let f0 = FundamentalMatrix::eight_point(&s.pairs).unwrap();
        let tl = normalising_transform_2d(s.pairs.iter().map(|p| &p.0)).unwrap();
        let tr = normalising_transform_2d(s.pairs.iter().map(|p| &p.1)).unwrap();
        let p = Rank2Param::from_matrix(&f0.0, tl, tr).unwrap();
        for (l, r) in &s.pairs {
            let (_, j) = p.residual_and_jacobian(l, r).unwrap();
            for k in 0..7 {
                let h = 1e-6;
                let mut d = SVector::<f64, 7>::zeros();
                d[k] = h;
                let rp = sampson_residual_grad(&p.updated(&d).matrix(), l, r).unwrap().0;
                d[k] = -h;
                let rm = sampson_residual_grad(&p.updated(&d).matrix(), l, r).unwrap().0;
                let fd = (rp - rm) / (2.0 * h);
                // Central differences: O(h^2) truncation plus ~1e-16/h rounding.
                assert!((fd - j[k]).abs() < 1e-5 * (1.0 + j[k].abs()), "k={k}: fd {fd} vs {}", j[k]);
            }
        }
    }

    #[test]
    fn estimate_fundamental_with_outliers() {
        let mut s = random_scene(3, 200, 0.5);
        let mut rng = ChaCha8Rng::seed_from_u64(99);
        let n_out = 40;
        for i in 0..n_out {
            s.pairs[i].1 = Point2::new(rng.random_range(0.0..768.0), rng.random_range(0.0..576.0));
        }
        let opts = RansacOptions { threshold: 2.0, ..Default::default() };
        let rep = estimate_fundamental(&s.pairs, &opts).unwrap();
        // Outliers are uniform in the image: a few may fall within 2 px of their epipolar line.
        let wrong = rep.inliers.iter().filter(|&&i| i < n_out).count();
        assert!(wrong <= 4, "{wrong} outliers accepted");
        let good = rep.inliers.iter().filter(|&&i| i >= n_out).count();
        assert!(good >= 155, "only {good} of 160 inliers");
        assert!(rep.rms_inlier_residual < 1.0);
        let again = estimate_fundamental(&s.pairs, &opts).unwrap();
        assert_eq!(rep, again);
    }

    #[test]
    fn degenerate_inputs_give_errors() {
        let p = Point2::new(1.0, 2.0);
        assert!(matches!(
            FundamentalMatrix::eight_point(&[(p, p); 5]),
            Err(GeometryError::NotEnoughData { .. })
        ));
        assert!(FundamentalMatrix::eight_point(&[(p, p); 10]).is_err());
        assert!(FundamentalMatrix::seven_point(&[(p, p); 8]).is_err());
        assert!(FundamentalMatrix::seven_point(&[(p, p); 7]).is_err());
        // Points on a line in both images.
        let line: Vec<_> = (0..12)
            .map(|i| (Point2::new(i as f64, 2.0 * i as f64), Point2::new(3.0 * i as f64, 1.0)))
            .collect();
        assert!(FundamentalMatrix::eight_point(&line).is_err());
        assert!(FundamentalMatrix(Matrix3::zeros()).epipoles().is_err());
        let nan = vec![(Point2::new(f64::NAN, 0.0), p); 9];
        assert!(FundamentalMatrix::eight_point(&nan).is_err());
    }

    /// A scene dominated by one plane: `on_plane` of the `n` points on a random plane 2.5-4
    /// m away, the rest spread 1.5-6 m; rig and intrinsics as in [`random_scene`].
    fn plane_scene(seed: u64, n: usize, on_plane: usize, sigma: f64) -> Scene {
        let mut s = random_scene(seed, 1, 0.0);
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x9e37_79b9);
        let normal = Normal::new(0.0, sigma.max(1e-300)).unwrap();
        let (d, a, b) =
            (rng.random_range(2.5..4.0), rng.random_range(-0.3..0.3), rng.random_range(-0.3..0.3));
        s.points.clear();
        s.pairs.clear();
        while s.points.len() < n {
            let (x, y) = (rng.random_range(-2.0..2.0), rng.random_range(-1.5..1.5));
            let z = if s.points.len() < on_plane { d + a * x + b * y } else { rng.random_range(1.5..6.0) };
            let p = Point3::new(x, y, z);
            let pr = s.right_from_left * p;
            if pr.z < 0.5 {
                continue;
            }
            let noise = |rng: &mut ChaCha8Rng| {
                if sigma > 0.0 {
                    nalgebra::Vector2::new(normal.sample(rng), normal.sample(rng))
                } else {
                    nalgebra::Vector2::zeros()
                }
            };
            let l = s.k_l.project(&p).unwrap() + noise(&mut rng);
            let r = s.k_r.project(&pr).unwrap() + noise(&mut rng);
            s.points.push(p);
            s.pairs.push((l, r));
        }
        s
    }

    #[test]
    fn degensac_triplets_cover_every_five_points() {
        // Any 5 of 7 points = all but a pair {a, b}: some triplet must avoid both.
        for a in 0..7 {
            for b in a + 1..7 {
                assert!(
                    DEGENSAC_TRIPLETS.iter().any(|t| !t.contains(&a) && !t.contains(&b)),
                    "no triplet inside the points without {a} and {b}"
                );
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        #[test]
        fn compatible_homography_maps_the_plane(seed in 0u64..1_000_000) {
            let s = plane_scene(seed, 20, 20, 0.0);
            let f = FundamentalMatrix(s.f_true());
            let (_, e_right) = f.epipoles().unwrap();
            let three = [s.pairs[0], s.pairs[1], s.pairs[2]];
            let h = homography_compatible_with_f(&f, &e_right, &three).unwrap();
            let h = crate::homography2d::Homography2(h);
            for (l, r) in &s.pairs {
                // 1e-6 px: exact data; the 3x3 solve in pixel units loses ~1e-10 relative.
                let e = h.transfer_error(l, r);
                prop_assert!(e < 1e-6, "{e}");
            }
            // ... and it is compatible with F: H^T F is antisymmetric (H&Z result 13.3).
            let m = h.0.transpose() * f.0;
            prop_assert!((m + m.transpose()).norm() < 1e-9 * m.norm(), "{}", (m + m.transpose()).norm());
        }

        #[test]
        fn plane_and_parallax_recovers_f_from_a_planar_sample(seed in 0u64..1_000_000) {
            // Noise-free, 7 sample points on the plane: the 7-point family is ambiguous, the
            // plane-and-parallax model is exact.
            let s = plane_scene(seed, 60, 40, 0.0);
            let est = FundamentalEstimator::default();
            let sample: Vec<usize> = (0..7).collect();
            let models = est.fit_minimal(&s.pairs, &sample);
            let best = models.iter().map(|f| same_up_to_sign(&f.0, &s.f_true())).fold(f64::INFINITY, f64::min);
            // 1e-6: exact data, F entries span ~1e-6..1 in pixel units.
            prop_assert!(best < 1e-6, "{best}");
        }
    }

    #[test]
    fn plane_dominated_scene_finds_every_inlier() {
        // 85 % of the points on one plane, 1 px noise, 15 % outliers: the estimate must
        // explain the data at least as well as the true F (MSAC cost within 2 %, a few
        // noisy points either side of the threshold), over several scenes and seeds.
        for seed in 0..12u64 {
            let mut s = plane_scene(seed, 300, 255, 1.0);
            let mut rng = ChaCha8Rng::seed_from_u64(seed + 77);
            for pair in s.pairs.iter_mut().take(45) {
                pair.1 = Point2::new(rng.random_range(0.0..768.0), rng.random_range(0.0..576.0));
            }
            let opts = RansacOptions { threshold: 3.0, seed, ..RansacOptions::default() };
            let rep = estimate_fundamental(&s.pairs, &opts).unwrap();
            let msac = |f: &Matrix3<f64>| -> f64 {
                let f = FundamentalMatrix(*f);
                s.pairs.iter().map(|(l, r)| f.sampson_distance(l, r).min(3.0).powi(2)).sum()
            };
            let (found, truth) = (msac(&rep.model.0), msac(&s.f_true()));
            assert!(found <= 1.02 * truth, "seed {seed}: MSAC {found:.1} vs true F {truth:.1}");
        }
    }

    #[test]
    fn cubic_roots() {
        // (x - 1)(x - 2)(x + 3) = x^3 - 7x + 6
        let mut r = real_roots_cubic([6.0, -7.0, 0.0, 1.0]);
        r.sort_by(f64::total_cmp);
        assert!((r[0] + 3.0).abs() < 1e-12 && (r[1] - 1.0).abs() < 1e-12 && (r[2] - 2.0).abs() < 1e-12);
        // x^3 + x + 1: one real root.
        assert_eq!(real_roots_cubic([1.0, 1.0, 0.0, 1.0]).len(), 1);
        // Leading coefficient zero: quadratic (x-1)(x-2).
        assert_eq!(real_roots_cubic([2.0, -3.0, 1.0, 0.0]).len(), 2);
    }
}
