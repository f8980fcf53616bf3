//! The Levenberg-Marquardt iteration of the rig bundle adjustment and its public entry
//! points (module docs of [`crate::bundle`], section Algorithm).
//!
//! # What it computes
//!
//! [`bundle_adjust`] minimises the robust cost of `problem.rs` over the camera parameters
//! and the points (their count of dof: `layout.rs` plus 3 per used point); the variants
//! hold the scene's depth scale near a target ([`bundle_adjust_at_depth_scale`], a
//! profile-likelihood point), hold named camera parameters
//! ([`bundle_adjust_holding`]), or ask a callback after some iterations whether to go on
//! ([`bundle_adjust_with_checkpoint`]). All run `adjust`, in named steps: `setup` (the
//! problem, the depth constraint, the held parameters), the iteration ([`crate::lm::run`]
//! on `Adjustment`: `keep_going` at the checkpoint, the linearisation of `normal.rs`, the
//! step by `candidate`), `noise_sigma` and the covariance (`covariance.rs`).
//!
//! The iteration is the project's one Levenberg-Marquardt ([`crate::lm`]: its damping
//! policy, Nielsen's rule from `lambda = 1e-3`, and its stopping rules) with the
//! point-Schur back end (`normal.rs`); a step is accepted only if the robust cost
//! decreases, so the result is never worse than the start. The stopping tolerances are
//! [`BundleOptions`]'s `function_tolerance` and `parameter_tolerance`, the state norm of
//! the parameter tolerance `x_norm` (intrinsics, baseline and used points); the damping
//! limit counts as converged, `max_iterations` does not. The noise for the covariance is
//! `noise_sigma_px`, or estimated from the residuals (`noise_sigma`, module docs,
//! Covariance). Costs are half squared pixels, tolerances relative.
//!
//! # Pitfalls
//!
//! - A far point whose step would cross infinity keeps its position for that step;
//!   rejecting the whole step for it would stall the solver from rough starts.
//! - The checkpoint changes nothing: a run that goes on is bit-identical to
//!   [`bundle_adjust`]'s, and one that converges before the checkpoint is never asked.
//! - The order of the stopping tests and the damping constants are part of every result
//!   (the experiments' outputs are compared cell for cell).
//! - A held or depth-constrained run reports the covariance of the data and priors alone
//!   (over the parameters left free), and `final_rms_px` of the pixels alone.

use nalgebra::{DVector, Vector3};

use super::covariance::covariance;
use super::layout::{Layout, Param, retract, retract_point};
use super::normal::Normal;
use super::prior::angle_prior_chi2;
use super::problem::{Eval, Problem, problem};
use super::robust::RobustLoss;
use super::state::{BundleObservation, BundleOptions, BundleReport, BundleResult, Motions, RigState};
use crate::{GeometryError, Result, lm};

/// Refine a rig state on the observations. See the module documentation.
pub fn bundle_adjust(
    initial: &RigState,
    observations: &[BundleObservation],
    options: &BundleOptions,
) -> Result<BundleResult> {
    adjust(initial, observations, options, None, None, &[])?.ok_or_else(never_abandoned)
}

/// What [`bundle_adjust_with_checkpoint`] shows its callback: the accepted state after
/// `iterations` iterations, not converged.
#[derive(Debug, Clone, Copy)]
pub struct BundleCheckpoint<'a> {
    /// The current (best so far) state.
    pub state: &'a RigState,
    /// Iterations done.
    pub iterations: usize,
    /// RMS reprojection error of the state over the used observations, pixels.
    pub rms_px: f64,
    /// Observations used.
    pub observations: usize,
}

impl BundleCheckpoint<'_> {
    /// [`BundleResult::chi2`] of the checkpoint's state (the same expression, so a caller
    /// comparing it with a finished result's compares like with like).
    pub fn chi2(&self, noise_px: f64, options: &BundleOptions) -> f64 {
        chi2_of(self.rms_px, self.observations, &self.state.motions, noise_px, options)
    }
}

/// The least-squares cost in chi-square units of `observations` residuals with RMS
/// `rms_px` at noise `noise_px`, plus the angle prior's chi-square under `options`
/// ([`BundleResult::chi2`], [`BundleCheckpoint::chi2`]).
pub(super) fn chi2_of(
    rms_px: f64,
    observations: usize,
    motions: &Motions,
    noise_px: f64,
    options: &BundleOptions,
) -> f64 {
    rms_px.powi(2) * observations as f64 / (noise_px * noise_px) + angle_prior_chi2(motions, options)
}

/// [`bundle_adjust`] that, if still not converged after `at_iteration` iterations, asks
/// `keep_going` whether to continue; `Ok(None)` when it says no. The run that continues is
/// exactly [`bundle_adjust`]'s (the solver is deterministic and the check changes
/// nothing), so a caller that would give up on a hopeless start pays for the iterations up
/// to the check only, and one that goes on does not repeat them (what running a short
/// probe and then the full adjustment from the start would cost).
pub fn bundle_adjust_with_checkpoint(
    initial: &RigState,
    observations: &[BundleObservation],
    options: &BundleOptions,
    at_iteration: usize,
    keep_going: &mut dyn FnMut(&BundleCheckpoint<'_>) -> bool,
) -> Result<Option<BundleResult>> {
    adjust(initial, observations, options, None, Some((at_iteration, keep_going)), &[])
}

/// The error for a run without a checkpoint that came back abandoned (cannot happen: only
/// the checkpoint's callback abandons).
fn never_abandoned() -> GeometryError {
    GeometryError::Numerical("the adjustment was abandoned without a checkpoint".into())
}

/// [`bundle_adjust`] with the scene's depth scale held near `target`: the stiff
/// pseudo-residual `(s - target) / tolerance` (cost units; `s` of [`log_depth_scale`] over
/// the adjusted points) joins the cost, so the result is the profile-likelihood point at
/// that depth scale (`tolerance` small against `sigma_s / sigma_px`). The reported
/// covariance and noise are those of the data and priors alone (the linearisation at the
/// profile point, without the constraint), and `final_rms_px` is of the pixels alone.
///
/// [`log_depth_scale`]: super::log_depth_scale
pub fn bundle_adjust_at_depth_scale(
    initial: &RigState,
    observations: &[BundleObservation],
    options: &BundleOptions,
    target: f64,
    tolerance: f64,
) -> Result<BundleResult> {
    if !(target.is_finite() && tolerance.is_finite() && tolerance > 0.0) {
        return Err(GeometryError::InvalidOption(format!(
            "depth-scale target {target} / tolerance {tolerance} must be finite, tolerance > 0"
        )));
    }
    adjust(initial, observations, options, Some((target, tolerance)), None, &[])?.ok_or_else(never_abandoned)
}

/// [`bundle_adjust`] with the named camera parameters (covariance names, e.g.
/// `right.fx`) held at their values in `initial`: the profile-likelihood point at those
/// values. The covariance is over the parameters left free. A name that is unknown or
/// not adjusted under `options` is [`GeometryError::InvalidOption`].
pub fn bundle_adjust_holding(
    initial: &RigState,
    observations: &[BundleObservation],
    options: &BundleOptions,
    held: &[&str],
) -> Result<BundleResult> {
    let held: Vec<Param> = held
        .iter()
        .map(|n| {
            Param::parse(n, initial).ok_or_else(|| GeometryError::InvalidOption(format!("no parameter {n}")))
        })
        .collect::<Result<_>>()?;
    adjust(initial, observations, options, None, None, &held)?.ok_or_else(never_abandoned)
}

/// The callback of [`bundle_adjust_with_checkpoint`] and the iteration count at which it
/// is asked.
type Checkpoint<'c> = (usize, &'c mut dyn FnMut(&BundleCheckpoint<'_>) -> bool);

/// The problem of [`adjust`] ([`problem`]) with the depth-scale constraint `depth` set and
/// the `held` parameters taken out of the layout. The tie `fy = fx` stays as the options
/// say, so a held `fy` is not tied to `fx`. A held parameter that is not free under the
/// options is [`GeometryError::InvalidOption`].
fn setup<'a>(
    initial: &RigState,
    observations: &[BundleObservation],
    options: &'a BundleOptions,
    depth: Option<(f64, f64)>,
    held: &[Param],
) -> Result<(RigState, Problem<'a>)> {
    let (state, mut problem) = problem(initial, observations, options)?;
    problem.depth = depth;
    if let Some(p) = held.iter().find(|p| !problem.layout.params.contains(p)) {
        return Err(GeometryError::InvalidOption(format!("{} is not a free parameter here", p.name())));
    }
    if !held.is_empty() {
        let kept = problem.layout.params.iter().copied().filter(|p| !held.contains(p)).collect();
        // A held `fy` is not a tie `fy = fx`: the tie follows the options.
        let square = problem.layout.square;
        problem.layout = Layout::from_params(kept, &state.motions)?;
        problem.layout.square = square;
    }
    Ok((state, problem))
}

/// The bundle adjustment as a [`lm::LeastSquares`] problem: the linearisation is the
/// point-Schur back end (`normal.rs`), the retraction [`candidate`], the evaluation the
/// robust cost, the state norm [`x_norm`]; the checkpoint's callback decides
/// [`lm::LeastSquares::keep_going`]; each iteration's normal equations come back
/// ([`lm::LeastSquares::recycle`]) to lend their storage to the next.
struct Adjustment<'p, 'a, 'c> {
    problem: &'p Problem<'a>,
    checkpoint: Option<Checkpoint<'c>>,
    n_obs: usize,
    /// The normal equations of the last iteration, whose storage the next linearisation
    /// reuses (`normal.rs`).
    spare: Option<Normal>,
}

impl lm::Evaluation for Eval {
    fn cost(&self) -> f64 {
        self.cost
    }
}

impl lm::LeastSquares for Adjustment<'_, '_, '_> {
    type State = RigState;
    type Normal = Normal;
    type Eval = Eval;
    type Error = GeometryError;

    fn linearise(&mut self, state: &RigState) -> Result<Option<Normal>> {
        match self.problem.normal_equations_reusing(state, self.problem.prior_weight, self.spare.take()) {
            Some(n) => Ok(Some(n)),
            None => Err(GeometryError::Numerical("linearisation failed at an accepted state".into())),
        }
    }

    fn retract(
        &self,
        state: &RigState,
        step: &(DVector<f64>, Vec<Vector3<f64>>),
    ) -> Result<Option<(RigState, f64)>> {
        candidate(self.problem, state, &step.0, &step.1).map(Some)
    }

    fn evaluate(&self, state: &RigState) -> Option<Eval> {
        self.problem.evaluate(state)
    }

    fn state_norm(&self, state: &RigState) -> f64 {
        x_norm(state, &self.problem.points)
    }

    fn keep_going(&mut self, iterations: usize, state: &RigState, current: &Eval) -> bool {
        keep_going(&mut self.checkpoint, iterations, state, current, self.n_obs)
    }

    fn recycle(&mut self, normal: Normal) {
        self.spare = Some(normal);
    }
}

/// Whether the iteration goes on at `iterations` done: asks the checkpoint's callback if
/// this is its iteration (showing it the accepted `state` and its RMS over the `n_obs`
/// used observations), true otherwise. False abandons the run.
fn keep_going(
    checkpoint: &mut Option<Checkpoint<'_>>,
    iterations: usize,
    state: &RigState,
    current: &Eval,
    n_obs: usize,
) -> bool {
    if let Some((at, ask)) = checkpoint.as_mut()
        && iterations == *at
    {
        let seen =
            BundleCheckpoint { state, iterations, rms_px: rms(current.sum_sq, n_obs), observations: n_obs };
        return ask(&seen);
    }
    true
}

/// The state moved by the step `(dc, dp)` (camera parameters by [`retract`], each used
/// point by [`retract_point`]) and the squared norm of the step as taken (the camera
/// step's plus each point's Euclidean move).
fn candidate(
    problem: &Problem<'_>,
    state: &RigState,
    dc: &DVector<f64>,
    dp: &[Vector3<f64>],
) -> Result<(RigState, f64)> {
    let mut cand = retract(state, &problem.layout, dc)?;
    let mut step_sq = dc.norm_squared();
    for (&pi, d) in problem.points.iter().zip(dp) {
        if let Some(x) = cand.points.get_mut(pi) {
            // A far point whose step would cross infinity keeps its position for this
            // step; rejecting the whole step for it stalls the solver from rough
            // starts (the damping grows until no step moves anything).
            if let Some(p) = retract_point(x, d) {
                step_sq += (p - *x).norm_squared();
                *x = p;
            }
        }
    }
    Ok((cand, step_sq))
}

/// The pixel noise for the covariance at the solution `state` (module docs, Covariance):
/// `noise_sigma_px` if given, else estimated from the `m = 2 n_obs + prior rows` residuals
/// with `n_params` parameters fitted: `sqrt(sum w |r|^2 / (m - n))` for plain least
/// squares, `median |r| / sqrt(2 ln 2) * sqrt(m / (m - n))` under a robust loss (the median
/// of Rayleigh-distributed residual norms, which outliers hardly move). Too few residuals
/// for the estimate is [`GeometryError::NotEnoughData`].
fn noise_sigma(
    problem: &Problem<'_>,
    state: &RigState,
    options: &BundleOptions,
    n_obs: usize,
    n_params: usize,
) -> Result<f64> {
    let m = 2 * n_obs + problem.prior_terms(state).len();
    let sigma = match options.noise_sigma_px {
        Some(s) => s,
        None => {
            if m <= n_params {
                return Err(GeometryError::NotEnoughData {
                    what: "residuals beyond parameters to estimate the noise",
                    needed: n_params + 1,
                    got: m,
                });
            }
            let dof = m as f64 / (m - n_params) as f64;
            match options.robust {
                RobustLoss::None => {
                    let Some(n) = problem.normal_equations(state, 1.0) else {
                        return Err(GeometryError::Numerical("linearisation failed at the solution".into()));
                    };
                    (n.sum_wsq / (m - n_params) as f64).sqrt()
                }
                RobustLoss::Huber { .. } | RobustLoss::Cauchy { .. } => {
                    // Outliers would inflate sum w r^2; use the median residual norm instead
                    // (Rayleigh: median = sigma sqrt(2 ln 2)), corrected for the fitted dof.
                    let Some(mut norms) = problem.residual_norms(state) else {
                        return Err(GeometryError::Numerical("residuals failed at the solution".into()));
                    };
                    norms.sort_by(f64::total_cmp);
                    let med = norms.get(norms.len() / 2).copied().unwrap_or(0.0);
                    med / (2.0 * std::f64::consts::LN_2).sqrt() * dof.sqrt()
                }
            }
        }
    };
    Ok(sigma)
}

/// The adjustment behind every entry point: [`setup`], then Levenberg-Marquardt (module
/// docs of this file) from `initial` until a stopping rule or `max_iterations`, asking the
/// `checkpoint` (if any) at its iteration (`Ok(None)` when it abandons), then the noise
/// ([`noise_sigma`]) and the covariance at the solution. `depth`: the depth-scale
/// constraint `(target, tolerance)` of [`bundle_adjust_at_depth_scale`]; `held`: the
/// parameters [`bundle_adjust_holding`] holds.
fn adjust(
    initial: &RigState,
    observations: &[BundleObservation],
    options: &BundleOptions,
    depth: Option<(f64, f64)>,
    checkpoint: Option<Checkpoint<'_>>,
    held: &[Param],
) -> Result<Option<BundleResult>> {
    let (state, problem) = setup(initial, observations, options, depth, held)?;
    let nc = problem.layout.len();
    let n_params = nc + 3 * problem.points.len();
    let n_obs = problem.obs.len();

    let Some(first) = problem.evaluate(&state) else {
        return Err(GeometryError::Numerical("the initial cost is not finite".into()));
    };
    let initial_rms_px = rms(first.sum_sq, n_obs);
    let lm_options = lm::LmOptions {
        max_iterations: options.max_iterations,
        function_tolerance: options.function_tolerance,
        parameter_tolerance: options.parameter_tolerance,
    };
    let mut adjustment = Adjustment { problem: &problem, checkpoint, n_obs, spare: None };
    let out = lm::run(&mut adjustment, state, first, &lm_options)?;
    if out.termination == lm::Termination::Abandoned {
        return Ok(None);
    }
    let lm::Outcome { state, value: current, iterations, termination } = out;
    let (converged, termination) = (termination.converged(), termination.reason().to_string());

    // Covariance at the solution.
    let sigma = noise_sigma(&problem, &state, options, n_obs, n_params)?;
    let (covariance, sigma_inflation) = covariance(&problem, &state, sigma, options.covariance_model, None)?;
    Ok(Some(BundleResult {
        state,
        report: BundleReport {
            iterations,
            initial_rms_px,
            final_rms_px: rms(current.sum_sq, n_obs),
            converged,
            termination,
            observations: n_obs,
            parameters: n_params,
            sigma_px: sigma,
            sigma_inflation,
        },
        covariance,
    }))
}

fn x_norm(state: &RigState, points: &[usize]) -> f64 {
    let mut s = state.right_from_left.translation.vector.norm_squared();
    for k in [&state.left, &state.right] {
        s += k.fx * k.fx + k.fy * k.fy + k.skew * k.skew + k.cx * k.cx + k.cy * k.cy;
    }
    for &p in points {
        if let Some(x) = state.points.get(p) {
            s += x.coords.norm_squared();
        }
    }
    s.sqrt()
}

fn rms(sum_sq: f64, n: usize) -> f64 {
    if n == 0 { 0.0 } else { (sum_sq / n as f64).sqrt() }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bundle::test_support::{distorted, state_distance};
    use crate::distortion::Distortion;
    use crate::synthetic::{perturb, synth};

    /// Noise-free data have zero residual at the truth, the gauge (view 0, baseline length)
    /// is fixed, so the truth is the isolated minimum; LM ends in Gauss-Newton with zero
    /// residual, which converges quadratically to rounding level (~1e-12). 1e-8 leaves room
    /// for the conditioning of 3 deg rotations (which amplifies rounding by ~1e3-1e4).
    #[test]
    fn joints_noise_free_converges_to_truth() {
        let s = synth(2, 200, 0.0, 0.0, false);
        let start = perturb(&s.truth, 20);
        assert!(state_distance(&start, &s.truth) > 1e-3);
        let res = bundle_adjust(&start, &s.obs, &BundleOptions::default()).unwrap();
        let d = state_distance(&res.state, &s.truth);
        assert!(res.report.converged, "{:?}", res.report);
        assert!(res.report.final_rms_px < 1e-8, "{:?}", res.report);
        assert!(d < 1e-8, "distance to truth {d:e}, {:?}", res.report);
    }

    /// The checkpoint changes nothing when the callback goes on (the same state to the
    /// bit, the same report), shows the state a run capped at that many iterations ends
    /// with (same chi-square), and abandons when told to.
    #[test]
    fn a_checkpoint_that_goes_on_is_the_plain_run() {
        let s = synth(5, 120, 1.0, 0.0, false);
        let start = perturb(&s.truth, 20);
        let options =
            BundleOptions { noise_sigma_px: Some(1.0), robust: RobustLoss::None, ..Default::default() };
        let plain = bundle_adjust(&start, &s.obs, &options).unwrap();
        assert!(plain.report.converged && plain.report.iterations > 3, "{:?}", plain.report);
        let at = 2;
        let capped =
            bundle_adjust(&start, &s.obs, &BundleOptions { max_iterations: at, ..options.clone() }).unwrap();
        let mut seen = Vec::new();
        let mut go_on = |c: &BundleCheckpoint<'_>| {
            seen.push((c.iterations, c.chi2(1.0, &options), c.state.left.fx));
            true
        };
        let checked =
            bundle_adjust_with_checkpoint(&start, &s.obs, &options, at, &mut go_on).unwrap().unwrap();
        assert_eq!(seen, vec![(at, capped.chi2(1.0, &options), capped.state.left.fx)]);
        assert_eq!(format!("{:?}", checked.report), format!("{:?}", plain.report));
        assert_eq!(format!("{:?}", checked.state), format!("{:?}", plain.state));
        assert_eq!(checked.covariance.matrix, plain.covariance.matrix);
        let mut stop = |_: &BundleCheckpoint<'_>| false;
        assert!(bundle_adjust_with_checkpoint(&start, &s.obs, &options, at, &mut stop).unwrap().is_none());
        // A run that converges before the checkpoint never asks.
        let mut never = |_: &BundleCheckpoint<'_>| -> bool { panic!("asked after convergence") };
        let late = plain.report.iterations + 1;
        let done =
            bundle_adjust_with_checkpoint(&start, &s.obs, &options, late, &mut never).unwrap().unwrap();
        assert_eq!(done.report.iterations, plain.report.iterations);
    }

    /// Two disconnected segments of a 30-view sequence (the sparse Schur path), each with
    /// its points in the frame of its first view: with the second segment's first view
    /// held (`gauge_views`) the noise-free problem converges to the truth (1e-8 as in
    /// `joints_noise_free_converges_to_truth`); without it the second segment can move
    /// rigidly at no cost and the covariance says a parameter is unobservable; a gauge at
    /// view 0 or beyond the views is refused.
    #[test]
    fn segments_converge_with_their_gauges() {
        let seq = crate::synthetic::sequence(5, 30, 2, 400, 0.0);
        let mut start = perturb(&seq.synth.truth, 6);
        if let Motions::Free { ref_from_cam } = &mut start.motions {
            for &g in &seq.gauge_views {
                ref_from_cam[g] = nalgebra::Isometry3::identity();
            }
        }
        let obs = &seq.synth.obs;
        let options = BundleOptions { gauge_views: seq.gauge_views.clone(), ..BundleOptions::default() };
        let res = bundle_adjust(&start, obs, &options).unwrap();
        let d = state_distance(&res.state, &seq.synth.truth);
        assert!(res.report.converged && d < 1e-8, "distance to truth {d:e}, {:?}", res.report);
        assert!(
            res.covariance.index("view15.rot0").is_none() && res.covariance.index("view16.rot0").is_some()
        );
        let e = bundle_adjust(&start, obs, &BundleOptions::default()).unwrap_err().to_string();
        assert!(e.contains("unobservable"), "{e}");
        for bad in [vec![0], vec![30]] {
            let o = BundleOptions { gauge_views: bad, ..BundleOptions::default() };
            assert!(matches!(bundle_adjust(&start, obs, &o), Err(GeometryError::InvalidOption(_))));
        }
    }

    #[test]
    fn free_noise_free_converges_to_truth() {
        let s = synth(3, 200, 0.0, 0.0, true);
        let start = perturb(&s.truth, 30);
        let res = bundle_adjust(&start, &s.obs, &BundleOptions::default()).unwrap();
        let d = state_distance(&res.state, &s.truth);
        assert!(res.report.converged, "{:?}", res.report);
        assert!(d < 1e-8, "distance to truth {d:e}, {:?}", res.report);
    }

    /// Noise-free distorted data from a pinhole start (K ~1.5 % off, distortion zero): the
    /// truth is the isolated zero-residual minimum, so LM ends in Gauss-Newton at rounding
    /// level; 1e-8 as in `joints_noise_free_converges_to_truth` (k1, k2 absolute, order 0.1).
    #[test]
    fn distortion_noise_free_converges_to_truth() {
        for (seed, free) in [(15, false), (16, true)] {
            let s = distorted(seed, 200, free);
            let mut start = perturb(&s.truth, seed * 10);
            start.left_distortion = Distortion::default();
            start.right_distortion = Distortion::default();
            // Without distortion in the model the fit cannot reach zero residual.
            let pinhole = bundle_adjust(&start, &s.obs, &BundleOptions::default()).unwrap();
            assert!(pinhole.report.final_rms_px > 0.05, "{:?}", pinhole.report);
            let opts = BundleOptions { estimate_distortion: true, ..BundleOptions::default() };
            let res = bundle_adjust(&start, &s.obs, &opts).unwrap();
            let d = state_distance(&res.state, &s.truth);
            eprintln!(
                "free={free}: pinhole rms {:.3} px fx {:.2} (true {:.2}); with distortion rms {:.1e}, distance {d:.1e}",
                pinhole.report.final_rms_px, pinhole.state.left.fx, s.truth.left.fx, res.report.final_rms_px
            );
            assert!(res.report.converged, "{:?}", res.report);
            assert!(res.report.final_rms_px < 1e-8, "{:?}", res.report);
            assert!(d < 1e-8, "distance to truth {d:e}, {:?}", res.report);
            for n in ["left.k1", "left.k2", "right.k1", "right.k2"] {
                assert!(res.covariance.index(n).is_some(), "{n} missing");
            }
            // perturbed() understands the distortion names.
            let mut delta = DVector::zeros(res.covariance.names.len());
            delta[res.covariance.index("right.k2").unwrap_or(0)] = 0.01;
            let moved = res.perturbed(&delta).unwrap();
            let k2 = |d: &crate::distortion::Distortion| d.param("k2").unwrap();
            assert!((k2(&moved.right_distortion) - k2(&res.state.right_distortion) - 0.01).abs() < 1e-15);
        }
    }

    /// Noise-free data through the other lens models, every coefficient free: the
    /// equidistant model (`k1..k4`) from the zero equidistant lens, the full
    /// radial-tangential model (`k1 k2 p1 p2 k3`) from the pinhole, and the double sphere
    /// (`xi alpha`) from `xi 0, alpha 0.5`, all with `K` ~1.5 % off: the truth is again the
    /// zero-residual minimum (1e-8 as above).
    #[test]
    fn other_lens_models_noise_free_converge_to_truth() {
        use crate::distortion::{DistortionTerms, LensKind};
        let equi = [
            Distortion::equidistant([0.02, -0.01, 0.003, -0.001]),
            Distortion::equidistant([-0.03, 0.01, 0.0, 0.0]),
        ];
        let radtan = [
            Distortion::from_params(LensKind::RadialTangential, [-0.2, 0.05, 1e-3, -5e-4, 0.01, 0.0]),
            Distortion::from_params(LensKind::RadialTangential, [-0.15, 0.03, -8e-4, 6e-4, -0.005, 0.0]),
        ];
        let ds = [Distortion::double_sphere(-0.15, 0.58), Distortion::double_sphere(0.1, 0.52)];
        for (seed, lenses, start_lens, terms) in [
            (17, equi, Distortion::zero(LensKind::Equidistant), DistortionTerms::Full4),
            (18, radtan, Distortion::default(), DistortionTerms::Full5),
            (19, ds, Distortion::double_sphere(0.0, 0.5), DistortionTerms::Radial2),
        ] {
            let s = crate::bundle::test_support::distorted_with(seed, 200, true, lenses);
            let mut start = perturb(&s.truth, seed * 10);
            start.left_distortion = start_lens;
            start.right_distortion = start_lens;
            let opts = BundleOptions {
                estimate_distortion: true,
                distortion_terms: terms,
                ..BundleOptions::default()
            };
            let res = bundle_adjust(&start, &s.obs, &opts).unwrap();
            let d = state_distance(&res.state, &s.truth);
            assert!(res.report.converged, "{:?}", res.report);
            assert!(res.report.final_rms_px < 1e-8, "{:?}", res.report);
            assert!(d < 1e-8, "{terms:?}: distance to truth {d:e}, {:?}", res.report);
            let names: Vec<&str> = lenses[0].kind.coefficient_names().to_vec();
            for n in names.iter().filter(|n| {
                **n != "k3" || terms == DistortionTerms::Full5 || lenses[0].kind == LensKind::Equidistant
            }) {
                assert!(res.covariance.index(&format!("left.{n}")).is_some(), "left.{n} missing");
            }
        }
    }

    /// Holding a camera parameter: at its own estimate the profile point is the estimate,
    /// and at `+-2 sigma` it stays there while everything else re-adjusts, the cost rising
    /// by about 4 in chi-square (exactly 4 for a linear model; measured 3.66-4.38 on this
    /// 80-point scene at 1 px, the model's curvature, so 2.5-6 is allowed),
    /// without the held parameter in the covariance. A held `fy` is not tied to `fx`;
    /// an unknown name, or one the options do not adjust, is an error.
    #[test]
    fn holding_a_parameter_gives_its_profile_likelihood() {
        let base = synth(12, 80, 1.0, 0.0, false);
        let opts =
            BundleOptions { robust: RobustLoss::None, noise_sigma_px: Some(1.0), ..BundleOptions::default() };
        let est = bundle_adjust(&perturb(&base.truth, 120), &base.obs, &opts).unwrap();
        assert!(est.report.converged, "{:?}", est.report);
        let same = bundle_adjust_holding(&est.state, &base.obs, &opts, &["right.fx"]).unwrap();
        assert!(
            state_distance(&same.state, &est.state) < 1e-6,
            "{}",
            state_distance(&same.state, &est.state)
        );
        assert!(same.covariance.index("right.fx").is_none() && same.covariance.index("right.fy").is_some());
        for name in ["right.fx", "left.fy"] {
            let sigma = est.covariance.sigma(name).unwrap();
            for sign in [-2.0, 2.0] {
                let mut start = est.state.clone();
                let held = match name {
                    "right.fx" => &mut start.right.fx,
                    _ => &mut start.left.fy,
                };
                *held += sign * sigma;
                let target = *held;
                let end = bundle_adjust_holding(&start, &base.obs, &opts, &[name]).unwrap();
                let got = if name == "right.fx" { end.state.right.fx } else { end.state.left.fy };
                assert_eq!(got, target, "{name} not held");
                let dchi2 = end.chi2(1.0, &opts) - est.chi2(1.0, &opts);
                eprintln!("{name} at {sign:+} sigma: chi-square rise {dchi2:.3}");
                assert!((2.5..6.0).contains(&dchi2), "{name} {sign}: chi-square rise {dchi2}");
            }
        }
        assert!(bundle_adjust_holding(&est.state, &base.obs, &opts, &["right.focal"]).is_err());
        // Distortion is not estimated under these options: nothing to hold.
        assert!(bundle_adjust_holding(&est.state, &base.obs, &opts, &["left.k1"]).is_err());
    }
}
