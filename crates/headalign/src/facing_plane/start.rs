//! Steps 2-3 of the planar route ([`super`] module docs): each rotated view's robust image
//! homography from the reference image (one camera), and the start of the adjustment.
//!
//! Homographies: RANSAC ([`Homography2Estimator`], 4-point DLT, transfer error in pixels,
//! [`super::PlanarOptions::homography`]) on the tracks the view shares with the
//! reference view; a view with fewer than `min_tracks` shared tracks or no fit is left
//! out and named. Start: `K` from the homographies as infinite homographies
//! ([`k_from_rotations`], Hartley's rotating camera, conditioned by the rough guess);
//! each joint's axis from its single-joint views, `R = (K^-1 H K)^T` (the homography maps
//! reference pixels into the view, `ref_from_cam = Rot(a, angle)`), `a = log R / angle`
//! with the commanded angle, averaged over the joint's views; angles at their commanded
//! values; axes through the camera centre; the plane `m = (0, 0, 1/3)` per metre (any
//! nonzero start: at `m = 0` and zero offsets the plane's part of the model has zero
//! gradient); points at `K^-1` of their reference pixels. Pitfall: a wall 1 m away
//! departs from `K R K^-1` by a few pixels, so the start is rough; the adjustment
//! absorbs that.

use std::collections::{BTreeMap, BTreeSet};

use headalign_geometry::bundle::Side;
use headalign_geometry::camera::Intrinsics;
use headalign_geometry::homography2d::Homography2Estimator;
use headalign_geometry::ransac::ransac;
use headalign_geometry::so3::{log, nearest_rotation};
use nalgebra::{Matrix3, Point2, Unit, Vector3};

use super::PlanarOptions;
use super::camera_joints;
use super::refine::{JointState, Observation, Problem};
use crate::error::AlignError;
use crate::observations::View;
use crate::verge_tilt::MOVED_DEG;
use crate::verge_tilt::starts::k_from_rotations;

/// One view of one camera.
pub(super) struct ViewData {
    /// Moved joints: (slot in [`camera_joints`], commanded difference in radians).
    pub moved: Vec<(usize, f64)>,
    /// Observations by track.
    pub obs: BTreeMap<u64, Point2<f64>>,
    /// The homography from the reference image (none for the reference view).
    pub homography: Option<Matrix3<f64>>,
    /// Tracks RANSAC kept.
    pub inliers: BTreeSet<u64>,
}

/// One camera's views.
pub(super) struct CameraData {
    /// Image size.
    pub image_size: [u32; 2],
    /// The views kept, the reference first.
    pub views: Vec<ViewData>,
}

/// Step 2 (module docs) for camera `side`; views left out are named in `dropped`.
pub(super) fn camera_data(
    views: &[View],
    side: Side,
    options: &PlanarOptions,
    dropped: &mut Vec<String>,
) -> Result<CameraData, AlignError> {
    let first = views.first().ok_or_else(|| AlignError::Observations("no views".into()))?;
    let joints = camera_joints(side);
    let side_name = if side == Side::Left { "left" } else { "right" };
    let obs_of = |v: &View| -> BTreeMap<u64, Point2<f64>> {
        let list = if side == Side::Left { &v.capture.left } else { &v.capture.right };
        list.iter().map(|o| (o.track, o.pixel)).collect()
    };
    let reference = obs_of(first);
    let mut out = vec![ViewData {
        moved: Vec::new(),
        obs: reference.clone(),
        homography: None,
        inliers: reference.keys().copied().collect(),
    }];
    for v in &views[1..] {
        let moved: Vec<(usize, f64)> = joints
            .iter()
            .enumerate()
            .map(|(slot, j)| (slot, v.capture.encoders.get(*j) - first.capture.encoders.get(*j)))
            .filter(|(_, d)| d.abs() > MOVED_DEG)
            .map(|(slot, d)| (slot, d.to_radians()))
            .collect();
        if moved.is_empty() {
            // The other camera's vergence moved: this camera did not.
            continue;
        }
        let obs = obs_of(v);
        let shared: Vec<u64> = obs.keys().filter(|t| reference.contains_key(t)).copied().collect();
        let pairs: Vec<(Point2<f64>, Point2<f64>)> =
            shared.iter().filter_map(|t| Some((*reference.get(t)?, *obs.get(t)?))).collect();
        if pairs.len() < options.min_tracks {
            dropped.push(format!(
                "{}: {side_name} camera shares {} tracks with the reference view, need {}",
                v.name,
                pairs.len(),
                options.min_tracks
            ));
            continue;
        }
        match ransac(&Homography2Estimator, &pairs, &options.homography) {
            Ok(r) if r.inliers.len() >= options.min_tracks => out.push(ViewData {
                moved,
                homography: Some(r.model.0),
                inliers: r.inliers.iter().map(|&i| shared[i]).collect(),
                obs,
            }),
            _ => dropped.push(format!("{}: no homography of the {side_name} camera fits", v.name)),
        }
    }
    Ok(CameraData { image_size: first.capture.image_size, views: out })
}

/// Step 3 (module docs): the start of the adjustment for one camera.
pub(super) fn initial_problem(data: &CameraData, side: Side) -> Result<Problem, AlignError> {
    let [w, h] = data.image_size;
    let k0 = Intrinsics::rough_guess(w, h);
    let hs: Vec<Matrix3<f64>> = data.views.iter().filter_map(|v| v.homography).collect();
    // The model has zero skew: start there.
    let k_full = k_from_rotations(&hs, &k0);
    let k = Intrinsics::new(k_full.fx, k_full.fy, k_full.cx, k_full.cy);
    let (km, k_inv) = (k.matrix(), k.inverse_matrix());
    // Axis of each joint from its single-joint views.
    let mut sums = [Vector3::zeros(); 3];
    let mut used = [false; 3];
    for v in &data.views {
        let (Some(hm), [(slot, angle)]) = (v.homography, v.moved.as_slice()) else { continue };
        let m = k_inv * hm * km;
        let d = m.determinant();
        if !(d.is_finite() && d.abs() > 1e-300) {
            continue;
        }
        let Some(r) = nearest_rotation(&(m / d.cbrt()).transpose()) else { continue };
        let w = log(&r);
        if w.norm() > 1e-9 {
            sums[*slot] += w / *angle;
            used[*slot] = true;
        }
    }
    let moved: BTreeSet<usize> = data.views.iter().flat_map(|v| v.moved.iter().map(|m| m.0)).collect();
    let mut joints = Vec::new();
    let mut slot_to_joint = [usize::MAX; 3];
    for slot in moved {
        if !used[slot] {
            let name = camera_joints(side)[slot].name();
            return Err(AlignError::MissingMotion(format!(
                "planar route: no view rotates the {name} joint alone with a usable homography"
            )));
        }
        slot_to_joint[slot] = joints.len();
        joints.push(JointState { slot, axis: Unit::new_normalize(sums[slot]), point: Vector3::zeros() });
    }
    for needed in [0, 1] {
        if slot_to_joint[needed] == usize::MAX {
            let name = camera_joints(side)[needed].name();
            return Err(AlignError::MissingMotion(format!("planar route: no view rotates the {name} joint")));
        }
    }
    let (mut angles, mut view_factors) = (Vec::new(), Vec::new());
    for v in &data.views {
        let mut factors: Vec<(usize, usize)> = v
            .moved
            .iter()
            .map(|(slot, a)| {
                angles.push(*a);
                (slot_to_joint[*slot], angles.len() - 1)
            })
            .collect();
        factors.sort_by_key(|f| joints[f.0].slot);
        view_factors.push(factors);
    }
    // Points: tracks of the reference view that some rotated view keeps as an inlier.
    let (mut points, mut tracks, mut obs) = (Vec::new(), Vec::new(), Vec::new());
    for (track, px) in &data.views[0].obs {
        let kept: Vec<usize> =
            (1..data.views.len()).filter(|&i| data.views[i].inliers.contains(track)).collect();
        if kept.is_empty() {
            continue;
        }
        let p = points.len();
        let r = k_inv * Vector3::new(px.x, px.y, 1.0);
        points.push(Point2::new(r.x / r.z, r.y / r.z));
        tracks.push(*track);
        obs.push(Observation { view: 0, point: p, pixel: *px });
        for i in kept {
            if let Some(q) = data.views[i].obs.get(track) {
                obs.push(Observation { view: i, point: p, pixel: *q });
            }
        }
    }
    Ok(Problem {
        k,
        joints,
        angle_cmd: angles.clone(),
        angles,
        view_factors,
        plane: Vector3::new(0.0, 0.0, 1.0 / 3.0),
        points,
        tracks,
        obs,
        plane_hold: None,
    })
}
