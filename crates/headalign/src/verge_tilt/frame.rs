//! Step 3 of the estimation ([`super`]): the projective frame and the projective
//! structure of every rig view (paper section 2 and section 3.2 step 1;
//! `docs/how-it-works.md#projective-structure-from-one-rig`).
//!
//! `F` fixes the cameras up to a projective transformation of space (15 dof); the frame
//! chosen here is the quasi-Euclidean one of [`headalign_geometry::frame`] (pixels
//! conditioned by the rough calibration `K0`, `F` decomposed as if it were an essential
//! matrix, the 4 remaining frame dof set so that the right camera is near `[R | t]`), so
//! that the plane at infinity lies near `(0, 0, 0, 1)` and the later linear
//! self-calibration is well conditioned. Both cameras map to pixels: `P_L = K0 [I | 0]`,
//! `P_R = K0 [A | t]`. Every stereo match of every rig view within the `F` threshold
//! (Sampson distance, pixels) is then triangulated optimally
//! ([`headalign_geometry::triangulation::triangulate_optimal`]: the match corrected onto
//! its epipolar lines first), giving one [`Reconstruction`] per view in the same frame.
//!
//! Units: pixels; the points are homogeneous 4-vectors of the projective frame (no
//! scale). Pitfall: the frame's plane at infinity can cut a deep scene, so some points
//! come out "behind" a camera under a metric start; the adjustment re-triangulates them
//! ([`super::adjust`]).

use std::collections::BTreeMap;

use headalign_geometry::camera::{Intrinsics, ProjectiveCamera};
use headalign_geometry::frame::{StereoFrame, quasi_euclidean_frame};
use headalign_geometry::fundamental::FundamentalMatrix;
use headalign_geometry::triangulation::triangulate_optimal;
use nalgebra::{Point2, Vector4};

use super::stereo::StereoGeometry;
use crate::error::{AlignError, StepContext};
use crate::rig::stereo::StereoMatch;

/// One view's reconstruction in the projective frame: track -> (X, left pixel, right pixel).
pub(crate) type Reconstruction = BTreeMap<u64, (Vector4<f64>, Point2<f64>, Point2<f64>)>;

/// The projective frame and the structure of every rig view ([`projective_frame`]).
pub(super) struct ProjectiveStructure {
    /// The quasi-Euclidean frame.
    pub frame: StereoFrame,
    /// The left camera, `K0 [I | 0]`.
    pub p_l: ProjectiveCamera,
    /// The right camera, `K0 [A | t]`.
    pub p_r: ProjectiveCamera,
    /// Per rig view (same order as the rig views), track -> (X, left pixel, right pixel).
    pub recon: Vec<Reconstruction>,
}

/// The quasi-Euclidean frame of `stereo.f` (conditioned by `k0`, cheirality voted by the
/// inliers of `F`) and every rig view's stereo matches within `threshold_px` (Sampson
/// distance) triangulated in it.
pub(super) fn projective_frame(
    stereo: &StereoGeometry,
    k0: &Intrinsics,
    threshold_px: f64,
) -> Result<ProjectiveStructure, AlignError> {
    let f = &stereo.f;
    let frame: StereoFrame =
        quasi_euclidean_frame(&f.0, k0, &stereo.inlier_pairs).step("projective frame")?;
    let (p_l, p_r) = (frame.left_camera(), frame.right_camera());
    let mut recon: Vec<Reconstruction> = Vec::new();
    for matches in &stereo.per_view {
        recon.push(triangulate_view(f, &p_l, &p_r, matches, threshold_px));
    }
    Ok(ProjectiveStructure { frame, p_l, p_r, recon })
}

/// One view's stereo matches within `threshold_px` of `f` (Sampson distance),
/// triangulated optimally under `f` with the cameras `p_l`, `p_r`; a match that does not
/// triangulate is left out.
fn triangulate_view(
    f: &FundamentalMatrix,
    p_l: &ProjectiveCamera,
    p_r: &ProjectiveCamera,
    matches: &[StereoMatch],
    threshold_px: f64,
) -> Reconstruction {
    let mut map = BTreeMap::new();
    for &(track, l, r) in matches {
        if f.sampson_distance(&l, &r) > threshold_px {
            continue;
        }
        if let Ok(x) = triangulate_optimal(f, p_l, p_r, &l, &r) {
            map.insert(track, (x, l, r));
        }
    }
    map
}
