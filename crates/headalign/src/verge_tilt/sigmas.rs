//! Steps 9 and 10 of the estimation ([`super`]): the reported covariance widened where
//! the linearisation at the estimate understates the spread (an addition to the paper,
//! whose procedure reports no uncertainty; it reports a covariance for every
//! calibrated quantity, `docs/how-it-works.md#the-rig-bundle-adjustment`).
//!
//! - [`profile_depth_scale`] (step 9): the scene's distance in baselines, the depth scale
//!   `s` (1 dof, [`headalign_geometry::bundle::log_depth_scale`]), is the badly determined
//!   direction and the linearised sigmas follow it, so each camera sigma becomes the
//!   largest of those at the estimate and at the estimate re-adjusted with `s` held
//!   `z sigma_s` either side ([`super::DepthProfile`]).
//! - [`bootstrap_covariance`] (step 10, optional): the maximum-likelihood least squares
//!   re-run on point tracks drawn with replacement (and the encoder readings redrawn from
//!   the angle prior), each camera sigma the larger of the linearised one and the
//!   replicates' spread.
//!
//! Both widen by `C' = D C D`, `D = diag(max(1, sigma_new / sigma))` capped at
//! [`MAX_END_WIDENING`] ([`widen_covariance`]): the correlations stay those of the
//! linearisation and the point estimate is unchanged. Units: `s` is a log distance (in
//! baselines), its sigma dimensionless; pixel noise from the maximum-likelihood pass.
//! Pitfalls: an end where some parameter became (nearly) unobservable is no linearisation
//! of a plausible solution and is skipped; profile ends that creep along the curved
//! constraint are capped at [`PROFILE_END_ITERATIONS`]; with fewer than 3 converged
//! replicates the bootstrap reports nothing.

use headalign_geometry::bootstrap::{BootstrapOptions, bootstrap_spread};
use headalign_geometry::bundle::{
    BundleObservation, BundleOptions, BundleResult, RobustLoss, bundle_adjust_at_depth_scale, log_depth_scale,
};

use super::adjust::FINAL_ITERATIONS;
use super::{BootstrapReport, DepthProfile, DepthProfileReport, EstimationOptions};

/// The largest sigma ratio, end over estimate, of a profile end that
/// [`profile_depth_scale`] uses; an end beyond it is skipped as degenerate.
pub const MAX_END_WIDENING: f64 = 10.0;

/// Levenberg-Marquardt iterations of each profile end of [`profile_depth_scale`]. The ends
/// start at the estimate, one depth-scale sigma away, and most converge in 5-9 iterations,
/// but the stiff depth-scale pseudo-residual makes some at 3 px creep along the curved
/// constraint to the 300-iteration limit (about 1 s each, most of the profile's former
/// +11 % CPU). Measured against ends run to 300 iterations: per end (16 ends, seeds
/// 1001-1008 at 3 px) the widening of every camera sigma agrees to a median 3e-7 and at
/// worst 7 % (a far scene whose end creeps at 300 iterations as well); on the reported
/// sigmas (`experiment calibration --only 3 --trials 60 --seed 1001 --depth-profile 1`,
/// 660 sigmas) the largest change is 0.93 % (seed 1008, 127 baselines away), 99 % are
/// within 0.52 %, and the estimates are identical.
pub const PROFILE_END_ITERATIONS: usize = 20;

/// [Estimation](super) step 9: widen the covariance of a least-squares `result` for the
/// nonlinearity along the scene's depth scale. With small rotations the scene's distance
/// in baselines is the badly determined direction (at 3 px known to tens of percent) and
/// the linearised sigmas follow it: a receding maximum-likelihood scene (about 5 % of the
/// trials at 3 px) reports sigmas 0.5-0.9 of the Cramer-Rao bound while its principal
/// points move to absorb the disparity (a past measurement). So the covariance is
/// evaluated along the profile likelihood in `s`: at `s_hat -+ z sigma_s` (everything
/// else re-optimised, [`bundle_adjust_at_depth_scale`]); each camera parameter's sigma
/// becomes the largest of the three and the correlations stay those of the estimate
/// (`C' = D C D`, `D = diag(max(1, sigma_end / sigma))`). The point estimate is
/// unchanged. Where the depth is well determined the three covariances agree and nothing
/// widens. A failed end adjustment is skipped (the estimate's sigma stays).
pub fn profile_depth_scale(
    result: BundleResult,
    obs: &[BundleObservation],
    profile: &DepthProfile,
    options: &EstimationOptions,
) -> (BundleResult, Option<DepthProfileReport>) {
    let noise = result.report.sigma_px;
    let ls = BundleOptions {
        max_iterations: options.bundle.max_iterations.max(FINAL_ITERATIONS),
        robust: RobustLoss::None,
        noise_sigma_px: Some(noise),
        ..options.bundle.clone()
    };
    let Ok((s, sigma_s)) = log_depth_scale(&result.state, obs, &ls, noise) else { return (result, None) };
    let mut report =
        DepthProfileReport { log_depth: s, sigma_log_depth: sigma_s, ends: 0, max_widening: 1.0 };
    if !(sigma_s > profile.min_sigma_log_depth && sigma_s > 0.0) {
        return (result, Some(report));
    }
    let n = result.covariance.matrix.nrows();
    let mut widen = vec![1.0_f64; n];
    let end_ls = BundleOptions { max_iterations: PROFILE_END_ITERATIONS, ..ls.clone() };
    for sign in [-1.0, 1.0] {
        let target = s + sign * profile.z * sigma_s;
        let Ok(end) =
            bundle_adjust_at_depth_scale(&result.state, obs, &end_ls, target, 1e-3 * sigma_s / noise)
        else {
            continue;
        };
        if end.covariance.names != result.covariance.names {
            continue;
        }
        let ratios: Vec<f64> = (0..n)
            .map(|i| (end.covariance.matrix[(i, i)] / result.covariance.matrix[(i, i)]).sqrt())
            .collect();
        // An end where some parameter became (nearly) unobservable is no linearisation of
        // a plausible solution: skipped (measured at 3 px with the mean log distance as `s`:
        // one end in 12 trials widened a sigma 3e6-fold).
        if !ratios.iter().all(|r| r.is_finite() && *r <= MAX_END_WIDENING) {
            continue;
        }
        report.ends += 1;
        for (w, r) in widen.iter_mut().zip(&ratios) {
            *w = w.max(*r);
        }
    }
    let mut result = result;
    widen_covariance(&mut result, &widen);
    report.max_widening = widen.iter().copied().fold(1.0, f64::max);
    (result, Some(report))
}

/// `C' = D C D` with `D = diag(widen)`: each camera sigma of `result` times its factor,
/// the correlations unchanged ([`profile_depth_scale`], [`bootstrap_covariance`]).
fn widen_covariance(result: &mut BundleResult, widen: &[f64]) {
    let m = &mut result.covariance.matrix;
    for i in 0..m.nrows().min(widen.len()) {
        for j in 0..m.ncols().min(widen.len()) {
            m[(i, j)] *= widen[i] * widen[j];
        }
    }
}

/// [Estimation](super) step 10: widen the covariance of the maximum-likelihood `result` (fitted
/// to `obs`) to the bootstrap spread of that least squares
/// ([`headalign_geometry::bootstrap::bootstrap_spread`]: point tracks drawn with
/// replacement, the encoder readings redrawn from the angle prior, each replicate started
/// at the estimate). As in [`profile_depth_scale`], `C' = D C D` with
/// `D = diag(max(1, sigma_boot / sigma))`, capped at [`MAX_END_WIDENING`]: the
/// correlations stay the linearisation's and the point estimate is unchanged. Why: with
/// small rotations in a near scene at 3 px the least squares spreads 1.1-1.2 times its
/// linearised sigma for the focal lengths (a past measurement). If fewer than 3
/// replicates converge, the covariance is left as it was and the report is `None`.
pub fn bootstrap_covariance(
    result: BundleResult,
    obs: &[BundleObservation],
    boot: &BootstrapOptions,
    options: &EstimationOptions,
) -> (BundleResult, Option<BootstrapReport>) {
    let ls = BundleOptions {
        robust: RobustLoss::None,
        noise_sigma_px: Some(result.report.sigma_px),
        ..options.bundle.clone()
    };
    let seeded = BootstrapOptions { seed: boot.seed.wrapping_add(options.seed), ..*boot };
    let Ok(spread) = bootstrap_spread(&result, obs, &ls, &seeded) else { return (result, None) };
    let n = result.covariance.matrix.nrows();
    let mut ratios: Vec<f64> =
        (0..n).map(|i| spread.sigma(i).unwrap_or(0.0) / result.covariance.matrix[(i, i)].sqrt()).collect();
    let widen: Vec<f64> =
        ratios.iter().map(|r| if r.is_finite() { r.clamp(1.0, MAX_END_WIDENING) } else { 1.0 }).collect();
    let mut result = result;
    widen_covariance(&mut result, &widen);
    ratios.retain(|r| r.is_finite());
    ratios.sort_by(f64::total_cmp);
    let report = BootstrapReport {
        replicates: spread.replicates,
        failed: spread.failed,
        max_widening: widen.iter().copied().fold(1.0, f64::max),
        median_ratio: ratios.get(ratios.len() / 2).copied().unwrap_or(f64::NAN),
    };
    (result, Some(report))
}
