//! Lens distortion of normalised image coordinates `x = K^-1 p`, in the two models users'
//! tools name ([`LensKind`]):
//!
//! - **radial-tangential** (OpenCV `plumb_bob`, ROS `plumb_bob`, Kalibr `pinhole-radtan`):
//!
//!   ```text
//!   r^2 = x^2 + y^2
//!   x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
//!   y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y
//!   ```
//!
//! - **equidistant** (OpenCV `fisheye`, ROS `equidistant`, Kalibr `pinhole-equi`):
//!
//!   ```text
//!   r = |x|,  theta = atan(r)
//!   theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
//!   x_d = (theta_d / r) x
//!   ```
//!
//! Degrees of freedom: radial-tangential 5 (`k1 k2 p1 p2 k3`, OpenCV's order of `D`),
//! equidistant 4 (`k1 k2 k3 k4`, OpenCV fisheye's `D`); which of them a bundle adjustment
//! estimates is [`DistortionTerms`]. Undistortion inverts the map by Newton's method with
//! the analytic 2x2 Jacobian (radial-tangential: at most 30 steps, stops below 1e-14 in
//! normalised units; equidistant: Newton on `theta` alone); where the map folds over
//! (beyond the radius at which a strong barrel model turns back) it is an error, never a
//! wrong point. [`Distortion::undistort_pixel`] maps a distorted pixel to the pixel an
//! ideal pinhole camera with the same `K` would see, which is how headalign uses a known
//! lens model: observations are undistorted once, everything after is pinhole.
//! [`Distortion::distort_with_jacobians`] also gives the derivatives with respect to the
//! coefficients, for the bundle adjustment.
//!
//! Units: coefficients are dimensionless (normalised coordinates; the equidistant ones
//! multiply powers of an angle in radians); pixels outside.
//!
//! Pitfalls: the coefficients belong to the `K` they were estimated with; undistorting with
//! a different `K` is a different lens model. The equidistant map is defined for rays in
//! front of the camera only (`theta < 90 deg` through a pinhole `x`), and its Jacobian
//! at the centre is the limit `r -> 0` (taken below `r = 1e-8`). The two models' `k1` are
//! different numbers for the same lens: `k1` of the equidistant model includes the
//! `-1/3 theta^2` of `atan`.

use nalgebra::{Matrix2, Point2, SMatrix, Vector2};
use serde::{Deserialize, Serialize};

use crate::camera::Intrinsics;
use crate::{GeometryError, Result};

/// The lens model a [`Distortion`]'s coefficients belong to.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LensKind {
    /// Radial-tangential: OpenCV / ROS `plumb_bob`, Kalibr `radtan` (the default; all
    /// coefficients zero is the pinhole).
    #[default]
    RadialTangential,
    /// Equidistant fisheye: OpenCV `fisheye`, ROS `equidistant`, Kalibr `equidistant`.
    Equidistant,
}

impl LensKind {
    /// ROS `sensor_msgs/CameraInfo.distortion_model`.
    pub fn ros_name(self) -> &'static str {
        match self {
            LensKind::RadialTangential => "plumb_bob",
            LensKind::Equidistant => "equidistant",
        }
    }

    /// Kalibr camchain `distortion_model`.
    pub fn kalibr_name(self) -> &'static str {
        match self {
            LensKind::RadialTangential => "radtan",
            LensKind::Equidistant => "equidistant",
        }
    }

    /// The model named by any of the usual spellings (`radtan`, `radial-tangential`,
    /// `plumb_bob`, `pinhole-radtan`; `equidistant`, `equi`, `fisheye`, `pinhole-equi`,
    /// `kannala_brandt`), case-insensitive.
    pub fn parse(name: &str) -> Option<Self> {
        match name.trim().to_ascii_lowercase().replace('_', "-").as_str() {
            "radtan" | "radial-tangential" | "plumb-bob" | "pinhole-radtan" | "rational-polynomial" => {
                Some(LensKind::RadialTangential)
            }
            "equidistant" | "equi" | "fisheye" | "pinhole-equi" | "kannala-brandt" => {
                Some(LensKind::Equidistant)
            }
            _ => None,
        }
    }

    /// Names of the coefficients in the order of [`Distortion::coefficients`].
    pub fn coefficient_names(self) -> &'static [&'static str] {
        match self {
            LensKind::RadialTangential => &["k1", "k2", "p1", "p2", "k3"],
            LensKind::Equidistant => &["k1", "k2", "k3", "k4"],
        }
    }
}

/// Lens distortion coefficients of one camera in the model `kind` (all zero in the
/// radial-tangential model is the pinhole; in the equidistant model it is the ideal
/// equidistant lens `theta_d = theta`, not a pinhole).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Distortion {
    /// The model (default radial-tangential; older files without it are radial-tangential).
    #[serde(default)]
    pub kind: LensKind,
    /// Radial: `r^2` (radial-tangential) or `theta^3` (equidistant).
    pub k1: f64,
    /// Radial: `r^4` or `theta^5`.
    pub k2: f64,
    /// Tangential (radial-tangential only; zero in the equidistant model).
    pub p1: f64,
    /// Tangential (radial-tangential only; zero in the equidistant model).
    pub p2: f64,
    /// Radial: `r^6` or `theta^7`.
    pub k3: f64,
    /// Radial `theta^9` (equidistant only; zero in the radial-tangential model).
    #[serde(default)]
    pub k4: f64,
}

/// Which coefficients a bundle adjustment estimates (the others are held at their
/// values, usually zero).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum DistortionTerms {
    /// `k1, k2` (either model; the default: the tangential terms are nearly degenerate with
    /// the principal point unless the data are strong).
    Radial2,
    /// `k1, k2, p1, p2` (radial-tangential: Kalibr's `radtan`) or `k1..k4` (equidistant:
    /// Kalibr's `equidistant`).
    Full4,
    /// `k1, k2, p1, p2, k3` (radial-tangential; equidistant as [`Self::Full4`]).
    Full5,
}

impl DistortionTerms {
    /// The estimated coefficients' slots of [`Distortion::slots`] in a `kind` lens.
    pub fn slots(self, kind: LensKind) -> &'static [usize] {
        match (self, kind) {
            (DistortionTerms::Radial2, _) => &[0, 1],
            (DistortionTerms::Full4, LensKind::RadialTangential) => &[0, 1, 2, 3],
            (DistortionTerms::Full5, LensKind::RadialTangential) => &[0, 1, 2, 3, 4],
            (_, LensKind::Equidistant) => &[0, 1, 4, 5],
        }
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

/// Newton iterations of [`Distortion::undistort`].
const MAX_STEPS: usize = 30;

/// Below this normalised radius the equidistant map is the identity to first order and its
/// Jacobian the limit at the centre.
const EQUI_CENTRE: f64 = 1e-8;

impl Distortion {
    /// Radial-tangential, radial terms only.
    pub fn radial(k1: f64, k2: f64) -> Self {
        Self { k1, k2, ..Self::default() }
    }

    /// Equidistant with `k1..k4`.
    pub fn equidistant(k: [f64; 4]) -> Self {
        Self { kind: LensKind::Equidistant, k1: k[0], k2: k[1], k3: k[2], k4: k[3], ..Self::default() }
    }

    /// All coefficients zero in the model `kind`.
    pub fn zero(kind: LensKind) -> Self {
        Self { kind, ..Self::default() }
    }

    /// From OpenCV's `D` vector (4, 5 or more entries: `k1 k2 p1 p2 [k3 ...]`; entries
    /// beyond `k3` must be zero, the rational model is not supported).
    pub fn from_opencv(d: &[f64]) -> Result<Self> {
        if d.len() < 4 {
            return Err(GeometryError::InvalidOption(format!(
                "a distortion vector needs at least 4 coefficients (k1 k2 p1 p2 [k3]), got {}",
                d.len()
            )));
        }
        if d.iter().skip(5).any(|&v| v != 0.0) {
            return Err(GeometryError::InvalidOption(
                "distortion coefficients beyond k3 (OpenCV's rational model) are not supported".into(),
            ));
        }
        let out = Self {
            k1: d[0],
            k2: d[1],
            p1: d[2],
            p2: d[3],
            k3: d.get(4).copied().unwrap_or(0.0),
            k4: 0.0,
            kind: LensKind::RadialTangential,
        };
        out.validate()?;
        Ok(out)
    }

    /// From a model and its coefficient vector in the order of
    /// [`LensKind::coefficient_names`] (radial-tangential: 4 or 5 entries; equidistant:
    /// exactly 4, OpenCV fisheye's `D`).
    pub fn from_coefficients(kind: LensKind, d: &[f64]) -> Result<Self> {
        match kind {
            LensKind::RadialTangential => Self::from_opencv(d),
            LensKind::Equidistant => {
                let [k1, k2, k3, k4] = <[f64; 4]>::try_from(d).map_err(|_| {
                    GeometryError::InvalidOption(format!(
                        "an equidistant (fisheye) lens has 4 coefficients k1 k2 k3 k4, got {}",
                        d.len()
                    ))
                })?;
                let out = Self::equidistant([k1, k2, k3, k4]);
                out.validate()?;
                Ok(out)
            }
        }
    }

    /// As OpenCV's 5-vector `k1 k2 p1 p2 k3` (radial-tangential; an equidistant lens gives
    /// its `k1 k2 0 0 k3`, which is not its model: use [`Self::coefficients`]).
    pub fn to_opencv(&self) -> [f64; 5] {
        [self.k1, self.k2, self.p1, self.p2, self.k3]
    }

    /// The model's coefficient vector, in the order of [`LensKind::coefficient_names`]
    /// (OpenCV's `D` of `plumb_bob` or of `fisheye`).
    pub fn coefficients(&self) -> Vec<f64> {
        match self.kind {
            LensKind::RadialTangential => self.to_opencv().to_vec(),
            LensKind::Equidistant => vec![self.k1, self.k2, self.k3, self.k4],
        }
    }

    /// All six coefficient slots `k1 k2 p1 p2 k3 k4` (the bundle adjustment's indices).
    pub fn slots(&self) -> [f64; 6] {
        [self.k1, self.k2, self.p1, self.p2, self.k3, self.k4]
    }

    /// Mutable access to slot `i` of [`Self::slots`] (`None` beyond 5).
    pub fn slot_mut(&mut self, i: usize) -> Option<&mut f64> {
        match i {
            0 => Some(&mut self.k1),
            1 => Some(&mut self.k2),
            2 => Some(&mut self.p1),
            3 => Some(&mut self.p2),
            4 => Some(&mut self.k3),
            5 => Some(&mut self.k4),
            _ => None,
        }
    }

    /// The slot of the model's `i`-th coefficient (order of [`Self::coefficients`]).
    pub fn slot_of(kind: LensKind, i: usize) -> Option<usize> {
        let map: &[usize] = match kind {
            LensKind::RadialTangential => &[0, 1, 2, 3, 4],
            LensKind::Equidistant => &[0, 1, 4, 5],
        };
        map.get(i).copied()
    }

    /// Every coefficient finite, and no coefficient set that the model does not have.
    pub fn validate(&self) -> Result<()> {
        if !self.slots().iter().all(|v| v.is_finite()) {
            return Err(GeometryError::InvalidOption("distortion coefficients must be finite".into()));
        }
        let foreign = match self.kind {
            LensKind::RadialTangential => self.k4 != 0.0,
            LensKind::Equidistant => self.p1 != 0.0 || self.p2 != 0.0,
        };
        if foreign {
            return Err(GeometryError::InvalidOption(format!(
                "a {:?} lens has no coefficient {}",
                self.kind,
                if self.kind == LensKind::Equidistant { "p1/p2" } else { "k4" }
            )));
        }
        Ok(())
    }

    /// True for the pinhole (a radial-tangential lens with every coefficient zero; an
    /// equidistant lens never is one).
    pub fn is_zero(&self) -> bool {
        self.kind == LensKind::RadialTangential && self.slots().iter().all(|&v| v == 0.0)
    }

    /// Distorted normalised coordinates and the Jacobian `d x_d / d x`.
    pub fn distort_with_jacobian(&self, x: &Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>) {
        match self.kind {
            LensKind::RadialTangential => self.radtan(x),
            LensKind::Equidistant => self.equidistant_map(x).0,
        }
    }

    /// Distorted normalised coordinates, `d x_d / d x`, and `d x_d / d slot` for the six
    /// slots of [`Self::slots`] (a slot the model does not have has a zero column).
    pub fn distort_with_jacobians(
        &self,
        x: &Vector2<f64>,
    ) -> (Vector2<f64>, Matrix2<f64>, SMatrix<f64, 2, 6>) {
        match self.kind {
            LensKind::RadialTangential => {
                let (xd, j) = self.radtan(x);
                let (u, v) = (x.x, x.y);
                let r2 = u * u + v * v;
                let mut jc = SMatrix::<f64, 2, 6>::zeros();
                jc.set_column(0, &(x * r2));
                jc.set_column(1, &(x * (r2 * r2)));
                jc.set_column(2, &Vector2::new(2.0 * u * v, r2 + 2.0 * v * v));
                jc.set_column(3, &Vector2::new(r2 + 2.0 * u * u, 2.0 * u * v));
                jc.set_column(4, &(x * (r2 * r2 * r2)));
                (xd, j, jc)
            }
            LensKind::Equidistant => {
                let ((xd, j), jc) = self.equidistant_map(x);
                (xd, j, jc)
            }
        }
    }

    /// The radial-tangential map and its Jacobian.
    fn radtan(&self, x: &Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>) {
        let (u, v) = (x.x, x.y);
        let r2 = u * u + v * v;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        // d radial / d r2
        let dradial = self.k1 + r2 * (2.0 * self.k2 + 3.0 * r2 * self.k3);
        let xd = u * radial + 2.0 * self.p1 * u * v + self.p2 * (r2 + 2.0 * u * u);
        let yd = v * radial + self.p1 * (r2 + 2.0 * v * v) + 2.0 * self.p2 * u * v;
        let j = Matrix2::new(
            radial + 2.0 * u * u * dradial + 2.0 * self.p1 * v + 6.0 * self.p2 * u,
            2.0 * u * v * dradial + 2.0 * self.p1 * u + 2.0 * self.p2 * v,
            2.0 * u * v * dradial + 2.0 * self.p1 * u + 2.0 * self.p2 * v,
            radial + 2.0 * v * v * dradial + 6.0 * self.p1 * v + 2.0 * self.p2 * u,
        );
        (Vector2::new(xd, yd), j)
    }

    /// `theta_d(theta)` and its derivative.
    fn theta_d(&self, theta: f64) -> (f64, f64) {
        let t2 = theta * theta;
        let poly = 1.0 + t2 * (self.k1 + t2 * (self.k2 + t2 * (self.k3 + t2 * self.k4)));
        let dpoly = 3.0 * self.k1 + t2 * (5.0 * self.k2 + t2 * (7.0 * self.k3 + t2 * 9.0 * self.k4));
        (theta * poly, 1.0 + t2 * dpoly)
    }

    /// The equidistant map, its Jacobian, and the coefficient Jacobian (slots 0, 1, 4, 5).
    fn equidistant_map(&self, x: &Vector2<f64>) -> ((Vector2<f64>, Matrix2<f64>), SMatrix<f64, 2, 6>) {
        let r = x.norm();
        let mut jc = SMatrix::<f64, 2, 6>::zeros();
        if r < EQUI_CENTRE {
            // theta_d / r -> 1 and its derivative -> 0 at the centre.
            for (slot, power) in [(0, 3), (1, 5), (4, 7), (5, 9)] {
                jc.set_column(slot, &(x * r.powi(power - 1)));
            }
            return ((*x, Matrix2::identity()), jc);
        }
        let theta = r.atan();
        let (td, dtd) = self.theta_d(theta);
        let s = td / r;
        // d s / d r = (dtd dtheta/dr r - td) / r^2, dtheta/dr = 1 / (1 + r^2).
        let ds = (dtd / (1.0 + r * r) * r - td) / (r * r);
        let n = x / r;
        let j = Matrix2::identity() * s + x * n.transpose() * ds;
        let t2 = theta * theta;
        let mut tp = theta * t2;
        for slot in [0, 1, 4, 5] {
            jc.set_column(slot, &(n * tp));
            tp *= t2;
        }
        ((x * s, j), jc)
    }

    /// Distorted normalised coordinates.
    pub fn distort(&self, x: &Vector2<f64>) -> Vector2<f64> {
        self.distort_with_jacobian(x).0
    }

    /// Undistorted normalised coordinates of distorted ones (Newton, see module docs).
    pub fn undistort(&self, xd: &Vector2<f64>) -> Result<Vector2<f64>> {
        if self.is_zero() {
            return Ok(*xd);
        }
        if !(xd.x.is_finite() && xd.y.is_finite()) {
            return Err(GeometryError::InvalidOption("non-finite point to undistort".into()));
        }
        match self.kind {
            LensKind::RadialTangential => self.undistort_radtan(xd),
            LensKind::Equidistant => self.undistort_equidistant(xd),
        }
    }

    fn undistort_radtan(&self, xd: &Vector2<f64>) -> Result<Vector2<f64>> {
        let mut x = *xd;
        for _ in 0..MAX_STEPS {
            let (f, j) = self.distort_with_jacobian(&x);
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
        let r = self.distort(&x) - xd;
        if r.norm() < 1e-9 {
            Ok(x)
        } else {
            Err(GeometryError::Numerical(format!(
                "undistortion did not converge at ({:.3}, {:.3})",
                xd.x, xd.y
            )))
        }
    }

    /// Newton on `theta_d(theta) = |x_d|` from `theta = |x_d|`, then `r = tan(theta)`.
    fn undistort_equidistant(&self, xd: &Vector2<f64>) -> Result<Vector2<f64>> {
        let rd = xd.norm();
        if rd < EQUI_CENTRE {
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
            let (td, dtd) = self.theta_d(theta);
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
        if (self.theta_d(theta).0 - rd).abs() > 1e-9 {
            return Err(GeometryError::Numerical(format!(
                "undistortion did not converge at ({:.3}, {:.3})",
                xd.x, xd.y
            )));
        }
        Ok(xd * (theta.tan() / rd))
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
            for slot in 0..6 {
                let (mut a, mut b) = (d, d);
                *a.slot_mut(slot).unwrap() += h;
                *b.slot_mut(slot).unwrap() -= h;
                let fd = (a.distort(&p) - b.distort(&p)) / (2.0 * h);
                let has = match d.kind {
                    LensKind::RadialTangential => slot != 5,
                    LensKind::Equidistant => slot != 2 && slot != 3,
                };
                if has {
                    prop_assert!((fd - jc.column(slot)).norm() < 1e-7, "slot {slot}: {fd:?} vs {:?}", jc.column(slot));
                } else {
                    prop_assert!(jc.column(slot).norm() == 0.0);
                }
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
        assert_eq!(LensKind::parse("ds"), None);
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
        assert_eq!(Distortion::from_opencv(&[0.1, 0.2, 0.0, 0.0]).unwrap(), Distortion::radial(0.1, 0.2));
        // A strong barrel lens folds over far out: an error, not a wrong point.
        let d = Distortion::radial(-0.5, 0.0);
        assert!(d.undistort(&Vector2::new(2.0, 0.0)).is_err());
        assert!(d.undistort(&Vector2::new(f64::NAN, 0.0)).is_err());
    }
}
