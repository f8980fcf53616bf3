//! The pinhole (no distortion): `m = (X/Z, Y/Z)`, no parameters. The radial-tangential
//! lens with every coefficient zero projects through it, bit for bit the arithmetic of
//! `Intrinsics::project` (the cost) and of the bundle adjustment's pinhole Jacobian.
//!
//! Pitfalls: a ray at or behind `Z = 0` has no projection (a NaN `Z` passes the cost's
//! test `Z <= 0`, as in `Intrinsics::project`, and gives a NaN point).

use nalgebra::{Matrix2x3, Vector2, Vector3};

use super::{KalibrForm, LensKind, LensModel, Linearised, MAX_PARAMS, ModelNames, ParamJacobian, Params};
use crate::Result;
use crate::camera::Intrinsics;

/// The pinhole model (module docs).
#[derive(Debug, Clone, Copy, Default)]
pub struct Pinhole;

static NAMES: ModelNames = ModelNames {
    id: "pinhole",
    short: "pinhole",
    opencv: None,
    ros: None,
    kalibr: Some(KalibrForm {
        camera_model: "pinhole",
        intrinsics: &[],
        distortion_model: "none",
        distortion_coeffs: &[],
    }),
    aliases: &["pinhole", "none"],
};

impl LensModel for Pinhole {
    fn kind(&self) -> LensKind {
        LensKind::Pinhole
    }
    fn names(&self) -> &'static ModelNames {
        &NAMES
    }
    fn param_names(&self) -> &'static [&'static str] {
        &[]
    }
    fn max_half_fov_deg(&self) -> f64 {
        90.0
    }
    fn pinhole_params(&self) -> Option<Params> {
        Some([0.0; MAX_PARAMS])
    }

    fn project(&self, _p: &Params, ray: &Vector3<f64>) -> Option<Vector2<f64>> {
        if ray.z <= 0.0 {
            return None;
        }
        Some(Vector2::new(ray.x / ray.z, ray.y / ray.z))
    }

    fn linearise(&self, k: &Intrinsics, _p: &Params, ray: &Vector3<f64>) -> Option<Linearised> {
        if !super::gt(ray.z, 0.0) {
            return None;
        }
        let iz = 1.0 / ray.z;
        let a = ray.x * iz;
        let b = ray.y * iz;
        let d_ray = Matrix2x3::new(
            k.fx * iz,
            k.skew * iz,
            -(k.fx * a + k.skew * b) * iz,
            0.0,
            k.fy * iz,
            -k.fy * b * iz,
        );
        Some(Linearised { m: Vector2::new(a, b), d_ray })
    }

    fn param_jacobian(
        &self,
        _k: &Intrinsics,
        _p: &Params,
        _ray: &Vector3<f64>,
        _estimated: &[bool; MAX_PARAMS],
    ) -> ParamJacobian {
        ParamJacobian::zeros()
    }

    fn unproject(&self, _p: &Params, m: &Vector2<f64>) -> Result<Vector3<f64>> {
        Ok(Vector3::new(m.x, m.y, 1.0).normalize())
    }
}
