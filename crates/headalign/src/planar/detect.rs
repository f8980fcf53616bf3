//! Step 1 of the planar route ([`super`] module docs): is the scene planar or depth-less?
//!
//! The reference view's stereo matches are fitted by RANSAC twice at the same threshold
//! (the general route's `F` threshold, 3 px): one plane homography (8 dof, transfer error)
//! and the fundamental matrix (7 dof, Sampson distance, [`estimate_fundamental`]). The
//! scene goes the planar way when the homography explains at least
//! [`PLANAR_SHARE`] of the matches `F` explains: then no match shows the parallax
//! projective structure needs (on a wall none has any; at 240 baselines the disparities
//! differ by about 2 px). A room's stereo matches lie on several surfaces with tens of
//! pixels of parallax between them; its best plane holds well under that share.
//!
//! Pitfalls: both fits are seeded (the estimation seed); a room seen mostly as one wall
//! with a little else in view could pass the test, which is why the share is high.

use headalign_geometry::fundamental::estimate_fundamental;
use headalign_geometry::homography2d::Homography2Estimator;
use headalign_geometry::ransac::{RansacOptions, ransac};
use nalgebra::Point2;
use serde::Serialize;

use crate::estimate::stereo_matches;
use crate::observations::View;

/// Share of `F`'s inliers one homography must explain for the scene to count as planar.
pub const PLANAR_SHARE: f64 = 0.95;

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
    /// How many of them one homography explains.
    pub homography_inliers: usize,
    /// Why, in words.
    pub why: String,
}

/// Step 1 (module docs) on the reference view (the first of `views`), with RANSAC
/// options `fundamental` (threshold and seed of the general route's `F`).
pub fn detect_scene(views: &[View], fundamental: &RansacOptions) -> SceneCheck {
    let pairs: Vec<(Point2<f64>, Point2<f64>)> =
        views.first().map(|v| stereo_matches(&v.capture).iter().map(|m| (m.1, m.2)).collect()).unwrap_or_default();
    let n = pairs.len();
    let general = |f_in: usize, h_in: usize, why: String| SceneCheck {
        kind: SceneKind::General,
        stereo_matches: n,
        f_inliers: f_in,
        homography_inliers: h_in,
        why,
    };
    if n < 8 {
        return general(0, 0, format!("{n} stereo matches: too few to test"));
    }
    let f_in = estimate_fundamental(&pairs, fundamental).map_or(0, |r| r.inliers.len());
    let h_options = RansacOptions { threshold: fundamental.threshold, seed: fundamental.seed, ..RansacOptions::default() };
    let h_in = ransac(&Homography2Estimator, &pairs, &h_options).map_or(0, |r| r.inliers.len());
    let share = if f_in > 0 { h_in as f64 / f_in as f64 } else { 0.0 };
    let what = format!(
        "one homography explains {h_in} of the {f_in} stereo matches F explains ({:.1} %, of {n}) at {} px",
        100.0 * share,
        fundamental.threshold
    );
    if f_in >= 8 && share >= PLANAR_SHARE {
        SceneCheck {
            kind: SceneKind::Planar,
            stereo_matches: n,
            f_inliers: f_in,
            homography_inliers: h_in,
            why: format!("{what}: no parallax for projective structure"),
        }
    } else {
        general(f_in, h_in, what)
    }
}
