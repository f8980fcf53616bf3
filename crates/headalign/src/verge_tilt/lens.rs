//! Lens models in the verge/tilt estimation ([`super`], [`EstimationOptions::lens`]): both
//! cameras' distortion coefficients estimated with everything else, radial-tangential
//! (OpenCV `plumb_bob`) or equidistant (OpenCV `fisheye`), or chosen among those and the
//! pinhole ([`LensChoice::Auto`]).
//!
//! What it computes, [`estimate_with_lens`]:
//! 1. **first estimate**: the whole chain of [`super::estimate_rig`] on the captured
//!    pixels, the linear steps treating them as pinhole pixels, the adjustments with the
//!    lens terms free from the model's zero lens (as [`crate::calibrate`] does);
//! 2. **the start on undistorted pixels**: every observation undistorted with that first
//!    lens (each camera's `K` and coefficients), steps 1-5 of the chain (F, frame, 3D
//!    homographies, the linear chain, the starts) run again on them, the starts given the
//!    first lens;
//! 3. **the adjustment on the original pixels**: steps 6-10 (robust adjustment,
//!    maximum-likelihood pass, restarts, depth profile, bootstrap) on the captured pixels
//!    with the lens free, so the reported covariance and sigmas include the lens terms
//!    (`left.k1` ... in the covariance's names).
//!
//! Why two passes: a barrel lens of `k1 = -0.25` moves the corner pixels of a 768 x 576
//! image by some 55 px; the linear steps see that as a projective error (F's RANSAC at
//! 3 px keeps mostly the centre, the plane homographies of the rotations are bent), so the
//! first estimate may start poorly and keep fewer inliers. The second pass starts from
//! pixels whose remaining distortion is the first estimate's error, a pinhole problem
//! again. When the second pass fails, the first estimate is reported with a note.
//!
//! [`LensChoice::Auto`]: the radial-tangential `k1 k2` estimate above, then the criterion
//! of [`crate::rig::lens_choice`] (BIC over the models and their terms on that
//! estimate's observations, the same code; a failed candidate is reported and left out);
//! a winner other than `radtan k1 k2` is estimated again with its own model and terms,
//! steps 2-3 only: the `k1 k2` estimate's lens undistorts the linear steps' pixels and
//! the starts carry the winner's refitted lens (the pinhole by the plain chain).
//!
//! Degrees of freedom: per camera the coefficients of [`EstimationOptions::lens_terms`]
//! (`k1, k2` by default; under `Auto` the chosen candidate's) on top of the pinhole
//! estimate's. Units: coefficients
//! dimensionless on normalised coordinates, residuals in pixels.
//!
//! Pitfalls: the rotations of the procedure are small (3-10 deg), and with small rotations
//! `k1` correlates with the focal length: the sigmas say how much. The undistortion of
//! the second pass uses the first estimate's `K`; the final adjustment refits both. The
//! pinhole ([`LensChoice::Pinhole`]) runs the chain exactly as without this module.

use headalign_geometry::distortion::{Distortion, LensKind};
use serde::Serialize;

use super::{EstimationOptions, HomographyMode, RigCalibration, estimate_rig_once};
use crate::error::AlignError;
use crate::observations::View;
use crate::rig::lens_choice::{BASE_LENS, select_lens};
use crate::rig::{LensChoice, LensModel, LensSelection};

/// The lens of a run of the chain (`estimate_rig_once`): the lens that undistorts the
/// pixels of its linear steps (`None`: the captured pixels), and the distortion its starts
/// are given (left, right).
pub(super) struct LensStart {
    /// Lenses undistorting the linear steps' pixels (left, right).
    pub chain: Option<[LensModel; 2]>,
    /// The starts' distortion (left, right).
    pub distortion: [Distortion; 2],
}

/// How the lens was estimated ([`super::EstimationReport::lens`]).
#[derive(Debug, Clone, Serialize)]
pub struct LensReport {
    /// The model estimated: `radtan` or `equidistant` (`pinhole` when `auto` chose it).
    pub model: String,
    /// The coefficients freed per camera, in the model's names (`k1`, `k2`, ...).
    pub terms: Vec<String>,
    /// The first estimate's coefficients (left, right), the lens the second pass
    /// undistorted with (module docs step 1); empty for the pinhole.
    pub first_estimate: [Vec<f64>; 2],
    /// Whether the reported calibration is the second pass's (false: the first estimate's,
    /// `note` says why).
    pub undistorted_start: bool,
    /// Why the first estimate is reported, if it is.
    pub note: Option<String>,
    /// How `auto` chose ([`LensChoice::Auto`]); `None` for a given model.
    pub selection: Option<LensSelection>,
}

/// The estimate with the lens of `options.lens` (module docs); the pinhole is
/// `estimate_rig_once` unchanged.
pub(super) fn estimate_with_lens(
    views: &[View],
    options: &EstimationOptions,
    mode: HomographyMode,
    at_view: &mut Option<usize>,
) -> Result<RigCalibration, AlignError> {
    match options.lens {
        LensChoice::Pinhole => estimate_rig_once(views, options, mode, at_view, None),
        LensChoice::Model(kind) => estimate_model(views, options, kind, mode, at_view),
        LensChoice::Auto => estimate_choosing(views, options, mode, at_view),
    }
}

/// The options with the lens terms of `options.lens_terms` free in every adjustment.
fn lens_free(options: &EstimationOptions) -> EstimationOptions {
    let mut o = options.clone();
    o.bundle.estimate_distortion = true;
    o.bundle.distortion_terms = options.lens_terms;
    o
}

/// Steps 1-3 of the module docs for the model `kind`.
fn estimate_model(
    views: &[View],
    options: &EstimationOptions,
    kind: LensKind,
    mode: HomographyMode,
    at_view: &mut Option<usize>,
) -> Result<RigCalibration, AlignError> {
    let free = lens_free(options);
    let zero = Distortion::zero(kind);
    let first_start = LensStart { chain: None, distortion: [zero, zero] };
    let first = estimate_rig_once(views, &free, mode, at_view, Some(&first_start))?;
    let state = &first.bundle.state;
    let start = lens_start(&first, [state.left_distortion, state.right_distortion]);
    let first_estimate = [state.left_distortion.coefficients(), state.right_distortion.coefficients()];
    Ok(match second_pass(views, options, kind, mode, &start, first_estimate) {
        Ok(second) => second,
        Err(failed) => {
            let (e, mut report) = *failed;
            report.undistorted_start = false;
            report.note = Some(format!(
                "the start on undistorted pixels failed ({e}); the first estimate (linear steps on the captured pixels) is reported"
            ));
            let mut first = first;
            first.report.lens = Some(report);
            first
        }
    })
}

/// The start of step 2 after the estimate `first`: its cameras and lenses undistort the
/// linear steps' pixels, and the starts carry `distortion` (left, right).
fn lens_start(first: &RigCalibration, distortion: [Distortion; 2]) -> LensStart {
    let state = &first.bundle.state;
    let lenses = [
        LensModel { k: state.left, distortion: state.left_distortion },
        LensModel { k: state.right, distortion: state.right_distortion },
    ];
    LensStart { chain: Some(lenses), distortion }
}

/// Steps 2-3 of the module docs for the model `kind` from `start`, with its report
/// (`first_estimate`: the lens of step 1); the error and the report when they fail
/// (boxed: the report is large).
fn second_pass(
    views: &[View],
    options: &EstimationOptions,
    kind: LensKind,
    mode: HomographyMode,
    start: &LensStart,
    first_estimate: [Vec<f64>; 2],
) -> Result<RigCalibration, Box<(AlignError, LensReport)>> {
    let names = kind.coefficient_names();
    let terms: Vec<String> = options
        .lens_terms
        .params(kind)
        .iter()
        .filter_map(|&i| names.get(i).map(|n| (*n).to_string()))
        .collect();
    let report = LensReport {
        model: kind.kalibr_name().to_string(),
        terms,
        first_estimate,
        undistorted_start: true,
        note: None,
        selection: None,
    };
    // The second pass's own view failures are not the caller's to drop: the first pass
    // already used these views.
    match estimate_rig_once(views, &lens_free(options), mode, &mut None, Some(start)) {
        Ok(mut second) => {
            second.report.lens = Some(report);
            Ok(second)
        }
        Err(e) => Err(Box::new((e, report))),
    }
}

/// [`LensChoice::Auto`] (module docs).
fn estimate_choosing(
    views: &[View],
    options: &EstimationOptions,
    mode: HomographyMode,
    at_view: &mut Option<usize>,
) -> Result<RigCalibration, AlignError> {
    let with = |terms| EstimationOptions { lens_terms: terms, ..options.clone() };
    let base = with(BASE_LENS.terms);
    let rich = estimate_model(views, &base, BASE_LENS.kind.unwrap_or_default(), mode, at_view)?;
    let selection =
        select_lens(&rich.bundle.state, &rich.observations, &lens_free(&base).bundle, options.lens_terms)?;
    let spec = selection.spec;
    let mut result = match spec.kind {
        _ if spec == BASE_LENS => Ok(rich.clone()),
        None => estimate_rig_once(views, options, mode, &mut None, None).map(|mut c| {
            c.report.lens = Some(LensReport {
                model: "pinhole".into(),
                terms: Vec::new(),
                first_estimate: [Vec::new(), Vec::new()],
                undistorted_start: false,
                note: None,
                selection: None,
            });
            c
        }),
        // Step 1 is the radtan k1 k2 estimate's: its lens undistorts the linear steps'
        // pixels, the starts carry the chosen candidate's refitted lens.
        Some(kind) => {
            let refit = &selection.state;
            let start = lens_start(&rich, [refit.left_distortion, refit.right_distortion]);
            let s = &rich.bundle.state;
            let first = [s.left_distortion.coefficients(), s.right_distortion.coefficients()];
            second_pass(views, &with(spec.terms), kind, mode, &start, first).map_err(|f| f.0)
        }
    }
    .unwrap_or_else(|e| {
        let mut r = rich;
        if let Some(l) = r.report.lens.as_mut() {
            l.note = Some(format!(
                "the lens criterion chose {}, but its estimate failed ({e}); the radtan k1 k2 result is reported",
                spec.label()
            ));
        }
        r
    });
    if let Some(l) = result.report.lens.as_mut() {
        l.selection = Some(selection);
    }
    Ok(result)
}
