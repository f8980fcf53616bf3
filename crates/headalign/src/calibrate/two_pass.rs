//! The starts of a self-calibration that estimates a lens model
//! ([`super::CalibrateOptions::lens`]): the chain on the captured pixels, and the chain
//! on pixels undistorted by a lens chosen on a grid, compared on the same observations.
//!
//! What it computes, [`calibrate_two_pass`]:
//! 1. **a lens to undistort with** ([`grid_start`]): per lens whose `k1` alone moves the
//!    image corner by -30 % to +30 % of its radius (steps of 5 %), the pixels undistorted
//!    with it and F, the frame and the 3D homographies fitted; the lens whose homographies
//!    keep the most quadruplets wins;
//! 2. **the lens-grid run**: the chain's steps 2-4 on the pixels undistorted with that
//!    lens, the adjustment on the captured pixels from starts that carry it;
//! 3. **the first estimate**: the chain of [`super::calibrate_rig`] on the captured
//!    pixels, its linear steps (F, the projective frame, the 3D homographies, the linear
//!    self-calibration) treating them as pinhole pixels, the adjustment with the lens
//!    terms free from three starts: the linear and the rigid one from the model's zero
//!    lens, and the lens-grid run's result (its cameras, lenses and motions, this run's
//!    points triangulated under them) when that is plausible. The start with the lowest
//!    truncated cost over this run's observations wins (`rig_bundle::adjust_starts`): the
//!    maximum-likelihood estimate is the lowest minimum found, whichever start reached it.
//!    Reported if it succeeds with every focal length in the plausible range
//!    ([`plausible`], [`MAX_FOCAL_WIDTHS`]); otherwise the lens-grid run's result if
//!    plausible (or if the first estimate failed outright).
//!
//! Why the lens-grid run's result as a start: with the procedure's 3 deg views the focal
//! length and `k1` share a long, shallow valley of the cost, and the linear and rigid
//! starts on distorted pixels can end in another minimum along it. Measured (`headalign
//! experiment lens --only 0.25,2 --trials 320`, 80 trials per condition, before this
//! start): radtan 0.25 px seed 6 ended at f +78-85 % (left fx 1249 for 700, `k1` -0.254) with
//! a truncated cost of 693 px^2, where the lens-grid run's result, adjusted on the same
//! observations, reaches f within 0.1 % at 477 px^2; seed 36 (f +15.5 %, cost 981 against
//! 358) and the fisheye's seed 36 (f +14 %, 1015 against 379) likewise. Those few trials
//! set the RMS focal error (radtan 0.25 px: 9.5 % RMS against a median of 0.54 %).
//!
//! Why the lens-grid run alone is not enough: with 10 deg views a barrel lens of
//! `k1 = -0.3` moves the corners of a 768 x 576 image by some 55 px. The linear steps see
//! that as projective error: F's RANSAC keeps mostly the centre, the quasi-Euclidean
//! frame is bent, and the 3D homographies read rotations of 0-11 deg (measured,
//! `experiment lens --rotation 10 --only 0.25`, seeds 1-40: the rigid 3-point motions
//! 0.1-11 deg for a true 10). The linear chain then fails and the rigid start can follow
//! the valley to the affine limit (f of 10^4-10^5 px, `k1` of 30-6600: 6 of 40 radtan
//! trials there); on undistorted pixels the remaining distortion is the grid lens's
//! error, nearly a pinhole problem where the linear chain works (40 of 40). Why the
//! first estimate's observations are the ones compared on: on the raw EuRoC pairs
//! (`real_data::euroc_raw_*` tests) the lens-grid run on its own keeps other tracks near
//! the border and ends with focal lengths 1.8-2.0 % short, against 0.9 % for the first
//! estimate.
//!
//! Degrees of freedom and units: none added (those of the adjustment); pixels; corner
//! displacements as fractions of the corner's radius; costs in pixels^2.
//!
//! The grid's lenses are scored in parallel (rayon) and reduced in the grid's order: the
//! same lens at any thread count. The winning lens's F and 3D homographies are kept
//! ([`LensStart::fitted`]): the lens-grid run with the same seed starts from them instead
//! of fitting them again.
//!
//! Pitfalls: a lens estimate costs 13 fits of F and the homographies, a second run of the
//! chain and a third adjustment of the first. The grid lens is normalised by the
//! image-size guess `K0`; the final adjustment refits everything. Observations the lens
//! cannot undistort are left out of the linear steps only. A true focal length beyond
//! [`MAX_FOCAL_WIDTHS`] image widths keeps the first estimate when the lens-grid run is
//! not plausible either. The pinhole ([`super::LensChoice::Pinhole`]) runs the chain
//! once, exactly as without this module.

use headalign_geometry::camera::Intrinsics;
use headalign_geometry::distortion::{Distortion, LensKind};
use rayon::prelude::*;

use super::fits::ChainFits;
use super::motion::ViewMotion;
use super::rig_stereo::StereoGeometry;
use super::{
    CalibrateOptions, LensModel, MotionCalibration, calibrate_once_from, calibrate_with_restarts,
    undistort_views, with_restarts,
};
use crate::error::AlignError;
use crate::observations::View;
use crate::verge_tilt::Reconstruction;

/// A focal length (`fx`, `fy` of either camera) more than this many image widths, or less
/// than its inverse, is not a plausible estimate ([`plausible`]): 20 widths is a field of
/// view of 2.9 deg, and the f-k1 valley's affine limit ends at 13-170 widths (module docs).
pub const MAX_FOCAL_WIDTHS: f64 = 5.0;

/// The lens start of a run of the chain: the lenses that undistort the pixels of its
/// linear steps (left, right), and the distortion its starts carry (step 3).
pub(super) struct LensStart {
    /// Lenses undistorting the linear steps' pixels (left, right).
    pub(super) chain: [LensModel; 2],
    /// The starts' distortion (left, right).
    pub(super) distortion: [Distortion; 2],
    /// Rays farther from the axis than this (degrees) are left out of the linear steps
    /// (a wide model's run, [`super::wide::WIDE_CHAIN_MAX_RAY_DEG`]); `None`: every ray in front.
    pub(super) max_ray_deg: Option<f64>,
    /// The stereo geometry and 3D homographies the grid fitted under [`Self::chain`] with
    /// the estimation seed it holds: the run with that seed takes them instead of fitting
    /// them again (the same inputs give the same result); `None`: fitted by the run.
    pub(super) fitted: Option<std::sync::Arc<GridFit>>,
}

/// What the lens grid fitted under its winning lens (steps 2-3 of the chain), for the run
/// from it ([`LensStart::fitted`]).
pub(super) struct GridFit {
    /// The estimation seed of the fit.
    pub(super) seed: u64,
    /// Step 2: F, frame, triangulation.
    pub(super) stereo: StereoGeometry,
    /// Step 3: the 3D homographies.
    pub(super) motions: Vec<ViewMotion>,
}

impl LensStart {
    /// The rig views as the linear steps see them: undistorted by [`Self::chain`], the
    /// rays beyond [`Self::max_ray_deg`] left out (of the linear steps only: the
    /// adjustment sees every observation of the points they reconstruct).
    pub(super) fn chain_views(&self, rig: &[View]) -> Vec<View> {
        let mut out = undistort_views(rig, &self.chain);
        if let Some(max) = self.max_ray_deg {
            let limit = max.to_radians().tan();
            for v in &mut out {
                for (list, lens) in
                    [(&mut v.capture.left, &self.chain[0]), (&mut v.capture.right, &self.chain[1])]
                {
                    list.retain(|o| lens.k.unproject(&o.pixel).xy().norm() < limit);
                }
            }
        }
        out
    }
}

/// True if every focal length of `c` is within [`MAX_FOCAL_WIDTHS`] of the image width
/// and finite.
pub(super) fn plausible(c: &MotionCalibration) -> bool {
    let w = f64::from(c.image_size[0].max(1));
    let s = &c.bundle.state;
    [s.left.fx, s.left.fy, s.right.fx, s.right.fy]
        .iter()
        .all(|f| f.is_finite() && *f <= MAX_FOCAL_WIDTHS * w && *f >= w / MAX_FOCAL_WIDTHS)
}

/// The stereo reconstructions `recon` (per rig view: track -> point, left pixel, right
/// pixel) with the pixels of the rig views `rig` in place of the undistorted ones; a
/// track missing from a view keeps the pixel it has.
pub(super) fn original_pixels(recon: &[Reconstruction], rig: &[View]) -> Vec<Reconstruction> {
    recon
        .iter()
        .zip(rig)
        .map(|(map, v)| {
            let left: std::collections::HashMap<u64, _> =
                v.capture.left.iter().map(|o| (o.track, o.pixel)).collect();
            let right: std::collections::HashMap<u64, _> =
                v.capture.right.iter().map(|o| (o.track, o.pixel)).collect();
            map.iter()
                .map(|(&t, &(x, l, r))| {
                    (t, (x, left.get(&t).copied().unwrap_or(l), right.get(&t).copied().unwrap_or(r)))
                })
                .collect()
        })
        .collect()
}

/// Steps 1-3 of the module docs; the pinhole is [`calibrate_with_restarts`] unchanged.
/// The first estimate's steps 2-3 are taken from `fits` when another run on the same
/// views fitted them with the same inputs ([`super::fits`]).
pub(super) fn calibrate_two_pass(
    views: &[View],
    options: &CalibrateOptions,
    fits: Option<&ChainFits>,
) -> Result<MotionCalibration, AlignError> {
    let Some(kind) = options.lens.kind() else {
        return calibrate_with_restarts(views, options);
    };
    if super::wide::is_wide(kind) {
        return super::wide::calibrate_wide(views, options, kind);
    }
    // The run on pixels undistorted by the grid's lens (steps 2-3).
    let second = grid_start(views, options, kind).map(|start| {
        with_restarts(options, |o, seeded| calibrate_once_from(views, o, seeded, Some(&start), None, None))
    });
    // The first estimate, its adjustment also started from the second run's result.
    let other = match &second {
        Some(Ok(c)) if plausible(c) => Some(&c.bundle.state),
        _ => None,
    };
    let first = with_restarts(options, |o, seeded| calibrate_once_from(views, o, seeded, None, other, fits));
    if first.as_ref().is_ok_and(plausible) {
        return first;
    }
    match second {
        Some(Ok(second)) if plausible(&second) || first.is_err() => Ok(second),
        Some(Err(e)) if first.is_err() => Err(e),
        _ => first,
    }
}

/// The corner displacements of [`grid_start`], fractions of the corner's radius
/// (negative: barrel): -30 % to +30 % in steps of 5 %.
fn grid_displacements() -> impl Iterator<Item = f64> {
    (-6..=6).map(|i| f64::from(i) * 0.05)
}

/// The lens of the model `kind` whose first parameter alone moves a point at normalised
/// radius `corner` radially by the fraction `delta` of its radius (the lens table's
/// `grid_lens`: `k1` of the radial-tangential and equidistant models; the double sphere's
/// `alpha` with `xi = 0`, barrel only). `None` where the model has no such lens (the
/// pinhole; the double sphere's pincushion).
fn grid_lens(kind: LensKind, delta: f64, corner: f64) -> Option<Distortion> {
    kind.model().grid_lens(delta, corner).map(|p| Distortion::from_params(kind, p))
}

/// Step 1's lens: per lens of the
/// model `kind` whose `k1` alone moves the image corner radially by a fraction
/// [`grid_displacements`] of its radius (under the image-size guess `K0`), the pixels
/// undistorted with it and steps 2-3 of the chain run (F, frame, 3D homographies); the
/// lens whose 3D homographies keep the most quadruplets (transfer error within the
/// options' threshold) wins. `None` if no lens gives every view a homography.
fn grid_start(views: &[View], options: &CalibrateOptions, kind: LensKind) -> Option<LensStart> {
    crate::timing::time(crate::timing::Stage::LensChoice, || {
        let rig = super::depth::select_views(views, options).ok()?;
        let [w, h] = rig.image_size;
        let k0 = Intrinsics::rough_guess(w, h);
        // The corner's normalised radius under K0 (and its angle from the axis).
        let corner = (k0.cx.hypot(k0.cy)) / k0.fx;
        // Each lens scored on its own (in parallel), the best taken in the grid's order.
        let lenses: Vec<Distortion> =
            grid_displacements().filter_map(|t| grid_lens(kind, t, corner)).collect();
        let scores: Vec<Option<(usize, GridFit)>> = lenses
            .par_iter()
            .map(|&d| {
                crate::timing::time(crate::timing::Stage::LensChoice, || {
                    let lens = LensModel { k: k0, distortion: d };
                    grid_fit(&undistort_views(&rig.rig, &[lens, lens]), &k0, options)
                })
            })
            .collect();
        best_scored(lenses.into_iter().zip(scores)).map(|(_, (d, fit))| LensStart {
            chain: [LensModel { k: k0, distortion: d }; 2],
            distortion: [d, d],
            max_ray_deg: None,
            fitted: Some(std::sync::Arc::new(fit)),
        })
    })
}

/// The candidate with the highest score among `scored` (in their order; `None` scores
/// left out), the first of equal ones, with what its score came with: the reduction of a
/// grid scored in parallel, the same at any thread count.
pub(super) fn best_scored<T, F>(
    scored: impl IntoIterator<Item = (T, Option<(usize, F)>)>,
) -> Option<(usize, (T, F))> {
    let mut best: Option<(usize, (T, F))> = None;
    for (candidate, score) in scored {
        let Some((score, fit)) = score else { continue };
        if best.as_ref().is_none_or(|(b, _)| score > *b) {
            best = Some((score, (candidate, fit)));
        }
    }
    best
}

/// The score of a candidate lens of a grid start: the 3D homographies' inliers summed over
/// the moved views of `chain` (the views under that lens), with the fit it came from (for
/// [`LensStart::fitted`]); `None` when the stereo geometry or a motion cannot be fitted.
pub(super) fn grid_fit(
    chain: &[View],
    k: &Intrinsics,
    options: &CalibrateOptions,
) -> Option<(usize, GridFit)> {
    let stereo = super::rig_stereo::stereo_geometry(chain, k, &options.estimation).ok()?;
    let motions = super::motion::fit_motions(chain, &stereo.recon, &stereo.frame, options, &mut None).ok()?;
    let score = motions.iter().map(|m| m.report.inliers).sum();
    Some((score, GridFit { seed: options.estimation.seed, stereo, motions }))
}
