//! Step 8 of the estimation ([`super`]): the least squares restarted from rigs with the
//! baseline's signs changed, the lower of the likelihood minima kept (an addition to the
//! paper's procedure: the rig bundle adjustment (`docs/how-it-works.md#the-rig-bundle-adjustment`) has more
//! than one minimum when the scene is far against the baseline).
//!
//! The scene is far against the baseline (median depth about 20 baselines), so the rig
//! with its baseline reversed (x component, or all of it) is a second least-squares
//! minimum with the points' depth order reversed; likewise the baseline with its y and z
//! components reversed (a forward component's sign is weakly determined too). And a
//! baseline more than 45 deg from the right camera's x axis is no stereo head's, so the
//! baseline along that axis, both ways, is tried as well. From each such rig (the 3
//! translation dof changed, everything else kept, every point re-triangulated by
//! [`super::adjust::retriangulate_points_by_support`]) the least squares is restarted
//! ([`reversed_rig_restart`]); a restart wins only if it keeps every observation in front
//! of the cameras and lowers the cost (prior included) by [`RESTART_MIN_GAIN`] at the
//! same noise; the maximum-likelihood pass then re-classifies from it. No ground truth is
//! used.
//!
//! Units: costs in chi-square units (squared residuals over the noise variance, prior
//! included). Pitfall: most restarts from a reversed rig do not converge in 300
//! iterations (far points creep towards infinity) and were most of the estimate's time;
//! hopeless ones are abandoned after a probe ([`restart_adjustment`]).

use headalign_geometry::bundle::{
    BundleCheckpoint, BundleObservation, BundleOptions, BundleResult, RigState, RobustLoss,
    bundle_adjust_with_checkpoint,
};
use nalgebra::Vector3;

use super::EstimationOptions;
use super::adjust::{FINAL_ITERATIONS, PointSources, retriangulate_points_by_support};
use super::likelihood::maximum_likelihood_pass;
use crate::error::AlignError;

/// [Estimation](super) step 8: the least squares restarted from the depth-reversed rig. The
/// scene is far compared with the baseline (median depth about 20 baselines), so the
/// horizontal disparity that the baseline adds to the vergence's is small and nearly
/// constant over the points: the rig with the baseline's x component (right camera
/// frame) reversed, plus a small change of relative yaw and principal point, fits the
/// images almost as well, with the depth order of the points reversed around the
/// fixation distance. Both are least-squares minima and the solver stays in the one its
/// start leads to. Measured once (no command reproduces it; seed 39, position 2, at 2 and
/// 3 px): the estimate had t = (+0.98, -0.11, -0.13) against (-0.98, -0.00, -0.19) at the
/// truth, right cx 63 px (6 sigma) off, and its cost was 40 (chi-square units) above the
/// minimum reached from the truth; from the reversed start the least squares reaches that
/// minimum (right cx 14 px off). Three restarts ([`RESTART_BASELINE_FLIPS`]; two more,
/// the baseline along the x axis both ways, when the estimate's is more than 45 deg from it,
/// [`SIDEWAYS_RESTART_MAX_COS`]), each with
/// every point re-triangulated under the restarted rig from the stereo match that agrees
/// best with its fitted observations ([`retriangulate_points_by_support`]): the x
/// component reversed, the whole baseline reversed (the other sign of `E`), and the y and z
/// components reversed (fig5-verge-tilt seeds 1119, 1130, 1211 at 3 px ended 2.9-5.5
/// chi-square units above the minimum reached from the truth; this start reaches it,
/// `docs/accuracy.md`). A restart wins only if it keeps every
/// observation in front of the cameras and lowers the cost (prior included) at the same
/// noise; the maximum-likelihood pass then re-classifies the observations from it. No
/// ground truth is used: this is the lower of two likelihood minima.
pub(super) fn reversed_rig_restart(
    current: BundleResult,
    obs: Vec<BundleObservation>,
    candidates: &[BundleObservation],
    points: &PointSources<'_>,
    options: &EstimationOptions,
) -> Result<(BundleResult, Vec<BundleObservation>), AlignError> {
    let noise = current.report.sigma_px;
    if !(noise.is_finite() && noise > 0.0) {
        return Ok((current, obs));
    }
    let ls = BundleOptions {
        max_iterations: options.bundle.max_iterations.max(FINAL_ITERATIONS),
        robust: RobustLoss::None,
        noise_sigma_px: Some(noise),
        ..options.bundle.clone()
    };
    let base = current.chi2(noise, &options.bundle);
    // Costs are non-negative: below the gain no restart can win (the noise-free runs of
    // the experiments' Cramer-Rao bound, where a restart ran up to 300 iterations in vain).
    if base < RESTART_MIN_GAIN {
        return Ok((current, obs));
    }
    let every = vec![true; current.state.points.len()];
    let mut best: Option<(BundleResult, f64)> = None;
    let t = current.state.right_from_left.translation.vector;
    let mut baselines: Vec<Vector3<f64>> =
        RESTART_BASELINE_FLIPS.iter().map(|f| t.component_mul(f)).collect();
    // A baseline far from the cameras' x axes is no stereo head's: restart side by side too.
    if t.x.abs() < SIDEWAYS_RESTART_MAX_COS * t.norm() {
        baselines.extend([-1.0, 1.0].map(|sign| Vector3::x() * (sign * t.norm())));
    }
    for baseline in baselines {
        let mut start = current.state.clone();
        start.right_from_left.translation.vector = baseline;
        retriangulate_points_by_support(&mut start, points, &every, &obs, options.reselect_sigmas * noise);
        // A restart that fails or loses observations (points behind a camera) is no
        // competitor: its cost is over fewer residuals.
        let Some(r) = restart_adjustment(&start, &obs, &ls, noise, base) else { continue };
        if r.report.observations != current.report.observations {
            continue;
        }
        let cost = r.chi2(noise, &options.bundle);
        if cost < base - RESTART_MIN_GAIN && best.as_ref().is_none_or(|(_, c)| cost < *c) {
            best = Some((r, cost));
        }
    }
    match best {
        Some((won, _)) => maximum_likelihood_pass(&won, candidates, &obs, points, options),
        None => Ok((current, obs)),
    }
}

/// The restarts' baseline sign changes (right camera frame, multiplied component-wise):
/// the x component reversed, the whole baseline reversed, and its y and z components
/// reversed (the product of the other two: with the estimate, the four form the group of
/// these sign changes). The third, measured once (no command reproduces it; fig5-verge-tilt seed
/// 1211, position 0, 3 px): the estimate had t = (-0.74, +0.19, +0.64), the minimum the
/// least squares reaches from the truth t = (-0.73, -0.43, -0.53) at 3.2 chi-square units
/// lower cost; the y-z reversed start reaches it (57 iterations), the other two do not. A
/// forward baseline component adds a disparity nearly proportional to the image radius
/// over a far scene, which a focal-length ratio absorbs, so its sign is as weakly
/// determined as the depth order of step 8 (the two minima differ in left and right fx by
/// 2-3 sigma).
const RESTART_BASELINE_FLIPS: [Vector3<f64>; 3] =
    [Vector3::new(-1.0, 1.0, 1.0), Vector3::new(-1.0, -1.0, -1.0), Vector3::new(1.0, -1.0, -1.0)];

/// Cosine of the angle between the estimated baseline and the right camera's x axis below
/// which [`reversed_rig_restart`] also restarts with the baseline along that axis, both
/// ways (45 deg). A stereo head's cameras sit side by side: verged by up to 20 deg the
/// baseline is within about 20 deg of each camera's x axis. Measured once (no command
/// reproduces it; calibration seed 368 at 3 px): the estimate's baseline was (0.01, -0.36, -0.93), 84 deg
/// from the truth's (-0.99, 0.00, -0.13), along the optical axis, with left fx 146 px
/// (3.7 sigma) off, 127 chi-square units above the minimum the least squares reaches from
/// the truth; no sign change of that baseline is near it.
const SIDEWAYS_RESTART_MAX_COS: f64 = std::f64::consts::FRAC_1_SQRT_2;

/// One restart's least squares ([`reversed_rig_restart`]) with an early exit for the
/// hopeless ones: one still unconverged after [`RESTART_PROBE_ITERATIONS`] and more than
/// [`RESTART_ABANDON_GAP`] above the estimate's cost `base` there is given up (`None`, no
/// competitor); any other goes on to the full iteration budget
/// ([`bundle_adjust_with_checkpoint`]: its result is exactly what the full run alone
/// gives; before, a probe of that many iterations was run and then the whole adjustment
/// again from `start`: `fig5-verge-tilt --trials 100` 38.4 -> 36.2 s). Measured
/// (`experiment coverage`/`fig5-verge-tilt`, 2-3 px): most restarts from the reversed rig
/// do not converge in 300 iterations (far points creep towards infinity) and end tens to
/// thousands of chi-square units above the estimate; they were most of the estimate's
/// time.
fn restart_adjustment(
    start: &RigState,
    obs: &[BundleObservation],
    ls: &BundleOptions,
    noise: f64,
    base: f64,
) -> Option<BundleResult> {
    let mut hopeful = |probe: &BundleCheckpoint<'_>| probe.chi2(noise, ls) <= base + RESTART_ABANDON_GAP;
    bundle_adjust_with_checkpoint(start, obs, ls, RESTART_PROBE_ITERATIONS, &mut hopeful).ok().flatten()
}

/// Iterations of a restart's first, probing least squares ([`restart_adjustment`]).
const RESTART_PROBE_ITERATIONS: usize = 50;

/// Cost above the estimate's (chi-square units) at which a restart still unconverged after
/// [`RESTART_PROBE_ITERATIONS`] is given up ([`restart_adjustment`]). Measured over 258
/// restarts at 1-3 px with noise (logged `experiment` runs: coverage, fig5-verge-tilt,
/// calibration): the 4 that won (by 0.6-1.6 units) were
/// between 1 below and 82 above the estimate there; of the 104 above 200, none came below
/// it in 300 iterations. Twice the largest winner's gap, for margin.
const RESTART_ABANDON_GAP: f64 = 200.0;

/// Smallest cost decrease (chi-square units) for which a restart replaces the estimate
/// ([`reversed_rig_restart`]): far below the 40 between the two minima of seed 39 and far
/// above the solver's tolerance, so a restart that re-converges to the same minimum never
/// replaces it.
const RESTART_MIN_GAIN: f64 = 0.5;
