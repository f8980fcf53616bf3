//! Lens distortion in OpenCV's `plumb_bob` model (also ROS's), on normalised image
//! coordinates `x = K^-1 p`:
//!
//! ```text
//! r^2 = x^2 + y^2
//! x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
//! y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y
//! ```
//!
//! Degrees of freedom: 5 (`k1 k2 p1 p2 k3`, OpenCV's order of `D`). Undistortion inverts
//! the map by Newton's method with the analytic 2x2 Jacobian (at most 30 steps, stops
//! below 1e-14 in normalised units); where the Jacobian is singular (beyond the radius at
//! which a strong barrel model folds back) it is an error, never a wrong point.
//! [`Distortion::undistort_pixel`] maps a distorted pixel to the pixel an ideal pinhole
//! camera with the same `K` would see, which is how headalign uses a known lens model:
//! observations are undistorted once, everything after is pinhole.
//!
//! Units: coefficients are dimensionless (normalised coordinates); pixels outside.
//! Pitfall: the coefficients belong to the `K` they were estimated with; undistorting with
//! a different `K` is a different lens model.

use nalgebra::{Matrix2, Point2, Vector2};
use serde::{Deserialize, Serialize};

use crate::camera::Intrinsics;
use crate::{GeometryError, Result};

/// OpenCV `plumb_bob` distortion coefficients (zero is the pinhole).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Distortion {
    /// Radial, `r^2`.
    pub k1: f64,
    /// Radial, `r^4`.
    pub k2: f64,
    /// Tangential.
    pub p1: f64,
    /// Tangential.
    pub p2: f64,
    /// Radial, `r^6`.
    pub k3: f64,
}

/// Newton iterations of [`Distortion::undistort`].
const MAX_STEPS: usize = 30;

impl Distortion {
    /// Radial only.
    pub fn radial(k1: f64, k2: f64) -> Self {
        Self { k1, k2, ..Self::default() }
    }

    /// From OpenCV's `D` vector (4, 5 or more entries: `k1 k2 p1 p2 [k3 ...]`; entries
    /// beyond `k3` must be zero, the rational model is not supported).
    pub fn from_opencv(d: &[f64]) -> Result<Self> {
        if d.len() < 4 {
            return Err(GeometryError::InvalidOption(format!(
                "a distortion vector needs at least 4 coefficients (k1 k2 p1 p2 [k3]), got {}",
                d.len()
            )));
        }
        if d.iter().skip(5).any(|&v| v != 0.0) {
            return Err(GeometryError::InvalidOption(
                "distortion coefficients beyond k3 (OpenCV's rational model) are not supported".into(),
            ));
        }
        let out = Self { k1: d[0], k2: d[1], p1: d[2], p2: d[3], k3: d.get(4).copied().unwrap_or(0.0) };
        out.validate()?;
        Ok(out)
    }

    /// As OpenCV's 5-vector `k1 k2 p1 p2 k3`.
    pub fn to_opencv(&self) -> [f64; 5] {
        [self.k1, self.k2, self.p1, self.p2, self.k3]
    }

    /// Every coefficient finite.
    pub fn validate(&self) -> Result<()> {
        if self.to_opencv().iter().all(|v| v.is_finite()) {
            Ok(())
        } else {
            Err(GeometryError::InvalidOption("distortion coefficients must be finite".into()))
        }
    }

    /// True for the pinhole (all zero).
    pub fn is_zero(&self) -> bool {
        self.to_opencv().iter().all(|&v| v == 0.0)
    }

    /// Distorted normalised coordinates and the Jacobian `d x_d / d x`.
    pub fn distort_with_jacobian(&self, x: &Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>) {
        let (u, v) = (x.x, x.y);
        let r2 = u * u + v * v;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        // d radial / d r2
        let dradial = self.k1 + r2 * (2.0 * self.k2 + 3.0 * r2 * self.k3);
        let xd = u * radial + 2.0 * self.p1 * u * v + self.p2 * (r2 + 2.0 * u * u);
        let yd = v * radial + self.p1 * (r2 + 2.0 * v * v) + 2.0 * self.p2 * u * v;
        let j = Matrix2::new(
            radial + 2.0 * u * u * dradial + 2.0 * self.p1 * v + 6.0 * self.p2 * u,
            2.0 * u * v * dradial + 2.0 * self.p1 * u + 2.0 * self.p2 * v,
            2.0 * u * v * dradial + 2.0 * self.p1 * u + 2.0 * self.p2 * v,
            radial + 2.0 * v * v * dradial + 6.0 * self.p1 * v + 2.0 * self.p2 * u,
        );
        (Vector2::new(xd, yd), j)
    }

    /// Distorted normalised coordinates.
    pub fn distort(&self, x: &Vector2<f64>) -> Vector2<f64> {
        self.distort_with_jacobian(x).0
    }

    /// Undistorted normalised coordinates of distorted ones (Newton, see module docs).
    pub fn undistort(&self, xd: &Vector2<f64>) -> Result<Vector2<f64>> {
        if self.is_zero() {
            return Ok(*xd);
        }
        if !(xd.x.is_finite() && xd.y.is_finite()) {
            return Err(GeometryError::InvalidOption("non-finite point to undistort".into()));
        }
        let mut x = *xd;
        for _ in 0..MAX_STEPS {
            let (f, j) = self.distort_with_jacobian(&x);
            let r = f - xd;
            if r.norm() < 1e-14 {
                return Ok(x);
            }
            let det = j.determinant();
            let inv = j.try_inverse().filter(|_| det > 1e-9).ok_or_else(|| {
                GeometryError::Degenerate(format!(
                    "distortion folds over near ({:.3}, {:.3}): not invertible there",
                    xd.x, xd.y
                ))
            })?;
            x -= inv * r;
        }
        let r = self.distort(&x) - xd;
        if r.norm() < 1e-9 {
            Ok(x)
        } else {
            Err(GeometryError::Numerical(format!(
                "undistortion did not converge at ({:.3}, {:.3})",
                xd.x, xd.y
            )))
        }
    }

    /// The pixel an ideal pinhole camera with intrinsics `k` would see for a pixel of this
    /// distorted camera.
    pub fn undistort_pixel(&self, k: &Intrinsics, pixel: &Point2<f64>) -> Result<Point2<f64>> {
        let ray = k.unproject(pixel);
        let x = self.undistort(&Vector2::new(ray.x, ray.y))?;
        Ok(k.project_unchecked(&nalgebra::Point3::new(x.x, x.y, 1.0)))
    }

    /// The distorted pixel of an ideal pinhole pixel (inverse of [`Self::undistort_pixel`]).
    pub fn distort_pixel(&self, k: &Intrinsics, pixel: &Point2<f64>) -> Point2<f64> {
        let ray = k.unproject(pixel);
        let x = self.distort(&Vector2::new(ray.x, ray.y));
        k.project_unchecked(&nalgebra::Point3::new(x.x, x.y, 1.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]
        /// Round trip over a 768x576 image with realistic lenses (|k1| <= 0.3): 1e-9 px
        /// (Newton converges quadratically; the stop is 1e-14 in normalised units).
        #[test]
        fn undistort_inverts_distort(
            k1 in -0.3..0.3f64, k2 in -0.1..0.1f64, p1 in -0.002..0.002f64, p2 in -0.002..0.002f64,
            k3 in -0.02..0.02f64, u in 0.0..768.0f64, v in 0.0..576.0f64,
        ) {
            let d = Distortion { k1, k2, p1, p2, k3 };
            let k = Intrinsics::new(700.0, 720.0, 390.0, 284.0);
            let ideal = Point2::new(u, v);
            let distorted = d.distort_pixel(&k, &ideal);
            let back = d.undistort_pixel(&k, &distorted).unwrap();
            prop_assert!((back - ideal).norm() < 1e-9, "{back:?} vs {ideal:?}");
        }

        /// Analytic Jacobian against central differences (step 1e-6, tolerance 1e-7).
        #[test]
        fn jacobian_matches_finite_differences(
            k1 in -0.3..0.3f64, k2 in -0.1..0.1f64, p1 in -0.01..0.01f64, p2 in -0.01..0.01f64,
            k3 in -0.05..0.05f64, x in -0.7..0.7f64, y in -0.5..0.5f64,
        ) {
            let d = Distortion { k1, k2, p1, p2, k3 };
            let p = Vector2::new(x, y);
            let (_, j) = d.distort_with_jacobian(&p);
            let h = 1e-6;
            for c in 0..2 {
                let mut e = Vector2::zeros();
                e[c] = h;
                let fd = (d.distort(&(p + e)) - d.distort(&(p - e))) / (2.0 * h);
                prop_assert!((fd - j.column(c)).norm() < 1e-7, "column {c}: {fd:?} vs {:?}", j.column(c));
            }
        }
    }

    #[test]
    fn bad_inputs_are_errors() {
        assert!(Distortion::from_opencv(&[0.1, 0.2]).is_err());
        assert!(Distortion::from_opencv(&[0.1, f64::NAN, 0.0, 0.0]).is_err());
        assert!(Distortion::from_opencv(&[0.1, 0.0, 0.0, 0.0, 0.0, 0.3]).is_err());
        assert_eq!(Distortion::from_opencv(&[0.1, 0.2, 0.0, 0.0]).unwrap(), Distortion::radial(0.1, 0.2));
        // A strong barrel lens folds over far out: an error, not a wrong point.
        let d = Distortion::radial(-0.5, 0.0);
        assert!(d.undistort(&Vector2::new(2.0, 0.0)).is_err());
        assert!(d.undistort(&Vector2::new(f64::NAN, 0.0)).is_err());
    }
}
