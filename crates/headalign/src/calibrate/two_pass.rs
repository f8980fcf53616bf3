//! The start of a self-calibration that estimates a lens model
//! ([`super::CalibrateOptions::lens`]) when the chain on the captured pixels fails.
//!
//! What it computes, [`calibrate_two_pass`]:
//! 1. **first estimate**: the chain of [`super::calibrate_rig`] on the captured pixels,
//!    its linear steps (F, the projective frame, the 3D homographies, the linear
//!    self-calibration) treating them as pinhole pixels, the adjustment with the lens
//!    terms free from the model's zero lens. Reported if it succeeds with every focal
//!    length in the plausible range ([`plausible`], [`MAX_FOCAL_WIDTHS`]);
//! 2. otherwise **a lens to undistort with** ([`grid_start`]): per lens whose `k1` alone
//!    moves the image corner by -30 % to +30 % of its radius (steps of 5 %), the pixels
//!    undistorted with it and F, the frame and the 3D homographies fitted; the lens whose
//!    homographies keep the most quadruplets wins;
//! 3. **the chain again on undistorted pixels**: steps 2-4 on the pixels undistorted
//!    with that lens, the adjustment on the captured pixels from starts that carry it.
//!    Reported if plausible (or if the first estimate failed outright).
//!
//! Why: a barrel lens of `k1 = -0.3` moves the corners of a 768 x 576 image by some
//! 55 px. The linear steps see that as projective error: F's RANSAC keeps mostly the
//! centre, the quasi-Euclidean frame is bent, and with 10 deg views the 3D homographies
//! read rotations of 0-11 deg (measured, `experiment lens --rotation 10 --only 0.25`,
//! seeds 1-40: the rigid 3-point motions 0.1-11 deg for a true 10). The linear chain then
//! fails ("too few tracks in front of the cameras", a conic that is not positive
//! definite) and the rigid start, far from the truth with the lens free from zero, can
//! follow the f-k1 valley to the affine limit (f of 10^4-10^5 px, `k1` of 30-6600: 6 of
//! 40 radtan trials there). On undistorted pixels the remaining distortion is the grid
//! lens's error: nearly a pinhole problem, where the linear chain works (40 of 40).
//!
//! Why not always the second pass (as the image procedures do): on the raw EuRoC pairs
//! (`real_data::euroc_raw_*` tests) the chain on pixels undistorted by the first
//! estimate keeps other tracks near the border and ends with focal lengths 1.8-2.0 %
//! short, against 0.9 % for the first estimate: it is kept for the starts that fail.
//!
//! Degrees of freedom and units: none added (those of the adjustment); pixels; corner
//! displacements as fractions of the corner's radius.
//!
//! Pitfalls: the fallback costs 13 fits of F and the homographies and a second run of the
//! chain. The grid lens is normalised by the image-size guess `K0`; the final adjustment
//! refits everything. Observations the lens cannot undistort are left out of the linear
//! steps only. A true focal length beyond [`MAX_FOCAL_WIDTHS`] image widths takes the
//! fallback too and keeps the first estimate when the fallback is not plausible either.
//! The pinhole ([`super::LensChoice::Pinhole`]) runs the chain once, exactly as without
//! this module.

use headalign_geometry::camera::Intrinsics;
use headalign_geometry::distortion::{Distortion, LensKind};

use super::{
    CalibrateOptions, LensModel, MotionCalibration, calibrate_once_from, calibrate_with_restarts,
    undistort_views, with_restarts,
};
use crate::error::AlignError;
use crate::estimate::Reconstruction;
use crate::observations::View;

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
pub(super) fn calibrate_two_pass(
    views: &[View],
    options: &CalibrateOptions,
) -> Result<MotionCalibration, AlignError> {
    let Some(kind) = options.lens.kind() else {
        return calibrate_with_restarts(views, options);
    };
    let first = calibrate_with_restarts(views, options);
    if first.as_ref().is_ok_and(plausible) {
        return first;
    }
    // The first estimate failed or left the plausible range: its lens when plausible is
    // none to undistort with, so the grid's.
    let Some(start) = grid_start(views, options, kind) else { return first };
    match with_restarts(options, |o, seeded| calibrate_once_from(views, o, seeded, Some(&start))) {
        Ok(second) if plausible(&second) || first.is_err() => Ok(second),
        Err(e) if first.is_err() => Err(e),
        _ => first,
    }
}

/// The corner displacements of [`grid_start`], fractions of the corner's radius
/// (negative: barrel): -30 % to +30 % in steps of 5 %.
fn grid_displacements() -> impl Iterator<Item = f64> {
    (-6..=6).map(|i| f64::from(i) * 0.05)
}

/// Step 2's lens when the first estimate failed or is not plausible: per lens of the
/// model `kind` whose `k1` alone moves the image corner radially by a fraction
/// [`grid_displacements`] of its radius (under the image-size guess `K0`), the pixels
/// undistorted with it and steps 2-3 of the chain run (F, frame, 3D homographies); the
/// lens whose 3D homographies keep the most quadruplets (transfer error within the
/// options' threshold) wins. `None` if no lens gives every view a homography.
fn grid_start(views: &[View], options: &CalibrateOptions, kind: LensKind) -> Option<LensStart> {
    let rig = super::depth::select_views(views, options).ok()?;
    let [w, h] = rig.image_size;
    let k0 = Intrinsics::rough_guess(w, h);
    // The corner's normalised radius under K0 (and its angle from the axis).
    let corner = (k0.cx.hypot(k0.cy)) / k0.fx;
    let mut best: Option<(usize, Distortion)> = None;
    for delta in grid_displacements() {
        let mut d = Distortion::zero(kind);
        d.k1 = match kind {
            LensKind::RadialTangential => delta / (corner * corner),
            LensKind::Equidistant => delta / corner.atan().powi(2),
        };
        let lens = LensModel { k: k0, distortion: d };
        let chain = undistort_views(&rig.rig, &[lens, lens]);
        let Ok(stereo) = super::stereo::stereo_geometry(&chain, &k0, &options.estimation) else { continue };
        let Ok(motions) =
            super::motion::fit_motions(&chain, &stereo.recon, &stereo.frame, options, &mut None)
        else {
            continue;
        };
        let score: usize = motions.iter().map(|m| m.report.inliers).sum();
        if best.as_ref().is_none_or(|(b, _)| score > *b) {
            best = Some((score, d));
        }
    }
    best.map(|(_, d)| LensStart { chain: [LensModel { k: k0, distortion: d }; 2], distortion: [d, d] })
}
