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
//! **Adding a model** is exactly:
//! 1. a file here with a unit struct implementing [`LensModel`]: its names
//!    ([`ModelNames`]: id, short name, OpenCV / ROS names or `None`, its [`KalibrForm`] or
//!    `None`, the spellings [`LensKind::parse`] accepts), its parameter names (at most
//!    [`MAX_PARAMS`]), its field ([`LensModel::max_half_fov_deg`]), `project`,
//!    `linearise`, `param_jacobian` and `unproject`; the other methods have defaults
//!    (override where the model has the property: `estimated` for terms that are not
//!    nested levels, `check_params` for a range, `read_coefficients` for a file's
//!    vector of another length, `distort` / `undistort` for a faster pinhole-plane map,
//!    the profile for the renderer's fold check, and the starts `calibrate` takes from
//!    the model: `grid_lens`, `stereographic`, `along_focal_valley`,
//!    `fit_radial_profile`);
//! 2. a [`LensKind`] variant, and its row in [`MODELS`] at the variant's index (the `mod`
//!    and `pub use` lines above);
//! 3. nothing else: `distortion::Distortion` stores any model's parameters by index and
//!    names them through the row (its JSON, the simulator's TOML table, the bundle
//!    adjustment's parameter names `left.<name>`), the residual projects through
//!    [`LensModel::linearise`], the file writers take the names and refuse a model their
//!    format lacks by its `None` name (Kalibr's form writes any model that has one), the
//!    renderer casts bearings for a model wider than 90 deg, and `--lens auto` offers
//!    every model of the table (the narrow ones at the nested levels of
//!    [`DistortionTerms`], a wide one when the observed field exceeds 60 deg).
//!
//! Tests to add: the model's rows in `tests.rs` (`instance`, `field`: the Jacobians and
//! the round trip are then checked), and its formula written out by hand for one ray.
//!
//! Named outside this folder, on purpose: the radial-tangential model as the default kind
//! (`LensKind::default`, older files without `kind`), OpenCV's `plumb_bob` `D`
//! (`Distortion::from_opencv`), and the base of `--lens auto`'s criterion (`BASE_LENS` of
//! `headalign::rig::lens_choice`); the conveniences `Distortion::radial`, `equidistant`
//! and `double_sphere`; and tests.
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

use nalgebra::{Matrix2, Matrix2x3, SMatrix, Vector2, Vector3};

use crate::camera::Intrinsics;
use crate::{GeometryError, Result};

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
    /// OpenCV's model (`None`: OpenCV has none; its writer refuses the model by name).
    pub opencv: Option<&'static str>,
    /// ROS `sensor_msgs/CameraInfo.distortion_model` (`None`: none; refused likewise).
    pub ros: Option<&'static str>,
    /// Kalibr's camchain form of the model (`None`: Kalibr has none).
    pub kalibr: Option<KalibrForm>,
    /// Every spelling [`LensKind::parse`] accepts (lower case, `-` for `_`).
    pub aliases: &'static [&'static str],
}

/// How Kalibr's `camchain.yaml` writes a model: `camera_model`, the model's parameters
/// that precede `fu fv pu pv` in `intrinsics`, `distortion_model` and the parameters of
/// `distortion_coeffs`. A parameter in neither list is not representable in Kalibr (the
/// writer notes a non-zero one in a comment).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct KalibrForm {
    /// `camera_model` (`pinhole`, `ds`).
    pub camera_model: &'static str,
    /// The parameters written before `fu fv pu pv` in `intrinsics` (the double sphere's `xi alpha`).
    pub intrinsics: &'static [&'static str],
    /// `distortion_model` (`radtan`, `equidistant`, `none`).
    pub distortion_model: &'static str,
    /// The parameters of `distortion_coeffs`, in Kalibr's order.
    pub distortion_coeffs: &'static [&'static str],
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

/// Which of a model's parameters a bundle adjustment estimates: always the model's first
/// ones, as many as [`LensModel::estimated`] says for the level (the others are held at
/// their values, usually zero).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum DistortionTerms {
    /// `k1, k2` (radial-tangential, equidistant; the default: the tangential terms are
    /// nearly degenerate with the principal point unless the data are strong); the double
    /// sphere's `xi, alpha`.
    Radial2,
    /// `k1, k2, p1, p2` (radial-tangential: Kalibr's `radtan`) or `k1..k4` (equidistant:
    /// Kalibr's `equidistant`); the double sphere's `xi, alpha`.
    Full4,
    /// `k1, k2, p1, p2, k3` (radial-tangential; the others as [`Self::Full4`]).
    Full5,
}

impl DistortionTerms {
    /// The levels, smallest first.
    pub const LEVELS: [DistortionTerms; 3] = [Self::Radial2, Self::Full4, Self::Full5];

    /// The count of leading parameters the level names (2, 4, 5), before a model caps it.
    pub fn count(self) -> usize {
        match self {
            Self::Radial2 => 2,
            Self::Full4 => 4,
            Self::Full5 => 5,
        }
    }

    /// The estimated parameters of a `kind` lens, as indices of its parameters
    /// ([`LensKind::coefficient_names`]).
    pub fn params(self, kind: LensKind) -> &'static [usize] {
        const ALL: [usize; MAX_PARAMS] = [0, 1, 2, 3, 4, 5];
        &ALL[..kind.model().estimated(self).min(MAX_PARAMS)]
    }

    /// Parse `k1k2` / `radial` (radial terms), `4` / `full4`, `5` / `full5`.
    pub fn parse(name: &str) -> Option<Self> {
        match name.trim().to_ascii_lowercase().as_str() {
            "radial" | "2" | "k1k2" | "radial2" => Some(Self::Radial2),
            "4" | "full4" => Some(Self::Full4),
            "5" | "full5" => Some(Self::Full5),
            _ => None,
        }
    }
}

/// One lens model (a row of [`MODELS`]; module docs).
pub trait LensModel: Sync {
    /// The identifier of this row.
    fn kind(&self) -> LensKind;
    /// The model's names in users' tools.
    fn names(&self) -> &'static ModelNames;
    /// The parameters, in the model's order (OpenCV's `D` where OpenCV has the model).
    fn param_names(&self) -> &'static [&'static str];
    /// The largest half field of view the model can represent, degrees (metadata; beyond
    /// 90 deg the model has rays with no pinhole point: the renderer casts bearings and
    /// `calibrate` takes its wide route).
    fn max_half_fov_deg(&self) -> f64;
    /// How many leading parameters an adjustment at `terms` estimates (default: the
    /// level's count, capped at the model's parameter count).
    fn estimated(&self, terms: DistortionTerms) -> usize {
        terms.count().min(self.param_names().len())
    }
    /// The model's parameters that make it the identity on the pinhole plane (the
    /// pinhole); `None` when no choice does (equidistant, double sphere).
    fn pinhole_params(&self) -> Option<Params> {
        None
    }
    /// Validity of the parameters beyond finiteness (`Err` names the rule broken).
    fn check_params(&self, _p: &Params) -> Result<()> {
        Ok(())
    }
    /// The parameters of a coefficient vector in the model's order as files write it
    /// (default: exactly [`Self::param_names`]'s count; the radial-tangential model reads
    /// OpenCV's `D` of 4 or 5 entries).
    fn read_coefficients(&self, d: &[f64]) -> Result<Params> {
        let names = self.param_names();
        if d.len() != names.len() {
            return Err(GeometryError::InvalidOption(format!(
                "a {} lens has {} coefficients {}, got {}",
                self.names().short,
                names.len(),
                names.join(" "),
                d.len()
            )));
        }
        let mut p = [0.0; MAX_PARAMS];
        for (o, v) in p.iter_mut().zip(d) {
            *o = *v;
        }
        Ok(p)
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
    /// The map of the pinhole plane: the image-plane point of the pinhole-plane point `x`,
    /// `d m / d x` and `d m / d parameter` (default: through [`Self::linearise`] and
    /// [`Self::param_jacobian`] at the ray `(x, y, 1)` with `K` the identity; NaN where
    /// the ray does not project).
    fn distort(&self, p: &Params, x: &Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>, ParamJacobian) {
        let ray = Vector3::new(x.x, x.y, 1.0);
        let unit = Intrinsics::new(1.0, 1.0, 0.0, 0.0);
        match self.linearise(&unit, p, &ray) {
            Some(l) => {
                let j = l.d_ray.fixed_view::<2, 2>(0, 0).into_owned();
                (l.m, j, self.param_jacobian(&unit, p, &ray, &[true; MAX_PARAMS]))
            }
            None => (Vector2::repeat(f64::NAN), Matrix2::repeat(f64::NAN), ParamJacobian::repeat(f64::NAN)),
        }
    }
    /// The pinhole-plane point of the image-plane point `m` (the inverse of
    /// [`Self::distort`]; default: [`Self::unproject`], an error for a ray at or beyond
    /// 90 deg).
    fn undistort(&self, p: &Params, m: &Vector2<f64>) -> Result<Vector2<f64>> {
        let b = self.unproject(p, m)?;
        if !gt(b.z, 1e-12) {
            return Err(GeometryError::Degenerate(format!(
                "({:.3}, {:.3}) is a ray at or beyond 90 deg: it has no pinhole point",
                m.x, m.y
            )));
        }
        Ok(Vector2::new(b.x / b.z, b.y / b.z))
    }
    /// The radial profile the renderer checks for a fold (`check_invertible` of the
    /// simulator): the end of its argument's range, and the image-plane radius along `+x`
    /// at argument `a` (terms that are not radially symmetric left out; NaN outside the
    /// model's region). Default: the argument is the pinhole-plane radius, up to 100.
    fn profile_end(&self) -> f64 {
        100.0
    }
    /// See [`Self::profile_end`].
    fn radial_profile(&self, p: &Params, a: f64) -> f64 {
        self.distort(p, &Vector2::new(a, 0.0)).0.x
    }
    /// The lens of `calibrate`'s lens grid (`calibrate::two_pass`): the parameters whose
    /// first parameter alone (the first two for a two-parameter shape) moves a point at
    /// pinhole-plane radius `corner` radially by the fraction `delta` of its radius;
    /// `None` where the model has no such lens (default: none).
    fn grid_lens(&self, _delta: f64, _corner: f64) -> Option<Params> {
        None
    }
    /// The start of a wide model's lens grid (`calibrate::wide`): the model's
    /// stereographic lens, `r = 2 f tan(theta / 2)`; `None` where it has none (default).
    fn stereographic(&self) -> Option<Params> {
        None
    }
    /// Along the model's focal valley (a parameter that trades with the focal length
    /// near the axis; `calibrate::wide`): the focal-length factor and the parameters with
    /// that parameter set to `value` that keep the central pixel scale and the pixel of a
    /// ray `theta` radians off the axis. `None`: the model has no such valley (default;
    /// `calibrate::wide` scans the valley only of a model that answers).
    fn along_focal_valley(&self, _p: &Params, _value: f64, _theta: f64) -> Option<(f64, Params)> {
        None
    }
    /// The lens of this model with `estimated` leading parameters free whose radial
    /// profile is closest to `profile` (image-plane radius of a pinhole-plane radius),
    /// over pinhole-plane radii up to `field`: the start of `--lens auto`'s refit of this
    /// model from the base (radial-tangential) fit. Default: the zero parameters.
    fn fit_radial_profile(&self, _profile: &dyn Fn(f64) -> f64, _field: f64, _estimated: usize) -> Params {
        [0.0; MAX_PARAMS]
    }
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
