//! Plane projective homographies `x' ~ G x` (8 dof): normalised 4-point DLT (Hartley &
//! Zisserman algorithm 4.2), one-sided transfer error in pixels, and a RANSAC adapter.
//!
//! Used as a robust prefilter: a small head rotation maps each camera's image almost by
//! the infinite homography `K R K^-1` (the parallax from axis offsets is a few pixels), so
//! a 4-point homography RANSAC with a threshold of a few pixels separates wrong matches
//! from right ones far more reliably than the 15-dof 3D homography's minimal solver.
//! Pitfall: this is an approximation for rotations, not a model of the scene; the 3D
//! homography and the bundle adjustment do the estimation.

use nalgebra::{DMatrix, Matrix3, Point2, Vector3};

use crate::linear::{normalising_transform_2d, smallest_right_singular_vectors};
use crate::ransac::Estimator;
use crate::{GeometryError, Result};

/// A plane homography, `x' ~ G x`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Homography2(pub Matrix3<f64>);

impl Homography2 {
    /// Normalised DLT from at least 4 correspondences.
    pub fn dlt(pairs: &[(Point2<f64>, Point2<f64>)]) -> Result<Self> {
        if pairs.len() < 4 {
            return Err(GeometryError::NotEnoughData {
                what: "point pairs for a homography",
                needed: 4,
                got: pairs.len(),
            });
        }
        let a_pts: Vec<Point2<f64>> = pairs.iter().map(|p| p.0).collect();
        let b_pts: Vec<Point2<f64>> = pairs.iter().map(|p| p.1).collect();
        let ta = normalising_transform_2d(a_pts.iter())?;
        let tb = normalising_transform_2d(b_pts.iter())?;
        let mut m = DMatrix::<f64>::zeros(2 * pairs.len(), 9);
        for (i, (a, b)) in pairs.iter().enumerate() {
            let x = ta * Vector3::new(a.x, a.y, 1.0);
            let y = tb * Vector3::new(b.x, b.y, 1.0);
            // y x (G x) = 0, two independent rows.
            for c in 0..3 {
                m[(2 * i, 3 + c)] = -y.z * x[c];
                m[(2 * i, 6 + c)] = y.y * x[c];
                m[(2 * i + 1, c)] = y.z * x[c];
                m[(2 * i + 1, 6 + c)] = -y.x * x[c];
            }
        }
        let (v, _) = smallest_right_singular_vectors(&m, 1)?;
        let h = v.first().ok_or_else(|| GeometryError::Numerical("no null vector".into()))?;
        let g = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
        let tb_inv =
            tb.try_inverse().ok_or_else(|| GeometryError::Numerical("singular normalisation".into()))?;
        let g = tb_inv * g * ta;
        let n = g.norm();
        if !n.is_finite() || n <= 0.0 || g.determinant().abs() < 1e-12 * n * n * n {
            return Err(GeometryError::Degenerate("homography is singular (collinear points?)".into()));
        }
        Ok(Self(g / n))
    }

    /// Distance in pixels between `G a` and `b` (infinite if `G a` is at infinity).
    pub fn transfer_error(&self, a: &Point2<f64>, b: &Point2<f64>) -> f64 {
        let p = self.0 * Vector3::new(a.x, a.y, 1.0);
        if p.z.abs() < 1e-300 {
            return f64::INFINITY;
        }
        ((p.x / p.z - b.x).powi(2) + (p.y / p.z - b.y).powi(2)).sqrt()
    }
}

/// RANSAC estimator: datum `(a, b)`, residual the transfer error in pixels.
#[derive(Debug, Clone, Copy, Default)]
pub struct Homography2Estimator;

impl Estimator for Homography2Estimator {
    type Datum = (Point2<f64>, Point2<f64>);
    type Model = Homography2;

    fn sample_size(&self) -> usize {
        4
    }

    fn fit_minimal(&self, data: &[Self::Datum], sample: &[usize]) -> Vec<Homography2> {
        let pairs: Vec<_> = sample.iter().filter_map(|&i| data.get(i).copied()).collect();
        Homography2::dlt(&pairs).into_iter().collect()
    }

    fn fit_inliers(&self, data: &[Self::Datum], inliers: &[usize]) -> Option<Homography2> {
        let pairs: Vec<_> = inliers.iter().filter_map(|&i| data.get(i).copied()).collect();
        Homography2::dlt(&pairs).ok()
    }

    fn residual(&self, model: &Homography2, datum: &Self::Datum) -> f64 {
        model.transfer_error(&datum.0, &datum.1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ransac::{RansacOptions, ransac};
    use proptest::prelude::*;

    proptest! {
        /// Noise-free: the DLT reproduces every correspondence to 1e-8 px (conditioned
        /// 9-column SVD, pixel coordinates ~1e3).
        #[test]
        fn dlt_is_exact(h in prop::array::uniform8(-0.2..0.2f64)) {
            let g = Matrix3::new(1.0 + h[0], h[1], 30.0 * h[2], h[3], 1.0 + h[4], 30.0 * h[5], 1e-4 * h[6], 1e-4 * h[7], 1.0);
            let pairs: Vec<_> = (0..30).map(|i| {
                let a = Point2::new((i * 37 % 768) as f64, (i * 53 % 576) as f64);
                let p = g * Vector3::new(a.x, a.y, 1.0);
                (a, Point2::new(p.x / p.z, p.y / p.z))
            }).collect();
            let est = Homography2::dlt(&pairs).unwrap();
            for (a, b) in &pairs {
                prop_assert!(est.transfer_error(a, b) < 1e-8);
            }
        }
    }

    #[test]
    fn ransac_rejects_outliers() {
        let g = Matrix3::new(1.01, 0.02, 5.0, -0.01, 0.99, -3.0, 1e-5, 0.0, 1.0);
        let mut data = Vec::new();
        for i in 0..100 {
            let a = Point2::new((i * 37 % 768) as f64, (i * 53 % 576) as f64);
            let p = g * Vector3::new(a.x, a.y, 1.0);
            let mut b = Point2::new(p.x / p.z, p.y / p.z);
            if i % 5 == 0 {
                b.x += 80.0;
            }
            data.push((a, b));
        }
        let rep =
            ransac(&Homography2Estimator, &data, &RansacOptions { threshold: 1.0, ..Default::default() })
                .unwrap();
        assert_eq!(rep.inliers.len(), 80);
        assert!(rep.inliers.iter().all(|i| i % 5 != 0));
        assert!(Homography2::dlt(&data[..3]).is_err());
    }
}
