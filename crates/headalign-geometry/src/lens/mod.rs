//! The lens models as a table ([`MODELS`], in the manner of COLMAP's `sensor/models.h` and
//! mrcal's lens list): one file per model, each implementing [`LensModel`], and one
//! dispatch point, [`model`], from a [`LensKind`] to its row.
//!
//! What a model computes: the map from a ray in the camera frame (any length, not
//! necessarily in front of the camera) to the model's **image-plane point** `m`, the point
//! the camera's intrinsics `K` take to the pixel (`pixel = K m`: `u = fx m_x + skew m_y +
//! cx`, `v = fy m_y + cy`), with the Jacobians of the pixel with respect to the ray and
//! to the model's parameters; and the inverse, from `m` to the unit bearing. The models:
//!
//! | model | file | parameters | OpenCV | ROS | Kalibr | half field |
//! |---|---|---|---|---|---|---|
//! | pinhole | `pinhole.rs` | none | (`D` = 0) | `plumb_bob` (`D` = 0) | `none` | < 90 deg |
//! | radial-tangential | `radtan.rs` | `k1 k2 p1 p2 k3` | `plumb_bob` | `plumb_bob` | `radtan` | < 90 deg |
//! | equidistant | `equidistant.rs` | `k1 k2 k3 k4` | `fisheye` | `equidistant` | `equidistant` | < 90 deg (here) |
//! | double sphere | `double_sphere.rs` | `xi alpha` | none | none | `ds` | up to 180 deg and beyond |
//!
//! Adding a model is adding a file that implements [`LensModel`], a [`LensKind`] variant
//! and a row of [`MODELS`]; `distortion::Distortion` stores every model's
//! parameters in its slots ([`LensModel::slots`]) and dispatches through [`model`].
//!
//! Degrees of freedom: those of the model's parameters ([`LensModel::param_names`]), on
//! top of the 4-5 of `K`. Units: rays in any length unit (only the direction matters),
//! `m` dimensionless, pixels outside, parameters dimensionless (the equidistant ones
//! multiply powers of an angle in radians).
//!
//! Pitfalls: the pinhole, radial-tangential and equidistant models here divide by the
//! ray's `z` (they are maps of the pinhole plane), so a ray at or behind `z = 0` has no
//! projection; only the double sphere projects rays beyond 90 deg (its own validity
//! region, [`LensModel::project`]). Parameters belong to the `K` they were estimated with.

mod double_sphere;
pub(crate) mod equidistant;
mod pinhole;
pub(crate) mod radtan;

pub use double_sphere::DoubleSphere;
pub use equidistant::Equidistant;
pub use pinhole::Pinhole;
pub use radtan::RadialTangential;

use nalgebra::{Matrix2x3, SMatrix, Vector2, Vector3};

use crate::Result;
use crate::camera::Intrinsics;

/// The most parameters a model has (radial-tangential: 5; the parameter arrays of
/// [`LensModel`] have this length, unused entries zero).
pub const MAX_PARAMS: usize = 6;

/// A model's parameters in its own order ([`LensModel::param_names`]), zero-padded.
pub type Params = [f64; MAX_PARAMS];

/// The pixel Jacobian with respect to the parameters, one column per parameter (columns
/// beyond the model's parameters zero).
pub type ParamJacobian = SMatrix<f64, 2, MAX_PARAMS>;

/// The names a model goes by in the tools users have.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ModelNames {
    /// headalign's name (kebab-case, the serde name of [`LensKind`]).
    pub id: &'static str,
    /// Short name in reports and the CLI (`radtan`, `equidistant`, `ds`, `pinhole`).
    pub short: &'static str,
    /// OpenCV's model (`None`: OpenCV has none).
    pub opencv: Option<&'static str>,
    /// ROS `sensor_msgs/CameraInfo.distortion_model` (`None`: none).
    pub ros: Option<&'static str>,
    /// Kalibr camchain `distortion_model` (or `camera_model` for the double sphere).
    pub kalibr: Option<&'static str>,
    /// Every spelling [`LensKind::parse`] accepts (lower case, `-` for `_`).
    pub aliases: &'static [&'static str],
}

/// Linearisation of a projection at one ray: the image-plane point and the pixel
/// Jacobian with respect to the ray.
#[derive(Debug, Clone, Copy)]
pub struct Linearised {
    /// The image-plane point `m` (`pixel = K m`).
    pub m: Vector2<f64>,
    /// `d pixel / d ray` (2x3, `K` included).
    pub d_ray: Matrix2x3<f64>,
}

/// One lens model (a row of [`MODELS`]; module docs).
pub trait LensModel: Sync {
    /// The identifier of this row.
    fn kind(&self) -> LensKind;
    /// The model's names in users' tools.
    fn names(&self) -> &'static ModelNames;
    /// The parameters, in the model's order (OpenCV's `D` where OpenCV has the model).
    fn param_names(&self) -> &'static [&'static str];
    /// The storage slot of each parameter in `Distortion::slots` (the `distortion` module).
    fn slots(&self) -> &'static [usize];
    /// The largest half field of view the model can represent, degrees (metadata).
    fn max_half_fov_deg(&self) -> f64;
    /// The model's parameters that make it the identity on the pinhole plane (the
    /// pinhole); `None` when no choice does (equidistant, double sphere).
    fn pinhole_params(&self) -> Option<Params> {
        None
    }
    /// Validity of the parameters beyond finiteness (`Err` names the rule broken).
    fn check_params(&self, _p: &Params) -> Result<()> {
        Ok(())
    }
    /// The image-plane point `m` of a ray in the camera frame; `None` outside the model's
    /// validity region.
    fn project(&self, p: &Params, ray: &Vector3<f64>) -> Option<Vector2<f64>>;
    /// [`Self::project`] with `d pixel / d ray` under the intrinsics `k`.
    fn linearise(&self, k: &Intrinsics, p: &Params, ray: &Vector3<f64>) -> Option<Linearised>;
    /// `d pixel / d parameter` under `k` at `ray` (a valid ray: call after
    /// [`Self::linearise`] succeeded); `estimated[i]` tells which columns are used (the
    /// others may be left zero).
    fn param_jacobian(
        &self,
        k: &Intrinsics,
        p: &Params,
        ray: &Vector3<f64>,
        estimated: &[bool; MAX_PARAMS],
    ) -> ParamJacobian;
    /// The unit bearing of an image-plane point `m` (the inverse of [`Self::project`]);
    /// an error outside the image of the model (where it folds or has no ray).
    fn unproject(&self, p: &Params, m: &Vector2<f64>) -> Result<Vector3<f64>>;
}

/// A lens model's identifier (the rows of [`MODELS`], in this order); a camera's lens
/// is this kind and its parameters (`Distortion` of the `distortion` module).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LensKind {
    /// Radial-tangential: OpenCV / ROS `plumb_bob`, Kalibr `radtan` (the default; all
    /// coefficients zero is the pinhole).
    #[default]
    RadialTangential,
    /// Equidistant fisheye: OpenCV `fisheye`, ROS `equidistant`, Kalibr `equidistant`.
    Equidistant,
    /// Double sphere (Usenko et al. 2018): Kalibr `ds`, parameters `xi alpha`.
    DoubleSphere,
    /// The pinhole, no parameters.
    Pinhole,
}

impl LensKind {
    /// The model's row of the table.
    pub fn model(self) -> &'static dyn LensModel {
        model(self)
    }

    /// ROS `sensor_msgs/CameraInfo.distortion_model` (`None`: ROS has no such model).
    pub fn ros(self) -> Option<&'static str> {
        self.model().names().ros
    }

    /// ROS `distortion_model`, or the short name where ROS has none.
    pub fn ros_name(self) -> &'static str {
        let n = self.model().names();
        n.ros.unwrap_or(n.short)
    }

    /// The short name (`radtan`, `equidistant`, `ds`, `pinhole`; Kalibr's where it has one).
    pub fn kalibr_name(self) -> &'static str {
        self.model().names().short
    }

    /// The model named by any of the usual spellings of the table (`radtan`,
    /// `radial-tangential`, `plumb_bob`, `pinhole-radtan`; `equidistant`, `equi`,
    /// `fisheye`, `pinhole-equi`, `kannala_brandt`; `ds`, `double-sphere`; `pinhole`),
    /// case-insensitive. OpenCV's `rational_polynomial` (8 coefficients) is none of them.
    pub fn parse(name: &str) -> Option<Self> {
        let key = name.trim().to_ascii_lowercase().replace('_', "-");
        MODELS.iter().find(|m| m.names().aliases.contains(&key.as_str())).map(|m| m.kind())
    }

    /// Names of the coefficients in the order of the `Distortion`'s coefficients.
    pub fn coefficient_names(self) -> &'static [&'static str] {
        self.model().param_names()
    }
}

/// The table: every model, in the order of [`LensKind`]'s variants. The one place that
/// enumerates the models.
pub static MODELS: [&dyn LensModel; 4] = [&RadialTangential, &Equidistant, &DoubleSphere, &Pinhole];

/// The row of `kind` (the single dispatch point from [`LensKind`] to its model).
pub fn model(kind: LensKind) -> &'static dyn LensModel {
    // `MODELS` is in the order of the variants (checked by the tests).
    MODELS[kind as usize]
}

/// The pixel of an image-plane point under `k` (`K m`).
#[inline]
pub fn pixel_of(k: &Intrinsics, m: &Vector2<f64>) -> Vector2<f64> {
    Vector2::new(k.fx * m.x + k.skew * m.y + k.cx, k.fy * m.y + k.cy)
}

/// The image-plane point of a pixel under `k` (`K^-1 pixel`).
#[inline]
pub fn plane_of(k: &Intrinsics, pixel: &Vector2<f64>) -> Vector2<f64> {
    let y = (pixel.y - k.cy) / k.fy;
    Vector2::new((pixel.x - k.cx - k.skew * y) / k.fx, y)
}

/// `a > b`, false when either is NaN (so `!gt(z, 0.0)` also refuses a NaN `z`).
#[inline]
pub(crate) fn gt(a: f64, b: f64) -> bool {
    a > b
}

/// `K`'s 2x2 linear part `[[fx, skew], [0, fy]]`.
#[inline]
pub(crate) fn k2(k: &Intrinsics) -> nalgebra::Matrix2<f64> {
    nalgebra::Matrix2::new(k.fx, k.skew, 0.0, k.fy)
}

#[cfg(test)]
mod tests;
