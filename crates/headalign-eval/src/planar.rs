//! `headalign experiment planar`: the planar route ([`headalign::facing_plane`], paper section
//! 3.3) in the `wall` and `far` scenes against image noise, beside the general route in
//! the default room.
//!
//! A trial: the simulated head of the scene (seed `seed + t`, the noise level, 10 %
//! outliers, encoder noise `--encoder-noise`), the procedure's views (reference,
//! elevation and pan +-r, both vergences +r; `--rotation` r degrees, default the
//! procedure's 3 deg: [`procedure_options`]) captured in point mode, the scene
//! detection, the planar estimate, the aligned readings ([`solve_alignment_axes`]) and
//! their sigmas ([`headalign::facing_plane::alignment_sigmas`] plus the reading noise). The
//! general scene runs [`VergeTiltRun::run`] (the general route, no detection), at 1 px
//! only (it costs some ten times a planar trial). Errors: aligned readings (elevation,
//! left and right vergence) minus the simulator's `aligned_encoders`, degrees.
//!
//! Summary per scene and noise: RMS error of each reading, the RMS of the reported sigmas
//! (the planar model's own bound: its covariance at the estimate, which at these noise
//! levels is its covariance at the truth to first order), their ratio, and the 95 %
//! coverage (`|error| <= 1.96 sigma`), and beside them the Cramér-Rao bound at the truth:
//! the planar model's covariance ([`PlanarOptions::covariance_sigma_px`] at the simulated
//! noise, no profile) at the fit of each view's exact observations ([`crb_views`]: the
//! simulator's noise-free pixels of the tracks whose noisy observation is no outlier,
//! the noisy encoder readings as the angle priors), propagated to the readings as the
//! reported sigmas are. `--only` picks noise levels (any, in pixels), `--scene wall` or
//! `far` one scene (and no general route). Not run by `all` (400 planar trials at the
//! default, and 200 wall trials at 1 px take 9-17 min on a loaded 2-core machine); `all`
//! keeps the planar section of the `results.md` it regenerates ([`kept_section`]).
//! `planar.csv` has one row per trial: the errors, sigmas and bounds, and per camera the
//! plane test's cost rise, the fitted plane's largest displacement of a view (pixels) and
//! the profile's widening (1: not profiled), which show where the normal was profiled.

use std::fmt::Write as _;

use anyhow::{Context, Result};
use headalign::alignment::solve_alignment_axes;
use headalign::facing_plane::{PlanarOptions, SceneKind, alignment_sigmas, detect_scene, estimate_planar};
use headalign::observations::View;
use headalign::procedure::{VergeTiltOptions, VergeTiltRun, capture_plan};
use headalign::verge_tilt::EstimationOptions;
use headalign_platform::{Encoders, StereoCapture, StereoHead, TrackObservation};
use headalign_sim::{Scenario, SimulatedHead};
use rayon::prelude::*;

use super::ExperimentArgs;
use super::stats::mean_and_standard_error;

/// The experiment's name.
pub const NAME: &str = "planar";

/// Noise levels, pixels.
const NOISE_PX: [f64; 4] = [0.0, 0.5, 1.0, 2.0];

/// Default trials per (scene, noise) condition.
const DEFAULT_TRIALS: usize = 50;

/// Largest `--rotation`, degrees (the lens experiment's limit).
const MAX_ROTATION_DEG: f64 = 30.0;

/// The rotation of every moved view, degrees: `--rotation`, or the verge/tilt procedure's
/// default `rotation_deg` (3); in (0, [`MAX_ROTATION_DEG`]].
fn rotation_deg(rotation: Option<f64>) -> Result<f64> {
    let r = rotation.unwrap_or(VergeTiltOptions::default().rotation_deg);
    if !(r.is_finite() && r > 0.0 && r <= MAX_ROTATION_DEG) {
        anyhow::bail!("--rotation must be in (0, {MAX_ROTATION_DEG}] degrees, got {r}");
    }
    Ok(r)
}

/// The procedure's options of every trial (planar and general route): the elevation and
/// pan views (`rotation_deg`) and the vergence view (`verge_rotation_deg`, both vergences)
/// turned by `rotation` degrees, as the procedure's automatic choice turns them when the
/// scene allows ([`headalign::procedure::AutoRotation::choose_verge`]); the rest default.
/// At the default 3 deg these are the default options.
fn procedure_options(rotation: f64) -> VergeTiltOptions {
    VergeTiltOptions { rotation_deg: rotation, verge_rotation_deg: rotation, ..VergeTiltOptions::default() }
}

/// One trial's result.
struct Trial {
    scene: &'static str,
    noise: f64,
    seed: u64,
    route: String,
    /// Errors (elevation, left, right vergence), degrees; sigmas and bounds the same.
    err: [f64; 3],
    sigma: [f64; 3],
    /// The Cramér-Rao bound at the truth ([`crb_views`]); NaN for the general route.
    crb: [f64; 3],
    /// Per camera (left, right) of the planar route: the plane test's cost rise
    /// (`CameraPlanar::plane_test`), the plane's largest displacement of a view in pixels
    /// (`plane_parallax_px`) and the profile's largest widening (`profile_widening`, 1:
    /// not profiled); NaN for the general route.
    plane: [[f64; 3]; 2],
    failure: Option<String>,
}

impl Trial {
    fn new(scene: &'static str, noise: f64, seed: u64, route: &str) -> Self {
        Self {
            scene,
            noise,
            seed,
            route: route.into(),
            err: [f64::NAN; 3],
            sigma: [f64::NAN; 3],
            crb: [f64::NAN; 3],
            plane: [[f64::NAN; 3]; 2],
            failure: None,
        }
    }
}

/// Largest distance (pixels) between a noisy observation and its exact pixel for the
/// exact one to enter the bound's views: five noise sigmas (a 2D Gaussian residual lies
/// beyond with probability `exp(-12.5)`); the simulated outliers, uniform over the image,
/// fall outside and stay out, as the estimator drops them.
const CRB_GATE_SIGMAS: f64 = 5.0;

/// The views of the Cramér-Rao bound (module docs): each view's exact observations
/// (simulator truth, at the joints' true positions `truth`) of the tracks whose noisy
/// observation in `noisy` is an inlier, with the noisy view's encoder readings (the same
/// angle priors).
fn crb_views(head: &SimulatedHead, noisy: &[View], truth: &[Encoders], noise: f64) -> Vec<View> {
    let gate = CRB_GATE_SIGMAS * noise.max(1e-9);
    let keep = |exact: Vec<TrackObservation>, noisy: &[TrackObservation]| -> Vec<TrackObservation> {
        exact
            .into_iter()
            .filter(|o| noisy.iter().any(|n| n.track == o.track && (n.pixel - o.pixel).norm() <= gate))
            .collect()
    };
    noisy
        .iter()
        .zip(truth)
        .map(|(v, e)| {
            let exact = head.exact_capture(e);
            View {
                name: v.name.clone(),
                capture: StereoCapture {
                    encoders: v.capture.encoders,
                    image_size: exact.image_size,
                    left: keep(exact.left, &v.capture.left),
                    right: keep(exact.right, &v.capture.right),
                },
            }
        })
        .collect()
}

/// Run one planar-route trial.
fn planar_trial(scene: &'static str, noise: f64, seed: u64, encoder_noise: f64, rotation: f64) -> Trial {
    let t = Trial::new(scene, noise, seed, "planar");
    let result = (|| -> Result<Trial> {
        let base = Scenario::preset(scene).map_err(|e| anyhow::anyhow!("{e}"))?;
        let scenario = Scenario {
            noise_px: noise,
            encoder_noise_deg: if noise > 0.0 { encoder_noise } else { 0.0 },
            ..base.with_seed(seed)
        };
        let mut head = SimulatedHead::new(scenario).map_err(|e| anyhow::anyhow!("{e}"))?;
        let options = procedure_options(rotation);
        let e0 = head.read_encoders()?;
        let (mut views, mut truth) = (Vec::new(), Vec::new());
        for (name, e) in capture_plan(&e0, &options) {
            head.move_to(&e)?;
            views.push(View { name, capture: head.capture()? });
            truth.push(e);
        }
        let rig = views.len() - 1;
        let estimation = EstimationOptions::default();
        let check = detect_scene(&views[..rig], &estimation.fundamental);
        let kind = check.kind;
        let calib = estimate_planar(&views, check.clone(), &PlanarOptions::default())?;
        let reference = views[0].capture.encoders;
        let sol = solve_alignment_axes(&calib.left.axes(), &calib.right.axes(), &reference)?;
        let reading = estimation.bundle.angle_prior_sigma.map_or(0.0, f64::to_degrees);
        let s = alignment_sigmas(&calib)?.with_reading_noise(reading);
        let crb = if noise > 0.0 {
            let exact = crb_views(&head, &views, &truth, noise);
            let options = PlanarOptions {
                covariance_sigma_px: Some(noise),
                normal_profile_z: None,
                ..PlanarOptions::default()
            };
            let at_truth = estimate_planar(&exact, check, &options).context("the bound's fit")?;
            let b = alignment_sigmas(&at_truth)?.with_reading_noise(reading);
            [b.elevation_deg, b.verge_left_deg, b.verge_right_deg]
        } else {
            [f64::NAN; 3]
        };
        let truth = head.aligned_encoders();
        let a = sol.aligned_encoders;
        let route = if kind == SceneKind::General { "general-detected" } else { calib.scene.kind.name() };
        Ok(Trial {
            err: [
                a.elevation - truth.elevation,
                a.verge_left - truth.verge_left,
                a.verge_right - truth.verge_right,
            ],
            sigma: [s.elevation_deg, s.verge_left_deg, s.verge_right_deg],
            crb,
            route: route.to_string(),
            plane: [&calib.left, &calib.right]
                .map(|c| [c.plane_test.rise, c.plane_parallax_px, c.profile_widening]),
            ..Trial::new(scene, noise, seed, "planar")
        })
    })();
    result.unwrap_or_else(|e| Trial { failure: Some(format!("{e:#}")), ..t })
}

/// Run one general-route trial in the default room.
fn general_trial(noise: f64, seed: u64, encoder_noise: f64, rotation: f64) -> Trial {
    let t = Trial::new("default", noise, seed, "general");
    let scenario =
        Scenario { noise_px: noise, encoder_noise_deg: encoder_noise, ..Scenario::default().with_seed(seed) };
    let result = SimulatedHead::new(scenario).map_err(|e| anyhow::anyhow!("{e}")).and_then(|mut head| {
        let out =
            VergeTiltRun::default().run(&mut head, &procedure_options(rotation)).context("general route")?;
        let (a, truth) = (out.solution.aligned_encoders, head.aligned_encoders());
        Ok(Trial {
            err: [
                a.elevation - truth.elevation,
                a.verge_left - truth.verge_left,
                a.verge_right - truth.verge_right,
            ],
            sigma: [out.sigmas.elevation_deg, out.sigmas.verge_left_deg, out.sigmas.verge_right_deg],
            ..Trial::new("default", noise, seed, "general")
        })
    });
    result.unwrap_or_else(|e| Trial { failure: Some(format!("{e:#}")), ..t })
}

/// Entry point: run, write `planar.csv` and `planar.md` in `--out`, print the summary.
pub fn run(args: &ExperimentArgs) -> Result<()> {
    let per = args.trials.unwrap_or(DEFAULT_TRIALS).max(1);
    let rotation = rotation_deg(args.rotation)?;
    let noises: Vec<f64> = if args.only.is_empty() { NOISE_PX.to_vec() } else { args.only.clone() };
    if noises.iter().any(|n| !(n.is_finite() && *n >= 0.0)) {
        anyhow::bail!("--only: noise levels must be non-negative pixels, got {noises:?}");
    }
    let scenes: Vec<&'static str> = match args.scene.as_str() {
        "default" => vec!["wall", "far"],
        "wall" => vec!["wall"],
        "far" => vec!["far"],
        other => anyhow::bail!("experiment planar: --scene wall or far (default: both), got '{other}'"),
    };
    let mut jobs: Vec<(&'static str, f64, u64)> = Vec::new();
    for &scene in &scenes {
        for &noise in &noises {
            for t in 0..per as u64 {
                jobs.push((scene, noise, args.seed + t));
            }
        }
    }
    let general_n = per.min(50) as u64;
    if args.scene == "default" && noises.iter().any(|n| (n - 1.0).abs() < 1e-9) {
        for t in 0..general_n {
            jobs.push(("default", 1.0, args.seed + t));
        }
    }
    let trials: Vec<Trial> = jobs
        .par_iter()
        .map(|&(scene, noise, seed)| {
            if scene == "default" {
                general_trial(noise, seed, args.encoder_noise, rotation)
            } else {
                planar_trial(scene, noise, seed, args.encoder_noise, rotation)
            }
        })
        .collect();
    std::fs::create_dir_all(&args.out).with_context(|| format!("cannot create {}", args.out.display()))?;
    let mut csv = String::from(
        "scene,noise_px,seed,route,err_elevation,err_verge_left,err_verge_right,sigma_elevation,sigma_verge_left,sigma_verge_right,crb_elevation,crb_verge_left,crb_verge_right,plane_rise_left,plane_parallax_px_left,widening_left,plane_rise_right,plane_parallax_px_right,widening_right,failure\n",
    );
    for t in &trials {
        let _ = writeln!(
            csv,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            t.scene,
            t.noise,
            t.seed,
            t.route,
            t.err[0],
            t.err[1],
            t.err[2],
            t.sigma[0],
            t.sigma[1],
            t.sigma[2],
            t.crb[0],
            t.crb[1],
            t.crb[2],
            t.plane[0][0],
            t.plane[0][1],
            t.plane[0][2],
            t.plane[1][0],
            t.plane[1][1],
            t.plane[1][2],
            t.failure.as_deref().unwrap_or("").replace([',', '\n'], ";")
        );
    }
    std::fs::write(args.out.join("planar.csv"), csv).context("planar.csv")?;
    let md = summary(&trials, per, args.seed, args.rotation);
    std::fs::write(args.out.join("planar.md"), &md).context("planar.md")?;
    use std::io::Write as _;
    let _ = writeln!(std::io::stdout(), "{md}");
    Ok(())
}

/// Heading of the planar section of `results.md` (written by hand from this experiment's
/// `planar.md`; [`kept_section`]).
pub const SECTION_HEADING: &str = "## planar — ";

/// The planar section of an existing `results.md` (from [`SECTION_HEADING`] to the next
/// `## ` heading or the end), which `experiment all` keeps when it rewrites the file.
pub fn kept_section(existing: &str) -> Option<String> {
    section(existing, SECTION_HEADING)
}

/// The section of `existing` (a `results.md`) that starts with the line `heading`, up to
/// the next `## ` heading (or the end), with one final newline.
pub fn section(existing: &str, heading: &str) -> Option<String> {
    let start = existing.find(&format!("\n{heading}"))? + 1;
    let rest = &existing[start..];
    let end = rest[heading.len()..].find("\n## ").map_or(rest.len(), |i| i + heading.len() + 1);
    Some(rest[..end].trim_end().to_string() + "\n")
}

/// The Markdown summary (module docs); the heading names `--rotation` when it was given.
fn summary(trials: &[Trial], per: usize, seed: u64, rotation: Option<f64>) -> String {
    let rotation = rotation.map_or_else(String::new, |r| format!(" --rotation {r}"));
    let mut md = format!(
        "## Planar route (`experiment planar --trials {per} --seed {seed}{rotation}`)\n\nAligned-reading errors (deg) against the truth: RMS, the RMS of the reported sigmas, the RMS of the planar model's Cramér-Rao bound at the truth (CRB), the ratios, the reported sigmas' 95 % coverage, the mean error with its standard error, the trials whose error exceeds three times their bound (a Gaussian error does so with probability 0.0027), and the cameras whose covariance the profile over the plane's normal widened.\n\n| scene | noise px | ok / n | routes | reading | RMS deg | sigma RMS deg | RMS / sigma | CRB RMS deg | RMS / CRB | coverage 95 % | mean error deg (standard error) | beyond 3 CRB | profiled cameras |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n"
    );
    let mut keys: Vec<(&str, f64)> = Vec::new();
    for t in trials {
        if !keys.iter().any(|k| k.0 == t.scene && k.1 == t.noise) {
            keys.push((t.scene, t.noise));
        }
    }
    for (scene, noise) in keys {
        let group: Vec<&Trial> = trials.iter().filter(|t| t.scene == scene && t.noise == noise).collect();
        let ok: Vec<&&Trial> = group.iter().filter(|t| t.failure.is_none()).collect();
        let mut routes: Vec<String> = ok.iter().map(|t| t.route.clone()).collect();
        routes.sort();
        routes.dedup();
        let count = |r: &str| ok.iter().filter(|t| t.route == r).count();
        let routes: Vec<String> = routes.iter().map(|r| format!("{r} {}", count(r))).collect();
        let profiled = if scene == "default" {
            "-".to_string()
        } else {
            let n = ok.iter().flat_map(|t| t.plane).filter(|p| p[2] > 1.0).count();
            format!("{n} of {}", 2 * ok.len())
        };
        for (i, name) in ["elevation", "verge_left", "verge_right"].iter().enumerate() {
            let n = ok.len().max(1) as f64;
            let rms = (ok.iter().map(|t| t.err[i].powi(2)).sum::<f64>() / n).sqrt();
            let srms = (ok.iter().map(|t| t.sigma[i].powi(2)).sum::<f64>() / n).sqrt();
            let cov = ok.iter().filter(|t| t.err[i].abs() <= 1.96 * t.sigma[i]).count() as f64 / n;
            let ratio = if srms > 0.0 { format!("{:.3}", rms / srms) } else { "-".into() };
            let bounded: Vec<f64> = ok.iter().map(|t| t.crb[i]).filter(|b| b.is_finite()).collect();
            let every_bounded = bounded.len() == ok.len() && !bounded.is_empty();
            let (crb, crb_ratio) = if every_bounded {
                let c = (bounded.iter().map(|b| b * b).sum::<f64>() / n).sqrt();
                (format!("{c:.4}"), if c > 0.0 { format!("{:.3}", rms / c) } else { "-".into() })
            } else {
                ("-".into(), "-".into())
            };
            let coverage = if noise > 0.0 { format!("{:.1} %", 100.0 * cov) } else { "-".into() };
            let (mean, se) = mean_and_standard_error(ok.iter().map(|t| t.err[i]));
            let beyond = if every_bounded {
                ok.iter().filter(|t| t.err[i].abs() > 3.0 * t.crb[i]).count().to_string()
            } else {
                "-".into()
            };
            let _ = writeln!(
                md,
                "| {scene} | {noise} | {} / {} | {} | {name} | {rms:.4} | {srms:.4} | {ratio} | {crb} | {crb_ratio} | {coverage} | {mean:+.3} ({se:.3}) | {beyond} | {profiled} |",
                ok.len(),
                group.len(),
                routes.join(", "),
            );
        }
    }
    md
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    /// `headalign experiment`'s arguments alone.
    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        args: ExperimentArgs,
    }

    fn parse(words: &[&str]) -> ExperimentArgs {
        let cli = Cli::try_parse_from(std::iter::once("experiment").chain(words.iter().copied()));
        cli.map(|c| c.args).unwrap_or_else(|e| panic!("{words:?}: {e}"))
    }

    /// `--rotation`: parsed for `planar`, the procedure's 3 deg when absent (then the
    /// default options), any size in (0, 30] deg turning the elevation, pan and vergence
    /// views; out of range, or given to an experiment without it, a clean error before any
    /// trial runs.
    #[test]
    fn rotation_turns_every_moved_view() {
        let args = parse(&["planar", "--scene", "wall", "--rotation", "6", "--only", "1"]);
        let r = rotation_deg(args.rotation).unwrap();
        assert_eq!(r, 6.0);
        let plan = capture_plan(&Encoders::default(), &procedure_options(r));
        let moved: Vec<(&str, f64, f64, f64, f64)> =
            plan.iter().map(|(n, e)| (n.as_str(), e.elevation, e.pan, e.verge_left, e.verge_right)).collect();
        assert_eq!(
            moved,
            [
                ("initial", 0.0, 0.0, 0.0, 0.0),
                ("elevation+", 6.0, 0.0, 0.0, 0.0),
                ("elevation-", -6.0, 0.0, 0.0, 0.0),
                ("pan+", 0.0, 6.0, 0.0, 0.0),
                ("pan-", 0.0, -6.0, 0.0, 0.0),
                ("verge", 0.0, 0.0, 6.0, 6.0),
            ]
        );
        let default = rotation_deg(parse(&["planar"]).rotation).unwrap();
        let (o, d) = (procedure_options(default), VergeTiltOptions::default());
        assert_eq!(
            (o.rotation_deg, o.verge_rotation_deg, o.diagonal_rotation_deg, o.both_directions),
            (d.rotation_deg, d.verge_rotation_deg, d.diagonal_rotation_deg, d.both_directions)
        );
        assert!(o.auto_rotation.is_none());
        for bad in ["0", "-3", "31", "NaN", "inf"] {
            let args = parse(&["planar", &format!("--rotation={bad}")]);
            assert!(rotation_deg(args.rotation).is_err(), "{bad}");
        }
        let out = std::env::temp_dir().join(format!("headalign-planar-rotation-{}", std::process::id()));
        let out = out.to_string_lossy().into_owned();
        for (name, rotation) in [("planar", "40"), ("points", "6"), ("ml-spread", "6")] {
            let args = parse(&[name, "--rotation", rotation, "--trials", "1", "--out", &out]);
            let e = super::super::run(&args).err().map(|e| e.to_string()).unwrap_or_default();
            assert!(e.contains("--rotation"), "{name}: {e}");
        }
        assert!(!std::path::Path::new(&out).exists(), "no trial ran");
    }

    /// The planar section is cut from its heading to the next one, or to the end.
    #[test]
    fn the_planar_section_is_kept() {
        let md = "# R\n\n## lens\n\ntext\n\n## planar — walls\n\n| a |\n\n## other\n\nx\n";
        assert_eq!(kept_section(md).as_deref(), Some("## planar — walls\n\n| a |\n"));
        let last = "# R\n\n## planar — walls\n\nend\n";
        assert_eq!(kept_section(last).as_deref(), Some("## planar — walls\n\nend\n"));
        assert_eq!(kept_section("# R\n\n## lens\n"), None);
    }
    /// Two wall trials: errors 0.1 and 0.5 deg against bounds 0.1 (one beyond three bounds),
    /// one camera of four profiled; the mean 0.3 with standard error 0.2 (sample sd
    /// 0.2828 over sqrt 2).
    #[test]
    fn the_summary_counts_tails_and_profiles() {
        let trial = |seed: u64, e: f64, widening: [f64; 2]| Trial {
            err: [e; 3],
            sigma: [0.3; 3],
            crb: [0.1; 3],
            plane: [[40.0, 1.5, widening[0]], [40.0, 1.5, widening[1]]],
            ..Trial::new("wall", 1.0, seed, "far")
        };
        let md = summary(&[trial(1, 0.1, [1.0, 1.4]), trial(2, 0.5, [1.0, 1.0])], 2, 1, None);
        let row = md.lines().find(|l| l.contains("| elevation |")).unwrap_or_default();
        assert!(row.ends_with("| +0.300 (0.200) | 1 | 1 of 4 |"), "{row}");
    }
}
