//! Step 2 of the estimation ([`super`]): the stereo geometry, one fundamental matrix `F`
//! from the stereo matches of every rig view together (paper section 3.2 step 1;
//! `docs/how-it-works.md#2-estimation` item 1).
//!
//! While only pan and elevation move the rig does not change, so the left-right matches
//! of all rig views obey one `F` (7 dof) and pooling them conditions it far better than
//! any single view. `F` comes from RANSAC (7-point samples, normalised 8-point polish,
//! the DEGENSAC test against a dominant plane) refined on Sampson distance
//! ([`headalign_geometry::fundamental::estimate_fundamental`]), with the threshold and the
//! minimum sample count of [`super::EstimationOptions::fundamental`].
//!
//! Units: Sampson distances in pixels. Pitfall: this `F` decides the basin of everything
//! after it. One fitted to a dominant plane, or a RANSAC stopped early by the adaptive
//! count, shifted the relative yaw against depth and cost up to 7 % in focal length, hence
//! DEGENSAC and at least 500 samples by default.

use headalign_geometry::fundamental::{FundamentalMatrix, estimate_fundamental};
use headalign_geometry::ransac::RansacOptions;
use nalgebra::Point2;

use super::EstimationOptions;
use crate::error::{AlignError, StepContext};
use crate::observations::View;
use crate::rig::stereo::{StereoMatch, rms, stereo_matches};

/// The stereo geometry of the rig views ([`stereo_geometry`]).
pub(super) struct StereoGeometry {
    /// Stereo matches of each rig view (in the order of the rig views), sorted by track.
    pub per_view: Vec<Vec<StereoMatch>>,
    /// The (left, right) pixels of every stereo match of every rig view.
    pub pairs: Vec<(Point2<f64>, Point2<f64>)>,
    /// Number of stereo inliers of `f`.
    pub inliers: usize,
    /// The fundamental matrix of the rig.
    pub f: FundamentalMatrix,
    /// The (left, right) pixels of the inliers of `f`.
    pub inlier_pairs: Vec<(Point2<f64>, Point2<f64>)>,
    /// RMS Sampson distance of the inliers, pixels.
    pub rms_px: f64,
}

/// One `F` from the stereo matches of the rig views `rig` (indices into `views`) pooled,
/// by RANSAC seeded with [`EstimationOptions::seed`]; fewer than
/// [`EstimationOptions::min_tracks`] matches is [`AlignError::TooFewTracks`].
pub(super) fn stereo_geometry(
    views: &[View],
    rig: &[usize],
    options: &EstimationOptions,
) -> Result<StereoGeometry, AlignError> {
    let per_view: Vec<Vec<StereoMatch>> = rig.iter().map(|&i| stereo_matches(&views[i].capture)).collect();
    let pairs: Vec<(Point2<f64>, Point2<f64>)> = per_view.iter().flatten().map(|m| (m.1, m.2)).collect();
    if pairs.len() < options.min_tracks {
        return Err(AlignError::TooFewTracks {
            what: "matched between left and right".into(),
            needed: options.min_tracks,
            got: pairs.len(),
        });
    }
    let f_opts = RansacOptions { seed: options.seed, ..options.fundamental };
    let f_report = estimate_fundamental(&pairs, &f_opts).step("fundamental matrix")?;
    let f: FundamentalMatrix = f_report.model;
    let inlier_pairs: Vec<(Point2<f64>, Point2<f64>)> = f_report.inliers.iter().map(|&i| pairs[i]).collect();
    let rms_px = rms(inlier_pairs.iter().map(|(l, r)| f.sampson_distance(l, r)));
    Ok(StereoGeometry { per_view, pairs, inliers: f_report.inliers.len(), f, inlier_pairs, rms_px })
}
