//! Experiment: how the Cramer-Rao bounds of the issue-5 bars depend on the simulated
//! scene the paper leaves open (depth range of the points, near structure).
//! `cargo run --release -p headalign --example crb_scenes -- [SEEDS]`
//!
//! Per scene variant and seed: the verge/tilt procedure noise-free (3 deg rotations,
//! 3 deg vergence move), then the bundle covariance at that state (zero iterations, no
//! robust loss) for the bar's noise, propagated to the aligned elevation as the procedure
//! does ([`alignment_sigmas`]) — the same bound as `headalign experiment`. Prints the RMS
//! over seeds of the bound of `f = fx` (percent, L/R pooled; 200 points, 3 px) and of the
//! aligned elevation (degrees; 50 points, 1.5 px). A second table varies the point spread
//! over the image in the default scene: all 200 points, only those in the central quarter
//! of the reference image (about 50), or as many spread over the whole image (measured, 10
//! seeds: f 14.1 % / 3.81 %, elevation 1.29 / 0.79 deg: the default scene's spread over
//! the whole image is the favourable layout).
use headalign::estimate::{EstimationOptions, RigCalibration};
use headalign::procedure::{VergeTiltOptions, VergeTiltRun, alignment_sigmas};
use headalign_geometry::bundle::{RobustLoss, bundle_adjust};
use headalign_sim::{Scenario, SimulatedHead};

/// Which points of the noise-free run the bound keeps (the point spread over the image).
#[derive(Clone, Copy)]
enum Spread {
    /// All of them.
    All,
    /// Those whose reference left pixel lies in the central half of the image in both
    /// directions (a quarter of its area).
    Central,
    /// Every k-th point, k chosen to keep as many as `Central` would (same count, spread
    /// over the whole image).
    Thinned,
}

/// (bound of f pooled in percent, bound of the aligned elevation in degrees), or why not.
type Bounds = Result<(f64, f64), Box<dyn std::error::Error>>;

/// [`Bounds`] of scenario `s` at `noise`.
fn bounds(s: &Scenario, noise: f64) -> Bounds {
    bounds_with(s, noise, Spread::All)
}

fn bounds_with(s: &Scenario, noise: f64, spread: Spread) -> Bounds {
    let mut head = SimulatedHead::new(Scenario { noise_px: 0.0, ..s.clone() })?;
    let opts = VergeTiltOptions {
        rotation_deg: 3.0,
        verge_rotation_deg: 3.0,
        estimation: EstimationOptions { seed: s.seed, ..EstimationOptions::default() },
        ..VergeTiltOptions::default()
    };
    let out = VergeTiltRun::default().run(&mut head, &opts)?;
    let calib = &out.calibration;
    let mut o = EstimationOptions::default().bundle;
    o.max_iterations = 0;
    o.robust = RobustLoss::None;
    o.noise_sigma_px = Some(noise);
    let [w, h] = s.image_size.map(f64::from);
    let central: Vec<usize> = calib
        .observations
        .iter()
        .filter(|b| {
            b.view == 0
                && b.side == headalign_geometry::bundle::Side::Left
                && (b.pixel.x - 0.5 * w).abs() <= 0.25 * w
                && (b.pixel.y - 0.5 * h).abs() <= 0.25 * h
        })
        .map(|b| b.point)
        .collect();
    let n_points = calib.bundle.state.points.len();
    let keep: Vec<bool> = match spread {
        Spread::All => vec![true; n_points],
        Spread::Central => (0..n_points).map(|i| central.contains(&i)).collect(),
        Spread::Thinned => {
            let k = (n_points as f64 / central.len().max(1) as f64).round().max(1.0) as usize;
            (0..n_points).map(|i| i % k == 0).collect()
        }
    };
    let obs: Vec<_> = calib.observations.iter().copied().filter(|b| keep[b.point]).collect();
    let bundle = bundle_adjust(&calib.bundle.state, &obs, &o)?;
    let at_truth = RigCalibration { bundle, ..calib.clone() };
    let sig = alignment_sigmas(&at_truth, &out.verge_axes, &calib.reference_encoders)?;
    let st = &at_truth.bundle.state;
    let c = &at_truth.bundle.covariance;
    let fl = c.sigma("left.fx").unwrap_or(f64::NAN) / st.left.fx * 100.0;
    let fr = c.sigma("right.fx").unwrap_or(f64::NAN) / st.right.fx * 100.0;
    Ok(((0.5 * (fl * fl + fr * fr)).sqrt(), sig.elevation_deg))
}

/// RMS over seeds `1..=seeds` of the focal bound of the first and the elevation bound of
/// the second of `two(seed)`, and how many seeds gave both (failures are printed).
fn rms_over_seeds(name: &str, seeds: u64, mut two: impl FnMut(u64) -> (Bounds, Bounds)) -> (f64, f64, usize) {
    let (mut sf, mut se, mut n) = (0.0, 0.0, 0usize);
    for seed in 1..=seeds {
        match two(seed) {
            (Ok((f, _)), Ok((_, e))) => {
                sf += f * f;
                se += e * e;
                n += 1;
            }
            (a, b) => eprintln!("{name} seed {seed}: {:?} {:?}", a.err(), b.err()),
        }
    }
    let nf = n.max(1) as f64;
    ((sf / nf).sqrt(), (se / nf).sqrt(), n)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let seeds: u64 = args.get(1).map_or(Ok(10), |s| s.parse())?;
    let d = Scenario::default();
    let range = |lo: f64, hi: f64| Scenario { scene_min_m: lo, scene_max_m: hi, ..Scenario::default() };
    let mut variants: Vec<(String, Scenario)> = vec![("default 1.5-6 m".into(), d.clone())];
    for (lo, hi) in
        [(3.0, 6.0), (1.5, 10.0), (1.0, 6.0), (1.5, 3.0), (1.0, 3.0), (0.7, 2.0), (0.7, 1.5), (0.5, 1.2)]
    {
        variants.push((format!("{lo}-{hi} m"), range(lo, hi)));
    }
    variants.push((
        "default + 6 near panels at 1 m".into(),
        Scenario { near_panels: Scenario::ROBOT_NEAR_PANELS, ..d.clone() },
    ));
    variants.push(("paper_lab preset".into(), Scenario::paper_lab()));
    println!("| scene | f bound, 200 pts, 3 px (%) | elevation bound, 50 pts, 1.5 px (deg) | ok seeds |");
    println!("|---|---|---|---|");
    for (name, s) in variants {
        let (f, e, n) = rms_over_seeds(&name, seeds, |seed| {
            let f200 = bounds(&Scenario { seed, points: 200, ..s.clone() }, 3.0);
            (f200, bounds(&Scenario { seed, points: 50, ..s.clone() }, 1.5))
        });
        println!("| {name} | {f:.2} | {e:.3} | {n}/{seeds} |");
    }
    // Point spread over the image: the default scene's 200 points, all of them, only the
    // central quarter of the image, or as many spread over the whole image.
    println!("\n| points of the default scene (200) | f bound, 3 px (%) | elevation bound, 1.5 px (deg) |");
    println!("|---|---|---|");
    for (name, spread) in [
        ("all", Spread::All),
        ("central half of the image (w/2 x h/2)", Spread::Central),
        ("same count, whole image", Spread::Thinned),
    ] {
        let (f, e, _) = rms_over_seeds(name, seeds, |seed| {
            let sc = Scenario { seed, ..d.clone() };
            (bounds_with(&sc, 3.0, spread), bounds_with(&sc, 1.5, spread))
        });
        println!("| {name} | {f:.2} | {e:.3} |");
    }
    Ok(())
}
