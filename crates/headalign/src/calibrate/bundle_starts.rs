//! Steps 4 and 5's starts ([`super`] module docs): the bundle's point set and
//! observations, and the two starting states of the adjustment.
//!
//! - The points: every track reconstructed by some rig view (the reference's first, then
//!   each later view's new ones; a point lives in the frame of the view that first
//!   reconstructed it, its "origin slot"), and every observation of them in every rig
//!   view (`all_obs`); the screening adjustment's `first_obs` keep, of a track that the
//!   reference and a moved view both reconstruct, only the observations in views whose
//!   3D homography counted it an inlier.
//! - The linear start (step 4; paper section 3.1, Hartley & Zisserman 2nd ed., sections
//!   19.5-19.6): the plane at infinity as the common fixed plane of the motions rotating
//!   by `min_rotation_deg` or more (3 dof), the infinite homographies, `K` from the image
//!   of the absolute conic (5 dof less the options' linear constraints), the Euclidean
//!   upgrade `H_PE`, the right camera by decomposition of `P_R H_PE^-1`, the motions
//!   `D_i`; lengths scaled so that the baseline is 1 (the gauge).
//! - The rigid start: `K = K0` (the image-size guess) for both cameras, the frame's rig,
//!   each view's rigid motion from step 3's 3-point RANSAC.
//!
//! Both starts apply the options' constraints (zero skew, square pixels, principal point
//! at the centre) exactly; the adjustment holds them from there. Pitfalls: too few
//! motions or constraints (one pure rotation, one motion without zero skew) make the
//! linear chain degenerate: that is structural, no start can fix it, and the chain's error
//! is the run's ([`linear_summary`]); any other failure of the linear chain leaves the
//! rigid start alone.

use std::collections::BTreeMap;

use headalign_geometry::GeometryError;
use headalign_geometry::bundle::{BundleObservation, Motions, RigState, Side};
use headalign_geometry::camera::{Intrinsics, dehomogenise3};
use headalign_geometry::distortion::Distortion;
use headalign_geometry::frame::StereoFrame;
use headalign_geometry::homography3d::Homography3;
use headalign_geometry::selfcal::{
    calibrate_from_infinite_homographies, decompose_camera, euclidean_upgrade, infinite_homography,
    motion_from_homography, plane_at_infinity_general,
};
use nalgebra::{Isometry3, Point3, UnitQuaternion};

use super::CalibrateOptions;
use super::motion::{ViewMotion, no_rotation};
use crate::error::{AlignError, StepContext};
use crate::observations::View;
use crate::verge_tilt::{Reconstruction, points_in_ref};

/// The bundle's points and observations (module docs).
pub(super) struct PointSet {
    /// Track id of each point.
    pub(super) point_tracks: Vec<u64>,
    /// The rig view that first reconstructed each point.
    pub(super) origin_slot: Vec<usize>,
    /// Every observation of the points in the rig views.
    pub(super) all_obs: Vec<BundleObservation>,
    /// The observations of the screening adjustment.
    pub(super) first_obs: Vec<BundleObservation>,
}

/// How the rig views are linked: per view the view its 3D homography was fitted from
/// (`None` for a gauge: the first view, and a sequence's other segment gauges) and its
/// segment (views of different segments share no point).
pub(super) struct Links {
    pub(super) parent: Vec<Option<usize>>,
    pub(super) segment: Vec<usize>,
}

impl Links {
    /// Every view's motion fitted from the first, one segment (the reference route).
    pub(super) fn reference(views: usize) -> Self {
        Self { parent: (0..views).map(|k| (k > 0).then_some(0)).collect(), segment: vec![0; views] }
    }
}

/// The point set and the observations of the rig views (module docs; as in
/// [`crate::verge_tilt`]), every view's motion fitted from the first.
pub(super) fn point_set(rig: &[View], recon: &[Reconstruction], motions: &[ViewMotion]) -> PointSet {
    crate::timing::time(crate::timing::Stage::Starts, || {
        point_set_linked(rig, recon, motions, &Links::reference(rig.len()))
    })
}

/// [`point_set`] with the views linked by `links`: a point's observations are those in
/// the views of its origin view's segment, and the screening observations of a track that
/// a view and its parent both reconstruct are those the view's 3D homography (from its
/// parent) counted an inlier.
pub(super) fn point_set_linked(
    rig: &[View],
    recon: &[Reconstruction],
    motions: &[ViewMotion],
    links: &Links,
) -> PointSet {
    crate::timing::time(crate::timing::Stage::Starts, || {
        let mut point_tracks: Vec<u64> = recon[0].keys().copied().collect();
        let mut origin_slot: Vec<usize> = vec![0; point_tracks.len()];
        let mut seen: std::collections::HashSet<u64> = point_tracks.iter().copied().collect();
        for (slot, map) in recon.iter().enumerate().skip(1) {
            for &track in map.keys() {
                if seen.insert(track) {
                    point_tracks.push(track);
                    origin_slot.push(slot);
                }
            }
        }
        let point_index: BTreeMap<u64, usize> =
            point_tracks.iter().enumerate().map(|(i, &t)| (t, i)).collect();
        let segment = |slot: usize| links.segment.get(slot).copied().unwrap_or(0);
        let mut all_obs = Vec::new();
        for (slot, v) in rig.iter().enumerate() {
            for (side, list) in [(Side::Left, &v.capture.left), (Side::Right, &v.capture.right)] {
                for o in list {
                    if let Some(&pi) = point_index.get(&o.track)
                        && segment(origin_slot[pi]) == segment(slot)
                    {
                        all_obs.push(BundleObservation { point: pi, view: slot, side, pixel: o.pixel });
                    }
                }
            }
        }
        let mut quad_inliers: Vec<Vec<u64>> = vec![Vec::new()];
        for m in motions {
            let mut t = m.inlier_tracks.clone();
            t.sort_unstable();
            quad_inliers.push(t);
        }
        let first_obs: Vec<BundleObservation> = all_obs
            .iter()
            .copied()
            .filter(|o| {
                let track = point_tracks[o.point];
                recon[o.view].contains_key(&track)
                    && match links.parent.get(o.view).copied().flatten() {
                        None => true,
                        Some(parent) => {
                            !recon[parent].contains_key(&track)
                                || quad_inliers[o.view].binary_search(&track).is_ok()
                        }
                    }
            })
            .collect();
        PointSet { point_tracks, origin_slot, all_obs, first_obs }
    })
}

/// Everything the starts need.
pub(super) struct Problem<'a> {
    pub(super) recon: &'a [Reconstruction],
    pub(super) point_tracks: &'a [u64],
    pub(super) origin_slot: &'a [usize],
    pub(super) min_tracks: usize,
}

impl Problem<'_> {
    /// A free-motion state from per-view poses and points given in the frame of the view
    /// that reconstructed them.
    fn state(
        &self,
        left: Intrinsics,
        right: Intrinsics,
        right_from_left: Isometry3<f64>,
        ref_from_cam: Vec<Isometry3<f64>>,
        point_in_cam: impl Fn(usize, u64) -> Option<Point3<f64>>,
    ) -> Result<RigState, AlignError> {
        let points =
            points_in_ref(self.point_tracks, self.origin_slot, &ref_from_cam, self.min_tracks, point_in_cam)?;
        Ok(RigState {
            left,
            right,
            left_distortion: Distortion::default(),
            right_distortion: Distortion::default(),
            right_from_left,
            motions: Motions::Free { ref_from_cam },
            points,
        })
    }
}

/// Apply the constraints to a start (the adjustment holds them from there).
fn constrain(k: &Intrinsics, options: &CalibrateOptions, k0: &Intrinsics) -> Intrinsics {
    let mut k = *k;
    if options.zero_skew {
        k.skew = 0.0;
    }
    if options.square_pixels {
        let f = k.mean_focal();
        k.fx = f;
        k.fy = f;
    }
    if options.fix_principal_point {
        k.cx = k0.cx;
        k.cy = k0.cy;
    }
    k
}

/// The linear start and what the report says of it (step 4).
pub(super) struct LinearStart {
    /// The start, or why the linear chain failed.
    pub(super) state: Result<RigState, AlignError>,
    /// Per motion: whether it entered the chain (rotation of its 3D homography at least
    /// `min_rotation_deg`).
    pub(super) used: Vec<bool>,
    /// Conditioning of the plane-at-infinity system, if the chain got that far.
    pub(super) plane_conditioning: Option<f64>,
    /// Uniqueness of the conic solution, if the chain got that far.
    pub(super) conic_uniqueness: Option<f64>,
}

/// Step 4 (module docs): the linear self-calibration from the motions rotating by
/// `min_rotation_deg` or more, as a start of the adjustment.
pub(super) fn linear_start(
    motions: &[ViewMotion],
    frame: &StereoFrame,
    k0: &Intrinsics,
    problem: &Problem<'_>,
    options: &CalibrateOptions,
) -> LinearStart {
    let used: Vec<bool> =
        motions.iter().map(|m| m.report.homography_rotation_deg >= options.min_rotation_deg).collect();
    linear_start_from(motions, used, frame, k0, problem, options)
}

/// [`linear_start`] from the motions marked in `used` (one flag per motion).
pub(super) fn linear_start_from(
    motions: &[ViewMotion],
    used: Vec<bool>,
    frame: &StereoFrame,
    k0: &Intrinsics,
    problem: &Problem<'_>,
    options: &CalibrateOptions,
) -> LinearStart {
    crate::timing::time(crate::timing::Stage::Starts, || {
        let mut diagnostics = LinearDiagnostics { plane_conditioning: None, conic_uniqueness: None };
        let state = linear_chain(motions, &used, frame, k0, problem, options, &mut diagnostics);
        LinearStart {
            state,
            used,
            plane_conditioning: diagnostics.plane_conditioning,
            conic_uniqueness: diagnostics.conic_uniqueness,
        }
    })
}

/// The conditioning figures of the linear chain, set as it reaches them.
struct LinearDiagnostics {
    plane_conditioning: Option<f64>,
    conic_uniqueness: Option<f64>,
}

/// The linear chain (module docs) over the motions marked in `used`.
fn linear_chain(
    motions: &[ViewMotion],
    used: &[bool],
    frame: &StereoFrame,
    k0: &Intrinsics,
    problem: &Problem<'_>,
    options: &CalibrateOptions,
    diagnostics: &mut LinearDiagnostics,
) -> Result<RigState, AlignError> {
    let p_r = frame.right_camera();
    let hs: Vec<Homography3> = motions
        .iter()
        .zip(used)
        .filter(|(_, u)| **u)
        .map(|(m, _)| m.model.h.normalized_det())
        .collect::<Result<_, _>>()
        .step("3D homography")?;
    if hs.is_empty() {
        let largest = motions.iter().map(|m| m.report.homography_rotation_deg).fold(0.0, f64::max);
        return Err(no_rotation(motions, largest, options));
    }
    let (plane, cond) = plane_at_infinity_general(&hs).step("plane at infinity")?;
    diagnostics.plane_conditioning = Some(cond);
    let ms = hs
        .iter()
        .map(|h| infinite_homography(h, &plane))
        .collect::<Result<Vec<_>, _>>()
        .step("infinite homography")?;
    let (k_c, uniq) =
        calibrate_from_infinite_homographies(&ms, &options.constraints()).step("self-calibration")?;
    diagnostics.conic_uniqueness = Some(uniq);
    let k_left = Intrinsics::from_matrix(&(k0.matrix() * k_c.matrix())).step("left intrinsics")?;
    let h_pe = euclidean_upgrade(&k_c, &plane).step("Euclidean upgrade")?;
    let h_pe_inv = h_pe.try_inverse().ok_or_else(|| AlignError::Geometry {
        step: "Euclidean upgrade".into(),
        cause: GeometryError::Numerical("H_PE is singular".into()),
    })?;
    let (k_right, right_from_left) = decompose_camera(&(p_r.0 * h_pe_inv)).step("right camera")?;
    let baseline = right_from_left.translation.vector.norm();
    if !(baseline.is_finite() && baseline > 0.0) {
        return Err(AlignError::Geometry {
            step: "right camera".into(),
            cause: GeometryError::Degenerate("zero baseline".into()),
        });
    }
    let scale = 1.0 / baseline;
    let scaled =
        |m: &Isometry3<f64>| Isometry3::from_parts((m.translation.vector * scale).into(), m.rotation);
    let mut ref_from_cam = vec![Isometry3::identity()];
    for m in motions {
        let d = motion_from_homography(&m.model.h, &h_pe).step("rigid motion")?;
        ref_from_cam.push(scaled(&d.inverse()));
    }
    problem.state(
        constrain(&k_left, options, k0),
        constrain(&k_right, options, k0),
        scaled(&right_from_left),
        ref_from_cam,
        |slot, track| {
            let (x, _, _) = problem.recon[slot].get(&track)?;
            dehomogenise3(&(h_pe * x)).map(|p| Point3::from(p.coords * scale))
        },
    )
}

/// The linear chain's intrinsics (left, right) or its error message, for the report; a
/// structural failure (too few motions or constraints: a degenerate geometry, or a
/// missing motion) is the run's error instead.
pub(super) fn linear_summary(
    linear: &Result<RigState, AlignError>,
) -> Result<(Option<[Intrinsics; 2]>, Option<String>), AlignError> {
    Ok(match linear {
        Ok(s) => (Some([s.left, s.right]), None),
        // Too few motions or constraints is structural: no start can fix it.
        Err(e @ AlignError::Geometry { cause: GeometryError::Degenerate(_), .. }) => {
            return Err(AlignError::MissingMotion(e.to_string()));
        }
        Err(AlignError::MissingMotion(m)) => return Err(AlignError::MissingMotion(m.clone())),
        Err(e) => (None, Some(e.to_string())),
    })
}

/// The rigid start (module docs): `K = K0`, the frame's rig, each view's rigid motion in
/// the frame.
pub(super) fn rigid_start(
    motions: &[ViewMotion],
    frame: &StereoFrame,
    k0: &Intrinsics,
    problem: &Problem<'_>,
    options: &CalibrateOptions,
) -> Result<RigState, AlignError> {
    crate::timing::time(crate::timing::Stage::Starts, || {
        let t = frame.right_conditioned.column(3).into_owned();
        let rot = headalign_geometry::so3::nearest_rotation(&frame.rotation_guess).ok_or_else(|| {
            AlignError::Geometry {
                step: "rigid start".into(),
                cause: GeometryError::Numerical("SVD failed".into()),
            }
        })?;
        let right_from_left = Isometry3::from_parts(t.into(), UnitQuaternion::from_rotation_matrix(&rot));
        let mut ref_from_cam = vec![Isometry3::identity()];
        for m in motions {
            let d = m.rigid.ok_or_else(|| AlignError::NotARotation {
                view: m.report.view.clone(),
                why: "no rigid motion fits its matches in the quasi-Euclidean frame".into(),
            })?;
            ref_from_cam.push(d.inverse());
        }
        problem.state(
            constrain(k0, options, k0),
            constrain(k0, options, k0),
            right_from_left,
            ref_from_cam,
            |slot, track| problem.recon[slot].get(&track).and_then(|(x, _, _)| dehomogenise3(x)),
        )
    })
}
