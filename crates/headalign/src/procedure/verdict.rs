//! The verdict on a verge/tilt run: whether the check after the last move agrees with the
//! uncertainty the run reports ([`check_verdict`]), and whether a planned move is within
//! the range the procedure plans ([`check_move`]). A run that fails either says so and
//! names the failed check: never a confident wrong answer.
//!
//! **The check rule.** After the last move to the aligned readings the check view is
//! resected against the calibration's points ([`crate::alignment::measure_cameras`]; the
//! planar route: [`crate::facing_plane::check_alignment`]) and gives the three correctable errors
//! `m` (left vergence, right vergence, left elevation; degrees, `asin` of the optical axis
//! on the estimated elevation and pan axes). Were the run's model and sigmas right, each
//! would be zero up to the aligned reading's own error, the check's measurement noise and
//! the move's repeatability: the bound of each component is
//!
//! `|m| <= CHECK_SIGMAS * sqrt(sigma_aligned^2 + sigma_check^2 + sigma_move^2)`
//!
//! with `sigma_aligned` the reported 1-sigma of the aligned reading that removes it
//! (elevation for the left elevation error, each vergence for its own), `sigma_check`
//! the check's own 1-sigma (general route: the resected pose's covariance
//! ([`super::resection_pose_covariance`], the bundle's pixel noise) projected on the
//! component, `sigma^2 = g^T C_w g`, `g = e3 x R^T a`, `R` the camera's orientation, `a`
//! the axis; planar route: `rms_px / (f sqrt(n))` radians, the rotation of a camera about
//! its centre fitted to `n` tracks of residual `rms_px`), and `sigma_move` the move's
//! repeatability, taken as the readings' noise (the estimation's angle prior, default
//! [`crate::verge_tilt::ENCODER_SIGMA_DEG`]). The right camera's elevation error is not
//! in the rule: no joint removes it and its prediction has no sigma of its own.
//!
//! Why [`CHECK_SIGMAS`] = 5: `sigma_aligned` over-states the spread of `m` (the check
//! uses the same calibration, so part of the aligned reading's error cancels in it), and
//! image-mode sigmas are themselves short by up to 1.5 times (z-score RMS 1.3-1.5 of the
//! aligned readings, `bench/seeds.py 1 20 --images`). At 1.5 times, 5 reported sigmas are
//! 3.3 true ones: a two-sided Gaussian tail of 1e-3 per component, 3e-3 per run over the
//! three. A model that does not hold (a lens the pinhole cannot follow) leaves errors of
//! many sigmas that the corrective moves cannot remove (the independent head, seed 2:
//! 4.2 deg on a vergence of sigma 0.69 deg).
//!
//! **The move rule.** The aligned readings are the reference view's readings plus the
//! solved turns. The procedure calibrates from turns of at most `rotation_deg` (10 deg
//! with the automatic rotations) and the head starts verged on a common view: a vergence
//! turned onto a near view (0.3 m at a 0.25 m baseline: 23 deg) plus a mount's zero
//! offset of a few degrees. A turn of more than [`MAX_ALIGNING_MOVE_DEG`] (30 deg) on any
//! joint, or more than the plan's own largest turn if that is larger, is outside that
//! range: the estimate extrapolates the model far beyond the views
//! it was made from, and the check after the move would see little of the calibrated
//! scene. Such a move is refused before it is sent ([`AlignError::ImplausibleMove`]); a
//! head that truly starts that far from aligned is turned nearer by hand first.
//!
//! Units: degrees. Degrees of freedom: none estimated here.

use headalign_platform::{Encoders, Joint};
use serde::Serialize;

use crate::alignment::MeasuredErrors;
use crate::error::AlignError;

/// Reported sigmas a check component may lie from zero (module docs: why 5).
pub const CHECK_SIGMAS: f64 = 5.0;

/// Largest turn of any joint from the reference view's reading to the aligned readings,
/// degrees (module docs: the move rule).
pub const MAX_ALIGNING_MOVE_DEG: f64 = 30.0;

/// One component of the check against its bound.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct CheckComponent {
    /// `verge_err_l_deg`, `verge_err_r_deg` or `elev_err_l_deg`.
    pub name: String,
    /// The measured error, degrees.
    pub measured_deg: f64,
    /// `sqrt(sigma_aligned^2 + sigma_check^2 + sigma_move^2)`, degrees.
    pub sigma_deg: f64,
    /// [`CHECK_SIGMAS`] times `sigma_deg`, degrees.
    pub bound_deg: f64,
    /// `|measured_deg| <= bound_deg`.
    pub passed: bool,
}

/// The verdict of the check after the last move (module docs).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct CheckVerdict {
    /// `passed`, `failed`, or `unchecked` (no check view could be measured).
    pub status: String,
    /// The check view it judges (`check-N`).
    pub check: String,
    /// Each correctable component.
    pub components: Vec<CheckComponent>,
    /// Reported sigmas allowed ([`CHECK_SIGMAS`]).
    pub sigmas_allowed: f64,
    /// The estimate's residuals against the image noise, when judged
    /// ([`CheckVerdict::judge_fit`]).
    pub model_fit: Option<FitJudgement>,
}

/// The model-fit part of a verdict ([`crate::verge_tilt::model_fit`]).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct FitJudgement {
    /// The residuals' noise over the image noise.
    pub residual_over_noise: f64,
    /// The largest accepted ([`crate::verge_tilt::MISFIT_FAIL_RATIO`]).
    pub bound: f64,
    /// The likely cause, when the check fired.
    pub cause: Option<String>,
    /// `false` when the misfit fails the run.
    pub passed: bool,
}

impl CheckVerdict {
    /// True when a component lies beyond its bound.
    pub fn failed(&self) -> bool {
        self.status == "failed"
    }

    /// A verdict without a check (the check view could not be measured).
    pub fn unchecked(check: &str) -> Self {
        Self {
            status: "unchecked".into(),
            check: check.into(),
            components: Vec::new(),
            sigmas_allowed: CHECK_SIGMAS,
            model_fit: None,
        }
    }

    /// Judge the estimate's fit to the images too (module docs of
    /// [`crate::verge_tilt::model_fit`]): a misfit beyond its bound fails the verdict.
    pub fn judge_fit(&mut self, fit: &crate::verge_tilt::ModelFit) {
        let Some(ratio) = fit.residual_over_noise else { return };
        let passed = !fit.failed;
        self.model_fit = Some(FitJudgement {
            residual_over_noise: ratio,
            bound: crate::verge_tilt::MISFIT_FAIL_RATIO,
            cause: fit.cause.clone(),
            passed,
        });
        if !passed {
            self.status = "failed".into();
        }
    }

    /// One line naming the failed components, their measured errors and bounds; `None` when
    /// it passed.
    pub fn failure_line(&self) -> Option<String> {
        if !self.failed() {
            return None;
        }
        if let Some(fit) = self.model_fit.as_ref().filter(|f| !f.passed) {
            return Some(format!(
                "the model does not fit the images (residuals {:.1} x the image noise, above {}): {}",
                fit.residual_over_noise,
                fit.bound,
                fit.cause.as_deref().unwrap_or("unknown cause"),
            ));
        }
        let parts: Vec<String> = self
            .components
            .iter()
            .filter(|c| !c.passed)
            .map(|c| format!("{} {:+.2} deg (bound {:.2})", c.name, c.measured_deg, c.bound_deg))
            .collect();
        Some(format!(
            "the check after the move ({}) measures {} beyond {} reported sigmas: the model does not hold for this head (lens model? try --lens auto)",
            self.check,
            parts.join(", "),
            self.sigmas_allowed
        ))
    }
}

/// The verdict on `measured` (the last check, view `check`) with the aligned readings'
/// sigmas `aligned` (elevation, left and right vergence), the check's own sigmas `check_sigma`
/// (per component, degrees; `None`: zero) and the move's repeatability `move_sigma_deg`
/// (module docs).
pub fn check_verdict(
    check: &str,
    measured: &MeasuredErrors,
    aligned: &super::AlignmentSigmas,
    check_sigma: Option<&MeasuredErrors>,
    move_sigma_deg: f64,
) -> CheckVerdict {
    let zero = MeasuredErrors {
        verge_err_l_deg: 0.0,
        verge_err_r_deg: 0.0,
        elev_err_l_deg: 0.0,
        elev_err_r_deg: 0.0,
    };
    let cs = check_sigma.unwrap_or(&zero);
    let components: Vec<CheckComponent> = [
        ("verge_err_l_deg", measured.verge_err_l_deg, aligned.verge_left_deg, cs.verge_err_l_deg),
        ("verge_err_r_deg", measured.verge_err_r_deg, aligned.verge_right_deg, cs.verge_err_r_deg),
        ("elev_err_l_deg", measured.elev_err_l_deg, aligned.elevation_deg, cs.elev_err_l_deg),
    ]
    .into_iter()
    .map(|(name, m, sa, sc)| {
        let sigma = (sa * sa + sc * sc + move_sigma_deg * move_sigma_deg).sqrt();
        let bound = CHECK_SIGMAS * sigma;
        // A non-finite measurement or sigma is no evidence of success.
        let passed = m.is_finite() && bound.is_finite() && m.abs() <= bound;
        CheckComponent { name: name.into(), measured_deg: m, sigma_deg: sigma, bound_deg: bound, passed }
    })
    .collect();
    let status = if components.iter().all(|c| c.passed) { "passed" } else { "failed" };
    CheckVerdict {
        status: status.into(),
        check: check.into(),
        components,
        sigmas_allowed: CHECK_SIGMAS,
        model_fit: None,
    }
}

/// The check's own 1-sigma per component (module docs: `sigma_check`, general route):
/// each resected pose's rotation covariance ([`super::resection_pose_covariance`] with
/// the bundle's pixel noise) projected on the component's axis, degrees; `None` when a
/// pose's covariance cannot be formed.
pub fn check_sigmas(
    calib: &crate::verge_tilt::RigCalibration,
    capture: &headalign_platform::StereoCapture,
    measured: &crate::alignment::MeasuredCameras,
    d_pan: f64,
) -> Option<MeasuredErrors> {
    use nalgebra::{Matrix3, Vector3};
    let state = &calib.bundle.state;
    let (pan, elev) = crate::verge_tilt::axes_of(state)?;
    let a_p = pan.direction.into_inner();
    let a_e =
        headalign_geometry::so3::rotation_about_line(&pan, d_pan).rotation * elev.direction.into_inner();
    let points: std::collections::HashMap<u64, nalgebra::Point3<f64>> = calib.points().into_iter().collect();
    let noise = Some(calib.report.sigma_px);
    let side = |k, obs: &[headalign_platform::TrackObservation], pose: &nalgebra::Isometry3<f64>| {
        let cov = super::resection_pose_covariance(k, &points, obs, pose, noise)?;
        let cw: Matrix3<f64> = cov.fixed_view::<3, 3>(0, 0).into_owned();
        let z = pose.rotation * Vector3::z();
        let sigma = |a: &Vector3<f64>| {
            // d asin(z . a) = (a . R (w x e3)) / cos = w . (e3 x R^T a) / cos.
            let g = Vector3::z().cross(&(pose.rotation.inverse() * a));
            let cos = (1.0 - z.dot(a).powi(2)).max(1e-12).sqrt();
            ((g.transpose() * cw * g)[(0, 0)].max(0.0)).sqrt() / cos
        };
        Some((sigma(&a_e).to_degrees(), sigma(&a_p).to_degrees()))
    };
    let (vl, el) = side(&state.left, &capture.left, &measured.ref_from_left)?;
    let (vr, er) = side(&state.right, &capture.right, &measured.ref_from_right)?;
    Some(MeasuredErrors { verge_err_l_deg: vl, verge_err_r_deg: vr, elev_err_l_deg: el, elev_err_r_deg: er })
}

/// Refuse a move to `target` whose turn of any joint from `reference` exceeds
/// [`MAX_ALIGNING_MOVE_DEG`], or the plan's own largest turn `planned_deg` if larger
/// (module docs: the move rule), before it is sent.
pub fn check_move(reference: &Encoders, target: &Encoders, planned_deg: f64) -> Result<(), AlignError> {
    let max_deg = MAX_ALIGNING_MOVE_DEG.max(planned_deg.abs());
    for joint in [Joint::Elevation, Joint::VergeLeft, Joint::VergeRight, Joint::Pan] {
        let turn = target.get(joint) - reference.get(joint);
        if !(turn.is_finite() && turn.abs() <= max_deg) {
            return Err(AlignError::ImplausibleMove {
                joint: joint_name(joint).into(),
                target_deg: target.get(joint),
                turn_deg: turn,
                max_deg,
            });
        }
    }
    Ok(())
}

fn joint_name(joint: Joint) -> &'static str {
    match joint {
        Joint::Pan => "pan",
        Joint::Elevation => "elevation",
        Joint::VergeLeft => "left vergence",
        Joint::VergeRight => "right vergence",
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::procedure::AlignmentSigmas;

    fn errors(l: f64, r: f64, e: f64) -> MeasuredErrors {
        MeasuredErrors { verge_err_l_deg: l, verge_err_r_deg: r, elev_err_l_deg: e, elev_err_r_deg: 9.0 }
    }

    const SIGMAS: AlignmentSigmas =
        AlignmentSigmas { elevation_deg: 0.03, verge_left_deg: 0.04, verge_right_deg: 0.05 };

    /// Errors within the bound pass, one beyond it fails and is named; the right camera's
    /// elevation (9 deg here) is not judged. The bound is 5 sqrt(0.05^2 + 0.02^2 + 0.01^2).
    #[test]
    fn the_rule_bounds_each_correctable_component() {
        let check = errors(0.0, 0.0, 0.0);
        let cs = errors(0.02, 0.02, 0.02);
        let ok = check_verdict("check-1", &errors(0.1, -0.2, 0.1), &SIGMAS, Some(&cs), 0.01);
        assert_eq!(ok.status, "passed", "{ok:?}");
        assert!(ok.failure_line().is_none());
        let bound = 5.0 * (0.05f64.powi(2) + 0.02f64.powi(2) + 0.01f64.powi(2)).sqrt();
        assert!((ok.components[1].bound_deg - bound).abs() < 1e-12);
        let bad = check_verdict("check-3", &errors(0.1, bound + 0.01, 0.1), &SIGMAS, Some(&cs), 0.01);
        assert!(bad.failed());
        let line = bad.failure_line().unwrap_or_default();
        assert!(
            line.contains("check-3") && line.contains("verge_err_r_deg") && !line.contains("verge_err_l_deg"),
            "{line}"
        );
        assert!(line.len() <= 300, "{line}");
        let nan = check_verdict("check-1", &errors(f64::NAN, 0.0, 0.0), &SIGMAS, Some(&check), 0.01);
        assert!(nan.failed());
    }

    /// A misfit beyond [`crate::verge_tilt::MISFIT_FAIL_RATIO`] fails a verdict whose check
    /// passed, and the line names the cause first; a fit within it leaves it passed.
    #[test]
    fn a_model_that_does_not_fit_fails_the_verdict() {
        use crate::rig::image_noise::ImageNoiseCheck;
        use crate::rig::residuals::ResidualStructure;
        let fit = |ratio: f64, failed: bool| crate::verge_tilt::ModelFit {
            residual_over_noise: Some(ratio),
            cause: failed.then(|| "radial pattern: try --lens auto".to_string()),
            failed,
            image_noise: ImageNoiseCheck::skipped("test"),
            residual_structure: ResidualStructure {
                sigma_px: 1.0,
                cameras: Vec::new(),
                sigma_widening: 1.0,
                warnings: Vec::new(),
            },
            warnings: Vec::new(),
        };
        let mut ok = check_verdict("check-1", &errors(0.0, 0.0, 0.0), &SIGMAS, None, 0.01);
        ok.judge_fit(&fit(1.1, false));
        assert_eq!(ok.status, "passed");
        let mut bad = ok.clone();
        bad.judge_fit(&fit(4.1, true));
        let line = bad.failure_line().unwrap_or_default();
        assert!(
            bad.failed() && line.starts_with("the model does not fit the images (residuals 4.1 x"),
            "{line}"
        );
        assert!(line.ends_with("radial pattern: try --lens auto"), "{line}");
        assert!(line.len() <= 300, "{line}");
    }

    /// A turn beyond the bound on any joint is refused and named; one within passes.
    #[test]
    fn far_moves_are_refused() {
        let reference = Encoders { pan: 0.0, elevation: -5.0, verge_left: 2.0, verge_right: -2.0 };
        let near = Encoders { elevation: 20.0, verge_left: -25.0, ..reference };
        assert!(check_move(&reference, &near, 10.0).is_ok());
        let far = Encoders { elevation: -61.0, ..reference };
        let e = check_move(&reference, &far, 10.0).err().map(|e| e.to_string()).unwrap_or_default();
        assert!(e.contains("elevation") && e.contains("-61.0") && e.contains("30"), "{e}");
        assert!(e.len() <= 300, "{e}");
        // A plan that itself turns 60 deg accepts a turn of 56.
        assert!(check_move(&reference, &far, 60.0).is_ok());
        let nan = Encoders { verge_right: f64::NAN, ..reference };
        assert!(check_move(&reference, &nan, 10.0).is_err());
    }
}
