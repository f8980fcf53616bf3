//! The run of a lens model whose field reaches beyond 90 deg (the double sphere; the
//! lens table's `max_half_fov_deg`), [`calibrate_wide`]: no pinhole image of such a lens
//! exists, so the chain's linear steps cannot see its captured pixels.
//!
//! What it computes:
//! 1. **the lens-grid run** ([`wide_grid_start`], then the chain of
//!    [`super::calibrate_rig`] from it): per half field at the image's horizontal edge of
//!    [`wide_grid_fields`] (50-110 deg), the stereographic double sphere (`xi = 0`,
//!    `alpha = 1/2`: `r = 2 f tan(theta / 2)`) with that field; the pixels undistorted with
//!    it, the rays within [`WIDE_CHAIN_MAX_RAY_DEG`] of the axis only, F and the 3D
//!    homographies fitted; the lens whose homographies keep the most quadruplets conditions
//!    the chain (its `K` is the rigid start's), and the chain's adjustment runs on every
//!    captured pixel of its points with the model free, a point left out triangulated from
//!    bearings (`adjust::triangulate_bearings`);
//! 2. **candidates along the f-xi valley** ([`candidate`]): near the axis the double
//!    sphere's pixel scale is `f / (1 + xi)`, and over the central field `f`, `xi` and
//!    `alpha` trade along a long curved valley with more than one minimum (measured on the
//!    180-deg session of the tests, seed 1 at 0.5 px: the run ends at `xi` 0.21 for a true
//!    -0.15, f +42 %, at the same RMS as the truth's to 1e-4 px). From the run's result and
//!    from starts along the valley (`xi` of [`wide_xi_starts`], `f` moved to keep
//!    `f / (1 + xi)` and `alpha` to keep the pixel of a ray at 60 deg, [`along_valley`]):
//!    least squares on the run's observations; then every stereo track the central linear
//!    steps never reconstructed (those seen only far from the axis, up to and beyond
//!    90 deg), triangulated from that candidate's bearings in one stereo view, with its
//!    observations within [`WIDE_GATE`] re-selection gates ([`add_wide_points`]), one
//!    robust adjustment over all, and least squares on the observations re-selected;
//! 3. **the choice**: the candidate with the lowest sum of squares over the run's own
//!    observations (common to all; each square capped at [`WIDE_GATE`] re-selection
//!    gates'). A cost over each candidate's own selection would compare different sets: on
//!    the rendered 180-deg session (seed 1, 0.05 px) the cost over every observation with
//!    capped squares kept the far end of the valley (f +42 %), which the sum of squares on
//!    the common observations rejects (10.23 px^2 against 10.15 from the truth, about 30
//!    chi-square units at 0.05 px).
//!
//! Degrees of freedom and units: those of the adjustment (the model's `xi alpha` per
//! camera); pixels; degrees for ray angles and fields.
//!
//! The grid's lenses and the valley's starts run in parallel (rayon), reduced in their
//! order: the same result at any thread count.
//!
//! Pitfalls: the grid assumes the image's horizontal edge is 50-110 deg off the axis (a
//! wide lens); a narrow lens calibrated with a wide model has its own, pinhole-plane route
//! only through `--lens auto`'s refit. The report's `start` names the kept start (`xi
//! scan` when a scan start won).

use std::collections::HashMap;

use headalign_geometry::bundle::{
    BundleObservation, BundleOptions, BundleResult, RigState, RobustLoss, Side, bundle_adjust,
    residual_pixels,
};
use headalign_geometry::camera::Intrinsics;
use headalign_geometry::distortion::{Distortion, LensKind};
use rayon::prelude::*;

use super::two_pass::LensStart;
use super::{CalibrateOptions, LensModel, MotionCalibration, calibrate_once_from, with_restarts};
use crate::error::AlignError;
use crate::observations::View;

/// True for a model whose field reaches beyond 90 deg (the lens table's metadata): its
/// run is [`calibrate_wide`].
pub(super) fn is_wide(kind: LensKind) -> bool {
    kind.model().max_half_fov_deg() > 90.0
}

/// Steps 1-3 of the module docs.
pub(super) fn calibrate_wide(
    views: &[View],
    options: &CalibrateOptions,
    kind: LensKind,
) -> Result<MotionCalibration, AlignError> {
    let start = wide_grid_start(views, options, kind).ok_or_else(|| {
        AlignError::MissingMotion(format!(
            "no {} lens of the grid gives every view a 3D homography (rays within {WIDE_CHAIN_MAX_RAY_DEG} deg)",
            kind.kalibr_name()
        ))
    })?;
    let run =
        with_restarts(options, |o, seeded| calibrate_once_from(views, o, seeded, Some(&start), None, None))?;
    let rig = super::depth::select_views(views, options)?;
    Ok(choose_along_valley(run, &rig.rig, options))
}

/// The largest ray angle from the axis (degrees) in the linear steps of a wide model's
/// run (the double sphere's): the pinhole image of the grid lens is well conditioned
/// there (a pinhole stretches a ray at 60 deg by 4x its central scale), and rays beyond
/// 90 deg have no pinhole pixel at all.
pub const WIDE_CHAIN_MAX_RAY_DEG: f64 = 60.0;

/// The half fields (degrees) at the image's horizontal edge of the grid lenses of
/// [`wide_grid_start`]: 50 to 110 deg in steps of 10.
fn wide_grid_fields() -> impl Iterator<Item = f64> {
    (5..=11).map(|i| f64::from(i) * 10.0)
}

/// [`grid_start`] for a wide model (the double sphere): per half field `phi` of
/// [`wide_grid_fields`], the model's stereographic lens (the lens table's
/// `stereographic`; `None` for a model without one; the double sphere's `xi = 0`, `alpha =
/// 1/2`: `r = 2 f tan(theta / 2)`) whose focal length puts `phi` at the image's horizontal
/// edge, the
/// pixels undistorted with it (rays within [`WIDE_CHAIN_MAX_RAY_DEG`]) and steps 2-3 of the
/// chain run; the lens whose 3D homographies keep the most quadruplets wins, and its `K`
/// conditions the chain and starts the rigid start. `None` if no lens gives every view a
/// homography.
fn wide_grid_start(views: &[View], options: &CalibrateOptions, kind: LensKind) -> Option<LensStart> {
    crate::timing::time(crate::timing::Stage::LensChoice, || {
        let rig = super::depth::select_views(views, options).ok()?;
        let [w, h] = rig.image_size;
        let guess = Intrinsics::rough_guess(w, h);
        let d = Distortion::from_params(kind, kind.model().stereographic()?);
        let lenses: Vec<LensModel> = wide_grid_fields()
            .map(|phi| {
                let phi = phi.to_radians();
                let f = 0.5 * f64::from(w) * (0.5 + 0.5 * phi.cos()) / phi.sin();
                LensModel { k: Intrinsics::new(f, f, guess.cx, guess.cy), distortion: d }
            })
            .collect();
        // Each lens scored on its own (in parallel), the best taken in the grid's order.
        let scores: Vec<Option<(usize, super::two_pass::GridFit)>> = lenses
            .par_iter()
            .map(|&lens| {
                crate::timing::time(crate::timing::Stage::LensChoice, || {
                    let start = LensStart {
                        chain: [lens; 2],
                        distortion: [lens.distortion; 2],
                        max_ray_deg: Some(WIDE_CHAIN_MAX_RAY_DEG),
                        fitted: None,
                    };
                    super::two_pass::grid_fit(&start.chain_views(&rig.rig), &lens.k, options)
                })
            })
            .collect();
        super::two_pass::best_scored(lenses.into_iter().zip(scores)).map(|(_, (lens, fit))| LensStart {
            chain: [lens; 2],
            distortion: [lens.distortion; 2],
            max_ray_deg: Some(WIDE_CHAIN_MAX_RAY_DEG),
            fitted: Some(std::sync::Arc::new(fit)),
        })
    })
}

/// The shifts `xi` of the valley starts of [`choose_along_valley`]: -0.6 to 0.6 in steps of 0.2.
fn wide_xi_starts() -> impl Iterator<Item = f64> {
    (-3..=3).map(|i| f64::from(i) * 0.2)
}

/// The lens with shift `xi` in the f-xi valley of `(k, d)` (the lens table's
/// `along_focal_valley`; the double sphere's: `f` scaled to keep the central pixel scale
/// `f / (1 + xi)`, and `alpha` chosen so that a ray at [`WIDE_CHAIN_MAX_RAY_DEG`] (the edge
/// of the linear steps' field) lands on the same pixel radius); `(k, d)` unchanged for a
/// model without the valley.
fn along_valley(k: &Intrinsics, d: &Distortion, xi: f64) -> (Intrinsics, Distortion) {
    let theta = WIDE_CHAIN_MAX_RAY_DEG.to_radians();
    match d.kind.model().along_focal_valley(&d.params(), xi, theta) {
        Some((scale, params)) => {
            (Intrinsics { fx: k.fx * scale, fy: k.fy * scale, ..*k }, Distortion::from_params(d.kind, params))
        }
        None => (*k, *d),
    }
}

/// Re-selection gates (of the candidate's noise estimate) within which an observation of
/// a track added by [`add_wide_points`] enters the candidate's robust adjustment (as the every-point
/// pass's first gate, `adjust::FIRST_PASS_GATE`): wide enough for a far-field residual of
/// a lens still in the f-xi valley, narrow enough to keep mismatches out.
pub const WIDE_GATE: f64 = 4.0;

/// One candidate of step 2: its adjustment, the track of each point, its observations, and
/// whether it started along the valley.
struct Candidate {
    bundle: BundleResult,
    tracks: Vec<u64>,
    observations: Vec<BundleObservation>,
    scanned: bool,
}

/// Steps 2-3 of the module docs on the run `run` of the rig views `rig`; the run with the
/// kept candidate's adjustment, points, observations and report numbers (`start` is `xi
/// scan` when a valley start won). Only the double sphere has the valley; other models
/// pass unchanged.
fn choose_along_valley(
    mut run: MotionCalibration,
    rig: &[View],
    options: &CalibrateOptions,
) -> MotionCalibration {
    let lens = run.bundle.state.left_distortion;
    let theta = WIDE_CHAIN_MAX_RAY_DEG.to_radians();
    if lens.kind.model().along_focal_valley(&lens.params(), 0.0, theta).is_none() {
        return run;
    }
    let gate = options.estimation.reselect_sigmas * run.report.sigma_px.max(0.05);
    // Each start adjusted on its own (in parallel), the lowest cost taken in their order.
    let xis: Vec<Option<f64>> = std::iter::once(None).chain(wide_xi_starts().map(Some)).collect();
    let candidates: Vec<Option<Candidate>> = xis
        .par_iter()
        .map(|&xi| {
            crate::timing::time(crate::timing::Stage::Adjustment, || {
                let mut start = run.bundle.state.clone();
                if let Some(xi) = xi {
                    for (k, d) in [
                        (&mut start.left, &mut start.left_distortion),
                        (&mut start.right, &mut start.right_distortion),
                    ] {
                        (*k, *d) = along_valley(k, d, xi);
                    }
                }
                candidate(start, &run, rig, options)
            })
        })
        .collect();
    let mut best: Option<(f64, Candidate)> = None;
    for (xi, c) in xis.into_iter().zip(candidates) {
        let Some(mut c) = c else { continue };
        c.scanned = xi.is_some();
        let cost = common_cost(&c, &run.observations, WIDE_GATE * gate);
        if cost.is_finite() && best.as_ref().is_none_or(|(b, _)| cost < *b) {
            best = Some((cost, c));
        }
    }
    if let Some((_, c)) = best {
        run.report.bundle_observations = c.observations.len();
        run.report.bundle_points = c.tracks.len();
        run.report.final_rms_px = c.bundle.report.final_rms_px;
        run.report.sigma_px = c.bundle.report.sigma_px;
        run.report.focal_sigma_pct = super::report::focal_sigma_pct(&c.bundle);
        if c.scanned {
            run.report.start = "xi scan".into();
        }
        run.observations = c.observations;
        run.point_tracks = c.tracks;
        run.bundle = c.bundle;
    }
    run
}

/// Step 2 of the module docs for one start; `None` if an adjustment fails.
fn candidate(
    start: RigState,
    run: &MotionCalibration,
    rig: &[View],
    options: &CalibrateOptions,
) -> Option<Candidate> {
    let est = super::rig_bundle::adjustment_options(options);
    let ls = BundleOptions {
        robust: RobustLoss::None,
        noise_sigma_px: None,
        max_iterations: est.bundle.max_iterations.max(crate::verge_tilt::FINAL_ITERATIONS),
        ..est.bundle.clone()
    };
    let fit = bundle_adjust(&start, &run.observations, &ls).ok()?;
    let sigma = fit.report.sigma_px.max(0.05);
    let (state, tracks, obs) = add_wide_points(
        fit.state,
        &run.point_tracks,
        &run.observations,
        rig,
        WIDE_GATE * est.reselect_sigmas * sigma,
    );
    let robust = bundle_adjust(&state, &obs, &est.bundle).ok()?;
    let gate = est.reselect_sigmas * robust.report.sigma_px.max(0.05);
    let selected = with_two_observations(
        obs.into_iter()
            .filter(|o| residual_pixels(&robust.state, o).is_some_and(|r| r.norm() <= gate))
            .collect(),
        robust.state.points.len(),
    );
    let bundle = bundle_adjust(&robust.state, &selected, &ls).ok()?;
    Some(Candidate { bundle, tracks, observations: selected, scanned: false })
}

/// The observations of points that keep at least two of them.
fn with_two_observations(mut obs: Vec<BundleObservation>, points: usize) -> Vec<BundleObservation> {
    let mut counts = vec![0usize; points];
    for o in &obs {
        if let Some(c) = counts.get_mut(o.point) {
            *c += 1;
        }
    }
    obs.retain(|o| counts.get(o.point).is_some_and(|&c| c >= 2));
    obs
}

/// Step 3's cost: over the run's own observations (common to every candidate: a
/// candidate's points extend the run's), the squared residual under the candidate capped
/// at `cap^2`.
fn common_cost(c: &Candidate, observations: &[BundleObservation], cap: f64) -> f64 {
    let cap2 = cap * cap;
    observations
        .iter()
        .map(|o| residual_pixels(&c.bundle.state, o).map_or(cap2, |r| r.norm_squared().min(cap2)))
        .sum()
}

/// Every track with a stereo match in some rig view that `tracks` has no point of,
/// triangulated from the bearings of `state` in the first view that matches it
/// (`adjust::triangulate_bearings`), with all its observations in the rig views within
/// `gate` pixels under `state` (a point needs 2): the state with the points added, the
/// tracks and the observations (`observations` and these).
fn add_wide_points(
    mut state: RigState,
    tracks: &[u64],
    observations: &[BundleObservation],
    rig: &[View],
    gate: f64,
) -> (RigState, Vec<u64>, Vec<BundleObservation>) {
    let mut tracks = tracks.to_vec();
    let mut index: HashMap<u64, usize> = tracks.iter().enumerate().map(|(i, &t)| (t, i)).collect();
    let first_new = tracks.len();
    for (slot, v) in rig.iter().enumerate() {
        let right: HashMap<u64, nalgebra::Point2<f64>> =
            v.capture.right.iter().map(|o| (o.track, o.pixel)).collect();
        for o in &v.capture.left {
            let Some(r) = right.get(&o.track) else { continue };
            if index.contains_key(&o.track) {
                continue;
            }
            if let Some(p) = super::rig_bundle::triangulate_bearings(&state, &o.pixel, r) {
                index.insert(o.track, tracks.len());
                tracks.push(o.track);
                state.points.push(state.motions.ref_from_cam(slot) * p);
            }
        }
    }
    let mut added = Vec::new();
    for (slot, v) in rig.iter().enumerate() {
        for (side, list) in [(Side::Left, &v.capture.left), (Side::Right, &v.capture.right)] {
            for o in list {
                if let Some(&point) = index.get(&o.track).filter(|&&i| i >= first_new) {
                    let obs = BundleObservation { point, view: slot, side, pixel: o.pixel };
                    if residual_pixels(&state, &obs).is_some_and(|r| r.norm() <= gate) {
                        added.push(obs);
                    }
                }
            }
        }
    }
    let mut obs = observations.to_vec();
    obs.extend(with_two_observations(added, state.points.len()));
    (state, tracks, obs)
}
