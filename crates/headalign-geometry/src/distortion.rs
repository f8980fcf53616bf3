//! A camera's lens model and its parameters ([`Distortion`]: a [`LensKind`] and the
//! parameter values), dispatched through the table of [`crate::lens`] (every model in its
//! own file there; this module names none of them but in the conveniences
//! [`Distortion::radial`], [`Distortion::equidistant`] and [`Distortion::double_sphere`]).
//!
//! What it computes: the maps between the pinhole plane `x = K^-1 p` and the model's image
//! plane `m` ([`Distortion::distort`], [`Distortion::undistort`]), with Jacobians, for the
//! code that works on the pinhole plane; [`Distortion::project`] and
//! [`Distortion::unproject`] for rays and bearings (the only form that reaches beyond
//! 90 deg). [`Distortion::undistort_pixel`] maps a distorted pixel to the pixel an ideal
//! pinhole camera with the same `K` would see, which is how headalign uses a known lens
//! model of a narrow lens: observations are undistorted once, everything after is
//! pinhole.
//!
//! Degrees of freedom: the model's parameters ([`LensKind::coefficient_names`]); which of
//! them a bundle adjustment estimates is [`DistortionTerms`]. Storage: the model's
//! parameters in its order ([`Distortion::params`], zero-padded to
//! [`crate::lens::MAX_PARAMS`]). The JSON form names them: `kind`, then `k1 k2 p1 p2 k3
//! k4` always (zero where the model has no such parameter: the form older files and
//! readers have), then the model's other parameters where non-zero ([`LEGACY_NAMES`],
//! [`Distortion::named_values`]); a file naming a non-zero parameter its model lacks is
//! an error.
//!
//! Units: parameters are dimensionless (normalised coordinates; the equidistant ones
//! multiply powers of an angle in radians); pixels outside.
//!
//! Pitfalls: the coefficients belong to the `K` they were estimated with; undistorting with
//! a different `K` is a different lens model. The pinhole plane holds rays in front of the
//! camera only: a double-sphere ray beyond 90 deg has a bearing ([`Distortion::unproject`])
//! but no undistorted pixel (an error, never a folded point). Where a model's map folds
//! over it is an error, never a wrong point. The radial-tangential and equidistant `k1`
//! are different numbers for the same lens: the equidistant one includes the
//! `-1/3 theta^2` of `atan`. Setting [`Distortion::kind`] directly reinterprets the
//! parameters in the other model's order: build another model's lens with
//! [`Distortion::from_params`].

use nalgebra::{Matrix2, Point2, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use crate::camera::Intrinsics;
use crate::lens::{self, MAX_PARAMS, ParamJacobian, Params};
pub use crate::lens::{DistortionTerms, LensKind};
use crate::{GeometryError, Result};

/// A camera's lens: the model `kind` and its parameters (all zero in the radial-tangential
/// model is the pinhole; in the equidistant model it is the ideal equidistant lens
/// `theta_d = theta`; in the double sphere it projects as the pinhole but is not treated
/// as one: [`Distortion::is_zero`] is false).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Distortion {
    /// The model (default radial-tangential; older files without it are radial-tangential).
    pub kind: LensKind,
    /// The model's parameters in its order, zero beyond its count.
    params: Params,
}

/// The parameter names every JSON form writes, zero where the model lacks them (the
/// radial-tangential and equidistant names: the form of older files; module docs).
pub const LEGACY_NAMES: [&str; 6] = ["k1", "k2", "p1", "p2", "k3", "k4"];

impl Distortion {
    /// A `kind` lens with the parameters `params` in its order (entries beyond its count
    /// are dropped; not validated: [`Self::validate`]).
    pub fn from_params(kind: LensKind, params: Params) -> Self {
        Self { kind, params }.masked()
    }

    /// Entries beyond the model's parameter count set to zero.
    fn masked(mut self) -> Self {
        let n = self.kind.model().param_names().len();
        for v in self.params.iter_mut().skip(n) {
            *v = 0.0;
        }
        self
    }

    /// Radial-tangential, radial terms only.
    pub fn radial(k1: f64, k2: f64) -> Self {
        Self::from_params(LensKind::RadialTangential, [k1, k2, 0.0, 0.0, 0.0, 0.0])
    }

    /// Equidistant with `k1..k4`.
    pub fn equidistant(k: [f64; 4]) -> Self {
        Self::from_params(LensKind::Equidistant, [k[0], k[1], k[2], k[3], 0.0, 0.0])
    }

    /// Double sphere with `xi` and `alpha`.
    pub fn double_sphere(xi: f64, alpha: f64) -> Self {
        Self::from_params(LensKind::DoubleSphere, [xi, alpha, 0.0, 0.0, 0.0, 0.0])
    }

    /// All coefficients zero in the model `kind`.
    pub fn zero(kind: LensKind) -> Self {
        Self { kind, params: [0.0; MAX_PARAMS] }
    }

    /// From OpenCV's `D` vector of the `plumb_bob` model (4 or 5 entries: `k1 k2 p1 p2
    /// [k3]`; more entries are OpenCV's rational or thin-prism models, which headalign does
    /// not have: an error unless they are all zero).
    pub fn from_opencv(d: &[f64]) -> Result<Self> {
        Self::from_coefficients(LensKind::RadialTangential, d)
    }

    /// From a model and its coefficient vector in the order of
    /// [`LensKind::coefficient_names`] (the model's
    /// [`crate::lens::LensModel::read_coefficients`]: radial-tangential 4 or 5 entries,
    /// OpenCV's `D`; the others exactly their count), validated.
    pub fn from_coefficients(kind: LensKind, d: &[f64]) -> Result<Self> {
        let out = Self { kind, params: kind.model().read_coefficients(d)? }.masked();
        out.validate()?;
        Ok(out)
    }

    /// From a model and named values (the JSON / TOML forms: any of the model's parameter
    /// names; a name of [`LEGACY_NAMES`] the model lacks only with the value zero; any
    /// other name an error). Not validated.
    pub fn from_named_values<'a>(
        kind: LensKind,
        values: impl IntoIterator<Item = (&'a str, f64)>,
    ) -> Result<Self> {
        let names = kind.model().param_names();
        let mut out = Self::zero(kind);
        for (name, v) in values {
            match names.iter().position(|n| *n == name) {
                Some(i) => out.params[i] = v,
                None if LEGACY_NAMES.contains(&name) && v == 0.0 => {}
                None => {
                    return Err(GeometryError::InvalidOption(format!(
                        "a {} lens has no coefficient {name} (its coefficients: {})",
                        kind.model().names().short,
                        names.join(" ")
                    )));
                }
            }
        }
        Ok(out)
    }

    /// The named values of the JSON form (module docs): [`LEGACY_NAMES`] always (zero
    /// where the model lacks them), then the model's other parameters where non-zero.
    pub fn named_values(&self) -> Vec<(&'static str, f64)> {
        let mut out: Vec<(&'static str, f64)> =
            LEGACY_NAMES.iter().map(|&n| (n, self.param(n).unwrap_or(0.0))).collect();
        let names = self.kind.model().param_names();
        for (&n, &v) in names.iter().zip(&self.params) {
            if !LEGACY_NAMES.contains(&n) && v != 0.0 {
                out.push((n, v));
            }
        }
        out
    }

    /// As OpenCV's 5-vector `k1 k2 p1 p2 k3` (radial-tangential; another model gives its
    /// parameters of those names, zero where it has none, which is not its model: use
    /// [`Self::coefficients`]).
    pub fn to_opencv(&self) -> [f64; 5] {
        ["k1", "k2", "p1", "p2", "k3"].map(|n| self.param(n).unwrap_or(0.0))
    }

    /// The model's coefficient vector, in the order of [`LensKind::coefficient_names`]
    /// (OpenCV's `D` of `plumb_bob` or of `fisheye`; `xi alpha` of the double sphere).
    pub fn coefficients(&self) -> Vec<f64> {
        let n = self.kind.model().param_names().len();
        self.params[..n.min(MAX_PARAMS)].to_vec()
    }

    /// The model's parameters in its order, zero-padded (the table's [`Params`]).
    pub fn params(&self) -> Params {
        self.params
    }

    /// The model's parameter named `name` (`None`: the model has no such parameter).
    pub fn param(&self, name: &str) -> Option<f64> {
        let i = self.kind.model().param_names().iter().position(|n| *n == name)?;
        self.params.get(i).copied()
    }

    /// Mutable access to the model's parameter `i` (order of [`Self::coefficients`];
    /// `None` beyond its count).
    pub fn param_mut(&mut self, i: usize) -> Option<&mut f64> {
        if i >= self.kind.model().param_names().len() {
            return None;
        }
        self.params.get_mut(i)
    }

    /// Mutable access to the model's parameter named `name`.
    pub fn param_named_mut(&mut self, name: &str) -> Option<&mut f64> {
        let i = self.kind.model().param_names().iter().position(|n| *n == name)?;
        self.params.get_mut(i)
    }

    /// Every coefficient finite, and the model's own rules (the double sphere's range).
    pub fn validate(&self) -> Result<()> {
        if !self.params.iter().all(|v| v.is_finite()) {
            return Err(GeometryError::InvalidOption("distortion coefficients must be finite".into()));
        }
        self.kind.model().check_params(&self.params)
    }

    /// True for the pinhole (the pinhole model, or a radial-tangential lens with every
    /// coefficient zero; an equidistant or double-sphere lens never is one).
    pub fn is_zero(&self) -> bool {
        self.kind.model().pinhole_params() == Some(self.params)
    }

    /// The image-plane point `m` of a ray in the camera frame (`None` outside the model's
    /// validity region; [`crate::lens::LensModel::project`]).
    pub fn project(&self, ray: &Vector3<f64>) -> Option<Vector2<f64>> {
        self.kind.model().project(&self.params, ray)
    }

    /// The unit bearing of an image-plane point `m` ([`crate::lens::LensModel::unproject`]).
    pub fn unproject(&self, m: &Vector2<f64>) -> Result<Vector3<f64>> {
        if !(m.x.is_finite() && m.y.is_finite()) {
            return Err(GeometryError::InvalidOption("non-finite point to unproject".into()));
        }
        self.kind.model().unproject(&self.params, m)
    }

    /// The pixel of a ray in the camera frame through `k` and this lens.
    pub fn project_pixel(&self, k: &Intrinsics, ray: &Vector3<f64>) -> Option<Point2<f64>> {
        self.project(ray).map(|m| Point2::from(lens::pixel_of(k, &m)))
    }

    /// The unit bearing of a pixel through `k` and this lens.
    pub fn unproject_pixel(&self, k: &Intrinsics, pixel: &Point2<f64>) -> Result<Vector3<f64>> {
        self.unproject(&lens::plane_of(k, &pixel.coords))
    }

    /// Distorted normalised coordinates and the Jacobian `d x_d / d x` of a pinhole-plane
    /// point `x`.
    pub fn distort_with_jacobian(&self, x: &Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>) {
        let (xd, j, _) = self.distort_with_jacobians(x);
        (xd, j)
    }

    /// Distorted normalised coordinates, `d x_d / d x`, and `d x_d / d parameter` (columns
    /// in the order of [`Self::coefficients`]; columns beyond the model's parameters zero):
    /// the model's [`crate::lens::LensModel::distort`].
    pub fn distort_with_jacobians(&self, x: &Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>, ParamJacobian) {
        self.kind.model().distort(&self.params, x)
    }

    /// Distorted normalised coordinates of a pinhole-plane point.
    pub fn distort(&self, x: &Vector2<f64>) -> Vector2<f64> {
        self.distort_with_jacobian(x).0
    }

    /// Undistorted normalised coordinates (the pinhole-plane point) of distorted ones:
    /// the model's inverse ([`crate::lens::LensModel::undistort`]: Newton for the
    /// radial-tangential and equidistant models, the closed form of the double sphere);
    /// an error where the model folds over or the ray is not in front of the camera.
    pub fn undistort(&self, xd: &Vector2<f64>) -> Result<Vector2<f64>> {
        if self.is_zero() {
            return Ok(*xd);
        }
        if !(xd.x.is_finite() && xd.y.is_finite()) {
            return Err(GeometryError::InvalidOption("non-finite point to undistort".into()));
        }
        self.kind.model().undistort(&self.params, xd)
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

impl Serialize for Distortion {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        let values = self.named_values();
        let mut map = s.serialize_map(Some(values.len() + 1))?;
        map.serialize_entry("kind", &self.kind)?;
        for (name, v) in values {
            map.serialize_entry(name, &v)?;
        }
        map.end()
    }
}

impl<'de> Deserialize<'de> for Distortion {
    fn deserialize<D: serde::Deserializer<'de>>(de: D) -> std::result::Result<Self, D::Error> {
        /// The JSON form: the model (default radial-tangential) and named values.
        #[derive(Deserialize)]
        struct Form {
            #[serde(default)]
            kind: LensKind,
            #[serde(flatten)]
            values: std::collections::BTreeMap<String, f64>,
        }
        let form = Form::deserialize(de)?;
        Self::from_named_values(form.kind, form.values.iter().map(|(n, v)| (n.as_str(), *v)))
            .map_err(serde::de::Error::custom)
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
            let d = Distortion::from_params(LensKind::RadialTangential, [k1, k2, p1, p2, k3, 0.0]);
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
            let d = Distortion::from_params(LensKind::RadialTangential, [k1, k2, p1, p2, k3, 0.0]);
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

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]
        /// Equidistant round trip over a 768x576 image with fisheye-like lenses (a 1.4-rad
        /// field at the corner): 1e-9 px, as for the radial-tangential model.
        #[test]
        fn equidistant_undistort_inverts_distort(
            k1 in -0.1..0.1f64, k2 in -0.05..0.05f64, k3 in -0.01..0.01f64, k4 in -0.005..0.005f64,
            u in 0.0..768.0f64, v in 0.0..576.0f64,
        ) {
            let d = Distortion::equidistant([k1, k2, k3, k4]);
            let k = Intrinsics::new(300.0, 310.0, 390.0, 284.0);
            let ideal = Point2::new(u, v);
            let distorted = d.distort_pixel(&k, &ideal);
            let back = d.undistort_pixel(&k, &distorted).unwrap();
            prop_assert!((back - ideal).norm() < 1e-9, "{back:?} vs {ideal:?}");
        }

        /// Both Jacobians of both models against central differences (step 1e-6 on the
        /// point, 1e-5 on a coefficient; tolerance 1e-7: truncation error h^2 times the
        /// third derivative ~ 1e-10, rounding 1e-16 / h ~ 1e-10).
        #[test]
        fn coefficient_jacobians_match_finite_differences(
            equi in any::<bool>(), c in proptest::array::uniform6(-0.05..0.05f64),
            x in -0.9..0.9f64, y in -0.7..0.7f64,
        ) {
            let d = if equi {
                Distortion::equidistant([c[0], c[1], c[4], c[5]])
            } else {
                Distortion::from_params(LensKind::RadialTangential, [c[0], c[1], c[2] * 0.1, c[3] * 0.1, c[4], 0.0])
            };
            let p = Vector2::new(x, y);
            let (xd, j, jc) = d.distort_with_jacobians(&p);
            prop_assert!((xd - d.distort(&p)).norm() == 0.0);
            let h = 1e-6;
            for col in 0..2 {
                let mut e = Vector2::zeros();
                e[col] = h;
                let fd = (d.distort(&(p + e)) - d.distort(&(p - e))) / (2.0 * h);
                prop_assert!((fd - j.column(col)).norm() < 1e-7, "x column {col}: {fd:?} vs {:?}", j.column(col));
            }
            let h = 1e-5;
            for i in 0..d.coefficients().len() {
                let (mut a, mut b) = (d, d);
                *a.param_mut(i).unwrap() += h;
                *b.param_mut(i).unwrap() -= h;
                let fd = (a.distort(&p) - b.distort(&p)) / (2.0 * h);
                prop_assert!((fd - jc.column(i)).norm() < 1e-7, "parameter {i}: {fd:?} vs {:?}", jc.column(i));
            }
            for i in d.coefficients().len()..MAX_PARAMS {
                prop_assert!(jc.column(i).norm() == 0.0);
            }
        }
    }

    /// The equidistant map against the fisheye formula written out by hand (OpenCV's
    /// `cv::fisheye` model): x = (0.3, 0.4), r = 0.5, theta = atan(0.5),
    /// theta_d = theta (1 + k1 theta^2 + ...), x_d = theta_d / r x.
    #[test]
    fn equidistant_matches_the_fisheye_formula() {
        let d = Distortion::equidistant([0.1, -0.02, 0.003, -0.0004]);
        let theta = 0.5f64.atan();
        let t2 = theta * theta;
        let td = theta * (1.0 + 0.1 * t2 - 0.02 * t2 * t2 + 0.003 * t2.powi(3) - 0.0004 * t2.powi(4));
        let got = d.distort(&Vector2::new(0.3, 0.4));
        let want = Vector2::new(0.3, 0.4) * (td / 0.5);
        assert!((got - want).norm() < 1e-15, "{got:?} vs {want:?}");
        // The zero equidistant lens is `atan`, not the pinhole.
        let zero = Distortion::zero(LensKind::Equidistant);
        assert!(!zero.is_zero());
        assert!((zero.distort(&Vector2::new(1.0, 0.0)).x - std::f64::consts::FRAC_PI_4).abs() < 1e-15);
        // Centre: the identity, continuous with the series.
        let tiny = Vector2::new(1e-9, -2e-9);
        assert!((d.distort(&tiny) - tiny).norm() < 1e-24);
    }

    #[test]
    fn names_and_coefficient_vectors() {
        for (name, kind) in [
            ("plumb_bob", LensKind::RadialTangential),
            ("radtan", LensKind::RadialTangential),
            ("Pinhole-Radtan", LensKind::RadialTangential),
            ("fisheye", LensKind::Equidistant),
            ("equidistant", LensKind::Equidistant),
            ("pinhole-equi", LensKind::Equidistant),
        ] {
            assert_eq!(LensKind::parse(name), Some(kind), "{name}");
        }
        assert_eq!(LensKind::parse("ds"), Some(LensKind::DoubleSphere));
        assert_eq!(LensKind::parse("Double_Sphere"), Some(LensKind::DoubleSphere));
        // OpenCV's 8-coefficient model is not the radial-tangential one.
        assert_eq!(LensKind::parse("rational_polynomial"), None);
        let ds = Distortion::from_coefficients(LensKind::DoubleSphere, &[-0.2, 0.6]).unwrap();
        assert_eq!(
            (ds.param("xi"), ds.param("alpha"), ds.coefficients()),
            (Some(-0.2), Some(0.6), vec![-0.2, 0.6])
        );
        assert!(Distortion::from_coefficients(LensKind::DoubleSphere, &[0.1, 1.5]).is_err());
        assert!(!ds.is_zero() && Distortion::zero(LensKind::Pinhole).is_zero());
        // xi and alpha appear in the JSON of a double sphere only.
        assert!(!serde_json::to_string(&Distortion::radial(0.1, 0.0)).unwrap().contains("xi"));
        let back: Distortion = serde_json::from_str(&serde_json::to_string(&ds).unwrap()).unwrap();
        assert_eq!(back, ds);
        let e = Distortion::from_coefficients(LensKind::Equidistant, &[0.1, 0.2, 0.3, 0.4]).unwrap();
        assert_eq!(e.coefficients(), vec![0.1, 0.2, 0.3, 0.4]);
        assert_eq!(["k1", "k2", "k3", "k4"].map(|n| e.param(n)), [0.1, 0.2, 0.3, 0.4].map(Some));
        assert_eq!(e.param("p1"), None);
        assert!(Distortion::from_coefficients(LensKind::Equidistant, &[0.1, 0.2, 0.3]).is_err());
        // A coefficient the model lacks: an error when read, unless zero (the JSON form
        // writes k1 k2 p1 p2 k3 k4 for every model).
        assert!(Distortion::from_named_values(LensKind::Equidistant, [("p1", 0.1)]).is_err());
        assert!(Distortion::from_named_values(LensKind::Equidistant, [("p1", 0.0), ("k4", 0.4)]).is_ok());
        assert!(serde_json::from_str::<Distortion>(r#"{"kind":"equidistant","p1":0.1}"#).is_err());
        assert!(serde_json::from_str::<Distortion>(r#"{"kind":"double-sphere","k5":0.0}"#).is_err());
        // The JSON form: kind, k1 k2 p1 p2 k3 k4 always, the model's others when non-zero.
        assert_eq!(
            serde_json::to_string(&ds).unwrap(),
            r#"{"kind":"double-sphere","k1":0.0,"k2":0.0,"p1":0.0,"p2":0.0,"k3":0.0,"k4":0.0,"xi":-0.2,"alpha":0.6}"#
        );
        assert_eq!(
            serde_json::to_string(&Distortion::radial(-0.2, 0.05)).unwrap(),
            r#"{"kind":"radial-tangential","k1":-0.2,"k2":0.05,"p1":0.0,"p2":0.0,"k3":0.0,"k4":0.0}"#
        );
        // Older JSON without `kind` and `k4` reads as radial-tangential.
        let old: Distortion =
            serde_json::from_str(r#"{"k1":-0.2,"k2":0.05,"p1":0.0,"p2":0.0,"k3":0.0}"#).unwrap();
        assert_eq!(old, Distortion::radial(-0.2, 0.05));
    }

    #[test]
    fn bad_inputs_are_errors() {
        assert!(Distortion::from_opencv(&[0.1, 0.2]).is_err());
        assert!(Distortion::from_opencv(&[0.1, f64::NAN, 0.0, 0.0]).is_err());
        assert!(Distortion::from_opencv(&[0.1, 0.0, 0.0, 0.0, 0.0, 0.3]).is_err());
        // OpenCV's rational_polynomial D (k1 k2 p1 p2 k3 k4 k5 k6) is refused by name.
        let e = Distortion::from_opencv(&[0.1, 0.0, 0.0, 0.0, 0.0, 0.3, 0.0, 0.0]).unwrap_err();
        assert!(e.to_string().contains("rational_polynomial"), "{e}");
        assert_eq!(Distortion::from_opencv(&[0.1, 0.2, 0.0, 0.0]).unwrap(), Distortion::radial(0.1, 0.2));
        // A strong barrel lens folds over far out: an error, not a wrong point.
        let d = Distortion::radial(-0.5, 0.0);
        assert!(d.undistort(&Vector2::new(2.0, 0.0)).is_err());
        assert!(d.undistort(&Vector2::new(f64::NAN, 0.0)).is_err());
    }
}
