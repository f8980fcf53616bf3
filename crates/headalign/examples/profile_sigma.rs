//! Diagnostic (not a test): are the intrinsics' linearised sigmas too small where the
//! likelihood is flatter than quadratic? For seeds `FIRST..FIRST+N` at `NOISE` px (scene
//! `SCENE`, default `paper`), each verge/tilt trial's intrinsic `q` is held at
//! `q_hat +- Z sigma` ([`bundle_adjust_holding`], everything else re-adjusted on the
//! estimate's inliers at its noise) and the cost rise `d` (chi-square units) gives the
//! profile half-width `Z sigma / sqrt(d)` on that side. Printed per quantity: the 95 %
//! coverage of the linearised sigma, of the larger of it and the profile's on the side the
//! truth lies, and of the largest of all three. The encoders read exactly (the preset's
//! default; `headalign experiment` reads them with 0.01 deg of noise), so the linearised
//! coverage runs higher than the experiments'; compare the columns with each other.
//! `cargo run --release -p headalign --example profile_sigma -- FIRST N NOISE [Z]`
use headalign_geometry::bundle::{RobustLoss, bundle_adjust, bundle_adjust_holding};
use headalign_geometry::camera::Intrinsics;
use headalign_platform::{Encoders, StereoHead};
use headalign_sim::Scenario;

mod common;

const QUANTITIES: [&str; 8] =
    ["left.fx", "left.fy", "left.cx", "left.cy", "right.fx", "right.fy", "right.cx", "right.cy"];

/// Intrinsic `name` of `k` (fx, fy, cx, cy), mutable.
fn field<'a>(k: &'a mut Intrinsics, name: &str) -> &'a mut f64 {
    match name {
        "fx" => &mut k.fx,
        "fy" => &mut k.fy,
        "cx" => &mut k.cx,
        _ => &mut k.cy,
    }
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let first: u64 = a[1].parse().unwrap();
    let n: u64 = a[2].parse().unwrap();
    let noise: f64 = a[3].parse().unwrap();
    let z: f64 = a.get(4).map_or(1.96, |s| s.parse().unwrap());
    let scene = std::env::var("SCENE").unwrap_or_else(|_| "paper".into());
    // Per quantity: hits of (linear, side profile, max of all), trials.
    let mut hits = [[0usize; 3]; 8];
    let mut trials = 0usize;
    for seed in first..first + n {
        let sc = Scenario { seed, noise_px: noise, ..Scenario::preset(&scene).expect("a scene preset") };
        let Some((head, out)) = common::verge_tilt_trial(&sc, &Encoders::default(), seed) else {
            println!("seed {seed}: failed");
            continue;
        };
        let t = head.truth().clone();
        let c = &out.calibration;
        let [w, h] = head.image_size();
        let mut o = headalign::estimate::EstimationOptions::default().bundle;
        o.robust = RobustLoss::None;
        o.noise_sigma_px = Some(c.bundle.report.sigma_px);
        o.max_iterations = 100;
        o.measurement_window = Some([-0.5, -0.5, f64::from(w) - 0.5, f64::from(h) - 0.5]);
        let Ok(base) = bundle_adjust(&c.bundle.state, &c.observations, &o) else { continue };
        let chi0 = base.chi2(c.bundle.report.sigma_px, &o);
        trials += 1;
        let mut line = format!("seed {seed:4}");
        for (qi, q) in QUANTITIES.iter().enumerate() {
            let (side, name) = q.split_once('.').unwrap();
            let pick = |l: &Intrinsics, r: &Intrinsics| {
                let mut k = if side == "left" { *l } else { *r };
                *field(&mut k, name)
            };
            let sigma = c.bundle.covariance.sigma(q).unwrap_or(f64::NAN);
            let est = pick(&c.bundle.state.left, &c.bundle.state.right);
            let err = est - pick(&t.left, &t.right);
            let at = pick(&base.state.left, &base.state.right);
            let mut half = [f64::NAN; 2];
            for (i, sign) in [-1.0, 1.0].into_iter().enumerate() {
                let mut start = base.state.clone();
                let k = if side == "left" { &mut start.left } else { &mut start.right };
                *field(k, name) = at + sign * z * sigma;
                if let Ok(end) = bundle_adjust_holding(&start, &c.observations, &o, &[q]) {
                    let d = end.chi2(c.bundle.report.sigma_px, &o) - chi0;
                    half[i] = if d > 0.0 { z * sigma / d.sqrt() } else { f64::INFINITY };
                }
            }
            let on_side = if err > 0.0 { half[0] } else { half[1] };
            let s_side = sigma.max(if on_side.is_finite() { on_side } else { sigma });
            let s_max = sigma.max(half[0].max(half[1]));
            let ok = |s: f64| (err.abs() <= 1.96 * s) as usize;
            hits[qi][0] += ok(sigma);
            hits[qi][1] += ok(s_side);
            hits[qi][2] += ok(s_max);
            line += &format!(" | {q} z {:+.2} w {:.2}/{:.2}", err / sigma, half[0] / sigma, half[1] / sigma);
        }
        println!("{line}");
    }
    println!("{trials} trials, noise {noise}, scene {scene}, Z {z}");
    for (qi, q) in QUANTITIES.iter().enumerate() {
        let f = |k: usize| 100.0 * hits[qi][k] as f64 / trials as f64;
        println!("{q:9}: linear {:5.1} %  side profile {:5.1} %  max {:5.1} %", f(0), f(1), f(2));
    }
}
