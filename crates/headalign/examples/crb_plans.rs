//! Experiment: the Cramer-Rao bound of the focal lengths for candidate sets of head
//! rotations (the views the verge/tilt procedure could capture), on the simulated head.
//! `cargo run --release -p headalign --example crb_plans -- [SEEDS [NOISE_PX]]`
//!
//! Per seed and plan: noise-free captures at the plan's (pan, elevation) offsets, the
//! estimate (equal to the truth), then the covariance at that state for `NOISE_PX` (zero
//! iterations, no robust loss), as `experiment`'s bound. Prints the RMS over seeds of the
//! bound of `f = fx` (percent, L/R pooled) and of the elevation axis direction, and the
//! smallest overlap (shared stereo tracks / reference stereo tracks) of the plan's views.
use headalign::estimate::{EstimationOptions, estimate_rig};
use headalign::observations::View;
use headalign::procedure::shared_stereo_tracks;
use headalign_geometry::bundle::{RobustLoss, bundle_adjust};
use headalign_platform::{Encoders, Joint, StereoHead};
use headalign_sim::{Scenario, SimulatedHead};

fn plans() -> Vec<(&'static str, Vec<(f64, f64)>)> {
    let cross = |r: f64| vec![(0.0, r), (0.0, -r), (r, 0.0), (-r, 0.0)];
    let diag = |r: f64| vec![(r, r), (r, -r), (-r, r), (-r, -r)];
    let cat = |a: Vec<(f64, f64)>, b: Vec<(f64, f64)>| a.into_iter().chain(b).collect::<Vec<_>>();
    vec![
        ("cross 3", cross(3.0)),
        ("cross 10", cross(10.0)),
        ("cross 10 + cross 5", cat(cross(10.0), cross(5.0))),
        ("cross 10 + diag 5", cat(cross(10.0), diag(5.0))),
        ("cross 10 + diag 7", cat(cross(10.0), diag(7.0))),
        ("cross 10 + diag 10", cat(cross(10.0), diag(10.0))),
        ("cross 10 + diag 10 + cross 5", cat(cat(cross(10.0), diag(10.0)), cross(5.0))),
        ("cross 10 + diag 10 + diag 5", cat(cat(cross(10.0), diag(10.0)), diag(5.0))),
        ("diag 10", diag(10.0)),
    ]
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let seeds: u64 = args.get(1).map_or(Ok(10), |s| s.parse())?;
    let noise: f64 = args.get(2).map_or(Ok(3.0), |s| s.parse())?;
    let only: Option<usize> = args.get(3).map(|s| s.parse()).transpose()?;
    for (pi, (name, plan)) in plans().into_iter().enumerate() {
        if only.is_some_and(|o| o != pi) {
            continue;
        }
        let (mut sum_f, mut sum_e, mut min_overlap, mut n) = (0.0, 0.0, 1.0f64, 0);
        for seed in 1..=seeds {
            let s = Scenario { seed, noise_px: 0.0, ..Scenario::default() };
            let mut head = SimulatedHead::new(s)?;
            let e0 = head.read_encoders()?;
            let mut views = vec![View { name: "initial".into(), capture: head.capture()? }];
            for (i, &(p, e)) in plan.iter().enumerate() {
                let enc: Encoders = e0.moved(Joint::Pan, p).moved(Joint::Elevation, e);
                head.move_to(&enc)?;
                let capture = head.capture()?;
                let (shared, total) = shared_stereo_tracks(&views[0].capture, &capture);
                min_overlap = min_overlap.min(shared as f64 / total as f64);
                views.push(View { name: format!("v{i}"), capture });
            }
            let calib =
                match estimate_rig(&views, &EstimationOptions { seed, ..EstimationOptions::default() }) {
                    Ok(c) => c,
                    Err(e) => {
                        eprintln!("{name} seed {seed}: {e}");
                        continue;
                    }
                };
            let mut o = EstimationOptions::default().bundle;
            o.max_iterations = 0;
            o.robust = RobustLoss::None;
            o.noise_sigma_px = Some(noise);
            let b = bundle_adjust(&calib.bundle.state, &calib.observations, &o)?;
            let st = &b.state;
            let c = &b.covariance;
            let fl = c.sigma("left.fx").unwrap_or(f64::NAN) / st.left.fx * 100.0;
            let fr = c.sigma("right.fx").unwrap_or(f64::NAN) / st.right.fx * 100.0;
            sum_f += 0.5 * (fl * fl + fr * fr);
            let el = c.sigma("left.fy").unwrap_or(f64::NAN) / st.left.fy * 100.0;
            sum_e += el * el;
            n += 1;
        }
        let nf = n as f64;
        println!(
            "{name:32} views {:2}  f=fx bound {:.3} %  left fy {:.3} %  min overlap {:.2}  ({n} seeds)",
            plan.len() + 1,
            (sum_f / nf).sqrt(),
            (sum_e / nf).sqrt(),
            min_overlap
        );
    }
    Ok(())
}
