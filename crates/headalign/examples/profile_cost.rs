//! Diagnostic (not a test): the cost and effect of the depth-scale profile of the
//! covariance ([`EstimationOptions::depth_profile`]). For each seed, one verge/tilt trial
//! as `experiment calibration` runs it (head position 0), once with the profile and once
//! without, timed in the same process, printing the depth scale (mean point distance in
//! baselines and its sigma), how far the profile widened the sigmas, and right.cx's
//! sigma with and without it.
//! `cargo run --release -p headalign --example profile_cost -- FIRST LAST NOISE [Z]`
//! (`Z`: the profile's ends in sigmas of the depth scale, default `DepthProfile::DEFAULT.z`;
//! always profiled here, whatever `sigma_s`)
//!
//! Measured (seeds 1001-1012 at 3 px, loaded machine, one run): 22.3 s with / 17.7 s
//! without (+26 % wall; the whole `experiment calibration --only 1.5,3` run: +12 % CPU);
//! right.cx's sigma widened x1.04-1.50, in the two far scenes (1008, 1011: 50-110
//! baselines, sigma_s 0.9-1.2) from 7.3-8.0 to 10.1-11.0 px.
use std::time::Instant;

use headalign::estimate::{DepthProfile, EstimationOptions};
use headalign::procedure::{VergeTiltOptions, VergeTiltRun};
use headalign_platform::{Encoders, StereoHead};
use headalign_sim::{Scenario, SimulatedHead};

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let arg = |i: usize, d: f64| a.get(i).and_then(|v| v.parse().ok()).unwrap_or(d);
    let (first, last, noise) = (arg(1, 1.0) as u64, arg(2, 10.0) as u64, arg(3, 3.0));
    let profile = DepthProfile { z: arg(4, DepthProfile::DEFAULT.z), min_sigma_log_depth: 0.0 };
    println!("seed  t_on t_off  dist sigma_s ends widen intr_widen cx_sigma_on cx_sigma_off cx_err");
    let (mut on_total, mut off_total) = (0.0, 0.0);
    for seed in first..=last {
        let sc = Scenario { seed, noise_px: noise, ..Scenario::default() };
        let run = |on: bool| {
            let mut head = SimulatedHead::new(sc.clone()).ok()?;
            head.move_to(&Encoders::default()).ok()?;
            let mut estimation = EstimationOptions::scaled_for_noise(noise, seed);
            estimation.depth_profile = on.then_some(profile);
            let opts = VergeTiltOptions {
                rotation_deg: sc.rotation_deg,
                verge_rotation_deg: 3.0,
                estimation,
                ..VergeTiltOptions::default()
            };
            let t = Instant::now();
            let out = VergeTiltRun::default().run(&mut head, &opts).ok()?;
            Some((t.elapsed().as_secs_f64(), out, head))
        };
        let (Some((t_on, on, head)), Some((t_off, off, _))) = (run(true), run(false)) else {
            println!("{seed} failed");
            continue;
        };
        on_total += t_on;
        off_total += t_off;
        let truth = head.truth().right.cx;
        let c = &on.calibration;
        let p = c.report.depth_profile;
        let sig = |r: &headalign::estimate::RigCalibration| {
            r.bundle.covariance.sigma("right.cx").unwrap_or(f64::NAN)
        };
        // The largest widening of the eight reported intrinsics' sigmas.
        let intr =
            ["left.fx", "left.fy", "left.cx", "left.cy", "right.fx", "right.fy", "right.cx", "right.cy"]
                .iter()
                .map(|n| {
                    let s = |r: &headalign::estimate::RigCalibration| {
                        r.bundle.covariance.sigma(n).unwrap_or(f64::NAN)
                    };
                    s(c) / s(&off.calibration)
                })
                .fold(1.0, f64::max);
        println!(
            "{seed:4} {t_on:5.2} {t_off:5.2} {:5.1} {:7.3} {:4} {:5.3} {intr:10.3} {:12.3} {:12.3} {:+7.2}",
            p.map_or(f64::NAN, |p| p.log_depth.exp()),
            p.map_or(f64::NAN, |p| p.sigma_log_depth),
            p.map_or(0, |p| p.ends),
            p.map_or(f64::NAN, |p| p.max_widening),
            sig(c),
            sig(&off.calibration),
            c.bundle.state.right.cx - truth
        );
    }
    println!("total time with / without the profile: {on_total:.1} s / {off_total:.1} s");
}
