//! The robot stages after the verge/tilt calibration, run in order over the platform
//! traits ([`run_robot_stages`]): the same driver in point mode (the simulated robot's
//! tracked points) and in image mode (the robot's renders through the image front end,
//! [`crate::tracking::TrackingHead`] in [`crate::tracking::TrackingMode::Previous`]:
//! [`crate::image_mode::robot_stages`]).
//!
//! Stage names ([`STAGES`]): `verge-tilt` (run before, by the caller), `pan`
//! ([`super::align_pan`]), `steering` ([`super::zero_steering`]), `pan-fixate`
//! ([`super::pan_fixation::align_pan_by_fixation`]), `one-motion`
//! ([`super::one_motion::align_one_motion`]). A stage may repeat. A [`RobotPlan`] holds
//! the stages and their settings; image mode's tuned settings are [`RobotPlan::images`]
//! ([`IMAGE_STEER_DRIVE_M`], [`IMAGE_PLANARITY_CHI2_MAX`]). Each stage's failure is
//! [`AlignError::InStep`] naming the stage.

use serde::{Deserialize, Serialize};

use super::one_motion::{Horizon, OneMotionOptions, OneMotionOutcome, align_one_motion};
use super::pan_fixation::{PanFixationOptions, PanFixationOutcome, align_pan_by_fixation};
use super::{PanOptions, PanOutcome, RigCheck, SteeringOptions, SteeringOutcome, align_pan, zero_steering};
use crate::alignment::VergeAxes;
use crate::error::AlignError;
use crate::procedure::AxisPerturbations;
use crate::verge_tilt::RigCalibration;
use headalign_platform::{StereoHead, Vehicle};

/// Steering drive of image mode, metres (point mode: 0.3, the library default).
/// A 0.3 m drive with the wheel at 30 deg turns the robot by about 15 deg and brings the
/// near panels 30 % closer; the single-scale corners and binary descriptors of the front
/// end then link few tracks across it (51-84 of about 500 stereo pairs, seed 1) and the
/// turning centres suffer: steering error 1.1 deg on seeds 1 and 2 against 0.43 and
/// 0.07 deg with 0.2 m (turns of 5-12 deg, still well above the 2 deg minimum).
pub const IMAGE_STEER_DRIVE_M: f64 = 0.2;

/// Planarity limit of image mode (chi-square, 3 dof; point mode:
/// [`super::PLANARITY_CHI2_MAX`], 25.9). On images a planar drive's chi-square
/// is inflated well beyond its 3-dof distribution (mean 3): seed 4 with `--pan-zero-max
/// 60` failed at 29.6 on a planar drive. With the track-clustered calibration covariance
/// ([`crate::image_mode::tracked_estimation`]) that drive gives 17.2, but the largest value
/// per run over seeds 1-20 (default stages) is still 1.8-16.2 (Gaussian covariance:
/// 1.8-14.6): the inflation is in the drive's own measurement, not the calibration's
/// sigmas, so the limit stays four times the point-mode one (the 1e-5 false-alarm
/// design; a 0.3 deg pitch still gives thousands).
pub const IMAGE_PLANARITY_CHI2_MAX: f64 = 4.0 * super::PLANARITY_CHI2_MAX;

/// Every stage name a plan may hold.
pub const STAGES: [&str; 5] = ["verge-tilt", "pan", "steering", "pan-fixate", "one-motion"];

/// The stages to run and their settings (recorded in an image session's `session.json`
/// as `stages`, so that a replay runs the same).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RobotPlan {
    /// Stage names in order (`verge-tilt` entries are skipped here).
    pub stages: Vec<String>,
    /// Forward drive of the pan, pan-fixate and one-motion stages, metres.
    pub drive_m: f64,
    /// One-motion: level with the drive direction instead of the calibrated pan axis.
    pub horizon_from_drive: bool,
    /// Drive per steering setting, metres (`None`: [`SteeringOptions::default`]).
    pub steer_drive_m: Option<f64>,
    /// Steering settings relative to the start reading, degrees (`None`: the default).
    pub steer_settings_deg: Option<Vec<f64>>,
    /// Stereo baseline, metres (to express the wheelbase in metres).
    pub baseline_m: f64,
    /// Planarity limit of the pan and steering drives (`None`: the library default;
    /// image mode: [`IMAGE_PLANARITY_CHI2_MAX`]).
    #[serde(default)]
    pub planarity_chi2_max: Option<f64>,
}

impl RobotPlan {
    /// True when a stage after the verge/tilt calibration drives the robot.
    pub fn drives(&self) -> bool {
        self.stages.iter().any(|s| s != "verge-tilt")
    }

    /// An error naming the first stage that is not one of [`STAGES`].
    pub fn validate(&self) -> Result<(), AlignError> {
        match self.stages.iter().find(|s| !STAGES.contains(&s.as_str())) {
            Some(st) => Err(AlignError::InvalidOption(format!(
                "unknown stage '{st}' (expected {})",
                STAGES.join(", ")
            ))),
            None => Ok(()),
        }
    }

    /// The plan of an image-mode run: the steering drive defaults to
    /// [`IMAGE_STEER_DRIVE_M`] and the planarity limit is [`IMAGE_PLANARITY_CHI2_MAX`].
    pub fn images(
        stages: Vec<String>,
        drive_m: f64,
        steer_drive_m: Option<f64>,
        steer_settings_deg: Option<Vec<f64>>,
        baseline_m: f64,
    ) -> Self {
        Self {
            stages,
            drive_m,
            horizon_from_drive: false,
            steer_drive_m: Some(steer_drive_m.unwrap_or(IMAGE_STEER_DRIVE_M)),
            steer_settings_deg,
            baseline_m,
            planarity_chi2_max: Some(IMAGE_PLANARITY_CHI2_MAX),
        }
    }
}

/// What the robot stages found.
#[derive(Debug, Clone, Default, Serialize)]
pub struct RobotOutcomes {
    /// Every `pan` stage.
    pub pan: Vec<PanOutcome>,
    /// Every `pan-fixate` stage.
    pub pan_fixate: Vec<PanFixationOutcome>,
    /// Every `one-motion` stage.
    pub one_motion: Vec<OneMotionOutcome>,
    /// The last `steering` stage.
    pub steering: Option<SteeringOutcome>,
}

impl RobotOutcomes {
    /// True when some stage moved the pan joint.
    pub fn panned(&self) -> bool {
        !self.pan.is_empty() || !self.pan_fixate.is_empty() || !self.one_motion.is_empty()
    }
}

/// The warning when a robot stage had to correct the stereo rig predicted at its
/// readings ([`RigCheck`]): the run goes on, but the calibration or the vergence axes do
/// not hold there.
fn rig_correction_warning(what: &str, check: &RigCheck) -> Option<String> {
    (check.correction_deg > 0.0).then(|| format!(
        "{what}: the stereo rig predicted at its readings misfit the captures (median {:.2} px, at most {:.2} px expected); its relative pose was re-fitted to them ({:.3} deg, median misfit now {:.2} px). The vergence axes or the calibration do not hold at these readings: consider running the verge/tilt stage again",
        check.misfit_px, check.bound_px, check.correction_deg, check.used_misfit_px
    ))
}

/// Callbacks of [`run_robot_stages`]: `stage(robot, name)` before each stage (a recording
/// head names the stage's captures with it), `warn(text)` for each warning as it arises.
pub struct StageHooks<'a, R> {
    /// Called before each stage with its name.
    pub stage: &'a mut dyn FnMut(&mut R, &str),
    /// Called with each warning (a rig corrected, a steering drive left out).
    pub warn: &'a mut dyn FnMut(&str),
}

/// Run the plan's robot stages in order on `robot`, with the verge/tilt stage's
/// calibration and vergence axes (`axes`: their perturbations, for the propagated
/// sigmas).
pub fn run_robot_stages<R: StereoHead + Vehicle>(
    robot: &mut R,
    plan: &RobotPlan,
    calib: &RigCalibration,
    verge: &VergeAxes,
    axes: Option<&AxisPerturbations>,
    hooks: StageHooks<'_, R>,
) -> Result<RobotOutcomes, AlignError> {
    let mut out = RobotOutcomes::default();
    let warn = hooks.warn;
    let warn_rig = |warn: &mut dyn FnMut(&str), what: &str, check: &RigCheck| {
        if let Some(w) = rig_correction_warning(what, check) {
            warn(&w);
        }
    };
    for st in &plan.stages {
        if st != "verge-tilt" {
            (hooks.stage)(robot, st);
        }
        match st.as_str() {
            "pan" => {
                let mut o = PanOptions { drive_m: plan.drive_m, ..PanOptions::default() };
                if let Some(c) = plan.planarity_chi2_max {
                    o.planarity_chi2_max = c;
                }
                let pan = align_pan(robot, calib, verge, axes, &o).map_err(|e| e.in_step("pan stage"))?;
                pan.steps.iter().for_each(|s| warn_rig(warn, "pan drive", &s.rig_check));
                out.pan.push(pan);
            }
            "one-motion" => {
                let horizon = if plan.horizon_from_drive { Horizon::Drive } else { Horizon::PanAxis };
                let o = OneMotionOptions { drive_m: plan.drive_m, horizon, ..OneMotionOptions::default() };
                let one =
                    align_one_motion(robot, calib, verge, &o).map_err(|e| e.in_step("one-motion stage"))?;
                one.steps.iter().for_each(|s| warn_rig(warn, "one-motion drive", &s.rig_check));
                out.one_motion.push(one);
            }
            "pan-fixate" => {
                let o = PanFixationOptions { drive_m: plan.drive_m, ..PanFixationOptions::default() };
                let p = align_pan_by_fixation(robot, &o).map_err(|e| e.in_step("pan fixation stage"))?;
                out.pan_fixate.push(p);
            }
            "steering" => {
                let st = steering_stage(robot, plan, calib, verge, axes)?;
                warn_rig(warn, "steering stage", &st.rig_check);
                for &k in &st.dropped_turns {
                    if let Some(t) = st.turns.get(k) {
                        warn(&format!(
                            "steering drive at {:+.1} deg failed the planarity test (chi-square {:.1}) while the others passed; it was left out",
                            t.steer_encoder_deg, t.planarity_chi2
                        ));
                    }
                }
                out.steering = Some(st);
            }
            _ => {}
        }
    }
    Ok(out)
}

/// The `steering` stage with the plan's settings.
fn steering_stage<R: StereoHead + Vehicle>(
    robot: &mut R,
    plan: &RobotPlan,
    calib: &RigCalibration,
    verge: &VergeAxes,
    axes: Option<&AxisPerturbations>,
) -> Result<SteeringOutcome, AlignError> {
    let mut o = SteeringOptions { baseline_m: plan.baseline_m, ..SteeringOptions::default() };
    if let Some(d) = plan.steer_drive_m {
        o.drive_m = d;
    }
    if let Some(v) = &plan.steer_settings_deg {
        o.settings_deg = v.clone();
    }
    if let Some(c) = plan.planarity_chi2_max {
        o.planarity_chi2_max = c;
    }
    zero_steering(robot, calib, verge, axes, &o).map_err(|e| e.in_step("steering stage"))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A plan of known stages validates; an unknown name is an error naming it. The image
    /// plan carries image mode's steering drive and planarity limit unless given.
    #[test]
    fn plans_validate_and_image_plans_carry_the_image_limits() {
        let plan = RobotPlan::images(vec!["verge-tilt".into(), "pan".into()], 0.1, None, None, 0.12);
        assert!(plan.validate().is_ok() && plan.drives());
        assert_eq!(plan.steer_drive_m, Some(IMAGE_STEER_DRIVE_M));
        assert_eq!(plan.planarity_chi2_max, Some(IMAGE_PLANARITY_CHI2_MAX));
        let bad = RobotPlan { stages: vec!["verge-tilt".into(), "spin".into()], ..plan };
        let e = bad.validate().err().map(|e| e.to_string()).unwrap_or_default();
        assert!(e.contains("unknown stage 'spin'"), "{e}");
        let still = RobotPlan { stages: vec!["verge-tilt".into()], ..bad };
        assert!(!still.drives());
    }
}
