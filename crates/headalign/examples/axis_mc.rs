//! Diagnostic: Monte-Carlo of the vergence axes' pose part at the robot's readings. For
//! each seed (robot scene, `NOISE` px, as `planarity_chi2`), the axis sources' captures
//! are re-drawn `DRAWS` times (exact pixels plus Gaussian noise of `NOISE` px, no
//! outliers), resected ([`measure_cameras`]) and turned into axes, the calibration held;
//! the spread of the stereo rig's rotation predicted at the verge/tilt stage's final
//! readings against the pose part of [`headalign::robot::predicted_rig`]'s covariance
//! (the [`AxisPerturbations`] pose modes at the bundle's noise estimate). Prints, per seed,
//! the trace ratio (Monte-Carlo / predicted, standard deviations) and the Monte-Carlo
//! mean offset from the estimate (a bias of the axes under noise).
//! `NOISE=3 DRAWS=200 cargo run --release -p headalign --example axis_mc -- FIRST LAST`
use headalign::alignment::{VergeAxes, measure_cameras, verge_axes_from_motion};
use headalign::procedure::{AxisMeasurement, AxisPerturbations, VergeTiltRun, axis_perturbations};
use headalign_sim::SimulatedRobot;

mod common;
use nalgebra::{Matrix3, Vector3};
use rand::{RngExt, SeedableRng};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let first: u64 = args.get(1).map_or(Ok(1), |s| s.parse())?;
    let last: u64 = args.get(2).map_or(Ok(first), |s| s.parse())?;
    let noise: f64 = std::env::var("NOISE").ok().and_then(|v| v.parse().ok()).unwrap_or(3.0);
    let draws: usize = std::env::var("DRAWS").ok().and_then(|v| v.parse().ok()).unwrap_or(200);
    for seed in first..=last {
        let s = common::robot_scenario(seed, noise);
        let mut robot = SimulatedRobot::new(s.clone())?;
        let opts = common::trial_options(&s, seed);
        let Ok(vt) = VergeTiltRun::default().run(robot.head_mut(), &opts) else { continue };
        let cal = &vt.calibration;
        let r0 = cal.reference_encoders;
        let enc = vt.final_encoders;
        let all = axis_perturbations(cal, &vt.verge_axes, &vt.axis_sources, &r0, Some(cal.report.sigma_px));
        let pose_only =
            AxisPerturbations { calibration: vec![None; all.calibration.len()], pose: all.pose.clone() };
        let (rig, cov) = headalign::robot::predicted_rig(cal, &vt.verge_axes, Some(&pose_only), &enc)?;
        let Some(cov) = cov else { continue };
        let pred: Matrix3<f64> = cov.fixed_view::<3, 3>(0, 0).into_owned();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let head = robot.head();
        let mut samples: Vec<Vector3<f64>> = Vec::new();
        for _ in 0..draws {
            let mut redraw = |src: &Option<AxisMeasurement>| -> Option<VergeAxes> {
                let Some(src) = src else { return Some(vt.verge_axes) };
                let mut c = head.exact_capture(&src.capture.encoders);
                for o in c.left.iter_mut().chain(c.right.iter_mut()) {
                    o.pixel.x += noise * rng.sample::<f64, _>(rand_distr::StandardNormal);
                    o.pixel.y += noise * rng.sample::<f64, _>(rand_distr::StandardNormal);
                }
                let m = measure_cameras(cal, &c, &src.measured.ref_from_left, &src.measured.ref_from_right)
                    .ok()?;
                verge_axes_from_motion(&cal.bundle.state, &r0, &c.encoders, &m).ok()
            };
            let (Some(l), Some(r)) = (redraw(&vt.axis_sources.left), redraw(&vt.axis_sources.right)) else {
                continue;
            };
            let axes = VergeAxes { left: l.left, right: r.right };
            let (p, _) = headalign::robot::predicted_rig(cal, &axes, None, &enc)?;
            samples.push((p.right_from_left * rig.right_from_left.inverse()).rotation.scaled_axis());
        }
        let n = samples.len() as f64;
        let mean: Vector3<f64> = samples.iter().sum::<Vector3<f64>>() / n;
        let c: Matrix3<f64> =
            samples.iter().map(|v| (v - mean) * (v - mean).transpose()).sum::<Matrix3<f64>>() / (n - 1.0);
        println!(
            "{seed} mc sd {:.4} deg predicted sd {:.4} deg ratio {:.3} mean offset {:.4} deg; verge moved {:.1}/{:.1} deg",
            c.trace().sqrt().to_degrees(),
            pred.trace().sqrt().to_degrees(),
            (c.trace() / pred.trace()).sqrt(),
            mean.norm().to_degrees(),
            enc.verge_left - r0.verge_left,
            enc.verge_right - r0.verge_right
        );
    }
    Ok(())
}
