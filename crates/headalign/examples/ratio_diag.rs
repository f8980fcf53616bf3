//! Diagnostic (not a test): for one seed, noise and initial head position, the verge/tilt
//! estimate's intrinsic errors, and the least-squares solution reached from the truth on
//! the same inlier observations (is the estimate a worse local minimum?), and from the
//! estimate with one part replaced by the truth (intrinsics, rig, motions, points: which
//! part decides the basin), with the rig's rotation and baseline direction against the
//! truth's (seed 39 at position 2: the rig decides; its baseline's x component was
//! reversed, see `estimate::reversed_rig_restart`).
//! Last, the depth-scale sweep (`docs/ratio-tail.md`): the least squares re-run from the
//! estimate held at depth scale `s_hat + k sigma_s` (k = -3..3) and then freed, with each
//! end's cost against the estimate's (chi-square units, prior included): does a start
//! along the badly determined direction reach the lower minimum the truth reaches?
//! `SWEEP_LOG=0.7,1.1,-0.7` sweeps those offsets of `s` instead (log units, not sigmas):
//! calibration seed 368 at 3 px, whose lower minimum lies 1.15 above, reached it from none.
//! `SCENE=paper` (or `robot`) runs that scene preset (`--scene` of `headalign experiment`);
//! `ENCNOISE=0` reads the encoders exactly (default 0.01 deg, as `headalign experiment`;
//! before the twenty-first session the default was exact readings, as in `docs/ratio-tail.md`).
//! `cargo run --release -p headalign --example ratio_diag -- SEED NOISE POSITION`
//! (POSITION 0, 1, 2 as in `experiment fig5-verge-tilt`).
use std::collections::HashMap;

use headalign::estimate::{ENCODER_SIGMA_DEG, EstimationOptions};
use headalign::procedure::VergeTiltOutcome;
use headalign_geometry::bundle::{
    BundleResult, RobustLoss, bundle_adjust, bundle_adjust_at_depth_scale, log_depth_scale,
};
use headalign_platform::Encoders;
use headalign_sim::{Scenario, SimulatedHead};

mod common;

fn run(s: &Scenario, initial: &Encoders) -> (SimulatedHead, VergeTiltOutcome) {
    common::verge_tilt_trial(s, initial, s.seed).expect("the simulator and the procedure run")
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let seed: u64 = a[1].parse().unwrap();
    let noise: f64 = a[2].parse().unwrap();
    let pos: usize = a[3].parse().unwrap();
    let positions = [
        Encoders::default(),
        Encoders { pan: 4.0, elevation: 4.0, verge_left: 2.0, verge_right: -2.0 },
        Encoders { pan: -4.0, elevation: -4.0, verge_left: -2.0, verge_right: 2.0 },
    ];
    let scene = std::env::var("SCENE").unwrap_or_else(|_| "default".into());
    // `ENCNOISE` (deg): the encoder readings' noise, default the experiments' (the noise the
    // estimate's angle prior assumes).
    let encoder_noise_deg =
        std::env::var("ENCNOISE").ok().and_then(|v| v.parse().ok()).unwrap_or(ENCODER_SIGMA_DEG);
    let sc = Scenario {
        seed,
        noise_px: noise,
        encoder_noise_deg,
        ..Scenario::preset(&scene).expect("a scene preset")
    };
    let (head, noisy) = run(&sc, &positions[pos]);
    // The noise-free run reads the encoders exactly, as the experiments' bound run does.
    let (_, clean) =
        run(&Scenario { noise_px: 1e-300, encoder_noise_deg: 0.0, ..sc.clone() }, &positions[pos]);
    let t = head.truth().clone();
    let c = &noisy.calibration;
    let st = &c.bundle.state;
    let show = |name: &str, s: &headalign_geometry::bundle::RigState, rms: f64, obs: usize| {
        println!(
            "{name:>8}: L fx {:+7.2} fy {:+7.2} cx {:+7.2} cy {:+7.2} | R fx {:+7.2} fy {:+7.2} cx {:+7.2} cy {:+7.2} | rms {rms:.5} obs {obs}",
            s.left.fx - t.left.fx,
            s.left.fy - t.left.fy,
            s.left.cx - t.left.cx,
            s.left.cy - t.left.cy,
            s.right.fx - t.right.fx,
            s.right.fy - t.right.fy,
            s.right.cx - t.right.cx,
            s.right.cy - t.right.cy,
        );
    };
    show("estimate", st, c.bundle.report.final_rms_px, c.bundle.report.observations);
    let sig = |n: &str| c.bundle.covariance.sigma(n).unwrap_or(f64::NAN);
    println!(
        "   sigma: L fx {:7.2} fy {:7.2} cx {:7.2} cy {:7.2} | R fx {:7.2} fy {:7.2} cx {:7.2} cy {:7.2} | noise {:.3}",
        sig("left.fx"),
        sig("left.fy"),
        sig("left.cx"),
        sig("left.cy"),
        sig("right.fx"),
        sig("right.fy"),
        sig("right.cx"),
        sig("right.cy"),
        c.bundle.report.sigma_px
    );
    println!(
        "   clean used {} obs, {} points; noisy {} obs, {} points",
        clean.calibration.observations.len(),
        clean.calibration.point_tracks.len(),
        c.observations.len(),
        c.point_tracks.len()
    );
    // Start from the truth (the clean run's state, same gauge) on the estimate's inliers.
    let cs = &clean.calibration.bundle.state;
    let by_track: HashMap<u64, usize> =
        clean.calibration.point_tracks.iter().enumerate().map(|(i, t)| (*t, i)).collect();
    let mut start = st.clone();
    start.left = cs.left;
    start.right = cs.right;
    start.right_from_left = cs.right_from_left;
    start.motions = cs.motions.clone();
    let mut missing = 0;
    for (i, tr) in c.point_tracks.iter().enumerate() {
        match by_track.get(tr) {
            Some(&j) if clean.calibration.point_observations[j] > 0 => start.points[i] = cs.points[j],
            _ => missing += 1,
        }
    }
    let mut o = EstimationOptions::default().bundle;
    o.robust = RobustLoss::None;
    o.noise_sigma_px = Some(c.bundle.report.sigma_px);
    o.max_iterations = 200;
    let again = bundle_adjust(st, &c.observations, &o).unwrap();
    show("re-run", &again.state, again.report.final_rms_px, again.report.observations);
    match bundle_adjust(&start, &c.observations, &o) {
        Ok(r) => {
            show("fromtrue", &r.state, r.report.final_rms_px, r.report.observations);
            println!(
                "   (from the truth: initial rms {:.5}, {} iterations, {})",
                r.report.initial_rms_px, r.report.iterations, r.report.termination
            );
        }
        Err(e) => println!("from truth failed: {e}"),
    }
    for (tag, which) in [("truth K", 0), ("truth rig", 1), ("truth mot", 2), ("truth pts", 3), ("K+rig", 4)] {
        let m = common::with_true_part(st, cs, &start.points, which);
        match bundle_adjust(&m, &c.observations, &o) {
            Ok(r) => show(tag, &r.state, r.report.final_rms_px, r.report.observations),
            Err(e) => println!("{tag} failed: {e}"),
        }
    }
    {
        let (a, b) = (st.right_from_left, cs.right_from_left);
        let d = a.rotation.inverse() * b.rotation;
        let ta = a.translation.vector.normalize();
        let tb = b.translation.vector.normalize();
        println!(
            "   rig: est rot {:?} deg, truth rot {:?} deg, diff {:.3} deg about {:?}; t est {:?} truth {:?} angle {:.3} deg",
            a.rotation.scaled_axis().map(f64::to_degrees),
            b.rotation.scaled_axis().map(f64::to_degrees),
            d.angle().to_degrees(),
            d.axis().map(|x| x.into_inner()),
            ta,
            tb,
            ta.angle(&tb).to_degrees()
        );
    }
    let mut centred = st.clone();
    for k in [&mut centred.left, &mut centred.right] {
        k.cx = 383.5;
        k.cy = 287.5;
    }
    match bundle_adjust(&centred, &c.observations, &o) {
        Ok(r) => show("centred", &r.state, r.report.final_rms_px, r.report.observations),
        Err(e) => println!("centred failed: {e}"),
    }
    println!("   ({missing} points without a clean counterpart kept at the estimate)");
    let noise = c.bundle.report.sigma_px;
    let cost = |r: &BundleResult| r.chi2(noise, &o);
    let base = cost(&again);
    if let Ok((s, sig)) = log_depth_scale(st, &c.observations, &o, noise) {
        println!("   depth scale s {s:.4} sigma {sig:.4} (estimate cost {base:.2})");
        if let Ok(r) = bundle_adjust(&start, &c.observations, &o) {
            let ts = log_depth_scale(&r.state, &c.observations, &o, noise).map(|x| x.0).unwrap_or(f64::NAN);
            println!(
                "   from the truth: s {ts:.4}, cost {:+.2}, t {:?}",
                cost(&r) - base,
                r.state.right_from_left.translation.vector.normalize()
            );
        }
        let ks: Vec<f64> = match std::env::var("SWEEP_LOG") {
            Ok(v) => v.split(',').filter_map(|x| x.parse::<f64>().ok()).map(|d| d / sig).collect(),
            Err(_) => vec![-3.0, -2.0, -1.0, 1.0, 2.0, 3.0],
        };
        for k in ks {
            let Ok(held) =
                bundle_adjust_at_depth_scale(st, &c.observations, &o, s + k * sig, 1e-3 * sig / noise)
            else {
                println!("   sweep {k:+}: held adjustment failed");
                continue;
            };
            match bundle_adjust(&held.state, &c.observations, &o) {
                Ok(r) => {
                    let fs = log_depth_scale(&r.state, &c.observations, &o, noise)
                        .map(|x| x.0)
                        .unwrap_or(f64::NAN);
                    show(&format!("sw{k:+}"), &r.state, r.report.final_rms_px, r.report.observations);
                    println!(
                        "      held cost {:+.2}, freed cost {:+.2}, s {fs:.4}, {} iterations",
                        cost(&held) - base,
                        cost(&r) - base,
                        r.report.iterations
                    );
                }
                Err(e) => println!("   sweep {k:+}: freed adjustment failed: {e}"),
            }
        }
    }
}
