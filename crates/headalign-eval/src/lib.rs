//! headalign-eval: the Monte-Carlo experiments of `headalign experiment <name>` (the
//! command line's subcommand calls [`run`] with its [`ExperimentArgs`]): the verge/tilt
//! procedure on the simulated head (paper section 5, figure 5), with the Cramer-Rao bound
//! ([`trial`]: the scoring of each trial against it) and the coverage of the reported
//! uncertainties.
//!
//! An experiment is a list of conditions (a swept parameter value `x`: noise in pixels,
//! point count, rotation in degrees or outlier fraction) times `trials` seeds. A *trial*
//! is one run of the procedure at one condition; `--trials N` is the total number of
//! trials of the experiment, split evenly over its conditions (`ceil(N / conditions)`
//! seeds, each run at every condition; so `fig5-verge-tilt --trials 100` is 20 seeds at
//! each of 5 noise levels). Seed index `t` uses seed `seed + t` for
//! every condition (common random numbers: the same head and scene at every noise level)
//! and, in `fig5-verge-tilt`, initial head position `t mod 3`. The trials of one seed run
//! in one rayon task and share one noise-free run, which gives the Cramer-Rao bound at
//! every noise level and is itself the noise-0 trial ([`trial`] module).
//!
//! `fig5-pan-tilt` (paper Figure 5 right, section 4) runs the robot stages instead
//! ([`pan`] module: verge/tilt, pan, steering, pan on the simulated robot) over three
//! groups of conditions (noise, largest initial pan, drive distance); it has no
//! Cramer-Rao bound (printed "-", the reason is in its summary), and its reported sigmas
//! (the last pan correction's, the steering zero's, the verge/tilt ones) get a coverage.
//! `coverage` runs the verge/tilt procedure at 0.5-3 px and adds `robot` conditions (1
//! and 3 px) that run the same robot trial, so that it covers every sigma headalign
//! reports in point mode, and a `three-view` condition (1 px): sessions of three views
//! (initial, +3 deg elevation, +3 deg pan; no vergence view) aligned offline as `align`
//! does, with nominal vergence axes; enough trials per condition (300) to tell a 90 % or
//! 98 % coverage from 95 %.
//!
//! Outputs in `--out DIR`: `<name>.csv` (every trial, failures included with their error
//! message), `<name>.png` and `<name>.svg` (RMS error against the parameter, with the
//! bound), `<name>.md` (summary tables: RMS per series, RMS / bound per reported
//! quantity, 95 % coverage). `all` runs every experiment and writes `results.md` beside
//! DIR with the paper's numbers and the bars.
//!
//! Each experiment's conditions, series and default trial count are defined in [`catalog`].
//! `lens` ([`lens`] module) runs the `calibrate` route with a lens model instead of the
//! verge/tilt procedure (its own runner, tables and plot); `all` runs it last. `check`
//! ([`check`] module) scores the targetless health check of a stereo calibration on
//! turned simulated rigs (its own runner; not in `all`).

// The experiments' docs link their private helpers (read with `cargo doc
// --document-private-items`).
#![allow(rustdoc::private_intra_doc_links)]

mod catalog;
pub mod check;
pub mod lens;
pub mod ml_spread;
pub mod pan;
pub mod planar;
pub mod plot;
pub mod stats;
pub mod trial;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use headalign::verge_tilt::{DepthProfile, ENCODER_SIGMA_DEG, EstimationOptions, LoneDepthGate};
use headalign_geometry::bootstrap::BootstrapOptions;
use headalign_geometry::bundle::AnglePrior;
use headalign_platform::Encoders;
use headalign_sim::Scenario;
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;
use serde_json::json;

use self::pan::{PAN_INDEX, ROBOT_QUANTITIES, run_pan_trial};
use self::plot::{Curve, write_plots};
use self::stats::{coverage, quantity_crb, quantity_rms, rms};
use self::trial::{CleanRun, RotationMode, SIGMA_QUANTITIES, TrialRecord, TrialSpec, run_trial};

/// Names accepted by `headalign experiment`.
pub const NAMES: [&str; 12] = [
    "fig5-verge-tilt",
    "fig5-pan-tilt",
    "calibration",
    "points",
    "rotation",
    "outliers",
    "coverage",
    "all",
    ml_spread::NAME,
    lens::NAME,
    planar::NAME,
    check::NAME,
];

/// Arguments of `headalign experiment`.
#[derive(Args, Debug)]
pub struct ExperimentArgs {
    /// Experiment: fig5-verge-tilt, fig5-pan-tilt, calibration, points, rotation, outliers,
    /// coverage, lens, or all; or ml-spread, planar, check (not in all).
    pub name: String,
    /// Total trials, split evenly over the experiment's conditions; default per
    /// experiment.
    // Seeds per condition: `ceil(trials / conditions)`, at least one (`run_one`).
    #[arg(long)]
    pub trials: Option<usize>,
    /// Rotation of the elevation and pan views of `lens`, and of every moved view of `planar`,
    /// degrees (default 3).
    #[arg(long)]
    pub rotation: Option<f64>,
    /// First seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Output directory.
    #[arg(long, default_value = "results")]
    pub out: PathBuf,
    /// Print a JSON summary on stdout instead of the Markdown table.
    #[arg(long)]
    pub json: bool,
    /// Run only the conditions whose swept value is in this comma-separated list (e.g.
    /// `--only 2,3`).
    // `--trials` is then split over the conditions kept.
    #[arg(long, value_delimiter = ',')]
    pub only: Vec<f64>,
    /// Scene preset of every condition: `default`, `paper`, `robot`, `wall` or `far` (as `demo --scene`);
    /// outputs of another scene than `default` are named `<experiment>-<scene>`.
    // `Scenario::preset`. `all` refuses it: it runs the default scene, then
    // `OTHER_SCENE_BARS` in the paper and robot scenes.
    #[arg(long, default_value = "default")]
    pub scene: String,
    /// Depth-scale profile of the reported covariance: `off`, `Z` (to Z sigmas of the
    /// depth scale) or `Z:MIN` (only when that sigma exceeds MIN).
    // `EstimationOptions::depth_profile`; unset: the library's default.
    #[arg(long, value_parser = parse_depth_profile)]
    pub depth_profile: Option<ProfileSetting>,
    /// Model the image border in the least squares: `on` or `off`.
    // `EstimationOptions::image_border`; unset: the library's default.
    #[arg(long, value_parser = parse_on_off)]
    pub image_border: Option<bool>,
    /// Depth test of points seen once by one camera: `off` or `Z` (the threshold in
    /// deviations).
    // `EstimationOptions::lone_depth_gate` (other fields `LoneDepthGate::DEFAULT`); unset:
    // the library's default.
    #[arg(long, value_parser = parse_lone_gate)]
    pub lone_depth_gate: Option<LoneSetting>,
    /// Standard deviation of the simulated encoder noise in the noisy trials, degrees
    /// (0: exact readings).
    // `Scenario::encoder_noise_deg`. Default `ENCODER_SIGMA_DEG`, the noise the estimate
    // and the bound assume; the noise-free run that gives the bound reads exactly.
    #[arg(long, value_parser = parse_encoder_noise, default_value_t = ENCODER_SIGMA_DEG)]
    pub encoder_noise: f64,
    /// Error model of the commanded angles in the bundle adjustment: `readings` (reading
    /// differences) or `independent`.
    // `BundleOptions::angle_prior`; unset: the library's default.
    #[arg(long, value_parser = parse_angle_prior)]
    pub angle_prior: Option<AnglePrior>,
    /// Bootstrap of the reported covariance: `off` or the number of replicates (at
    /// least 3).
    // `EstimationOptions::bootstrap`; unset: the library's default (off). Each noisy trial
    // then runs one more warm-started adjustment per replicate.
    #[arg(long, value_parser = parse_bootstrap)]
    pub bootstrap: Option<BootstrapSetting>,
}

/// A `--bootstrap` value: `None` is `off`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BootstrapSetting(pub Option<BootstrapOptions>);

/// Parse `off` or a replicate count, validated as [`EstimationOptions::validate`] does.
fn parse_bootstrap(v: &str) -> Result<BootstrapSetting, String> {
    if v == "off" {
        return Ok(BootstrapSetting(None));
    }
    crate::parse_replicates(v).map(|b| BootstrapSetting(Some(b)))
}

/// Parse a bootstrap replicate count (`--bootstrap` of `experiment` and `align`),
/// validated as [`EstimationOptions::validate`] does.
pub fn parse_replicates(v: &str) -> Result<BootstrapOptions, String> {
    let replicates = v.trim().parse::<usize>().map_err(|e| format!("'{v}': {e}"))?;
    let b = BootstrapOptions { replicates, ..BootstrapOptions::default() };
    EstimationOptions { bootstrap: Some(b), ..EstimationOptions::default() }
        .validate()
        .map_err(|e| e.to_string())?;
    Ok(b)
}

/// Parse `readings` / `independent`.
fn parse_angle_prior(v: &str) -> Result<AnglePrior, String> {
    match v {
        "readings" => Ok(AnglePrior::ReadingDifferences),
        "independent" => Ok(AnglePrior::Independent),
        other => Err(format!("expected 'readings' or 'independent', got '{other}'")),
    }
}

/// Parse a finite, non-negative encoder noise in degrees.
fn parse_encoder_noise(v: &str) -> Result<f64, String> {
    match v.trim().parse::<f64>() {
        Ok(x) if x.is_finite() && x >= 0.0 => Ok(x),
        _ => Err(format!("expected a finite encoder noise >= 0 in degrees, got '{v}'")),
    }
}

/// Parse `on` / `off`.
fn parse_on_off(v: &str) -> Result<bool, String> {
    match v {
        "on" => Ok(true),
        "off" => Ok(false),
        other => Err(format!("expected 'on' or 'off', got '{other}'")),
    }
}

/// The estimation settings an experiment run may change from the library's defaults.
#[derive(Clone, Copy, Debug)]
struct Tuning {
    depth_profile: Option<DepthProfile>,
    image_border: bool,
    lone_depth_gate: Option<LoneDepthGate>,
    encoder_noise_deg: f64,
    angle_prior: AnglePrior,
    bootstrap: Option<BootstrapOptions>,
}

/// A `--lone-depth-gate` value: `None` is `off`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoneSetting(pub Option<LoneDepthGate>);

/// Parse `off` or `Z`, validated as [`EstimationOptions::validate`] does.
fn parse_lone_gate(v: &str) -> Result<LoneSetting, String> {
    if v == "off" {
        return Ok(LoneSetting(None));
    }
    let z = v.trim().parse::<f64>().map_err(|e| format!("'{v}': {e}"))?;
    let g = LoneDepthGate { z, ..LoneDepthGate::DEFAULT };
    EstimationOptions { lone_depth_gate: Some(g), ..EstimationOptions::default() }
        .validate()
        .map_err(|e| e.to_string())?;
    Ok(LoneSetting(Some(g)))
}

/// A `--depth-profile` value: `None` is `off`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProfileSetting(pub Option<DepthProfile>);

/// Parse `off`, `Z` or `Z:MIN` (module docs of `--depth-profile`), validated as
/// [`EstimationOptions::validate`] does.
fn parse_depth_profile(v: &str) -> Result<ProfileSetting, String> {
    if v == "off" {
        return Ok(ProfileSetting(None));
    }
    let num = |t: &str| t.trim().parse::<f64>().map_err(|e| format!("'{t}': {e}"));
    let (z, min) = match v.split_once(':') {
        Some((z, m)) => (num(z)?, num(m)?),
        None => (num(v)?, DepthProfile::DEFAULT.min_sigma_log_depth),
    };
    let p = DepthProfile { z, min_sigma_log_depth: min };
    EstimationOptions { depth_profile: Some(p), ..EstimationOptions::default() }
        .validate()
        .map_err(|e| e.to_string())?;
    Ok(ProfileSetting(Some(p)))
}

/// One condition: a point of the swept parameter.
#[derive(Clone, Debug)]
struct Condition {
    /// Group ("fixed", "auto"): one plotted line set per group in the table; only the
    /// first group is plotted.
    group: &'static str,
    /// The swept value.
    x: f64,
    scenario: Scenario,
    rotation: RotationMode,
    /// Run the robot stages ([`pan`] module) in this condition even when the experiment
    /// is not a robot one.
    robot: bool,
}

type Extract = fn(&TrialRecord) -> f64;

/// A plotted series: signed error per trial and optionally its bound per trial.
struct Series {
    label: &'static str,
    value: Extract,
    crb: Option<Extract>,
}

struct Experiment {
    name: &'static str,
    title: &'static str,
    x_label: &'static str,
    y_label: &'static str,
    /// Trials of `--trials` when not given. The two grids that judge the ratio bar
    /// (`fig5-verge-tilt`, `calibration`) run 250 seeds per noise level: an RMS over `n`
    /// trials is known to `1 / sqrt(2 n)` (4.5 % at 250; 95 % interval of the ratio about
    /// +-9 %), against 13 % at the former 30 seeds, where single seeds made 1.24-1.40 of
    /// an estimator at 1.0-1.18 over 300 (docs/accuracy.md). 250 rather than 300 keeps
    /// `experiment all` near 15 min on an idle 2-core machine. `outliers`, where nothing
    /// is judged, runs 10 seeds.
    default_trials: usize,
    positions: Vec<Encoders>,
    conditions: Vec<Condition>,
    series: Vec<Series>,
    /// Run the robot stages after the verge/tilt procedure ([`pan`] module) instead of
    /// the verge/tilt procedure alone with its Cramer-Rao bound.
    robot: bool,
    /// Names of the quantities reported with a sigma, in record order.
    quantities: &'static [&'static str],
    /// Extra paragraph of the Markdown summary (empty: none).
    note: &'static str,
}

fn q_rel_pct(r: &TrialRecord, i: usize) -> f64 {
    r.quantities.get(i).map_or(f64::NAN, |q| 100.0 * (q.est - q.truth) / q.truth)
}
fn q_crb_pct(r: &TrialRecord, i: usize) -> f64 {
    r.quantities.get(i).map_or(f64::NAN, |q| 100.0 * q.crb / q.truth)
}
fn q_crb(r: &TrialRecord, i: usize) -> f64 {
    r.quantities.get(i).map_or(f64::NAN, |q| q.crb)
}

fn verge_left() -> Series {
    Series { label: "verge left (deg)", value: |r| r.verge_err_l_deg, crb: Some(|r| q_crb(r, 9)) }
}

fn elevation_left() -> Series {
    Series { label: "elevation left (deg)", value: |r| r.elev_err_l_deg, crb: Some(|r| q_crb(r, 8)) }
}

/// The paper's focal length: its cameras have a focal length `f` and an aspect ratio `a`
/// (its Figure 6), so `f` is our `fx` (`fy = a f`); the per-trial value
/// `sqrt((e_L^2 + e_R^2) / 2)` makes the RMS over trials the RMS pooled over both
/// cameras, and its bound is pooled the same way.
fn focal_pooled() -> Series {
    Series {
        label: "focal length f = fx, L/R pooled (%)",
        value: |r| (0.5 * (q_rel_pct(r, 0).powi(2) + q_rel_pct(r, 4).powi(2))).sqrt(),
        crb: Some(|r| (0.5 * (q_crb_pct(r, 0).powi(2) + q_crb_pct(r, 4).powi(2))).sqrt()),
    }
}

fn worst_focal() -> Series {
    Series { label: "focal length, worst of 4 (%)", value: |r| r.f_err_pct, crb: None }
}

/// Reconstruction error, RMS over points per trial (then RMS over trials).
fn recon_rms() -> Series {
    Series { label: "reconstruction, RMS over points (%)", value: |r| r.recon_err_pct, crb: None }
}

/// Reconstruction error, median over points per trial (then RMS over trials).
fn recon_median() -> Series {
    Series { label: "reconstruction, median over points (%)", value: |r| r.recon_median_pct, crb: None }
}

fn alignment_series() -> Vec<Series> {
    vec![
        verge_left(),
        Series { label: "verge right (deg)", value: |r| r.verge_err_r_deg, crb: Some(|r| q_crb(r, 10)) },
        elevation_left(),
        Series { label: "elevation right, excess (deg)", value: |r| r.elev_err_r_excess_deg, crb: None },
    ]
}

fn base(scene: &Scenario, noise: f64) -> Scenario {
    Scenario { noise_px: noise, ..scene.clone() }
}

fn fixed(x: f64, scenario: Scenario) -> Condition {
    Condition { group: "fixed", x, scenario, rotation: RotationMode::Fixed, robot: false }
}

/// Noise levels (pixels) of the `coverage` experiment's verge/tilt (`fixed`) group.
const COVERAGE_FIXED_PX: [f64; 4] = [0.5, 1.0, 2.0, 3.0];
/// Noise levels (pixels) of the `coverage` experiment's `robot` group (robot stages).
const COVERAGE_ROBOT_PX: [f64; 2] = [1.0, 3.0];
/// Noise levels (pixels) of the `coverage` experiment's `three-view` group (offline
/// sessions without a vergence view, 10 % outliers as every condition).
const COVERAGE_THREE_VIEW_PX: [f64; 1] = [1.0];
/// Default trials per condition of `coverage`: with 300 trials a calibrated 95 % interval
/// covers 92.5-97.5 % with 95 % probability (binomial standard deviation 1.3 %), so a
/// coverage of 90 % (or 98 %) is told from 95 % by about 4 (or 2.4) standard deviations.
const COVERAGE_TRIALS: usize = 300;

/// Noise levels (pixels) of the figure 5 noise sweeps.
const NOISE_GRID: [f64; 5] = [0.0, 0.5, 1.0, 2.0, 3.0];

/// Experiment `name` with every condition in `scene` (a preset, any seed).
fn experiment(name: &str, scene: &Scenario) -> Result<Experiment> {
    Ok(match name {
        "fig5-verge-tilt" => catalog::fig5_verge_tilt(scene),
        "calibration" => catalog::calibration(scene),
        "points" => catalog::points(scene),
        "rotation" => catalog::rotation(scene),
        "outliers" => catalog::outliers(scene),
        "coverage" => catalog::coverage(scene),
        "fig5-pan-tilt" => catalog::fig5_pan_tilt(scene),
        other => bail!("unknown experiment '{other}'; expected one of {}", NAMES.join(", ")),
    })
}

/// The outcome of one trial slot.
struct Outcome {
    condition: usize,
    trial: usize,
    seed: u64,
    result: Result<TrialRecord, String>,
}

fn spec(exp: &Experiment, c: &Condition, trial: usize, seed: u64, tuning: Tuning) -> TrialSpec {
    let initial = exp.positions.get(trial % exp.positions.len().max(1)).copied().unwrap_or_default();
    TrialSpec {
        scenario: Scenario { seed, encoder_noise_deg: tuning.encoder_noise_deg, ..c.scenario.clone() },
        initial,
        rotation: c.rotation,
        depth_profile: tuning.depth_profile,
        image_border: tuning.image_border,
        lone_depth_gate: tuning.lone_depth_gate,
        angle_prior: tuning.angle_prior,
        bootstrap: tuning.bootstrap,
    }
}

/// All trials of one seed: conditions that differ only in noise share one noise-free run.
fn run_seed(exp: &Experiment, trial: usize, seed: u64, tuning: Tuning) -> Vec<Outcome> {
    let mut out = Vec::new();
    let mut clean: Vec<(TrialSpec, Result<CleanRun, String>)> = Vec::new();
    for (ci, c) in exp.conditions.iter().enumerate() {
        if exp.robot || c.robot {
            let result = run_pan_trial(&spec(exp, c, trial, seed, tuning)).map_err(|e| format!("{e:#}"));
            out.push(Outcome { condition: ci, trial, seed, result });
            continue;
        }
        let s = spec(exp, c, trial, seed, tuning);
        let mut key = s.clone();
        key.scenario.noise_px = 0.0; // a key only: `CleanRun::new` sets its own tiny noise
        let idx = match clean.iter().position(|(k, _)| {
            k.scenario == key.scenario && k.initial == key.initial && k.rotation == key.rotation
        }) {
            Some(i) => i,
            None => {
                let run = CleanRun::new(&key).map_err(|e| format!("{e:#}"));
                clean.push((key, run));
                clean.len() - 1
            }
        };
        let result = match clean.get(idx).map(|c| &c.1) {
            Some(Ok(run)) => {
                if s.scenario.noise_px == 0.0 {
                    run.record().map_err(|e| format!("{e:#}"))
                } else {
                    let crb = run.crb_sigmas(s.scenario.noise_px).ok();
                    run_trial(&s, crb.as_deref()).map_err(|e| format!("{e:#}"))
                }
            }
            // No bound without the noise-free run; the trial itself still runs.
            _ => run_trial(&s, None).map_err(|e| format!("{e:#}")),
        };
        out.push(Outcome { condition: ci, trial, seed, result });
    }
    out
}

fn run_experiment(exp: &Experiment, trials: usize, seed: u64, tuning: Tuning) -> Vec<Outcome> {
    let bar = ProgressBar::new((trials * exp.conditions.len()) as u64);
    if let Ok(style) =
        ProgressStyle::with_template("{prefix:>16} [{bar:30}] {pos}/{len} trials {elapsed}<{eta}")
    {
        bar.set_style(style.progress_chars("=> "));
    }
    bar.set_prefix(exp.name);
    let mut all: Vec<Outcome> = (0..trials)
        .into_par_iter()
        .flat_map_iter(|t| {
            let v = run_seed(exp, t, seed + t as u64, tuning);
            bar.inc(v.len() as u64);
            v
        })
        .collect();
    bar.finish_and_clear();
    all.sort_by_key(|o| (o.condition, o.trial));
    all
}

/// Per-condition summary.
struct ConditionSummary {
    group: &'static str,
    x: f64,
    ok: usize,
    total: usize,
    /// (rms, crb rms) per series.
    series: Vec<(f64, f64)>,
    /// (rms, crb rms) per reported quantity.
    quantities: Vec<(f64, f64)>,
    /// (coverage, n) per reported quantity.
    coverage: Vec<(f64, usize)>,
    mean_rotation_deg: f64,
}

fn summarise(exp: &Experiment, outcomes: &[Outcome]) -> Vec<ConditionSummary> {
    exp.conditions
        .iter()
        .enumerate()
        .map(|(ci, c)| {
            let mine: Vec<&Outcome> = outcomes.iter().filter(|o| o.condition == ci).collect();
            let recs: Vec<&TrialRecord> = mine.iter().filter_map(|o| o.result.as_ref().ok()).collect();
            let series = exp
                .series
                .iter()
                .map(|s| {
                    (
                        rms(recs.iter().map(|r| (s.value)(r))),
                        s.crb.map_or(f64::NAN, |f| rms(recs.iter().map(|r| f(r)))),
                    )
                })
                .collect();
            let quantities =
                (0..exp.quantities.len()).map(|i| (quantity_rms(&recs, i), quantity_crb(&recs, i))).collect();
            // Noise-free trials: errors and sigmas are both at the solver's tolerance, so a
            // coverage would count rounding, not statistics ("-").
            let coverage = (0..exp.quantities.len())
                .map(|i| {
                    if c.scenario.noise_px > 0.0 {
                        coverage(recs.iter().filter_map(|r| r.quantities.get(i)))
                    } else {
                        (f64::NAN, 0)
                    }
                })
                .collect();
            // NaN (printed "-") when no trial succeeded.
            let n = if recs.is_empty() { f64::NAN } else { recs.len() as f64 };
            ConditionSummary {
                group: c.group,
                x: c.x,
                ok: recs.len(),
                total: mine.len(),
                series,
                quantities,
                coverage,
                mean_rotation_deg: recs.iter().map(|r| r.rotation_deg).sum::<f64>() / n,
            }
        })
        .collect()
}

fn f(v: f64, digits: usize) -> String {
    if v.is_finite() { format!("{v:.digits$}") } else { "-".into() }
}

fn write_csv(path: &Path, exp: &Experiment, outcomes: &[Outcome]) -> Result<()> {
    let mut s = String::from(
        "experiment,group,x,trial,seed,noise_px,points,outlier_fraction,rotation_mode,ok,error,rotation_deg,verge_err_l_deg,verge_err_r_deg,elev_err_l_deg,elev_err_r_deg,elev_err_r_excess_deg,f_err_pct,aspect_err_pct,pp_err_pct,recon_err_pct,recon_median_pct,pan_err_deg,seconds",
    );
    for q in exp.quantities {
        for p in ["est", "truth", "sigma", "crb"] {
            let _ = write!(s, ",{q}.{p}");
        }
    }
    s.push('\n');
    for o in outcomes {
        let Some(c) = exp.conditions.get(o.condition) else { continue };
        let sc = &c.scenario;
        let _ = write!(
            s,
            "{},{},{},{},{},{},{},{},{:?},",
            exp.name, c.group, c.x, o.trial, o.seed, sc.noise_px, sc.points, sc.outlier_fraction, c.rotation
        );
        match &o.result {
            Ok(r) => {
                let _ = write!(
                    s,
                    "true,,{},{},{},{},{},{},{},{},{},{},{},{},{:.4}",
                    r.rotation_deg,
                    r.verge_err_l_deg,
                    r.verge_err_r_deg,
                    r.elev_err_l_deg,
                    r.elev_err_r_deg,
                    r.elev_err_r_excess_deg,
                    r.f_err_pct,
                    r.aspect_err_pct,
                    r.pp_err_pct,
                    r.recon_err_pct,
                    r.recon_median_pct,
                    r.pan_err_deg,
                    r.seconds
                );
                // One column group per quantity of the experiment (a verge/tilt trial in
                // `coverage` has no robot quantities: NaN).
                for i in 0..exp.quantities.len() {
                    match r.quantities.get(i) {
                        Some(q) => {
                            let _ = write!(s, ",{},{},{},{}", q.est, q.truth, q.sigma, q.crb);
                        }
                        None => s.push_str(",NaN,NaN,NaN,NaN"),
                    }
                }
            }
            Err(e) => {
                let msg = e.replace([',', '\n', '"'], ";");
                let _ = write!(s, "false,{msg}");
                s.push_str(&",".repeat(13 + 4 * exp.quantities.len()));
            }
        }
        s.push('\n');
    }
    std::fs::write(path, s).with_context(|| format!("cannot write {}", path.display()))
}

fn markdown(exp: &Experiment, trials: usize, seed: u64, sums: &[ConditionSummary], seconds: f64) -> String {
    let mut m = String::new();
    let _ = writeln!(m, "## {} — {}\n", exp.name, exp.title);
    let _ = writeln!(
        m,
        "{trials} trials per condition (seeds {seed}-{}), {} position(s), {:.0} s. RMS over successful trials{}.\n",
        seed + trials as u64 - 1,
        exp.positions.len(),
        seconds,
        if exp.robot {
            ""
        } else {
            "; in brackets the Cramer-Rao bound (RMS over trials of the covariance-predicted sigma at the truth)"
        }
    );
    if !exp.note.is_empty() {
        let _ = writeln!(m, "{}\n", exp.note);
    }
    let mut head = format!("| group | {} | ok | rotation (deg) |", exp.x_label);
    let mut rule = String::from("|---|---|---|---|");
    for s in &exp.series {
        let _ = write!(head, " {} |", s.label);
        rule.push_str("---|");
    }
    let _ = writeln!(m, "{head}\n{rule}");
    for c in sums {
        let _ = write!(m, "| {} | {} | {}/{} | {} |", c.group, c.x, c.ok, c.total, f(c.mean_rotation_deg, 1));
        for (s, (v, b)) in exp.series.iter().zip(&c.series) {
            if s.crb.is_some() {
                let _ = write!(m, " {} ({}) |", f(*v, 3), f(*b, 3));
            } else {
                let _ = write!(m, " {} |", f(*v, 3));
            }
        }
        m.push('\n');
    }
    let n_ok = sums.iter().map(|c| c.ok).max().unwrap_or(0);
    let mut head = format!("| group | {} |", exp.x_label);
    let mut rule = String::from("|---|---|");
    for q in exp.quantities {
        let _ = write!(head, " {q} |");
        rule.push_str("---|");
    }
    if !exp.robot {
        let (lo, hi) = stats::ratio_interval(n_ok);
        let _ = writeln!(
            m,
            "\nRMS error / Cramer-Rao bound per reported quantity (1.00 = efficient). With {n_ok} trials an efficient estimator's ratio lies in [{lo:.2}, {hi:.2}] with 95 % probability (chi-square with n degrees of freedom).\n"
        );
        let _ = writeln!(m, "{head}\n{rule}");
        for c in sums {
            let _ = write!(m, "| {} | {} |", c.group, c.x);
            for (v, b) in &c.quantities {
                let _ = write!(m, " {} |", f(v / b, 2));
            }
            m.push('\n');
        }
    }
    let _ = writeln!(
        m,
        "\n95 % coverage of the reported sigmas (fraction of trials with |est - truth| <= 1.96 sigma; with {n_ok} trials a calibrated sigma gives {:.0}-{:.0} % with 95 % probability; '-' at noise 0):\n",
        100.0 * stats::coverage_interval(n_ok).0,
        100.0 * stats::coverage_interval(n_ok).1
    );
    let _ = writeln!(m, "{head}\n{rule}");
    for c in sums {
        let _ = write!(m, "| {} | {} |", c.group, c.x);
        for (v, _) in &c.coverage {
            let _ = write!(m, " {} |", f(100.0 * v, 0));
        }
        m.push('\n');
    }
    let _ = writeln!(m, "\n![{}]({}.png)\n", exp.name, exp.name);
    m
}

fn curves(exp: &Experiment, sums: &[ConditionSummary]) -> Vec<Curve> {
    let first = sums.first().map_or("fixed", |s| s.group);
    let plotted: Vec<&ConditionSummary> = sums.iter().filter(|s| s.group == first).collect();
    let mut out = Vec::new();
    for (i, s) in exp.series.iter().enumerate() {
        out.push(Curve {
            label: s.label.to_string(),
            points: plotted.iter().map(|c| (c.x, c.series.get(i).map_or(f64::NAN, |v| v.0))).collect(),
            colour: i,
            bound: false,
        });
        if s.crb.is_some() {
            out.push(Curve {
                label: format!("{} bound", s.label),
                points: plotted.iter().map(|c| (c.x, c.series.get(i).map_or(f64::NAN, |v| v.1))).collect(),
                colour: i,
                bound: true,
            });
        }
    }
    out
}

/// What one experiment produced, for `all`'s report.
struct Produced {
    name: &'static str,
    /// Scene preset the experiment ran in.
    scene: &'static str,
    /// Output file stem (`name`, or `name-scene` for a non-default scene).
    stem: String,
    markdown: String,
    sums: Vec<ConditionSummary>,
    series_labels: Vec<&'static str>,
    quantities: &'static [&'static str],
}

/// Which trials [`run_one`] runs: the scene preset, the swept values kept (empty: all)
/// and the seeds per condition (`None`: `--trials` or the experiment's default, split over
/// the conditions kept).
struct Selection<'a> {
    scene: &'static str,
    only: &'a [f64],
    seeds: Option<usize>,
}

/// The `&'static` name of a scene preset (rejects unknown names with the list).
fn scene_name(name: &str) -> Result<&'static str> {
    Scenario::PRESETS
        .iter()
        .copied()
        .find(|p| *p == name)
        .map_or_else(|| bail!("unknown scene '{name}'; expected one of {}", Scenario::PRESETS.join(", ")), Ok)
}

fn run_one(name: &str, args: &ExperimentArgs, sel: &Selection<'_>) -> Result<Produced> {
    let scene = Scenario::preset(sel.scene).map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut exp = experiment(name, &scene)?;
    if !sel.only.is_empty() {
        exp.conditions.retain(|c| sel.only.iter().any(|x| (x - c.x).abs() <= 1e-9 * x.abs().max(1.0)));
        if exp.conditions.is_empty() {
            bail!("--only {:?} matches no condition of experiment '{}'", sel.only, exp.name);
        }
    }
    let trials = match sel.seeds {
        Some(n) => n,
        None => {
            let total = args.trials.unwrap_or(exp.default_trials);
            if total == 0 {
                bail!("--trials must be at least 1");
            }
            total.div_ceil(exp.conditions.len().max(1))
        }
    };
    // Files of a non-default scene: `<experiment>-<scene>`.
    let stem =
        if sel.scene == "default" { exp.name.to_string() } else { format!("{}-{}", exp.name, sel.scene) };
    std::fs::create_dir_all(&args.out).with_context(|| format!("cannot create {}", args.out.display()))?;
    let t0 = Instant::now();
    let profile = args.depth_profile.map_or(EstimationOptions::default().depth_profile, |p| p.0);
    let image_border = args.image_border.unwrap_or(EstimationOptions::default().image_border);
    let lone_depth_gate = args.lone_depth_gate.map_or(EstimationOptions::default().lone_depth_gate, |g| g.0);
    let tuning = Tuning {
        depth_profile: profile,
        image_border,
        lone_depth_gate,
        encoder_noise_deg: args.encoder_noise,
        angle_prior: args.angle_prior.unwrap_or(EstimationOptions::default().bundle.angle_prior),
        bootstrap: args.bootstrap.map_or(EstimationOptions::default().bootstrap, |b| b.0),
    };
    let outcomes = run_experiment(&exp, trials, args.seed, tuning);
    let seconds = t0.elapsed().as_secs_f64();
    let sums = summarise(&exp, &outcomes);
    write_csv(&args.out.join(format!("{stem}.csv")), &exp, &outcomes)?;
    write_plots(&args.out.join(&stem), exp.title, exp.x_label, exp.y_label, &curves(&exp, &sums))?;
    let mut md = markdown(&exp, trials, args.seed, &sums, seconds);
    if sel.scene != "default" {
        md = md
            .replacen(&format!("## {} — ", exp.name), &format!("## {stem} — scene `{}`: ", sel.scene), 1)
            .replace(&format!("]({}.png)", exp.name), &format!("]({stem}.png)"));
    }
    // The simulated encoder noise and the settings changed from the library's defaults,
    // each a line after the heading (the last one given comes first).
    let mut settings: Vec<String> = Vec::new();
    if args.depth_profile.is_some() {
        let how = profile.map_or("off".to_string(), |p| {
            format!("z = {}, only when sigma_s > {}", p.z, p.min_sigma_log_depth)
        });
        settings.push(format!("Depth-scale profile of the sigmas (`--depth-profile`): {how}."));
    }
    if let Some(b) = args.bootstrap {
        let how = b.0.map_or("off".to_string(), |b| format!("{} replicates", b.replicates));
        settings.push(format!("Bootstrap of the sigmas over point tracks (`--bootstrap`): {how}."));
    }
    if let Some(on) = args.image_border {
        let how = if on { "on" } else { "off" };
        settings.push(format!("Image border modelled in the least squares (`--image-border`): {how}."));
    }
    if args.encoder_noise == ENCODER_SIGMA_DEG {
        settings.push(format!(
            "Encoder readings with Gaussian noise of {} deg (`--encoder-noise`), as the estimate's angle prior assumes.",
            args.encoder_noise
        ));
    } else {
        settings.push(format!(
            "Encoder readings with Gaussian noise of {} deg (`--encoder-noise`; the estimate's angle prior assumes {ENCODER_SIGMA_DEG} deg).",
            args.encoder_noise
        ));
    }
    if let Some(model) = args.angle_prior {
        let how = match model {
            AnglePrior::ReadingDifferences => "reading differences (the shared reference reading modelled)",
            AnglePrior::Independent => "independent errors",
        };
        settings.push(format!("Error model of the commanded angles (`--angle-prior`): {how}."));
    }
    if args.lone_depth_gate.is_some() {
        let how = lone_depth_gate.map_or("off".to_string(), |g| format!("z = {}", g.z));
        settings.push(format!("Depth test of points seen once by a camera (`--lone-depth-gate`): {how}."));
    }
    for line in settings {
        md = md.replacen("\n\n", &format!("\n\n{line}\n\n"), 1);
    }
    std::fs::write(args.out.join(format!("{stem}.md")), &md)
        .with_context(|| format!("cannot write {stem}.md"))?;
    Ok(Produced {
        name: exp.name,
        scene: sel.scene,
        stem,
        markdown: md,
        sums,
        series_labels: exp.series.iter().map(|s| s.label).collect(),
        quantities: exp.quantities,
    })
}

fn summary_json(p: &Produced) -> serde_json::Value {
    let conds: Vec<_> = p
        .sums
        .iter()
        .map(|c| {
            let series: serde_json::Map<String, serde_json::Value> = p
                .series_labels
                .iter()
                .zip(&c.series)
                .map(|(l, (v, b))| (l.to_string(), json!({"rms": nan_null(*v), "crb": nan_null(*b)})))
                .collect();
            let quantities: serde_json::Map<String, serde_json::Value> = p
                .quantities
                .iter()
                .zip(c.quantities.iter().zip(&c.coverage))
                .map(|(n, ((v, b), (cov, k)))| {
                    (n.to_string(), json!({"rms": nan_null(*v), "crb": nan_null(*b), "coverage": nan_null(*cov), "n": k}))
                })
                .collect();
            json!({"group": c.group, "x": c.x, "ok": c.ok, "total": c.total, "series": series, "quantities": quantities})
        })
        .collect();
    json!({"experiment": p.name, "scene": p.scene, "conditions": conds})
}

fn nan_null(v: f64) -> serde_json::Value {
    if v.is_finite() { json!(v) } else { serde_json::Value::Null }
}

/// (scene, experiment, swept value) that `all` also runs outside the default scene: the
/// focal length bar at 3 px and the 50-point bars, in the paper-like scene
/// (`Scenario::paper_lab`) and the robot's (`Scenario::robot_room`). The paper does not
/// give its scene, and the bounds of these bars depend on the points' depth spread.
const OTHER_SCENE_BARS: [(&str, &str, f64); 4] = [
    ("paper", "calibration", 3.0),
    ("paper", "points", 50.0),
    ("robot", "calibration", 3.0),
    ("robot", "points", 50.0),
];

/// Entry point of `headalign experiment`.
pub fn run(args: &ExperimentArgs) -> Result<()> {
    if args.rotation.is_some() && args.name != lens::NAME && args.name != planar::NAME {
        bail!("--rotation applies to the lens and planar experiments only");
    }
    if args.name == ml_spread::NAME {
        return ml_spread::run(args);
    }
    if args.name == lens::NAME {
        return lens::run(args);
    }
    if args.name == planar::NAME {
        return planar::run(args);
    }
    if args.name == check::NAME {
        return check::run(args);
    }
    let scene = scene_name(&args.scene)?;
    if args.name == "all" && scene != "default" {
        bail!(
            "`experiment all` runs the default scene and the bars in the paper-like and robot scenes itself; --scene is for single experiments"
        );
    }
    let names: Vec<&str> = if args.name == "all" {
        NAMES
            .iter()
            .copied()
            .filter(|n| {
                *n != "all"
                    && *n != ml_spread::NAME
                    && *n != lens::NAME
                    && *n != planar::NAME
                    && *n != check::NAME
            })
            .collect()
    } else {
        experiment(&args.name, &Scenario::default())?;
        vec![args.name.as_str()]
    };
    let mut produced = Vec::new();
    let sel = Selection { scene, only: &args.only, seeds: None };
    for n in names {
        produced.push(run_one(n, args, &sel)?);
    }
    if args.name == "all" {
        // The bars' conditions again in the other scenes, with as many seeds per
        // condition as the default run used.
        for (scene, n, x) in OTHER_SCENE_BARS {
            let seeds = produced.iter().find(|p| p.name == n).map(|p| p.sums.iter().map(|c| c.total).max());
            let sel = Selection { scene, only: &[x], seeds: seeds.flatten() };
            produced.push(run_one(n, args, &sel)?);
        }
    }
    if args.name == "all" {
        // The lens experiment (its own runner: the calibrate route), after the others.
        let (stem, markdown) = lens::run_for_all(args)?;
        produced.push(Produced {
            name: lens::NAME,
            scene: "default",
            stem,
            markdown,
            sums: Vec::new(),
            series_labels: Vec::new(),
            quantities: &[],
        });
        let path = results_path(&args.out);
        // The planar section is not regenerated here (`planar` module docs), nor the timing
        // of `calibrate` (`cargo bench -p headalign --bench calibrate`): kept as they are.
        let old = std::fs::read_to_string(&path).ok();
        let kept = old.as_deref().and_then(planar::kept_section);
        let timing = old.as_deref().and_then(|o| planar::section(o, TIMING_HEADING));
        let mut md = report::results_md(&produced, &args.out);
        for section in [kept, timing].into_iter().flatten() {
            md = format!("{}\n\n{section}", md.trim_end());
        }
        std::fs::write(&path, md).with_context(|| format!("cannot write {}", path.display()))?;
    }
    use std::io::Write as _;
    let mut stdout = std::io::stdout();
    if args.json {
        let v: Vec<_> = produced.iter().map(summary_json).collect();
        let _ = writeln!(stdout, "{}", serde_json::to_string_pretty(&v)?);
    } else {
        for p in &produced {
            let _ = writeln!(stdout, "{}", p.markdown);
        }
    }
    Ok(())
}

/// The heading of the section of `results.md` that `cargo bench -p headalign --bench
/// calibrate` fills (kept when `all` regenerates the file).
const TIMING_HEADING: &str = "## Timing of `calibrate`";

/// `results.md` beside the output directory (`docs/results` -> `docs/results.md`).
fn results_path(out: &Path) -> PathBuf {
    let name = out.file_name().map_or_else(|| "results".into(), |n| n.to_string_lossy().into_owned());
    out.with_file_name(format!("{name}.md"))
}

mod report;

#[cfg(test)]
mod tests {
    use super::*;

    /// `results.md` rows of the bars in the three scenes: the 50-point rows of the fixed and
    /// the auto group, each with its bound, and the scene named (one seed, 50 points).
    #[test]
    fn bar_rows_name_their_scene_and_bound() {
        let args = ExperimentArgs {
            name: "points".into(),
            trials: None,
            rotation: None,
            seed: 3,
            out: std::env::temp_dir().join(format!("headalign-scene-rows-{}", std::process::id())),
            json: false,
            only: vec![],
            scene: "default".into(),
            depth_profile: None,
            image_border: None,
            lone_depth_gate: None,
            encoder_noise: 0.0,
            angle_prior: None,
            bootstrap: None,
        };
        let mut ps = Vec::new();
        for scene in ["default", "paper", "robot"] {
            let sel = Selection { scene, only: &[50.0], seeds: Some(1) };
            ps.push(run_one("points", &args, &sel).unwrap());
        }
        let md = report::results_md(&ps, &args.out);
        for words in [
            "default scene (points 1.5-6 m)",
            "paper-like scene (`--scene paper`",
            "robot scene (`--scene robot`",
        ] {
            for rot in ["3 deg rotations", "rotations chosen by the procedure"] {
                let row = md
                    .lines()
                    .find(|l| l.contains(words) && l.contains(rot) && l.contains("elevation error"))
                    .unwrap_or_else(|| panic!("no row for {words} / {rot} in {md}"));
                assert!(row.contains("1/1 trials succeeded; bound 0."), "{row}");
            }
        }
        assert!(md.contains("](results/points-paper.png)") || md.contains("points-paper.png)"), "{md}");
        assert!(scene_name("moon").is_err());
    }

    /// `--depth-profile`: `off`, `Z` (the default threshold), `Z:MIN`; bad values are
    /// clean errors, not panics.
    /// `--image-border`: `on` or `off`, anything else is an error.
    #[test]
    fn image_border_values_parse() {
        assert_eq!(parse_on_off("on"), Ok(true));
        assert_eq!(parse_on_off("off"), Ok(false));
        assert!(parse_on_off("yes").is_err() && parse_on_off("").is_err());
    }

    /// `--lone-depth-gate`: `off` or a positive threshold; bad values are clean errors.
    #[test]
    fn lone_gate_values_parse() {
        assert_eq!(parse_lone_gate("off"), Ok(LoneSetting(None)));
        assert_eq!(
            parse_lone_gate("3"),
            Ok(LoneSetting(Some(LoneDepthGate { z: 3.0, ..LoneDepthGate::DEFAULT })))
        );
        for bad in ["0", "-1", "on", "NaN", ""] {
            assert!(parse_lone_gate(bad).is_err(), "{bad}");
        }
        assert_eq!(parse_encoder_noise("0.01"), Ok(0.01));
        for bad in ["-0.01", "inf", "x", ""] {
            assert!(parse_encoder_noise(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn bootstrap_values_parse() {
        assert_eq!(parse_bootstrap("off"), Ok(BootstrapSetting(None)));
        let b = parse_bootstrap("40").unwrap().0.unwrap();
        assert_eq!(b.replicates, 40);
        for bad in ["2", "-1", "x", ""] {
            assert!(parse_bootstrap(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn depth_profile_values_parse() {
        assert_eq!(parse_depth_profile("off"), Ok(ProfileSetting(None)));
        let d = DepthProfile::DEFAULT.min_sigma_log_depth;
        assert_eq!(
            parse_depth_profile("1.5"),
            Ok(ProfileSetting(Some(DepthProfile { z: 1.5, min_sigma_log_depth: d })))
        );
        assert_eq!(
            parse_depth_profile("1:0.2"),
            Ok(ProfileSetting(Some(DepthProfile { z: 1.0, min_sigma_log_depth: 0.2 })))
        );
        for bad in ["0", "-1", "abc", "1:-0.1", "1:x", "NaN", ""] {
            assert!(parse_depth_profile(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn unknown_is_a_clean_error() {
        let e = experiment("nope", &Scenario::default()).err().map(|e| e.to_string()).unwrap_or_default();
        assert!(e.contains("unknown experiment"), "{e}");
        assert_eq!(results_path(Path::new("docs/results")), Path::new("docs/results.md"));
    }

    /// The sections `all` keeps when it regenerates `results.md` are found in the
    /// repository's own file: the planar one and the timing of `calibrate`, each up to the
    /// next heading.
    #[test]
    fn kept_sections_are_found_in_results_md() {
        let md = include_str!("../../../docs/results.md");
        assert!(planar::kept_section(md).is_some_and(|s| s.starts_with("## planar")));
        let timing = planar::section(md, TIMING_HEADING).unwrap_or_default();
        assert!(timing.starts_with(TIMING_HEADING) && timing.contains("--bench calibrate"), "{timing}");
    }
}
