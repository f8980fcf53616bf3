//! Diagnostic (not a test): estimated noise vs the truth, and which observations the
//! final pass keeps. `cargo run --release -p headalign --example noise_diag -- NOISE OUTLIERS SEED0 SEED1`
use std::collections::HashMap;

use headalign::estimate::{EstimationOptions, estimate_rig};
use headalign::observations::View;
use headalign::procedure::{VergeTiltOptions, capture_plan};
use headalign_geometry::bundle::Side;
use headalign_platform::StereoHead;
use headalign_sim::{Scenario, SimulatedHead};

fn views(s: Scenario) -> Vec<View> {
    let mut head = SimulatedHead::new(s).unwrap();
    let e0 = head.read_encoders().unwrap();
    let plan = capture_plan(&e0, &VergeTiltOptions::default());
    let mut out = Vec::new();
    for (name, enc) in plan {
        head.move_to(&enc).unwrap();
        out.push(View { name, capture: head.capture().unwrap() });
    }
    out.pop();
    out
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let noise: f64 = a[1].parse().unwrap();
    let outl: f64 = a[2].parse().unwrap();
    let s0: u64 = a[3].parse().unwrap();
    let s1: u64 = a[4].parse().unwrap();
    for seed in s0..=s1 {
        let sc = Scenario { seed, noise_px: noise, outlier_fraction: outl, ..Default::default() };
        let noisy = views(sc.clone());
        let exact = views(Scenario { noise_px: 1e-300, ..sc.clone() });
        let mut truth = HashMap::new();
        for (vi, v) in exact.iter().enumerate() {
            for (side, list) in [(0, &v.capture.left), (1, &v.capture.right)] {
                for o in list {
                    truth.insert((vi, side, o.track), o.pixel);
                }
            }
        }
        // All inlier (|true residual| < 6 sigma) observations.
        let (mut all_ss, mut all_n) = (0.0, 0usize);
        for (vi, v) in noisy.iter().enumerate() {
            for (side, list) in [(0, &v.capture.left), (1, &v.capture.right)] {
                for o in list {
                    if let Some(t) = truth.get(&(vi, side, o.track)) {
                        let r = (o.pixel - t).norm_squared();
                        if r < 36.0 * noise * noise {
                            all_ss += r;
                            all_n += 1;
                        }
                    }
                }
            }
        }
        let s = noise.max(1.0);
        let d = EstimationOptions::default();
        let mut o = EstimationOptions { seed, prefilter_px: d.prefilter_px * s, ..d };
        o.fundamental.threshold *= s;
        o.homography.threshold *= s;
        let Ok(c) = estimate_rig(&noisy, &o) else {
            println!("seed {seed} failed");
            continue;
        };
        let (mut ss, mut n, mut outl_used) = (0.0, 0usize, 0usize);
        for ob in &c.observations {
            let track = c.point_tracks[ob.point];
            let side = usize::from(ob.side == Side::Right);
            if let Some(t) = truth.get(&(ob.view, side, track)) {
                let r = (ob.pixel - t).norm_squared();
                if r > 36.0 * noise * noise {
                    outl_used += 1;
                }
                ss += r;
                n += 1;
            }
        }
        // Rejection rate by |true residual| / sigma, over observations of used points.
        let used: std::collections::HashSet<(usize, usize, u64)> = c
            .observations
            .iter()
            .map(|ob| (ob.view, usize::from(ob.side == Side::Right), c.point_tracks[ob.point]))
            .collect();
        let used_points: std::collections::HashSet<u64> = used.iter().map(|k| k.2).collect();
        let mut buckets = [[0usize; 2]; 7];
        let mut lost_points = [0usize; 7];
        for (vi, v) in noisy.iter().enumerate() {
            for (side, list) in [(0, &v.capture.left), (1, &v.capture.right)] {
                for ob in list {
                    if let Some(t) = truth.get(&(vi, side, ob.track)) {
                        let z = (ob.pixel - t).norm() / noise;
                        let b = (z as usize).min(6);
                        if used_points.contains(&ob.track) {
                            buckets[b][0] += 1;
                            if used.contains(&(vi, side, ob.track)) {
                                buckets[b][1] += 1;
                            }
                        } else {
                            lost_points[b] += 1;
                        }
                    }
                }
            }
        }
        let kept: Vec<String> =
            buckets.iter().map(|[a, b]| format!("{:.3}", *b as f64 / (*a).max(1) as f64)).collect();
        println!(
            "  kept fraction by |r|/sigma 0..6+: {kept:?}; obs of unused points by bucket {lost_points:?}"
        );
        let rep = &c.bundle.report;
        println!(
            "seed {seed}: sigma_hat/true {:.3}  true-rms(all inl)/true {:.3}  true-rms(used)/true {:.3}  used {}/{} inl ({} outl used) params {} fitrms {:.3}",
            rep.sigma_px / noise,
            (all_ss / (2.0 * all_n as f64)).sqrt() / noise,
            (ss / (2.0 * n as f64)).sqrt() / noise,
            n,
            all_n,
            outl_used,
            rep.parameters,
            rep.final_rms_px,
        );
    }
}
