//! Steps 5 and 6 of the chain ([`super`] module docs): the maximum-likelihood rig bundle
//! adjustment from each start, the pass over every point seen at least twice, and the
//! choice between the starts' results.
//!
//! The adjustment (shared with [`crate::verge_tilt`]: [`adjust_from_starts`]) minimises the
//! reprojection error (pixels) over both cameras' intrinsics (5 dof each less the
//! options' constraints, plus the estimated lens coefficients of `options.lens`), the rig's
//! relative pose (5 dof: the baseline is the scale gauge), a free 6-dof pose per moved
//! view and 3 dof per point, with a robust loss and re-selection at `reselect_sigmas`
//! times the estimated noise (paper section 3.1, "refine"; Hartley & Zisserman 2nd ed.,
//! section 18.1 and appendix 6). Then [`every_point_pass`] (step 6). Each start is
//! adjusted to convergence and the two results are compared on the same observations
//! (all of them, each squared residual truncated at the re-selection gate of the noisier
//! result, floor 0.05 px): each adjustment re-selects its own inliers, and a result that
//! keeps fewer of them would look better by its own RMS.
//!
//! With a lens estimated, a third start can join (`super::two_pass`): another run's
//! result (the lens-grid run's cameras, lenses and motions) with this run's points
//! triangulated under it, compared on the same truncated cost.
//!
//! The starts are adjusted in parallel (rayon) and compared in their order: the same
//! result at any thread count.
//!
//! Pitfalls: with one general motion the cost has shallow valleys: a start that screens
//! better after a few iterations can end in the worse minimum, hence every start to
//! convergence. The adjustment is seeded by nothing, but its starts are (step 3): when it
//! fails from both, the run is retried with the next seed.

use headalign_geometry::bundle::residual_pixels;
use headalign_geometry::bundle::{
    BundleObservation, BundleOptions, RigState, RobustLoss, Side, bundle_adjust,
};
use headalign_geometry::camera::{ProjectiveCamera, dehomogenise3};
use headalign_geometry::distortion::Distortion;
use headalign_geometry::triangulation::triangulate_linear;
use nalgebra::{Isometry3, Point2, Point3};
use rayon::prelude::*;

use super::CalibrateOptions;
use super::bundle_starts::PointSet;
use crate::error::AlignError;
use crate::verge_tilt::{
    Adjustment, DEPTH_RATIO, EstimationOptions, FINAL_ITERATIONS, Reconstruction, adjust_from_starts,
};

/// Steps 5 and 6 (module docs): adjust from each start (`starts[0]` the linear one, `[1]`
/// the rigid one), run [`every_point_pass`] on each result, keep the one with the lower
/// truncated cost over all observations. The error of the last start that failed if both
/// did. With the lens estimated, the starts carry `start_lens` (left, right), or the
/// model's zero lens when it is `None`. `other`, when given, is a third start: the
/// cameras, lenses and motions of another run's result (the lens-grid run of
/// [`super::two_pass`]) with this run's points triangulated under them ([`transplant`]),
/// so that the starts' minima are compared on the same observations.
pub(super) fn adjust_starts(
    starts: [Result<RigState, AlignError>; 2],
    points: &PointSet,
    recon: &[Reconstruction],
    options: &CalibrateOptions,
    start_lens: Option<[Distortion; 2]>,
    other: Option<&RigState>,
) -> Result<Adjustment, AlignError> {
    crate::timing::time(crate::timing::Stage::Adjustment, || {
        let est = &options.estimation;
        let (first_obs, all_obs) = (&points.first_obs, &points.all_obs);
        let (point_tracks, origin_slot) = (&points.point_tracks, &points.origin_slot);
        let adjust_options = adjustment_options(options);
        let kind = options.lens.kind();
        let sources = PointSources { point_tracks, origin_slot, recon };
        // The start's lens: `start_lens`, else zero in the estimated model (the equidistant
        // one's zero is `atan`, a mild barrel: a fair start for a wide lens).
        let mut all_starts: Vec<Result<RigState, AlignError>> = starts
            .into_iter()
            .map(|start| {
                start.map(|mut s| {
                    if let Some(kind) = kind {
                        [s.left_distortion, s.right_distortion] =
                            start_lens.unwrap_or([Distortion::zero(kind), Distortion::zero(kind)]);
                    }
                    s
                })
            })
            .collect();
        if let Some(other) = other {
            all_starts.push(Ok(transplant(other, &sources)));
        }
        // Each start adjusted on its own (in parallel), the results kept in the starts'
        // order: the same choice at any thread count.
        let adjusted: Vec<Result<Adjustment, AlignError>> = all_starts
            .into_par_iter()
            .enumerate()
            .map(|(index, start)| {
                crate::timing::time(crate::timing::Stage::Adjustment, || {
                    let mut a = adjust_from_starts(
                        vec![start],
                        first_obs,
                        all_obs,
                        point_tracks,
                        origin_slot,
                        recon,
                        &adjust_options,
                    )?;
                    a.start_index = index;
                    Ok(every_point_pass(a, all_obs, &sources, &adjust_options))
                })
            })
            .collect();
        let mut results: Vec<Adjustment> = Vec::new();
        let mut last_error = None;
        for a in adjusted {
            match a {
                Ok(a) => results.push(a),
                Err(e) => last_error = Some(e),
            }
        }
        let gate = est.reselect_sigmas * results.iter().map(|a| a.last.report.sigma_px).fold(0.05, f64::max);
        let truncated_cost = |a: &Adjustment| -> f64 {
            all_obs
                .iter()
                .map(|o| {
                    residual_pixels(&a.last.state, o)
                        .map_or(gate * gate, |r| r.norm_squared().min(gate * gate))
                })
                .sum()
        };
        let adjusted = results.into_iter().min_by(|a, b| truncated_cost(a).total_cmp(&truncated_cost(b)));
        adjusted.ok_or_else(|| {
            last_error.unwrap_or_else(|| AlignError::MissingMotion("no initialisation".into()))
        })
    })
}

/// Steps 5 and 6 for many motions (a sequence's: the cost has one clear valley there):
/// both starts screened by the short adjustment of [`adjust_from_starts`], only the better
/// one (by its MSAC score) adjusted to convergence and through [`every_point_pass`]. Half
/// the cost of [`adjust_starts`], which takes both to convergence for the shallow valleys
/// of one or two motions.
pub(super) fn adjust_best_start(
    starts: [Result<RigState, AlignError>; 2],
    points: &PointSet,
    recon: &[Reconstruction],
    options: &CalibrateOptions,
) -> Result<Adjustment, AlignError> {
    crate::timing::time(crate::timing::Stage::Adjustment, || {
        let adjust_options = adjustment_options(options);
        let (point_tracks, origin_slot) = (&points.point_tracks, &points.origin_slot);
        let a = adjust_from_starts(
            starts.into_iter().collect(),
            &points.first_obs,
            &points.all_obs,
            point_tracks,
            origin_slot,
            recon,
            &adjust_options,
        )?;
        let sources = PointSources { point_tracks, origin_slot, recon };
        Ok(every_point_pass(a, &points.all_obs, &sources, &adjust_options))
    })
}

/// The estimation options of the adjustment: the options' constraints and lens model set
/// in its bundle options.
pub(super) fn adjustment_options(options: &CalibrateOptions) -> EstimationOptions {
    let mut adjust_options = options.estimation.clone();
    adjust_options.bundle.zero_skew = options.zero_skew;
    adjust_options.bundle.square_pixels = options.square_pixels;
    adjust_options.bundle.fix_principal_point = options.fix_principal_point;
    adjust_options.bundle.estimate_distortion = options.lens.kind().is_some();
    adjust_options.bundle.distortion_terms = options.lens_terms;
    adjust_options
}

/// Where each bundle point came from: its track, the rig view that first reconstructed
/// it, and the per-view stereo reconstructions.
struct PointSources<'a> {
    point_tracks: &'a [u64],
    origin_slot: &'a [usize],
    recon: &'a [Reconstruction],
}

/// A point the adjustment did not use, triangulated (linear, undistorted pixels) from the
/// stereo match of the view that first reconstructed it with the calibrated rig of
/// `state`, in the reference frame; `None` if it does not lie in front of both cameras.
fn triangulate_in_state(state: &RigState, src: &PointSources<'_>, i: usize) -> Option<Point3<f64>> {
    let slot = *src.origin_slot.get(i)?;
    let (_, l, r) = src.recon.get(slot)?.get(src.point_tracks.get(i)?)?;
    if [state.left_distortion.kind, state.right_distortion.kind].into_iter().any(super::wide::is_wide) {
        return triangulate_bearings(state, l, r).map(|p| state.motions.ref_from_cam(slot) * p);
    }
    let l = state.left_distortion.undistort_pixel(&state.left, l).ok()?;
    let r = state.right_distortion.undistort_pixel(&state.right, r).ok()?;
    let p_l = ProjectiveCamera::from_pose(&state.left, &Isometry3::identity());
    let p_r = ProjectiveCamera::from_pose(&state.right, &state.right_from_left);
    let x = triangulate_linear(&p_l, &p_r, &l, &r).ok()?;
    let p = dehomogenise3(&x)?;
    (p.z > 0.0 && (state.right_from_left * p).z > 0.0).then(|| state.motions.ref_from_cam(slot) * p)
}

/// The midpoint of the closest approach of the two cameras' bearings of a stereo match
/// (the lens models' unprojection, [`Distortion::unproject_pixel`]), in the left camera's
/// frame: the triangulation of a wide lens, whose rays may lie beyond 90 deg where a
/// pinhole pixel does not exist. `None` for rays that do not unproject, near-parallel rays
/// (1 - cos^2 of their angle below 1e-12) or a point behind either camera along its ray.
pub(super) fn triangulate_bearings(
    state: &RigState,
    l: &Point2<f64>,
    r: &Point2<f64>,
) -> Option<Point3<f64>> {
    let bl = state.left_distortion.unproject_pixel(&state.left, l).ok()?;
    let br = state.right_distortion.unproject_pixel(&state.right, r).ok()?;
    let left_from_right = state.right_from_left.inverse();
    let c = left_from_right.translation.vector;
    let dr = left_from_right.rotation * br;
    // Minimise |s bl - (c + u dr)|: the 2x2 normal equations.
    let (a, b, cc) = (bl.dot(&bl), bl.dot(&dr), dr.dot(&dr));
    let (d, e) = (bl.dot(&c), dr.dot(&c));
    let det = a * cc - b * b;
    if det.is_nan() || det <= 1e-12 {
        return None;
    }
    let s = (d * cc - b * e) / det;
    let u = (b * d - a * e) / det;
    (s > 0.0 && u > 0.0).then(|| Point3::from((bl * s + c + dr * u) * 0.5))
}

/// The start of [`adjust_starts`] from another run's result `other`: its cameras, lenses,
/// rig and motions, and every point of `src` triangulated under them
/// ([`triangulate_in_state`]; a point that does not triangulate in front of both cameras
/// is put at the reference camera's centre, where it projects nowhere and the screening
/// leaves it out until the adjustment re-triangulates it). The rig views must be the same
/// (they are: the view selection is deterministic).
fn transplant(other: &RigState, src: &PointSources<'_>) -> RigState {
    let mut state = RigState {
        left: other.left,
        right: other.right,
        left_distortion: other.left_distortion,
        right_distortion: other.right_distortion,
        right_from_left: other.right_from_left,
        motions: other.motions.clone(),
        points: Vec::new(),
    };
    let points: Vec<Point3<f64>> = (0..src.point_tracks.len())
        .map(|i| triangulate_in_state(&state, src, i).unwrap_or_else(Point3::origin))
        .collect();
    state.points = points;
    state
}

/// Width of the first gate of [`every_point_pass`], in re-selection gates (about 14
/// sigmas, 7 px at 0.5 px noise). Measured: 3, 4 and 6 give the same one-motion results
/// (seeds 1-20, point mode) and keep the rendered barrel-lens session within 0.5 %.
const FIRST_PASS_GATE: f64 = 4.0;

/// Step 6 (module docs): the adjustment over the observations of every point seen at
/// least twice. The shared adjustment ([`adjust_from_starts`]) keeps only points seen in
/// at least four images, which for one motion of a rig leaves out the points seen by one
/// stereo view only (more than half of the observations, and with them the rig's
/// epipolar geometry over the whole image), and its re-selection gate, applied at a
/// solution in a wrong valley of the shallow one-motion cost, drops exactly the
/// observations that disagree with that valley. So: the points it left out are
/// triangulated with its calibration, one adjustment under the robust loss takes every
/// observation within [`FIRST_PASS_GATE`] re-selection gates (points with at least 2,
/// depths within `DEPTH_RATIO` of the median), then
/// plain least squares on those within `reselect_sigmas` of it, re-selected until stable
/// (at most 3 times). Measured on the one-general-motion session (point mode, 0.5 px,
/// seeds 1-20): the sigma of f falls by up to 2x, and seed 17 (the robust stage 7.2 %
/// off, bound 0.26 %) ends at 0.41 %, the minimum an adjustment started at the truth
/// reaches. Stereo-only points cannot bend to a wrong match beyond the epipolar residual
/// F already checked. A failed adjustment keeps the previous result.
fn every_point_pass(
    adjusted: Adjustment,
    all_obs: &[BundleObservation],
    src: &PointSources<'_>,
    options: &EstimationOptions,
) -> Adjustment {
    let mut state = adjusted.last.state.clone();
    let mut used = vec![false; state.points.len()];
    for o in &adjusted.observations {
        if let Some(u) = used.get_mut(o.point) {
            *u = true;
        }
    }
    for (i, u) in used.iter().enumerate() {
        if !u && let Some(p) = triangulate_in_state(&state, src, i) {
            state.points[i] = p;
        }
    }
    let ls = BundleOptions {
        robust: RobustLoss::None,
        noise_sigma_px: None,
        max_iterations: options.bundle.max_iterations.max(FINAL_ITERATIONS),
        ..options.bundle.clone()
    };
    let key = |o: &BundleObservation| (o.point, o.view, o.side == Side::Left);
    let mut best = adjusted;
    let mut sigma = best.last.report.sigma_px;
    let mut previous: Vec<(usize, usize, bool)> = Vec::new();
    for pass in 0..4 {
        // The first pass takes the observations within FIRST_PASS_GATE re-selection gates
        // under the robust loss, so that those that disagree with a solution in a wrong
        // valley can pull it out (the re-selection gate at once would drop exactly those
        // and keep the valley); gross outliers stay out (with every observation under the
        // Huber loss, the rendered barrel-lens session moved f by 2.3 %).
        let gate = options.reselect_sigmas * sigma.max(0.05) * if pass == 0 { FIRST_PASS_GATE } else { 1.0 };
        let gated: Vec<BundleObservation> = all_obs
            .iter()
            .copied()
            .filter(|o| residual_pixels(&state, o).is_some_and(|r| r.norm() <= gate))
            .collect();
        let mut counts = vec![0usize; state.points.len()];
        for o in &gated {
            counts[o.point] += 1;
        }
        let mut dist: Vec<f64> = (0..state.points.len())
            .filter(|&i| counts[i] >= 2)
            .map(|i| state.points[i].coords.norm())
            .collect();
        dist.sort_by(f64::total_cmp);
        let Some(&median) = dist.get(dist.len() / 2) else { break };
        let tame = |i: usize| {
            let d = state.points[i].coords.norm();
            d.is_finite() && d <= median * DEPTH_RATIO && d >= median / DEPTH_RATIO
        };
        let obs: Vec<BundleObservation> =
            gated.into_iter().filter(|o| counts[o.point] >= 2 && tame(o.point)).collect();
        let keys: Vec<(usize, usize, bool)> = obs.iter().map(key).collect();
        if (keys == previous && pass > 1) || obs.len() < options.min_tracks {
            break;
        }
        let robust = BundleOptions { robust: options.bundle.robust, ..ls.clone() };
        let Ok(result) = bundle_adjust(&state, &obs, if pass == 0 { &robust } else { &ls }) else { break };
        sigma = result.report.sigma_px;
        state = result.state.clone();
        previous = keys;
        best = Adjustment { last: result, observations: obs, ..best };
    }
    best
}
