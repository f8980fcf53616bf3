//! The lens model of self-calibration ([`LensChoice`]) and its automatic choice
//! ([`LensChoice::Auto`]): pinhole, radial-tangential or equidistant, decided by the
//! Bayesian information criterion on one common set of observations.
//!
//! What it computes: the calibration with the radial-tangential model (the richest model
//! that any of the three nests closely: it is run through the whole chain, so its robust
//! re-selection decides which observations are inliers); then, on exactly that
//! adjustment's observations and points, a least-squares refit of each candidate model
//! from its state (the pinhole with no lens, the radial-tangential model, the equidistant
//! model from its zero lens), and per candidate
//!
//! ```text
//! chi2 = RSS / sigma^2,   BIC = chi2 + p ln(n)
//! ```
//!
//! with `RSS` the sum of squared residuals (pixels^2), `sigma` the radial-tangential
//! adjustment's noise estimate (pixels), `p` the number of lens coefficients estimated
//! (both cameras) and `n` the number of residual components (twice the observations).
//! The smallest `BIC` wins (Schwarz 1978; it penalises each added coefficient by `ln n`,
//! about 9 chi-square units for 2,000 observations, so that a lens term is kept only when
//! the data need it). Two models with the same `p` are decided by their chi-square alone.
//! When the winner is not the radial-tangential model, the chain runs again with it, so
//! that the reported calibration, its inliers and its sigmas are that model's own. The
//! chain is the reference chain of [`super::calibrate_rig`] or the sequence chain of
//! [`super::calibrate_sequence`] (`choose_lens`); a sequence's refits hold its segment
//! gauges as its adjustment does.
//!
//! Degrees of freedom: per camera 0 (pinhole), or the coefficients of
//! [`CalibrateOptions::lens_terms`] (`k1, k2` by default, in either model).
//! Units: residuals in pixels, chi-square and BIC dimensionless.
//!
//! Pitfalls: the criterion compares fits, not truths: on a narrow lens the two distorted
//! models fit almost equally (their chi-squares differ by a few units), and either is
//! then a good description of the image; the choice matters for extrapolation beyond the
//! observed field. The criterion assumes independent Gaussian pixel errors at the
//! estimated `sigma`; correlated tracking errors inflate every chi-square alike.

use headalign_geometry::bundle::{
    BundleObservation, BundleOptions, RigState, RobustLoss, bundle_adjust, residual_pixels,
};
use headalign_geometry::distortion::{Distortion, DistortionTerms, LensKind};
use serde::Serialize;

use super::two_pass::calibrate_two_pass;
use super::{CalibrateOptions, MotionCalibration};
use crate::error::AlignError;
use crate::estimate::FINAL_ITERATIONS;
use crate::observations::View;

/// The lens model of [`CalibrateOptions::lens`].
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

    /// The model named `pinhole`, `radtan` (also `radial-tangential`, `plumb_bob`),
    /// `equidistant` (also `fisheye`, `equi`) or `auto`.
    pub fn parse(name: &str) -> Option<Self> {
        match name.trim().to_ascii_lowercase().as_str() {
            "pinhole" | "none" => Some(LensChoice::Pinhole),
            "auto" => Some(LensChoice::Auto),
            other => LensKind::parse(other).map(LensChoice::Model),
        }
    }

    /// The name users give it (`pinhole`, `radtan`, `equidistant`, `auto`).
    pub fn name(self) -> &'static str {
        match self {
            LensChoice::Pinhole => "pinhole",
            LensChoice::Model(kind) => kind.kalibr_name(),
            LensChoice::Auto => "auto",
        }
    }
}

/// One candidate of the automatic choice.
#[derive(Debug, Clone, Serialize)]
pub struct LensCandidate {
    /// `pinhole`, `radtan` or `equidistant`.
    pub model: String,
    /// Lens coefficients estimated, both cameras.
    pub parameters: usize,
    /// RMS reprojection error of the refit, pixels.
    pub rms_px: f64,
    /// Sum of squared residuals over the noise variance.
    pub chi2: f64,
    /// `chi2 + parameters ln(n)`.
    pub bic: f64,
}

/// How [`LensChoice::Auto`] chose.
#[derive(Debug, Clone, Serialize)]
pub struct LensSelection {
    /// The model kept.
    pub chosen: String,
    /// The criterion, in words, with its numbers.
    pub reason: String,
    /// Residual components `n` (twice the common observations).
    pub residuals: usize,
    /// The noise sigma of the chi-squares, pixels.
    pub sigma_px: f64,
    /// Every candidate, in the order pinhole, radtan, equidistant.
    pub candidates: Vec<LensCandidate>,
}

/// [`super::calibrate_rig`] with [`LensChoice::Auto`] (module docs).
pub(super) fn calibrate_choosing_lens(
    views: &[View],
    options: &CalibrateOptions,
) -> Result<MotionCalibration, AlignError> {
    choose_lens(options, |o| calibrate_two_pass(views, o))
}

/// [`LensChoice::Auto`] (module docs) over a chain with a fixed lens model (`chain`: the
/// reference chain of [`super::calibrate_rig`] or the sequence chain of
/// [`super::calibrate_sequence`], with its restarts): the radial-tangential run, the
/// criterion on its observations, and the chosen model's own run.
pub(super) fn choose_lens(
    options: &CalibrateOptions,
    chain: impl Fn(&CalibrateOptions) -> Result<MotionCalibration, AlignError>,
) -> Result<MotionCalibration, AlignError> {
    let with = |lens: LensChoice| CalibrateOptions { lens, ..options.clone() };
    let rich = chain(&with(LensChoice::Model(LensKind::RadialTangential)))?;
    let selection = select(&rich, options)?;
    let chosen = match selection.chosen.as_str() {
        "pinhole" => LensChoice::Pinhole,
        "equidistant" => LensChoice::Model(LensKind::Equidistant),
        _ => LensChoice::Model(LensKind::RadialTangential),
    };
    let mut result = if chosen == LensChoice::Model(LensKind::RadialTangential) {
        rich
    } else {
        match chain(&with(chosen)) {
            Ok(c) => c,
            Err(e) => {
                let mut r = rich;
                r.report.warnings.push(format!(
                    "the lens criterion chose the {} model, but its calibration failed ({e}); the radial-tangential result is reported",
                    chosen.name()
                ));
                r
            }
        }
    };
    result.report.lens_selection = Some(selection);
    Ok(result)
}

/// The views (indices of [`super::CalibrateReport::views`]) whose poses a refit of `cal`
/// holds: a sequence's segment gauges after the first (none on the reference route).
pub(super) fn held_gauges(cal: &MotionCalibration) -> Vec<usize> {
    let views = &cal.report.views;
    cal.report.sequence.as_ref().map_or_else(Vec::new, |s| {
        s.segments.iter().skip(1).filter_map(|g| views.iter().position(|v| *v == g.gauge)).collect()
    })
}

/// The criterion of the module docs on the observations of `rich` (a radial-tangential
/// calibration); a sequence's segment gauges after the first stay held in the refits, as
/// in its adjustment.
fn select(rich: &MotionCalibration, options: &CalibrateOptions) -> Result<LensSelection, AlignError> {
    let gauge_views = held_gauges(rich);
    let bundle = BundleOptions {
        zero_skew: options.zero_skew,
        square_pixels: options.square_pixels,
        fix_principal_point: options.fix_principal_point,
        gauge_views,
        ..options.estimation.bundle.clone()
    };
    select_lens(
        &rich.bundle.state,
        &rich.observations,
        rich.bundle.report.sigma_px,
        &bundle,
        options.lens_terms,
    )
}

/// The criterion of the module docs: each candidate model refitted by least squares from
/// `state` (a radial-tangential solution) on exactly the observations `obs`, chi-square
/// at `sigma_px` (the radial-tangential adjustment's noise estimate), the smallest BIC
/// wins. `bundle` carries the intrinsic constraints and the rest of the adjustment's
/// options; its loss, noise, lens flags and iteration floor are set here. Shared by
/// [`super::calibrate_rig`] and the verge/tilt estimator
/// ([`crate::estimate::EstimationOptions::lens`]).
pub(crate) fn select_lens(
    state: &RigState,
    obs: &[BundleObservation],
    sigma_px: f64,
    bundle: &BundleOptions,
    lens_terms: DistortionTerms,
) -> Result<LensSelection, AlignError> {
    let n = 2 * obs.len();
    let sigma = sigma_px.max(1e-6);
    let per_camera = |kind: LensKind| lens_terms.slots(kind).len();
    let models = [
        ("pinhole", None, 0),
        ("radtan", Some(LensKind::RadialTangential), 2 * per_camera(LensKind::RadialTangential)),
        ("equidistant", Some(LensKind::Equidistant), 2 * per_camera(LensKind::Equidistant)),
    ];
    let mut candidates = Vec::new();
    for (name, kind, parameters) in models {
        let mut state = state.clone();
        let lens = kind.map_or_else(Distortion::default, Distortion::zero);
        if kind != Some(LensKind::RadialTangential) {
            state.left_distortion = lens;
            state.right_distortion = lens;
        }
        let ls = BundleOptions {
            robust: RobustLoss::None,
            noise_sigma_px: None,
            max_iterations: bundle.max_iterations.max(FINAL_ITERATIONS),
            estimate_distortion: kind.is_some(),
            distortion_terms: lens_terms,
            ..bundle.clone()
        };
        let refit = bundle_adjust(&state, obs, &ls)
            .map_err(|cause| AlignError::Geometry { step: format!("lens choice: {name} refit"), cause })?;
        let rss: f64 =
            obs.iter().filter_map(|o| residual_pixels(&refit.state, o)).map(|r| r.norm_squared()).sum();
        let chi2 = rss / (sigma * sigma);
        candidates.push(LensCandidate {
            model: name.to_string(),
            parameters,
            rms_px: (rss / obs.len().max(1) as f64).sqrt(),
            chi2,
            bic: chi2 + parameters as f64 * (n.max(1) as f64).ln(),
        });
    }
    let best = candidates
        .iter()
        .min_by(|a, b| a.bic.total_cmp(&b.bic))
        .ok_or_else(|| AlignError::InvalidOption("no lens candidate".into()))?;
    let runner_up = candidates
        .iter()
        .filter(|c| c.model != best.model)
        .min_by(|a, b| a.bic.total_cmp(&b.bic))
        .map_or(0.0, |c| c.bic - best.bic);
    let listed: Vec<String> = candidates
        .iter()
        .map(|c| format!("{} {:.1} ({} coefficients)", c.model, c.bic, c.parameters))
        .collect();
    let reason = format!(
        "smallest BIC = chi2 + p ln(n) on the same {} observations (n = {n}, sigma {sigma:.3} px): {}; {} is lower than the next by {runner_up:.1}",
        obs.len(),
        listed.join(", "),
        best.model
    );
    Ok(LensSelection { chosen: best.model.clone(), reason, residuals: n, sigma_px: sigma, candidates })
}
