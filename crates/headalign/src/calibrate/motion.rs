//! Step 3 of the chain ([`super`] module docs): per moved view, the 3D homography `H`
//! (`Y ~ H X`, 15 dof; a rigid motion conjugated by the frame's unknown projective map)
//! from the reference view's reconstruction to the view's, over the tracks both
//! reconstruct (quadruplets: both pixels of both views). First a 3-point rigid RANSAC in
//! the quasi-Euclidean frame (robust to the large motions of a hand-held rig; 6 dof), and
//! where it explains fewer than half of the quadruplets the 5-point DLT RANSAC as
//! fallback; the better model is polished on the symmetric transfer error (pixels, the
//! four image distances of a quadruplet, threshold `estimation.homography.threshold`) and
//! its inliers re-selected until stable (at most 10 rounds; Hartley & Zisserman 2nd ed.,
//! section 4.7; paper section 3). The rigid model is also kept, as the rigid start of
//! step 5.
//!
//! Seeds: each view's RANSAC uses the estimation seed plus the view's slot, so a restart
//! with the next seed ([`CalibrateOptions::restarts`](super::CalibrateOptions::restarts))
//! draws other samples; the views are fitted in parallel (rayon), the first failure in
//! the rig's order reported: the same result at any thread count. Pitfalls: the rotation angle read from `H`'s trace is a
//! similarity invariant but noisy for small motions; a view that fits no `H` fails the
//! run (seeded: another seed may pass), as does one with fewer than
//! `estimation.min_tracks` common tracks (not seeded).

use headalign_geometry::frame::StereoFrame;
use headalign_geometry::homography3d::{
    Homography3, Homography3Estimator, Quadruplet, TransferModel, symmetric_transfer_error,
};
use headalign_geometry::ransac::{RansacOptions, ransac};
use headalign_geometry::registration::RigidFrameEstimator;
use nalgebra::{Isometry3, UnitQuaternion};
use rayon::prelude::*;

use super::{CalibrateOptions, MotionReport, Seeded};
use crate::error::AlignError;
use crate::observations::View;
use crate::rig::stereo::rms;
use crate::verge_tilt::{PolishedHomography, Reconstruction, guided_reselection, polish};

/// Rotation angle (radians) of a 3D homography conjugate to a rigid motion, from its
/// trace at determinant 1 (`tr D = 2 + 2 cos theta`).
fn homography_angle(h: &Homography3) -> Option<f64> {
    let n = h.normalized_det().ok()?;
    Some(((n.0.trace() - 2.0) / 2.0).clamp(-1.0, 1.0).acos())
}

/// A 3D homography between the reference and one view (module docs, step 3).
pub(super) struct ViewMotion {
    pub(super) model: TransferModel,
    pub(super) rigid: Option<Isometry3<f64>>,
    pub(super) inlier_tracks: Vec<u64>,
    pub(super) report: MotionReport,
}

/// The 3D homography of one view from another (module docs, step 3) over their
/// quadruplets `quads` (of tracks `tracks`), RANSAC seeded by `seed`; `view` names the
/// moved view in errors.
pub(super) fn fit_motion(
    quads: &[Quadruplet],
    tracks: &[u64],
    frame: &StereoFrame,
    options: &CalibrateOptions,
    view: &str,
    seed: u64,
) -> Result<ViewMotion, AlignError> {
    let (p_l, p_r) = (frame.left_camera(), frame.right_camera());
    let threshold = options.estimation.homography.threshold;
    let opts = RansacOptions { seed, ..options.estimation.homography };
    let rigid_estimator = RigidFrameEstimator { p_left: p_l, p_right: p_r };
    let all: Vec<usize> = (0..quads.len()).collect();
    let select = |m: &TransferModel| -> Vec<usize> {
        all.iter()
            .copied()
            .filter(|&i| symmetric_transfer_error(m, &p_l, &p_r, &quads[i]) <= threshold)
            .collect()
    };
    let mut best: Option<(TransferModel, usize)> = None;
    let mut rigid = None;
    if let Ok(rep) = ransac(&rigid_estimator, quads, &opts) {
        rigid = Some(rep.model);
        let start = polish(&rep.model, quads, &rep.inliers, &p_l, &p_r).unwrap_or(rep.model);
        let n = select(&start).len();
        best = Some((start, n));
    }
    if best.as_ref().is_none_or(|(_, n)| *n * 2 < quads.len()) {
        let estimator = Homography3Estimator { p_left: p_l, p_right: p_r };
        if let Ok(rep) = ransac(&PolishedHomography(&estimator), quads, &opts) {
            let n = select(&rep.model).len();
            if best.as_ref().is_none_or(|(_, b)| n > *b) {
                best = Some((rep.model, n));
            }
        }
    }
    let Some((model, _)) = best else {
        return Err(AlignError::NotARotation {
            view: view.to_string(),
            why: "no 3D homography fits its matches with the reference view".into(),
        });
    };
    let (model, inliers, _) = guided_reselection(model, quads, &p_l, &p_r, threshold);
    if inliers.len() < options.estimation.min_tracks {
        return Err(AlignError::TooFewTracks {
            what: format!("fitting the 3D homography of view '{view}'"),
            needed: options.estimation.min_tracks,
            got: inliers.len(),
        });
    }
    let rigid_motion = rigid.map(|m| {
        let h = m.h.0 / m.h.0[(3, 3)];
        let r = headalign_geometry::so3::nearest_rotation(&h.fixed_view::<3, 3>(0, 0).into_owned());
        let t = h.fixed_view::<3, 1>(0, 3).into_owned();
        r.map(|r| Isometry3::from_parts(t.into(), UnitQuaternion::from_rotation_matrix(&r)))
    });
    let angle = homography_angle(&model.h).unwrap_or(f64::NAN);
    Ok(ViewMotion {
        model,
        rigid: rigid_motion.flatten(),
        inlier_tracks: inliers.iter().map(|&i| tracks[i]).collect(),
        report: MotionReport {
            view: view.to_string(),
            candidates: quads.len(),
            inliers: inliers.len(),
            rms_transfer_px: rms(inliers
                .iter()
                .map(|&i| symmetric_transfer_error(&model, &p_l, &p_r, &quads[i]))),
            homography_rotation_deg: angle.to_degrees(),
            relative_to: None,
            linear: false,
            rotation_deg: f64::NAN,
            axis: [f64::NAN; 3],
            translation_baselines: f64::NAN,
            along_axis_baselines: f64::NAN,
        },
    })
}

/// The error of views that show the scene from (nearly) the same rig pose.
/// `largest`: the largest rotation found (deg), by the 3D homographies or by the
/// adjustment.
pub(super) fn no_rotation(motions: &[ViewMotion], largest: f64, options: &CalibrateOptions) -> AlignError {
    AlignError::MissingMotion(format!(
        "no view is rotated by {} deg or more relative to the first (largest {largest:.2} deg over {} views): the matches between views see the scene from the same rig pose. A fixed rig looking at a moving target sees a static background, and a planar target (a chessboard) has no projective reconstruction to relate between views: self-calibration needs the rig itself to move in a scene with depth (with known intrinsics, --intrinsics gives the rig from the fundamental matrix)",
        options.min_rotation_deg,
        motions.len()
    ))
}

/// Step 3 (module docs): the 3D homography of every moved view of `rig` from the
/// reference (`recon[0]`), in the rig's order. Sets `seeded` when a view fits none (the
/// tracks it shares with the reference); an error also when a view shares fewer than
/// `min_tracks` tracks with the reference, or no view moved.
pub(super) fn fit_motions(
    rig: &[View],
    recon: &[Reconstruction],
    frame: &StereoFrame,
    options: &CalibrateOptions,
    seeded: &mut Option<Seeded>,
) -> Result<Vec<ViewMotion>, AlignError> {
    let est = &options.estimation;
    // Each moved view's quadruplets and 3D homography on its own (in parallel, each
    // seeded by its slot), the first failure in the rig's order reported.
    let fitted: Vec<Result<ViewMotion, (AlignError, Option<Seeded>)>> = rig
        .par_iter()
        .enumerate()
        .skip(1)
        .map(|(slot, v)| {
            crate::timing::time(crate::timing::Stage::Homographies, || {
                let (mut tracks, mut quads) = (Vec::new(), Vec::new());
                for (track, (x, l0, r0)) in &recon[0] {
                    if let Some((y, l1, r1)) = recon[slot].get(track) {
                        tracks.push(*track);
                        quads.push(Quadruplet {
                            x: *x,
                            y: *y,
                            left0: *l0,
                            right0: *r0,
                            left1: *l1,
                            right1: *r1,
                        });
                    }
                }
                if quads.len() < est.min_tracks {
                    return Err((
                        AlignError::TooFewTracks {
                            what: format!("seen in both stereo views '{}' and '{}'", rig[0].name, v.name),
                            needed: est.min_tracks,
                            got: quads.len(),
                        },
                        None,
                    ));
                }
                let common = quads.len();
                fit_motion(&quads, &tracks, frame, options, &v.name, est.seed.wrapping_add(slot as u64))
                    .map_err(|e| (e, Some(Seeded { common_tracks: common, fitting: 0 })))
            })
        })
        .collect();
    let mut motions: Vec<ViewMotion> = Vec::with_capacity(fitted.len());
    for f in fitted {
        match f {
            Ok(m) => motions.push(m),
            Err((e, s)) => {
                if s.is_some() {
                    *seeded = s;
                }
                return Err(e);
            }
        }
    }
    if motions.is_empty() {
        return Err(AlignError::MissingMotion(
            "one usable view: self-calibration needs the rig in at least two positions".into(),
        ));
    }
    Ok(motions)
}

/// What a failure of the adjustment from every start reports ([`Seeded`]): the motion
/// with the fewest tracks fitting its 3D homography, and the tracks it shares with the
/// reference.
pub(super) fn weakest_motion(motions: &[ViewMotion]) -> Option<Seeded> {
    motions
        .iter()
        .map(|m| Seeded { common_tracks: m.report.candidates, fitting: m.report.inliers })
        .min_by_key(|x| x.fitting)
}
