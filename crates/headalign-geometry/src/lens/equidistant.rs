//! The equidistant fisheye lens (OpenCV `fisheye`, ROS `equidistant`, Kalibr
//! `equidistant`; Kannala-Brandt with four terms), a map of the pinhole plane
//! `x = (X/Z, Y/Z)`:
//!
//! ```text
//! r = |x|,  theta = atan(r)
//! theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
//! m = (theta_d / r) x
//! ```
//!
//! Parameters `k1 k2 k3 k4` (OpenCV fisheye's `D`), multiplying powers of an angle in
//! radians. Unprojection: Newton on `theta_d(theta) = |m|` alone (at most 30 steps), then
//! the bearing at angle `theta`.
//!
//! Pitfalls: through the pinhole plane the model covers rays in front of the camera only
//! (`theta < 90 deg`), although the formula itself extends beyond; all zero is the ideal
//! equidistant lens `theta_d = theta`, not a pinhole. Its Jacobian at the centre is the
//! limit `r -> 0` (taken below `r = 1e-8`). Its `k1` includes the `-1/3 theta^2` of `atan`:
//! it is not the radial-tangential `k1` of the same lens.

use nalgebra::{Matrix2, Matrix2x3, Vector2, Vector3};

use super::{KalibrForm, LensKind, LensModel, Linearised, MAX_PARAMS, ModelNames, ParamJacobian, Params, k2};
use crate::camera::Intrinsics;
use crate::{GeometryError, Result};

/// Newton iterations of the unprojection.
const MAX_STEPS: usize = 30;

/// Below this pinhole-plane radius the map is the identity to first order and its
/// Jacobian the limit at the centre.
const CENTRE: f64 = 1e-8;

/// The equidistant model (module docs).
#[derive(Debug, Clone, Copy, Default)]
pub struct Equidistant;

static NAMES: ModelNames = ModelNames {
    id: "equidistant",
    short: "equidistant",
    opencv: Some("fisheye"),
    ros: Some("equidistant"),
    kalibr: Some(KalibrForm {
        camera_model: "pinhole",
        intrinsics: &[],
        distortion_model: "equidistant",
        distortion_coeffs: &["k1", "k2", "k3", "k4"],
    }),
    aliases: &["equidistant", "equi", "fisheye", "pinhole-equi", "kannala-brandt"],
};

/// `theta_d(theta)` and its derivative.
fn theta_d(p: &Params, theta: f64) -> (f64, f64) {
    let [k1, k2, k3, k4, ..] = *p;
    let t2 = theta * theta;
    let poly = 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)));
    let dpoly = 3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4));
    (theta * poly, 1.0 + t2 * dpoly)
}

/// The map of a pinhole-plane point, its 2x2 Jacobian, and `d m / d (k1..k4)`.
pub(crate) fn distort(p: &Params, x: &Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>, ParamJacobian) {
    let r = x.norm();
    let mut jc = ParamJacobian::zeros();
    if r < CENTRE {
        // theta_d / r -> 1 and its derivative -> 0 at the centre.
        for (c, power) in [3, 5, 7, 9].into_iter().enumerate() {
            jc.set_column(c, &(x * r.powi(power - 1)));
        }
        return (*x, Matrix2::identity(), jc);
    }
    let theta = r.atan();
    let (td, dtd) = theta_d(p, theta);
    let s = td / r;
    // d s / d r = (dtd dtheta/dr r - td) / r^2, dtheta/dr = 1 / (1 + r^2).
    let ds = (dtd / (1.0 + r * r) * r - td) / (r * r);
    let n = x / r;
    let j = Matrix2::identity() * s + x * n.transpose() * ds;
    let t2 = theta * theta;
    let mut tp = theta * t2;
    for c in 0..4 {
        jc.set_column(c, &(n * tp));
        tp *= t2;
    }
    (x * s, j, jc)
}

/// Newton on `theta_d(theta) = |m|` from `theta = |m|`, then `r = tan(theta)`: the
/// pinhole-plane point.
pub(crate) fn undistort(p: &Params, xd: &Vector2<f64>) -> Result<Vector2<f64>> {
    let rd = xd.norm();
    if rd < CENTRE {
        return Ok(*xd);
    }
    let fold = || {
        GeometryError::Degenerate(format!(
            "distortion folds over near ({:.3}, {:.3}): not invertible there",
            xd.x, xd.y
        ))
    };
    let mut theta = rd.min(1.5);
    for _ in 0..MAX_STEPS {
        let (td, dtd) = theta_d(p, theta);
        if dtd <= 1e-9 {
            return Err(fold());
        }
        let step = (td - rd) / dtd;
        theta -= step;
        if !(0.0..std::f64::consts::FRAC_PI_2).contains(&theta) {
            return Err(fold());
        }
        if step.abs() < 1e-15 {
            break;
        }
    }
    if (theta_d(p, theta).0 - rd).abs() > 1e-9 {
        return Err(GeometryError::Numerical(format!(
            "undistortion did not converge at ({:.3}, {:.3})",
            xd.x, xd.y
        )));
    }
    Ok(xd * (theta.tan() / rd))
}

impl LensModel for Equidistant {
    fn kind(&self) -> LensKind {
        LensKind::Equidistant
    }
    fn names(&self) -> &'static ModelNames {
        &NAMES
    }
    fn param_names(&self) -> &'static [&'static str] {
        &["k1", "k2", "k3", "k4"]
    }
    fn max_half_fov_deg(&self) -> f64 {
        90.0
    }

    fn project(&self, p: &Params, ray: &Vector3<f64>) -> Option<Vector2<f64>> {
        if !super::gt(ray.z, 0.0) {
            return None;
        }
        Some(distort(p, &Vector2::new(ray.x / ray.z, ray.y / ray.z)).0)
    }

    fn linearise(&self, k: &Intrinsics, p: &Params, ray: &Vector3<f64>) -> Option<Linearised> {
        if !super::gt(ray.z, 0.0) {
            return None;
        }
        let iz = 1.0 / ray.z;
        let (m, jd, _) = distort(p, &Vector2::new(ray.x * iz, ray.y * iz));
        let dpi = Matrix2x3::new(iz, 0.0, -ray.x * iz * iz, 0.0, iz, -ray.y * iz * iz);
        Some(Linearised { m, d_ray: k2(k) * jd * dpi })
    }

    fn param_jacobian(
        &self,
        k: &Intrinsics,
        p: &Params,
        ray: &Vector3<f64>,
        _estimated: &[bool; MAX_PARAMS],
    ) -> ParamJacobian {
        let iz = 1.0 / ray.z;
        let (_, _, jc) = distort(p, &Vector2::new(ray.x * iz, ray.y * iz));
        let kk = k2(k);
        let mut out = ParamJacobian::zeros();
        for c in 0..4 {
            out.set_column(c, &(kk * jc.column(c)));
        }
        out
    }

    fn unproject(&self, p: &Params, m: &Vector2<f64>) -> Result<Vector3<f64>> {
        let x = undistort(p, m)?;
        Ok(Vector3::new(x.x, x.y, 1.0).normalize())
    }

    fn distort(&self, p: &Params, x: &Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>, ParamJacobian) {
        distort(p, x)
    }

    fn undistort(&self, p: &Params, m: &Vector2<f64>) -> Result<Vector2<f64>> {
        undistort(p, m)
    }

    /// The argument is the ray angle, up to 90 deg.
    fn profile_end(&self) -> f64 {
        std::f64::consts::FRAC_PI_2
    }

    fn radial_profile(&self, p: &Params, a: f64) -> f64 {
        distort(p, &Vector2::new(a.tan(), 0.0)).0.x
    }

    /// `k1 = delta / atan(corner)^2`.
    fn grid_lens(&self, delta: f64, corner: f64) -> Option<Params> {
        Some([delta / corner.atan().powi(2), 0.0, 0.0, 0.0, 0.0, 0.0])
    }

    /// Least squares over 50 radii up to `field` of `theta (1 + k1 theta^2 + k2 theta^4 +
    /// ...) - profile(r)`, `theta = atan r`, for the first `estimated` coefficients (the
    /// powers `theta^3, ^5, ^7, ^9`); the ideal equidistant lens (all zero) when the field
    /// is empty or the fit singular.
    fn fit_radial_profile(&self, profile: &dyn Fn(f64) -> f64, field: f64, estimated: usize) -> Params {
        let mut out = [0.0; MAX_PARAMS];
        let n = estimated.min(4);
        if !(field.is_finite() && field > 0.0) {
            return out;
        }
        let samples = 50;
        let mut a = nalgebra::DMatrix::<f64>::zeros(samples, n);
        let mut b = nalgebra::DVector::<f64>::zeros(samples);
        for i in 0..samples {
            let r = field * (i + 1) as f64 / samples as f64;
            let theta = r.atan();
            let rd = profile(r);
            for j in 0..n {
                a[(i, j)] = theta.powi(2 * j as i32 + 3);
            }
            b[i] = rd - theta;
        }
        if let Ok(x) = a.svd(true, true).solve(&b, 1e-12) {
            for (o, v) in out.iter_mut().zip(x.iter()) {
                if v.is_finite() {
                    *o = *v;
                }
            }
        }
        out
    }
}
