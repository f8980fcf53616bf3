//! Step 1 of the chain ([`super`] module docs): which views the self-calibration uses.
//! A view whose vergence readings differ from the reference view's by more than
//! [`MOVED_DEG`] shows another rig and is left out; every remaining view gets the
//! scene-depth check: one plane homography fitted by RANSAC to its own stereo matches
//! (8 dof, transfer error in pixels against `planar_threshold_px`, default 2 px), and the
//! view counts as planar when it explains at least `planar_fraction` (default 98 %) of
//! them. A planar view is left out; if the reference or every moved view is planar, the
//! scene has no depth to calibrate from and the error names the views.
//!
//! Why (Hartley & Zisserman 2nd ed., section 10.3 and 19.5): a planar scene has no
//! projective reconstruction, so no 3D homography relates its views; a chessboard in
//! front of a fixed rig is the typical case. Pitfalls: the check is seeded (the
//! estimation seed) like every RANSAC of the chain; a scene mostly on one wall passes it
//! and is warned about later ([`CalibrateReport::plane_share`]).
//!
//! [`CalibrateReport::plane_share`]: super::CalibrateReport::plane_share

use headalign_geometry::GeometryError;
use headalign_geometry::homography2d::Homography2Estimator;
use headalign_geometry::ransac::{RansacOptions, ransac};
use headalign_platform::{Encoders, Joint};
use nalgebra::Point2;
use serde::Serialize;

use super::CalibrateOptions;
use crate::error::AlignError;
use crate::observations::View;
use crate::rig::stereo::stereo_matches;
use crate::verge_tilt::MOVED_DEG;

/// The scene-depth check of one view.
#[derive(Debug, Clone, Serialize)]
pub struct PlaneCheck {
    /// The view.
    pub view: String,
    /// Its stereo matches.
    pub stereo_matches: usize,
    /// How many of them one plane homography explains.
    pub on_one_plane: usize,
    /// True if that is at least `planar_fraction` of them.
    pub planar: bool,
}

/// Step 1 of the module docs for every view.
pub fn check_planarity(views: &[View], options: &CalibrateOptions) -> Vec<PlaneCheck> {
    views
        .iter()
        .map(|v| {
            let pairs: Vec<(Point2<f64>, Point2<f64>)> =
                stereo_matches(&v.capture).iter().map(|m| (m.1, m.2)).collect();
            let ransac_options = RansacOptions {
                threshold: options.planar_threshold_px,
                seed: options.estimation.seed,
                ..RansacOptions::default()
            };
            let on_plane = if pairs.len() >= 8 {
                ransac(&Homography2Estimator, &pairs, &ransac_options).map_or(0, |r| r.inliers.len())
            } else {
                0
            };
            PlaneCheck {
                view: v.name.clone(),
                stereo_matches: pairs.len(),
                on_one_plane: on_plane,
                planar: pairs.len() >= 8 && on_plane as f64 >= options.planar_fraction * pairs.len() as f64,
            }
        })
        .collect()
}

/// The error of a scene with no depth, naming the planar views.
pub(super) fn planar_error(checks: &[PlaneCheck]) -> AlignError {
    let named: Vec<String> = checks
        .iter()
        .filter(|c| c.planar)
        .take(4)
        .map(|c| format!("'{}' ({} of {})", c.view, c.on_one_plane, c.stereo_matches))
        .collect();
    AlignError::Geometry {
        step: "scene depth".into(),
        cause: GeometryError::Degenerate(format!(
            "all stereo matches lie on one plane in views {}{}: a plane has no projective reconstruction, so no 3D homography relates the views and the rig cannot self-calibrate from them; record a scene with depth (a planar target still gives the fundamental matrix from several poses, and the rig with known intrinsics)",
            named.join(", "),
            if checks.iter().filter(|c| c.planar).count() > 4 { ", ..." } else { "" }
        )),
    }
}

/// Whether a set of views can be calibrated by general-motion self-calibration at all
/// (used by callers that want the scene-depth error before tracking across views):
/// the scene-depth check of step 1 on each view's own stereo matches.
pub fn require_depth(views: &[View], options: &CalibrateOptions) -> Result<Vec<PlaneCheck>, AlignError> {
    let checks = check_planarity(views, options);
    if !checks.is_empty() && checks.iter().all(|c| c.planar) {
        return Err(planar_error(&checks));
    }
    Ok(checks)
}

/// The views step 1 keeps, and why the others went.
pub(super) struct RigViews {
    /// The views of the rig, the reference first (vergence unmoved, not planar).
    pub(super) rig: Vec<View>,
    /// Views left out, with the reason.
    pub(super) skipped: Vec<String>,
    /// The scene-depth check of every view with the reference's vergence.
    pub(super) planarity: Vec<PlaneCheck>,
    /// Image size of the reference view.
    pub(super) image_size: [u32; 2],
}

/// Step 1 (module docs): leave out the views whose vergence moved and those whose stereo
/// matches lie on one plane; an error if no view remains besides the reference, or the
/// reference or every moved view is planar.
pub(super) fn select_views(views: &[View], options: &CalibrateOptions) -> Result<RigViews, AlignError> {
    let Some(first) = views.first() else {
        return Err(AlignError::Observations("no views".into()));
    };
    let mut skipped = Vec::new();
    let mut used: Vec<&View> = Vec::new();
    let e0 = first.capture.encoders;
    for v in views {
        let changed = [Joint::VergeLeft, Joint::VergeRight]
            .iter()
            .any(|&j| (v.capture.encoders.get(j) - e0.get(j)).abs() > MOVED_DEG);
        if changed {
            skipped.push(format!("{}: vergence moved (the rig changed)", v.name));
        } else {
            used.push(v);
        }
    }
    let owned: Vec<View> = used.iter().map(|v| (*v).clone()).collect();
    let planarity = check_planarity(&owned, options);
    if planarity.first().is_some_and(|c| c.planar) || planarity.iter().skip(1).all(|c| c.planar) {
        if owned.len() < 2 {
            return Err(AlignError::MissingMotion(format!(
                "{} usable view(s): self-calibration needs the rig in at least two positions",
                owned.len()
            )));
        }
        return Err(planar_error(&planarity));
    }
    let mut rig: Vec<View> = Vec::new();
    for (v, c) in owned.into_iter().zip(&planarity) {
        if c.planar {
            skipped.push(format!("{}: all stereo matches on one plane", v.name));
        } else {
            rig.push(v);
        }
    }
    Ok(RigViews { rig, skipped, planarity, image_size: first.capture.image_size })
}

/// The views of one rig among recorded views ([`select_rig`]): indices into the input.
#[derive(Debug, Clone, PartialEq)]
pub struct RigChoice {
    /// The views used, in order (the first is the reference).
    pub used: Vec<usize>,
    /// The views left out, each with the reason.
    pub left_out: Vec<(usize, String)>,
}

/// Choose the views of one rig among `(name, encoders)` views whose vergence readings
/// differ, as a recorded session's do (verging captures, the verge/tilt views, the verge
/// view, the views after alignment): the rig changes with every vergence reading, and
/// [`calibrate_rig`](super::calibrate_rig) needs one. The views are grouped by their
/// vergence readings (both within [`MOVED_DEG`] of the group's first view). The group
/// kept is the one whose views turn the head about two joints (pan and elevation both
/// move, by more than [`MOVED_DEG`], within the group: rotations about two axes fix the
/// plane at infinity and the conic), then the one with more views, then the earlier.
/// Pitfall: the views of the robot stages share one rig but move it only about vertical
/// axes (pan, turns of the robot): such planar motions leave a focal length
/// undetermined (a session of seed 3 calibrated from them gave fy 3286 +- 1957 px for a
/// true 720), so the two-joint rule prefers the verge/tilt views even when fewer.
/// Views without encoder readings (all zero) form one group: all are used.
pub fn select_rig(views: &[(&str, Encoders)]) -> RigChoice {
    let verge = |e: &Encoders| [e.verge_left, e.verge_right];
    let mut groups: Vec<Vec<usize>> = Vec::new();
    for (i, (_, e)) in views.iter().enumerate() {
        let same = |g: &&mut Vec<usize>| {
            let first = verge(&views[g[0]].1);
            verge(e).iter().zip(first).all(|(a, b)| (a - b).abs() <= MOVED_DEG)
        };
        match groups.iter_mut().find(same) {
            Some(g) => g.push(i),
            None => groups.push(vec![i]),
        }
    }
    let two_joints = |g: &[usize]| {
        let e0 = views[g[0]].1;
        [Joint::Pan, Joint::Elevation]
            .iter()
            .all(|&j| g.iter().any(|&i| (views[i].1.get(j) - e0.get(j)).abs() > MOVED_DEG))
    };
    // The first best group: `max_by_key` keeps the last of equals, so search reversed.
    let Some(best) = groups.iter().rev().max_by_key(|g| (two_joints(g), g.len())).cloned() else {
        return RigChoice { used: Vec::new(), left_out: Vec::new() };
    };
    let reference = views[best[0]].0;
    let left_out = (0..views.len())
        .filter(|i| !best.contains(i))
        .map(|i| {
            let [l, r] = verge(&views[i].1);
            (
                i,
                format!(
                    "{}: another rig (vergence readings {l:.3}, {r:.3} deg differ from those of the reference view '{reference}')",
                    views[i].0
                ),
            )
        })
        .collect();
    RigChoice { used: best, left_out }
}
