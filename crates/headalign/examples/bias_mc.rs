//! Diagnostic (not a test): is the maximum-likelihood bundle adjustment itself biased at
//! the experiments' geometry (`docs/ratio-tail.md`, eleventh session)? For each seed, the
//! clean trial's state (the truth) and its inlier observations; fresh Gaussian pixel
//! noise, the least squares from the truth, and the mean error of each intrinsic in units
//! of its reported sigma (and as mean error over mean sigma). `TRUNCATE=1` drops the
//! observations that the noise pushed out of the image, as the simulator does (the same
//! draws otherwise: a paired comparison); `WINDOW=1` has the adjustment model that border
//! (`BundleOptions::measurement_window`). Also RMS error / RMS bound (the covariance at
//! the truth with the same noise): the least squares' own ratio, with no outliers, no
//! selection and no starts (`docs/efficiency.md`, nineteenth session).
//! `SCENE=paper` (or `robot`) runs that scene preset. Also the 95 % coverage of the
//! adjustment's own sigma (its covariance at its estimate) and of the bound.
//! `cargo run --release -p headalign --example bias_mc -- FIRST_SEED SEEDS DRAWS NOISE`
use headalign::estimate::EstimationOptions;
use headalign_geometry::bundle::{BundleObservation, BundleOptions, RobustLoss, bundle_adjust};
use headalign_platform::Encoders;
use headalign_sim::Scenario;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

mod common;

fn main() {
    let a: Vec<f64> = std::env::args().skip(1).map(|s| s.parse().expect("numbers")).collect();
    let (first, seeds, draws, noise) = (a[0] as u64, a[1] as u64, a[2] as usize, a[3]);
    let names = ["left.fx", "left.fy", "right.fx", "right.fy", "left.cx", "right.cy"];
    let mut obs_sum = vec![0.0; names.len()];
    let mut count = 0.0_f64;
    let mut raw = vec![0.0; names.len()];
    let mut sig = vec![0.0; names.len()];
    // Squared errors and squared bounds (the covariance at the truth), for RMS / bound.
    let mut err2 = vec![0.0; names.len()];
    let mut bound2 = vec![0.0; names.len()];
    // Trials with |error| <= 1.96 sigma: the estimate's own sigma, and the bound.
    let mut covered = vec![0.0; names.len()];
    let mut covered_bound = vec![0.0; names.len()];
    let scene = std::env::var("SCENE").unwrap_or_else(|_| "default".into());
    let preset = Scenario::preset(&scene).expect("a scene preset");
    let mut rng = ChaCha8Rng::seed_from_u64(first);
    // TRUNCATE=1: drop the observations that noise pushed out of the image, as the
    // simulator does.
    let truncate = std::env::var("TRUNCATE").is_ok();
    // WINDOW=1: the adjustment models the image border (`BundleOptions::measurement_window`).
    let window = std::env::var("WINDOW").is_ok();
    for seed in first..first + seeds {
        let sc = Scenario { seed, noise_px: 1e-300, ..preset.clone() };
        let Some((_, clean)) = common::verge_tilt_trial(&sc, &Encoders::default(), seed) else { continue };
        let truth = &clean.calibration.bundle.state;
        let mut o = EstimationOptions::default().bundle;
        o.robust = RobustLoss::None;
        o.noise_sigma_px = Some(noise);
        o.max_iterations = 300;
        if window {
            let [w, h] = sc.image_size.map(f64::from);
            o.measurement_window = Some([-0.5, -0.5, w - 0.5, h - 0.5]);
        }
        let at_truth = bundle_adjust(
            truth,
            &clean.calibration.observations,
            &BundleOptions { max_iterations: 0, ..o.clone() },
        );
        let Ok(at_truth) = at_truth else { continue };
        for _ in 0..draws {
            let obs: Vec<BundleObservation> =
                common::with_pixel_noise(&clean.calibration.observations, noise, &mut rng)
                    .into_iter()
                    .filter(|b| !truncate || headalign_sim::scene::pixel_in_image(&b.pixel, sc.image_size))
                    .collect();
            let Ok(r) = bundle_adjust(truth, &obs, &o) else { continue };
            let get = |s: &headalign_geometry::bundle::RigState, n: &str| match n {
                "left.fx" => s.left.fx,
                "left.fy" => s.left.fy,
                "right.fx" => s.right.fx,
                "right.fy" => s.right.fy,
                "left.cx" => s.left.cx,
                _ => s.right.cy,
            };
            for (i, n) in names.iter().enumerate() {
                let s = r.covariance.sigma(n).expect("named");
                obs_sum[i] += (get(&r.state, n) - get(truth, n)) / s;
                raw[i] += get(&r.state, n) - get(truth, n);
                err2[i] += (get(&r.state, n) - get(truth, n)).powi(2);
                let b = at_truth.covariance.sigma(n).expect("named");
                bound2[i] += b.powi(2);
                let e = (get(&r.state, n) - get(truth, n)).abs();
                covered[i] += f64::from(u8::from(e <= 1.96 * s));
                covered_bound[i] += f64::from(u8::from(e <= 1.96 * b));
                sig[i] += s;
            }
            count += 1.0;
        }
    }
    println!("{count} adjustments at {noise} px (mean error / sigma; se {:.3}):", 1.0 / count.sqrt());
    for (i, n) in names.iter().enumerate() {
        println!(
            "{n:>9}: mean error / sigma {:+.3}  (mean error / mean sigma {:+.3}); RMS error / RMS bound at the truth {:.3}; coverage {:.1} % (bound's {:.1} %)",
            obs_sum[i] / count,
            raw[i] / sig[i],
            (err2[i] / bound2[i]).sqrt(),
            100.0 * covered[i] / count,
            100.0 * covered_bound[i] / count
        );
    }
}
