//! The maximum-likelihood refit of the rig rotation with the intrinsics and the lens held
//! (3 degrees of freedom), its robust selection and its covariance ([`super`] module docs,
//! "Method").
//!
//! The model: `R_now = dR R_given`, `T_now = dR T_given` (the right camera turned about its
//! own centre), so the essential matrix is `E(dR) = [dR T]x dR R = dR E_given` and the
//! fundamental matrix of the undistorted pixels `F(dR) = K_R^-T dR E_given K_L^-1`. The
//! residual of a match is its signed Sampson distance under `F` (pixels: the first-order
//! geometric distance of the match to the epipolar constraint, Hartley & Zisserman 2nd ed.
//! section 11.4.3). The state is `dR`, moved by `dR <- exp(delta) dR` (`delta` about the
//! right camera's x, y, z axes); `d F / d delta_k = K_R^-T [e_k]x K_R^T F` (analytic),
//! chained with the Sampson distance's gradient in `F`.
//!
//! Outliers: RANSAC with a 3-match minimal solver ([`RotationChange`]: the epipolar
//! constraint `x_R^T exp(w) E x_L = 0` linearised in `w` at the current rotation, three
//! Newton steps) and the LM refit as its local optimisation; then the selection is made
//! by the measured noise ([`select_by_noise`]: `sigma` from the median absolute residual, the
//! matches within `k sigma` refitted, until the selection is stable).
//!
//! Pitfalls: `[T]x` makes `E` of rank 2, so a rotation about the baseline and one about an
//! axis across it are seen through different matches' geometry; every axis is observable
//! only when the matches spread over the image (the sigmas say how well).

use headalign_geometry::essential::{signed_sampson, signed_sampson_gradient};
use headalign_geometry::lm::minimise;
use headalign_geometry::ransac::Estimator;
use headalign_geometry::so3;
use nalgebra::{Matrix3, Point2, Rotation3, SMatrix, SVector, Vector3};

/// One match: undistorted pinhole pixels `(left, right)`.
pub type Match = (Point2<f64>, Point2<f64>);

/// The given rig's epipolar geometry in undistorted pixels: `F(dR) = K_R^-T dR E K_L^-1`.
#[derive(Debug, Clone, Copy)]
pub struct EpipolarModel {
    /// `E = [T]x R` of the given calibration.
    pub essential: Matrix3<f64>,
    /// `K_L^-1` of the given left camera.
    pub kl_inv: Matrix3<f64>,
    /// `K_R^-1` of the given right camera.
    pub kr_inv: Matrix3<f64>,
    /// `K_R` of the given right camera.
    pub kr: Matrix3<f64>,
}

impl EpipolarModel {
    /// `F(dR)` (not normalised; the Sampson distance does not depend on `F`'s scale).
    pub fn fundamental(&self, dr: &Rotation3<f64>) -> Matrix3<f64> {
        self.kr_inv.transpose() * dr.matrix() * self.essential * self.kl_inv
    }

    /// The signed Sampson distances (pixels) of `matches[selected]` under `dR`.
    pub fn residuals(&self, dr: &Rotation3<f64>, matches: &[Match], selected: &[usize]) -> Vec<f64> {
        let f = self.fundamental(dr);
        selected.iter().map(|&i| signed_sampson(&f, &matches[i].0, &matches[i].1)).collect()
    }

    /// The Jacobian rows (1 x 3 each, in `delta` of `dR <- exp(delta) dR`) and residuals of
    /// `matches[selected]` at `dR`; a match whose Sampson distance is undefined is left out.
    pub fn jacobian(
        &self,
        dr: &Rotation3<f64>,
        matches: &[Match],
        selected: &[usize],
    ) -> Vec<(f64, Vector3<f64>)> {
        let f = self.fundamental(dr);
        let df: [Matrix3<f64>; 3] = std::array::from_fn(|k| {
            self.kr_inv.transpose() * so3::skew(&Vector3::ith(k, 1.0)) * self.kr.transpose() * f
        });
        selected
            .iter()
            .filter_map(|&i| {
                let (s, g) = signed_sampson_gradient(&f, &matches[i].0, &matches[i].1)?;
                let row = Vector3::from_fn(|k, _| (0..9).map(|e| g[e] * df[k][(e / 3, e % 3)]).sum());
                Some((s, row))
            })
            .collect()
    }
}

/// A refitted rotation change.
#[derive(Debug, Clone, Copy)]
pub struct RotationFit {
    /// `dR`.
    pub dr: Rotation3<f64>,
    /// Sum of squared Sampson distances of the selection, pixels squared.
    pub cost: f64,
    /// `J^T J` at `dR` (in `delta`), pixels squared per radian squared.
    pub jtj: Matrix3<f64>,
}

/// The least-squares `dR` on `matches[selected]` from `start` (the geometry crate's
/// Levenberg-Marquardt, [`minimise`]); `None` with fewer than 3 usable matches.
pub fn refit_rotation(
    model: &EpipolarModel,
    matches: &[Match],
    selected: &[usize],
    start: &Rotation3<f64>,
) -> Option<RotationFit> {
    if selected.len() < 3 {
        return None;
    }
    let cost =
        |dr: &Rotation3<f64>| model.residuals(dr, matches, selected).iter().map(|r| r * r).sum::<f64>();
    let normal = |dr: &Rotation3<f64>| -> Option<(SMatrix<f64, 3, 3>, SVector<f64, 3>)> {
        let rows = model.jacobian(dr, matches, selected);
        let mut jtj = Matrix3::zeros();
        let mut jtr = Vector3::zeros();
        for (s, j) in &rows {
            jtj += j * j.transpose();
            jtr += j * *s;
        }
        (jtj.iter().chain(jtr.iter()).all(|v| v.is_finite())).then_some((jtj, jtr))
    };
    let c0 = cost(start);
    if !c0.is_finite() {
        return None;
    }
    let (dr, c) = minimise(*start, c0, 100, normal, |dr, d| Some(so3::exp(d) * dr), cost);
    let (jtj, _) = normal(&dr)?;
    Some(RotationFit { dr, cost: c, jtj })
}

/// The largest Newton step of [`minimal_rotation`], radians (0.2 rad = 11 deg: a camera
/// turned farther is not a calibration to check but one to redo; such samples are refused).
pub const MAX_MINIMAL_STEP_RAD: f64 = 0.2;

/// The rotation change explaining three (or more) matches exactly in the algebraic sense:
/// `x_R^T exp(w) E x_L = 0` linearised in `w` at the current rotation (`(a x x_R) . w =
/// -x_R^T a` with `a = dR E x_L`, normalised coordinates), three Newton steps from the
/// identity. Exact for the changes a check meets (a few degrees); `None` for a degenerate
/// sample.
pub fn minimal_rotation(model: &EpipolarModel, sample: &[Match]) -> Option<Rotation3<f64>> {
    let mut dr = Rotation3::<f64>::identity();
    for _ in 0..3 {
        let mut ata = Matrix3::<f64>::zeros();
        let mut atb = Vector3::<f64>::zeros();
        for (l, r) in sample {
            let xl = model.kl_inv * Vector3::new(l.x, l.y, 1.0);
            let xr = model.kr_inv * Vector3::new(r.x, r.y, 1.0);
            let a: Vector3<f64> = dr.matrix() * model.essential * xl;
            let row = a.cross(&xr);
            ata += row * row.transpose();
            atb -= row * xr.dot(&a);
        }
        let w = ata.try_inverse()? * atb;
        if !w.iter().all(|v| v.is_finite()) || w.norm() > MAX_MINIMAL_STEP_RAD {
            return None;
        }
        dr = so3::exp(&w) * dr;
    }
    Some(dr)
}

/// RANSAC's view of the rotation change ([`headalign_geometry::ransac::ransac`]): minimal
/// samples of 3 matches ([`minimal_rotation`]), the LM refit as the local optimisation,
/// the absolute Sampson distance as the residual (pixels).
pub struct RotationChange<'a> {
    /// The given rig.
    pub model: &'a EpipolarModel,
}

impl Estimator for RotationChange<'_> {
    type Datum = Match;
    type Model = Rotation3<f64>;

    fn sample_size(&self) -> usize {
        3
    }

    fn fit_minimal(&self, data: &[Match], sample: &[usize]) -> Vec<Rotation3<f64>> {
        let s: Vec<Match> = sample.iter().map(|&i| data[i]).collect();
        minimal_rotation(self.model, &s).into_iter().collect()
    }

    fn fit_inliers(&self, data: &[Match], inliers: &[usize]) -> Option<Rotation3<f64>> {
        let start = minimal_rotation(self.model, &inliers.iter().map(|&i| data[i]).collect::<Vec<_>>())
            .unwrap_or_else(Rotation3::identity);
        refit_rotation(self.model, data, inliers, &start).map(|f| f.dr)
    }

    fn residual(&self, model: &Rotation3<f64>, datum: &Match) -> f64 {
        signed_sampson(&self.model.fundamental(model), &datum.0, &datum.1).abs()
    }
}

/// The robust refit: the rotation, the matches it keeps, the measured noise and the
/// covariance of the rotation change.
#[derive(Debug, Clone)]
pub struct RobustFit {
    /// The refit on `selected`.
    pub fit: RotationFit,
    /// Indices of the matches kept (within `k sigma` of the refit), increasing.
    pub selected: Vec<usize>,
    /// The measured noise of a Sampson distance, pixels ([`noise_sigma`]).
    pub sigma_px: f64,
    /// Covariance of `w = log(dR)` (pitch, yaw, roll), radians squared.
    pub covariance: Matrix3<f64>,
}

/// Re-selection rounds of [`select_by_noise`] at most.
pub const SELECTION_ROUNDS: usize = 10;

/// From `start` (RANSAC's rotation and inliers): `sigma` measured on the selection, the
/// matches within `k sigma` selected and refitted, until the selection is stable (at most
/// [`SELECTION_ROUNDS`] rounds). `sigma` is `1.4826 median |r|` of RANSAC's inliers at
/// first, then [`noise_sigma`] of the refit. `None` when fewer than `min_matches` remain.
pub fn select_by_noise(
    model: &EpipolarModel,
    matches: &[Match],
    start: (Rotation3<f64>, Vec<usize>),
    k: f64,
    min_matches: usize,
) -> Option<RobustFit> {
    let (mut dr, mut selected) = start;
    let all: Vec<usize> = (0..matches.len()).collect();
    let mut abs_r: Vec<f64> = model.residuals(&dr, matches, &selected).iter().map(|r| r.abs()).collect();
    let mut sigma = 1.4826 * median(&mut abs_r)?;
    let mut fit = None;
    for _ in 0..SELECTION_ROUNDS {
        let r = model.residuals(&dr, matches, &all);
        let next: Vec<usize> = all.iter().copied().filter(|&i| r[i].abs() <= k * sigma).collect();
        if next.len() < min_matches.max(4) {
            return None;
        }
        let stable = fit.is_some() && next == selected;
        selected = next;
        if stable {
            break;
        }
        let f = refit_rotation(model, matches, &selected, &dr)?;
        dr = f.dr;
        sigma = noise_sigma(f.cost, selected.len(), 3, k)?;
        fit = Some(f);
    }
    let fit = fit?;
    let jl_inv = left_jacobian_inverse(&so3::log(&fit.dr));
    let covariance = jl_inv * fit.jtj.try_inverse()? * jl_inv.transpose() * (sigma * sigma);
    Some(RobustFit { fit, selected, sigma_px: sigma, covariance })
}

/// The noise sigma of the residuals of a least-squares fit of `params` parameters to `n`
/// residuals selected within `k` sigmas: `sqrt(cost / (n - params) / c(k))`, where `c(k)`
/// ([`truncated_normal_variance`]) undoes the truncation of the Gaussian's tails at `k`
/// sigmas. `None` when `n <= params` or the cost is not finite.
pub fn noise_sigma(cost: f64, n: usize, params: usize, k: f64) -> Option<f64> {
    let dof = n.checked_sub(params).filter(|&d| d > 0)? as f64;
    let s = (cost / dof / truncated_normal_variance(k)).sqrt();
    s.is_finite().then_some(s)
}

/// The variance of a standard normal variable truncated to `|x| <= k`: `1 - 2 k phi(k) /
/// (2 Phi(k) - 1)` (Simpson's rule for the integral of `phi`, 2000 intervals: 1e-12 for
/// `k` up to 10). 1 for `k` of infinity; 0.9733 at `k = 3`.
pub fn truncated_normal_variance(k: f64) -> f64 {
    if !k.is_finite() {
        return 1.0;
    }
    let phi = |x: f64| (-0.5 * x * x).exp() / (2.0 * std::f64::consts::PI).sqrt();
    let n = 2000;
    let h = k / n as f64;
    let sum: f64 = (0..=n)
        .map(|i| {
            let w = if i == 0 || i == n {
                1.0
            } else if i % 2 == 1 {
                4.0
            } else {
                2.0
            };
            w * phi(i as f64 * h)
        })
        .sum();
    let mass = 2.0 * sum * h / 3.0; // 2 Phi(k) - 1
    if mass <= 0.0 { 1.0 } else { 1.0 - 2.0 * k * phi(k) / mass }
}

/// The inverse of SO(3)'s left Jacobian at `w`: `exp(delta) exp(w) = exp(w + J_l^-1(w)
/// delta + O(delta^2))`, so a covariance in `delta` maps to one in `w` by it.
/// `J_l^-1 = I - [w]x / 2 + (1/theta^2 - (1 + cos theta) / (2 theta sin theta)) [w]x^2`.
pub fn left_jacobian_inverse(w: &Vector3<f64>) -> Matrix3<f64> {
    let t = w.norm();
    let k = so3::skew(w);
    let c = if t < 1e-4 {
        1.0 / 12.0 + t * t / 720.0
    } else {
        1.0 / (t * t) - (1.0 + t.cos()) / (2.0 * t * t.sin())
    };
    Matrix3::identity() - k * 0.5 + k * k * c
}

/// The median of `v` (reordered); `None` when empty.
pub fn median(v: &mut [f64]) -> Option<f64> {
    percentile(v, 0.5)
}

/// The `q`-quantile of `v` (reordered; the nearest rank below); `None` when empty.
pub fn percentile(v: &mut [f64], q: f64) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let i = ((v.len() - 1) as f64 * q.clamp(0.0, 1.0)).round() as usize;
    v.get(i).copied()
}
