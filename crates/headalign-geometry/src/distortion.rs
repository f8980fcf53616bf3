//! A camera's lens model and its parameters ([`Distortion`]: a [`LensKind`] and the
//! parameter values), dispatched through the table of [`crate::lens`]: the pinhole,
//! radial-tangential (OpenCV `plumb_bob`), equidistant (OpenCV `fisheye`) and double-sphere
//! (Kalibr `ds`) models, each in its own file there.
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
//! them a bundle adjustment estimates is [`DistortionTerms`]. Storage: every model's
//! parameters live in the eight slots `k1 k2 p1 p2 k3 k4 xi alpha` ([`Distortion::slots`],
//! the table's [`crate::lens::LensModel::slots`]); the JSON form names them (`xi`, `alpha`
//! appear only when non-zero, so files without them read as before).
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
//! `-1/3 theta^2` of `atan`.

use nalgebra::{Matrix2, Point2, SMatrix, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use crate::camera::Intrinsics;
pub use crate::lens::LensKind;
use crate::lens::{self, MAX_PARAMS, ParamJacobian, Params};
use crate::{GeometryError, Result};

/// A camera's lens: the model `kind` and its parameters (all zero in the radial-tangential
/// model is the pinhole; in the equidistant model it is the ideal equidistant lens
/// `theta_d = theta`; in the double sphere it projects as the pinhole but is not treated
/// as one: [`Distortion::is_zero`] is false).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Distortion {
    /// The model (default radial-tangential; older files without it are radial-tangential).
    #[serde(default)]
    pub kind: LensKind,
    /// Radial: `r^2` (radial-tangential) or `theta^3` (equidistant).
    pub k1: f64,
    /// Radial: `r^4` or `theta^5`.
    pub k2: f64,
    /// Tangential (radial-tangential only).
    pub p1: f64,
    /// Tangential (radial-tangential only).
    pub p2: f64,
    /// Radial: `r^6` or `theta^7`.
    pub k3: f64,
    /// Radial `theta^9` (equidistant only).
    #[serde(default)]
    pub k4: f64,
    /// Double sphere: the shift of the second sphere (zero in the other models).
    #[serde(default, skip_serializing_if = "is_zero_f64")]
    pub xi: f64,
    /// Double sphere: the shift of the pinhole, `alpha / (1 - alpha)` (zero in the other
    /// models).
    #[serde(default, skip_serializing_if = "is_zero_f64")]
    pub alpha: f64,
}

fn is_zero_f64(v: &f64) -> bool {
    *v == 0.0
}

/// Which coefficients a bundle adjustment estimates (the others are held at their
/// values, usually zero).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
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
    /// The estimated parameters of a `kind` lens, as indices of its parameters
    /// ([`LensKind::coefficient_names`]).
    pub fn params(self, kind: LensKind) -> &'static [usize] {
        const ALL: [usize; MAX_PARAMS] = [0, 1, 2, 3, 4, 5];
        let n = kind.model().param_names().len();
        let wanted = match (self, kind) {
            (_, LensKind::Pinhole) => 0,
            (_, LensKind::DoubleSphere) => 2,
            (DistortionTerms::Radial2, _) => 2,
            (DistortionTerms::Full4, _) => 4,
            (DistortionTerms::Full5, _) => 5,
        };
        &ALL[..wanted.min(n)]
    }

    /// The estimated parameters' slots of [`Distortion::slots`] in a `kind` lens.
    pub fn slots(self, kind: LensKind) -> &'static [usize] {
        // The estimated parameters are always the model's first ones.
        let slots = kind.model().slots();
        &slots[..self.params(kind).len().min(slots.len())]
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

/// The names of the eight storage slots of [`Distortion::slots`].
pub const SLOT_NAMES: [&str; 8] = ["k1", "k2", "p1", "p2", "k3", "k4", "xi", "alpha"];

impl Distortion {
    /// Radial-tangential, radial terms only.
    pub fn radial(k1: f64, k2: f64) -> Self {
        Self { k1, k2, ..Self::default() }
    }

    /// Equidistant with `k1..k4`.
    pub fn equidistant(k: [f64; 4]) -> Self {
        Self { kind: LensKind::Equidistant, k1: k[0], k2: k[1], k3: k[2], k4: k[3], ..Self::default() }
    }

    /// Double sphere with `xi` and `alpha`.
    pub fn double_sphere(xi: f64, alpha: f64) -> Self {
        Self { kind: LensKind::DoubleSphere, xi, alpha, ..Self::default() }
    }

    /// All coefficients zero in the model `kind`.
    pub fn zero(kind: LensKind) -> Self {
        Self { kind, ..Self::default() }
    }

    /// From OpenCV's `D` vector of the `plumb_bob` model (4 or 5 entries: `k1 k2 p1 p2
    /// [k3]`; more entries are OpenCV's rational or thin-prism models, which headalign does
    /// not have: an error unless they are all zero).
    pub fn from_opencv(d: &[f64]) -> Result<Self> {
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
        let out = Self {
            k1: d[0],
            k2: d[1],
            p1: d[2],
            p2: d[3],
            k3: d.get(4).copied().unwrap_or(0.0),
            ..Self::default()
        };
        out.validate()?;
        Ok(out)
    }

    /// From a model and its coefficient vector in the order of
    /// [`LensKind::coefficient_names`] (radial-tangential: 4 or 5 entries, OpenCV's `D`;
    /// the others exactly their count).
    pub fn from_coefficients(kind: LensKind, d: &[f64]) -> Result<Self> {
        if kind == LensKind::RadialTangential {
            return Self::from_opencv(d);
        }
        let model = kind.model();
        let names = model.param_names();
        if d.len() != names.len() {
            return Err(GeometryError::InvalidOption(format!(
                "a {} lens has {} coefficients {}, got {}",
                model.names().short,
                names.len(),
                names.join(" "),
                d.len()
            )));
        }
        let mut out = Self::zero(kind);
        for (&slot, &v) in model.slots().iter().zip(d) {
            if let Some(o) = out.slot_mut(slot) {
                *o = v;
            }
        }
        out.validate()?;
        Ok(out)
    }

    /// As OpenCV's 5-vector `k1 k2 p1 p2 k3` (radial-tangential; another model gives its
    /// slots `k1 k2 p1 p2 k3`, which is not its model: use [`Self::coefficients`]).
    pub fn to_opencv(&self) -> [f64; 5] {
        [self.k1, self.k2, self.p1, self.p2, self.k3]
    }

    /// The model's coefficient vector, in the order of [`LensKind::coefficient_names`]
    /// (OpenCV's `D` of `plumb_bob` or of `fisheye`; `xi alpha` of the double sphere).
    pub fn coefficients(&self) -> Vec<f64> {
        let n = self.kind.model().param_names().len();
        self.params()[..n].to_vec()
    }

    /// The model's parameters in its order, zero-padded (the table's [`Params`]).
    pub fn params(&self) -> Params {
        let slots = self.slots();
        let mut p = [0.0; MAX_PARAMS];
        for (o, &s) in p.iter_mut().zip(self.kind.model().slots()) {
            *o = slots.get(s).copied().unwrap_or(0.0);
        }
        p
    }

    /// Mutable access to the model's parameter `i` (order of [`Self::coefficients`]).
    pub fn param_mut(&mut self, i: usize) -> Option<&mut f64> {
        let slot = *self.kind.model().slots().get(i)?;
        self.slot_mut(slot)
    }

    /// All eight storage slots `k1 k2 p1 p2 k3 k4 xi alpha` ([`SLOT_NAMES`]).
    pub fn slots(&self) -> [f64; 8] {
        [self.k1, self.k2, self.p1, self.p2, self.k3, self.k4, self.xi, self.alpha]
    }

    /// Mutable access to slot `i` of [`Self::slots`] (`None` beyond 7).
    pub fn slot_mut(&mut self, i: usize) -> Option<&mut f64> {
        match i {
            0 => Some(&mut self.k1),
            1 => Some(&mut self.k2),
            2 => Some(&mut self.p1),
            3 => Some(&mut self.p2),
            4 => Some(&mut self.k3),
            5 => Some(&mut self.k4),
            6 => Some(&mut self.xi),
            7 => Some(&mut self.alpha),
            _ => None,
        }
    }

    /// The slot of the model's `i`-th coefficient (order of [`Self::coefficients`]).
    pub fn slot_of(kind: LensKind, i: usize) -> Option<usize> {
        kind.model().slots().get(i).copied()
    }

    /// Every coefficient finite, no slot set that the model does not have, and the
    /// model's own rules (the double sphere's range).
    pub fn validate(&self) -> Result<()> {
        if !self.slots().iter().all(|v| v.is_finite()) {
            return Err(GeometryError::InvalidOption("distortion coefficients must be finite".into()));
        }
        let model = self.kind.model();
        let foreign: Vec<&str> = self
            .slots()
            .iter()
            .enumerate()
            .filter(|(i, v)| **v != 0.0 && !model.slots().contains(i))
            .filter_map(|(i, _)| SLOT_NAMES.get(i).copied())
            .collect();
        if !foreign.is_empty() {
            return Err(GeometryError::InvalidOption(format!(
                "a {:?} lens has no coefficient {}",
                self.kind,
                foreign.join("/")
            )));
        }
        model.check_params(&self.params())
    }

    /// True for the pinhole (the pinhole model, or a radial-tangential lens with every
    /// coefficient zero; an equidistant or double-sphere lens never is one).
    pub fn is_zero(&self) -> bool {
        match self.kind.model().pinhole_params() {
            Some(p) => self.slots().iter().all(|&v| v == 0.0) && self.params() == p,
            None => false,
        }
    }

    /// The image-plane point `m` of a ray in the camera frame (`None` outside the model's
    /// validity region; [`crate::lens::LensModel::project`]).
    pub fn project(&self, ray: &Vector3<f64>) -> Option<Vector2<f64>> {
        self.kind.model().project(&self.params(), ray)
    }

    /// The unit bearing of an image-plane point `m` ([`crate::lens::LensModel::unproject`]).
    pub fn unproject(&self, m: &Vector2<f64>) -> Result<Vector3<f64>> {
        if !(m.x.is_finite() && m.y.is_finite()) {
            return Err(GeometryError::InvalidOption("non-finite point to unproject".into()));
        }
        self.kind.model().unproject(&self.params(), m)
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
    /// in the order of [`Self::coefficients`]; columns beyond the model's parameters zero).
    pub fn distort_with_jacobians(&self, x: &Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>, ParamJacobian) {
        let p = self.params();
        match self.kind {
            LensKind::RadialTangential => {
                let (xd, j) = lens::radtan::distort(&p, x);
                (xd, j, lens::radtan::coefficient_jacobian(x))
            }
            LensKind::Equidistant => lens::equidistant::distort(&p, x),
            // The other models through their ray projection at (x, y, 1), K = identity.
            _ => {
                let model = self.kind.model();
                let ray = Vector3::new(x.x, x.y, 1.0);
                let unit = Intrinsics::new(1.0, 1.0, 0.0, 0.0);
                match model.linearise(&unit, &p, &ray) {
                    Some(l) => {
                        let j = l.d_ray.fixed_view::<2, 2>(0, 0).into_owned();
                        (l.m, j, model.param_jacobian(&unit, &p, &ray, &[true; MAX_PARAMS]))
                    }
                    None => (Vector2::repeat(f64::NAN), Matrix2::repeat(f64::NAN), SMatrix::repeat(f64::NAN)),
                }
            }
        }
    }

    /// Distorted normalised coordinates of a pinhole-plane point.
    pub fn distort(&self, x: &Vector2<f64>) -> Vector2<f64> {
        self.distort_with_jacobian(x).0
    }

    /// Undistorted normalised coordinates (the pinhole-plane point) of distorted ones:
    /// the model's inverse (Newton for the radial-tangential and equidistant models, the
    /// closed form of the double sphere); an error where the model folds over or the
    /// ray is not in front of the camera.
    pub fn undistort(&self, xd: &Vector2<f64>) -> Result<Vector2<f64>> {
        if self.is_zero() {
            return Ok(*xd);
        }
        if !(xd.x.is_finite() && xd.y.is_finite()) {
            return Err(GeometryError::InvalidOption("non-finite point to undistort".into()));
        }
        let p = self.params();
        match self.kind {
            LensKind::RadialTangential => lens::radtan::undistort(&p, xd),
            LensKind::Equidistant => lens::equidistant::undistort(&p, xd),
            _ => {
                let b = self.kind.model().unproject(&p, xd)?;
                if !lens::gt(b.z, 1e-12) {
                    return Err(GeometryError::Degenerate(format!(
                        "({:.3}, {:.3}) is a ray at or beyond 90 deg: it has no pinhole point",
                        xd.x, xd.y
                    )));
                }
                Ok(Vector2::new(b.x / b.z, b.y / b.z))
            }
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
            let d = Distortion { k1, k2, p1, p2, k3, ..Distortion::default() };
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
            let d = Distortion { k1, k2, p1, p2, k3, ..Distortion::default() };
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
                Distortion { k1: c[0], k2: c[1], p1: c[2] * 0.1, p2: c[3] * 0.1, k3: c[4], ..Distortion::default() }
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
        assert_eq!((ds.xi, ds.alpha, ds.coefficients()), (-0.2, 0.6, vec![-0.2, 0.6]));
        assert!(Distortion::from_coefficients(LensKind::DoubleSphere, &[0.1, 1.5]).is_err());
        assert!(!ds.is_zero() && Distortion::zero(LensKind::Pinhole).is_zero());
        // xi and alpha appear in the JSON of a double sphere only.
        assert!(!serde_json::to_string(&Distortion::radial(0.1, 0.0)).unwrap().contains("xi"));
        let back: Distortion = serde_json::from_str(&serde_json::to_string(&ds).unwrap()).unwrap();
        assert_eq!(back, ds);
        let e = Distortion::from_coefficients(LensKind::Equidistant, &[0.1, 0.2, 0.3, 0.4]).unwrap();
        assert_eq!(e.coefficients(), vec![0.1, 0.2, 0.3, 0.4]);
        assert_eq!([e.k1, e.k2, e.k3, e.k4], [0.1, 0.2, 0.3, 0.4]);
        assert!(Distortion::from_coefficients(LensKind::Equidistant, &[0.1, 0.2, 0.3]).is_err());
        let mut bad = e;
        bad.p1 = 0.1;
        assert!(bad.validate().is_err());
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
