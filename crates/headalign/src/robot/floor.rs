//! The floor's normal of the robot stages ([`super`] module docs, "floor normal"): a unit
//! vector `n` in the left camera frame, estimated from the drives of a stage, and the
//! planarity limit for the degrees of freedom its fit leaves.
//!
//! **Model.** The robot moves on a plane: every drive is a rotation about `n` and a
//! translation perpendicular to it. A drive `cam2_from_cam1` has an out-of-plane part
//! `v(n)` (3 values: its rotation vector's components along two axes perpendicular to
//! `n`, radians, and the camera centre's displacement along `n`, baselines;
//! `propagation::out_of_plane`), zero for a planar drive. `n` is parametrised by its
//! tangent offset `a` (2 dof, radians) from the calibrated pan axis `u`,
//! `n(a) = (u + a_1 e_1 + a_2 e_2) / |...|`, with a Gaussian prior `a ~ N(0, s^2 I)`,
//! `s` = [`FLOOR_TILT_PRIOR_DEG`], and fitted on `sum_k v_k(a)^T W_k v_k(a) + |a|^2 / s^2`
//! (`W_k` the inverse of drive `k`'s out-of-plane covariance from its own motion's
//! covariance, fixed at `n = u`, so the estimate is a smooth function of the motions and
//! can be propagated by central differences) by the project's Levenberg-Marquardt
//! (`headalign_geometry::lm`, its damping policy, run to rounding: until no step lowers
//! the cost, as a fit with a numerical Jacobian needs; at most 50 linearisations). A turn
//! of angle `phi` fixes `n` through its rotation axis (to about `sigma_rot / phi` per
//! component); a straight drive fixes the component of `n` along its travel direction
//! through `t . n = 0` (to about `sigma_t / |t|`) and leaves the other to
//! the prior. Jacobian by central differences (step 1e-7 rad; `v` is smooth and O(1)).
//!
//! **Why a prior of 5 deg.** A real robot's pan axis stands 1-3 deg off its floor's
//! normal; the stages must work up to 5 deg. The prior only decides the components no
//! drive determines (a pan stage's straight drive leaves `n`'s tilt across the travel
//! direction free): those change neither the pan correction (an angle about the pan axis)
//! nor, to first order, the planarity test (a straight drive's rotation is near zero, so
//! its rotation components do not depend on `n`). A tighter prior would bias the
//! determined components of a 5 deg tilt; a looser one lets noise tilt the free ones
//! without bound (both harmless to the estimates, but the reported tilt would mean less).
//! The reported tilt's sigma then says how much of it the drives determined.
//!
//! **Degrees of freedom of the planarity test.** With `n` fitted, each drive's chi-square
//! `v_k^T C_k^-1 v_k` at the fitted `n` (`C_k` its motion's and the calibration's
//! covariance) has fewer than 3 degrees of freedom: `3 - h_k`, `h_k = tr(J_k Sigma_a
//! J_k^T W_k)` the drive's leverage in the fit (`Sigma_a` the fit's covariance; the
//! leverages of all drives plus the prior's sum to 2). The limit is then the quantile at
//! `3 - h_k` degrees of freedom with the false alarm rate the 3-dof limit `chi2_max`
//! states ([`planarity_limit`]): a pan drive (`h` about 1) is tested at about 2 dof, a
//! steering turn (four turns share `n`: `h` about 0.5) at about 2.5.
//!
//! **The prior's test.** The prior says `|a|^2 / s^2` is chi-square with 2 dof; a fit
//! beyond its quantile at the false alarm rate of the planarity limit (23 deg with the
//! point-mode default) is [`AlignError::NotPlanar`] (`FloorFit::plausible`). It is what
//! catches a pitching robot's straight drive: with exact data its best "floor" is the one
//! perpendicular to the pitch axis, 90 deg off, where the drive's own chi-square vanishes;
//! the fit's minimum, between that floor and the prior, lies far beyond the quantile
//! (a step is taken only if it lowers the cost, so the fit goes there by descent and
//! stops at that minimum or at the iteration limit, never at a jump).
//!
//! Pitfalls: the fit cannot tell a floor that is a ramp from a level one (both are
//! planes: the motion is planar either way); a robot that pitches or rolls during a drive
//! rotates about an axis that is not the same for drives of opposite turns, or, for a
//! straight drive, about an axis perpendicular to `n` that no tilt of `n` within the
//! prior absorbs, so it still fails the test. The tilt reported is `atan |a|`, and its
//! sigma is `|a|`'s along `a` (for a tilt below its sigma it is a Rayleigh-like magnitude,
//! biased up).

use headalign_geometry::lm::{LmOptions, minimise_with};
use nalgebra::{Isometry3, Matrix2, Matrix3, SMatrix, Unit, UnitQuaternion, Vector2, Vector3};
use serde::Serialize;

use super::propagation::{out_of_plane, perpendicular_basis};
use crate::error::AlignError;

/// Standard deviation of the prior on the pan axis' tilt from the floor normal (each
/// tangent component), degrees (module docs, "why a prior of 5 deg").
pub const FLOOR_TILT_PRIOR_DEG: f64 = 5.0;

/// Linearisations of the fit at most: it converges in a few (`v` is nearly linear in `a`
/// for tilts of a few degrees; the remaining ones reach rounding); a fit that needs many
/// (a pitching robot's straight drive pulls the normal towards its pitch axis, 90 deg
/// away) ends far out and fails [`FloorFit::plausible`].
const FIT_ITERATIONS: usize = 50;

/// The floor's normal estimated from a stage's drives (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FloorNormal {
    /// Angle of the calibrated pan axis from the estimated floor normal, degrees.
    pub pan_tilt_deg: f64,
    /// Its standard deviation (the fit's covariance along the tilt; module docs),
    /// degrees.
    pub sigma_pan_tilt_deg: f64,
    /// The floor normal, unit, in the left camera frame of the stage's first drive
    /// (pointing up, like the pan axis).
    pub normal: [f64; 3],
    /// Degrees of freedom the fit took from the drives (sum of their leverages, at most
    /// 2; the rest is the prior's).
    pub fitted_dof: f64,
    /// The prior's chi-square at the fit, `|a|^2 / s^2` (2 dof; module docs, "the
    /// prior's test").
    pub prior_chi2: f64,
}

/// The fit of [`fit_floor_normal`].
#[derive(Debug, Clone)]
pub(super) struct FloorFit {
    /// The estimated normal (unit), same frame as the drives.
    pub(super) n: Vector3<f64>,
    /// A basis perpendicular to `n` (the pan axis' basis moved with it).
    pub(super) basis: [Vector3<f64>; 2],
    /// Each drive's leverage `h_k` (module docs).
    pub(super) leverage: Vec<f64>,
    /// The report.
    pub(super) report: FloorNormal,
}

/// The normal at tangent offset `a` from `up` and the perpendicular basis moved with it.
fn normal_at(
    up: &Vector3<f64>,
    e: &[Vector3<f64>; 2],
    a: &Vector2<f64>,
) -> (Vector3<f64>, [Vector3<f64>; 2]) {
    let n = (up + e[0] * a.x + e[1] * a.y).normalize();
    let q = UnitQuaternion::rotation_between(up, &n).unwrap_or_else(UnitQuaternion::identity);
    (n, [q * e[0], q * e[1]])
}

/// Weights `W_k` of the fit: the inverses of the drives' out-of-plane covariances
/// (`covs`, at the pan axis); `None` for a covariance that cannot be inverted.
pub(super) fn floor_weights(covs: &[Matrix3<f64>]) -> Option<Vec<Matrix3<f64>>> {
    covs.iter().map(|c| (c + Matrix3::identity() * FLOOR_WEIGHT_FLOOR).try_inverse()).collect()
}

/// Variance floor of the fit's weights (radians squared / baselines squared), as the
/// planarity test's: rounding of noise-free data.
const FLOOR_WEIGHT_FLOOR: f64 = 1e-12;

/// Fit the floor normal to drives `motions` (`cam2_from_cam1`, same camera frame) with
/// weights `weights` (module docs), starting at and regularised towards `up` (the
/// calibrated pan axis, unit). `None` when the normal equations are singular.
pub(super) fn fit_floor_normal(
    up: &Vector3<f64>,
    motions: &[Isometry3<f64>],
    weights: &[Matrix3<f64>],
) -> Option<FloorFit> {
    let e = perpendicular_basis(up);
    let prior_w = 1.0 / FLOOR_TILT_PRIOR_DEG.to_radians().powi(2);
    let residuals = |a: &Vector2<f64>| -> Vec<Vector3<f64>> {
        let (n, b) = normal_at(up, &e, a);
        motions.iter().map(|m| out_of_plane(m, &n, &b)).collect()
    };
    let jacobians = |a: &Vector2<f64>| -> Vec<SMatrix<f64, 3, 2>> {
        let h = 1e-7;
        let mut j = vec![SMatrix::<f64, 3, 2>::zeros(); motions.len()];
        for p in 0..2 {
            let mut d = Vector2::zeros();
            d[p] = h;
            let plus = residuals(&(a + d));
            let minus = residuals(&(a - d));
            for (k, jk) in j.iter_mut().enumerate() {
                jk.set_column(p, &((plus[k] - minus[k]) / (2.0 * h)));
            }
        }
        j
    };
    let normal_matrix = |j: &[SMatrix<f64, 3, 2>]| -> Matrix2<f64> {
        j.iter().zip(weights).map(|(jk, w)| jk.transpose() * w * jk).sum::<Matrix2<f64>>()
            + Matrix2::identity() * prior_w
    };
    let cost = |a: &Vector2<f64>| -> f64 {
        let r = residuals(a);
        r.iter().zip(weights).map(|(rk, w)| (rk.transpose() * w * rk)[(0, 0)]).sum::<f64>()
            + a.norm_squared() * prior_w
    };
    let normal_equations = |a: &Vector2<f64>| -> Option<(Matrix2<f64>, Vector2<f64>)> {
        let r = residuals(a);
        let j = jacobians(a);
        let g: Vector2<f64> =
            j.iter().zip(weights).zip(&r).map(|((jk, w), rk)| jk.transpose() * w * rk).sum::<Vector2<f64>>()
                + a * prior_w;
        Some((normal_matrix(&j), g))
    };
    // Run to rounding (function tolerance 0: until no step lowers the cost).
    let options =
        LmOptions { max_iterations: FIT_ITERATIONS, function_tolerance: 0.0, parameter_tolerance: 0.0 };
    let start = Vector2::zeros();
    let (a, _) = minimise_with(start, cost(&start), &options, normal_equations, |a, d| Some(a + d), cost);
    let j = jacobians(&a);
    let sigma_a = normal_matrix(&j).try_inverse()?;
    let leverage: Vec<f64> =
        j.iter().zip(weights).map(|(jk, w)| (jk * sigma_a * jk.transpose() * w).trace()).collect();
    let (n, basis) = normal_at(up, &e, &a);
    let along = if a.norm() > 1e-15 { a.normalize() } else { Vector2::x() };
    let sigma = (along.transpose() * sigma_a * along)[(0, 0)].max(0.0).sqrt();
    let report = FloorNormal {
        pan_tilt_deg: a.norm().atan().to_degrees(),
        sigma_pan_tilt_deg: sigma.to_degrees(),
        normal: [n.x, n.y, n.z],
        fitted_dof: leverage.iter().sum(),
        prior_chi2: a.norm_squared() * prior_w,
    };
    if !n.iter().all(|x| x.is_finite()) {
        return None;
    }
    Some(FloorFit { n, basis, leverage, report })
}

impl FloorFit {
    /// The normal as a unit vector.
    pub(super) fn unit(&self) -> Unit<Vector3<f64>> {
        Unit::new_unchecked(self.n)
    }

    /// The prior's test (module docs): the fitted tilt's chi-square `|a|^2 / s^2` against
    /// the 2-dof quantile of the false alarm rate `chi2_max_3dof` states; beyond it is
    /// [`AlignError::NotPlanar`] (`what` names the stage).
    pub(super) fn plausible(&self, chi2_max_3dof: f64, what: &str) -> Result<(), AlignError> {
        let limit = planarity_limit(chi2_max_3dof, 2.0);
        if self.report.prior_chi2 > limit {
            let max_deg = (limit.sqrt() * FLOOR_TILT_PRIOR_DEG.to_radians()).atan().to_degrees();
            return Err(AlignError::NotPlanar(format!(
                "{what}: the motion fits no floor within {max_deg:.1} deg of the pan axis (the best is {:.1} deg off: chi-square {:.1} (2 dof) of the {FLOOR_TILT_PRIOR_DEG} deg prior above {limit:.3}); the robot pitched or rolled",
                self.report.pan_tilt_deg, self.report.prior_chi2
            )));
        }
        Ok(())
    }
}

/// The planarity limit of a drive with `dof` degrees of freedom left (module docs): the
/// chi-square quantile at `dof` whose tail probability is that of `chi2_max_3dof` at 3
/// degrees of freedom. `dof` is clamped to `[0.5, 3]`.
pub fn planarity_limit(chi2_max_3dof: f64, dof: f64) -> f64 {
    let dof = if dof.is_finite() { dof.clamp(0.5, 3.0) } else { 3.0 };
    if (dof - 3.0).abs() < 1e-12 {
        return chi2_max_3dof;
    }
    let ln_p = ln_gamma_q(1.5, 0.5 * chi2_max_3dof);
    2.0 * gamma_q_inverse(0.5 * dof, ln_p)
}

/// `ln Gamma(s)`, `s > 0` (Lanczos, g = 7, 9 terms: relative error about 1e-15).
fn ln_gamma(s: f64) -> f64 {
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if s < 0.5 {
        // Reflection.
        let pi = std::f64::consts::PI;
        return (pi / (pi * s).sin()).ln() - ln_gamma(1.0 - s);
    }
    let x = s - 1.0;
    let mut sum = C[0];
    for (i, c) in C.iter().enumerate().skip(1) {
        sum += c / (x + i as f64);
    }
    let t = x + 7.5;
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + sum.ln()
}

/// `ln Q(s, x)`, the regularised upper incomplete gamma function (Numerical Recipes
/// 3rd ed. section 6.2: the series of `P` below `x = s + 1`, Lentz's continued fraction
/// of `Q` above; logarithm so that far tails do not underflow).
fn ln_gamma_q(s: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 0.0;
    }
    let ln_front = -x + s * x.ln() - ln_gamma(s);
    if x < s + 1.0 {
        let (mut term, mut sum, mut ap) = (1.0 / s, 1.0 / s, s);
        for _ in 0..500 {
            ap += 1.0;
            term *= x / ap;
            sum += term;
            if term.abs() < sum.abs() * 1e-16 {
                break;
            }
        }
        return (-(ln_front + sum.ln()).exp()).ln_1p();
    }
    let tiny = 1e-300;
    let mut b = x + 1.0 - s;
    let mut c = 1.0 / tiny;
    let mut d = 1.0 / b;
    let mut h = d;
    for i in 1..500 {
        let an = -(i as f64) * (i as f64 - s);
        b += 2.0;
        d = an * d + b;
        if d.abs() < tiny {
            d = tiny;
        }
        c = b + an / c;
        if c.abs() < tiny {
            c = tiny;
        }
        d = 1.0 / d;
        let del = d * c;
        h *= del;
        if (del - 1.0).abs() < 1e-16 {
            break;
        }
    }
    ln_front + h.ln()
}

/// The `x` with `ln Q(s, x) = ln_p` (bisection: `Q` falls monotonically in `x`).
fn gamma_q_inverse(s: f64, ln_p: f64) -> f64 {
    let mut hi = 1.0;
    while ln_gamma_q(s, hi) > ln_p && hi < 1e6 {
        hi *= 2.0;
    }
    let mut lo = 0.0;
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if ln_gamma_q(s, mid) > ln_p {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo < 1e-12 * hi {
            break;
        }
    }
    0.5 * (lo + hi)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The quantiles against tables: chi-square 3 dof at 1e-5 is 25.902 (the default
    /// limit maps to itself), 2 dof at 1e-5 is `-2 ln 1e-5` = 23.026 (exact closed
    /// form), 1 dof at 1e-5 is 19.511; the gamma function at 0.5 and 5.
    #[test]
    fn planarity_limits_match_tables() {
        assert!((ln_gamma(0.5) - std::f64::consts::PI.sqrt().ln()).abs() < 1e-13);
        assert!((ln_gamma(5.0) - 24f64.ln()).abs() < 1e-13);
        assert_eq!(planarity_limit(25.902, 3.0), 25.902);
        // 25.902 is the table's rounding of the 3-dof quantile (25.9017...).
        assert!((planarity_limit(25.902, 2.0) - 23.026).abs() < 2e-3, "{}", planarity_limit(25.902, 2.0));
        assert!((planarity_limit(25.902, 1.0) - 19.511).abs() < 2e-3, "{}", planarity_limit(25.902, 1.0));
        let q = ln_gamma_q(1.0, 0.5 * 23.025_850_93).exp();
        assert!((q - 1e-5).abs() < 1e-12, "{q}");
        // The image-mode limit (4 x 25.902) is far in the tail: still finite and ordered.
        let (l2, l25) = (planarity_limit(103.608, 2.0), planarity_limit(103.608, 2.5));
        assert!(l2 < l25 && l25 < 103.608 && l2 > 90.0, "{l2} {l25}");
    }

    /// A noise-free set of turns about a tilted normal: the fit recovers the normal to
    /// rounding, each leverage lies in [0, 2] and they sum to at most 2, and the out-of-plane parts vanish.
    #[test]
    fn turns_about_a_tilted_floor_give_its_normal() {
        let up = -Vector3::y();
        let n_true = UnitQuaternion::from_scaled_axis(Vector3::new(0.03, 0.0, -0.04)) * up;
        let motions: Vec<Isometry3<f64>> = [0.2, -0.15, 0.25]
            .iter()
            .map(|phi: &f64| {
                let r = UnitQuaternion::from_scaled_axis(n_true * *phi);
                let centre = Vector3::new(1.0 / phi, 0.3, 0.5);
                Isometry3::from_parts((centre - r * centre).into(), r).inverse()
            })
            .collect();
        // Weights of noise-free data (the planarity floor, 1e-12): the prior's pull is then
        // about 1e-12 / s^2 of the tilt, below rounding.
        let w = vec![Matrix3::from_diagonal_element(1e12); 3];
        let fit = fit_floor_normal(&up, &motions, &w).unwrap();
        assert!(fit.n.angle(&n_true) < 1e-9, "{}", fit.n.angle(&n_true));
        assert!((fit.report.pan_tilt_deg - n_true.angle(&up).to_degrees()).abs() < 1e-7);
        assert!(fit.leverage.iter().all(|h| (0.0..=2.0 + 1e-9).contains(h)), "{:?}", fit.leverage);
        assert!(fit.report.fitted_dof <= 2.0 + 1e-9, "{:?}", fit.report);
        assert!(fit.plausible(25.902, "test").is_ok());
        for m in &motions {
            assert!(out_of_plane(m, &fit.n, &fit.basis).norm() < 1e-9);
        }
    }
}
