//! The double-sphere lens (Usenko, Demmel & Cremers 2018, "The Double Sphere Camera
//! Model", 3DV; Basalt's `DoubleSphereCamera`, Kalibr's `ds`): a ray `(X, Y, Z)` is
//! projected onto a unit sphere, the sphere shifted by `xi` along the axis, onto a second
//! unit sphere, and then by a pinhole shifted by `alpha / (1 - alpha)`:
//!
//! ```text
//! d1 = |(X, Y, Z)|,   s = xi d1 + Z,   d2 = |(X, Y, s)|
//! D  = alpha d2 + (1 - alpha) s
//! m  = (X, Y) / D                    (pixel = K m: u = fx m_x + cx, v = fy m_y + cy)
//! ```
//!
//! valid where `Z > -w2 d1`, with `w1 = alpha / (1 - alpha)` if `alpha <= 1/2` else
//! `(1 - alpha) / alpha`, and `w2 = (w1 + xi) / sqrt(2 w1 xi + xi^2 + 1)` (the paper's
//! eq. 43-45): rays beyond 90 deg from the axis project when `w2 > 0`. The unprojection is
//! closed-form (the paper's eq. 46-51): with `r^2 = m_x^2 + m_y^2`,
//!
//! ```text
//! m_z = (1 - alpha^2 r^2) / (alpha sqrt(1 - (2 alpha - 1) r^2) + 1 - alpha)
//! bearing ~ (m_z xi + sqrt(m_z^2 + (1 - xi^2) r^2)) / (m_z^2 + r^2) (m_x, m_y, m_z) - (0, 0, xi)
//! ```
//!
//! defined where `alpha <= 1/2` or `r^2 <= 1 / (2 alpha - 1)`, and where the square root's
//! argument is not negative.
//!
//! Parameters `xi alpha` (dimensionless; Kalibr writes `intrinsics: [xi, alpha, fu, fv,
//! pu, pv]`). Jacobians: analytic, `d D / d ray = alpha d d2 / d ray + (1 - alpha) d s /
//! d ray`, `d s / d ray = xi ray / d1 + e_z`, `d d2 / d ray = ((X, Y, 0) + s d s / d ray)
//! / d2`; `d D / d xi = d1 (alpha s / d2 + 1 - alpha)`, `d D / d alpha = d2 - s`.
//!
//! Pitfalls: `alpha` in `[0, 1]` and `xi` in `(-1, 1]` are the paper's range (checked by
//! [`LensModel::check_params`]); with `alpha = 0` and `xi = 0` it is the pinhole, with
//! `alpha = 0` the unified model. Near the axis `m = (X, Y) / ((1 + xi) Z)`: the pixel scale at the
//! image centre is `fx / (1 + xi)`, not `fx`, so a focal length is compared only with
//! another of the same model.

use nalgebra::{Matrix2x3, RowVector3, Vector2, Vector3};

use super::{
    DistortionTerms, KalibrForm, LensKind, LensModel, Linearised, MAX_PARAMS, ModelNames, ParamJacobian,
    Params, k2,
};
use crate::camera::Intrinsics;
use crate::{GeometryError, Result};

/// The double-sphere model (module docs).
#[derive(Debug, Clone, Copy, Default)]
pub struct DoubleSphere;

static NAMES: ModelNames = ModelNames {
    id: "double-sphere",
    short: "ds",
    opencv: None,
    ros: None,
    kalibr: Some(KalibrForm {
        camera_model: "ds",
        intrinsics: &["xi", "alpha"],
        distortion_model: "none",
        distortion_coeffs: &[],
    }),
    aliases: &["double-sphere", "ds", "doublesphere", "ds-none"],
};

/// The quantities of one projection (module docs' names).
struct Terms {
    d1: f64,
    s: f64,
    d2: f64,
    den: f64,
}

/// `w2` of the validity test `Z > -w2 d1`.
fn w2(xi: f64, alpha: f64) -> f64 {
    let w1 = if alpha <= 0.5 { alpha / (1.0 - alpha) } else { (1.0 - alpha) / alpha };
    (w1 + xi) / (2.0 * w1 * xi + xi * xi + 1.0).sqrt()
}

/// The projection's terms, `None` outside the validity region or at a non-positive
/// denominator.
fn terms(p: &Params, ray: &Vector3<f64>) -> Option<Terms> {
    let [xi, alpha, ..] = *p;
    let d1 = ray.norm();
    if !super::gt(d1, 0.0) || !super::gt(ray.z, -w2(xi, alpha) * d1) {
        return None;
    }
    let s = xi * d1 + ray.z;
    let d2 = (ray.x * ray.x + ray.y * ray.y + s * s).sqrt();
    let den = alpha * d2 + (1.0 - alpha) * s;
    (den > 0.0 && den.is_finite()).then_some(Terms { d1, s, d2, den })
}

impl LensModel for DoubleSphere {
    fn kind(&self) -> LensKind {
        LensKind::DoubleSphere
    }
    fn names(&self) -> &'static ModelNames {
        &NAMES
    }
    fn param_names(&self) -> &'static [&'static str] {
        &["xi", "alpha"]
    }
    /// Both parameters at every level (`xi alpha` are one shape, not nested terms).
    fn estimated(&self, _terms: DistortionTerms) -> usize {
        2
    }
    fn max_half_fov_deg(&self) -> f64 {
        // Up to 90 deg + asin(w2) (module docs): beyond 90 deg for any w2 > 0.
        180.0
    }

    fn check_params(&self, p: &Params) -> Result<()> {
        let [xi, alpha, ..] = *p;
        if (0.0..=1.0).contains(&alpha) && xi > -1.0 && xi <= 1.0 {
            Ok(())
        } else {
            Err(GeometryError::InvalidOption(format!(
                "a double-sphere lens needs alpha in [0, 1] and xi in (-1, 1], got xi {xi}, alpha {alpha}"
            )))
        }
    }

    fn project(&self, p: &Params, ray: &Vector3<f64>) -> Option<Vector2<f64>> {
        let t = terms(p, ray)?;
        Some(Vector2::new(ray.x / t.den, ray.y / t.den))
    }

    fn linearise(&self, k: &Intrinsics, p: &Params, ray: &Vector3<f64>) -> Option<Linearised> {
        let [xi, alpha, ..] = *p;
        let Terms { d1, s, d2, den } = terms(p, ray)?;
        let ds: RowVector3<f64> = (ray * (xi / d1) + Vector3::z()).transpose();
        let dd2: RowVector3<f64> = (RowVector3::new(ray.x, ray.y, 0.0) + ds * s) / d2;
        let dden = dd2 * alpha + ds * (1.0 - alpha);
        let m = Vector2::new(ray.x / den, ray.y / den);
        let dm = Matrix2x3::new(1.0 / den, 0.0, 0.0, 0.0, 1.0 / den, 0.0) - m * dden / den;
        Some(Linearised { m, d_ray: k2(k) * dm })
    }

    fn param_jacobian(
        &self,
        k: &Intrinsics,
        p: &Params,
        ray: &Vector3<f64>,
        _estimated: &[bool; MAX_PARAMS],
    ) -> ParamJacobian {
        let [_, alpha, ..] = *p;
        let mut out = ParamJacobian::zeros();
        let Some(Terms { d1, s, d2, den }) = terms(p, ray) else { return out };
        let m = Vector2::new(ray.x / den, ray.y / den);
        let dxi = d1 * (alpha * s / d2 + 1.0 - alpha);
        let dalpha = d2 - s;
        let kk = k2(k);
        out.set_column(0, &(kk * (m * (-dxi / den))));
        out.set_column(1, &(kk * (m * (-dalpha / den))));
        out
    }

    fn unproject(&self, p: &Params, m: &Vector2<f64>) -> Result<Vector3<f64>> {
        let [xi, alpha, ..] = *p;
        let outside = || {
            GeometryError::Degenerate(format!(
                "({:.3}, {:.3}) is outside the image of the double-sphere lens (xi {xi}, alpha {alpha})",
                m.x, m.y
            ))
        };
        if !(m.x.is_finite() && m.y.is_finite()) {
            return Err(outside());
        }
        let r2 = m.norm_squared();
        let root1 = 1.0 - (2.0 * alpha - 1.0) * r2;
        if root1 < 0.0 {
            return Err(outside());
        }
        let mz = (1.0 - alpha * alpha * r2) / (alpha * root1.sqrt() + 1.0 - alpha);
        let root2 = mz * mz + (1.0 - xi * xi) * r2;
        if root2 < 0.0 {
            return Err(outside());
        }
        let f = (mz * xi + root2.sqrt()) / (mz * mz + r2);
        let b = Vector3::new(f * m.x, f * m.y, f * mz - xi);
        let n = b.norm();
        if !(n > 0.0 && n.is_finite()) {
            return Err(outside());
        }
        Ok(b / n)
    }

    /// The argument is the ray angle, up to 180 deg (NaN outside the model's region).
    fn profile_end(&self) -> f64 {
        std::f64::consts::PI
    }

    fn radial_profile(&self, p: &Params, a: f64) -> f64 {
        self.project(p, &Vector3::new(a.sin(), 0.0, a.cos())).map_or(f64::NAN, |m| m.x)
    }

    /// `alpha` with `xi = 0` (`m = x / (alpha |ray| + (1 - alpha) z)`): `alpha = c (1 / (1
    /// + delta) - 1) / (1 - c)`, `c` the cosine of the corner's ray angle; barrel only
    /// (`None` outside `alpha` in `[0, 1]`).
    fn grid_lens(&self, delta: f64, corner: f64) -> Option<Params> {
        let c = corner.atan().cos();
        let alpha = c * (1.0 / (1.0 + delta) - 1.0) / (1.0 - c);
        (0.0..=1.0).contains(&alpha).then_some([0.0, alpha, 0.0, 0.0, 0.0, 0.0])
    }

    /// `xi = 0`, `alpha = 1/2`: `m = sin theta / ((1 + cos theta) / 2) = 2 tan(theta / 2)`.
    fn stereographic(&self) -> Option<Params> {
        Some([0.0, 0.5, 0.0, 0.0, 0.0, 0.0])
    }

    /// The f-xi valley: near the axis the pixel scale is `f / (1 + xi)`, so `f` scales by
    /// `(1 + value) / (1 + xi)`, and `alpha` is chosen so that the ray at `theta` lands on
    /// the same pixel radius (`m = sin theta / (alpha d2 + (1 - alpha) s)`, `s = value +
    /// cos theta`, solved for `alpha`, clamped to `[0, 1]`; kept where not finite).
    fn along_focal_valley(&self, p: &Params, value: f64, theta: f64) -> Option<(f64, Params)> {
        let scale = (1.0 + value) / (1.0 + p[0]);
        let ray = Vector3::new(theta.sin(), 0.0, theta.cos());
        let mut out = *p;
        out[0] = value;
        if let Some(m) = self.project(p, &ray) {
            // The new lens's denominator D' for the same pixel radius f m = f' sin / D'.
            let den = scale * theta.sin() / m.x;
            let s = value + theta.cos();
            let d2 = (theta.sin().powi(2) + s * s).sqrt();
            let alpha = (den - s) / (d2 - s);
            if alpha.is_finite() {
                out[1] = alpha.clamp(0.0, 1.0);
            }
        }
        Some((scale, out))
    }

    /// `xi = 0` and `alpha` on a grid of 0.01 in `[0, 0.95]` whose profile `sin(theta) /
    /// (alpha + (1 - alpha) cos(theta))` is closest to `profile` in least squares over 50
    /// radii up to `field`; `alpha = 0.5` when the field is empty.
    fn fit_radial_profile(&self, profile: &dyn Fn(f64) -> f64, field: f64, _estimated: usize) -> Params {
        let cost = |alpha: f64| -> f64 {
            (1..=50)
                .map(|i| {
                    let r = field * f64::from(i) / 50.0;
                    let theta = r.atan();
                    let m = theta.sin() / (alpha + (1.0 - alpha) * theta.cos());
                    (m - profile(r)).powi(2)
                })
                .sum()
        };
        if !(field.is_finite() && field > 0.0) {
            return [0.0, 0.5, 0.0, 0.0, 0.0, 0.0];
        }
        let alpha = (0..=95).map(|i| f64::from(i) * 0.01).min_by(|a, b| cost(*a).total_cmp(&cost(*b)));
        [0.0, alpha.unwrap_or(0.5), 0.0, 0.0, 0.0, 0.0]
    }
}
