//! Summary statistics of experiment trials: RMS errors, Cramer-Rao bound RMS, their
//! ratio, and the coverage of the reported 95 % intervals.
//!
//! RMS over successful trials of a signed error `e`: `sqrt(mean e^2)` (it includes any
//! bias, as the paper's figures do). The bound's summary is `sqrt(mean crb^2)`, the RMS
//! error an efficient unbiased estimator would reach over the same trials (the bound
//! varies with each seed's head and scene). Coverage: fraction of trials with
//! `|est - truth| <= 1.96 sigma` (two-sided 95 % for a Gaussian). Empty inputs give NaN.
//!
//! How many trials a verdict needs: the RMS of `n` Gaussian errors has a relative standard
//! deviation of about `1 / sqrt(2 n)` (13 % at 30 trials, 5 % at 200), so a ratio bar of
//! 1.15 cannot be judged with 30 trials; [`ratio_interval`] and [`coverage_interval`] give
//! the 95 % ranges an efficient, calibrated estimator would show.

use super::trial::{Quantity, TrialRecord};

/// `sqrt(mean v^2)` over the finite values; NaN if none.
pub fn rms(values: impl IntoIterator<Item = f64>) -> f64 {
    let (sum, n) =
        values.into_iter().filter(|v| v.is_finite()).fold((0.0, 0usize), |(s, n), v| (s + v * v, n + 1));
    if n == 0 { f64::NAN } else { (sum / n as f64).sqrt() }
}

/// Fraction (0-1) of quantities whose 95 % interval (1.96 sigma) contains the truth;
/// quantities without a finite sigma are skipped. NaN if none.
pub fn coverage<'a>(quantities: impl IntoIterator<Item = &'a Quantity>) -> (f64, usize) {
    let (hit, n) = quantities
        .into_iter()
        .filter(|q| q.sigma.is_finite() && q.sigma > 0.0 && q.est.is_finite())
        .fold((0usize, 0usize), |(h, n), q| {
            (h + usize::from((q.est - q.truth).abs() <= 1.96 * q.sigma), n + 1)
        });
    (if n == 0 { f64::NAN } else { hit as f64 / n as f64 }, n)
}

/// 95 % interval of `RMS / sigma` for `n` Gaussian errors of standard deviation `sigma`
/// (`n RMS^2 / sigma^2` is chi-square with `n` degrees of freedom; Wilson-Hilferty
/// quantiles, within 1 % of the exact ones for `n >= 10`). NaN for `n = 0`.
pub fn ratio_interval(n: usize) -> (f64, f64) {
    if n == 0 {
        return (f64::NAN, f64::NAN);
    }
    let k = n as f64;
    let q = |z: f64| k * (1.0 - 2.0 / (9.0 * k) + z * (2.0 / (9.0 * k)).sqrt()).powi(3);
    let z = 1.959_964;
    ((q(-z) / k).max(0.0).sqrt(), (q(z) / k).sqrt())
}

/// 95 % interval of the observed coverage of a calibrated 95 % interval over `n` trials
/// (normal approximation of the binomial, clamped to [0, 1]). NaN for `n = 0`.
pub fn coverage_interval(n: usize) -> (f64, f64) {
    if n == 0 {
        return (f64::NAN, f64::NAN);
    }
    let sd = (0.95 * 0.05 / n as f64).sqrt();
    ((0.95 - 1.96 * sd).max(0.0), (0.95 + 1.96 * sd).min(1.0))
}

/// Mean of `values` and its standard error (sample standard deviation over `sqrt n`; NaN
/// below two values).
pub fn mean_and_standard_error(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let v: Vec<f64> = values.collect();
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
    (mean, if v.len() < 2 { f64::NAN } else { (var / n).sqrt() })
}

/// Probability that a calibrated 95 % interval covers the truth in a fraction between `lo`
/// and `hi` (inclusive) of `n` independent trials: the exact binomial sum (log-space terms,
/// exact for any `n`). 0 for `n = 0`. The bar 90-98 % over 60 trials: 0.78.
pub fn coverage_in_bar(n: usize, lo: f64, hi: f64) -> f64 {
    let (p, nf) = (0.95_f64, n as f64);
    let mut ln_choose = 0.0_f64; // ln C(n, k), updated k by k
    let mut sum = 0.0;
    for k in 0..=n {
        if k > 0 {
            ln_choose += ((nf - k as f64 + 1.0) / k as f64).ln();
        }
        let frac = k as f64 / nf;
        // A tolerance of 1e-9 on the fraction: 54 / 60 is 0.9 exactly in decimal.
        if frac >= lo - 1e-9 && frac <= hi + 1e-9 {
            sum += (ln_choose + k as f64 * p.ln() + (nf - k as f64) * (1.0 - p).ln()).exp();
        }
    }
    sum
}

/// RMS of `est - truth` of quantity `i` over the records.
pub fn quantity_rms(records: &[&TrialRecord], i: usize) -> f64 {
    rms(records.iter().filter_map(|r| r.quantities.get(i)).map(|q| q.est - q.truth))
}

/// RMS of the Cramer-Rao bound of quantity `i` over the records.
pub fn quantity_crb(records: &[&TrialRecord], i: usize) -> f64 {
    rms(records.iter().filter_map(|r| r.quantities.get(i)).map(|q| q.crb))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rms_and_coverage() {
        assert!((rms([3.0, -4.0, f64::NAN]) - (12.5f64).sqrt()).abs() < 1e-12);
        assert!(rms(std::iter::empty()).is_nan());
        let q = |est: f64| Quantity { est, truth: 0.0, sigma: 1.0, crb: 1.0 };
        let qs = [q(0.5), q(1.9), q(2.0), q(-3.0), Quantity { sigma: f64::NAN, ..q(0.0) }];
        let (c, n) = coverage(&qs);
        assert_eq!(n, 4);
        assert!((c - 0.5).abs() < 1e-12);
    }

    /// Wilson-Hilferty against exact chi-square quantiles: n = 30: 16.791 and 46.979;
    /// n = 200: 162.728 and 241.058 (tables). Coverage: n = 100 gives 95 +- 4.27 %.
    #[test]
    fn intervals() {
        let (lo, hi) = ratio_interval(30);
        assert!((lo - (16.791f64 / 30.0).sqrt()).abs() < 2e-3, "{lo}");
        assert!((hi - (46.979f64 / 30.0).sqrt()).abs() < 2e-3, "{hi}");
        let (lo, hi) = ratio_interval(200);
        assert!((lo - (162.728f64 / 200.0).sqrt()).abs() < 1e-3, "{lo}");
        assert!((hi - (241.058f64 / 200.0).sqrt()).abs() < 1e-3, "{hi}");
        assert!(ratio_interval(0).0.is_nan());
        let (lo, hi) = coverage_interval(100);
        assert!((lo - 0.9073).abs() < 1e-3 && (hi - 0.9927).abs() < 1e-3, "{lo} {hi}");
    }

    /// 1, 2, 3: mean 2, sample sd 1, standard error 1 / sqrt 3; one value has none.
    #[test]
    fn mean_and_its_standard_error() {
        let (m, se) = mean_and_standard_error([1.0, 2.0, 3.0].into_iter());
        assert!((m - 2.0).abs() < 1e-12 && (se - (1.0f64 / 3.0).sqrt()).abs() < 1e-12);
        assert!(mean_and_standard_error([1.0].into_iter()).1.is_nan());
    }

    /// Exact binomial sums computed independently (Python `math.comb`): over 60 trials,
    /// 54-58 hits has probability 0.778753, 59-60 hits 0.191553; the whole range sums to 1.
    #[test]
    fn binomial_bar() {
        assert!((coverage_in_bar(60, 0.90, 0.98) - 0.778_753).abs() < 1e-6);
        assert!((coverage_in_bar(60, 0.98, 1.0) - 0.191_553).abs() < 1e-6);
        assert!((coverage_in_bar(500, 0.0, 1.0) - 1.0).abs() < 1e-9);
        assert_eq!(coverage_in_bar(0, 0.9, 0.98), 0.0);
    }
}
