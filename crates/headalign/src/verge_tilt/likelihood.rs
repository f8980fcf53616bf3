//! Step 7 of the estimation ([`super`]): the maximum-likelihood pass, plain least squares
//! under Gaussian pixel noise with re-classified observations
//! (`docs/how-it-works.md#the-rig-bundle-adjustment`:
//! "maximum likelihood over K_L, K_R, the rig's relative pose, the motions ... and the 3D
//! points").
//!
//! The Huber loss of step 6 is robust but not the likelihood of Gaussian pixel noise
//! (with its fixed 2 px scale, at 2-3 px of noise most inliers are down-weighted), and its
//! angle prior is weighted as if the noise were 1 px (at 3 px the prior is then 9 times
//! too weak against the pixels). So [`maximum_likelihood_pass`]: the noise is estimated
//! from the robust solution (median residual norm), the observations within
//! `reselect_sigmas` of it are kept ([`plausible_points`]), plain least squares runs with
//! the prior weighted by that noise; then the observations are re-classified at the
//! least-squares solution (studentised residuals, [`residual_scale`], within
//! `reselect_sigmas` of the unbiased, truncation-corrected noise estimate,
//! [`truncated_noise_estimate`]) and the adjustment repeated until the set is stable
//! ([`ML_ROUNDS`] at most). Its covariance is the one reported.
//!
//! Degrees of freedom of the noise estimate: `m - p`, `m = 2 n` pixel residuals plus one
//! per angle prior, `p` the parameters including 3 per point. Units: pixels.
//!
//! Pitfalls: classifying the inliers once, at the robust solution, biased the noise
//! estimate 5 % low at 2-3 px (true inliers with 2-4 sigma errors were dropped); the
//! iterated classification at the least-squares solution fixes that (measured in
//! `docs/accuracy.md`). A point seen only once by one camera takes its depth from that
//! observation alone, so a wrong one is fitted exactly at a wrong depth that no residual
//! shows; such a point is left out when that depth is off its neighbours' by more than its
//! own stereo noise and the scene's roughness allow ([`lone_depth_outliers`]).

use std::collections::HashSet;

use headalign_geometry::bundle::{
    BundleObservation, BundleOptions, BundleResult, Motions, RigState, RobustLoss, Side, bundle_adjust,
    residual_pixels,
};

use super::adjust::{
    DEPTH_RATIO, FINAL_ITERATIONS, MIN_POINT_OBSERVATIONS, PointSources, retriangulate_points_by_support,
    robust_sigma,
};
use super::{EstimationOptions, LoneDepthGate};
use crate::error::{AlignError, StepContext};

/// Rounds of classification and least squares in the maximum-likelihood pass (module
/// docs step 7; measured: the set is stable after 2-3 at 1-3 px).
pub const ML_ROUNDS: usize = 5;

/// The maximum-likelihood pass (estimation step 7, this file's module docs). The robust solution's noise is
/// estimated from the median residual norm (MAD-like, immune to the outliers still in
/// `candidates`) and gives the first classification: observations of `candidates` within
/// `reselect_sigmas` of it, points keeping at least [`MIN_POINT_OBSERVATIONS`] and of
/// plausible depth. Plain least squares then runs with the angle prior weighted by the
/// noise, and the classification is repeated at the least-squares solution itself until
/// it is stable ([`ML_ROUNDS`] at most):
/// - the noise is re-estimated by [`truncated_noise_estimate`]: `RSS / (m - p)` (`m`
///   residuals including the angle priors, `p` parameters including 3 per point: the
///   classical unbiased estimate) divided by the variance factor of the truncation to
///   `reselect_sigmas` ([`truncated_variance_factor`], 0.987 at 3.5);
/// - an observation is kept when its residual is within `reselect_sigmas` standard
///   deviations of *its own* distribution ([`residual_scale`]): a fitted residual is
///   smaller than the noise by its leverage, a residual of an observation left out of the
///   fit larger.
///
/// Measured cause (docs/accuracy.md): gating at the Huber solution once, where an
/// inlier with a large error keeps its full residual but the median-based scale is that of
/// fitted residuals (about 0.88 of the noise at 2 px), dropped 7-12 % of the true inliers
/// with errors of 2-3 sigma and 50-85 % of those at 3-4 sigma, so the least-squares noise
/// came out 0.95 of the truth and the reported sigmas 5 % small.
pub(super) fn maximum_likelihood_pass(
    robust: &BundleResult,
    candidates: &[BundleObservation],
    fallback: &[BundleObservation],
    points: &PointSources<'_>,
    options: &EstimationOptions,
) -> Result<(BundleResult, Vec<BundleObservation>), AlignError> {
    let c = options.reselect_sigmas;
    let mut sigma = robust_sigma(&robust.state, fallback).max(1e-6);
    // Points the robust pass left out (their observations gated away under an early,
    // unconverged solution, or placed by a wrong stereo match) get a fresh position under
    // the final calibration, from the view whose stereo match agrees best with their
    // candidate observations ([`retriangulate_points_by_support`]), so that their good
    // observations can come back.
    let mut state = robust.state.clone();
    let mut adjusted = vec![false; state.points.len()];
    for o in fallback {
        adjusted[o.point] = true;
    }
    let redo: Vec<bool> = adjusted.iter().map(|a| !a).collect();
    retriangulate_points_by_support(&mut state, points, &redo, candidates, c * sigma.max(0.05));
    let gated: Vec<BundleObservation> = candidates
        .iter()
        .copied()
        .filter(|o| residual_pixels(&state, o).is_some_and(|r| r.norm() <= c * sigma.max(0.05)))
        .collect();
    let mut obs = plausible_points(&state, gated, options, sigma);
    if obs.len() < options.min_tracks {
        obs = fallback.to_vec();
        state = robust.state.clone();
    }
    let ls = |noise: f64| BundleOptions {
        max_iterations: options.bundle.max_iterations.max(FINAL_ITERATIONS),
        robust: RobustLoss::None,
        noise_sigma_px: Some(noise),
        ..options.bundle.clone()
    };
    let mut result =
        bundle_adjust(&state, &obs, &ls(sigma)).step("bundle adjustment (maximum likelihood)")?;
    let priors = prior_count(&result.state, &options.bundle);
    for _ in 1..ML_ROUNDS {
        let refit = truncated_noise_estimate(&result, priors, c).unwrap_or(sigma);
        // Re-classify every candidate at the least-squares solution with that noise.
        let in_fit: HashSet<(usize, usize, bool)> =
            obs.iter().map(|o| (o.point, o.view, o.side == Side::Right)).collect();
        let mut per_point = vec![0usize; result.state.points.len()];
        for o in &obs {
            per_point[o.point] += 1;
        }
        let camera_share = camera_parameter_share(&result);
        let next: Vec<BundleObservation> = candidates
            .iter()
            .copied()
            .filter(|o| {
                let fitted = in_fit.contains(&(o.point, o.view, o.side == Side::Right));
                let scale = residual_scale(per_point[o.point], camera_share, fitted);
                residual_pixels(&result.state, o).is_some_and(|r| r.norm() <= c * refit.max(0.05) * scale)
            })
            .collect();
        let next = plausible_points(&result.state, next, options, refit);
        let key = |o: &BundleObservation| (o.point, o.view, o.side == Side::Right);
        let stable = next.len() == obs.len() && next.iter().zip(&obs).all(|(a, b)| key(a) == key(b));
        let moved = (refit / sigma - 1.0).abs() > 0.01;
        if next.len() < options.min_tracks || (stable && !moved) {
            break;
        }
        // A re-classification that leaves a parameter unobservable (a 50-point trial at
        // 1.5 px in 150: its reduced camera system became singular) ends the rounds at the
        // last classification that fitted, instead of failing the whole estimate.
        let Ok(trial) = bundle_adjust(&result.state, &next, &ls(refit)) else { break };
        obs = next;
        sigma = refit;
        result = trial;
    }
    // The reported noise and covariance are those of the final classification.
    if let Some(refit) = truncated_noise_estimate(&result, priors, c)
        && (refit / sigma - 1.0).abs() > 0.01
    {
        result = bundle_adjust(&result.state, &obs, &ls(refit))
            .step("bundle adjustment (maximum likelihood, noise re-estimated)")?;
    }
    Ok((result, obs))
}

/// Observations of points that keep at least [`MIN_POINT_OBSERVATIONS`], at least
/// `min_camera_observations` in each camera that sees them, and are not nearer than the
/// median point distance over [`DEPTH_RATIO`]. Far points are kept: at
/// 2-3 px the depth of a far point is ill-determined and its least-squares position can
/// lie beyond `DEPTH_RATIO` times the median, or near infinity, with every residual
/// within the noise; dropping them (as the robust pass does, against wrong tracks)
/// removed 20-40 of 200 points in some trials at 3 px, selected by their noise. Wrong
/// tracks are left to the studentised gate.
pub(super) fn plausible_points(
    state: &RigState,
    gated: Vec<BundleObservation>,
    options: &EstimationOptions,
    noise_px: f64,
) -> Vec<BundleObservation> {
    let per_camera = camera_counts(state.points.len(), &gated);
    let mut counts: Vec<usize> = per_camera.iter().map(|k| k[0] + k[1]).collect();
    // A point seen once by one camera takes its depth from that observation alone
    // (`EstimationOptions::min_camera_observations`, `lone_depth_gate`).
    let lone = match &options.lone_depth_gate {
        Some(g) => lone_depth_outliers(state, &gated, noise_px, g),
        None => vec![false; state.points.len()],
    };
    for ((c, k), lone) in counts.iter_mut().zip(&per_camera).zip(lone) {
        if lone || k.iter().any(|&n| n > 0 && n < options.min_camera_observations) {
            *c = 0;
        }
    }
    let mut dist: Vec<f64> = (0..state.points.len())
        .filter(|&i| counts[i] >= MIN_POINT_OBSERVATIONS)
        .map(|i| state.points[i].coords.norm())
        .collect();
    dist.sort_by(f64::total_cmp);
    let median = dist.get(dist.len() / 2).copied().unwrap_or(f64::NAN);
    let tame = |i: usize| {
        let d = state.points[i].coords.norm();
        !d.is_nan() && d >= median / DEPTH_RATIO
    };
    gated.into_iter().filter(|o| counts[o.point] >= MIN_POINT_OBSERVATIONS && tame(o.point)).collect()
}

/// Observations of each point by the left and the right camera.
fn camera_counts(points: usize, obs: &[BundleObservation]) -> Vec<[usize; 2]> {
    let mut per_camera = vec![[0usize; 2]; points];
    for o in obs {
        if let Some(k) = per_camera.get_mut(o.point) {
            k[usize::from(o.side == Side::Right)] += 1;
        }
    }
    per_camera
}

/// Points seen once by one camera (and at least [`MIN_POINT_OBSERVATIONS`] times in
/// all) whose depth disagrees with their neighbours' ([`LoneDepthGate`]), flagged per
/// point of `state`.
///
/// Why: the other camera's views, a few degrees apart, fix such a point's direction but
/// hardly its depth, so the one observation sets the depth; a wrong observation near the
/// epipolar line is fitted exactly at a wrong depth (a past measurement: 116 of
/// the 117 outliers the final adjustment kept at 3 px). A wrong pixel anywhere along the
/// line is a wrong disparity, usually far from that of the surface around the point.
///
/// The neighbours are the `gate.neighbours` points nearest in direction (from the
/// reference origin) among those seen by no camera exactly once; the deviation is
/// `ln d - median ln d_j`, over `hypot(sqrt 2 sigma_ln_d, 1.4826 MAD, roughness)` with
/// `sigma_ln_d = noise d / (f |t|)` the log-depth noise of one stereo disparity (`f` the
/// lone camera's fx, `|t|` the baseline, `d` the distance). Units: `noise_px` pixels,
/// `state` in any length unit. Pitfall: a lone point on a near object in front of a
/// wall is flagged too (its information is lost, not its correctness).
pub fn lone_depth_outliers(
    state: &RigState,
    obs: &[BundleObservation],
    noise_px: f64,
    gate: &LoneDepthGate,
) -> Vec<bool> {
    let n = state.points.len();
    let per_camera = camera_counts(n, obs);
    let mut flags = vec![false; n];
    let baseline = state.right_from_left.translation.vector.norm();
    let usable = |i: usize| {
        let d = state.points[i].coords.norm();
        d.is_finite() && d > 0.0
    };
    let anchored: Vec<(nalgebra::Vector3<f64>, f64)> = (0..n)
        .filter(|&i| {
            let k = per_camera[i];
            k[0] != 1 && k[1] != 1 && k[0] + k[1] >= MIN_POINT_OBSERVATIONS && usable(i)
        })
        .map(|i| (state.points[i].coords.normalize(), state.points[i].coords.norm().ln()))
        .collect();
    if anchored.len() < gate.neighbours || baseline.is_nan() || baseline <= 0.0 {
        return flags;
    }
    for (i, k) in per_camera.iter().enumerate() {
        let lone_side = match k {
            [1, r] if *r + 1 >= MIN_POINT_OBSERVATIONS => Side::Left,
            [l, 1] if *l + 1 >= MIN_POINT_OBSERVATIONS => Side::Right,
            _ => continue,
        };
        if !usable(i) {
            continue;
        }
        let p = state.points[i].coords;
        let dir = p.normalize();
        let mut near: Vec<(f64, f64)> = anchored.iter().map(|(u, l)| (u.dot(&dir), *l)).collect();
        near.sort_by(|a, b| b.0.total_cmp(&a.0));
        let mut logs: Vec<f64> = near.iter().take(gate.neighbours).map(|x| x.1).collect();
        logs.sort_by(f64::total_cmp);
        let median = logs[logs.len() / 2];
        let mut spread: Vec<f64> = logs.iter().map(|l| (l - median).abs()).collect();
        spread.sort_by(f64::total_cmp);
        let mad = spread[spread.len() / 2];
        let f = match lone_side {
            Side::Left => state.left.fx,
            Side::Right => state.right.fx,
        };
        let sigma_ln_d = noise_px * p.norm() / (f.abs() * baseline);
        let scale = (2.0 * sigma_ln_d * sigma_ln_d + (1.4826 * mad).powi(2) + gate.roughness.powi(2)).sqrt();
        flags[i] = (p.norm().ln() - median).abs() > gate.z * scale;
    }
    flags
}

/// Number of angle-prior residuals of a state under `options` (one per free joint angle of
/// every view but the reference).
fn prior_count(state: &RigState, options: &BundleOptions) -> usize {
    match (&state.motions, options.angle_prior_sigma) {
        (Motions::Joints { angles, .. }, Some(_)) => angles.iter().skip(1).map(Vec::len).sum(),
        _ => 0,
    }
}

/// The camera (non-point) parameters' share of the leverage of one residual component:
/// `p_camera / (2 n)`.
fn camera_parameter_share(result: &BundleResult) -> f64 {
    let n = result.report.observations.max(1) as f64;
    let cameras = result.covariance.names.len() as f64;
    cameras / (2.0 * n)
}

/// Standard deviation of an observation's residual in units of the pixel noise, under the
/// average-leverage approximation: a point seen `k` times spends its 3 parameters over
/// `2 k` residual components (leverage `3 / 2k` each), the camera parameters theirs over
/// all of them (`camera_share`). A fitted residual has variance `(1 - h) sigma^2`, the
/// prediction error of an observation left out of the fit `(1 + h) sigma^2` (the classical
/// internally / externally studentised residuals). Clamped to [0.3, 2] (`k` = 2: the point
/// is fixed by that observation alone).
pub fn residual_scale(k: usize, camera_share: f64, fitted: bool) -> f64 {
    let h = 3.0 / (2.0 * k.max(2) as f64) + camera_share.max(0.0);
    let v = if fitted { 1.0 - h } else { 1.0 + h };
    v.clamp(0.09, 4.0).sqrt()
}

/// The fraction of its variance that a 2D isotropic Gaussian keeps when truncated to
/// `|r| <= c sigma`: `|r|^2 / sigma^2` is chi-square with 2 degrees of freedom
/// (exponential with mean 2), so `E[|r|^2 | |r| <= c sigma] / (2 sigma^2) =
/// 1 - (c^2 / 2) e^(-c^2/2) / (1 - e^(-c^2/2))` (0.987 at c = 3.5; 1 as c grows).
pub fn truncated_variance_factor(c: f64) -> f64 {
    if !(c.is_finite() && c > 0.0) {
        return 1.0;
    }
    let t = 0.5 * c * c;
    let tail = (-t).exp();
    1.0 - t * tail / (1.0 - tail)
}

/// Noise estimate of a least-squares solution whose observations were selected by
/// `|r| <= c sigma` (studentised): `sqrt(RSS / ((m - p) kappa(c)))` with `RSS` the sum of
/// squared pixel residuals, `m = 2 n + priors` the residual count, `p` the parameters
/// (points included) and `kappa` [`truncated_variance_factor`]. The angle priors, nearly
/// hard constraints, contribute about no residual but fix one parameter each, hence their
/// count in `m`. `None` without redundancy.
pub fn truncated_noise_estimate(result: &BundleResult, priors: usize, c: f64) -> Option<f64> {
    let r = &result.report;
    let m = 2 * r.observations + priors;
    let dof = m.checked_sub(r.parameters).filter(|&d| d > 0)? as f64;
    let rss = r.final_rms_px.powi(2) * r.observations as f64;
    let s = (rss / (dof * truncated_variance_factor(c))).sqrt();
    (s.is_finite() && s > 0.0).then_some(s.max(1e-9))
}
