//! Step 5 of the estimation ([`super`]): the starting points of the rig bundle
//! adjustment (`docs/how-it-works.md#2-estimation` item 5; the paper's step 4 starts from the linear
//! decomposition alone, section 3.2).
//!
//! Each start is a complete [`RigState`] in the reference view's left camera frame: both
//! cameras' intrinsics (4 dof each), the rig pose (5 dof: the baseline is the unit of
//! length), the pan and elevation axes (4 dof each, directed like the encoders) from the
//! single-joint views' motions, the commanded joint angles, and every point (3 dof) of the
//! point set ([`point_set`]). Five starts, in this order ([`initial_states`]):
//! 1. the linear self-calibration chain ([`super::linear`]);
//! 2. rotating-camera self-calibration: each camera's `K` from its plane homographies
//!    `G ~ K R K^-1` (Hartley's `G w* G^T = w*`), the rig from `E = K_R^T F K_L`;
//! 3. a rough start: `K = K0` (focal length = image width) and the rig of the frame's
//!    essential-matrix decomposition;
//! 4. with the rotation start's `K`s, the rig pose estimated directly (5 dof, MSAC over
//!    all stereo matches, [`headalign_geometry::essential`]) from the pose of `F` and from
//!    generic stereo-head poses;
//! 5. the same from the stereo-head prior alone (baseline along x) with `K0`.
//!
//! Points are triangulated in the view that first reconstructed them and moved into the
//! reference frame by that view's motion, found by resecting its left camera against the
//! reference view's points (outliers beyond 10 px left out). Units: pixels, radians, the
//! scene in baselines. Pitfalls: with nearly parallel cameras `F`'s epipole is
//! ill-determined (at 3 px some seeds' best `F` had it inside the image, and every
//! `F`-based start put the near points behind the cameras), hence starts 4 and 5; a wall
//! facing the head admits a second relative pose with the baseline along its normal,
//! which only the rotations reject, hence start 5 goes to the screening whatever its
//! stereo cost. Which start wins is decided by [`super::adjust`] on a common score.

use std::collections::HashMap;

use headalign_geometry::bundle::{Motions, RigState};
use headalign_geometry::camera::{Intrinsics, ProjectiveCamera, dehomogenise3};
use headalign_geometry::frame::{StereoFrame, relative_pose};
use headalign_geometry::fundamental::FundamentalMatrix;
use headalign_geometry::so3::{Line, screw_from_isometry};
use headalign_geometry::triangulation::triangulate_optimal;
use nalgebra::{Isometry3, Matrix3, Point2, Point3};

use super::frame::{ProjectiveStructure, Reconstruction};
use super::homographies::{PlanePair, RotationHomographies};
use super::linear::linear_initial_state;
use super::roles::{MOVED_DEG, ViewRole};
use super::stereo::StereoGeometry;
use crate::error::{AlignError, StepContext};
use crate::observations::View;

/// The point set of the adjustment: the tracks reconstructed in the reference view (in
/// track order), then those first reconstructed in another rig view (in view and track
/// order), with the slot of the rig view that reconstructed each (`origin_slot`).
pub(super) fn point_set(recon: &[Reconstruction]) -> (Vec<u64>, Vec<usize>) {
    let mut point_tracks: Vec<u64> = recon[0].keys().copied().collect();
    let mut origin_slot: Vec<usize> = vec![0; point_tracks.len()];
    for (slot, map) in recon.iter().enumerate().skip(1) {
        for &track in map.keys() {
            if !recon[0].contains_key(&track) && !point_tracks.contains(&track) {
                point_tracks.push(track);
                origin_slot.push(slot);
            }
        }
    }
    (point_tracks, origin_slot)
}

/// The commanded (pan, elevation) differences of each rig view to the reference view,
/// radians, from the encoder readings ([`ViewRole::Rig`]).
pub(super) fn commanded_angles(roles: &[ViewRole], rig: &[usize]) -> Vec<[f64; 2]> {
    rig.iter()
        .map(|&i| match roles[i] {
            ViewRole::Rig { pan_deg, elevation_deg } => [pan_deg.to_radians(), elevation_deg.to_radians()],
            _ => [0.0, 0.0],
        })
        .collect()
}

/// The five starts of the module docs, in that order: linear chain (or `linear_blocked`,
/// why it cannot run), rotating-camera intrinsics, rough, calibrated pose, lateral prior.
/// `k0` is the rough calibration, `threshold_px` the `F` threshold (MSAC of the
/// calibrated pose). A start that fails is its error; the screening skips it.
pub(super) fn initial_states(
    ctx: &InitContext<'_>,
    linear_blocked: Option<AlignError>,
    rotations: &RotationHomographies,
    stereo: &StereoGeometry,
    structure: &ProjectiveStructure,
    k0: &Intrinsics,
    threshold_px: f64,
) -> Vec<Result<RigState, AlignError>> {
    let (f, image_rotations) = (&stereo.f, &rotations.image_rotations);
    let linear = match linear_blocked {
        Some(e) => Err(e),
        None => linear_initial_state(ctx, &rotations.homographies, k0, &structure.p_r),
    };
    let rough = rough_initial_state(ctx, &structure.frame);
    let rotation = rotation_initial_state(ctx, f, &stereo.inlier_pairs, image_rotations, k0);
    let rotation_k = rotation_intrinsics(image_rotations, k0);
    let calibrated = calibrated_initial_state(ctx, f, &stereo.pairs, rotation_k, threshold_px, false);
    let lateral = calibrated_initial_state(ctx, f, &stereo.pairs, (*k0, *k0), threshold_px, true);
    vec![linear, rotation, rough, calibrated, lateral]
}

/// What every start needs.
pub(super) struct InitContext<'a> {
    /// All views.
    pub views: &'a [View],
    /// The rig views (indices into `views`); slot 0 is the reference view.
    pub rig: &'a [usize],
    /// Per rig slot, the projective reconstruction.
    pub recon: &'a [Reconstruction],
    /// The point set ([`point_set`]).
    pub point_tracks: &'a [u64],
    /// The rig slot that reconstructed each point.
    pub origin_slot: &'a [usize],
    /// Commanded (pan, elevation) of each rig slot, radians ([`commanded_angles`]).
    pub commanded: &'a [[f64; 2]],
    /// Fewest points in front of the cameras a start may have.
    pub min_tracks: usize,
}

impl InitContext<'_> {
    /// `ref_from_cam` of every rig view by resection of its left camera (intrinsics `k`)
    /// against the reference view's points; the reference view is the identity.
    fn resect_views(
        &self,
        k: &Intrinsics,
        reference: &HashMap<u64, Point3<f64>>,
    ) -> Result<Vec<Isometry3<f64>>, AlignError> {
        let options =
            headalign_geometry::resection::ResectionOptions { outlier_px: 10.0, ..Default::default() };
        let mut ref_from_cam = vec![Isometry3::identity(); self.rig.len()];
        for (slot, &vi) in self.rig.iter().enumerate().skip(1) {
            let (mut p3, mut p2) = (Vec::new(), Vec::new());
            for o in &self.views[vi].capture.left {
                if let Some(p) = reference.get(&o.track) {
                    p3.push(*p);
                    p2.push(o.pixel);
                }
            }
            let r = headalign_geometry::resection::resect(k, &p3, &p2, &Isometry3::identity(), &options)
                .step(&format!("initial motion of view '{}'", self.views[vi].name))?;
            ref_from_cam[slot] = r.cam_from_world.inverse();
        }
        Ok(ref_from_cam)
    }

    /// The Joints-model state from per-view poses `ref_from_cam` and points given in the
    /// frame of the view that reconstructed them (`point_in_cam(slot, X)`).
    #[allow(clippy::needless_range_loop)] // slots index several parallel per-view arrays
    pub(super) fn state(
        &self,
        left: Intrinsics,
        right: Intrinsics,
        right_from_left: Isometry3<f64>,
        ref_from_cam: &[Isometry3<f64>],
        point_in_cam: impl Fn(usize, u64) -> Option<Point3<f64>>,
    ) -> Result<RigState, AlignError> {
        // Axes from single-joint views, directed like the encoder; the largest move wins.
        let mut axes: [Option<(Line, f64)>; 2] = [None, None];
        let moved = |x: f64| x.abs() > MOVED_DEG.to_radians();
        for slot in 1..self.rig.len() {
            for j in 0..2 {
                if moved(self.commanded[slot][1 - j]) || !moved(self.commanded[slot][j]) {
                    continue;
                }
                let Some(screw) = screw_from_isometry(&ref_from_cam[slot], 1e-6) else {
                    return Err(AlignError::NotARotation {
                        view: self.views[self.rig[slot]].name.clone(),
                        why: "the recovered motion has no rotation".into(),
                    });
                };
                let line = if screw.angle * self.commanded[slot][j] < 0.0 {
                    screw.axis.reversed()
                } else {
                    screw.axis
                };
                if axes[j].is_none_or(|(_, a)| self.commanded[slot][j].abs() > a) {
                    axes[j] = Some((line, self.commanded[slot][j].abs()));
                }
            }
        }
        let (Some((pan_axis, _)), Some((elev_axis, _))) = (axes[0], axes[1]) else {
            return Err(AlignError::MissingMotion("single-joint rotations about pan and elevation".into()));
        };
        let points =
            points_in_ref(self.point_tracks, self.origin_slot, ref_from_cam, self.min_tracks, point_in_cam)?;
        let angles: Vec<Vec<f64>> = self.commanded.iter().map(|c| c.to_vec()).collect();
        Ok(RigState {
            left,
            right,
            left_distortion: Default::default(),
            right_distortion: Default::default(),
            right_from_left,
            motions: Motions::Joints {
                axes: vec![pan_axis, elev_axis],
                angles: angles.clone(),
                commanded: angles,
            },
            points,
        })
    }
}

/// The start's points in the reference frame: track `point_tracks[i]` as reconstructed
/// by the view in slot `origin_slot[i]` (`point_in_cam(slot, track)`, that view's camera
/// frame), moved by `ref_from_cam[slot]`. A point with no finite position keeps the index
/// layout and starts far ahead; fewer than `min_tracks` points in front of their camera
/// is [`AlignError::TooFewTracks`].
pub(crate) fn points_in_ref(
    point_tracks: &[u64],
    origin_slot: &[usize],
    ref_from_cam: &[Isometry3<f64>],
    min_tracks: usize,
    point_in_cam: impl Fn(usize, u64) -> Option<Point3<f64>>,
) -> Result<Vec<Point3<f64>>, AlignError> {
    let mut points = Vec::with_capacity(point_tracks.len());
    let mut in_front = 0;
    for (&track, &slot) in point_tracks.iter().zip(origin_slot) {
        let p = match point_in_cam(slot, track) {
            Some(p) if p.coords.iter().all(|v| v.is_finite()) => {
                if p.z > 0.0 {
                    in_front += 1;
                }
                p
            }
            _ => Point3::new(0.0, 0.0, 1e3),
        };
        points.push(ref_from_cam[slot] * p);
    }
    if in_front < min_tracks {
        return Err(AlignError::TooFewTracks {
            what: "reconstructed in front of the cameras".into(),
            needed: min_tracks,
            got: in_front,
        });
    }
    Ok(points)
}

/// Initial state with `K = K0` for both cameras, the rig of the frame's essential-matrix
/// decomposition, and each view's motion by resection of its left camera against the
/// reference view's quasi-Euclidean points.
fn rough_initial_state(ctx: &InitContext<'_>, frame: &StereoFrame) -> Result<RigState, AlignError> {
    let k0 = frame.k0;
    let t = frame.right_conditioned.column(3).into_owned();
    let rot = headalign_geometry::so3::nearest_rotation(&frame.rotation_guess).ok_or_else(|| {
        AlignError::Geometry {
            step: "rough initialisation".into(),
            cause: headalign_geometry::GeometryError::Numerical("SVD failed".into()),
        }
    })?;
    let right_from_left =
        Isometry3::from_parts(t.into(), nalgebra::UnitQuaternion::from_rotation_matrix(&rot));
    let reference: HashMap<u64, Point3<f64>> =
        ctx.recon[0].iter().filter_map(|(&track, (x, _, _))| dehomogenise3(x).map(|p| (track, p))).collect();
    let ref_from_cam = ctx.resect_views(&k0, &reference)?;
    ctx.state(k0, k0, right_from_left, &ref_from_cam, |slot, track| {
        let (x, _, _) = ctx.recon[slot].get(&track)?;
        dehomogenise3(x)
    })
}

/// `K` of a rotating camera from its image homographies `G_i ~ K R_i K^-1` (Hartley's
/// rotating-camera self-calibration: `G w* G^T = w*`, the solver of
/// [`headalign_geometry::selfcal::dual_image_of_absolute_conic`]), in coordinates
/// conditioned by `k0`. Falls back to `k0` if the conic is not positive definite.
pub(crate) fn k_from_rotations(gs: &[Matrix3<f64>], k0: &Intrinsics) -> Intrinsics {
    let (k, k_inv) = (k0.matrix(), k0.inverse_matrix());
    let ms: Vec<Matrix3<f64>> = gs
        .iter()
        .filter_map(|g| {
            let m = k_inv * g * k;
            let d = m.determinant();
            (d.is_finite() && d != 0.0).then(|| m / d.cbrt())
        })
        .collect();
    headalign_geometry::selfcal::dual_image_of_absolute_conic(&ms)
        .and_then(|w| headalign_geometry::selfcal::k_from_dual_conic(&w))
        .and_then(|kn| Intrinsics::from_matrix(&(k * kn.matrix())))
        .ok()
        .filter(|kk| kk.fx > 0.3 * k0.fx && kk.fx < 3.0 * k0.fx && kk.fy > 0.3 * k0.fy && kk.fy < 3.0 * k0.fy)
        .unwrap_or(*k0)
}

/// Initial state from the image homographies of the rotations: each camera's `K` by
/// rotating-camera self-calibration, the rig from `E = K_R^T F K_L`, Euclidean
/// triangulation, and each view's motion by resection of its left camera.
fn rotation_initial_state(
    ctx: &InitContext<'_>,
    f: &FundamentalMatrix,
    matches: &[(Point2<f64>, Point2<f64>)],
    image_rotations: &[PlanePair],
    k0: &Intrinsics,
) -> Result<RigState, AlignError> {
    let (k_left, k_right) = rotation_intrinsics(image_rotations, k0);
    let right_from_left = relative_pose(&f.0, &k_left, &k_right, matches).step("relative pose of the rig")?;
    rig_start(ctx, f, k_left, k_right, right_from_left)
}

/// Each camera's `K` by rotating-camera self-calibration from its plane homographies.
fn rotation_intrinsics(image_rotations: &[PlanePair], k0: &Intrinsics) -> (Intrinsics, Intrinsics) {
    let gl: Vec<Matrix3<f64>> = image_rotations.iter().map(|g| g.0).collect();
    let gr: Vec<Matrix3<f64>> = image_rotations.iter().map(|g| g.1).collect();
    (k_from_rotations(&gl, k0), k_from_rotations(&gr, k0))
}

/// A start from intrinsics and a rig pose: points triangulated (optimal, under `f`) in
/// the view that first reconstructed them, views resected against the reference points.
fn rig_start(
    ctx: &InitContext<'_>,
    f: &FundamentalMatrix,
    k_left: Intrinsics,
    k_right: Intrinsics,
    right_from_left: Isometry3<f64>,
) -> Result<RigState, AlignError> {
    let p_l = ProjectiveCamera::from_pose(&k_left, &Isometry3::identity());
    let p_r = ProjectiveCamera::from_pose(&k_right, &right_from_left);
    let triangulate = |slot: usize, track: u64| -> Option<Point3<f64>> {
        let (_, l, r) = ctx.recon[slot].get(&track)?;
        dehomogenise3(&triangulate_optimal(f, &p_l, &p_r, l, r).ok()?)
    };
    let reference: Vec<(u64, Point3<f64>)> = ctx.recon[0]
        .keys()
        .filter_map(|&t| triangulate(0, t).filter(|p| p.z > 0.0).map(|p| (t, p)))
        .collect();
    let reference: HashMap<u64, Point3<f64>> = reference.into_iter().collect();
    let ref_from_cam = ctx.resect_views(&k_left, &reference)?;
    ctx.state(k_left, k_right, right_from_left, &ref_from_cam, triangulate)
}

/// The calibrated start: the rotation start's intrinsics, but the rig pose estimated
/// directly with them ([`headalign_geometry::essential::calibrated_relative_pose`], 5 dof,
/// MSAC over all stereo matches at the F threshold) from the pose decomposed from `F` and
/// from generic stereo-head poses (identity rotation, baseline along x or y), instead of
/// taken from `F`. With nearly parallel cameras `F`'s epipole is ill-determined: at 3 px
/// the best-supported `F` of some seeds had its epipole inside the image (true: thousands
/// of pixels outside), and every `F`-based start put the near points behind the cameras.
/// With `lateral_only`, the only start is the stereo-head prior (identity rotation,
/// baseline along x) and the rough intrinsics are used: a scene dominated by a wall facing
/// the head admits, like a plane homography, a second relative pose with the baseline
/// along the wall's normal, which the stereo matches alone cannot reject at 3 px (seed 87:
/// every stereo-only start ended with the baseline forward); the rotations in the
/// adjustment can, so this start goes to the screening whatever its stereo cost.
fn calibrated_initial_state(
    ctx: &InitContext<'_>,
    f: &FundamentalMatrix,
    matches: &[(Point2<f64>, Point2<f64>)],
    (k_left, k_right): (Intrinsics, Intrinsics),
    threshold_px: f64,
    lateral_only: bool,
) -> Result<RigState, AlignError> {
    use headalign_geometry::essential::{calibrated_relative_pose, fundamental_from_pose};
    use nalgebra::{Translation3, UnitQuaternion};
    let lateral = Isometry3::from_parts(Translation3::new(1.0, 0.0, 0.0), UnitQuaternion::identity());
    let mut starts = vec![lateral];
    if !lateral_only {
        starts.push(Isometry3::from_parts(Translation3::new(0.0, 1.0, 0.0), UnitQuaternion::identity()));
        if let Ok(p) = relative_pose(&f.0, &k_left, &k_right, matches) {
            starts.push(p);
            for t in [Translation3::new(1.0, 0.0, 0.0), Translation3::new(0.0, 1.0, 0.0)] {
                starts.push(Isometry3::from_parts(t, p.rotation));
            }
        }
    }
    let (right_from_left, _) = calibrated_relative_pose(&k_left, &k_right, &starts, matches, threshold_px)
        .step("calibrated relative pose of the rig")?;
    let f_cal = fundamental_from_pose(&k_left, &k_right, &right_from_left);
    rig_start(ctx, &f_cal, k_left, k_right, right_from_left)
}
