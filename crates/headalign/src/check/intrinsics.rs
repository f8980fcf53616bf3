//! The test of whether the intrinsics changed ([`super`] module docs, "Intrinsics test"):
//! the refit of [`super::refit`] with the right camera's vertical focal length `fy` (a
//! scale) and principal point row `cy` free as well (5 degrees of freedom), on the same
//! matches, against the held refit.
//!
//! What a stereo pair shows: only what moves points across the epipolar lines, which run
//! along the rows of a rectified rig. The right camera's `fx` and `cx` move points along
//! the rows (a disparity change, exactly invisible to the epipolar constraint), and a
//! change common to both cameras leaves the epipolar geometry unchanged: these need depth
//! or rig motions (`calibrate`). `fy` scales the rows about `cy` (a vertical disparity
//! growing with the row), `cy` shifts them (nearly a pitch: told apart by the pitch's
//! perspective term `y^2 / f`, so its sigma is large and it correlates with the pitch).
//! Units: the focal change in percent, the principal point in pixels; their sigmas from
//! the measured noise of the held refit times the pairs' scatter ratio (`sigma^2 (J^T
//! J)^-1`, [`super`] module docs, "Method" step 4). Jacobian: the rotation
//! columns analytic (as in [`super::refit`], with the moved `K_R`), the intrinsic columns by
//! central differences of `F` (steps 1e-6 in the scale, 1e-3 px in `cy`: `F` is smooth
//! and O(1) in these units).

use headalign_geometry::essential::{signed_sampson, signed_sampson_gradient};
use headalign_geometry::lm::minimise;
use headalign_geometry::so3;
use nalgebra::{Matrix3, Rotation3, SMatrix, SVector, Vector2, Vector3};
use serde::Serialize;

use super::refit::{EpipolarModel, Match};

/// A change with its standard deviation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Estimate {
    /// The change.
    pub value: f64,
    /// Its standard deviation.
    pub sigma: f64,
}

impl Estimate {
    /// `|value| / sigma` (infinite for a zero sigma and a non-zero value).
    pub fn z(&self) -> f64 {
        if self.sigma > 0.0 {
            self.value.abs() / self.sigma
        } else if self.value == 0.0 {
            0.0
        } else {
            f64::INFINITY
        }
    }
}

/// The intrinsics test's result.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct IntrinsicsChange {
    /// Change of the right camera's `fy`, percent.
    pub fy_pct: Estimate,
    /// Change of the right camera's `cy`, pixels.
    pub cy_px: Estimate,
    /// The fall of the squared Sampson distances when they are freed, over the noise
    /// variance: chi-squared with 2 degrees of freedom when nothing changed.
    pub chi2: f64,
    /// Any of the three changes beyond the significance (in sigmas) of the options.
    pub significant: bool,
}

/// The state of the free refit: `dR` and `[scale, dcy]` of the right camera's `fy`, `cy`.
#[derive(Debug, Clone, Copy)]
struct State {
    dr: Rotation3<f64>,
    k: Vector2<f64>,
}

/// `K_R` moved by `k = [scale, dcy]`: `fy` times `1 + scale`, `cy + dcy`.
fn moved(kr: &Matrix3<f64>, k: &Vector2<f64>) -> Matrix3<f64> {
    let mut m = *kr;
    m[(1, 1)] *= 1.0 + k.x;
    m[(1, 2)] += k.y;
    m
}

fn fundamental(model: &EpipolarModel, s: &State) -> Option<Matrix3<f64>> {
    let kr = moved(&model.kr, &s.k);
    Some(kr.try_inverse()?.transpose() * s.dr.matrix() * model.essential * model.kl_inv)
}

/// `(J^T J, J^T r)` of the free refit at `s` over `matches[selected]`.
fn normal(
    model: &EpipolarModel,
    s: &State,
    matches: &[Match],
    selected: &[usize],
) -> Option<(SMatrix<f64, 5, 5>, SVector<f64, 5>)> {
    let f = fundamental(model, s)?;
    let kr = moved(&model.kr, &s.k);
    let kr_inv_t = kr.try_inverse()?.transpose();
    let mut df: [Matrix3<f64>; 5] = [Matrix3::zeros(); 5];
    for (k, d) in df.iter_mut().enumerate().take(3) {
        *d = kr_inv_t * so3::skew(&Vector3::ith(k, 1.0)) * kr.transpose() * f;
    }
    for k in 0..2 {
        let h = if k == 0 { 1e-6 } else { 1e-3 };
        let step = |sign: f64| State { k: s.k + Vector2::ith(k, sign * h), ..*s };
        df[3 + k] = (fundamental(model, &step(1.0))? - fundamental(model, &step(-1.0))?) / (2.0 * h);
    }
    let mut jtj = SMatrix::<f64, 5, 5>::zeros();
    let mut jtr = SVector::<f64, 5>::zeros();
    for &i in selected {
        let Some((r, g)) = signed_sampson_gradient(&f, &matches[i].0, &matches[i].1) else { continue };
        let row = SVector::<f64, 5>::from_fn(|k, _| (0..9).map(|e| g[e] * df[k][(e / 3, e % 3)]).sum());
        jtj += row * row.transpose();
        jtr += row * r;
    }
    (jtj.iter().chain(jtr.iter()).all(|v| v.is_finite())).then_some((jtj, jtr))
}

/// The free refit from the held one (`dr`, cost `held_cost`) on `matches[selected]`, with
/// the noise `sigma_px`; `significance` in sigmas. `None` when the normal matrix is
/// singular.
pub fn intrinsics_change(
    model: &EpipolarModel,
    matches: &[Match],
    selected: &[usize],
    dr: &Rotation3<f64>,
    held_cost: f64,
    sigma_px: f64,
    significance: f64,
) -> Option<IntrinsicsChange> {
    let cost = |s: &State| -> f64 {
        let Some(f) = fundamental(model, s) else { return f64::INFINITY };
        selected.iter().map(|&i| signed_sampson(&f, &matches[i].0, &matches[i].1).powi(2)).sum()
    };
    let start = State { dr: *dr, k: Vector2::zeros() };
    let retract = |s: &State, d: &SVector<f64, 5>| {
        Some(State {
            dr: so3::exp(&Vector3::new(d[0], d[1], d[2])) * s.dr,
            k: s.k + Vector2::new(d[3], d[4]),
        })
    };
    let (s, c) = minimise(start, held_cost, 100, |s| normal(model, s, matches, selected), retract, cost);
    let (jtj, _) = normal(model, &s, matches, selected)?;
    let cov = jtj.try_inverse()? * (sigma_px * sigma_px);
    let sd = |i: usize| cov[(i, i)].max(0.0).sqrt();
    let fy_pct = Estimate { value: 100.0 * s.k.x, sigma: 100.0 * sd(3) };
    let cy_px = Estimate { value: s.k.y, sigma: sd(4) };
    let significant = [fy_pct, cy_px].iter().any(|e| e.z() >= significance);
    Some(IntrinsicsChange {
        fy_pct,
        cy_px,
        chi2: (held_cost - c).max(0.0) / (sigma_px * sigma_px),
        significant,
    })
}
