//! Shared by the diagnostic examples (`axis_diag`, `ratio_diag`, `verge_seeds`): one
//! verge/tilt trial as `headalign experiment` runs it (the scenario's fixed rotation, a
//! 3 deg vergence move, thresholds scaled by the noise via
//! [`EstimationOptions::scaled_for_noise`]) on a simulated head started at `initial`.
use headalign::estimate::EstimationOptions;
use headalign::procedure::{VergeTiltOptions, VergeTiltOutcome, VergeTiltRun};
use headalign_platform::{Encoders, StereoHead};
use headalign_sim::{Scenario, SimulatedHead};

/// The trial with estimation seed `estimation_seed`; `None` if the simulator or the
/// procedure fails.
pub fn verge_tilt_trial(
    s: &Scenario,
    initial: &Encoders,
    estimation_seed: u64,
) -> Option<(SimulatedHead, VergeTiltOutcome)> {
    let mut head = SimulatedHead::new(s.clone()).ok()?;
    head.move_to(initial).ok()?;
    let opts = VergeTiltOptions {
        rotation_deg: s.rotation_deg,
        verge_rotation_deg: 3.0,
        estimation: EstimationOptions::scaled_for_noise(s.noise_px, estimation_seed),
        ..VergeTiltOptions::default()
    };
    let out = VergeTiltRun::default().run(&mut head, &opts).ok()?;
    Some((head, out))
}
