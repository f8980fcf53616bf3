//! Shared by the diagnostic examples: one verge/tilt trial as `headalign experiment` runs
//! it (`axis_diag`, `ratio_diag`, `verge_seeds`: the scenario's fixed rotation, a 3 deg
//! vergence move, thresholds scaled by the noise via
//! [`EstimationOptions::scaled_for_noise`]) on a simulated head started at `initial`;
//! the views' observations grouped by track and the true projective cameras of each view
//! (`track_errors`, `onegen_diag`). Each example uses only part of it.
#![allow(dead_code)]

use std::collections::BTreeMap;

use headalign::estimate::EstimationOptions;
use headalign::observations::View;
use headalign::procedure::{VergeTiltOptions, VergeTiltOutcome, VergeTiltRun};
use headalign_geometry::camera::ProjectiveCamera;
use headalign_platform::{Encoders, StereoHead};
use headalign_sim::{Scenario, SimulatedHead};
use nalgebra::Point2;

/// The trial with estimation seed `estimation_seed`; `None` if the simulator or the
/// procedure fails.
pub fn verge_tilt_trial(
    s: &Scenario,
    initial: &Encoders,
    estimation_seed: u64,
) -> Option<(SimulatedHead, VergeTiltOutcome)> {
    let mut head = SimulatedHead::new(s.clone()).ok()?;
    head.move_to(initial).ok()?;
    let opts = VergeTiltOptions {
        rotation_deg: s.rotation_deg,
        verge_rotation_deg: 3.0,
        estimation: EstimationOptions::scaled_for_noise(s.noise_px, estimation_seed),
        ..VergeTiltOptions::default()
    };
    let out = VergeTiltRun::default().run(&mut head, &opts).ok()?;
    Some((head, out))
}

/// Every observation of `views` grouped by track id: `(view index, side (0 left, 1 right),
/// pixel)` in view order.
pub fn tracks_by_id(views: &[View]) -> BTreeMap<u64, Vec<(usize, usize, Point2<f64>)>> {
    let mut tracks: BTreeMap<u64, Vec<(usize, usize, Point2<f64>)>> = BTreeMap::new();
    for (vi, v) in views.iter().enumerate() {
        for (side, list) in [(0, &v.capture.left), (1, &v.capture.right)] {
            for o in list {
                tracks.entry(o.track).or_default().push((vi, side, o.pixel));
            }
        }
    }
    tracks
}

/// The true projective cameras `[left, right]` of a view whose cameras sit at
/// `scene_from_left`, `scene_from_right` (the simulator's truth), with the true
/// intrinsics `left`, `right`.
pub fn true_cameras(
    left: &headalign_geometry::camera::Intrinsics,
    right: &headalign_geometry::camera::Intrinsics,
    scene_from_left: &nalgebra::Isometry3<f64>,
    scene_from_right: &nalgebra::Isometry3<f64>,
) -> [ProjectiveCamera; 2] {
    [
        ProjectiveCamera::from_pose(left, &scene_from_left.inverse()),
        ProjectiveCamera::from_pose(right, &scene_from_right.inverse()),
    ]
}
