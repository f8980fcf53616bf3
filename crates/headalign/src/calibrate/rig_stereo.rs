//! Step 2 of the chain ([`super`] module docs): the rig's stereo geometry. One
//! fundamental matrix from the stereo matches of all the rig's views together (the rig is
//! fixed between them; DEGENSAC RANSAC on the normalised 8/7-point estimates, then
//! refinement on the Sampson distance: 7 dof, pixels, threshold
//! `estimation.fundamental.threshold`), the quasi-Euclidean projective frame
//! `P_L = [I | 0]` (`K0`, the rough guess from the image size, conditions it), and each
//! view's inlier matches triangulated by optimal correction (Hartley & Zisserman 2nd ed.,
//! sections 11.6, 10.4 and 12.5). Also [`rig_from_known_intrinsics`]: the rig from known
//! intrinsics, what a planar target or a single stereo pair still gives (`E = K_R^T F K_L`,
//! 5 dof refined on the Sampson distance).
//!
//! Pitfalls: the matches of all views share one `F` only if the vergence did not move
//! (step 1 left such views out); too few matches over all views is an error, not a
//! degenerate `F`. The frame is projective: lengths mean nothing before step 4.

use headalign_geometry::camera::Intrinsics;
use headalign_geometry::frame::{StereoFrame, quasi_euclidean_frame};
use headalign_geometry::fundamental::{FundamentalMatrix, estimate_fundamental};
use headalign_geometry::ransac::{RansacOptions, RansacReport};
use headalign_geometry::triangulation::triangulate_optimal;
use nalgebra::{Isometry3, Point2};
use rayon::prelude::*;

use crate::error::{AlignError, StepContext};
use crate::observations::View;
use crate::rig::stereo::{StereoMatch, rms, stereo_matches};
use crate::verge_tilt::{EstimationOptions, Reconstruction};

/// The stereo geometry of the rig's views (step 2).
pub(super) struct StereoGeometry {
    /// Stereo matches over all views.
    pub(super) matches: usize,
    /// Inliers of F.
    pub(super) inliers: usize,
    /// RMS Sampson distance of the inliers, pixels.
    pub(super) rms_px: f64,
    /// The quasi-Euclidean projective frame of F.
    pub(super) frame: StereoFrame,
    /// Per view (the rig's order), its inlier matches triangulated in the frame.
    pub(super) recon: Vec<Reconstruction>,
}

/// Step 2 (module docs): F from the stereo matches of all `rig` views, the projective
/// frame, each view's inliers triangulated. `k0` conditions the frame.
pub(super) fn stereo_geometry(
    rig: &[View],
    k0: &Intrinsics,
    est: &EstimationOptions,
) -> Result<StereoGeometry, AlignError> {
    stereo_geometry_sampled(rig, k0, est, None)
}

/// [`stereo_geometry`] with F's RANSAC run on at most `ransac_pairs` of the stereo
/// matches (every `n`-th, in view order), then refined on the Sampson distance over the
/// inliers among all of them and re-selected until stable (at most 10 rounds, as the
/// RANSAC's own refinement). For a sequence's keyframes (tens of thousands of matches of
/// one rig): the RANSAC's cost grows with the matches it scores, the refinement's hardly.
pub(super) fn stereo_geometry_sampled(
    rig: &[View],
    k0: &Intrinsics,
    est: &EstimationOptions,
    ransac_pairs: Option<usize>,
) -> Result<StereoGeometry, AlignError> {
    crate::timing::time(crate::timing::Stage::StereoF, || {
        let per_view: Vec<Vec<StereoMatch>> = rig.iter().map(|v| stereo_matches(&v.capture)).collect();
        let pairs: Vec<(Point2<f64>, Point2<f64>)> = per_view.iter().flatten().map(|m| (m.1, m.2)).collect();
        let (f, inliers) = match ransac_pairs.filter(|&m| pairs.len() > m) {
            None => {
                let f_report = stereo_fundamental(&pairs, est)?;
                (f_report.model, f_report.inliers)
            }
            Some(m) => {
                let step = pairs.len().div_ceil(m.max(1));
                let sample: Vec<(Point2<f64>, Point2<f64>)> = pairs.iter().copied().step_by(step).collect();
                let f_report = stereo_fundamental(&sample, est)?;
                refine_on_all(f_report.model, &pairs, est.fundamental.threshold)
            }
        };
        let inlier_pairs: Vec<(Point2<f64>, Point2<f64>)> = inliers.iter().map(|&i| pairs[i]).collect();
        let stereo_rms = rms(inlier_pairs.iter().map(|(l, r)| f.sampson_distance(l, r)));
        let frame = quasi_euclidean_frame(&f.0, k0, &inlier_pairs).step("projective frame")?;
        let (p_l, p_r) = (frame.left_camera(), frame.right_camera());
        // Each view's matches triangulated on their own (in parallel, in the views' order).
        let recon: Vec<Reconstruction> = per_view
            .par_iter()
            .map(|matches| {
                matches
                    .iter()
                    .filter(|(_, l, r)| f.sampson_distance(l, r) <= est.fundamental.threshold)
                    .filter_map(|&(t, l, r)| {
                        triangulate_optimal(&f, &p_l, &p_r, &l, &r).ok().map(|x| (t, (x, l, r)))
                    })
                    .collect()
            })
            .collect();
        Ok(StereoGeometry { matches: pairs.len(), inliers: inliers.len(), rms_px: stereo_rms, frame, recon })
    })
}

/// `f` refined on the Sampson distance over its inliers (within `threshold`) among all
/// `pairs`, re-selected until the set is stable or the refinement stops improving (at most
/// 10 rounds); the model and its inliers.
fn refine_on_all(
    f: FundamentalMatrix,
    pairs: &[(Point2<f64>, Point2<f64>)],
    threshold: f64,
) -> (FundamentalMatrix, Vec<usize>) {
    let select = |f: &FundamentalMatrix| -> Vec<usize> {
        (0..pairs.len()).filter(|&i| f.sampson_distance(&pairs[i].0, &pairs[i].1) <= threshold).collect()
    };
    let (mut f, mut inliers) = (f, select(&f));
    for _ in 0..10 {
        let inlier_pairs: Vec<_> = inliers.iter().map(|&i| pairs[i]).collect();
        let Ok(refined) = f.refine_sampson(&inlier_pairs) else { break };
        let next = select(&refined);
        if next.len() < inliers.len() {
            break;
        }
        f = refined;
        if next == inliers {
            break;
        }
        inliers = next;
    }
    (f, inliers)
}

/// The rig from known intrinsics (no self-calibration): what a planar target or a single
/// stereo pair still gives. The views' observations must already be undistorted.
#[derive(Debug, Clone)]
pub struct KnownIntrinsicsRig {
    /// The fundamental matrix of the refined rig, `K_R^-T [t]x R K_L^-1` (pixels,
    /// `x_R^T F x_L = 0`).
    pub fundamental: FundamentalMatrix,
    /// `right_from_left` with a unit translation: decomposed from `E = K_R^T F K_L` of
    /// the RANSAC `F`, then refined on its 5 dof over F's inliers (Sampson distance).
    pub right_from_left: Isometry3<f64>,
    /// Stereo matches over all views.
    pub stereo_matches: usize,
    /// Inliers of F.
    pub stereo_inliers: usize,
    /// RMS Sampson distance of the inliers under the refined rig, pixels.
    pub stereo_rms_px: f64,
    /// The inlier matches (left, right).
    pub inlier_pairs: Vec<(Point2<f64>, Point2<f64>)>,
}

/// F by RANSAC (the estimation's options and seed) from the stereo matches `pairs`
/// (left, right) of all views together; too few matches is an error.
fn stereo_fundamental(
    pairs: &[(Point2<f64>, Point2<f64>)],
    options: &EstimationOptions,
) -> Result<RansacReport<FundamentalMatrix>, AlignError> {
    if pairs.len() < options.min_tracks {
        return Err(AlignError::TooFewTracks {
            what: "matched between left and right".into(),
            needed: options.min_tracks,
            got: pairs.len(),
        });
    }
    estimate_fundamental(pairs, &RansacOptions { seed: options.seed, ..options.fundamental })
        .step("fundamental matrix")
}

/// F by RANSAC from the stereo matches of every view (the rig is fixed, so matches on
/// different board poses together are not planar), then the rig from `E` with the known
/// intrinsics `k_left`, `k_right` (cheirality vote over the inliers).
pub fn rig_from_known_intrinsics(
    views: &[View],
    k_left: &Intrinsics,
    k_right: &Intrinsics,
    options: &EstimationOptions,
) -> Result<KnownIntrinsicsRig, AlignError> {
    options.validate()?;
    let pairs: Vec<(Point2<f64>, Point2<f64>)> =
        views.iter().flat_map(|v| stereo_matches(&v.capture)).map(|m| (m.1, m.2)).collect();
    let f_report = stereo_fundamental(&pairs, options)?;
    let f = f_report.model;
    let inlier_pairs: Vec<(Point2<f64>, Point2<f64>)> = f_report.inliers.iter().map(|&i| pairs[i]).collect();
    let decomposed = headalign_geometry::frame::relative_pose(&f.0, k_left, k_right, &inlier_pairs)
        .step("relative pose from E")?;
    // The 5-dof ML refinement on the inliers: decomposing the 7-dof F alone lets noise in
    // its two surplus degrees of freedom leak into the pose (measured on the Middlebury
    // motorcycle pair, docs/results-real.md).
    let (right_from_left, stereo_rms_px) =
        headalign_geometry::frame::refine_relative_pose(&decomposed, k_left, k_right, &inlier_pairs, 100)
            .step("relative pose refinement")?;
    let f =
        FundamentalMatrix(headalign_geometry::frame::fundamental_of_pose(&right_from_left, k_left, k_right));
    Ok(KnownIntrinsicsRig {
        stereo_rms_px,
        fundamental: f,
        right_from_left,
        stereo_matches: pairs.len(),
        stereo_inliers: inlier_pairs.len(),
        inlier_pairs,
    })
}
