//! One trial of the robot stages (paper section 4, Figure 5 right: pan alignment by a
//! forward drive) on the simulated robot, scored against the truth.
//!
//! A trial runs what `headalign demo` runs by default, in point mode: the verge/tilt
//! procedure (as in [`super::trial`], thresholds scaled with the noise), then the pan
//! stage, the steering stage and the pan stage again ([`align_pan`], [`zero_steering`];
//! the second pan drive runs with the wheel straight, where the pan estimate is exact
//! wherever the pan axis stands). The scenario sets the noise (pixels), the initial pan
//! error (`pan_zero_max_deg`: the pan zero is drawn in +-this, degrees), the drive
//! (`drive_m`, metres), the near panels (the paper's robot faced a scene about 1 m
//! away; [`Scenario::ROBOT_NEAR_PANELS`] unless the scenario has some) and the floor's
//! tilt against the pan axis (`pan_tilt_deg`, default 2 deg; the stages fit the floor's
//! normal, [`headalign::robot::floor`]).
//!
//! Recorded: the pan error after the last drive (degrees, signed: the true pan of the
//! head from the direction of travel at the final readings), the alignment errors of
//! both cameras after all stages (elevation left/right, degrees), and the reported
//! quantities [`ROBOT_QUANTITIES`]: the verge/tilt stage's (in the robot's scene), then
//! `pan.aligned`, the final pan reading, its truth (final reading minus the pan error)
//! and the sigma of the last drive's correction ([`headalign::robot::PanStep::sigma_deg`]:
//! the verge/tilt calibration's uncertainty propagated, plus the image noise; the
//! remaining error after the last correction is that correction's error), and
//! `steer.zero`, the steering zero with its sigma.
//!
//! No Cramer-Rao bound: the pan stage has no joint likelihood of both drives, steering
//! and calibration whose covariance could be evaluated at the truth, so the bound is NaN
//! and printed "-" rather than invented.

use std::time::Instant;

use anyhow::{Context, Result, anyhow};
use headalign::robot::{PanOptions, PanOutcome, SteeringOptions, align_pan, zero_steering};
use headalign_sim::{Scenario, SimulatedRobot};

use super::trial::{Quantity, SIGMA_QUANTITIES, TrialRecord, TrialSpec, record_from, verge_tilt_on};

/// The quantities a robot trial reports with a sigma, in record order: the verge/tilt
/// stage's ([`SIGMA_QUANTITIES`], in the robot's scene), then the final pan reading and
/// the steering zero (degrees).
pub const ROBOT_QUANTITIES: [&str; SIGMA_QUANTITIES.len() + 2] = {
    let mut q = ["steer.zero"; SIGMA_QUANTITIES.len() + 2];
    let mut i = 0;
    while i < SIGMA_QUANTITIES.len() {
        q[i] = SIGMA_QUANTITIES[i];
        i += 1;
    }
    q[PAN_INDEX] = "pan.aligned";
    q
};

/// Index of `pan.aligned` in [`ROBOT_QUANTITIES`] (`steer.zero` follows it).
pub const PAN_INDEX: usize = SIGMA_QUANTITIES.len();

/// Pan options for a scenario: its drive; the stage scales its pixel thresholds with the
/// calibration's noise estimate itself ([`PanOptions::scale_to_noise`]), where the
/// verge/tilt stage is given them scaled by the scenario's noise
/// ([`super::trial::estimation_options`]).
pub fn pan_options(scenario: &Scenario) -> PanOptions {
    PanOptions { drive_m: scenario.drive_m, ..PanOptions::default() }
}

/// Steering options for a scenario: its baseline (thresholds as [`pan_options`]).
fn steering_options(scenario: &Scenario) -> SteeringOptions {
    SteeringOptions { baseline_m: scenario.baseline_m, ..SteeringOptions::default() }
}

/// Sigma of the last drive's pan correction, degrees (NaN without a drive): the
/// calibration and image-noise sigma the stage reports ([`headalign::robot::PanStep::sigma_deg`]).
pub fn last_correction_sigma_deg(outcome: &PanOutcome) -> f64 {
    outcome.steps.last().map_or(f64::NAN, |s| s.sigma_deg)
}

/// Run one trial of the robot stages (module docs).
pub fn run_pan_trial(spec: &TrialSpec) -> Result<TrialRecord> {
    let t0 = Instant::now();
    let mut scenario = spec.scenario.clone();
    if scenario.near_panels == 0 {
        scenario.near_panels = Scenario::ROBOT_NEAR_PANELS;
    }
    let mut robot = SimulatedRobot::new(scenario.clone()).map_err(|e| anyhow!("simulator: {e}"))?;
    let vt = verge_tilt_on(robot.head_mut(), spec)?;
    let (cal, verge) = (&vt.calibration, &vt.verge_axes);
    let perturbations = vt.axis_perturbations();
    let axes = Some(&perturbations);
    let pan = pan_options(&scenario);
    align_pan(&mut robot, cal, verge, axes, &pan).context("pan stage")?;
    let steer = zero_steering(&mut robot, cal, verge, axes, &steering_options(&scenario))
        .context("steering stage")?;
    let steer_err = robot.steer_err_deg(robot.steering_encoder_deg());
    let last = align_pan(&mut robot, cal, verge, axes, &pan).context("pan stage, wheel straight")?;
    let enc = robot.head().encoders();
    let pan_err = robot.pan_err_deg(&enc);
    let mut rec = record_from(robot.head(), &vt, &spec.initial, None, t0.elapsed().as_secs_f64());
    rec.pan_err_deg = pan_err;
    rec.quantities.push(Quantity {
        est: enc.pan,
        truth: enc.pan - pan_err,
        sigma: last_correction_sigma_deg(&last),
        crb: f64::NAN,
    });
    rec.quantities.push(Quantity {
        est: steer.steer_zero_deg,
        truth: steer.steer_zero_deg - steer_err,
        sigma: steer.sigma_steer_zero_deg,
        crb: f64::NAN,
    });
    Ok(rec)
}

#[cfg(test)]
mod tests {
    use super::super::trial::RotationMode;
    use super::*;
    use headalign::verge_tilt::ENCODER_SIGMA_DEG;
    use headalign_platform::Encoders;

    fn spec(noise: f64) -> TrialSpec {
        TrialSpec {
            scenario: Scenario { seed: 2, noise_px: noise, ..Scenario::default() },
            initial: Encoders::default(),
            rotation: RotationMode::Fixed,
            depth_profile: headalign::verge_tilt::EstimationOptions::default().depth_profile,
            image_border: headalign::verge_tilt::EstimationOptions::default().image_border,
            lone_depth_gate: headalign::verge_tilt::EstimationOptions::default().lone_depth_gate,
            angle_prior: headalign_geometry::bundle::AnglePrior::default(),
            bootstrap: None,
        }
    }

    /// Noise-free: the pan error is at the verge/tilt solver's tolerance (1e-3 deg, as
    /// `robot::tests`), and the reported quantity's truth is consistent with the error.
    #[test]
    fn noise_free_pan_trial_is_exact() {
        let r = run_pan_trial(&spec(0.0)).unwrap();
        assert!(r.pan_err_deg.abs() < 1e-3, "{r:?}");
        assert!(r.elev_err_l_deg.abs() < 1e-3, "{r:?}");
        assert_eq!(r.quantities.len(), ROBOT_QUANTITIES.len());
        let q = r.quantities[PAN_INDEX];
        assert!((q.est - q.truth - r.pan_err_deg).abs() < 1e-12);
        // Noise-free: the truths are matched to rounding, and both robot sigmas are those
        // of the readings' noise the stages assume (`PanOptions::encoder_sigma_deg`, 0.01
        // deg, which the simulator's exact readings lack): the pan's is that read's noise
        // and the rig's prediction error from it, measured 0.0125 deg; the steering
        // zero's is the rig's part alone, 0.0070 deg.
        for q in &r.quantities[PAN_INDEX..] {
            assert!((q.est - q.truth).abs() < 1e-9 && q.sigma < 2.0 * ENCODER_SIGMA_DEG, "{q:?}");
        }
        assert!(q.crb.is_nan());
    }

    /// Regression, 3 px seed 170 (`experiment coverage` / `fig5-pan-tilt`), under the
    /// experiments' protocol (readings with 0.01 deg of noise): the trial completes with
    /// both robot quantities within 4 reported sigmas. It used to have one steering drive
    /// fail the planarity test and be left out (`SteeringOutcome::dropped_turns`); with
    /// the 200-sample drive registration (`robot::DRIVE_MIN_ITERATIONS`) all four pass
    /// (chi-square 4.0 / 5.1 / 6.1 / 2.0), so this seed no longer exercises that rule.
    /// With exact readings (the former set-up) its first drive was left out and the other
    /// three (24-57 tracks each) left the steering zero undetermined; since session 19
    /// (points re-triangulated by support) that trial completes, and the rule is tested
    /// with a lowered limit (`robot::tests::an_undetermined_steering_zero_is_named`).
    #[test]
    fn seed_170_robot_trial_is_within_its_sigmas() {
        let scenario = Scenario {
            seed: 170,
            noise_px: 3.0,
            encoder_noise_deg: ENCODER_SIGMA_DEG,
            ..Scenario::default()
        };
        let s = TrialSpec { scenario, ..spec(3.0) };
        let r = run_pan_trial(&s).unwrap();
        // Within 4 reported sigmas (both are about 1 deg here).
        for q in &r.quantities[PAN_INDEX..] {
            assert!((q.est - q.truth).abs() < 4.0 * q.sigma, "{q:?}");
        }
    }
}
