//! Step 7 of the chain ([`super`] module docs): what the report says of an adjusted
//! calibration. Each motion's screw (rotation angle in degrees, axis, translation and its
//! part along the axis in baselines) read from the adjusted pose; the rotation test on
//! the adjusted motions (a noisy 3D homography can pass the test of step 4 although the
//! rig never turned); the sigma of each focal length in percent of it (from the
//! adjustment's covariance); the mean share of the used views' stereo matches on one
//! plane; and the warnings about data that determine the calibration poorly.
//!
//! Thresholds: [`CalibrateOptions::warn_focal_sigma_pct`](super::CalibrateOptions)
//! (default 0.5 %) and, with one motion only,
//! [`CalibrateOptions::warn_plane_fraction`](super::CalibrateOptions) (default 0.85).
//! Pitfalls: the covariance is linearised at the solution: near a critical configuration
//! the estimate can be off by several of its sigmas, which is why a large sigma is a
//! warning and not only a number. An unknown sigma (a singular covariance) counts as
//! infinite where sigmas are compared ([`worst_focal_sigma_pct`]).

use headalign_geometry::bundle::{BundleResult, RigState};
use headalign_geometry::so3::screw_from_isometry;

use headalign_geometry::camera::Intrinsics;

use super::depth::PlaneCheck;
use super::motion::{ViewMotion, no_rotation};
use super::rig_stereo::StereoGeometry;
use super::sequence::SequenceReport;
use super::{CalibrateOptions, CalibrateReport, MotionReport};
use crate::error::AlignError;
use crate::verge_tilt::Adjustment;

/// What one run of a chain (the reference route's or a sequence's) hands its report
/// ([`chain_report`]).
pub(super) struct ChainRun<'a> {
    /// The rig views used, in the adjustment's order.
    pub(super) views: Vec<String>,
    /// Views left out, with the reason.
    pub(super) skipped: Vec<String>,
    /// The scene-depth check of every view.
    pub(super) planarity: Vec<PlaneCheck>,
    /// Step 2: F, the frame, the triangulations.
    pub(super) stereo: &'a StereoGeometry,
    /// The reported motions (after the adjustment).
    pub(super) motions: Vec<MotionReport>,
    /// Motions fitted by step 3 (the count the warnings judge).
    pub(super) motions_fitted: usize,
    /// Step 4: its plane-at-infinity conditioning and conic uniqueness, its intrinsics
    /// or why it failed.
    pub(super) plane_conditioning: Option<f64>,
    pub(super) conic_uniqueness: Option<f64>,
    pub(super) linear_k: Option<[Intrinsics; 2]>,
    pub(super) linear_error: Option<String>,
    /// Steps 5-6.
    pub(super) adjusted: &'a Adjustment,
    /// Points of the adjustment.
    pub(super) points: usize,
    /// The sequence route's segments (absent on the reference route).
    pub(super) sequence: Option<SequenceReport>,
}

/// The report of one run of a chain (step 7): its parts, the focal sigmas, the plane
/// share and the data warnings; the later stages (restarts, lens choice and sigmas, the
/// residual checks) fill in their own fields.
pub(super) fn chain_report(run: ChainRun<'_>, options: &CalibrateOptions) -> CalibrateReport {
    let adjusted = run.adjusted;
    let focal_sigma_pct = focal_sigma_pct(&adjusted.last);
    let plane_share = plane_share(&run.planarity);
    let warnings = data_warnings(&focal_sigma_pct, plane_share, run.motions_fitted, options);
    CalibrateReport {
        views: run.views,
        skipped: run.skipped,
        planarity: run.planarity,
        stereo_matches: run.stereo.matches,
        stereo_inliers: run.stereo.inliers,
        stereo_rms_px: run.stereo.rms_px,
        motions: run.motions,
        plane_conditioning: run.plane_conditioning,
        conic_uniqueness: run.conic_uniqueness,
        linear: run.linear_k,
        linear_error: run.linear_error,
        start: match adjusted.start_index {
            0 => "linear",
            1 => "rigid",
            _ => "lens grid",
        }
        .to_string(),
        bundle_observations: adjusted.observations.len(),
        bundle_points: run.points,
        bundle_iterations: adjusted.last.report.iterations,
        initial_rms_px: adjusted.first.report.initial_rms_px,
        final_rms_px: adjusted.last.report.final_rms_px,
        sigma_px: adjusted.last.report.sigma_px,
        focal_sigma_pct,
        plane_share,
        estimation_seed: options.estimation.seed,
        restarts: 0,
        lens_selection: None,
        residual_structure: None,
        lens_sigmas: None,
        image_noise: None,
        sequence: run.sequence,
        warnings,
    }
}

/// Each motion's report with the adjusted pose of its view (`state`, view `i + 1` for
/// motion `i`) and whether it entered the linear chain (`linear_used`).
pub(super) fn adjusted_motions(
    motions: &[ViewMotion],
    linear_used: &[bool],
    state: &RigState,
) -> Vec<MotionReport> {
    let mut motion_reports = Vec::new();
    for (i, (m, used)) in motions.iter().zip(linear_used).enumerate() {
        let mut r = m.report.clone();
        r.linear = *used;
        let pose = state.motions.ref_from_cam(i + 1);
        r.translation_baselines = pose.translation.vector.norm();
        if let Some(screw) = screw_from_isometry(&pose, 1e-9) {
            r.rotation_deg = screw.angle.to_degrees();
            r.axis = [screw.axis.direction.x, screw.axis.direction.y, screw.axis.direction.z];
            r.along_axis_baselines = pose.translation.vector.dot(&screw.axis.direction);
        }
        motion_reports.push(r);
    }
    motion_reports
}

/// The rotation test on the adjusted motions: an error if none rotates by
/// `min_rotation_deg` or more.
pub(super) fn require_rotation(
    motions: &[ViewMotion],
    motion_reports: &[MotionReport],
    options: &CalibrateOptions,
) -> Result<(), AlignError> {
    // A noisy 3D homography can pass the rotation test although the rig never turned (a
    // fixed rig and a moving chessboard: one homography passed the test, 0.03-0.15 deg
    // after the adjustment, with a meaningless K). The adjusted motions decide.
    let largest = motion_reports.iter().map(|r| r.rotation_deg).filter(|a| a.is_finite()).fold(0.0, f64::max);
    if largest < options.min_rotation_deg {
        return Err(no_rotation(motions, largest, options));
    }
    Ok(())
}

/// Sigma of the left and right focal length `fx`, percent of it
/// ([`CalibrateReport::focal_sigma_pct`]).
pub(super) fn focal_sigma_pct(bundle: &BundleResult) -> [Option<f64>; 2] {
    let state = &bundle.state;
    let cov = &bundle.covariance;
    [("left", &state.left), ("right", &state.right)]
        .map(|(side, k)| cov.sigma(&format!("{side}.fx")).map(|s| 100.0 * s / k.fx))
}

/// Mean fraction of the used views' stereo matches on one plane
/// ([`CalibrateReport::plane_share`]).
pub(super) fn plane_share(planarity: &[PlaneCheck]) -> f64 {
    let used_checks: Vec<&PlaneCheck> = planarity.iter().filter(|c| !c.planar).collect();
    used_checks.iter().map(|c| c.on_one_plane as f64 / c.stereo_matches.max(1) as f64).sum::<f64>()
        / used_checks.len().max(1) as f64
}

/// The warnings about the data ([`CalibrateReport::warnings`]): a poorly determined focal
/// length, with the lens distortion estimated also that note; one motion in a scene that
/// is mostly one plane.
pub(super) fn data_warnings(
    focal_sigma_pct: &[Option<f64>; 2],
    plane_share: f64,
    motions: usize,
    options: &CalibrateOptions,
) -> Vec<String> {
    let mut warnings = Vec::new();
    if focal_sigma_weak(focal_sigma_pct, options) {
        warnings.push(format!(
            "the focal length is poorly determined: sigma {} (left) / {} (right) of f, above {} %. These motions and this scene are close to a critical configuration, where the estimate can be off by several sigmas. Add a motion about another axis, or turn the rig 20-30 deg about an axis perpendicular to both the baseline and the optical axis (the vertical, for a side-by-side rig) while moving it 0.2-0.3 m along that axis, in a scene with depth (not one wall); avoid turning about the baseline or the optical axis",
            fmt_pct(focal_sigma_pct[0]),
            fmt_pct(focal_sigma_pct[1]),
            options.warn_focal_sigma_pct
        ));
        if options.lens != super::LensChoice::Pinhole {
            warnings.push(
                "the lens distortion is estimated: k1 correlates with f (one motion, 0.5 px: the bound of f grows from 0.14-0.40 % to 0.32-0.65 %); a known lens (a lens file) or a second motion tightens it".into(),
            );
        }
    }
    // One motion in a scene that is mostly one plane: the cost can have its minimum far
    // from the truth, further than the linearised sigma says (rendered seed 20: 92 % and
    // 87 % of the matches on one wall, f 20 % off with a sigma of 0.9 %).
    if plane_weak(motions, plane_share, options) {
        warnings.push(format!(
            "one motion in a scene that is mostly one plane ({:.0} % of the stereo matches on one plane, on average over the views): self-calibration is close to degenerate and the focal length can be off by far more than its sigma; record a second motion, or a scene with more depth",
            100.0 * plane_share
        ));
    }
    warnings
}

/// Either focal sigma above [`CalibrateOptions::warn_focal_sigma_pct`] (the warning of a
/// poorly determined focal length).
fn focal_sigma_weak(focal_sigma_pct: &[Option<f64>; 2], options: &CalibrateOptions) -> bool {
    focal_sigma_pct.iter().flatten().copied().fold(0.0, f64::max) > options.warn_focal_sigma_pct
}

/// The larger of the two focal sigmas, percent; infinite if either is unknown (a singular
/// covariance determines nothing).
pub(super) fn worst_focal_sigma_pct(focal_sigma_pct: &[Option<f64>; 2]) -> f64 {
    focal_sigma_pct.iter().map(|s| s.filter(|v| v.is_finite()).unwrap_or(f64::INFINITY)).fold(0.0, f64::max)
}

/// One motion in a scene mostly on one plane (the warning of
/// [`CalibrateOptions::warn_plane_fraction`]).
fn plane_weak(motions: usize, plane_share: f64, options: &CalibrateOptions) -> bool {
    motions == 1 && plane_share > options.warn_plane_fraction
}

/// True if a calibration carries a warning about its data (the focal length poorly
/// determined, or one motion in a mostly planar scene; not the note that a restart was
/// needed): the data may give more if the images are read more densely ([`Density`]).
///
/// [`Density`]: super::Density
pub fn weak_data(report: &CalibrateReport, options: &CalibrateOptions) -> bool {
    focal_sigma_weak(&report.focal_sigma_pct, options)
        || plane_weak(report.motions.len(), report.plane_share, options)
}

/// A percentage for a message, or "unknown".
pub(super) fn fmt_pct(v: Option<f64>) -> String {
    v.map_or_else(|| "unknown".to_string(), |v| format!("{v:.2} %"))
}
