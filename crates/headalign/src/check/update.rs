//! The full update (`check --update OUT --full`): the intrinsics and the lenses refitted
//! as well as the rig, by the self-calibration of the same views
//! ([`crate::calibrate::calibrate_views`]; it needs rig motions between the views), in the
//! given calibration's lens model (radial-tangential with the terms the given one has:
//! `k3` or `p1 p2` non-zero) and with its baseline length; then the rotation refitted
//! on the stereo matches by the check itself ([`super::check_views`] of the new
//! calibration, whose `updated` is taken).
//!
//! Validation: the update is offered only when the self-calibration succeeds, the re-check
//! offers its own rotation update, and the re-check's refitted median Sampson distance is
//! at most the given calibration's (the update fits the matches at least as well as what
//! it replaces). Otherwise [`FullUpdate::refused`] says why and nothing is offered.
//! Units: those of the check. Pitfalls: the self-calibration is far slower than the check
//! (seconds per view), and from a few views its focal lengths carry sigmas of a percent:
//! the re-check sees only what moves points across the epipolar lines.

use super::{CheckError, CheckOptions, CheckReport, check_views};
use crate::calibrate::LensChoice;
use crate::calibrate::views::{CalibrateViewsOptions, StereoViews, calibrate_views};
use crate::calibration::{StereoCalibration, TranslationUnit};
use headalign_geometry::distortion::{DistortionTerms, LensKind};

/// What the full update found.
pub struct FullUpdate {
    /// The updated calibration (`None`: refused).
    pub calibration: Option<StereoCalibration>,
    /// The check of the self-calibration's result on the same views (`None` when the
    /// self-calibration failed).
    pub recheck: Option<CheckReport>,
    /// Why nothing is offered.
    pub refused: Option<String>,
}

impl FullUpdate {
    fn refusal(why: String, recheck: Option<CheckReport>) -> Self {
        Self { calibration: None, recheck, refused: Some(why) }
    }
}

/// The full update of `given` from `views`, whose check is `report` (module docs);
/// `calibrate` holds the self-calibration's options (its lens choice is replaced by the
/// given calibration's model).
pub fn update_full(
    views: StereoViews<'_>,
    given: &StereoCalibration,
    report: &CheckReport,
    options: &CheckOptions,
    calibrate: &CalibrateViewsOptions,
) -> Result<FullUpdate, CheckError> {
    let baseline_m = super::metric_baseline(given, options)?;
    let mut opts = calibrate.clone();
    let kind = given.distortion[0].kind;
    opts.calibrate.lens =
        if kind == LensKind::Pinhole { LensChoice::Pinhole } else { LensChoice::Model(kind) };
    let d = given.distortion[0];
    let terms = match kind {
        LensKind::RadialTangential if d.k3 != 0.0 => Some(DistortionTerms::Full5),
        LensKind::RadialTangential if d.p1 != 0.0 || d.p2 != 0.0 => Some(DistortionTerms::Full4),
        _ => None,
    };
    opts.calibrate.lens_terms = crate::calibrate::lens_terms(opts.calibrate.lens, terms);
    opts.lenses = None;
    let cal = match calibrate_views(views, &opts, &mut |_| {}) {
        Ok(c) => c,
        Err(e) => return Ok(FullUpdate::refusal(format!("self-calibration failed: {e}"), None)),
    };
    let bundle = &cal.calibration.bundle;
    let mut fresh = StereoCalibration::from_bundle(bundle, given.image_size, Some(baseline_m))?;
    fresh.distortion = [bundle.state.left_distortion, bundle.state.right_distortion];
    if given.unit == TranslationUnit::Baselines {
        fresh.right_from_left.translation.vector /= baseline_m;
        fresh.unit = TranslationUnit::Baselines;
    }
    let recheck =
        check_views(views, &fresh, &CheckOptions { baseline_m: Some(baseline_m), ..options.clone() })?;
    let Some(updated) = recheck.updated.clone() else {
        let why = recheck.update_refused.clone().unwrap_or_default();
        return Ok(FullUpdate::refusal(
            format!("the re-check's refit does not validate: {why}"),
            Some(recheck),
        ));
    };
    let (now, before) = (recheck.refit.sampson_px.median, report.sampson_px.median);
    if now.partial_cmp(&before) == Some(std::cmp::Ordering::Greater) || now.is_nan() {
        return Ok(FullUpdate::refusal(
            format!(
                "the self-calibration fits the matches worse than the given calibration (median Sampson {now:.3} px against {before:.3} px)"
            ),
            Some(recheck),
        ));
    }
    Ok(FullUpdate { calibration: Some(updated), recheck: Some(recheck), refused: None })
}
