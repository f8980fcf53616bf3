//! Summary statistics of experiment trials: RMS errors, Cramer-Rao bound RMS, their
//! ratio, and the coverage of the reported 95 % intervals.
//!
//! RMS over successful trials of a signed error `e`: `sqrt(mean e^2)` (it includes any
//! bias, as the paper's figures do). The bound's summary is `sqrt(mean crb^2)`, the RMS
//! error an efficient unbiased estimator would reach over the same trials (the bound
//! varies with each seed's head and scene). Coverage: fraction of trials with
//! `|est - truth| <= 1.96 sigma` (two-sided 95 % for a Gaussian). Empty inputs give NaN.

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
}
