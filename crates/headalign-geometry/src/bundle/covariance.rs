//! The covariance of the rig bundle adjustment's camera parameters and the scene's depth
//! scale (module docs of [`crate::bundle`], section Covariance).
//!
//! # What it computes
//!
//! - `covariance`: at the solution, undamped, with the final robust weights, the reduced
//!   camera system `S` (`normal.rs`, points eliminated by the Schur complement) is formed
//!   with the angle priors weighted by `sigma^2`; under [`CovarianceModel::Gaussian`] the
//!   covariance is `sigma^2 S^-1`, the marginal covariance of the camera parameters in the
//!   tangent parametrisation of `layout.rs` (units: pixels for intrinsics, radians and
//!   baselines for the rest). Under [`CovarianceModel::PointClustered`] it is the
//!   cluster-robust sandwich `S^-1 (sum_p s_p s_p^T + sigma^2 P) S^-1 * 2n / (2n - c)`
//!   with each point's efficient score `s_p = g_p - W_p V_p^-1 h_p` (pixels; `c` camera
//!   parameters, `2n` residual components, `P` the priors' information), consistent when
//!   a point's errors are correlated across its observations (White 1980; Liang and Zeger
//!   1986), with [`BundleReport::sigma_inflation`]
//!   its widening over the Gaussian sigmas.
//! - [`clustered_covariance`]: the same sandwich with clusters given by the caller (points
//!   sharing a label), for diagnostics of correlation across points.
//! - [`log_depth_scale`]: the scene's depth scale `s = -ln(mean 1/|X|)` (the log
//!   harmonic-mean distance from the reference camera, in baselines) over the adjusted
//!   points, with its sigma `sigma_px sqrt(a^T N^-1 a)` from the linearisation (points not
//!   eliminated); `log_depth_scale_of` and `log_depth_scale_jacobian` (over each point's
//!   homogeneous tangent step) also serve the depth-scale constraint of
//!   `bundle_adjust_at_depth_scale` (`problem.rs`, `normal.rs`).
//!
//! # Pitfalls
//!
//! - Points whose undamped `V_p` is not positive definite are left out (conservative), and
//!   so are the observations of a point collapsed onto a camera centre (information above
//!   `MAX_POINT_INFORMATION_RATIO` = 1e8 times the median point's): its terms would swamp
//!   the camera parameters' in rounding and make `S` indefinite.
//! - A singular `S` at the solution means a parameter the data do not determine:
//!   [`GeometryError::Numerical`], not a huge sigma.
//! - The sandwich needs many more clusters than camera parameters (hundreds of points
//!   against 20-40 parameters); over a few coarse clusters it is noisy and biased low.
//! - Inverse distance, not log distance, is averaged for the depth scale: a far point's log
//!   distance is unbounded (measured sigmas up to 570 at 3 px).
//!
//! [`BundleReport::sigma_inflation`]: super::BundleReport::sigma_inflation

use std::collections::BTreeMap;

use nalgebra::{DMatrix, DVector, Vector3};
use serde::{Deserialize, Serialize};

use super::gt;
use super::layout::{homogeneous_basis, point_homogeneous};
use super::normal::{Normal, reduced_camera_system, solve_rhs};
use super::problem::{Problem, problem};
use super::sparse::ProfileCholesky;
use super::state::{BundleObservation, BundleOptions, RigState};
use crate::{GeometryError, Result};

/// The noise model behind the reported covariance (module docs, Covariance).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CovarianceModel {
    /// Independent isotropic Gaussian pixel errors of one `sigma`: `sigma^2 S^-1`.
    #[default]
    Gaussian,
    /// Cluster-robust (sandwich) estimate with each point's observations as one cluster:
    /// errors may be correlated within a point's observations and differ between points.
    PointClustered,
}

/// Marginal covariance of the camera (non-point) parameters.
#[derive(Clone, Debug)]
pub struct Covariance {
    /// Parameter names, in the order of the matrix.
    pub names: Vec<String>,
    /// Covariance matrix in the solver's tangent parametrisation.
    pub matrix: DMatrix<f64>,
}

impl Covariance {
    /// Index of a named parameter.
    pub fn index(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }

    /// Standard deviation of a named parameter.
    pub fn sigma(&self, name: &str) -> Option<f64> {
        let i = self.index(name)?;
        Some(self.matrix[(i, i)].max(0.0).sqrt())
    }
}

/// The covariance of the camera parameters under `model` (module docs, Covariance) and
/// its [`BundleReport::sigma_inflation`]. Points collapsed onto a camera centre
/// ([`MAX_POINT_INFORMATION_RATIO`]) are left out of it.
/// `clusters`, under `PointClustered`: the cluster of each point (indexed like
/// `state.points`; `None`: each point its own).
///
/// [`BundleReport::sigma_inflation`]: super::BundleReport::sigma_inflation
pub(super) fn covariance(
    problem: &Problem<'_>,
    state: &RigState,
    sigma: f64,
    model: CovarianceModel,
    clusters: Option<&[usize]>,
) -> Result<(Covariance, f64)> {
    let names = problem.layout.names();
    let Some(n) = problem.normal_equations(state, sigma * sigma) else {
        return Err(GeometryError::Numerical("linearisation failed at the solution".into()));
    };
    // A point collapsed onto a camera centre cannot be eliminated in floating point: the
    // covariance is that of the problem without its observations (the adjustment itself
    // keeps them).
    let excessive = overinformed_points(&n);
    if !excessive.is_empty() {
        let kept: Vec<BundleObservation> = problem
            .obs
            .iter()
            .zip(&problem.obs_point)
            .filter(|(_, p)| !excessive.contains(p))
            .map(|(o, _)| *o)
            .collect();
        let (_, mut reduced) = self::problem(state, &kept, problem.options)?;
        reduced.prior_weight = problem.prior_weight;
        reduced.depth = problem.depth;
        if !problem.layout.params.iter().all(|p| reduced.layout.params.contains(p)) {
            return Err(GeometryError::Numerical("a parameter lost every observation".into()));
        }
        // Parameters held by [`bundle_adjust_holding`] stay held.
        reduced.layout = problem.layout.clone();
        return covariance(&reduced, state, sigma, model, clusters);
    }
    // A point whose block is singular carries no usable information: left out.
    let Some((s, l_inv)) = reduced_camera_system(&n, |_| 0.0, true) else {
        return Err(GeometryError::Numerical("reduced camera system is not finite".into()));
    };
    let singular = || {
        GeometryError::Numerical(
            "reduced camera system is singular at the solution: a parameter is unobservable".into(),
        )
    };
    let inv = match &n.order {
        None => s.cholesky().ok_or_else(singular)?.inverse(),
        Some(order) => ProfileCholesky::new(&s, order.clone()).ok_or_else(singular)?.inverse(),
    };
    let gaussian = 0.5 * (&inv + inv.transpose()) * (sigma * sigma);
    if model == CovarianceModel::Gaussian {
        return Ok((Covariance { names, matrix: gaussian }, 1.0));
    }
    let Some(scores) = problem.point_scores(state) else {
        return Err(GeometryError::Numerical("linearisation failed at the solution".into()));
    };
    let nc = inv.nrows();
    // Sum of the efficient scores per cluster (compact point index -> cluster).
    let mut sums: BTreeMap<usize, DVector<f64>> = BTreeMap::new();
    for (i, ((gc, gp), li)) in scores.iter().zip(&l_inv).enumerate() {
        // W_p V_p^-1.
        let Some(wv) = li.map(|li| n.w.times(i, &(li.transpose() * li), nc)) else { continue };
        let cluster = match clusters {
            Some(c) => problem.points.get(i).and_then(|&p| c.get(p)).copied().unwrap_or(usize::MAX),
            None => i,
        };
        *sums.entry(cluster).or_insert_with(|| DVector::zeros(nc)) += gc - wv * gp;
    }
    let mut meat = DMatrix::zeros(nc, nc);
    for sp in sums.values() {
        meat.ger(1.0, sp, sp, 1.0);
    }
    // Camera parameters' share of the leverage: fitted residuals are that much smaller.
    let components = 2.0 * problem.obs.len() as f64;
    if components > nc as f64 {
        meat *= components / (components - nc as f64);
    }
    // The angle priors, as modelled: information sigma^2 P, so their meat is sigma^2 (sigma^2 P).
    let s2 = sigma * sigma;
    for row in problem.prior_terms(state) {
        for &(a, da) in &row.entries {
            for &(b, db) in &row.entries {
                meat[(a, b)] += s2 * s2 * da * db;
            }
        }
    }
    let sandwich = &inv * meat * &inv;
    let matrix = 0.5 * (&sandwich + sandwich.transpose());
    let inflation = (0..nc)
        .filter(|&i| gaussian[(i, i)] > 0.0)
        .map(|i| matrix[(i, i)] / gaussian[(i, i)])
        .fold(0.0_f64, f64::max)
        .sqrt();
    Ok((Covariance { names, matrix }, inflation))
}

/// A point whose information (trace of its `V_p`) exceeds this multiple of the median
/// point's. Information grows as the inverse square of depth, so such a point is about
/// `1e4` times nearer than the median one: a point collapsed onto a camera centre (a
/// wrong track "explained" at depth `1e-11` in a 3 px trial), which no lens sees. Its
/// `U` and `W V^-1 W^T` terms are then some `1e24` times the camera parameters'
/// information and cancel to rounding noise, so the reduced camera system is not
/// positive definite although every parameter is observable.
const MAX_POINT_INFORMATION_RATIO: f64 = 1e8;

/// Compact indices of the points whose information exceeds
/// [`MAX_POINT_INFORMATION_RATIO`] times the median point's.
fn overinformed_points(n: &Normal) -> Vec<usize> {
    let mut traces: Vec<f64> = n.v.iter().map(|v| v.trace()).collect();
    traces.sort_by(f64::total_cmp);
    let Some(&median) = traces.get(traces.len() / 2) else { return Vec::new() };
    let limit = MAX_POINT_INFORMATION_RATIO * median;
    n.v.iter().enumerate().filter(|(_, v)| gt(v.trace(), limit)).map(|(p, _)| p).collect()
}

/// The cluster-robust covariance of the camera parameters of a converged `state` (module
/// docs, Covariance) with the points grouped into clusters: points with the same
/// `cluster_of_point` entry (indexed like `state.points`) form one cluster, whose errors may
/// be correlated across all their observations. With every point its own cluster this is
/// the covariance of [`CovarianceModel::PointClustered`]. `sigma_px` weights the angle
/// priors as in [`bundle_adjust`] (its reported `sigma_px`). For diagnostics: coarser
/// clusters (an image region, a surface) test whether errors are correlated across points.
///
/// [`bundle_adjust`]: super::bundle_adjust
pub fn clustered_covariance(
    state: &RigState,
    observations: &[BundleObservation],
    options: &BundleOptions,
    sigma_px: f64,
    cluster_of_point: &[usize],
) -> Result<Covariance> {
    if cluster_of_point.len() != state.points.len() {
        return Err(GeometryError::InvalidOption(format!(
            "{} cluster labels for {} points",
            cluster_of_point.len(),
            state.points.len()
        )));
    }
    if !(sigma_px.is_finite() && sigma_px > 0.0) {
        return Err(GeometryError::InvalidOption(format!("sigma_px must be positive, got {sigma_px}")));
    }
    let (state, problem) = problem(state, observations, options)?;
    let model = CovarianceModel::PointClustered;
    Ok(covariance(&problem, &state, sigma_px, model, Some(cluster_of_point))?.0)
}

/// The scene's depth scale `s` of a state: `-ln` of the mean inverse distance (the log
/// harmonic-mean distance) from the reference left camera, in units of the baseline
/// length (the scale gauge, held by the adjustment), over the points that
/// [`bundle_adjust`] would adjust with these observations (seen at least twice, in front
/// of the cameras), and its standard
/// deviation from the linearisation at `state` with pixel noise `sigma_px` (data and
/// priors; points not eliminated: `sigma_px^2 a^T N^-1 a`). Why: with small rotations the
/// scene's distance in baselines is the badly determined direction of the rig (a
/// receding scene with shifted principal points fits nearly as well), and the camera
/// covariance varies along it.
///
/// [`bundle_adjust`]: super::bundle_adjust
pub fn log_depth_scale(
    state: &RigState,
    observations: &[BundleObservation],
    options: &BundleOptions,
    sigma_px: f64,
) -> Result<(f64, f64)> {
    let opts = BundleOptions { noise_sigma_px: Some(sigma_px), ..options.clone() };
    let (state, problem) = problem(state, observations, &opts)?;
    let numerical = |w: &str| GeometryError::Numerical(format!("depth scale: {w}"));
    let s = log_depth_scale_of(&state, &problem.points).ok_or_else(|| numerical("non-finite point"))?;
    let a = log_depth_scale_jacobian(&state, &problem.points).ok_or_else(|| numerical("non-finite point"))?;
    let n =
        problem.normal_equations(&state, problem.prior_weight).ok_or_else(|| numerical("linearisation"))?;
    let (_, z) = solve_rhs(&n, 0.0, &DVector::zeros(problem.layout.len()), &a)
        .ok_or_else(|| numerical("singular normal equations"))?;
    let q: f64 = a.iter().zip(&z).map(|(ai, zi)| ai.dot(zi)).sum();
    if !(q.is_finite() && q >= 0.0) {
        return Err(numerical("negative variance"));
    }
    Ok((s, sigma_px * q.sqrt()))
}

/// `s = -ln(mean 1/|X|)` over the given points (original indices): the log of their
/// harmonic-mean distance. Inverse distance, not log distance, is averaged because a far
/// point's inverse distance is bounded and nearly linear in its disparity while its log
/// distance is unbounded (measured at 3 px: the mean log distance had sigmas up to 570,
/// carried by a few points near infinity). `None` if any point is not finite or at the
/// origin, or there are none.
pub(super) fn log_depth_scale_of(state: &RigState, points: &[usize]) -> Option<f64> {
    let mut sum = 0.0;
    for &i in points {
        let d = state.points.get(i)?.coords.norm();
        if !(d.is_finite() && d > 0.0) {
            return None;
        }
        sum += 1.0 / d;
    }
    let m = sum / points.len() as f64;
    (!points.is_empty() && m > 0.0).then(|| -m.ln())
}

/// Gradient of [`log_depth_scale_of`] with respect to each point's homogeneous tangent
/// step `d` of [`retract_point`] (compact order):
/// `X^T / (n m |X|^3) (B_xyz - X B_w) / h_w`, `m` the mean inverse distance.
///
/// [`retract_point`]: super::layout::retract_point
pub(super) fn log_depth_scale_jacobian(state: &RigState, points: &[usize]) -> Option<Vec<Vector3<f64>>> {
    let n = points.len() as f64;
    let mut m = 0.0;
    for &i in points {
        m += 1.0 / state.points.get(i)?.coords.norm();
    }
    m /= n;
    points
        .iter()
        .map(|&i| {
            let x = state.points.get(i)?;
            let h = point_homogeneous(x);
            let b = homogeneous_basis(&h);
            let dxdd = (b.fixed_view::<3, 3>(0, 0) - x.coords * b.fixed_view::<1, 3>(3, 0)) / h.w;
            let g = (dxdd.transpose() * x.coords) / (x.coords.norm().powi(3) * n * m);
            g.iter().all(|v| v.is_finite()).then_some(g)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bundle::layout::retract_point;
    use crate::bundle::test_support::{distorted, state_distance};
    use crate::bundle::{
        Motions, RobustLoss, Side, bundle_adjust, bundle_adjust_at_depth_scale, residual_pixels,
    };
    use crate::synthetic::{gauss, perturb, synth};
    use nalgebra::{Point2, Point3, Vector2};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// With 0.5 px noise the covariance of k1 is positive and its error is within a few sigma.
    #[test]
    fn distortion_covariance_is_consistent() {
        let mut s = distorted(17, 150, false);
        let mut rng = ChaCha8Rng::seed_from_u64(170);
        for o in &mut s.obs {
            o.pixel += Vector2::new(gauss(&mut rng), gauss(&mut rng)) * 0.5;
        }
        let opts = BundleOptions { estimate_distortion: true, ..BundleOptions::default() };
        let res = bundle_adjust(&s.truth, &s.obs, &opts).unwrap();
        let k = |d: &crate::distortion::Distortion, name: &str| d.param(name).unwrap();
        for (n, est, tru) in [
            ("left.k1", k(&res.state.left_distortion, "k1"), k(&s.truth.left_distortion, "k1")),
            ("right.k2", k(&res.state.right_distortion, "k2"), k(&s.truth.right_distortion, "k2")),
        ] {
            let sigma = res.covariance.sigma(n).unwrap();
            eprintln!("{n}: est {est:.5} true {tru:.5} sigma {sigma:.5}");
            // 5 sigma: one seed, a failure here is a real inconsistency, not bad luck.
            assert!(sigma > 0.0 && (est - tru).abs() < 5.0 * sigma, "{n}: {est} vs {tru}, sigma {sigma}");
        }
    }

    /// Commanded angles as differences of noisy readings ([`AnglePrior::ReadingDifferences`]):
    /// every view's reading of every joint, view 0's included, gets Gaussian noise `sigma`.
    ///
    /// [`AnglePrior::ReadingDifferences`]: crate::bundle::AnglePrior::ReadingDifferences
    fn scatter_readings(motions: &mut Motions, sigma: f64, rng: &mut ChaCha8Rng) {
        if let Motions::Joints { commanded, .. } = motions {
            let reference: Vec<f64> =
                (0..commanded.first().map_or(0, Vec::len)).map(|_| sigma * gauss(rng)).collect();
            for row in commanded.iter_mut().skip(1) {
                for (c, r0) in row.iter_mut().zip(&reference) {
                    *c += sigma * gauss(rng) - r0;
                }
            }
        }
    }

    /// Monte-Carlo spread of `left.fx` and `left.cx` against the mean predicted sigma of
    /// both covariance models, for errors built by `err(point, side, rng)`.
    fn spread_and_predictions(
        err: &mut dyn FnMut(usize, &BundleObservation, &mut ChaCha8Rng) -> Vector2<f64>,
        names: &[&str],
    ) -> Vec<(f64, f64, f64)> {
        let base = synth(8, 80, 0.0, 0.0, false);
        let trials = 40;
        let mut rng = ChaCha8Rng::seed_from_u64(801);
        let mut est = vec![Vec::new(); names.len()];
        let mut pred = vec![(0.0, 0.0); names.len()];
        let sigma_prior = BundleOptions::default().angle_prior_sigma.unwrap_or(1e-3);
        for trial in 0..trials {
            // Commanded angles from noisy readings, as the prior claims.
            let mut start = base.truth.clone();
            scatter_readings(&mut start.motions, sigma_prior, &mut rng);
            let obs: Vec<BundleObservation> = base
                .obs
                .iter()
                .map(|o| BundleObservation { pixel: o.pixel + err(trial, o, &mut rng), ..*o })
                .collect();
            let opts = BundleOptions {
                robust: RobustLoss::None,
                covariance_model: CovarianceModel::PointClustered,
                // Both error models below have 1 px per component in total; the prior is
                // weighted by it in the fit and in both covariances (as the estimator's
                // maximum-likelihood pass does with its noise estimate).
                noise_sigma_px: Some(1.0),
                ..BundleOptions::default()
            };
            let res = bundle_adjust(&start, &obs, &opts).unwrap();
            let gauss = bundle_adjust(
                &res.state,
                &obs,
                &BundleOptions { covariance_model: CovarianceModel::Gaussian, max_iterations: 1, ..opts },
            )
            .unwrap();
            assert!(res.report.sigma_inflation >= 1.0 - 0.5 && gauss.report.sigma_inflation == 1.0);
            for (i, n) in names.iter().enumerate() {
                let (l, r) = (&res.state.left, &res.state.right);
                est[i].push(match *n {
                    "left.fx" => l.fx,
                    "left.cx" => l.cx,
                    _ => r.fy,
                });
                pred[i].0 += gauss.covariance.sigma(n).unwrap() / trials as f64;
                pred[i].1 += res.covariance.sigma(n).unwrap() / trials as f64;
            }
        }
        est.iter()
            .zip(&pred)
            .map(|(v, p)| {
                let n = v.len() as f64;
                let mean = v.iter().sum::<f64>() / n;
                ((v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt(), p.0, p.1)
            })
            .collect()
    }

    /// The clustered covariance: with i.i.d. noise it agrees with the Gaussian one (the
    /// sandwich's expectation is `sigma^2 S^-1`); when every observation of a point in one
    /// camera carries the same offset (a tracked feature's localisation bias), the
    /// Gaussian sigmas are wrong (here 1.4-2.8x too large: the point absorbs most of a
    /// shared offset; measured empirical/clustered 0.83-1.09) and the clustered ones
    /// follow the spread. 40 trials:
    /// a sample standard deviation is within about 25 % of the truth (2 sigma), hence the
    /// 0.7-1.4 band; the correlated case must separate the models by more than that.
    #[test]
    fn clustered_covariance_follows_correlated_errors() {
        let names = ["left.fx", "left.cx", "right.fy"];
        let iid = spread_and_predictions(&mut |_, _, rng| Vector2::new(gauss(rng), gauss(rng)), &names);
        for ((emp, g, c), n) in iid.iter().zip(names) {
            eprintln!("iid {n}: empirical {emp:.4}, gaussian {g:.4}, clustered {c:.4}");
            assert!((0.85..1.18).contains(&(c / g)), "{n}: clustered {c} vs gaussian {g}");
            assert!((0.7..1.4).contains(&(emp / c)), "{n}: empirical {emp} vs clustered {c}");
        }
        // Offset per (point, side), shared by every view, plus 0.3 px i.i.d. noise.
        let mut offsets: std::collections::HashMap<(usize, usize, bool), Vector2<f64>> =
            std::collections::HashMap::new();
        let mut salt = ChaCha8Rng::seed_from_u64(802);
        let corr = spread_and_predictions(
            &mut |trial, o, rng| {
                let key = (trial, o.point, o.side == Side::Right);
                let b =
                    *offsets.entry(key).or_insert_with(|| Vector2::new(gauss(&mut salt), gauss(&mut salt)));
                0.95 * b + 0.3 * Vector2::new(gauss(rng), gauss(rng))
            },
            &names,
        );
        let mut separated = false;
        for ((emp, g, c), n) in corr.iter().zip(names) {
            eprintln!("correlated {n}: empirical {emp:.4}, gaussian {g:.4}, clustered {c:.4}");
            assert!((0.7..1.4).contains(&(emp / c)), "{n}: empirical {emp} vs clustered {c}");
            separated |= emp / g > 1.6 || g / emp > 1.6;
        }
        assert!(separated, "the correlated errors did not make the Gaussian sigmas wrong: {corr:?}");
    }

    /// [`clustered_covariance`]: with every point its own cluster it is the covariance of
    /// `PointClustered` (the same sums in the same order, at the state as re-normalised by
    /// the adjustment's set-up, which moves the axes' unit directions in the last bit; the
    /// covariance's conditioning amplifies that by up to ~1e4: measured 1.2e-12 relative,
    /// allowed 1e-10); merging
    /// points two by two, whose i.i.d. errors are independent, leaves its expectation
    /// unchanged (one draw, 120 clusters against 240 with 25 camera parameters: measured
    /// ratios 0.76-1.06; the variance of a sandwich term from ~100 effective clusters is
    /// within about 30 % at 2 sigma, hence the 0.55-1.45 band); bad labels and noise are
    /// errors.
    #[test]
    fn clustered_covariance_by_labels() {
        let mut s = synth(9, 240, 0.0, 0.0, false);
        let mut rng = ChaCha8Rng::seed_from_u64(803);
        for o in &mut s.obs {
            o.pixel += Vector2::new(gauss(&mut rng), gauss(&mut rng)) * 0.5;
        }
        let opts = BundleOptions {
            robust: RobustLoss::None,
            noise_sigma_px: Some(0.5),
            covariance_model: CovarianceModel::PointClustered,
            ..BundleOptions::default()
        };
        let res = bundle_adjust(&s.truth, &s.obs, &opts).unwrap();
        let n = res.state.points.len();
        let own: Vec<usize> = (0..n).collect();
        let same = clustered_covariance(&res.state, &s.obs, &opts, 0.5, &own).unwrap();
        assert_eq!(same.names, res.covariance.names);
        let scale = res.covariance.matrix.amax();
        let rel = (&same.matrix - &res.covariance.matrix).amax() / scale;
        assert!(rel <= 1e-10, "{rel:e}");
        let pairs: Vec<usize> = (0..n).map(|p| p / 2).collect();
        let merged = clustered_covariance(&res.state, &s.obs, &opts, 0.5, &pairs).unwrap();
        for (i, name) in res.covariance.names.iter().enumerate() {
            let ratio = merged.matrix[(i, i)] / res.covariance.matrix[(i, i)];
            eprintln!("{name}: merged / own variance {ratio:.3}");
            assert!((0.55..1.45).contains(&ratio), "{name}: variance ratio {ratio}");
        }
        assert!(clustered_covariance(&res.state, &s.obs, &opts, 0.5, &pairs[1..]).is_err());
        assert!(clustered_covariance(&res.state, &s.obs, &opts, f64::NAN, &pairs).is_err());
        assert!(clustered_covariance(&res.state, &s.obs, &opts, 0.0, &pairs).is_err());
    }

    #[test]
    fn covariance_predicts_the_spread() {
        let base = synth(8, 80, 0.0, 0.0, false);
        let opts = BundleOptions { robust: RobustLoss::None, ..BundleOptions::default() };
        let sigma_prior = opts.angle_prior_sigma.unwrap();
        let trials = 50;
        let mut fx = Vec::new();
        let mut predicted = Vec::new();
        let mut rng = ChaCha8Rng::seed_from_u64(800);
        for _ in 0..trials {
            let obs: Vec<BundleObservation> = base
                .obs
                .iter()
                .map(|o| BundleObservation {
                    pixel: o.pixel + Vector2::new(gauss(&mut rng), gauss(&mut rng)),
                    ..*o
                })
                .collect();
            // Commanded angles from noisy readings, as the prior claims.
            let mut start = base.truth.clone();
            scatter_readings(&mut start.motions, sigma_prior, &mut rng);
            let res = bundle_adjust(&start, &obs, &opts).unwrap();
            assert!(res.report.converged, "{:?}", res.report);
            fx.push(res.state.left.fx);
            predicted.push(res.covariance.sigma("left.fx").unwrap());
        }
        let n = trials as f64;
        let mean = fx.iter().sum::<f64>() / n;
        let std = (fx.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        let pred = predicted.iter().sum::<f64>() / n;
        let ratio = std / pred;
        eprintln!("fx: empirical std {std:.4}, predicted {pred:.4}, ratio {ratio:.3}");
        assert!((0.7..1.4).contains(&ratio), "empirical {std} predicted {pred}");
    }

    /// The depth scale's gradient over each point's homogeneous tangent step against
    /// central differences of `retract_point` (step 1e-6: truncation ~1e-12, rounding
    /// ~1e-10 relative to the entry).
    #[test]
    fn depth_scale_jacobian_matches_finite_differences() {
        let s = synth(11, 40, 0.0, 0.0, false);
        let points: Vec<usize> = (0..s.truth.points.len()).collect();
        let a = log_depth_scale_jacobian(&s.truth, &points).unwrap();
        let h = 1e-6;
        for i in [0, 7, 19, 39] {
            for k in 0..3 {
                let mut d = Vector3::zeros();
                d[k] = h;
                let mut plus = s.truth.clone();
                plus.points[i] = retract_point(&s.truth.points[i], &d).unwrap();
                let mut minus = s.truth.clone();
                minus.points[i] = retract_point(&s.truth.points[i], &-d).unwrap();
                let fd = (log_depth_scale_of(&plus, &points).unwrap()
                    - log_depth_scale_of(&minus, &points).unwrap())
                    / (2.0 * h);
                let scale = a[i].norm().max(1e-12);
                assert!((fd - a[i][k]).abs() < 1e-6 * scale, "point {i} dof {k}: fd {fd:e} vs {:e}", a[i][k]);
            }
        }
    }

    /// The profile at the estimate's own depth scale is the estimate (to the solver's
    /// tolerance), and at `s + 2 sigma_s` it holds `s` there and costs about 4 in chi-square
    /// if the depth scale were linear; measured 3.07 on this 80-point scene (sigma_s 0.21:
    /// the profile is flatter than its linearisation on the far side, which is why the
    /// estimate profiles it), so 1.5-6 is allowed.
    #[test]
    fn depth_scale_profile_holds_the_scale_and_costs_its_chi_square() {
        let base = synth(12, 80, 1.0, 0.0, false);
        let opts =
            BundleOptions { robust: RobustLoss::None, noise_sigma_px: Some(1.0), ..BundleOptions::default() };
        let est = bundle_adjust(&perturb(&base.truth, 120), &base.obs, &opts).unwrap();
        assert!(est.report.converged, "{:?}", est.report);
        let (s0, sig) = log_depth_scale(&est.state, &base.obs, &opts, 1.0).unwrap();
        assert!(sig > 0.0 && sig < 1.0, "sigma_s {sig}");
        let cost = |st: &RigState| {
            let (_, p) = problem(st, &base.obs, &opts).unwrap();
            p.evaluate(st).unwrap().cost
        };
        let tol = 1e-3 * sig;
        let same = bundle_adjust_at_depth_scale(&est.state, &base.obs, &opts, s0, tol).unwrap();
        assert!(
            state_distance(&same.state, &est.state) < 1e-6,
            "{}",
            state_distance(&same.state, &est.state)
        );
        let far = bundle_adjust_at_depth_scale(&est.state, &base.obs, &opts, s0 + 2.0 * sig, tol).unwrap();
        let (s1, _) = log_depth_scale(&far.state, &base.obs, &opts, 1.0).unwrap();
        assert!((s1 - s0 - 2.0 * sig).abs() < 1e-2 * sig, "held at {s1}, wanted {}", s0 + 2.0 * sig);
        let dchi2 = 2.0 * (cost(&far.state) - cost(&est.state));
        eprintln!("s {s0:.4} sigma_s {sig:.4}: chi-square rise at +2 sigma_s {dchi2:.3}");
        assert!((1.5..6.0).contains(&dchi2), "chi-square rise {dchi2}");
        // Its covariance is the unconstrained linearisation at the profile point.
        assert_eq!(far.covariance.names, est.covariance.names);
        assert!(bundle_adjust_at_depth_scale(&est.state, &base.obs, &opts, s0, 0.0).is_err());
    }

    /// Regression (calibration experiment, 3 px, seed 53): a wrong track "explained" by a
    /// point at depth 1e-11 made the reduced camera system indefinite by rounding (its
    /// terms some 1e24 times the cameras' information) and failed the whole estimate.
    /// Such a point now leaves the covariance, which then equals the covariance without
    /// its observations (to 1e-9 relative: the same sums in the same order); kept, it
    /// makes this covariance differ from that by more than that (rounding noise).
    #[test]
    fn a_point_at_a_camera_centre_leaves_the_covariance() {
        let s = synth(13, 60, 0.5, 0.0, false);
        let mut state = s.truth.clone();
        state.points[0] = Point3::from(state.left.unproject(&Point2::new(400.0, 300.0)) * 1e-11);
        let others: Vec<BundleObservation> = s.obs.iter().copied().filter(|o| o.point != 0).collect();
        let mut all = others.clone();
        for view in 0..3 {
            for side in [Side::Left, Side::Right] {
                let o = BundleObservation { point: 0, view, side, pixel: Point2::origin() };
                if let Some(r) = residual_pixels(&state, &o).filter(|r| r.iter().all(|v| v.is_finite())) {
                    all.push(BundleObservation { pixel: Point2::from(r), ..o });
                }
            }
        }
        assert!(all.len() >= others.len() + 2, "the collapsed point needs two observations");
        let opts = BundleOptions::default();
        let own: Vec<usize> = (0..state.points.len()).collect();
        let with = clustered_covariance(&state, &all, &opts, 0.5, &own).unwrap();
        let without = clustered_covariance(&state, &others, &opts, 0.5, &own).unwrap();
        assert_eq!(with.names, without.names);
        let scale = without.matrix.abs().max();
        assert!((&with.matrix - &without.matrix).abs().max() <= 1e-9 * scale);
    }
}
