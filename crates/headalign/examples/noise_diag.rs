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
        let o = EstimationOptions::scaled_for_noise(noise, seed);
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
        // Compare with the noise-free run of the same seed: which observations it uses
        // that this run does not, and why.
        let clean_views = views(Scenario { noise_px: 1e-300, ..sc.clone() });
        let d0 = EstimationOptions::default();
        let o0 = EstimationOptions { seed, ..d0.clone() };
        if let Ok(c0) = estimate_rig(&clean_views, &o0) {
            let used0: std::collections::HashSet<(usize, usize, u64)> = c0
                .observations
                .iter()
                .map(|ob| (ob.view, usize::from(ob.side == Side::Right), c0.point_tracks[ob.point]))
                .collect();
            let tracks: std::collections::HashSet<u64> = c.point_tracks.iter().copied().collect();
            let (mut no_track, mut point_dropped, mut gated) = (0, 0, 0);
            for k in used0.difference(&used) {
                if !tracks.contains(&k.2) {
                    no_track += 1;
                } else if !used_points.contains(&k.2) {
                    point_dropped += 1;
                } else {
                    gated += 1;
                }
            }
            let extra = used.difference(&used0).count();
            let k0 = &c0.bundle.state;
            let k = &c.bundle.state;
            println!(
                "  clean used {} ; missing here: {} (track absent {no_track}, point dropped {point_dropped}, obs gated {gated}); extra here {extra}; fx err L {:.2}% R {:.2}% (clean {:.3}% {:.3}%) rms_in {:.2}",
                used0.len(),
                no_track + point_dropped + gated,
                (k.left.fx / k0.left.fx - 1.0) * 100.0,
                (k.right.fx / k0.right.fx - 1.0) * 100.0,
                (k0.left.fx / 700.0 - 1.0) * 100.0,
                (k0.right.fx / 705.0 - 1.0) * 100.0,
                c.report.initial_rms_px,
            );
            println!(
                "  report {:?}",
                c.report.homographies.iter().map(|h| (h.candidates, h.inliers)).collect::<Vec<_>>()
            );
            println!(
                "  clean  {:?} stereo {} / {} vs clean {} / {}",
                c0.report.homographies.iter().map(|h| (h.candidates, h.inliers)).collect::<Vec<_>>(),
                c.report.stereo_inliers,
                c.report.stereo_matches,
                c0.report.stereo_inliers,
                c0.report.stereo_matches
            );
        }
        if std::env::var("DROPPED").is_ok() {
            let st = &c.bundle.state;
            let mut dists: Vec<f64> = st.points.iter().map(|p| p.coords.norm()).collect();
            dists.sort_by(f64::total_cmp);
            let med = dists[dists.len() / 2];
            let mut shown = 0;
            for (pi, tr) in c.point_tracks.iter().enumerate() {
                if used_points.contains(tr) || shown >= 12 {
                    continue;
                }
                shown += 1;
                let mut res = Vec::new();
                for (vi, v) in noisy.iter().enumerate() {
                    for (side, list) in [(Side::Left, &v.capture.left), (Side::Right, &v.capture.right)] {
                        for ob in list.iter().filter(|o| o.track == *tr) {
                            let bo = headalign_geometry::bundle::BundleObservation {
                                point: pi,
                                view: vi,
                                side,
                                pixel: ob.pixel,
                            };
                            let r = headalign_geometry::bundle::residual_pixels(st, &bo)
                                .map_or(-1.0, |r| r.norm());
                            res.push(format!("{vi}{}:{r:.1}", if side == Side::Left { "L" } else { "R" }));
                        }
                    }
                }
                println!(
                    "   dropped point {pi} track {tr} dist/med {:.2} residuals {}",
                    st.points[pi].coords.norm() / med,
                    res.join(" ")
                );
            }
        }
        if std::env::var("FDIAG").is_ok() {
            use headalign_geometry::fundamental::estimate_fundamental;
            let pairs_of = |vs: &[View]| -> Vec<(nalgebra::Point2<f64>, nalgebra::Point2<f64>)> {
                let mut out = Vec::new();
                for v in vs {
                    let r: HashMap<u64, nalgebra::Point2<f64>> =
                        v.capture.right.iter().map(|o| (o.track, o.pixel)).collect();
                    for o in &v.capture.left {
                        if let Some(p) = r.get(&o.track) {
                            out.push((o.pixel, *p));
                        }
                    }
                }
                out
            };
            let pn = pairs_of(&noisy);
            let pc = pairs_of(&clean_views);
            let fopt = headalign_geometry::ransac::RansacOptions { seed, ..o.fundamental };
            let fnz = estimate_fundamental(&pn, &fopt).unwrap();
            let fc = estimate_fundamental(
                &pc,
                &headalign_geometry::ransac::RansacOptions { seed, ..d0.fundamental },
            )
            .unwrap();
            let t = o.fundamental.threshold;
            let msac = |f: &headalign_geometry::fundamental::FundamentalMatrix| -> (f64, usize) {
                (
                    pn.iter().map(|(l, r)| f.sampson_distance(l, r).min(t).powi(2)).sum::<f64>(),
                    pn.iter().filter(|(l, r)| f.sampson_distance(l, r) <= t).count(),
                )
            };
            let inl: Vec<_> =
                pn.iter().copied().filter(|(l, r)| fc.model.sampson_distance(l, r) <= t).collect();
            let fr = fc.model.refine_sampson(&inl).unwrap();
            let ep = |f: &headalign_geometry::fundamental::FundamentalMatrix| {
                let (e, _) = f.epipoles().unwrap();
                (e.x / e.z, e.y / e.z)
            };
            println!(
                "  F noisy msac {:?} epi {:?}; F true msac {:?} epi {:?}; F true refined msac {:?} epi {:?}",
                msac(&fnz.model),
                ep(&fnz.model),
                msac(&fc.model),
                ep(&fc.model),
                msac(&fr),
                ep(&fr)
            );
        }
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
