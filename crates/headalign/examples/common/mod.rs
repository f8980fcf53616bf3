//! Shared by the diagnostic examples: one verge/tilt trial as `headalign experiment` runs
//! it (`axis_diag`, `ratio_diag`, `verge_seeds`: the scenario's fixed rotation, a 3 deg
//! vergence move, thresholds scaled by the noise via
//! [`EstimationOptions::scaled_for_noise`]) on a simulated head started at `initial`;
//! the views' observations grouped by track, the true projective cameras of each view and
//! an N-view DLT with them (`track_errors`, `onegen_diag`, `cluster_diag`); the tracked
//! verge/tilt rig views of a robot-scene seed (`track_errors`, `cluster_diag`); fresh
//! Gaussian pixel noise on exact observations (`bias_mc`, `bootstrap_mc`). Each example
//! uses only part of it.
#![allow(dead_code)]

use std::collections::BTreeMap;

use headalign::estimate::EstimationOptions;
use headalign::frontend::{FrontEndOptions, TrackingHead};
use headalign::imaging::{VergingOptions, verge_to_common_view};
use headalign::observations::View;
use headalign::procedure::{VergeTiltOptions, VergeTiltOutcome, VergeTiltRun, capture_plan};
use headalign_geometry::bundle::RigState;
use headalign_geometry::camera::ProjectiveCamera;
use headalign_platform::{Encoders, StereoHead};
use headalign_sim::{Scenario, SimulatedHead};
use nalgebra::{DMatrix, Point2, Point3, Vector4};

/// The trial with estimation seed `estimation_seed`; `None` if the simulator or the
/// procedure fails.
pub fn verge_tilt_trial(
    s: &Scenario,
    initial: &Encoders,
    estimation_seed: u64,
) -> Option<(SimulatedHead, VergeTiltOutcome)> {
    let mut head = SimulatedHead::new(s.clone()).ok()?;
    head.move_to(initial).ok()?;
    let out = VergeTiltRun::default().run(&mut head, &trial_options(s, estimation_seed)).ok()?;
    Some((head, out))
}

/// The verge/tilt options of a trial in `s`: the scenario's fixed rotation, a 3 deg
/// vergence move, thresholds scaled by its noise, estimation seed `estimation_seed`.
pub fn trial_options(s: &Scenario, estimation_seed: u64) -> VergeTiltOptions {
    VergeTiltOptions {
        rotation_deg: s.rotation_deg,
        verge_rotation_deg: 3.0,
        estimation: EstimationOptions::scaled_for_noise(s.noise_px, estimation_seed),
        ..VergeTiltOptions::default()
    }
}

/// The robot's scene (default room with [`Scenario::ROBOT_NEAR_PANELS`]) at `seed` and
/// `noise_px` (`axis_mc`, `planarity_chi2`).
pub fn robot_scenario(seed: u64, noise_px: f64) -> Scenario {
    Scenario { seed, noise_px, ..Scenario::robot_room() }
}

/// `estimate` with some of its parts taken from `truth` (`sigma_diag`, `ratio_diag`: which
/// part moves a sigma or a cost): 0 both cameras' intrinsics, 1 the stereo rig, 2 the view
/// motions, 3 the points (`true_points`), anything else intrinsics and rig.
pub fn with_true_part(
    estimate: &RigState,
    truth: &RigState,
    true_points: &[Point3<f64>],
    which: usize,
) -> RigState {
    let mut m = estimate.clone();
    match which {
        0 => {
            m.left = truth.left;
            m.right = truth.right;
        }
        1 => m.right_from_left = truth.right_from_left,
        2 => m.motions = truth.motions.clone(),
        3 => m.points = true_points.to_vec(),
        _ => {
            m.left = truth.left;
            m.right = truth.right;
            m.right_from_left = truth.right_from_left;
        }
    }
    m
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

/// The front end's default options, with patch refinement as the environment's `REFINE`
/// says: `off` (the detector's corners), `temporal` (later views only), `stereo` (stereo
/// partners too), anything else or unset the default (`stereo`): before/after in one build.
pub fn front_end_options() -> FrontEndOptions {
    let mut f = FrontEndOptions::default();
    match std::env::var("REFINE").as_deref() {
        Ok("off") => f.refine = None,
        Ok("temporal") => f.refine_stereo = false,
        Ok("stereo") => f.refine_stereo = true,
        _ => {}
    }
    f
}

/// The head, the views and each view's true encoder readings ([`tracked_rig_views`]).
pub type TrackedViews = (SimulatedHead, Vec<View>, Vec<Encoders>);

/// The verge/tilt rig views (the vergence move left out) of seed `seed`'s robot scene
/// (`Scenario::ROBOT_NEAR_PANELS`), tracked by the image front end after verging to a
/// common view: the head, the views and each view's true encoder readings.
pub fn tracked_rig_views(seed: u64) -> Result<TrackedViews, Box<dyn std::error::Error>> {
    let s = Scenario { seed, near_panels: Scenario::ROBOT_NEAR_PANELS, ..Scenario::default() };
    let mut head = SimulatedHead::new(s)?;
    let verged = verge_to_common_view(&mut head, &VergingOptions::default())?;
    let mut plan = capture_plan(&verged.encoders, &VergeTiltOptions::default());
    plan.pop(); // the vergence move: not a rig view
    let mut views = Vec::new();
    let mut true_enc = Vec::new();
    {
        let mut th = TrackingHead::new(&mut head, front_end_options())?;
        for (name, enc) in &plan {
            th.move_to(enc)?;
            true_enc.push(th.inner().encoders());
            views.push(View { name: name.clone(), capture: th.capture()? });
        }
    }
    Ok((head, views, true_enc))
}

/// The true cameras `[left, right]` of every view of [`tracked_rig_views`].
pub fn true_view_cameras(head: &SimulatedHead, true_enc: &[Encoders]) -> Vec<[ProjectiveCamera; 2]> {
    let truth = head.truth();
    true_enc
        .iter()
        .map(|e| {
            let (l, r) = head.scene_from_cameras(e);
            true_cameras(&truth.left, &truth.right, &l, &r)
        })
        .collect()
}

/// N-view DLT of one track with the cameras `cams[view][side]` from its observations
/// `(view, side, pixel)`, rows not normalised (the diagnostics' own, kept so their quoted
/// numbers stay; the library's `triangulation::triangulate_views` normalises each row).
/// `None` if the SVD gives no `V`.
pub fn triangulate_track(
    cams: &[[ProjectiveCamera; 2]],
    obs: impl ExactSizeIterator<Item = (usize, usize, Point2<f64>)>,
) -> Option<Vector4<f64>> {
    let mut a = DMatrix::zeros(2 * obs.len(), 4);
    for (i, (v, side, px)) in obs.enumerate() {
        let p = cams[v][side].0;
        for c in 0..4 {
            a[(2 * i, c)] = px.x * p[(2, c)] - p[(0, c)];
            a[(2 * i + 1, c)] = px.y * p[(2, c)] - p[(1, c)];
        }
    }
    let vt = a.svd(false, true).v_t?;
    Some(Vector4::from_iterator(vt.row(3).iter().copied()))
}

/// `obs` with fresh Gaussian noise of `noise_px` per pixel coordinate.
pub fn with_pixel_noise(
    obs: &[headalign_geometry::bundle::BundleObservation],
    noise_px: f64,
    rng: &mut rand_chacha::ChaCha8Rng,
) -> Vec<headalign_geometry::bundle::BundleObservation> {
    use rand_distr::{Distribution, StandardNormal};
    obs.iter()
        .map(|b| {
            let e =
                nalgebra::Vector2::new(StandardNormal.sample(&mut *rng), StandardNormal.sample(&mut *rng));
            headalign_geometry::bundle::BundleObservation { pixel: b.pixel + e * noise_px, ..*b }
        })
        .collect()
}
