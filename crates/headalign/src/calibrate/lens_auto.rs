//! [`crate::rig::LensChoice::Auto`] over calibrate's chains: the radial-tangential `k1 k2` run
//! ([`BASE_LENS`]), the criterion of [`crate::rig::lens_choice`] on its observations, and
//! the chosen model's own run (that module's docs: what it computes, degrees of freedom,
//! units, pitfalls). A sequence's refits hold its segment gauges as its adjustment does.
//! On the reference route the chosen model's run takes the radial-tangential run's F,
//! frame and 3D homographies of the captured pixels (`super::fits`: they do not depend on
//! the lens model) instead of fitting them again.

use headalign_geometry::bundle::{BundleOptions, RigState};

use super::fits::ChainFits;
use super::two_pass::calibrate_two_pass;
use super::{CalibrateOptions, MotionCalibration, calibrate_once_from, with_restarts};
use crate::error::AlignError;
use crate::observations::View;
use crate::rig::lens_choice::{BASE_LENS, LensSelection, LensSpec, select_lens};

/// [`super::calibrate_rig`] with [`crate::rig::LensChoice::Auto`] (module docs).
pub(super) fn calibrate_choosing_lens(
    views: &[View],
    options: &CalibrateOptions,
) -> Result<MotionCalibration, AlignError> {
    // The runs' steps 2-3 on the captured pixels do not depend on the lens model: the
    // chosen model's run takes the radial-tangential run's (`fits` module docs).
    let fits = ChainFits::default();
    let from_refit = |o: &CalibrateOptions, state: &RigState| {
        with_restarts(o, |o, seeded| calibrate_once_from(views, o, seeded, None, Some(state), Some(&fits)))
    };
    choose_lens(options, |o| calibrate_two_pass(views, o, Some(&fits)), Some(&from_refit))
}

/// A chain from a start: the chosen model's run with the refitted candidate as a start of
/// its adjustment.
pub(super) type ChainFrom<'a> =
    &'a dyn Fn(&CalibrateOptions, &RigState) -> Result<MotionCalibration, AlignError>;

/// [`crate::rig::LensChoice::Auto`] (module docs) over a chain with a fixed lens model (`chain`: the
/// reference chain of [`super::calibrate_rig`] or the sequence chain of
/// [`super::calibrate_sequence`], with its restarts): the radial-tangential `k1 k2` run,
/// the criterion on its observations, and the chosen model's own run: `from_refit` (one
/// run of the chain with the chosen candidate's refit as a further start) when given and
/// it ends plausibly, otherwise `chain`.
pub(super) fn choose_lens(
    options: &CalibrateOptions,
    chain: impl Fn(&CalibrateOptions) -> Result<MotionCalibration, AlignError>,
    from_refit: Option<ChainFrom<'_>>,
) -> Result<MotionCalibration, AlignError> {
    let with =
        |spec: LensSpec| CalibrateOptions { lens: spec.choice(), lens_terms: spec.terms, ..options.clone() };
    let rich = chain(&with(BASE_LENS))?;
    let selection = select(&rich, options)?;
    let spec = selection.spec;
    let mut result = if spec == BASE_LENS {
        rich
    } else {
        let quick = from_refit.map(|f| f(&with(spec), &selection.state));
        let own = match quick {
            Some(Ok(c)) if super::two_pass::plausible(&c) => Ok(c),
            _ => chain(&with(spec)),
        };
        match own {
            Ok(c) => c,
            Err(e) => {
                let mut r = rich;
                r.report.warnings.push(format!(
                    "the lens criterion chose {}, but its calibration failed ({e}); the radtan k1 k2 result is reported",
                    spec.label()
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
    crate::timing::time(crate::timing::Stage::LensChoice, || {
        let gauge_views = held_gauges(rich);
        let bundle = BundleOptions {
            zero_skew: options.zero_skew,
            square_pixels: options.square_pixels,
            fix_principal_point: options.fix_principal_point,
            gauge_views,
            ..options.estimation.bundle.clone()
        };
        select_lens(&rich.bundle.state, &rich.observations, &bundle, options.lens_terms)
    })
}
