//! Diagnostic (not a test): would a bootstrap over point tracks give the intrinsics
//! sigmas that cover where the linearised ones do not (the paper-like scene at 3 px,
//! `docs/ratio-tail.md` section 4)? As `bias_mc`: each seed's noise-free trial state (the
//! truth) and its inlier observations, fresh Gaussian pixel noise, the least squares from
//! the truth. Then `B` bootstrap replicates: the points drawn with replacement (each
//! drawn point a new point with all its observations), the least squares from the
//! estimate; the replicates' standard deviation is the bootstrap sigma. Printed per
//! intrinsic: 95 % coverage of the linearised sigma, of the bootstrap's, of the larger of
//! the two, and the median ratio bootstrap / linearised.
//! `SCENE=paper` (default `paper`; or `default`, `robot`).
//! `cargo run --release -p headalign --example bootstrap_mc -- FIRST_SEED SEEDS DRAWS NOISE B`
use headalign::estimate::EstimationOptions;
use headalign_geometry::bundle::{BundleObservation, BundleOptions, RigState, RobustLoss, bundle_adjust};
use headalign_platform::Encoders;
use headalign_sim::Scenario;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

mod common;

const NAMES: [&str; 8] =
    ["left.fx", "left.fy", "left.cx", "left.cy", "right.fx", "right.fy", "right.cx", "right.cy"];

fn get(s: &RigState, n: &str) -> f64 {
    match n {
        "left.fx" => s.left.fx,
        "left.fy" => s.left.fy,
        "left.cx" => s.left.cx,
        "left.cy" => s.left.cy,
        "right.fx" => s.right.fx,
        "right.fy" => s.right.fy,
        "right.cx" => s.right.cx,
        _ => s.right.cy,
    }
}

/// The points drawn with replacement: each draw a new point (its position and all its
/// observations).
fn resample(
    state: &RigState,
    obs: &[BundleObservation],
    rng: &mut ChaCha8Rng,
) -> (RigState, Vec<BundleObservation>) {
    let n = state.points.len();
    let mut by_point: Vec<Vec<BundleObservation>> = vec![Vec::new(); n];
    for o in obs {
        by_point[o.point].push(*o);
    }
    let mut s = state.clone();
    s.points.clear();
    let mut out = Vec::new();
    for _ in 0..n {
        let p = rng.random_range(0..n);
        let idx = s.points.len();
        s.points.push(state.points[p]);
        out.extend(by_point[p].iter().map(|o| BundleObservation { point: idx, ..*o }));
    }
    (s, out)
}

fn main() {
    let a: Vec<f64> = std::env::args().skip(1).map(|s| s.parse().expect("numbers")).collect();
    let (first, seeds, draws, noise, b) = (a[0] as u64, a[1] as u64, a[2] as usize, a[3], a[4] as usize);
    let scene = std::env::var("SCENE").unwrap_or_else(|_| "paper".into());
    let preset = Scenario::preset(&scene).expect("a scene preset");
    let mut rng = ChaCha8Rng::seed_from_u64(first);
    let (mut lin, mut boot, mut both) = ([0.0; 8], [0.0; 8], [0.0; 8]);
    let mut ratios: Vec<Vec<f64>> = vec![Vec::new(); 8];
    let mut count = 0.0_f64;
    for seed in first..first + seeds {
        let sc = Scenario { seed, noise_px: 1e-300, ..preset.clone() };
        let Some((_, clean)) = common::verge_tilt_trial(&sc, &Encoders::default(), seed) else { continue };
        let truth = &clean.calibration.bundle.state;
        let mut o: BundleOptions = EstimationOptions::default().bundle;
        o.robust = RobustLoss::None;
        o.noise_sigma_px = Some(noise);
        o.max_iterations = 300;
        for _ in 0..draws {
            let obs = common::with_pixel_noise(&clean.calibration.observations, noise, &mut rng);
            let Ok(r) = bundle_adjust(truth, &obs, &o) else { continue };
            let mut reps: Vec<[f64; 8]> = Vec::new();
            let ob = BundleOptions { max_iterations: 30, ..o.clone() };
            for _ in 0..b {
                let (s, rb) = resample(&r.state, &obs, &mut rng);
                if let Ok(x) = bundle_adjust(&s, &rb, &ob) {
                    reps.push(NAMES.map(|n| get(&x.state, n)));
                }
            }
            if reps.len() < 3 {
                continue;
            }
            count += 1.0;
            for (i, n) in NAMES.iter().enumerate() {
                let m = reps.iter().map(|r| r[i]).sum::<f64>() / reps.len() as f64;
                let sd =
                    (reps.iter().map(|r| (r[i] - m).powi(2)).sum::<f64>() / (reps.len() - 1) as f64).sqrt();
                let sl = r.covariance.sigma(n).expect("named");
                let e = (get(&r.state, n) - get(truth, n)).abs();
                lin[i] += f64::from(u8::from(e <= 1.96 * sl));
                boot[i] += f64::from(u8::from(e <= 1.96 * sd));
                both[i] += f64::from(u8::from(e <= 1.96 * sd.max(sl)));
                ratios[i].push(sd / sl);
            }
        }
    }
    println!("{count} estimates at {noise} px, scene {scene}, {b} replicates each: 95 % coverage");
    for (i, n) in NAMES.iter().enumerate() {
        ratios[i].sort_by(f64::total_cmp);
        let med = ratios[i].get(ratios[i].len() / 2).copied().unwrap_or(f64::NAN);
        println!(
            "{n:>9}: linearised {:5.1} %  bootstrap {:5.1} %  larger {:5.1} %  median bootstrap / linearised {med:.3}",
            100.0 * lin[i] / count,
            100.0 * boot[i] / count,
            100.0 * both[i] / count
        );
    }
}
