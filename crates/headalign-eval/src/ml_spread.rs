//! `headalign experiment ml-spread`: the least squares' own Monte-Carlo spread from the
//! truth, the floor under every ratio the procedure's experiments report
//! (`docs/accuracy.md`).
//!
//! What it computes. For each seed of the scene preset: the verge/tilt procedure's
//! noise-free run (head position 0, exact encoder readings, pixel noise
//! [`CLEAN_NOISE_PX`] so that the outliers are those of the noisy trials and RANSAC drops
//! them exactly) gives the truth (its bundle state, equal to the simulator's truth in the
//! estimator's gauge to the solver's tolerance) and its inlier observations. Then, at each
//! noise level, [`DRAWS`] draws of fresh Gaussian pixel noise (`noise_px` per coordinate)
//! on those observations, each adjusted by the maximum-likelihood bundle adjustment
//! started at the truth: no robust loss, no outliers, no selection, no starts, the
//! encoder-angle prior centred on the truth, at most 300 iterations. The Cramer-Rao bound
//! is the covariance at the truth with the same noise (zero iterations), as the
//! experiments evaluate it. Reported per intrinsic (pixels; the eight of
//! [`QUANTITIES`], 1 degree of freedom each): RMS error / RMS bound (1.00 = efficient),
//! the 95 % coverage of the adjustment's own sigma (its covariance at its estimate) and of
//! the bound (|error| <= 1.96 sigma), the mean error / sigma and mean error / mean sigma
//! (bias, in units of the spread).
//!
//! Random numbers: one `ChaCha8Rng` seeded with `--seed` per noise level, drawing the
//! noise of the seeds in order and, within a seed, of its draws in order (x then y of each
//! observation); a seed whose noise-free run or bound fails draws nothing. The adjustments
//! run in parallel but are summed in that order, so the numbers do not depend on the
//! thread count.
//!
//! Options: `--trials N` adjustments in total (default 2000), split evenly over the noise
//! levels and rounded up to whole seeds of [`DRAWS`] draws (so 1000 per level is seeds
//! `--seed` .. `--seed` + 249, 4 draws each); `--only` the noise levels in pixels (any
//! positive values; default 2 and 3 px, the ratio bar's worst levels); `--scene` the
//! preset; `--image-border on` models the image border in the adjustments
//! (`BundleOptions::measurement_window`, the whole image; default off, the plain least
//! squares the bound describes). The procedure's tuning flags do not apply (error).
//! Outputs in `--out`: `ml-spread.csv` (one row per adjustment: the error, own sigma and
//! bound of each quantity; failures with their message) and `ml-spread.md` (the tables);
//! `ml-spread-<scene>` for a non-default scene. Not part of `experiment all`.
//!
//! Pitfall: the draws ignore the image border (a noisy pixel may leave the image; the
//! simulator would have dropped it), which is what the bound assumes.

use std::fmt::Write as _;
use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result, anyhow, bail};
use headalign::procedure::{VergeTiltOptions, VergeTiltRun};
use headalign::verge_tilt::{ENCODER_SIGMA_DEG, EstimationOptions};
use headalign_geometry::bundle::{BundleObservation, BundleOptions, RigState, RobustLoss, bundle_adjust};
use headalign_platform::{Encoders, StereoHead};
use headalign_sim::{Scenario, SimulatedHead};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;
use serde_json::json;

use super::ExperimentArgs;
use super::stats::{coverage_interval, ratio_interval};
use super::trial::CLEAN_NOISE_PX;

/// The experiment's name.
pub const NAME: &str = "ml-spread";

/// Noise draws per seed.
pub const DRAWS: usize = 4;

/// Default total adjustments: 250 seeds x [`DRAWS`] at each default noise level.
const DEFAULT_TRIALS: usize = 2000;

/// Default noise levels, pixels.
const DEFAULT_NOISE_PX: [f64; 2] = [2.0, 3.0];

/// Seeds whose draws are generated and adjusted together (bounds the memory of the noisy
/// observation sets; the order of the sums does not depend on it).
const BATCH_SEEDS: usize = 32;

/// The intrinsics reported, pixels.
pub const QUANTITIES: [&str; 8] =
    ["left.fx", "left.fy", "left.cx", "left.cy", "right.fx", "right.fy", "right.cx", "right.cy"];

/// Value of quantity `q` ([`QUANTITIES`]) in a state.
fn value(s: &RigState, q: usize) -> f64 {
    let k = if q < 4 { &s.left } else { &s.right };
    [k.fx, k.fy, k.cx, k.cy][q % 4]
}

/// One quantity of one adjustment, pixels.
#[derive(Clone, Copy, Debug)]
struct Spread {
    /// Estimate minus truth.
    error: f64,
    /// The adjustment's own sigma (covariance at its estimate).
    sigma: f64,
    /// The bound (covariance at the truth).
    bound: f64,
}

/// One adjustment (or a seed that produced none: `draw` is `None`).
struct Row {
    seed: u64,
    draw: Option<usize>,
    result: Result<[Spread; QUANTITIES.len()], String>,
}

/// The truth and its inlier observations of one seed (module docs).
struct CleanSeed {
    truth: RigState,
    observations: Vec<BundleObservation>,
}

/// The noise-free run of seed `seed` in `preset` (module docs).
fn clean_seed(preset: &Scenario, seed: u64) -> Result<CleanSeed> {
    let sc = Scenario { seed, noise_px: CLEAN_NOISE_PX, ..preset.clone() };
    let mut head = SimulatedHead::new(sc.clone()).map_err(|e| anyhow!("simulator: {e}"))?;
    head.move_to(&Encoders::default()).map_err(|e| anyhow!("simulator: {e}"))?;
    let options = VergeTiltOptions {
        rotation_deg: sc.rotation_deg,
        verge_rotation_deg: 3.0,
        estimation: EstimationOptions::scaled_for_noise(sc.noise_px, seed),
        ..VergeTiltOptions::default()
    };
    let out = VergeTiltRun::default().run(&mut head, &options).context("noise-free verge/tilt run")?;
    Ok(CleanSeed { truth: out.calibration.bundle.state, observations: out.calibration.observations })
}

/// `obs` with fresh Gaussian noise of `noise_px` per pixel coordinate (x then y).
fn with_pixel_noise(
    obs: &[BundleObservation],
    noise_px: f64,
    rng: &mut ChaCha8Rng,
) -> Vec<BundleObservation> {
    obs.iter()
        .map(|b| {
            let e =
                nalgebra::Vector2::new(StandardNormal.sample(&mut *rng), StandardNormal.sample(&mut *rng));
            BundleObservation { pixel: b.pixel + e * noise_px, ..*b }
        })
        .collect()
}

/// The adjustment's options at `noise_px` (module docs); `window`: the image border.
fn adjustment_options(noise_px: f64, window: Option<[f64; 4]>) -> BundleOptions {
    let mut o = EstimationOptions::default().bundle;
    o.robust = RobustLoss::None;
    o.noise_sigma_px = Some(noise_px);
    o.max_iterations = 300;
    o.measurement_window = window;
    o
}

/// The sigmas of [`QUANTITIES`] in a covariance.
fn sigmas(cov: &headalign_geometry::bundle::Covariance) -> Result<[f64; QUANTITIES.len()]> {
    let mut out = [0.0; QUANTITIES.len()];
    for (o, n) in out.iter_mut().zip(QUANTITIES) {
        *o = cov.sigma(n).ok_or_else(|| anyhow!("no sigma of {n}"))?;
    }
    Ok(out)
}

/// One adjustment from the truth on noisy observations, against the bound `bound`.
fn adjust(
    clean: &CleanSeed,
    noisy: &[BundleObservation],
    o: &BundleOptions,
    bound: &[f64; QUANTITIES.len()],
) -> Result<[Spread; QUANTITIES.len()]> {
    let r = bundle_adjust(&clean.truth, noisy, o).context("least squares from the truth")?;
    let own = sigmas(&r.covariance)?;
    let mut out = [Spread { error: f64::NAN, sigma: f64::NAN, bound: f64::NAN }; QUANTITIES.len()];
    for (q, s) in out.iter_mut().enumerate() {
        *s = Spread { error: value(&r.state, q) - value(&clean.truth, q), sigma: own[q], bound: bound[q] };
    }
    Ok(out)
}

/// One adjustment to run: the seed's truth, its bound and the noisy observations.
type Job<'a> = (&'a CleanSeed, &'a [f64; QUANTITIES.len()], Vec<BundleObservation>);

/// Every adjustment at one noise level, in seed and draw order (module docs).
fn run_level(
    cleans: &[(u64, Result<CleanSeed, String>)],
    noise_px: f64,
    first_seed: u64,
    window: Option<[f64; 4]>,
) -> Vec<Row> {
    let o = adjustment_options(noise_px, window);
    let at_truth = BundleOptions { max_iterations: 0, ..o.clone() };
    // The bound of each seed (in parallel; it draws no random numbers).
    let bounds: Vec<Result<[f64; QUANTITIES.len()], String>> = cleans
        .par_iter()
        .map(|(_, c)| {
            let c = c.as_ref().map_err(String::clone)?;
            let r = bundle_adjust(&c.truth, &c.observations, &at_truth)
                .map_err(|e| format!("covariance at the truth: {e}"))?;
            sigmas(&r.covariance).map_err(|e| format!("{e:#}"))
        })
        .collect();
    let mut rng = ChaCha8Rng::seed_from_u64(first_seed);
    let mut rows = Vec::new();
    let items: Vec<_> = cleans.iter().zip(&bounds).collect();
    for batch in items.chunks(BATCH_SEEDS) {
        // The noise, drawn in order; then the adjustments in parallel, kept in order.
        let mut jobs: Vec<(u64, Option<usize>, Result<Job<'_>, String>)> = Vec::new();
        for &((seed, clean), bound) in batch {
            match (clean, bound) {
                (Ok(c), Ok(b)) => {
                    for d in 0..DRAWS {
                        let noisy = with_pixel_noise(&c.observations, noise_px, &mut rng);
                        jobs.push((*seed, Some(d), Ok((c, b, noisy))));
                    }
                }
                (Err(e), _) | (Ok(_), Err(e)) => jobs.push((*seed, None, Err(e.clone()))),
            }
        }
        let done: Vec<Row> = jobs
            .into_par_iter()
            .map(|(seed, draw, job)| {
                let result = job
                    .and_then(|(c, bound, noisy)| adjust(c, &noisy, &o, bound).map_err(|e| format!("{e:#}")));
                Row { seed, draw, result }
            })
            .collect();
        rows.extend(done);
    }
    rows
}

/// The summary of one noise level.
struct Summary {
    noise_px: f64,
    /// Successful adjustments.
    n: usize,
    /// Seeds without a noise-free run or bound, adjustments that failed.
    failed_seeds: usize,
    failed_draws: usize,
    /// Per quantity: mean error / sigma, mean error / mean sigma, RMS error / RMS bound,
    /// coverage of the own sigma and of the bound (0-1).
    mean_z: Vec<f64>,
    mean_over_mean: Vec<f64>,
    ratio: Vec<f64>,
    coverage: Vec<f64>,
    coverage_bound: Vec<f64>,
}

/// Sum the rows in order (module docs).
fn summarise(noise_px: f64, rows: &[Row]) -> Summary {
    let k = QUANTITIES.len();
    let (mut z, mut raw, mut sig, mut err2, mut bound2) =
        (vec![0.0; k], vec![0.0; k], vec![0.0; k], vec![0.0; k], vec![0.0; k]);
    let (mut covered, mut covered_bound) = (vec![0.0; k], vec![0.0; k]);
    let mut count = 0.0_f64;
    let (mut failed_seeds, mut failed_draws) = (0, 0);
    for row in rows {
        let spreads = match (&row.result, row.draw) {
            (Ok(s), _) => s,
            (Err(_), None) => {
                failed_seeds += 1;
                continue;
            }
            (Err(_), Some(_)) => {
                failed_draws += 1;
                continue;
            }
        };
        for (i, s) in spreads.iter().enumerate() {
            z[i] += s.error / s.sigma;
            raw[i] += s.error;
            err2[i] += s.error.powi(2);
            bound2[i] += s.bound.powi(2);
            let e = s.error.abs();
            covered[i] += f64::from(u8::from(e <= 1.96 * s.sigma));
            covered_bound[i] += f64::from(u8::from(e <= 1.96 * s.bound));
            sig[i] += s.sigma;
        }
        count += 1.0;
    }
    let per = |v: &[f64]| v.iter().map(|x| x / count).collect::<Vec<f64>>();
    Summary {
        noise_px,
        n: count as usize,
        failed_seeds,
        failed_draws,
        mean_z: per(&z),
        mean_over_mean: raw.iter().zip(&sig).map(|(r, s)| r / s).collect(),
        ratio: err2.iter().zip(&bound2).map(|(e, b)| (e / b).sqrt()).collect(),
        coverage: per(&covered),
        coverage_bound: per(&covered_bound),
    }
}

fn f(v: f64, digits: usize) -> String {
    if v.is_finite() { format!("{v:.digits$}") } else { "-".into() }
}

/// The CSV of every level's rows.
fn write_csv(path: &Path, levels: &[(f64, Vec<Row>)]) -> Result<()> {
    let mut s = String::from("experiment,noise_px,seed,draw,ok,error");
    for q in QUANTITIES {
        let _ = write!(s, ",{q}.error,{q}.sigma,{q}.bound");
    }
    s.push('\n');
    for (noise, rows) in levels {
        for r in rows {
            let draw = r.draw.map_or(String::new(), |d| d.to_string());
            let _ = write!(s, "{NAME},{noise},{},{draw},", r.seed);
            match &r.result {
                Ok(spreads) => {
                    s.push_str("true,");
                    for p in spreads {
                        let _ = write!(s, ",{},{},{}", p.error, p.sigma, p.bound);
                    }
                }
                Err(e) => {
                    let _ = write!(s, "false,{}", e.replace([',', '\n', '"'], ";"));
                    s.push_str(&",".repeat(3 * QUANTITIES.len()));
                }
            }
            s.push('\n');
        }
    }
    std::fs::write(path, s).with_context(|| format!("cannot write {}", path.display()))
}

/// One table: a row per level, a column per quantity.
fn table(m: &mut String, sums: &[Summary], cell: impl Fn(&Summary, usize) -> String) {
    let _ = write!(m, "| noise (px) | adjustments |");
    for q in QUANTITIES {
        let _ = write!(m, " {q} |");
    }
    let _ = writeln!(m, "\n|---|---|{}", "---|".repeat(QUANTITIES.len()));
    for s in sums {
        let _ = write!(m, "| {} | {} |", s.noise_px, s.n);
        for i in 0..QUANTITIES.len() {
            let _ = write!(m, " {} |", cell(s, i));
        }
        m.push('\n');
    }
}

/// The Markdown summary.
fn markdown(stem: &str, scene: &str, seeds: usize, first: u64, sums: &[Summary], seconds: f64) -> String {
    let mut m = String::new();
    let _ = writeln!(m, "## {stem} — the least squares' own spread from the truth\n");
    let _ = writeln!(
        m,
        "Scene `{scene}`, seeds {first}-{} x {DRAWS} noise draws per noise level, {seconds:.0} s. For each seed the noise-free verge/tilt run (head position 0, exact readings) gives the truth and its inlier observations; each draw adds fresh Gaussian pixel noise and runs the least squares from the truth (no robust loss, no outliers, no selection, no starts; the encoder prior centred on the truth). The bound is the covariance at the truth at the same noise. No procedure built on this estimator does better on these data.\n",
        first + seeds as u64 - 1
    );
    for s in sums.iter().filter(|s| s.failed_seeds + s.failed_draws > 0) {
        let _ = writeln!(
            m,
            "At {} px: {} seed(s) without a noise-free run or bound, {} failed adjustment(s) (`{NAME}.csv`).\n",
            s.noise_px, s.failed_seeds, s.failed_draws
        );
    }
    let n = sums.iter().map(|s| s.n).max().unwrap_or(0);
    let (lo, hi) = ratio_interval(n);
    let _ = writeln!(
        m,
        "RMS error / RMS bound (1.00 = efficient; with {n} adjustments an efficient estimator's ratio lies in [{lo:.2}, {hi:.2}] with 95 % probability):\n"
    );
    table(&mut m, sums, |s, i| f(s.ratio[i], 3));
    let (lo, hi) = coverage_interval(n);
    let _ = writeln!(
        m,
        "\n95 % coverage of the adjustment's own sigma, in brackets of the bound (an oracle), percent (|error| <= 1.96 sigma; a calibrated sigma gives {:.0}-{:.0} % with 95 % probability):\n",
        100.0 * lo,
        100.0 * hi
    );
    table(&mut m, sums, |s, i| {
        format!("{} ({})", f(100.0 * s.coverage[i], 1), f(100.0 * s.coverage_bound[i], 1))
    });
    let _ = writeln!(
        m,
        "\nMean error / sigma, in brackets mean error / mean sigma (bias in units of the spread; standard error {}):\n",
        f(1.0 / (n as f64).sqrt(), 3)
    );
    table(&mut m, sums, |s, i| format!("{:+.3} ({:+.3})", s.mean_z[i], s.mean_over_mean[i]));
    m
}

/// The summary as JSON (`--json`).
fn summary_json(stem: &str, scene: &str, sums: &[Summary]) -> serde_json::Value {
    let nan_null = |v: f64| if v.is_finite() { json!(v) } else { serde_json::Value::Null };
    let levels: Vec<_> = sums
        .iter()
        .map(|s| {
            let q: serde_json::Map<String, serde_json::Value> = QUANTITIES
                .iter()
                .enumerate()
                .map(|(i, n)| {
                    (n.to_string(), json!({
                        "ratio": nan_null(s.ratio[i]),
                        "coverage": nan_null(s.coverage[i]),
                        "coverage_bound": nan_null(s.coverage_bound[i]),
                        "mean_error_over_sigma": nan_null(s.mean_z[i]),
                        "mean_error_over_mean_sigma": nan_null(s.mean_over_mean[i]),
                    }))
                })
                .collect();
            json!({"noise_px": s.noise_px, "adjustments": s.n, "failed_seeds": s.failed_seeds, "failed_adjustments": s.failed_draws, "quantities": q})
        })
        .collect();
    json!({"experiment": stem, "scene": scene, "draws_per_seed": DRAWS, "levels": levels})
}

/// The procedure's tuning flags, which the least squares alone does not have.
fn refuse_tuning(args: &ExperimentArgs) -> Result<()> {
    let given = [
        (args.depth_profile.is_some(), "--depth-profile"),
        (args.lone_depth_gate.is_some(), "--lone-depth-gate"),
        (args.angle_prior.is_some(), "--angle-prior"),
        (args.bootstrap.is_some(), "--bootstrap"),
        (args.encoder_noise != ENCODER_SIGMA_DEG, "--encoder-noise"),
        (args.rotation.is_some(), "--rotation"),
    ];
    if let Some((_, flag)) = given.iter().find(|(g, _)| *g) {
        bail!("{flag} does not apply to {NAME}, which runs the least squares alone from the truth");
    }
    Ok(())
}

/// Entry point of `headalign experiment ml-spread`.
pub fn run(args: &ExperimentArgs) -> Result<()> {
    refuse_tuning(args)?;
    let preset = Scenario::preset(&args.scene).map_err(|e| anyhow!("{e}"))?;
    let levels: Vec<f64> = if args.only.is_empty() { DEFAULT_NOISE_PX.to_vec() } else { args.only.clone() };
    if let Some(bad) = levels.iter().find(|n| !(n.is_finite() && **n > 0.0)) {
        bail!("--only: noise levels must be positive pixels, got {bad}");
    }
    let total = args.trials.unwrap_or(DEFAULT_TRIALS);
    if total == 0 {
        bail!("--trials must be at least 1");
    }
    let seeds = total.div_ceil(levels.len()).div_ceil(DRAWS);
    let stem = if args.scene == "default" { NAME.to_string() } else { format!("{NAME}-{}", args.scene) };
    std::fs::create_dir_all(&args.out).with_context(|| format!("cannot create {}", args.out.display()))?;
    let window = (args.image_border == Some(true)).then(|| {
        let [w, h] = preset.image_size.map(f64::from);
        [-0.5, -0.5, w - 0.5, h - 0.5]
    });
    let t0 = Instant::now();
    // The noise-free runs do not depend on the noise: one per seed serves every level.
    let cleans: Vec<(u64, Result<CleanSeed, String>)> = (0..seeds as u64)
        .into_par_iter()
        .map(|t| (args.seed + t, clean_seed(&preset, args.seed + t).map_err(|e| format!("{e:#}"))))
        .collect();
    let results: Vec<(f64, Vec<Row>)> =
        levels.iter().map(|&noise| (noise, run_level(&cleans, noise, args.seed, window))).collect();
    let seconds = t0.elapsed().as_secs_f64();
    let sums: Vec<Summary> = results.iter().map(|(noise, rows)| summarise(*noise, rows)).collect();
    write_csv(&args.out.join(format!("{stem}.csv")), &results)?;
    let mut md = markdown(&stem, &args.scene, seeds, args.seed, &sums, seconds);
    if window.is_some() {
        md = md.replacen(
            "\n\n",
            "\n\nImage border modelled in the adjustments (`--image-border on`: the measurement window is the whole image).\n\n",
            1,
        );
    }
    std::fs::write(args.out.join(format!("{stem}.md")), &md)
        .with_context(|| format!("cannot write {stem}.md"))?;
    use std::io::Write as _;
    let mut stdout = std::io::stdout();
    if args.json {
        let _ =
            writeln!(stdout, "{}", serde_json::to_string_pretty(&summary_json(&stem, &args.scene, &sums))?);
    } else {
        let _ = writeln!(stdout, "{md}");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two seeds, one draw level: every adjustment succeeds, the sums are finite, and the
    /// same seeds give the same rows whatever the batch split (the noise is drawn in order).
    #[test]
    fn small_run_is_finite_and_reproducible() {
        let preset = Scenario::default();
        let cleans: Vec<(u64, Result<CleanSeed, String>)> =
            (1..=2).map(|s| (s, clean_seed(&preset, s).map_err(|e| format!("{e:#}")))).collect();
        let rows = run_level(&cleans, 2.0, 1, None);
        assert_eq!(rows.len(), 2 * DRAWS);
        let again = run_level(&cleans, 2.0, 1, None);
        for (a, b) in rows.iter().zip(&again) {
            let (Ok(a), Ok(b)) = (&a.result, &b.result) else { panic!("failed adjustment") };
            for (p, q) in a.iter().zip(b) {
                assert_eq!(p.error.to_bits(), q.error.to_bits());
            }
        }
        let s = summarise(2.0, &rows);
        assert_eq!(s.n, 2 * DRAWS);
        assert!(s.ratio.iter().chain(&s.coverage).all(|v| v.is_finite()), "{:?}", s.ratio);
        // Errors of a few sigmas at most from the truth.
        assert!(s.mean_z.iter().all(|z| z.abs() < 4.0), "{:?}", s.mean_z);
    }
}
