//! Linear-algebra steps shared by the linear solvers (fundamental matrix, plane and 3D
//! homographies, triangulation): the right null space of a homogeneous system by SVD and
//! the Hartley normalisation of 2D points (Hartley & Zisserman 2nd ed., section 4.4.4).
//!
//! Pitfalls handled: nalgebra's SVD is thin, so a system with fewer rows than columns is
//! padded with zero rows to square (the thin SVD would drop the null space), and one with
//! many rows is first reduced to its square `R` factor by QR (same right singular vectors,
//! without forming `A^T A`, which would square the condition number); SVDs use `try_svd`
//! with an iteration limit and fail with a typed error; coincident points (zero spread)
//! cannot be normalised and are an error. No units: the inputs' own.

use nalgebra::{DMatrix, DVector, Matrix3, Point2};

use crate::{GeometryError, Result};

/// Iteration limit of every SVD in this crate's linear solvers.
pub(crate) const SVD_MAX_ITER: usize = 1000;

/// Right singular vectors of `a` for its `k` smallest singular values (smallest first),
/// and all singular values in decreasing order (padded with zeros to the column count).
///
/// Handles any number of rows: fewer rows than columns are padded with zero rows (the
/// thin SVD would otherwise drop the null space), more are reduced by QR to a square `R`.
pub(crate) fn smallest_right_singular_vectors(
    a: &DMatrix<f64>,
    k: usize,
) -> Result<(Vec<DVector<f64>>, DVector<f64>)> {
    let (m, n) = a.shape();
    if !a.iter().all(|v| v.is_finite()) {
        return Err(GeometryError::Numerical("non-finite entry in a linear system".into()));
    }
    let square = if m > n {
        a.clone().qr().r()
    } else {
        let mut s = DMatrix::zeros(n, n);
        s.view_mut((0, 0), (m, n)).copy_from(a);
        s
    };
    let svd = square
        .try_svd(false, true, f64::EPSILON, SVD_MAX_ITER)
        .ok_or_else(|| GeometryError::Numerical("SVD did not converge".into()))?;
    let v_t = svd.v_t.ok_or_else(|| GeometryError::Numerical("SVD without V".into()))?;
    // try_svd sorts the singular values in decreasing order.
    let out = (0..k.min(n)).map(|i| v_t.row(n - 1 - i).transpose()).collect();
    Ok((out, svd.singular_values))
}

/// Hartley normalisation of 2D points: the similarity `T` moving the centroid to the
/// origin and the mean distance to it to sqrt 2.
pub(crate) fn normalising_transform_2d<'a>(
    points: impl Iterator<Item = &'a Point2<f64>> + Clone,
) -> Result<Matrix3<f64>> {
    let n = points.clone().count() as f64;
    if n == 0.0 {
        return Err(GeometryError::NotEnoughData { what: "points to normalise", needed: 1, got: 0 });
    }
    let c = points.clone().map(|p| p.coords).sum::<nalgebra::Vector2<f64>>() / n;
    let mean_dist = points.map(|p| (p.coords - c).norm()).sum::<f64>() / n;
    if !mean_dist.is_finite() || mean_dist <= 1e-12 * (1.0 + c.norm()) {
        return Err(GeometryError::Degenerate("all points coincide".into()));
    }
    let s = std::f64::consts::SQRT_2 / mean_dist;
    Ok(Matrix3::new(s, 0.0, -s * c.x, 0.0, s, -s * c.y, 0.0, 0.0, 1.0))
}
