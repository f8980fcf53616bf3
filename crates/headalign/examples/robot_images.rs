//! Experiment: how well the image front end links tracks across a robot drive
//! ([`TrackingMode::Previous`]), against the simulator's truth.
//! `cargo run --release -p headalign --example robot_images -- SEED [DRIVE_M [STEER_DEG [PAN_DEG]]]`
//!
//! Prints, for the captures before and after one drive, the tracks seen in all four
//! images and the error of each after-drive left pixel against the projection of the
//! point triangulated (true cameras) from the before-drive stereo pair.
use headalign::frontend::{FrontEndOptions, TrackingHead, TrackingMode};
use headalign::imaging::{VergingOptions, verge_to_common_view};
use headalign_geometry::camera::{ProjectiveCamera, dehomogenise3};
use headalign_geometry::triangulation::triangulate_linear;
use headalign_platform::{Joint, StereoCapture, StereoHead, Vehicle};
use headalign_sim::{Scenario, SimulatedRobot};
use std::collections::HashMap;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let seed: u64 = args.get(1).map_or(Ok(1), |s| s.parse())?;
    let drive: f64 = args.get(2).map_or(Ok(0.1), |s| s.parse())?;
    let steer: f64 = args.get(3).map_or(Ok(0.0), |s| s.parse())?;
    let pan: f64 = args.get(4).map_or(Ok(0.0), |s| s.parse())?;
    let s = Scenario { seed, near_panels: Scenario::ROBOT_NEAR_PANELS, ..Scenario::default() };
    let mut robot = SimulatedRobot::new(s)?;
    let verged = verge_to_common_view(&mut robot, &VergingOptions::default())?;
    let mut enc = verged.encoders.moved(Joint::Pan, pan);
    // ENC=pan,elevation,verge_left,verge_right: capture there instead (e.g. a demo's
    // aligned readings).
    if let Ok(v) = std::env::var("ENC") {
        let v: Vec<f64> = v.split(',').map(str::parse).collect::<Result<_, _>>()?;
        if let [p, e, l, r] = v[..] {
            enc = headalign_platform::Encoders { pan: p, elevation: e, verge_left: l, verge_right: r };
        }
    }
    robot.move_to(&enc)?;
    robot.steer_to(steer)?;
    let truth = robot.head().truth().clone();
    let cams = |r: &SimulatedRobot| {
        let (l, rr) = r.head().scene_from_cameras(&enc);
        (
            ProjectiveCamera::from_pose(&truth.left, &l.inverse()),
            ProjectiveCamera::from_pose(&truth.right, &rr.inverse()),
        )
    };
    let (pl0, pr0) = cams(&robot);
    let options = FrontEndOptions { mode: TrackingMode::Previous, ..FrontEndOptions::default() };
    let t0 = std::time::Instant::now();
    let (before, after) = {
        // The true stereo F as the prior (the demo uses the calibrated rig's).
        let t2 = truth.clone();
        let prior = move |e: &headalign_platform::Encoders| {
            let (l, r) = t2.world_from_cameras(e);
            let rl = r.inverse() * l;
            let ess = rl.translation.vector.cross_matrix() * rl.rotation.to_rotation_matrix().into_inner();
            Some(t2.right.inverse_matrix().transpose() * ess * t2.left.inverse_matrix())
        };
        let mut th = TrackingHead::new(&mut robot, options)?;
        if std::env::var("NOPRIOR").is_err() {
            th = th.with_stereo_prior(Box::new(prior));
        }
        let b = th.capture()?;
        th.drive(drive)?;
        let a = th.capture()?;
        println!("tracking: {:?}", th.tracking);
        (b, a)
    };
    println!("two captures {:.2} s", t0.elapsed().as_secs_f64());
    let (pl1, pr1) = cams(&robot);
    let map = |c: &StereoCapture| {
        let l: HashMap<u64, _> = c.left.iter().map(|o| (o.track, o.pixel)).collect();
        let r: HashMap<u64, _> = c.right.iter().map(|o| (o.track, o.pixel)).collect();
        (l, r)
    };
    let (bl, br) = map(&before);
    // Stereo pairs of the first capture against the true cameras: reprojection error of
    // the triangulated point.
    let mut st: Vec<f64> = Vec::new();
    for (id, xl) in &bl {
        let Some(xr) = br.get(id) else { continue };
        let Ok(x) = triangulate_linear(&pl0, &pr0, xl, xr) else { continue };
        if let (Some(ql), Some(qr)) = (pl0.project(&x), pr0.project(&x)) {
            st.push((ql - xl).norm().max((qr - xr).norm()));
        }
    }
    st.sort_by(f64::total_cmp);
    println!(
        "stereo pairs {}: reprojection median {:.2} px, 90 % {:.2} px",
        st.len(),
        st.get(st.len() / 2).copied().unwrap_or(f64::NAN),
        st.get(st.len() * 9 / 10).copied().unwrap_or(f64::NAN)
    );
    let (al, ar) = map(&after);
    let mut errs = Vec::new();
    let (mut along, mut across, mut mean) = (Vec::new(), Vec::new(), nalgebra::Vector2::zeros());
    for (id, xl) in &bl {
        let (Some(xr), Some(yl), Some(yr)) = (br.get(id), al.get(id), ar.get(id)) else { continue };
        let Ok(x) = triangulate_linear(&pl0, &pr0, xl, xr) else { continue };
        let Some(p) = dehomogenise3(&x) else { continue };
        let h = nalgebra::Vector4::new(p.x, p.y, p.z, 1.0);
        let (Some(ql), Some(qr)) = (pl1.project(&h), pr1.project(&h)) else { continue };
        let e = (ql - yl).norm().max((qr - yr).norm());
        errs.push((e, (yl - xl).norm(), p.coords.norm()));
        let flow = ql - xl;
        if flow.norm() > 3.0 {
            let d = yl - ql;
            let u = flow / flow.norm();
            along.push(d.dot(&u));
            across.push(d.x * -u.y + d.y * u.x);
            mean += d;
        }
    }
    errs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let stats = |v: &[f64]| {
        let m = v.iter().sum::<f64>() / v.len().max(1) as f64;
        let r = (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt();
        (m, r)
    };
    println!(
        "left residual after the drive (measured - true, tracks with flow > 3 px: {}): mean {:.3?}; along flow mean/RMS {:.3?}, across {:.3?}",
        along.len(),
        mean / along.len().max(1) as f64,
        stats(&along),
        stats(&across)
    );
    let n = errs.len();
    let bad = errs.iter().filter(|e| e.0 > 3.0).count();
    println!("four-image tracks {n}, error > 3 px: {bad}");
    for q in [0.5, 0.9, 0.95, 0.99] {
        if n > 0 {
            let e = errs[((n as f64 * q) as usize).min(n - 1)];
            println!("  quantile {q}: error {:.2} px (flow {:.1} px, range {:.2} m)", e.0, e.1, e.2);
        }
    }
    let near = errs.iter().filter(|e| e.2 < 2.0).count();
    let near_ok = errs.iter().filter(|e| e.2 < 2.0 && e.0 <= 3.0).count();
    println!("  points nearer than 2 m: {near} ({near_ok} good)");
    Ok(())
}
