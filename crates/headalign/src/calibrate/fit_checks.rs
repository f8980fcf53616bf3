//! The rig kernel's checks of the fit applied to a calibration
//! ([`crate::rig::residuals`], [`crate::rig::image_noise`]; their module docs say what
//! they compute, their units and pitfalls): each adds its warnings to the report and
//! widens the intrinsics' and lens sigmas by its factor; the report's focal sigmas follow.

use super::{MotionCalibration, report};
use crate::rig::image_noise::{ImageNoiseCheck, MeasuredVariances, RESIDUAL_OVER_NOISE_WARN, noise_check_of};
use crate::rig::residuals::{residual_structure, widen_intrinsics};

/// Check a calibration's residuals ([`residual_structure`]), add its warnings to the
/// report and widen the intrinsics' and lens sigmas by its factor (`C' = D C D`, `D` the
/// factor on those parameters and 1 elsewhere); the focal sigmas of the report follow.
pub(super) fn check_and_widen(calibration: &mut MotionCalibration) {
    crate::timing::time(crate::timing::Stage::Covariance, || {
        let structure = residual_structure(
            &calibration.bundle.state,
            &calibration.observations,
            calibration.image_size,
            calibration.bundle.report.sigma_px,
        );
        let f = structure.sigma_widening;
        if f > 1.0 {
            widen_intrinsics(&mut calibration.bundle.covariance, f);
            calibration.report.focal_sigma_pct = report::focal_sigma_pct(&calibration.bundle);
        }
        calibration.report.warnings.extend(structure.warnings.iter().cloned());
        calibration.report.residual_structure = Some(structure);
    })
}

/// The statistics of the module docs for `calibration` with the measured noise
/// `measured` (a check without warning or widening yet).
pub fn image_noise_check(calibration: &MotionCalibration, measured: &MeasuredVariances) -> ImageNoiseCheck {
    noise_check_of(
        &calibration.bundle,
        &calibration.observations,
        &calibration.report.views,
        &calibration.point_tracks,
        measured,
    )
}

/// Check a calibration's residuals against the measured noise ([`image_noise_check`]):
/// when the check fires (module docs), warn and widen the intrinsics' and lens sigmas to
/// `sqrt(chi2 / dof)` times the adjustment's (what exceeds the residual structure's
/// widening); the report's focal sigmas follow.
pub fn check_against_images(calibration: &mut MotionCalibration, measured: &MeasuredVariances) {
    crate::timing::time(crate::timing::Stage::Covariance, || {
        let mut check = image_noise_check(calibration, measured);
        if let (Some(ratio), Some(limit), Some(residual), Some(noise)) =
            (check.ratio, check.ratio_limit, check.residual_sigma_px, check.expected_residual_sigma_px)
            && ratio > limit
            && ratio.sqrt() > RESIDUAL_OVER_NOISE_WARN
        {
            let already = calibration.report.residual_structure.as_ref().map_or(1.0, |s| s.sigma_widening);
            let extra = (ratio.sqrt() / already).max(1.0);
            if extra > 1.0 {
                widen_intrinsics(&mut calibration.bundle.covariance, extra);
                calibration.report.focal_sigma_pct = report::focal_sigma_pct(&calibration.bundle);
            }
            check.sigma_widening = extra;
            calibration.report.warnings.push(format!(
            "the reprojection residuals are {:.1} x the localisation noise measured from the images ({residual:.3} px against {noise:.3} px; chi-square {:.0} for {:.0} degrees of freedom, 99.9 % limit {:.0}): the model does not fit these images (lens model? rolling shutter? moving scene?); the intrinsics' and lens sigmas are widened {:.1} times",
            ratio.sqrt(),
            check.chi2.unwrap_or(f64::NAN),
            check.dof.unwrap_or(f64::NAN),
            limit * check.dof.unwrap_or(f64::NAN),
            ratio.sqrt().max(already)
        ));
        }
        calibration.report.image_noise = Some(check);
    })
}
