//! The wide-field condition of `headalign experiment lens` (issue 45): the double sphere
//! (Usenko et al. 2018, Kalibr's `ds`) estimated by `calibrate` on the camera it is for,
//! a 180-deg field, in views 15 deg apart at 0.5 px.
//!
//! What a trial computes: the simulated head of the scene preset (seed `seed + t`, 400
//! points, no outliers) with the 180-deg double-sphere camera of `calibrate`'s tests in
//! both cameras ([`lens`]: `xi = -0.15`, `alpha = 0.55`; `fx = fy = 188` left and 191
//! right on a 768 x 576 image, so that the image's horizontal edges are 90 deg off the
//! axis and its corners about 115 deg) captures, at [`WIDE_NOISE_PX`] of Gaussian pixel
//! noise, the initial view and views after [`WIDE_ROTATION_DEG`] of elevation and of pan
//! (point mode); `calibrate` estimates the double sphere (`LensChoice::Model`) with zero
//! skew, as for the narrow lenses (`super::run_trial`). Recorded per quantity (the four
//! focal lengths, `xi` and `alpha` of both cameras): the estimate, the truth and the
//! reported sigma.
//!
//! Reported ([`WideSummary`], the section [`markdown`] of `lens.md`): trials that
//! succeeded; RMS and median over trials of the focal error in percent (the four focal
//! lengths pooled) and of the `xi` and `alpha` errors (both cameras pooled), each beside
//! the RMS and median reported sigma; the 95 % coverage of every quantity; and the issue's
//! bar per trial (every focal length within 1 %, every lens parameter within 3 reported
//! sigmas): the trials that meet it. Output: `<stem>-wide.csv` with the columns of
//! `lens.csv` for this lens (`lens.csv` itself is that of the narrow conditions alone).
//!
//! Options: the condition runs when the noise levels (`--only`) include
//! [`WIDE_NOISE_PX`] (the default levels do), with as many trials as each narrow
//! condition; `--rotation` applies to the narrow conditions only (the wide views are
//! [`WIDE_ROTATION_DEG`] apart: at 3 deg the valley of the double sphere's focal length and
//! `xi`, `calibrate::wide`, is not resolved). Units: pixels, percent of `f`, lens
//! parameters dimensionless.
//!
//! Pitfalls: near the axis the double sphere's pixel scale is `f / (1 + xi)`, so its
//! focal error is that of `f` itself, not of the central scale; the coverage is over the
//! trials that succeeded, a failed trial is counted in the table.

use std::fmt::Write as _;

use headalign_geometry::camera::Intrinsics;
use headalign_geometry::distortion::{Distortion, DistortionTerms};
use headalign_sim::Scenario;
use rayon::prelude::*;

use super::{Lens, Quantity, Trial, f, run_trial};
use crate::stats::{coverage_interval, rms};

/// Pixel noise of the wide condition, pixels (the bar).
pub const WIDE_NOISE_PX: f64 = 0.5;

/// Rotation of the elevation and pan views of the wide condition, degrees (the bar's 10-20
/// deg apart).
pub const WIDE_ROTATION_DEG: f64 = 15.0;

/// The wide condition's lens: the double sphere `xi = -0.15`, `alpha = 0.55` (module docs).
pub fn lens() -> Lens {
    Lens { label: "ds", distortion: Distortion::double_sphere(-0.15, 0.55), terms: DistortionTerms::Radial2 }
}

/// The preset with the wide condition's cameras, points and outliers (module docs).
fn scene(preset: &Scenario) -> Scenario {
    Scenario {
        points: 400,
        outlier_fraction: 0.0,
        left: Intrinsics::new(188.0, 188.0, 383.5, 287.5),
        right: Intrinsics::new(191.0, 191.0, 381.0, 290.0),
        ..preset.clone()
    }
}

/// `seeds` trials of the wide condition from seed `first` (in parallel, in seed order).
pub fn run_trials(preset: &Scenario, seeds: usize, first: u64) -> Vec<Trial> {
    let (scene, lens) = (scene(preset), lens());
    (0..seeds as u64)
        .into_par_iter()
        .map(|t| {
            let seed = first + t;
            let start = std::time::Instant::now();
            let result = run_trial(&scene, &lens, WIDE_NOISE_PX, seed, WIDE_ROTATION_DEG)
                .map_err(|e| format!("{e:#}"));
            Trial { lens: 0, noise_px: WIDE_NOISE_PX, seed, seconds: start.elapsed().as_secs_f64(), result }
        })
        .collect()
}

/// RMS and median of some values over trials, and of their reported sigmas.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Spread {
    /// RMS of the errors.
    pub rms: f64,
    /// Median of |error|.
    pub median: f64,
    /// RMS of the sigmas.
    pub sigma_rms: f64,
    /// Median of the sigmas.
    pub sigma_median: f64,
}

/// The summary of the wide condition (module docs).
#[derive(Clone, Debug)]
pub struct WideSummary {
    /// Trials that succeeded, and in all.
    pub ok: usize,
    /// Trials in all.
    pub total: usize,
    /// Focal error, percent (the four focal lengths pooled).
    pub focal_pct: Spread,
    /// `xi` error (both cameras pooled).
    pub xi: Spread,
    /// `alpha` error (both cameras pooled).
    pub alpha: Spread,
    /// Per quantity of [`Lens::quantities`]: trials whose 95 % interval covers the truth,
    /// trials with a sigma.
    pub coverage_counts: Vec<(usize, usize)>,
    /// Trials meeting the bar: every focal length within 1 %, every lens parameter within 3 sigmas.
    pub bar_met: usize,
}

/// The median of the finite values (NaN when there are none).
fn median(mut v: Vec<f64>) -> f64 {
    v.retain(|x| x.is_finite());
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

/// The summary of the wide trials (module docs).
pub fn summarise(trials: &[Trial]) -> WideSummary {
    let names = lens().quantities();
    let ok: Vec<&Vec<Quantity>> =
        trials.iter().filter_map(|t| t.result.as_ref().ok()).map(|o| &o.quantities).collect();
    let pick = |suffixes: &[&str], scale: &dyn Fn(&Quantity) -> f64| -> Spread {
        let chosen: Vec<&Quantity> = ok
            .iter()
            .flat_map(|qs| {
                names.iter().zip(qs.iter()).filter(|(n, _)| suffixes.iter().any(|s| n.ends_with(s)))
            })
            .map(|(_, q)| q)
            .collect();
        let err: Vec<f64> = chosen.iter().map(|q| (q.est - q.truth) * scale(q)).collect();
        let sigma: Vec<f64> = chosen.iter().map(|q| q.sigma * scale(q)).collect();
        Spread {
            rms: rms(err.iter().copied()),
            median: median(err.iter().map(|e| e.abs()).collect()),
            sigma_rms: rms(sigma.iter().copied()),
            sigma_median: median(sigma),
        }
    };
    let coverage_counts = (0..names.len())
        .map(|i| {
            let with_sigma: Vec<&Quantity> = ok
                .iter()
                .filter_map(|qs| qs.get(i))
                .filter(|q| q.sigma.is_finite() && q.sigma > 0.0)
                .collect();
            (
                with_sigma.iter().filter(|q| (q.est - q.truth).abs() <= 1.96 * q.sigma).count(),
                with_sigma.len(),
            )
        })
        .collect();
    let is_focal = |n: &str| n.ends_with(".fx") || n.ends_with(".fy");
    let bar_met = ok
        .iter()
        .filter(|qs| {
            names.iter().zip(qs.iter()).all(|(n, q)| {
                if is_focal(n) {
                    (q.est - q.truth).abs() <= 0.01 * q.truth
                } else {
                    (q.est - q.truth).abs() <= 3.0 * q.sigma
                }
            })
        })
        .count();
    WideSummary {
        ok: ok.len(),
        total: trials.len(),
        focal_pct: pick(&[".fx", ".fy"], &|q| 100.0 / q.truth),
        xi: pick(&[".xi"], &|_| 1.0),
        alpha: pick(&[".alpha"], &|_| 1.0),
        coverage_counts,
        bar_met,
    }
}

/// The section of `lens.md` for the wide condition (`first`: the first seed; `csv`: the
/// name of its CSV).
pub fn markdown(s: &WideSummary, first: u64, csv: &str) -> String {
    let mut m = String::new();
    let l = lens();
    let _ = writeln!(
        m,
        "### The wide lens: double sphere on a 180-deg field\n\n{} trials (seeds {first}-{}): the condition's camera (`xi` = -0.15, `alpha` = 0.55, f = 188 / 191 px on 768 x 576: the horizontal edges 90 deg off the axis, the corners about 115 deg; 400 points, no outliers), views {WIDE_ROTATION_DEG} deg apart (elevation and pan), {WIDE_NOISE_PX} px; `calibrate` estimates the double sphere with zero skew. Errors pooled as above (`xi`, `alpha`: both cameras). CSV: `{csv}`.\n",
        s.total,
        first + s.total.max(1) as u64 - 1,
    );
    let _ = writeln!(
        m,
        "| lens | noise (px) | ok | f error RMS / median (%) | f sigma RMS / median (%) | xi error RMS / median | xi sigma RMS / median | alpha error RMS / median | alpha sigma RMS / median | bar met (f within 1 %, xi and alpha within 3 sigma) |"
    );
    let _ = writeln!(m, "|---|---|---|---|---|---|---|---|---|---|");
    let pair = |a: f64, b: f64, d: usize| format!("{} / {}", f(a, d), f(b, d));
    let _ = writeln!(
        m,
        "| {} | {WIDE_NOISE_PX} | {}/{} | {} | {} | {} | {} | {} | {} | {}/{} |\n",
        l.label,
        s.ok,
        s.total,
        pair(s.focal_pct.rms, s.focal_pct.median, 3),
        pair(s.focal_pct.sigma_rms, s.focal_pct.sigma_median, 3),
        pair(s.xi.rms, s.xi.median, 5),
        pair(s.xi.sigma_rms, s.xi.sigma_median, 5),
        pair(s.alpha.rms, s.alpha.median, 5),
        pair(s.alpha.sigma_rms, s.alpha.sigma_median, 5),
        s.bar_met,
        s.ok,
    );
    let n = s.coverage_counts.iter().map(|c| c.1).min().unwrap_or(0);
    let (lo, hi) = coverage_interval(n);
    let _ = writeln!(
        m,
        "95 % coverage, percent (calibrated sigmas give {}-{} % with 95 % probability over {n} trials):\n",
        f(100.0 * lo, 0),
        f(100.0 * hi, 0)
    );
    let names = l.quantities();
    let _ = writeln!(m, "| {} |{}", l.label, names.iter().map(|q| format!(" {q} |")).collect::<String>());
    let _ = writeln!(m, "|---|{}", "---|".repeat(names.len()));
    let cells: String = s
        .coverage_counts
        .iter()
        .map(|&(h, t)| format!(" {} |", f(if t == 0 { f64::NAN } else { 100.0 * h as f64 / t as f64 }, 1)))
        .collect();
    let _ = writeln!(m, "| {WIDE_NOISE_PX} |{cells}\n");
    m
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lens::Outcome;

    /// A trial of the wide lens whose quantities are `truth + error` with `sigma`, in the
    /// order of [`Lens::quantities`].
    fn trial(seed: u64, errors: [f64; 8], sigma: f64) -> Trial {
        let names = lens().quantities();
        let truth = |n: &str| match n.split_once('.').map(|(_, w)| w) {
            Some("xi") => -0.15,
            Some("alpha") => 0.55,
            _ => 188.0,
        };
        let quantities = names
            .iter()
            .zip(errors)
            .map(|(n, e)| Quantity { est: truth(n) + e, truth: truth(n), sigma })
            .collect();
        let outcome = Outcome { quantities, sigma_px: 0.5, widening: 1.0, start: "grid".into() };
        Trial { lens: 0, noise_px: WIDE_NOISE_PX, seed, seconds: 1.0, result: Ok(outcome) }
    }

    /// Two trials: one within the bar (f errors 0.94 px = 0.5 %, lens errors 1 sigma), one
    /// outside it (left fx 3.76 px = 2 % off); a failed third is counted, not summarised.
    /// The summary's pooled errors, coverage and bar count follow, and the section names them.
    #[test]
    fn the_wide_summary_pools_and_counts_the_bar() {
        let good = trial(1, [0.94, -0.94, 0.94, -0.94, 0.01, -0.01, 0.01, -0.01], 0.01);
        let bad = trial(2, [3.76, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], 0.01);
        let failed =
            Trial { lens: 0, noise_px: WIDE_NOISE_PX, seed: 3, seconds: 1.0, result: Err("x".into()) };
        let s = summarise(&[good, bad, failed]);
        assert_eq!((s.ok, s.total, s.bar_met), (2, 3, 1));
        // xi errors 0.01, -0.01, 0, 0 (pooled over cameras and trials): RMS 0.01 / sqrt(2).
        assert!((s.xi.rms - 0.01 / 2f64.sqrt()).abs() < 1e-12, "{:?}", s.xi);
        // Focal |errors| in percent: four of 0.5 %, one of 2 %, three of 0: median 0.5.
        assert!((s.focal_pct.median - 0.5).abs() < 1e-9, "{:?}", s.focal_pct);
        // Every lens parameter within 1.96 sigma in both trials; the focal sigmas (0.01 px)
        // cover only the exact ones.
        assert_eq!(s.coverage_counts[4..], [(2, 2); 4]);
        assert_eq!(s.coverage_counts[0], (0, 2));
        let md = markdown(&s, 1, "lens-wide.csv");
        assert!(
            md.contains("| ds | 0.5 | 2/3 |") && md.contains("| 1/2 |") && md.contains("right.alpha"),
            "{md}"
        );
    }
}
