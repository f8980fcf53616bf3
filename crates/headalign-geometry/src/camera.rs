//! Pinhole cameras.
//!
//! - [`Intrinsics`]: the calibration matrix `K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]`
//!   (5 degrees of freedom), pixels.
//! - [`ProjectiveCamera`]: a general 3x4 projection `P` (11 degrees of freedom, defined up
//!   to scale), used for the projective frame of a stereo rig.
//! - Rigid poses are `nalgebra::Isometry3<f64>` named by their frames, `b_from_a` maps a
//!   point in frame `a` to frame `b` (Hartley & Zisserman ch. 6).
//!
//! Pixel convention: (0, 0) is the centre of the top-left pixel. Projection of a point
//! behind the camera (z <= 0) is reported as `None` by the checked functions.

use nalgebra::{Isometry3, Matrix3, Matrix3x4, Point2, Point3, Vector3, Vector4};
use serde::{Deserialize, Serialize};

use crate::{GeometryError, Result};

/// Pinhole intrinsics in pixels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Skew, pixels (zero for rectangular pixels).
    pub skew: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
}

impl Intrinsics {
    /// Intrinsics with zero skew.
    pub fn new(fx: f64, fy: f64, cx: f64, cy: f64) -> Self {
        Self { fx, fy, skew: 0.0, cx, cy }
    }

    /// A rough guess for an uncalibrated camera: focal length equal to the image width,
    /// principal point at the image centre. Used to condition pixel coordinates.
    pub fn rough_guess(width: u32, height: u32) -> Self {
        let w = f64::from(width);
        let h = f64::from(height);
        Self::new(w, w, (w - 1.0) / 2.0, (h - 1.0) / 2.0)
    }

    /// The 3x3 calibration matrix.
    pub fn matrix(&self) -> Matrix3<f64> {
        Matrix3::new(self.fx, self.skew, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }

    /// Intrinsics from an upper-triangular calibration matrix (normalised so `K[2][2] = 1`).
    ///
    /// Errors if `K[2][2]` vanishes, the matrix is not upper triangular to 1e-9 relative,
    /// or a focal length is not positive.
    pub fn from_matrix(k: &Matrix3<f64>) -> Result<Self> {
        let s = k[(2, 2)];
        if !s.is_finite() || s.abs() < 1e-300 {
            return Err(GeometryError::InvalidEstimate("K[2][2] is zero".into()));
        }
        let k = k / s;
        let scale = k.abs().max();
        if k[(1, 0)].abs() > 1e-9 * scale || k[(2, 0)].abs() > 1e-9 * scale || k[(2, 1)].abs() > 1e-9 * scale
        {
            return Err(GeometryError::InvalidEstimate("K is not upper triangular".into()));
        }
        let out = Self { fx: k[(0, 0)], fy: k[(1, 1)], skew: k[(0, 1)], cx: k[(0, 2)], cy: k[(1, 2)] };
        if !out.is_finite() || out.fx <= 0.0 || out.fy <= 0.0 {
            return Err(GeometryError::InvalidEstimate(format!(
                "focal lengths must be positive and finite, got fx={}, fy={}",
                out.fx, out.fy
            )));
        }
        Ok(out)
    }

    /// True if every parameter is finite.
    pub fn is_finite(&self) -> bool {
        [self.fx, self.fy, self.skew, self.cx, self.cy].iter().all(|v| v.is_finite())
    }

    /// The inverse calibration matrix (closed form for upper-triangular `K`).
    pub fn inverse_matrix(&self) -> Matrix3<f64> {
        let (fx, fy, s, cx, cy) = (self.fx, self.fy, self.skew, self.cx, self.cy);
        Matrix3::new(
            1.0 / fx,
            -s / (fx * fy),
            (s * cy - cx * fy) / (fx * fy),
            0.0,
            1.0 / fy,
            -cy / fy,
            0.0,
            0.0,
            1.0,
        )
    }

    /// Pixel of a point in this camera's frame; `None` if it is not in front (z <= 0).
    pub fn project(&self, point_in_cam: &Point3<f64>) -> Option<Point2<f64>> {
        if point_in_cam.z <= 0.0 {
            return None;
        }
        Some(self.project_unchecked(point_in_cam))
    }

    /// Pixel of a point in this camera's frame, without the cheirality check.
    pub fn project_unchecked(&self, p: &Point3<f64>) -> Point2<f64> {
        let x = p.x / p.z;
        let y = p.y / p.z;
        Point2::new(self.fx * x + self.skew * y + self.cx, self.fy * y + self.cy)
    }

    /// Ray direction (z = 1) in the camera frame through a pixel.
    pub fn unproject(&self, pixel: &Point2<f64>) -> Vector3<f64> {
        let y = (pixel.y - self.cy) / self.fy;
        let x = (pixel.x - self.cx - self.skew * y) / self.fx;
        Vector3::new(x, y, 1.0)
    }

    /// Mean focal length `(fx + fy) / 2`.
    pub fn mean_focal(&self) -> f64 {
        0.5 * (self.fx + self.fy)
    }
}

/// A general projective camera `P` (3x4, up to scale).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProjectiveCamera(pub Matrix3x4<f64>);

impl ProjectiveCamera {
    /// The canonical camera `[I | 0]`.
    pub fn canonical() -> Self {
        Self(Matrix3x4::identity())
    }

    /// `K [R | t]` from intrinsics and the pose `cam_from_world`.
    pub fn from_pose(k: &Intrinsics, cam_from_world: &Isometry3<f64>) -> Self {
        let r = cam_from_world.rotation.to_rotation_matrix().into_inner();
        let t = cam_from_world.translation.vector;
        let mut rt = Matrix3x4::zeros();
        rt.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
        rt.set_column(3, &t);
        Self(k.matrix() * rt)
    }

    /// Homogeneous image point of a homogeneous 3D point.
    pub fn project_h(&self, x: &Vector4<f64>) -> Vector3<f64> {
        self.0 * x
    }

    /// Pixel of a homogeneous 3D point; `None` if the image point is at infinity.
    pub fn project(&self, x: &Vector4<f64>) -> Option<Point2<f64>> {
        let h = self.0 * x;
        if h.z.abs() < 1e-300 || !h.z.is_finite() {
            return None;
        }
        Some(Point2::new(h.x / h.z, h.y / h.z))
    }

    /// Camera centre: the right null vector of `P` (homogeneous 4-vector, unit norm).
    pub fn centre(&self) -> Result<Vector4<f64>> {
        // Cofactor formula: C_i = (-1)^i det(P without column i).
        let p = &self.0;
        let mut c = Vector4::zeros();
        for i in 0..4 {
            let cols: Vec<usize> = (0..4).filter(|&j| j != i).collect();
            let m = Matrix3::from_columns(&[p.column(cols[0]), p.column(cols[1]), p.column(cols[2])]);
            let sign = if i % 2 == 0 { 1.0 } else { -1.0 };
            c[i] = sign * m.determinant();
        }
        let n = c.norm();
        if !n.is_finite() || n <= 0.0 {
            return Err(GeometryError::Degenerate("camera matrix has rank < 3".into()));
        }
        Ok(c / n)
    }
}

/// Point from homogeneous coordinates; `None` at (or numerically near) infinity.
pub fn dehomogenise3(x: &Vector4<f64>) -> Option<Point3<f64>> {
    if x.w.abs() <= 1e-12 * x.xyz().norm() || !x.w.is_finite() || x.w == 0.0 {
        return None;
    }
    Some(Point3::from(x.xyz() / x.w))
}

/// Point from a homogeneous image point; `None` at infinity.
pub fn dehomogenise2(x: &Vector3<f64>) -> Option<Point2<f64>> {
    if x.z == 0.0 || x.z.abs() <= 1e-15 * x.xy().norm() {
        return None;
    }
    Some(Point2::new(x.x / x.z, x.y / x.z))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn inverse_matrix_is_inverse() {
        let k = Intrinsics { fx: 700.0, fy: 720.0, skew: 3.0, cx: 390.0, cy: 284.0 };
        let prod = k.matrix() * k.inverse_matrix();
        assert!((prod - Matrix3::identity()).norm() < 1e-14);
    }

    #[test]
    fn project_unproject_round_trip() {
        let k = Intrinsics { fx: 700.0, fy: 720.0, skew: 1.5, cx: 390.0, cy: 284.0 };
        let p = Point3::new(0.3, -0.2, 2.5);
        let px = k.project(&p).unwrap();
        let ray = k.unproject(&px);
        assert!((ray * p.z - p.coords).norm() < 1e-12);
        assert!(k.project(&Point3::new(0.0, 0.0, -1.0)).is_none());
    }

    #[test]
    fn from_matrix_round_trip_and_errors() {
        let k = Intrinsics { fx: 700.0, fy: 720.0, skew: 1.5, cx: 390.0, cy: 284.0 };
        let back = Intrinsics::from_matrix(&(k.matrix() * 3.0)).unwrap();
        assert!((back.matrix() - k.matrix()).norm() < 1e-10);
        let mut bad = k.matrix();
        bad[(1, 0)] = 5.0;
        assert!(Intrinsics::from_matrix(&bad).is_err());
        assert!(Intrinsics::from_matrix(&Matrix3::zeros()).is_err());
    }

    #[test]
    fn camera_centre_is_null_vector() {
        let k = Intrinsics::new(700.0, 720.0, 390.0, 284.0);
        let pose = Isometry3::from_parts(
            Translation3::new(0.1, -0.2, 0.3),
            UnitQuaternion::from_euler_angles(0.1, 0.2, -0.3),
        );
        let p = ProjectiveCamera::from_pose(&k, &pose);
        let c = p.centre().unwrap();
        assert!((p.0 * c).norm() < 1e-10 * p.0.norm());
        let c3 = dehomogenise3(&c).unwrap();
        let expected = pose.inverse() * Point3::origin();
        assert!((c3 - expected).norm() < 1e-12);
    }
}
