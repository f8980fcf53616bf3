//! Experiment: turning centres of the steering stage against the simulator's truth.
//! `cargo run --release -p headalign --example robot_turns -- SEED [DRIVE_M [S1,S2,...]]`
use headalign::estimate::EstimationOptions;
use headalign::procedure::{VergeTiltOptions, VergeTiltRun};
use headalign::robot::{SteeringOptions, zero_steering};
use headalign_sim::{Scenario, SimulatedRobot};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let seed: u64 = args.get(1).map_or(Ok(1), |s| s.parse())?;
    let mut o = SteeringOptions::default();
    if let Some(d) = args.get(2) {
        o.drive_m = d.parse()?;
    }
    if let Some(v) = args.get(3) {
        o.settings_deg = v.split(',').map(|x| x.parse()).collect::<Result<_, _>>()?;
    }
    let noise: f64 = std::env::var("NOISE").ok().and_then(|v| v.parse().ok()).unwrap_or(1.0);
    let outliers: f64 = std::env::var("OUTLIERS").ok().and_then(|v| v.parse().ok()).unwrap_or(0.1);
    let s = Scenario {
        seed,
        noise_px: noise,
        outlier_fraction: outliers,
        near_panels: Scenario::ROBOT_NEAR_PANELS,
        ..Scenario::default()
    };
    let mut robot = SimulatedRobot::new(s)?;
    let opts = VergeTiltOptions {
        estimation: EstimationOptions { seed, ..EstimationOptions::default() },
        ..VergeTiltOptions::default()
    };
    let vt = VergeTiltRun::default().run(robot.head_mut(), &opts)?;
    let enc = robot.head().encoders();
    let (robot_from_left, _) = robot.head().world_from_cameras(&enc);
    let st = zero_steering(&mut robot, &vt.calibration, &vt.verge_axes, Some(&vt.axis_perturbations()), &o)?;
    let z = robot.truth().steer_zero_deg;
    for t in &st.turns {
        let c_true = robot.truth().turning_centre(t.steer_encoder_deg - z).unwrap_or_default();
        // The estimate is in baselines (0.25 m), left camera frame.
        let c_est = robot_from_left * nalgebra::Point3::from(nalgebra::Vector3::from(t.centre) * 0.25);
        println!(
            "setting {:+.1}: true turn {:+.2} turn {:+.2} deg, inliers {}, centre est x {:+.3} z {:+.3}, true x {:+.3} z {:+.3}",
            t.steer_encoder_deg,
            (o.drive_m * (t.steer_encoder_deg - z).to_radians().tan() / robot.truth().wheelbase_m)
                .to_degrees(),
            t.turn_deg,
            t.inliers,
            c_est.x,
            c_est.z,
            c_true.x,
            c_true.z
        );
    }
    println!("zero {:+.3} truth {:+.3}; wheelbase {:.3}", st.steer_zero_deg, z, st.wheelbase_m);
    Ok(())
}
