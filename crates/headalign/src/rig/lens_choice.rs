//! The lens model of self-calibration ([`LensChoice`]) and its automatic choice
//! ([`LensChoice::Auto`]): the model and its terms, among the pinhole, radial-tangential
//! (`k1 k2`; `k1 k2 p1 p2`; `k1 k2 p1 p2 k3`) and equidistant (`k1 k2`; `k1..k4`)
//! lenses ([`LensSpec::candidates`]), and the double sphere (`xi alpha`, started from
//! the `alpha` closest to the base lens's profile) when the observed field reaches beyond
//! [`WIDE_FIELD`] (60 deg off the axis), decided by the Bayesian information criterion on
//! one common set of observations.
//!
//! What it computes: the calibration with the radial-tangential `k1 k2` model
//! ([`BASE_LENS`]: run through the whole chain, so its robust re-selection decides which
//! observations are inliers); then, on exactly that adjustment's observations and points,
//! a least-squares refit of each candidate, each from the best start at hand
//! (`candidate_start`): a nested candidate from the fit it extends (its added terms
//! zero), the pinhole from the base state without lens, the equidistant `k1 k2` from the
//! lens whose radial profile is closest to the base lens's over the observed field; and
//! per candidate
//!
//! ```text
//! chi2 = RSS / sigma^2,   BIC = chi2 + p ln(n)
//! ```
//!
//! with `RSS` the sum of squared residuals (pixels^2), `sigma` the smallest of the
//! candidates' own noise estimates (the best-fitting model's, pixels: a model that misses
//! a real lens term inflates its own estimate and would shrink every chi-square
//! difference), `p` the number of lens coefficients estimated (both cameras) and `n` the
//! number of residual components (twice the observations). The smallest `BIC` wins
//! (Schwarz 1978; it penalises each added coefficient by `ln n`, about 9 chi-square units
//! for 2,000 observations, so that a lens term is kept only when the data need it). A
//! candidate whose refit fails (a singular system, non-finite residuals) is reported in
//! [`LensSelection::failed`] with its reason and left out; only when every candidate
//! fails is the choice an error. When the winner is not the base model, the chain runs
//! again with it, its refit a further start of the adjustment (`from_refit`: one run of
//! the chain, not the two-pass lens start), and with the full chain of that model when
//! this run fails or ends implausibly, so that the reported calibration, its inliers and
//! its sigmas are that model's own (the bootstrap of the lens sigmas runs for it alone).
//! The chain is the reference chain of [`crate::calibrate::calibrate_rig`] or the sequence chain of
//! [`crate::calibrate::calibrate_sequence`] (`calibrate`'s `choose_lens`, without `from_refit`); a sequence's
//! refits hold its segment gauges as its adjustment does.
//!
//! Degrees of freedom: per camera 0 (pinhole), or the candidate's coefficients (at most
//! those of [`crate::calibrate::CalibrateOptions::lens_terms`], which caps the candidates' terms under
//! `Auto`). Units: residuals in pixels, chi-square and BIC dimensionless.
//!
//! Pitfalls: the criterion compares fits, not truths: on a narrow lens the two distorted
//! models fit almost equally (their chi-squares differ by a few units), and either is
//! then a good description of the image; the choice matters for extrapolation beyond the
//! observed field. The tangential terms trade off against the principal point: with few
//! motions their chi-square gain is small and BIC keeps them only when it exceeds their
//! penalty. The criterion assumes independent Gaussian pixel errors at the estimated
//! `sigma`; correlated tracking errors inflate every chi-square alike.

use headalign_geometry::bundle::{
    BundleObservation, BundleOptions, RigState, RobustLoss, Side, bundle_adjust, residual_pixels,
};
use headalign_geometry::distortion::{Distortion, DistortionTerms, LensKind};
use headalign_geometry::lens::{MAX_PARAMS, MODELS};
use serde::Serialize;

use super::FINAL_ITERATIONS;
use crate::error::AlignError;

/// The lens model of [`crate::calibrate::CalibrateOptions::lens`] and
/// [`crate::verge_tilt::EstimationOptions::lens`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum LensChoice {
    /// No distortion estimated (the pinhole, or a known lens already removed).
    #[default]
    Pinhole,
    /// Estimate this model's coefficients.
    Model(LensKind),
    /// Choose among the three by the criterion of the module docs, and report it.
    Auto,
}

impl LensChoice {
    /// The estimated model, if any (`None` for the pinhole and for `Auto`).
    pub fn kind(self) -> Option<LensKind> {
        match self {
            LensChoice::Model(kind) => Some(kind),
            LensChoice::Pinhole | LensChoice::Auto => None,
        }
    }

    /// The model named `pinhole`, `auto`, or any name of the lens table
    /// ([`LensKind::parse`]: `radtan`, `plumb_bob`, `equidistant`, `fisheye`, `ds`, ...).
    pub fn parse(name: &str) -> Option<Self> {
        match name.trim().to_ascii_lowercase().as_str() {
            "pinhole" | "none" => Some(LensChoice::Pinhole),
            "auto" => Some(LensChoice::Auto),
            other => LensKind::parse(other).map(LensChoice::Model),
        }
    }

    /// The name users give it (`pinhole`, `radtan`, `equidistant`, `ds`, `auto`).
    pub fn name(self) -> &'static str {
        match self {
            LensChoice::Pinhole => "pinhole",
            LensChoice::Model(kind) => kind.kalibr_name(),
            LensChoice::Auto => "auto",
        }
    }
}

/// One candidate of the automatic choice: a model and the coefficients it estimates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LensSpec {
    /// The model (`None`: the pinhole).
    pub kind: Option<LensKind>,
    /// Its coefficients (unused for the pinhole).
    pub terms: DistortionTerms,
}

impl LensSpec {
    /// The candidates of [`LensChoice::Auto`] whose terms do not exceed `max_terms`, in
    /// the order pinhole; radtan `k1 k2`, `k1 k2 p1 p2`, `k1 k2 p1 p2 k3`; equidistant
    /// `k1 k2`, `k1..k4` (each nested model after the one it extends: its start).
    pub fn candidates(max_terms: DistortionTerms) -> Vec<LensSpec> {
        let mut out = vec![LensSpec { kind: None, terms: DistortionTerms::Radial2 }];
        // Every narrow model of the lens table with parameters, at each level of terms up
        // to `max_terms` that adds parameters to the level before.
        for m in MODELS.iter().filter(|m| !m.param_names().is_empty() && m.max_half_fov_deg() <= 90.0) {
            let mut last = 0;
            for terms in DistortionTerms::LEVELS.into_iter().filter(|t| t.count() <= max_terms.count()) {
                if m.estimated(terms) > last {
                    last = m.estimated(terms);
                    out.push(LensSpec { kind: Some(m.kind()), terms });
                }
            }
        }
        out
    }

    /// The lens choice of a calibration with this model.
    pub fn choice(self) -> LensChoice {
        self.kind.map_or(LensChoice::Pinhole, LensChoice::Model)
    }

    /// `pinhole`, `radtan` or `equidistant`.
    pub fn model(self) -> &'static str {
        self.choice().name()
    }

    /// The coefficients estimated per camera, by name (`k1`, `k2`, `p1`, ...; none for
    /// the pinhole).
    pub fn term_names(self) -> Vec<String> {
        self.kind.map_or_else(Vec::new, |kind| {
            let names = kind.coefficient_names();
            self.terms.params(kind).iter().filter_map(|&i| names.get(i).map(|n| (*n).to_string())).collect()
        })
    }

    /// The model and its terms in words (`radtan k1 k2 p1 p2`, `pinhole`).
    pub fn label(self) -> String {
        std::iter::once(self.model().to_string()).chain(self.term_names()).collect::<Vec<_>>().join(" ")
    }
}

/// One candidate of the automatic choice.
#[derive(Debug, Clone, Serialize)]
pub struct LensCandidate {
    /// `pinhole`, `radtan` or `equidistant`.
    pub model: String,
    /// The coefficients estimated per camera (`k1`, `k2`, `p1`, ...; empty for the pinhole).
    pub terms: Vec<String>,
    /// Lens coefficients estimated, both cameras.
    pub parameters: usize,
    /// RMS reprojection error of the refit, pixels.
    pub rms_px: f64,
    /// Sum of squared residuals over the noise variance.
    pub chi2: f64,
    /// `chi2 + parameters ln(n)`.
    pub bic: f64,
}

/// A candidate of the automatic choice whose refit failed: left out of the choice.
#[derive(Debug, Clone, Serialize)]
pub struct FailedCandidate {
    /// The model and its terms (`radtan k1 k2 p1 p2`).
    pub candidate: String,
    /// Why, in one line.
    pub reason: String,
}

/// How [`LensChoice::Auto`] chose.
#[derive(Debug, Clone, Serialize)]
pub struct LensSelection {
    /// The model kept (`pinhole`, `radtan`, `equidistant`).
    pub chosen: String,
    /// The coefficients of the model kept, per camera (`k1`, `k2`, ...).
    pub terms: Vec<String>,
    /// The criterion, in words, with its numbers.
    pub reason: String,
    /// Residual components `n` (twice the common observations).
    pub residuals: usize,
    /// The noise sigma of the chi-squares, pixels: the smallest of the candidates' own
    /// noise estimates (the best-fitting model's).
    pub sigma_px: f64,
    /// Every candidate refitted, in the order of [`LensSpec::candidates`].
    pub candidates: Vec<LensCandidate>,
    /// The candidates whose refit failed (left out), with the reason.
    pub failed: Vec<FailedCandidate>,
    /// The model and terms kept.
    #[serde(skip)]
    pub spec: LensSpec,
    /// The kept candidate's refitted state (cameras, lenses, poses, points of the
    /// compared observations): a start of that model's own calibration.
    #[serde(skip)]
    pub state: RigState,
}

/// The model every candidate is compared on: the radial-tangential `k1 k2` (module docs).
pub const BASE_LENS: LensSpec =
    LensSpec { kind: Some(LensKind::RadialTangential), terms: DistortionTerms::Radial2 };

/// A candidate refitted: its state, sum of squared residuals (pixels^2) and its own
/// noise estimate (pixels).
struct Refit {
    spec: LensSpec,
    state: RigState,
    rss: f64,
    sigma_px: f64,
}

/// The criterion of the module docs: each candidate of [`LensSpec::candidates`] (terms up
/// to `max_terms`) refitted by least squares on exactly the observations `obs`, from
/// `state` (a radial-tangential solution) or the nearest candidate fitted before it
/// ([`candidate_start`]); chi-square at the smallest of the candidates' noise estimates;
/// the smallest BIC wins. A candidate whose refit fails is reported in
/// [`LensSelection::failed`] and left out; only when every one fails is it an error.
/// `bundle` carries the intrinsic constraints and the rest of the adjustment's options;
/// its loss, noise, lens flags and iteration floor are set here. Shared by
/// [`crate::calibrate::calibrate_rig`] and the verge/tilt estimator
/// ([`crate::verge_tilt::EstimationOptions::lens`]).
pub(crate) fn select_lens(
    state: &RigState,
    obs: &[BundleObservation],
    bundle: &BundleOptions,
    max_terms: DistortionTerms,
) -> Result<LensSelection, AlignError> {
    let n = 2 * obs.len();
    let mut fitted: Vec<Refit> = Vec::new();
    let mut failed = Vec::new();
    let mut specs = LensSpec::candidates(max_terms);
    // The double sphere competes when the lens is wide (module docs).
    if observed_field(state, obs).iter().any(|&f| f > WIDE_FIELD) {
        let wide = MODELS.iter().filter(|m| m.max_half_fov_deg() > 90.0);
        specs.extend(wide.map(|m| LensSpec { kind: Some(m.kind()), terms: DistortionTerms::Radial2 }));
    }
    for spec in specs {
        let start = candidate_start(spec, state, &fitted, obs);
        match refit(spec, start, obs, bundle) {
            Ok(r) => fitted.push(r),
            Err(reason) => failed.push(FailedCandidate { candidate: spec.label(), reason }),
        }
    }
    let sigma = fitted.iter().map(|r| r.sigma_px).fold(f64::INFINITY, f64::min).max(1e-6);
    let candidates: Vec<LensCandidate> = fitted
        .iter()
        .map(|r| {
            let parameters = 2 * r.spec.term_names().len();
            let chi2 = r.rss / (sigma * sigma);
            LensCandidate {
                model: r.spec.model().to_string(),
                terms: r.spec.term_names(),
                parameters,
                rms_px: (r.rss / obs.len().max(1) as f64).sqrt(),
                chi2,
                bic: chi2 + parameters as f64 * (n.max(1) as f64).ln(),
            }
        })
        .collect();
    let Some(best) = (0..candidates.len()).min_by(|&a, &b| candidates[a].bic.total_cmp(&candidates[b].bic))
    else {
        let reasons: Vec<String> = failed.iter().map(|f| format!("{}: {}", f.candidate, f.reason)).collect();
        return Err(AlignError::Geometry {
            step: "lens choice".into(),
            cause: headalign_geometry::GeometryError::Degenerate(format!(
                "every lens candidate failed ({})",
                reasons.join("; ")
            )),
        });
    };
    let reason = selection_reason(&candidates, &failed, best, obs.len(), n, sigma);
    let kept = fitted.swap_remove(best);
    Ok(LensSelection {
        chosen: kept.spec.model().to_string(),
        terms: kept.spec.term_names(),
        reason,
        residuals: n,
        sigma_px: sigma,
        candidates,
        failed,
        spec: kept.spec,
        state: kept.state,
    })
}

/// The criterion in words: every candidate's BIC, the winner's margin, the failures.
fn selection_reason(
    candidates: &[LensCandidate],
    failed: &[FailedCandidate],
    best: usize,
    observations: usize,
    n: usize,
    sigma: f64,
) -> String {
    let label = |c: &LensCandidate| {
        std::iter::once(c.model.clone()).chain(c.terms.clone()).collect::<Vec<_>>().join(" ")
    };
    let runner_up = candidates
        .iter()
        .enumerate()
        .filter(|(i, _)| *i != best)
        .map(|(_, c)| c.bic - candidates[best].bic)
        .fold(f64::INFINITY, f64::min);
    let listed: Vec<String> = candidates.iter().map(|c| format!("{} {:.1}", label(c), c.bic)).collect();
    let mut reason = format!(
        "smallest BIC = chi2 + p ln(n) on the same {observations} observations (n = {n}, sigma {sigma:.3} px): {}; {} is lower than the next by {}",
        listed.join(", "),
        label(&candidates[best]),
        if runner_up.is_finite() { format!("{runner_up:.1}") } else { "(no other candidate)".into() }
    );
    if !failed.is_empty() {
        let names: Vec<&str> = failed.iter().map(|f| f.candidate.as_str()).collect();
        reason.push_str(&format!("; left out (refit failed): {}", names.join(", ")));
    }
    reason
}

/// The start of candidate `spec`'s refit: the last candidate fitted of the same model
/// whose terms it extends (its extra coefficients zero), else `state` with the lens the
/// model takes from it: none for the pinhole, `state`'s own radial-tangential lens with
/// the coefficients outside `spec`'s terms zeroed, or the equidistant lens closest to
/// `state`'s radial profile over the observed field ([`profile_like`]).
fn candidate_start(
    spec: LensSpec,
    state: &RigState,
    fitted: &[Refit],
    obs: &[BundleObservation],
) -> RigState {
    // The fit's own lens with the parameters outside `spec`'s terms zeroed.
    let keep = |d: Distortion, kind: LensKind| {
        let mut p = [0.0; MAX_PARAMS];
        for &i in spec.terms.params(kind) {
            p[i] = d.params()[i];
        }
        Distortion::from_params(kind, p)
    };
    let nested = fitted.iter().rev().find(|r| r.spec.kind == spec.kind && r.spec.kind.is_some());
    let mut start = nested.map_or_else(|| state.clone(), |r| r.state.clone());
    let lenses = match spec.kind {
        None => [Distortion::default(); 2],
        Some(kind) if nested.is_some() || spec.kind == BASE_LENS.kind => {
            [keep(start.left_distortion, kind), keep(start.right_distortion, kind)]
        }
        Some(kind) => {
            let field = observed_field(state, obs);
            [
                profile_like(kind, &state.left_distortion, field[0], spec.terms),
                profile_like(kind, &state.right_distortion, field[1], spec.terms),
            ]
        }
    };
    [start.left_distortion, start.right_distortion] = lenses;
    start
}

/// Candidate `spec`'s least-squares refit from `start` on `obs` (module docs); the error
/// in one line.
fn refit(
    spec: LensSpec,
    start: RigState,
    obs: &[BundleObservation],
    bundle: &BundleOptions,
) -> Result<Refit, String> {
    let ls = BundleOptions {
        robust: RobustLoss::None,
        noise_sigma_px: None,
        max_iterations: bundle.max_iterations.max(FINAL_ITERATIONS),
        estimate_distortion: spec.kind.is_some(),
        distortion_terms: spec.terms,
        ..bundle.clone()
    };
    let fit = bundle_adjust(&start, obs, &ls).map_err(|e| one_line(&e.to_string()))?;
    let rss: f64 = obs.iter().filter_map(|o| residual_pixels(&fit.state, o)).map(|r| r.norm_squared()).sum();
    let sigma_px = fit.report.sigma_px;
    if !(rss.is_finite() && sigma_px.is_finite() && sigma_px > 0.0) {
        return Err(format!("non-finite residuals (RSS {rss}, sigma {sigma_px})"));
    }
    Ok(Refit { spec, state: fit.state, rss, sigma_px })
}

/// The first line of `text`, at most 200 characters.
fn one_line(text: &str) -> String {
    let line = text.lines().next().unwrap_or("");
    match line.char_indices().nth(200) {
        Some((i, _)) => format!("{}...", &line[..i]),
        None => line.to_string(),
    }
}

/// The undistorted normalised radius (of the base fit, `observed_field`) beyond which
/// the double sphere is a candidate of [`LensChoice::Auto`]: `tan 60 deg`. Narrower
/// fields are described by the pinhole-plane models (the radial-tangential and
/// equidistant candidates), and there the double sphere would only add a refit.
pub const WIDE_FIELD: f64 = 1.732_050_807_568_877_2;

/// The lens of the model `kind` with the parameters of `terms` whose radial profile is
/// closest, over the observed field (pinhole-plane radii up to `field`), to the base
/// radial-tangential lens `radtan`'s profile `r (1 + k1 r^2 + k2 r^4 + k3 r^6)` (its
/// tangential terms ignored): the lens table's `fit_radial_profile` (the equidistant
/// model: least squares over 50 radii, all zero when the field is empty or the fit
/// singular; the double sphere: `xi = 0` and the best `alpha` on a grid of 0.01 in `[0,
/// 0.95]`, 0.5 when the field is empty).
fn profile_like(kind: LensKind, radtan: &Distortion, field: f64, terms: DistortionTerms) -> Distortion {
    let [k1, k2, k3] = ["k1", "k2", "k3"].map(|n| radtan.param(n).unwrap_or(0.0));
    let profile = |r: f64| {
        let r2 = r * r;
        r * (1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2)
    };
    let model = kind.model();
    Distortion::from_params(kind, model.fit_radial_profile(&profile, field, model.estimated(terms)))
}

/// Per camera (left, right), the largest undistorted normalised radius of the
/// observations under `state`'s cameras and lenses (the field the lens is seen over).
fn observed_field(state: &RigState, obs: &[BundleObservation]) -> [f64; 2] {
    let mut field = [0.0f64; 2];
    for o in obs {
        let (k, d, slot) = match o.side {
            Side::Left => (&state.left, &state.left_distortion, 0),
            Side::Right => (&state.right, &state.right_distortion, 1),
        };
        if let Ok(p) = d.undistort_pixel(k, &o.pixel) {
            let r = ((p.x - k.cx) / k.fx).hypot((p.y - k.cy) / k.fy);
            if r.is_finite() {
                field[slot] = field[slot].max(r);
            }
        }
    }
    field
}

/// The coefficients estimated of `lens`: `given` when given; otherwise every candidate's
/// terms for [`LensChoice::Auto`] (it chooses them) and `k1 k2` for a given model.
pub fn lens_terms(lens: LensChoice, given: Option<DistortionTerms>) -> DistortionTerms {
    match (lens, given) {
        (_, Some(t)) => t,
        (LensChoice::Auto, None) => DistortionTerms::Full5,
        (_, None) => DistortionTerms::Radial2,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector2;

    /// The candidates nest in order and `lens_terms` caps them: `k1 k2` models only with
    /// `radial`, the tangential and `k1..k4` ones with `4`, `k3` with `5`.
    #[test]
    fn candidates_are_capped_by_the_terms() {
        let labels = |t| LensSpec::candidates(t).into_iter().map(LensSpec::label).collect::<Vec<String>>();
        assert_eq!(labels(DistortionTerms::Radial2), ["pinhole", "radtan k1 k2", "equidistant k1 k2"]);
        assert_eq!(labels(DistortionTerms::Full4).len(), 5);
        assert_eq!(
            labels(DistortionTerms::Full5),
            [
                "pinhole",
                "radtan k1 k2",
                "radtan k1 k2 p1 p2",
                "radtan k1 k2 p1 p2 k3",
                "equidistant k1 k2",
                "equidistant k1 k2 k3 k4"
            ]
        );
        assert!(LensSpec::candidates(DistortionTerms::Full5).contains(&BASE_LENS));
    }

    /// The equidistant start of a radial-tangential lens follows its radial profile over
    /// the field: EuRoC's `k1 = -0.283`, `k2 = 0.074` out to a normalised radius of 1.0
    /// (the corner of a 752 x 480 image at f 458 is at 0.97 distorted). The 4-term fit
    /// stays within 2e-4 (0.1 px at f 458) of it, the 2-term one within 2e-3 (the
    /// `theta^3, theta^5` pair bends less than `r^3, r^5`); an empty field gives the ideal
    /// equidistant lens.
    #[test]
    fn the_equidistant_start_follows_the_radial_profile() {
        let radtan = Distortion::radial(-0.283, 0.074);
        for (terms, tolerance) in [(DistortionTerms::Full4, 2e-4), (DistortionTerms::Radial2, 2e-3)] {
            let equi = profile_like(LensKind::Equidistant, &radtan, 1.0, terms);
            assert_eq!(equi.kind, LensKind::Equidistant);
            let worst = (1..=20)
                .map(|i| {
                    let x = Vector2::new(f64::from(i) * 0.05, 0.0);
                    (equi.distort(&x) - radtan.distort(&x)).norm()
                })
                .fold(0.0, f64::max);
            assert!(worst < tolerance, "{terms:?}: {worst} {equi:?}");
        }
        assert_eq!(
            profile_like(LensKind::Equidistant, &radtan, 0.0, DistortionTerms::Full4),
            Distortion::zero(LensKind::Equidistant)
        );
    }
}
