//! The Gaussian prior on the joint angles of [`Motions::Joints`] (module docs of
//! [`crate::bundle`], section Parameters and degrees of freedom).
//!
//! # What it computes
//!
//! With `angle_prior_sigma` set, every joint angle `theta_kj` of a view `k >= 1` is a
//! free parameter (one dof, radians) with a prior centred on its commanded value. The `m`
//! errors `e_k = theta_kj - commanded_kj` of joint `j` are whitened into dimensionless
//! residuals whose sum of squares is the prior's chi-square `e^T C^-1 e`
//! ([`angle_prior_residuals`], [`angle_prior_chi2`]):
//!
//! - [`AnglePrior::ReadingDifferences`] (default): each commanded angle is a difference of
//!   two encoder readings of noise `sigma`, the view's and view 0's, so
//!   `C = sigma^2 (I + 1 1^T)`, whitened as `(I - beta 1 1^T) e / sigma` with
//!   `beta = (1 - 1/sqrt(m + 1)) / m` (`prior_beta`: the root below `1/m` of
//!   `2 beta - m beta^2 = 1/(m + 1)`);
//! - [`AnglePrior::Independent`]: `C = sigma^2 I`, `e / sigma`.
//!
//! In the cost the prior rows are weighted by `sigma_px^2` (`Problem::prior_weight`; 1 px
//! without `noise_sigma_px`), as if they were pixel residuals at that noise.
//! `Problem::prior_terms` gives each row with its constant derivatives
//! `(delta_il - beta) / sigma` with respect to the angle parameters.
//!
//! # Pitfalls
//!
//! - Taking reading differences as independent states each angle's error too small by
//!   `sqrt 2` and misses their correlation (the module docs give the measured effect).
//! - Without `angle_prior_sigma` the angles are held at the commanded values: no angle
//!   parameters and no prior rows.
//! - Row 0 of the angles is the gauge and never in the prior.

use super::problem::Problem;
use super::state::{BundleOptions, Motions, RigState};

/// The error model of the commanded joint angles of [`Motions::Joints`] (module docs,
/// Parameters).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum AnglePrior {
    /// Each commanded angle is a difference of two encoder readings, the view's and view
    /// 0's, each with independent noise `angle_prior_sigma`: the angles of one joint share
    /// the reference reading's error (covariance `sigma^2 (I + 1 1^T)` over the views).
    #[default]
    ReadingDifferences,
    /// Each commanded angle has its own independent error of `angle_prior_sigma` (e.g.
    /// relative moves measured by a joint's own incremental sensor).
    Independent,
}

/// One row of the angle prior: a dimensionless residual and its derivative with respect
/// to each camera parameter it involves (`(parameter index, d residual / d parameter)`).
#[derive(Clone, Debug)]
pub(super) struct PriorRow {
    pub(super) entries: Vec<(usize, f64)>,
    pub(super) residual: f64,
}

/// The whitened angle-prior residuals of one joint (module docs, Parameters): `errors`
/// are `theta_k - commanded_k` over the views `k >= 1` (radians), `sigma` the prior's
/// sigma (radians). Returns one dimensionless residual per error; their sum of squares is
/// the prior's chi-square `e^T C^-1 e` (`C = sigma^2 I` for [`AnglePrior::Independent`],
/// `sigma^2 (I + 1 1^T)` for [`AnglePrior::ReadingDifferences`]).
pub fn angle_prior_residuals(errors: &[f64], sigma: f64, model: AnglePrior) -> Vec<f64> {
    let beta = prior_beta(errors.len(), model);
    let sum: f64 = errors.iter().sum();
    errors.iter().map(|e| (e - beta * sum) / sigma).collect()
}

/// The prior's chi-square of a motion model under `options` (0 without a prior or for
/// [`Motions::Free`]): the sum of the squares of [`angle_prior_residuals`] over every joint.
pub fn angle_prior_chi2(motions: &Motions, options: &BundleOptions) -> f64 {
    let (Some(sigma), Motions::Joints { angles, commanded, .. }) = (options.angle_prior_sigma, motions)
    else {
        return 0.0;
    };
    let joints = angles.first().map_or(0, Vec::len);
    (0..joints)
        .map(|j| {
            let errors: Vec<f64> = angles
                .iter()
                .zip(commanded)
                .skip(1)
                .map(|(a, c)| a.get(j).copied().unwrap_or(0.0) - c.get(j).copied().unwrap_or(0.0))
                .collect();
            angle_prior_residuals(&errors, sigma, options.angle_prior).iter().map(|r| r * r).sum::<f64>()
        })
        .sum()
}

/// `beta` of the whitening `(I - beta 1 1^T)` of `m` reading differences (0 for
/// independent errors): `(I - beta 1 1^T)^2 = (I + 1 1^T)^-1` needs
/// `2 beta - m beta^2 = 1 / (m + 1)`, the root below `1 / m`.
pub(super) fn prior_beta(m: usize, model: AnglePrior) -> f64 {
    match model {
        AnglePrior::Independent => 0.0,
        AnglePrior::ReadingDifferences if m == 0 => 0.0,
        AnglePrior::ReadingDifferences => (1.0 - 1.0 / ((m + 1) as f64).sqrt()) / m as f64,
    }
}

impl Problem<'_> {
    pub(super) fn prior_terms(&self, state: &RigState) -> Vec<PriorRow> {
        let mut out = Vec::new();
        let (Some(sigma), Motions::Joints { angles, commanded, .. }) =
            (self.options.angle_prior_sigma, &state.motions)
        else {
            return out;
        };
        let joints = self.layout.angle.iter().map(Vec::len).max().unwrap_or(0);
        for j in 0..joints {
            // The free angles of joint j: (parameter index, theta - commanded).
            let free: Vec<(usize, f64)> = self
                .layout
                .angle
                .iter()
                .enumerate()
                .filter_map(|(k, row)| {
                    let idx = (*row.get(j)?)?;
                    let a = angles.get(k).and_then(|r| r.get(j)).copied().unwrap_or(0.0);
                    let c = commanded.get(k).and_then(|r| r.get(j)).copied().unwrap_or(0.0);
                    Some((idx, a - c))
                })
                .collect();
            let errors: Vec<f64> = free.iter().map(|f| f.1).collect();
            let residuals = angle_prior_residuals(&errors, sigma, self.options.angle_prior);
            let beta = prior_beta(free.len(), self.options.angle_prior);
            for (i, residual) in residuals.into_iter().enumerate() {
                let entries = free
                    .iter()
                    .enumerate()
                    .map(|(l, f)| (f.0, (if i == l { 1.0 } else { 0.0 } - beta) / sigma))
                    .collect();
                out.push(PriorRow { entries, residual });
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::gauss;
    use nalgebra::{DMatrix, DVector};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// The whitened prior residuals' chi-square is `e^T C^-1 e` with the model's `C`, on
    /// random error vectors of 1-6 views (to rounding: the whitening is exact).
    #[test]
    fn angle_prior_whitening_is_the_inverse_covariance() {
        let mut rng = ChaCha8Rng::seed_from_u64(5150);
        for trial in 0..200 {
            let m = 1 + trial % 6;
            let sigma = 1e-4 * (1.0 + (trial % 7) as f64);
            let e: Vec<f64> = (0..m).map(|_| sigma * gauss(&mut rng)).collect();
            let ev = DVector::from_vec(e.clone());
            for (model, c) in [
                (AnglePrior::Independent, DMatrix::identity(m, m) * (sigma * sigma)),
                (
                    AnglePrior::ReadingDifferences,
                    (DMatrix::identity(m, m) + DMatrix::from_element(m, m, 1.0)) * (sigma * sigma),
                ),
            ] {
                let chi2: f64 = angle_prior_residuals(&e, sigma, model).iter().map(|r| r * r).sum();
                let exact = (ev.transpose() * c.try_inverse().unwrap() * &ev)[(0, 0)];
                assert!((chi2 - exact).abs() <= 1e-12 * exact.max(1.0), "{model:?} m {m}: {chi2} vs {exact}");
            }
        }
        assert!(angle_prior_residuals(&[], 1e-3, AnglePrior::ReadingDifferences).is_empty());
    }

    /// The prior rows' analytic derivatives `(delta_il - beta) / sigma` (as
    /// `Problem::prior_terms` builds them) against central differences of the residuals
    /// (linear in the errors: equal up to the rounding of a 1e-7 rad step on errors of
    /// 1e-4 rad, 1e-6 relative).
    #[test]
    fn angle_prior_derivatives_match_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(5151);
        for m in 1..=6 {
            let sigma = 2e-4;
            let e: Vec<f64> = (0..m).map(|_| sigma * gauss(&mut rng)).collect();
            for model in [AnglePrior::Independent, AnglePrior::ReadingDifferences] {
                let beta = prior_beta(m, model);
                for l in 0..m {
                    let h = 1e-7;
                    let (mut plus, mut minus) = (e.clone(), e.clone());
                    plus[l] += h;
                    minus[l] -= h;
                    let rp = angle_prior_residuals(&plus, sigma, model);
                    let rm = angle_prior_residuals(&minus, sigma, model);
                    for i in 0..m {
                        let fd = (rp[i] - rm[i]) / (2.0 * h);
                        let analytic = (if i == l { 1.0 } else { 0.0 } - beta) / sigma;
                        assert!(
                            (fd - analytic).abs() <= 1e-6 * (1.0 / sigma),
                            "{model:?} m {m} d r{i}/d e{l}: {fd} vs {analytic}"
                        );
                    }
                }
            }
        }
    }
}
