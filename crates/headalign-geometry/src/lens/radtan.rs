//! The radial-tangential lens (OpenCV and ROS `plumb_bob`, Kalibr `radtan`): a map of the
//! pinhole plane `x = (X/Z, Y/Z)`,
//!
//! ```text
//! r^2 = x^2 + y^2
//! m_x = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
//! m_y = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y
//! ```
//!
//! Parameters `k1 k2 p1 p2 k3` (OpenCV's order of `D`), dimensionless. All zero is the
//! pinhole: then the projection is [`super::Pinhole`]'s, bit for bit. Unprojection inverts
//! the map by Newton's method with the analytic 2x2 Jacobian (at most 30 steps, stops
//! below 1e-14 in normalised units); where the map folds over (beyond the radius at which
//! a strong barrel model turns back) it is an error, never a wrong point.
//!
//! Pitfalls: defined for rays in front of the camera only (`Z > 0`); the field it can
//! represent ends where the polynomial folds.

use nalgebra::{Matrix2, Matrix2x3, Vector2, Vector3};

use super::{
    KalibrForm, LensKind, LensModel, Linearised, MAX_PARAMS, ModelNames, ParamJacobian, Params, Pinhole, k2,
};
use crate::camera::Intrinsics;
use crate::{GeometryError, Result};

/// Newton iterations of the unprojection.
const MAX_STEPS: usize = 30;

/// The radial-tangential model (module docs).
#[derive(Debug, Clone, Copy, Default)]
pub struct RadialTangential;

static NAMES: ModelNames = ModelNames {
    id: "radial-tangential",
    short: "radtan",
    opencv: Some("plumb_bob"),
    ros: Some("plumb_bob"),
    kalibr: Some(KalibrForm {
        camera_model: "pinhole",
        intrinsics: &[],
        distortion_model: "radtan",
        distortion_coeffs: &["k1", "k2", "p1", "p2"],
    }),
    aliases: &["radtan", "radial-tangential", "plumb-bob", "pinhole-radtan"],
};

/// True if every coefficient is zero (the pinhole).
fn is_pinhole(p: &Params) -> bool {
    p.iter().all(|&v| v == 0.0)
}

/// The distorted point of a pinhole-plane point and its 2x2 Jacobian.
pub(crate) fn distort(p: &Params, x: &Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>) {
    let [k1, k2, p1, p2, k3, _] = *p;
    let (u, v) = (x.x, x.y);
    let r2 = u * u + v * v;
    let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
    // d radial / d r2
    let dradial = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3);
    let xd = u * radial + 2.0 * p1 * u * v + p2 * (r2 + 2.0 * u * u);
    let yd = v * radial + p1 * (r2 + 2.0 * v * v) + 2.0 * p2 * u * v;
    let j = Matrix2::new(
        radial + 2.0 * u * u * dradial + 2.0 * p1 * v + 6.0 * p2 * u,
        2.0 * u * v * dradial + 2.0 * p1 * u + 2.0 * p2 * v,
        2.0 * u * v * dradial + 2.0 * p1 * u + 2.0 * p2 * v,
        radial + 2.0 * v * v * dradial + 6.0 * p1 * v + 2.0 * p2 * u,
    );
    (Vector2::new(xd, yd), j)
}

/// `d m / d parameter` at the pinhole-plane point `x` (columns `k1 k2 p1 p2 k3`).
pub(crate) fn coefficient_jacobian(x: &Vector2<f64>) -> ParamJacobian {
    let (u, v) = (x.x, x.y);
    let r2 = u * u + v * v;
    let mut jc = ParamJacobian::zeros();
    jc.set_column(0, &(x * r2));
    jc.set_column(1, &(x * (r2 * r2)));
    jc.set_column(2, &Vector2::new(2.0 * u * v, r2 + 2.0 * v * v));
    jc.set_column(3, &Vector2::new(r2 + 2.0 * u * u, 2.0 * u * v));
    jc.set_column(4, &(x * (r2 * r2 * r2)));
    jc
}

/// Newton on `distort(x) = xd` from `x = xd` (module docs).
pub(crate) fn undistort(p: &Params, xd: &Vector2<f64>) -> Result<Vector2<f64>> {
    let mut x = *xd;
    for _ in 0..MAX_STEPS {
        let (f, j) = distort(p, &x);
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
    let r = distort(p, &x).0 - xd;
    if r.norm() < 1e-9 {
        Ok(x)
    } else {
        Err(GeometryError::Numerical(format!("undistortion did not converge at ({:.3}, {:.3})", xd.x, xd.y)))
    }
}

impl LensModel for RadialTangential {
    fn kind(&self) -> LensKind {
        LensKind::RadialTangential
    }
    fn names(&self) -> &'static ModelNames {
        &NAMES
    }
    fn param_names(&self) -> &'static [&'static str] {
        &["k1", "k2", "p1", "p2", "k3"]
    }
    fn max_half_fov_deg(&self) -> f64 {
        90.0
    }
    fn pinhole_params(&self) -> Option<Params> {
        Some([0.0; MAX_PARAMS])
    }

    fn project(&self, p: &Params, ray: &Vector3<f64>) -> Option<Vector2<f64>> {
        if is_pinhole(p) {
            return Pinhole.project(p, ray);
        }
        if !super::gt(ray.z, 0.0) {
            return None;
        }
        Some(distort(p, &Vector2::new(ray.x / ray.z, ray.y / ray.z)).0)
    }

    fn linearise(&self, k: &Intrinsics, p: &Params, ray: &Vector3<f64>) -> Option<Linearised> {
        if is_pinhole(p) {
            return Pinhole.linearise(k, p, ray);
        }
        if !super::gt(ray.z, 0.0) {
            return None;
        }
        // pixel = K2 distort(pi(ray)): d pixel / d ray = K2 J_dist d pi / d ray.
        let iz = 1.0 / ray.z;
        let (m, jd) = distort(p, &Vector2::new(ray.x * iz, ray.y * iz));
        let dpi = Matrix2x3::new(iz, 0.0, -ray.x * iz * iz, 0.0, iz, -ray.y * iz * iz);
        Some(Linearised { m, d_ray: k2(k) * jd * dpi })
    }

    fn param_jacobian(
        &self,
        k: &Intrinsics,
        _p: &Params,
        ray: &Vector3<f64>,
        estimated: &[bool; MAX_PARAMS],
    ) -> ParamJacobian {
        let iz = 1.0 / ray.z;
        let (u, v) = (ray.x * iz, ray.y * iz);
        if estimated[2..].iter().all(|e| !e) {
            // d m / d k1 = x r^2, d / d k2 = x r^4 (x the pinhole-plane point), times K.
            let r2 = u * u + v * v;
            let mut out = ParamJacobian::zeros();
            for (c, m) in [r2, r2 * r2].into_iter().enumerate() {
                out.set_column(c, &Vector2::new((k.fx * u + k.skew * v) * m, k.fy * v * m));
            }
            return out;
        }
        let jc = coefficient_jacobian(&Vector2::new(u, v));
        let kk = k2(k);
        let mut out = ParamJacobian::zeros();
        for c in 0..5 {
            out.set_column(c, &(kk * jc.column(c)));
        }
        out
    }

    fn unproject(&self, p: &Params, m: &Vector2<f64>) -> Result<Vector3<f64>> {
        let x = if is_pinhole(p) { *m } else { undistort(p, m)? };
        Ok(Vector3::new(x.x, x.y, 1.0).normalize())
    }

    /// OpenCV's `D` of `plumb_bob`: 4 or 5 entries `k1 k2 p1 p2 [k3]`; more entries are
    /// OpenCV's rational or thin-prism models, which headalign does not have: an error
    /// unless they are all zero.
    fn read_coefficients(&self, d: &[f64]) -> Result<Params> {
        if d.len() < 4 {
            return Err(GeometryError::InvalidOption(format!(
                "a distortion vector needs at least 4 coefficients (k1 k2 p1 p2 [k3]), got {}",
                d.len()
            )));
        }
        if d.iter().skip(5).any(|&v| v != 0.0) {
            return Err(GeometryError::InvalidOption(format!(
                "{} distortion coefficients with non-zero entries beyond k3: OpenCV's rational_polynomial (k1 k2 p1 p2 k3 k4 k5 k6) or thin-prism model, which headalign does not support (use plumb_bob or fisheye)",
                d.len()
            )));
        }
        Ok([d[0], d[1], d[2], d[3], d.get(4).copied().unwrap_or(0.0), 0.0])
    }

    fn distort(&self, p: &Params, x: &Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>, ParamJacobian) {
        let (xd, j) = distort(p, x);
        (xd, j, coefficient_jacobian(x))
    }

    fn undistort(&self, p: &Params, m: &Vector2<f64>) -> Result<Vector2<f64>> {
        undistort(p, m)
    }

    /// The radial polynomial alone (`p1 = p2 = 0`) at pinhole-plane radius `a`.
    fn radial_profile(&self, p: &Params, a: f64) -> f64 {
        let radial = [p[0], p[1], 0.0, 0.0, p[4], p[5]];
        distort(&radial, &Vector2::new(a, 0.0)).0.x
    }

    /// `k1 = delta / corner^2`.
    fn grid_lens(&self, delta: f64, corner: f64) -> Option<Params> {
        Some([delta / (corner * corner), 0.0, 0.0, 0.0, 0.0, 0.0])
    }
}
