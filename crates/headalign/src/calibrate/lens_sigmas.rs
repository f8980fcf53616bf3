//! The focal-length and lens sigmas of a self-calibration that estimates a lens model
//! ([`super::CalibrateOptions::lens`]): the linearised covariance widened to the bootstrap
//! spread over point tracks.
//!
//! What it computes, [`bootstrap_lens_sigmas`]: the final least squares re-run on point
//! tracks drawn with replacement ([`headalign_geometry::bootstrap::bootstrap_spread`]:
//! [`BOOTSTRAP_REPLICATES`] replicates, each started at the estimate with at most
//! [`BOOTSTRAP_ITERATIONS`] linearisations, plain least squares on the final observations
//! at the final noise estimate); each focal length's (`fx`, `fy`) and each estimated lens
//! coefficient's sigma becomes the larger of the linearised one and the replicates'
//! spread (the ratio capped at [`MAX_WIDENING`]); the covariance is widened by
//! `C' = W C W`, `W` diagonal, so the correlations stay the linearisation's and the point
//! estimate is unchanged (as `verge_tilt::bootstrap_covariance` for the procedure).
//!
//! Rule: always when a lens model is estimated (no threshold); never when it is not (the
//! pinhole calibration keeps its sigmas exactly). Why: with the procedure's small
//! rotations (3 deg views) the focal length and `k1` share a shallow valley of the cost,
//! and the linearised 95 % intervals covered 85-90 % of the trials for some focal
//! lengths (`headalign experiment lens`, its module docs). The likelihood along the
//! valley is close to quadratic there (measured: the profile deviance with one focal
//! length or `k1` held 1.96 sigmas either side is 3.4-4.3 against 3.84 for a quadratic
//! one, 0.5 px, seeds 25 and 39), so the curvature is not what the linearisation misses:
//! the tracks' errors are (outliers within the re-selection gate, points seen by few
//! views). The pairs bootstrap (Efron & Tibshirani 1993, ch. 9, the track as the pair)
//! sees the spread the data themselves give.
//!
//! Degrees of freedom: none estimated. Units: the covariance's (pixels for focal lengths,
//! dimensionless coefficients). Cost: [`BOOTSTRAP_REPLICATES`] warm-started adjustments
//! (measured in `experiment lens` at 0.5 px: about 0.5-1 s of 2-4 s per calibration).
//!
//! A sequence's calibration ([`super::calibrate_sequence`]) is bootstrapped the same way,
//! its segment gauges after the first held as in its adjustment.
//!
//! Pitfalls: a sigma from 30 replicates is known to about 13 %, and the widening takes
//! the larger of two sigmas, so it errs towards wider intervals; the random draws are
//! seeded by the estimation seed (the same run gives the same sigmas). With fewer than 3
//! converged replicates nothing is widened.

use headalign_geometry::bootstrap::{BootstrapOptions, bootstrap_spread};
use headalign_geometry::bundle::{BundleOptions, RobustLoss};
use serde::Serialize;

use super::{CalibrateOptions, MotionCalibration};

/// Bootstrap replicates (a sigma to about 13 %).
pub const BOOTSTRAP_REPLICATES: usize = 30;

/// Linearisations per replicate (from the estimate; most converge in 3-8).
pub const BOOTSTRAP_ITERATIONS: usize = 30;

/// The largest widening of one sigma.
pub const MAX_WIDENING: f64 = 10.0;

/// What [`bootstrap_lens_sigmas`] did.
#[derive(Debug, Clone, Serialize)]
pub struct LensSigmaReport {
    /// Replicates that converged.
    pub replicates: usize,
    /// Replicates that failed (skipped).
    pub failed: usize,
    /// Per widened parameter: covariance name and widening factor (>= 1).
    pub widening: Vec<(String, f64)>,
    /// The largest widening.
    pub max_widening: f64,
}

/// Whether a covariance name is a focal length or a lens coefficient.
fn widened(name: &str) -> bool {
    let Some((side, what)) = name.split_once('.') else { return false };
    (side == "left" || side == "right")
        && matches!(what, "fx" | "fy" | "k1" | "k2" | "p1" | "p2" | "k3" | "k4")
}

/// Widen the focal-length and lens sigmas of `cal` to the bootstrap spread (module docs);
/// `None` (nothing done) when no lens model is estimated or too few replicates converge.
pub fn bootstrap_lens_sigmas(
    cal: &mut MotionCalibration,
    options: &CalibrateOptions,
) -> Option<LensSigmaReport> {
    options.lens.kind()?;
    let noise = cal.bundle.report.sigma_px;
    if !(noise.is_finite() && noise > 0.0) {
        return None;
    }
    let ls = BundleOptions {
        robust: RobustLoss::None,
        noise_sigma_px: Some(noise),
        gauge_views: super::lens_auto::held_gauges(cal),
        ..super::rig_bundle::adjustment_options(options).bundle
    };
    let boot = BootstrapOptions {
        replicates: BOOTSTRAP_REPLICATES,
        max_iterations: BOOTSTRAP_ITERATIONS,
        seed: options.estimation.seed,
    };
    let spread = bootstrap_spread(&cal.bundle, &cal.observations, &ls, &boot).ok()?;
    let names = cal.bundle.covariance.names.clone();
    let n = names.len();
    let mut widen = vec![1.0_f64; n];
    let mut report = LensSigmaReport {
        replicates: spread.replicates,
        failed: spread.failed,
        widening: Vec::new(),
        max_widening: 1.0,
    };
    for (i, name) in names.iter().enumerate() {
        if !widened(name) {
            continue;
        }
        let r = spread.sigma(i).unwrap_or(0.0) / cal.bundle.covariance.matrix[(i, i)].max(0.0).sqrt();
        if r.is_finite() {
            widen[i] = r.clamp(1.0, MAX_WIDENING);
        }
        report.widening.push((name.clone(), widen[i]));
    }
    let m = &mut cal.bundle.covariance.matrix;
    for r in 0..n {
        for c in 0..n {
            m[(r, c)] *= widen[r] * widen[c];
        }
    }
    report.max_widening = widen.iter().copied().fold(1.0, f64::max);
    cal.report.focal_sigma_pct = super::report::focal_sigma_pct(&cal.bundle);
    Some(report)
}
