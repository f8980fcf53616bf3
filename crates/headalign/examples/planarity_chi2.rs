//! Diagnostic: the planarity chi-square of every drive of the robot stages (pan,
//! steering, pan), as `headalign experiment fig5-pan-tilt` runs them, with the planarity
//! test switched off, so its distribution can be compared with a chi-square of 3 dof
//! (mean 3; 99.999 % quantile 25.9). One line per drive: seed, stage, chi-square; then
//! the trial's pan and steering-zero errors over their sigmas. `LIMIT=25.902` restores
//! the default test (a failing stage then ends the seed); `DETAIL=1` prints, on stderr,
//! the calibrated rig's error at the reference and at the robot's readings (vergence
//! axes; before the first pan stage and after it) and each steering drive's true camera
//! displacement (baselines).
//! `NOISE=3 cargo run --release -p headalign --example planarity_chi2 -- FIRST LAST`
//!
//! `AXES=held`: the vergence axes taken as exact (the robot stages before their
//! uncertainty was propagated); default: their uncertainty
//! ([`headalign::procedure::VergeTiltOutcome::axis_perturbations`]), at the bundle's
//! noise (`AXIS_NOISE=px` or `=resection` to change it). `RIGCHI=1` prints
//! the chi-square (3 dof) of the rig's rotation error at the first steering drive's
//! readings (and at the reference) against its propagated covariance. `EXACT_CAL=1`
//! calibrates a noise-free twin of the head: the drives' own covariance alone.
//! `ENCNOISE=deg` reads the encoders with Gaussian noise (default 0: exact).
//!
//! Measured (3 px, seeds 1-120, 960 drives, one run each): mean chi-square, first pan
//! stage / steering / second pan stage, 3.29 / 3.38 / 3.36 with the axes held (above the
//! 95 % quantile 8.8 / 7.5 / 7.5 % of drives), 3.27 / 3.24 / 3.53 with their uncertainty
//! (8.8 / 5.6 / 9.6 %), against 3 (standard error 0.16 / 0.11 / 0.16); at 1 px (seeds
//! 1-100) 2.91 / 2.37 / 2.88 held, 2.88 / 2.32 / 2.87 propagated. `RIGCHI=1`, seeds
//! 1-30: the rig at the readings 9.7 held, 3.5 propagated (at the reference 2.9; the
//! least-squares pose covariance instead of the bootstrap gave 4.1). `EXACT_CAL=1`: 3.2 / 3.5 / 3.0 at 1 px (seeds 1-40), 3.9 / 4.9 / 4.3 at 3 px
//! (seeds 1-60): the remaining excess at 3 px is the drive motions' own covariance. Seed
//! 170's first steering drive (far points only, rig at the readings 0.47 deg off): 42.7
//! held, 30.0 propagated, but from two runs whose pan stages left the head in different
//! places (`AXES=held` changes the pan stage too): on the same drives it is 42.8
//! propagated (`robot::tests::scan_steering_chi2`). These figures predate
//! `EstimationOptions::image_border` as the default.
use headalign::procedure::{VergeTiltRun, axis_perturbations};
use headalign::robot::{PanOptions, SteeringOptions, align_pan, zero_steering};
use headalign_sim::{Scenario, SimulatedRobot};

mod common;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let first: u64 = args.get(1).map_or(Ok(1), |s| s.parse())?;
    let last: u64 = args.get(2).map_or(Ok(first), |s| s.parse())?;
    let noise: f64 = std::env::var("NOISE").ok().and_then(|v| v.parse().ok()).unwrap_or(3.0);
    let limit: f64 = std::env::var("LIMIT").ok().and_then(|v| v.parse().ok()).unwrap_or(f64::INFINITY);
    for seed in first..=last {
        let encoder_noise_deg = std::env::var("ENCNOISE").ok().and_then(|v| v.parse().ok()).unwrap_or(0.0);
        let s = Scenario { encoder_noise_deg, ..common::robot_scenario(seed, noise) };
        let mut robot = SimulatedRobot::new(s.clone())?;
        let opts = common::trial_options(&s, seed);
        // EXACT_CAL=1: the calibration from a noise-free twin of the head (the robot then
        // starts at the twin's final readings): the drives' own covariance alone.
        let vt = if std::env::var("EXACT_CAL").is_ok() {
            let mut twin = SimulatedRobot::new(Scenario { noise_px: 0.0, ..s.clone() })?;
            let vt = VergeTiltRun::default().run(twin.head_mut(), &opts);
            if let Ok(v) = &vt {
                use headalign_platform::StereoHead;
                robot.head_mut().move_to(&v.final_encoders)?;
            }
            vt
        } else {
            VergeTiltRun::default().run(robot.head_mut(), &opts)
        };
        let vt = match vt {
            Ok(v) => v,
            Err(e) => {
                println!("{seed} verge-tilt-failed {e}");
                continue;
            }
        };
        if std::env::var("DETAIL").is_ok() {
            let st = &vt.calibration.bundle.state;
            let (wl, wr) = robot.head().world_from_cameras(&vt.calibration.reference_encoders);
            let t_rl = wr.inverse() * wl;
            let d = st.right_from_left.inverse() * t_rl;
            eprintln!(
                "  rig: fx {:.1}/{:.1} truth {:.1}/{:.1}; right_from_left err rot {:.3} deg, t dir err {:.3} deg",
                st.left.fx,
                st.right.fx,
                robot.head().truth().left.fx,
                robot.head().truth().right.fx,
                d.rotation.angle().to_degrees(),
                st.right_from_left.translation.vector.angle(&t_rl.translation.vector).to_degrees()
            );
        }
        // The stages scale their thresholds with the calibration's noise estimate.
        let pan = PanOptions { drive_m: s.drive_m, planarity_chi2_max: limit, ..PanOptions::default() };
        let st = SteeringOptions {
            baseline_m: s.baseline_m,
            planarity_chi2_max: limit,
            ..SteeringOptions::default()
        };
        let (cal, verge) = (&vt.calibration, &vt.verge_axes);
        // The vergence axes' uncertainty (default) or, with `AXES=held`, the axes taken as
        // exact (the robot stages before it was propagated).
        let held = std::env::var("AXES").is_ok_and(|v| v == "held");
        let perturbations = (!held).then(|| {
            // The axis views' pixel noise: the bundle's estimate (`AXIS_NOISE=px` sets it,
            // `AXIS_NOISE=resection` estimates it from the resections' truncated residuals).
            let px = match std::env::var("AXIS_NOISE").ok() {
                Some(v) if v == "resection" => None,
                Some(v) => v.parse().ok(),
                None => Some(cal.report.sigma_px),
            };
            if std::env::var("DETAIL").is_ok() {
                eprintln!("  bundle noise {:.3} px", cal.report.sigma_px);
            }
            axis_perturbations(cal, verge, &vt.axis_sources, &cal.reference_encoders, px)
        });
        let axes = perturbations.as_ref();
        if std::env::var("DETAIL").is_ok() {
            eprintln!("  before the pan stage: verge axes {:?}", vt.verge_axes);
            print_rig_error(&robot, &vt, s.baseline_m);
        }
        let p1 = match align_pan(&mut robot, cal, verge, axes, &pan) {
            Ok(p) => p,
            Err(e) => {
                println!("{seed} pan-failed {e}");
                continue;
            }
        };
        if std::env::var("DETAIL").is_ok() {
            eprintln!(
                "  verge axes {:?}\nDBG ref enc {:?}\nDBG now enc {:?}",
                vt.verge_axes,
                vt.calibration.reference_encoders,
                robot.head().encoders()
            );
        }
        if std::env::var("DETAIL").is_ok() {
            print_rig_error(&robot, &vt, s.baseline_m);
            let s0 = robot.steering_encoder_deg();
            let (robot_from_left, _) = robot.head().world_from_cameras(&robot.head().encoders());
            for set in &st.settings_deg {
                let sigma = s0 + set - robot.truth().steer_zero_deg;
                let m = robot.truth().motion(sigma, st.drive_m);
                let c = (robot_from_left.inverse() * m * robot_from_left) * nalgebra::Point3::origin();
                eprintln!("  true c {:?}", (c.coords / s.baseline_m).as_slice());
            }
        }
        for p in &p1.steps {
            println!("{seed} pan1 {:.3}", p.planarity_chi2);
        }
        if std::env::var("RIGCHI").is_ok() {
            // The rig predicted at the first steering drive's readings against the truth:
            // chi-square (3 dof) of its rotation error under the covariance with the
            // axes held and with the axes' uncertainty.
            let enc = robot.head().encoders();
            let (wl, wr) = robot.head().world_from_cameras(&enc);
            let truth = wr.inverse() * wl;
            let r0 = cal.reference_encoders;
            let (wl0, wr0) = robot.head().world_from_cameras(&r0);
            let truth0 = wr0.inverse() * wl0;
            for (name, a, at, t) in [
                ("ref", None, r0, truth0),
                ("held", None, enc, truth),
                ("axes", perturbations.as_ref(), enc, truth),
            ] {
                let (rig, cov) = headalign::robot::predicted_rig(cal, verge, a, &at)?;
                let d = (t * rig.right_from_left.inverse()).rotation.scaled_axis();
                let c = cov.map(|c| c.fixed_view::<3, 3>(0, 0).into_owned());
                let chi =
                    c.and_then(|c| c.try_inverse()).map_or(f64::NAN, |i| (d.transpose() * i * d)[(0, 0)]);
                let sd = c.map_or(f64::NAN, |c| c.trace().sqrt().to_degrees());
                println!("{seed} rigchi {name} {chi:.3} err {:.3} sd {sd:.3}", d.norm().to_degrees());
            }
        }
        let sz = match zero_steering(&mut robot, cal, verge, axes, &st) {
            Ok(p) => p,
            Err(e) => {
                println!("{seed} steer-failed {e}");
                continue;
            }
        };
        for t in &sz.turns {
            println!("{seed} steer {:.3}", t.planarity_chi2);
        }
        let steer_err = robot.steer_err_deg(robot.steering_encoder_deg());
        let p2 = match align_pan(&mut robot, cal, verge, axes, &pan) {
            Ok(p) => p,
            Err(e) => {
                println!("{seed} pan2-failed {e}");
                continue;
            }
        };
        for p in &p2.steps {
            println!("{seed} pan2 {:.3}", p.planarity_chi2);
        }
        let pan_err = robot.pan_err_deg(&robot.head().encoders());
        let ps = p2.steps.last().map_or(f64::NAN, |p| p.sigma_deg);
        println!("{seed} z pan {:.3} steer {:.3}", pan_err / ps, steer_err / sz.sigma_steer_zero_deg);
    }
    Ok(())
}

/// The stereo rig predicted at the robot's current readings (calibration and vergence
/// axes) against the truth, on stderr.
fn print_rig_error(robot: &SimulatedRobot, vt: &headalign::procedure::VergeTiltOutcome, baseline_m: f64) {
    let enc = robot.head().encoders();
    let r0 = vt.calibration.reference_encoders;
    let rot = |axis: &Option<headalign_geometry::so3::Line>, a: f64| {
        axis.map(|l| headalign_geometry::so3::rotation_about_line(&l, a.to_radians()))
            .unwrap_or_else(nalgebra::Isometry3::identity)
    };
    let rl = rot(&vt.verge_axes.left, enc.verge_left - r0.verge_left);
    let rr = rot(&vt.verge_axes.right, enc.verge_right - r0.verge_right);
    let pred = vt.calibration.bundle.state.right_from_left * rr.inverse() * rl;
    let (wl, wr) = robot.head().world_from_cameras(&enc);
    let truth = wr.inverse() * wl;
    let d = pred.inverse() * truth;
    eprintln!(
        "  rig at readings: rot err {:.3} deg ({:?}), t dir err {:.3} deg, |t| {:.3} vs {:.3}",
        d.rotation.angle().to_degrees(),
        d.rotation.scaled_axis().as_slice(),
        pred.translation.vector.angle(&truth.translation.vector).to_degrees(),
        pred.translation.vector.norm(),
        truth.translation.vector.norm() / baseline_m
    );
}
