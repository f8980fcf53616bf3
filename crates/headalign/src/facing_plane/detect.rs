//! Step 1 of the planar route ([`super`] module docs): is the scene planar or depth-less?
//!
//! The reference view's stereo matches are fitted by `F` (RANSAC, Sampson distance, the
//! general route's threshold and seed, [`estimate_fundamental`]); the pixel noise is
//! estimated from its inliers' Sampson distances (`sigma = 1.4826 MAD`, at least
//! [`MIN_SIGMA_PX`]: a Sampson distance is the first-order distance to the two-view
//! variety, one noise dimension). One plane homography is then fitted by RANSAC at
//! `T = 4 sqrt 2 sigma` on the one-sided transfer error (whose noise is `sqrt 2 sigma` per
//! coordinate: a noise-only match lies beyond `T` with probability `exp(-8)`), at least
//! [`MIN_THRESHOLD_PX`]. On a plane `F` is fitted to degenerate data (a one-parameter
//! family of `F` explains a homography's matches) and follows the noise, so its Sampson
//! distances can put the noise far too low (0.1 px, the floor, on rendered images of the
//! wall, whose tracked corners are 0.2-0.6 px off); the threshold is therefore also at
//! least `4 sqrt 2` times the noise the reference view's best homography itself shows
//! (`plane_sigma_px`: its inliers at `F`'s threshold, median transfer error over 1.665,
//! the median of a Rayleigh norm of `sqrt 2 sigma` per coordinate). The scene goes the
//! planar way when at most [`MAX_PERSISTENT_OFF_PLANE`] tracks, or
//! [`MAX_PERSISTENT_OFF_PLANE_SHARE`] of `F`'s inliers if more, lie beyond `T` of their
//! view's best homography in two or more views: no match then shows parallax beyond the
//! noise, which projective structure needs (on a wall none has any; at 800 baselines and
//! beyond the disparities differ by under a pixel). A room's matches lie on several
//! surfaces tens of pixels of parallax apart (disparities of 30-120 px at 1.5-6 m).
//!
//! Why not the share of matches one homography explains at `F`'s threshold, or GRIC
//! (Torr): both prefer the homography for a room dominated by its front wall (seed 1 of
//! the default room: 76 % of `F`'s inliers on one plane at 3 px), where the general
//! route works well; the question here is whether *any* parallax is measurable.
//! Pitfalls: both fits are seeded; wrong matches that pass `F` (a random pixel within 3 px
//! of its epipolar line: well under 1 % of the matches) count as off the plane.

use headalign_geometry::fundamental::estimate_fundamental;
use headalign_geometry::homography2d::Homography2Estimator;
use headalign_geometry::ransac::{RansacOptions, ransac};
use nalgebra::Point2;
use serde::Serialize;

use crate::observations::View;
use crate::rig::stereo::stereo_matches;

/// Most tracks off the best homography in two or more views for a planar scene.
pub const MAX_PERSISTENT_OFF_PLANE: usize = 1;

/// Most tracks off the best homography in two or more views for a planar scene, as a
/// share of `F`'s inliers (when above [`MAX_PERSISTENT_OFF_PLANE`]): a tracker's few
/// stereo mismatches along the epipolar line stay off the plane in every view, their
/// tracks being linked (seed 1 of the wall on rendered images: 4 of 858), where a room on
/// images has 10-15 % of them off any plane.
pub const MAX_PERSISTENT_OFF_PLANE_SHARE: f64 = 0.01;

/// Median of the Rayleigh-distributed norm of a 2D Gaussian residual over its sigma per
/// coordinate, times `sqrt 2` (one-sided transfer error): `sqrt(2 ln 2) sqrt 2`.
const TRANSFER_MEDIAN_OVER_SIGMA: f64 = 1.665;

/// Floor of the estimated pixel noise, pixels (noise-free data).
pub const MIN_SIGMA_PX: f64 = 0.1;

/// Floor of the homography threshold, pixels.
pub const MIN_THRESHOLD_PX: f64 = 0.75;

/// What the scene is, for the route.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum SceneKind {
    /// Depth enough for projective structure: the general route.
    General,
    /// One plane explains the stereo matches: the planar route.
    Planar,
    /// The planar route, and the plane's normal is undetermined: the scene is far.
    Far,
}

impl SceneKind {
    /// The name used in reports.
    pub fn name(self) -> &'static str {
        match self {
            SceneKind::General => "general",
            SceneKind::Planar => "planar",
            SceneKind::Far => "far",
        }
    }
}

/// The detection's numbers and verdict.
#[derive(Debug, Clone, Serialize)]
pub struct SceneCheck {
    /// The verdict.
    pub kind: SceneKind,
    /// Stereo matches of the reference view.
    pub stereo_matches: usize,
    /// How many of them `F` explains.
    pub f_inliers: usize,
    /// How many of `F`'s inliers lie off the best homography (beyond the threshold) in
    /// the reference view.
    pub off_plane: usize,
    /// Tracks off their view's best homography, and explained by `F`, in two or more views.
    pub persistent_off_plane: usize,
    /// The noise estimated from `F`'s inliers, pixels.
    pub sigma_px: f64,
    /// The noise the reference view's best homography shows (module docs), pixels.
    pub plane_sigma_px: f64,
    /// The homography's threshold, pixels.
    pub threshold_px: f64,
    /// Why, in words.
    pub why: String,
}

/// Step 1 (module docs) on the reference view (the first of `views`), with RANSAC
/// options `fundamental` (threshold and seed of the general route's `F`).
pub fn detect_scene(views: &[View], fundamental: &RansacOptions) -> SceneCheck {
    let matches_of = |v: &View| -> Vec<(u64, Point2<f64>, Point2<f64>)> { stereo_matches(&v.capture) };
    let reference = views.first().map(matches_of).unwrap_or_default();
    let pairs: Vec<(Point2<f64>, Point2<f64>)> = reference.iter().map(|m| (m.1, m.2)).collect();
    let n = pairs.len();
    let mut check = SceneCheck {
        kind: SceneKind::General,
        stereo_matches: n,
        f_inliers: 0,
        off_plane: 0,
        persistent_off_plane: 0,
        sigma_px: f64::NAN,
        plane_sigma_px: f64::NAN,
        threshold_px: f64::NAN,
        why: String::new(),
    };
    let Some(f) = (n >= 8).then(|| estimate_fundamental(&pairs, fundamental).ok()).flatten() else {
        check.why = format!("{n} stereo matches and no F: nothing to test");
        return check;
    };
    let mut d: Vec<f64> =
        f.inliers.iter().map(|&i| f.model.sampson_distance(&pairs[i].0, &pairs[i].1).abs()).collect();
    d.sort_by(f64::total_cmp);
    let sigma = (1.4826 * d.get(d.len() / 2).copied().unwrap_or(0.0)).max(MIN_SIGMA_PX);
    let plane_sigma = plane_noise(&pairs, fundamental);
    let threshold = (4.0 * std::f64::consts::SQRT_2 * sigma.max(plane_sigma)).max(MIN_THRESHOLD_PX);
    let h_options = RansacOptions { threshold, seed: fundamental.seed, ..RansacOptions::default() };
    // Per view: the tracks F explains that the view's best homography does not.
    let mut off_count: std::collections::BTreeMap<u64, usize> = std::collections::BTreeMap::new();
    let mut off_reference = 0;
    for (vi, v) in views.iter().enumerate() {
        let m = if vi == 0 { reference.clone() } else { matches_of(v) };
        let pairs: Vec<(Point2<f64>, Point2<f64>)> = m.iter().map(|x| (x.1, x.2)).collect();
        if pairs.len() < 8 {
            continue;
        }
        let on: std::collections::BTreeSet<usize> = ransac(&Homography2Estimator, &pairs, &h_options)
            .map(|h| h.inliers.into_iter().collect())
            .unwrap_or_default();
        let mut off = 0;
        for (i, (track, a, b)) in m.iter().enumerate() {
            if f.model.sampson_distance(a, b).abs() <= fundamental.threshold && !on.contains(&i) {
                *off_count.entry(*track).or_insert(0) += 1;
                off += 1;
            }
        }
        if vi == 0 {
            off_reference = off;
        }
    }
    let persistent = off_count.values().filter(|c| **c >= 2).count();
    check.f_inliers = f.inliers.len();
    check.off_plane = off_reference;
    check.persistent_off_plane = persistent;
    check.sigma_px = sigma;
    check.plane_sigma_px = plane_sigma;
    check.threshold_px = threshold;
    let what = format!(
        "{persistent} tracks lie off the best homography (beyond {threshold:.2} px, noise {sigma:.2} px, on the plane {plane_sigma:.2} px) in two or more of the {} views while F explains them ({off_reference} of {} in the reference view)",
        views.len(),
        f.inliers.len()
    );
    let allowed = MAX_PERSISTENT_OFF_PLANE
        .max((MAX_PERSISTENT_OFF_PLANE_SHARE * f.inliers.len() as f64).floor() as usize);
    if f.inliers.len() >= 8 && persistent <= allowed {
        check.kind = SceneKind::Planar;
        check.why = format!("{what}: no parallax for projective structure");
    } else {
        check.why = what;
    }
    check
}

/// The noise the best homography of `pairs` shows (module docs): RANSAC at `F`'s
/// threshold and seed, its inliers' median transfer error over
/// [`TRANSFER_MEDIAN_OVER_SIGMA`], at least [`MIN_SIGMA_PX`]; the floor when no
/// homography fits.
fn plane_noise(pairs: &[(Point2<f64>, Point2<f64>)], fundamental: &RansacOptions) -> f64 {
    let options = RansacOptions {
        threshold: fundamental.threshold,
        seed: fundamental.seed,
        ..RansacOptions::default()
    };
    let Ok(h) = ransac(&Homography2Estimator, pairs, &options) else { return MIN_SIGMA_PX };
    let mut e: Vec<f64> =
        h.inliers.iter().map(|&i| h.model.transfer_error(&pairs[i].0, &pairs[i].1)).collect();
    e.sort_by(f64::total_cmp);
    (e.get(e.len() / 2).copied().unwrap_or(0.0) / TRANSFER_MEDIAN_OVER_SIGMA).max(MIN_SIGMA_PX)
}
