//! The robust loss of the rig bundle adjustment and the measurement window's truncated
//! mean (module docs of [`crate::bundle`], sections Algorithm and Measurement window).
//!
//! # What it computes
//!
//! - [`RobustLoss`] and `robust`: a loss `rho` on the norm `s` of each 2D residual (pixels;
//!   one loss per observation, not per image axis): plain least squares `s^2 / 2`, Huber
//!   (quadratic below `scale_px`, linear above), Cauchy `k^2 / 2 ln(1 + s^2 / k^2)`.
//!   `robust` returns `(rho(s), rho'(s) / s)`; the solver minimises by iteratively
//!   reweighted least squares, the weights `rho'(s) / s` taken at each linearisation
//!   point.
//! - [`truncated_mean_shift`]: a detector reports a feature only if its *measured*
//!   position lies in a window (the image), so near the border the reported measurements
//!   are pulled inward. For a prediction `mu`, Gaussian noise `sigma` and window
//!   `[lo, hi]` it gives the shift of the expected reported measurement and its derivative
//!   (the mean and variance of a truncated normal: `a = (lo - mu)/sigma`,
//!   `b = (hi - mu)/sigma`, `Z = Phi(b) - Phi(a)`, shift `sigma (phi(a) - phi(b)) / Z`);
//!   `Problem::observe` adds it to each image axis's residual and scales the Jacobian row
//!   by `1 + d shift / d mu` (moment matching: the residuals' expectation is zero at the
//!   truth near the border too). Pixels in, pixels out.
//!
//! # Pitfalls
//!
//! - IRLS converges linearly: with 10 % outliers expect ~45 iterations to the default
//!   tolerances against ~10 for plain least squares. The reported RMS is of the
//!   unweighted residuals, outliers included.
//! - The Huber and Cauchy scales are pixels on the 2D norm, not sigmas per axis.
//! - The window applies only with `noise_sigma_px` set; more than 6 sigma inside it
//!   nothing is computed (`WINDOW_REACH_SIGMAS`), more than 4 sigma outside the shift is
//!   held (`WINDOW_CLAMP_SIGMAS`), so such an observation still pulls its point back.
//! - `Phi` is `libm::erfc`, accurate to rounding: the residual and its analytic derivative
//!   must agree.

use super::gt;

/// Robust loss on the norm of each 2D residual.
#[derive(Clone, Copy, Debug)]
pub enum RobustLoss {
    /// Plain least squares.
    None,
    /// Huber: quadratic below `scale_px`, linear above.
    Huber {
        /// Threshold, pixels.
        scale_px: f64,
    },
    /// Cauchy: `s^2/2 log(1 + r^2/s^2)`.
    Cauchy {
        /// Scale, pixels.
        scale_px: f64,
    },
}

/// `(rho(s), weight = rho'(s)/s)` for a squared residual norm `s2`.
pub(super) fn robust(loss: RobustLoss, s2: f64) -> (f64, f64) {
    match loss {
        RobustLoss::None => (0.5 * s2, 1.0),
        RobustLoss::Huber { scale_px: k } => {
            let s = s2.sqrt();
            if s <= k { (0.5 * s2, 1.0) } else { (k * s - 0.5 * k * k, k / s) }
        }
        RobustLoss::Cauchy { scale_px: k } => {
            let q = s2 / (k * k);
            (0.5 * k * k * q.ln_1p(), 1.0 / (1.0 + q))
        }
    }
}

/// Predictions farther than this many sigmas outside a measurement window get the shift
/// of this distance (the expectation's limit is the border itself; beyond it the ratio of
/// two vanishing probabilities is not computed).
const WINDOW_CLAMP_SIGMAS: f64 = 4.0;

/// Predictions farther than this many sigmas inside both borders of a window are not
/// shifted (the shift is below `7e-9` sigma there, and the test is all that most
/// observations cost).
const WINDOW_REACH_SIGMAS: f64 = 6.0;

/// The standard normal cumulative distribution `Phi(t) = erfc(-t / sqrt 2) / 2` (`libm`'s
/// `erfc`, accurate to rounding: the residual and its analytic derivative must agree).
fn normal_cdf(t: f64) -> f64 {
    0.5 * libm::erfc(-t / std::f64::consts::SQRT_2)
}

/// The standard normal density.
fn normal_pdf(t: f64) -> f64 {
    (-0.5 * t * t).exp() / (2.0 * std::f64::consts::PI).sqrt()
}

/// Shift of the expected measurement from the prediction `mu` when Gaussian noise of
/// `sigma` is added and only measurements in `[lo, hi]` are reported, and its derivative
/// with respect to `mu`: with `a = (lo - mu) / sigma`, `b = (hi - mu) / sigma` and
/// `Z = Phi(b) - Phi(a)`, `shift = sigma (phi(a) - phi(b)) / Z` and
/// `d shift / d mu = (a phi(a) - b phi(b)) / Z - (shift / sigma)^2` (so `1 + d shift / d mu`
/// is the truncated variance over `sigma^2`, in `(0, 1]`). `(0, 0)` more than 6 sigma
/// (`WINDOW_REACH_SIGMAS`) inside both borders; for a prediction more than 4 sigma
/// (`WINDOW_CLAMP_SIGMAS`) outside, the shift at that distance is held (derivative 0), so
/// the expected measurement follows the prediction there and such an observation still
/// pulls its point back towards the window.
#[inline]
pub fn truncated_mean_shift(mu: f64, lo: f64, hi: f64, sigma: f64) -> (f64, f64) {
    if !(gt(sigma, 0.0) && mu.is_finite() && lo < hi) {
        return (0.0, 0.0);
    }
    if mu - lo > WINDOW_REACH_SIGMAS * sigma && hi - mu > WINDOW_REACH_SIGMAS * sigma {
        return (0.0, 0.0);
    }
    let (lo_c, hi_c) = (lo - WINDOW_CLAMP_SIGMAS * sigma, hi + WINDOW_CLAMP_SIGMAS * sigma);
    let clamped = mu < lo_c || mu > hi_c;
    let m = mu.clamp(lo_c, hi_c);
    let a = (lo - m) / sigma;
    let b = (hi - m) / sigma;
    let z = normal_cdf(b) - normal_cdf(a);
    if !gt(z, 0.0) {
        return (0.0, 0.0);
    }
    let (pa, pb) = (normal_pdf(a), normal_pdf(b));
    let ratio = (pa - pb) / z;
    let slope = if clamped { 0.0 } else { (a * pa - b * pb) / z - ratio * ratio };
    (sigma * ratio, slope)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bundle::layout::{retract, retract_point};
    use crate::bundle::problem::problem;
    use crate::bundle::residual::{rig_geom, view_geoms};
    use crate::bundle::test_support::{angle_between, axes, state_distance};
    use crate::bundle::{
        BundleObservation, BundleOptions, BundleResult, RigState, bundle_adjust, residual_pixels,
    };
    use crate::synthetic::{perturb, synth};
    use nalgebra::{DVector, Point3, Vector2, Vector3};

    #[test]
    fn noisy_with_outliers_huber_is_accurate() {
        let s = synth(4, 200, 1.0, 0.10, false);
        let start = perturb(&s.truth, 40);
        let res = bundle_adjust(&start, &s.obs, &BundleOptions::default()).unwrap();
        eprintln!("{:?}", res.report);
        assert!(res.report.converged, "{:?}", res.report);
        for (side, est, tru) in
            [("left", &res.state.left, &s.truth.left), ("right", &res.state.right, &s.truth.right)]
        {
            for (n, e, t) in [("fx", est.fx, tru.fx), ("fy", est.fy, tru.fy)] {
                // One seed: within 4 of its own sigma (a 6e-5 chance for a calibrated
                // sigma), and that sigma about 1.4 % at 1 px with 200 points and 3 deg.
                let sd = res.covariance.sigma(&format!("{side}.{n}")).unwrap_or(f64::NAN);
                assert!((e - t).abs() < 4.0 * sd && sd / t < 0.02, "{side}.{n}: {e} vs {t}, sigma {sd}");
            }
        }
        for (le, lt) in axes(&res.state).iter().zip(axes(&s.truth).iter()) {
            let a = angle_between(&le.direction, &lt.direction).to_degrees();
            assert!(a < 0.5, "axis direction off by {a} deg");
        }
        // Never worse than the start; robust weights keep the inlier RMS near 1 px.
        assert!(res.report.final_rms_px < res.report.initial_rms_px);
        assert!((0.7..1.5).contains(&res.report.sigma_px), "{:?}", res.report);
    }

    #[test]
    fn cauchy_and_plain_losses_run() {
        let s = synth(5, 60, 0.5, 0.0, false);
        for robust in [RobustLoss::None, RobustLoss::Cauchy { scale_px: 3.0 }] {
            let opts = BundleOptions { robust, ..BundleOptions::default() };
            let res = bundle_adjust(&perturb(&s.truth, 50), &s.obs, &opts).unwrap();
            assert!(res.report.converged && res.report.final_rms_px < 1.0, "{:?}", res.report);
        }
    }

    /// The truncated mean and its derivative against numerical integration and central
    /// differences, over predictions inside, at and outside a window's borders.
    #[test]
    fn truncated_mean_shift_matches_integration() {
        let (lo, hi, sigma) = (-0.5, 99.5, 3.0);
        for &mu in &[-12.0, -6.0, -2.0, -0.5, 0.0, 1.0, 3.0, 7.0, 20.0, 50.0, 93.0, 99.0, 101.0, 104.0, 111.0]
        {
            let (shift, slope) = truncated_mean_shift(mu, lo, hi, sigma);
            // Midpoint rule over the window: the truncated mean of the measurement.
            let steps = 200_000;
            let dx = (hi - lo) / steps as f64;
            let (mut w, mut wx) = (0.0, 0.0);
            for i in 0..steps {
                let x = lo + (i as f64 + 0.5) * dx;
                let p = normal_pdf((x - mu) / sigma);
                w += p;
                wx += p * x;
            }
            let numeric = wx / w - mu;
            // Outside the clamp the shift is held, not the expectation's.
            if (lo - mu) <= WINDOW_CLAMP_SIGMAS * sigma && (mu - hi) <= WINDOW_CLAMP_SIGMAS * sigma {
                // The midpoint rule's error over 0.0005 px steps is about 1e-8 relative.
                assert!(
                    (shift - numeric).abs() < 1e-5 * (1.0 + numeric.abs()),
                    "mu {mu}: {shift} vs {numeric}"
                );
                let h = 1e-4;
                let d = (truncated_mean_shift(mu + h, lo, hi, sigma).0
                    - truncated_mean_shift(mu - h, lo, hi, sigma).0)
                    / (2.0 * h);
                assert!((slope - d).abs() < 1e-4, "mu {mu}: slope {slope} vs {d}");
                assert!(
                    1.0 + slope > 0.0 && 1.0 + slope <= 1.0 + 1e-9,
                    "mu {mu}: variance ratio {}",
                    1.0 + slope
                );
            } else {
                assert_eq!(slope, 0.0);
            }
        }
        assert_eq!(truncated_mean_shift(50.0, lo, hi, sigma), (0.0, 0.0));
        assert!(
            (truncated_mean_shift(-0.5, lo, hi, sigma).0 - sigma * (2.0 / std::f64::consts::PI).sqrt()).abs()
                < 1e-6
        );
        assert!(
            (normal_cdf(1.959_963_985) - 0.975).abs() < 1e-7
                && (normal_cdf(-3.0) - 0.001_349_898).abs() < 1e-9
        );
    }

    /// The windowed residuals are unbiased estimating equations: on "mean data" (every
    /// observation at its expected reported measurement, the projection plus the
    /// truncated-Gaussian shift of a 3 px noise inside a window a few pixels within the
    /// points' spread) the windowed fit recovers the truth from a perturbed start to rounding,
    /// while the plain fit, which takes those shifts for geometry, does not.
    #[test]
    fn a_measurement_window_recovers_the_truth_from_mean_data() {
        let s = synth(2, 200, 0.0, 0.0, false);
        let window = [180.0, 70.0, 700.0, 506.0];
        let sigma = 3.0;
        let mut shifted = 0;
        let obs: Vec<BundleObservation> = s
            .obs
            .iter()
            .filter(|o| {
                o.pixel.x > window[0]
                    && o.pixel.x < window[2]
                    && o.pixel.y > window[1]
                    && o.pixel.y < window[3]
            })
            .map(|o| {
                let (dx, _) = truncated_mean_shift(o.pixel.x, window[0], window[2], sigma);
                let (dy, _) = truncated_mean_shift(o.pixel.y, window[1], window[3], sigma);
                if dx.abs() + dy.abs() > 0.1 {
                    shifted += 1;
                }
                BundleObservation { pixel: o.pixel + Vector2::new(dx, dy), ..*o }
            })
            .collect();
        assert!(shifted > 30, "{shifted} observations near a border");
        let start = perturb(&s.truth, 20);
        let opts = BundleOptions {
            noise_sigma_px: Some(sigma),
            measurement_window: Some(window),
            ..BundleOptions::default()
        };
        // Cameras, rig and axes (points seen fewer than twice inside the window keep their
        // start).
        let distance = |r: &BundleResult| {
            state_distance(&RigState { points: s.truth.points.clone(), ..r.state.clone() }, &s.truth)
        };
        let res = bundle_adjust(&start, &obs, &opts).unwrap();
        let d = distance(&res);
        assert!(res.report.final_rms_px < 1e-8 && d < 1e-7, "distance to truth {d:e}, {:?}", res.report);
        let plain = bundle_adjust(&start, &obs, &BundleOptions { measurement_window: None, ..opts }).unwrap();
        let dp = distance(&plain);
        assert!(dp > 1e-3, "plain fit distance {dp:e}");
    }

    /// With a measurement window the residuals and both Jacobians (camera parameters and
    /// point) still agree with central differences (a wide sigma so that most
    /// observations are near a border).
    #[test]
    fn windowed_jacobians_match_finite_differences() {
        let s = synth(3, 30, 0.0, 0.0, false);
        let options = BundleOptions {
            noise_sigma_px: Some(40.0),
            measurement_window: Some([150.0, 40.0, 700.0, 540.0]),
            ..BundleOptions::default()
        };
        let (state, problem) = problem(&s.truth, &s.obs, &options).unwrap();
        let residual = |st: &RigState, o: &BundleObservation, x: &Point3<f64>| {
            let views = view_geoms(st, &problem.layout, false);
            problem.observe(st, &views, &rig_geom(st), o, x, None).unwrap().0
        };
        let views = view_geoms(&state, &problem.layout, true);
        let rig = rig_geom(&state);
        let h = 1e-6;
        let mut shifted = 0;
        for o in problem.obs.iter().step_by(3) {
            let x = state.points[o.point];
            let mut cols = Vec::new();
            let (r, jp) = problem.observe(&state, &views, &rig, o, &x, Some(&mut cols)).unwrap();
            assert!((r - residual(&state, o, &x)).norm() < 1e-12);
            if (r - residual_pixels(&state, o).unwrap()).norm() > 0.1 {
                shifted += 1;
            }
            let mut dense = vec![Vector2::zeros(); problem.layout.len()];
            for (i, c) in &cols {
                dense[*i] += c;
            }
            for (i, analytic) in dense.iter().enumerate() {
                let mut e = DVector::zeros(problem.layout.len());
                e[i] = h;
                let plus = residual(&retract(&state, &problem.layout, &e).unwrap(), o, &x);
                let minus = residual(&retract(&state, &problem.layout, &(-e)).unwrap(), o, &x);
                let numeric = (plus - minus) / (2.0 * h);
                assert!(
                    (numeric - analytic).norm() < 1e-5 * (1.0 + numeric.norm()),
                    "{i}: {analytic:?} {numeric:?}"
                );
            }
            for c in 0..3 {
                let mut e = Vector3::zeros();
                e[c] = h;
                let plus = residual(&state, o, &retract_point(&x, &e).unwrap());
                let minus = residual(&state, o, &retract_point(&x, &(-e)).unwrap());
                let numeric = (plus - minus) / (2.0 * h);
                assert!((numeric - jp.column(c)).norm() < 1e-6 * (1.0 + numeric.norm()), "point {c}");
            }
        }
        assert!(shifted > 10, "only {shifted} observations near a border");
    }
}
