//! Least-squares registration of 3D point sets (Kabsch / Umeyama, "Least-squares
//! estimation of transformation parameters between two point patterns", PAMI 1991), and
//! a RANSAC adapter that uses it as a 3-point minimal solver for 3D homographies in a
//! quasi-Euclidean frame.
//!
//! [`similarity_fit`] finds `y ~ s R x + t` (7 dof; 6 with the scale fixed to 1) minimising
//! the sum of squared 3D distances. Degenerate when the points are collinear (rank < 2 of
//! the centred cross-covariance).
//!
//! [`RigidFrameEstimator`]: in the frame of [`crate::frame`] the reconstruction is
//! Euclidean up to the error of the rough calibration, so the 3D homography of a head
//! rotation is close to a rigid motion. A 3-point rigid fit is far better conditioned
//! under noise than the 15-dof 5-point DLT (whose consensus under 1 px noise stalls at
//! about half the inliers), so it is used to find the consensus; its residual is the same
//! symmetric transfer error in pixels, with a looser threshold that absorbs the frame's
//! residual distortion (a few pixels). The full `H` is then fitted on the consensus.

use nalgebra::{Isometry3, Matrix3, Matrix4, Point3, Translation3, UnitQuaternion, Vector3};

use crate::camera::{ProjectiveCamera, dehomogenise3};
use crate::homography3d::{Homography3, Quadruplet, TransferModel, symmetric_transfer_error};
use crate::ransac::Estimator;
use crate::so3::nearest_rotation;
use crate::{GeometryError, Result};

/// A similarity `y = scale * rotation * x + translation`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Similarity {
    /// Scale factor (1 for a rigid fit).
    pub scale: f64,
    /// Rotation and translation.
    pub isometry: Isometry3<f64>,
}

impl Similarity {
    /// Apply to a point.
    pub fn transform(&self, x: &Point3<f64>) -> Point3<f64> {
        Point3::from(self.isometry.rotation * (x.coords * self.scale) + self.isometry.translation.vector)
    }

    /// The 4x4 matrix.
    pub fn to_matrix(&self) -> Matrix4<f64> {
        let mut m = self.isometry.to_homogeneous();
        for r in 0..3 {
            for c in 0..3 {
                m[(r, c)] *= self.scale;
            }
        }
        m
    }
}

/// Least-squares similarity (`with_scale`) or rigid motion mapping `x` onto `y`.
pub fn similarity_fit(x: &[Point3<f64>], y: &[Point3<f64>], with_scale: bool) -> Result<Similarity> {
    if x.len() != y.len() {
        return Err(GeometryError::InvalidOption("point sets differ in size".into()));
    }
    if x.len() < 3 {
        return Err(GeometryError::NotEnoughData {
            what: "point pairs for registration",
            needed: 3,
            got: x.len(),
        });
    }
    let n = x.len() as f64;
    let cx = x.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / n;
    let cy = y.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / n;
    let mut cov = Matrix3::zeros();
    let mut var_x = 0.0;
    for (a, b) in x.iter().zip(y) {
        let (da, db) = (a.coords - cx, b.coords - cy);
        cov += db * da.transpose();
        var_x += da.norm_squared();
    }
    cov /= n;
    var_x /= n;
    let svd =
        cov.try_svd(true, true, 1e-15, 200).ok_or_else(|| GeometryError::Numerical("SVD failed".into()))?;
    let mut s = svd.singular_values;
    s.as_mut_slice().sort_by(|a, b| b.total_cmp(a));
    if s[1].is_nan() || s[1] <= 1e-12 * s[0].max(1e-300) {
        return Err(GeometryError::Degenerate("points are collinear or coincident".into()));
    }
    let r = nearest_rotation(&cov).ok_or_else(|| GeometryError::Numerical("SVD failed".into()))?;
    let scale = if with_scale {
        // trace(D S) / var_x with the sign correction folded into nearest_rotation.
        let rc = r.matrix().transpose() * cov;
        rc.trace() / var_x
    } else {
        1.0
    };
    let t = cy - r * cx * scale;
    Ok(Similarity {
        scale,
        isometry: Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_rotation_matrix(&r)),
    })
}

/// RANSAC estimator of 3D homographies by 3-point rigid fits in a quasi-Euclidean frame
/// (module docs). Residual: symmetric transfer error, pixels.
#[derive(Debug, Clone, Copy)]
pub struct RigidFrameEstimator {
    /// Left camera of the frame (pixels).
    pub p_left: ProjectiveCamera,
    /// Right camera of the frame (pixels).
    pub p_right: ProjectiveCamera,
}

impl RigidFrameEstimator {
    fn fit(&self, data: &[Quadruplet], idx: &[usize]) -> Option<TransferModel> {
        let mut xs = Vec::with_capacity(idx.len());
        let mut ys = Vec::with_capacity(idx.len());
        for &i in idx {
            let q = data.get(i)?;
            xs.push(dehomogenise3(&q.x)?);
            ys.push(dehomogenise3(&q.y)?);
        }
        let sim = similarity_fit(&xs, &ys, false).ok()?;
        TransferModel::new(Homography3(sim.to_matrix())).ok()
    }
}

impl Estimator for RigidFrameEstimator {
    type Datum = Quadruplet;
    type Model = TransferModel;

    fn sample_size(&self) -> usize {
        3
    }

    fn fit_minimal(&self, data: &[Quadruplet], sample: &[usize]) -> Vec<TransferModel> {
        self.fit(data, sample).into_iter().collect()
    }

    fn fit_inliers(&self, data: &[Quadruplet], inliers: &[usize]) -> Option<TransferModel> {
        self.fit(data, inliers)
    }

    fn residual(&self, model: &TransferModel, datum: &Quadruplet) -> f64 {
        symmetric_transfer_error(model, &self.p_left, &self.p_right, datum)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Noise-free similarity recovered to 1e-10 (3x3 SVD of a well-spread cloud).
        #[test]
        fn recovers_similarity(wx in -1.0..1.0f64, wy in -1.0..1.0f64, wz in -1.0..1.0f64, s in 0.2..5.0f64, tx in -3.0..3.0f64) {
            let truth = Similarity { scale: s, isometry: Isometry3::from_parts(Translation3::new(tx, 1.0, -2.0), UnitQuaternion::from_scaled_axis(Vector3::new(wx, wy, wz))) };
            let x: Vec<Point3<f64>> = (0..12).map(|i| {
                let f = i as f64;
                Point3::new((f * 1.3).sin() * 2.0, (f * 0.7).cos(), f * 0.25 - 1.0)
            }).collect();
            let y: Vec<Point3<f64>> = x.iter().map(|p| truth.transform(p)).collect();
            let est = similarity_fit(&x, &y, true).unwrap();
            prop_assert!((est.to_matrix() - truth.to_matrix()).norm() < 1e-10 * s.max(1.0));
            let rigid_truth = Similarity { scale: 1.0, ..truth };
            let y: Vec<Point3<f64>> = x.iter().map(|p| rigid_truth.transform(p)).collect();
            let est = similarity_fit(&x, &y, false).unwrap();
            prop_assert!((est.to_matrix() - rigid_truth.to_matrix()).norm() < 1e-10);
        }
    }

    #[test]
    fn degenerate_sets_are_errors() {
        let x = vec![Point3::new(0.0, 0.0, 0.0), Point3::new(1.0, 0.0, 0.0), Point3::new(2.0, 0.0, 0.0)];
        assert!(similarity_fit(&x, &x, false).is_err());
        assert!(similarity_fit(&x[..2], &x[..2], false).is_err());
        assert!(similarity_fit(&x, &x[..2], false).is_err());
    }
}
