//! Is a stereo calibration still good? A targetless health check of a given calibration
//! against stereo pairs of natural scenes ([`check_views`]), its rotation-only correction
//! ([`CheckReport::updated`]) and the full one ([`update`]). The user's guide:
//! `docs/check.md`.
//!
//! # What it computes
//!
//! The rotation change of the right camera relative to the left since the calibration:
//! `dR` with `R_now = dR R_given`, where `R` is OpenCV's right-from-left rotation and `dR =
//! exp([pitch, yaw, roll])` turns about the right camera's x, y and z axes (3 degrees of
//! freedom, reported in degrees with sigmas). The translation follows the rotation: `T_now
//! = dR T_given`, the right camera turned about its own centre (a knock or a loose mount
//! turns a camera; a shift of a few tenths of a millimetre is invisible in the epipolar
//! geometry of distant points and, for near ones, would show as part of the rotation). The
//! intrinsics and the lenses are held. Beside it: a test of whether the right camera's
//! intrinsics changed ([`intrinsics`]), the vertical disparity after rectifying with the
//! given calibration and the Sampson error of the given and the refitted calibration, the
//! depth error the change causes at 1, 2, 5 and 10 m ([`depth`]), and a verdict.
//!
//! # Method
//!
//! 1. Matches: each pair's own left-right matches by the front end of `calibrate`, the
//!    given lenses removed ([`mod@matches`]).
//! 2. Outliers: RANSAC with a 3-match minimal solver of the rotation change, pooled over
//!    the pairs (one rig), threshold [`CheckOptions::ransac`] on the Sampson
//!    distance ([`refit`]).
//! 3. The maximum-likelihood refit: least squares of the Sampson distances (the
//!    first-order reprojection error, Hartley & Zisserman 2nd ed. section 11.4.3) by the
//!    geometry crate's Levenberg-Marquardt, on the matches within
//!    [`CheckOptions::inlier_sigmas`] of the measured noise, re-selected until stable.
//! 4. Sigmas: the noise `sigma` measured from the residuals (`sqrt(cost / (n - 3))`, the
//!    truncation of the tails undone; with independent noise of `s` pixels in each
//!    coordinate a Sampson distance has the sigma `s`), covariance `sigma^2 (J^T J)^-1`,
//!    mapped from the refit's tangent steps to `w = log(dR)`. With several
//!    pairs, each pair is refitted alone on its selected matches; when the pairs scatter
//!    about the pooled change more than their sigmas allow (`chi2 / dof > 1`, `dof = 3
//!    (pairs - 1)`), the sigmas are multiplied by `sqrt(chi2 / dof)` (Birge's ratio: the
//!    errors the image noise does not explain, such as a lens model's residual, are
//!    counted), reported as `scatter_ratio`.
//!
//! # Units
//!
//! Residuals, noise and thresholds in pixels of the undistorted images; angles in degrees
//! in the report (radians inside); depth errors in percent; the baseline in metres.
//!
//! # Verdict
//!
//! With `z_i = |w_i| / sigma_i` per axis, the significant part of the change `w_s` (the
//! axes with `z_i >= significance_sigmas`, 5; the others set to zero), and `e(w)` the
//! depth error at [`CheckOptions::reference_depth_m`] (5 m) of a change `w`:
//! - `recalibrate`: `e(w_s) > depth_limit_pct` (1 %): a significant change that matters;
//! - `can-improve`: otherwise, when `e(w_s) > improve_fraction` (1/4) of the limit, or
//!   when the intrinsics test is significant;
//! - `good`: otherwise.
//!
//! Only the significant part counts: an axis within its noise (yaw, the worst seen, often
//! is) would otherwise decide the verdict by its noise alone.
//!
//! `conclusive` says whether the data can tell: `e` at every corner of the box `|w_i| +
//! bound_sigmas sigma_i` (3 sigma) is below the limit, or the verdict is `recalibrate`. A
//! `good` that is not conclusive means no harmful change was seen, but the sigmas are too
//! large to exclude one: check more pairs.
//!
//! # Pitfalls
//!
//! - Yaw changes disparities most and the vertical disparity least: only the refit sees
//!   it. The vertical disparity is reported for comparison, not used.
//! - The depth error needs the baseline in metres: a calibration in baselines needs
//!   [`CheckOptions::baseline_m`].
//! - A scene with all points far away cannot tell a translation change from a rotation;
//!   the model's assumption (`T_now = dR T_given`) is then harmless.
//! - Several pairs are assumed of one rig; sessions whose encoders differ are reduced to
//!   one rig state (the others are named in `skipped`).

pub mod depth;
pub mod intrinsics;
pub mod live;
pub mod matches;
pub mod refit;
pub mod split;
#[cfg(test)]
mod tests;
pub mod update;

use headalign_geometry::camera::Intrinsics;
use headalign_geometry::ransac::{RansacOptions, ransac};
use headalign_geometry::so3;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::Serialize;
use thiserror::Error;

use crate::AlignError;
use crate::calibrate::views::{StereoViews, one_rig, stereo_only};
use crate::calibration::StereoCalibration;
use crate::rig::{LensModel, undistort_views};
use crate::tracking::FrontEndOptions;
pub use depth::{DepthErrors, disparity_shift_px};
pub use intrinsics::{Estimate, IntrinsicsChange};
use matches::{PairMatches, pair_matches, vertical_disparity};
use refit::{EpipolarModel, Match, RobustFit, percentile, refit_rotation, select_by_noise};
pub use update::{FullUpdate, update_full};

/// The options of [`check_views`].
#[derive(Debug, Clone)]
pub struct CheckOptions {
    /// The front end for images. Default [`FrontEndOptions::default`] (1500 corners).
    pub front_end: FrontEndOptions,
    /// RANSAC's inlier threshold on the Sampson distance, pixels, and its seed. Default
    /// [`RansacOptions::default`] (1.5 px, seed 0).
    pub ransac: RansacOptions,
    /// The matches kept after RANSAC: within this many measured sigmas. Default 3.
    pub inlier_sigmas: f64,
    /// Fewest matches kept over all pairs. Default 30 (10 matches per parameter).
    pub min_matches: usize,
    /// A change is significant at this many sigmas. Default 5.
    pub significance_sigmas: f64,
    /// The depth error that asks for recalibration, percent at `reference_depth_m`.
    /// Default 1.
    pub depth_limit_pct: f64,
    /// The depth of the verdict's depth error, metres. Default 5.
    pub reference_depth_m: f64,
    /// `can-improve` needs the change's significant part to cause this fraction of the
    /// depth limit. Default 0.25.
    pub improve_fraction: f64,
    /// `conclusive` needs the change plus this many sigmas below the limit. Default 3.
    pub bound_sigmas: f64,
    /// Baseline in metres for a calibration whose translation is in baselines. Default none.
    pub baseline_m: Option<f64>,
}

impl Default for CheckOptions {
    fn default() -> Self {
        Self {
            front_end: FrontEndOptions::default(),
            ransac: RansacOptions::default(),
            inlier_sigmas: 3.0,
            min_matches: 30,
            significance_sigmas: 5.0,
            depth_limit_pct: 1.0,
            reference_depth_m: 5.0,
            improve_fraction: 0.25,
            bound_sigmas: 3.0,
            baseline_m: None,
        }
    }
}

impl CheckOptions {
    /// An error naming the first bad option.
    pub fn validate(&self) -> Result<(), CheckError> {
        self.front_end.validate()?;
        self.ransac.validate().map_err(|e| CheckError::InvalidOption(format!("RANSAC: {e}")))?;
        let positive = [
            ("inlier sigmas", self.inlier_sigmas),
            ("significance sigmas", self.significance_sigmas),
            ("depth limit", self.depth_limit_pct),
            ("reference depth", self.reference_depth_m),
            ("bound sigmas", self.bound_sigmas),
            ("improve fraction", self.improve_fraction),
            ("baseline", self.baseline_m.unwrap_or(1.0)),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(CheckError::InvalidOption(format!("{name} must be positive, got {v}")));
            }
        }
        if self.min_matches < 4 {
            return Err(CheckError::InvalidOption(format!(
                "min matches must be at least 4, got {}",
                self.min_matches
            )));
        }
        Ok(())
    }
}

/// Why a check could not be made.
#[derive(Debug, Error)]
pub enum CheckError {
    /// A bad option.
    #[error("invalid option: {0}")]
    InvalidOption(String),
    /// The given calibration cannot be used (no baseline, non-finite numbers).
    #[error("calibration: {0}")]
    Calibration(String),
    /// Too few matches survive the robust selection.
    #[error("too few stereo matches: {got} after outlier removal over {pairs} pairs, need at least {needed}")]
    TooFewMatches {
        /// Matches kept.
        got: usize,
        /// Needed.
        needed: usize,
        /// Pairs.
        pairs: usize,
    },
    /// The front end or the undistortion failed.
    #[error(transparent)]
    Align(#[from] AlignError),
}

/// Three angles about the right camera's x, y, z axes, degrees.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Angles {
    /// About x.
    pub pitch: f64,
    /// About y.
    pub yaw: f64,
    /// About z.
    pub roll: f64,
}

impl Angles {
    /// From a rotation vector in radians.
    pub fn from_rad(w: &Vector3<f64>) -> Self {
        Self { pitch: w.x.to_degrees(), yaw: w.y.to_degrees(), roll: w.z.to_degrees() }
    }

    /// As a rotation vector in radians.
    pub fn to_rad(self) -> Vector3<f64> {
        Vector3::new(self.pitch.to_radians(), self.yaw.to_radians(), self.roll.to_radians())
    }
}

/// The median and the 90th percentile of absolute values, pixels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Spread {
    /// Median.
    pub median: f64,
    /// 90th percentile.
    pub p90: f64,
}

impl Spread {
    /// Of the absolute values `v` (`NaN`s when empty).
    pub fn of(mut v: Vec<f64>) -> Self {
        for x in &mut v {
            *x = x.abs();
        }
        Self {
            median: percentile(&mut v, 0.5).unwrap_or(f64::NAN),
            p90: percentile(&mut v, 0.9).unwrap_or(f64::NAN),
        }
    }
}

/// The verdict ([`super::check`] module docs, "Verdict").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Verdict {
    /// The calibration is good: the change is known to cause less than the depth limit.
    Good,
    /// A change that may matter, or changed intrinsics: an update can improve the depth.
    CanImprove,
    /// A significant change causing more than the depth limit: recalibrate (or update).
    Recalibrate,
}

impl Verdict {
    /// `good`, `can-improve` or `recalibrate`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Good => "good",
            Self::CanImprove => "can-improve",
            Self::Recalibrate => "recalibrate",
        }
    }
}

/// One pair's share of the check.
#[derive(Debug, Clone, Serialize)]
pub struct PairReport {
    /// The pair's name.
    pub name: String,
    /// Its matches (undistorted).
    pub matches: usize,
    /// Those kept by the pooled selection.
    pub inliers: usize,
    /// The rotation change refitted on this pair alone (`None`: too few matches).
    pub rotation_change_deg: Option<Angles>,
    /// Its sigmas (the pooled noise).
    pub rotation_change_sigma_deg: Option<Angles>,
    /// `|dy|` after the given rectification, pixels.
    pub vertical_disparity_px: Spread,
    /// Sampson distances under the given calibration, pixels.
    pub sampson_px: Spread,
}

/// What the refitted calibration gives on the same matches.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct RefitQuality {
    /// `|dy|` after the refitted calibration's rectification, pixels.
    pub vertical_disparity_px: Spread,
    /// Sampson distances, pixels.
    pub sampson_px: Spread,
}

/// The check's result.
#[derive(Debug, Clone, Serialize)]
pub struct CheckReport {
    /// The verdict.
    pub verdict: Verdict,
    /// Whether the data can tell (module docs, "Verdict").
    pub conclusive: bool,
    /// The rotation change `dR` (module docs), degrees.
    pub rotation_change_deg: Angles,
    /// Its sigmas, degrees (with the pairs' scatter: `scatter_ratio`).
    pub rotation_change_sigma_deg: Angles,
    /// `|dy|` after rectifying with the given calibration, pixels (the kept matches).
    pub vertical_disparity_px: Spread,
    /// Sampson distances under the given calibration, pixels (the kept matches).
    pub sampson_px: Spread,
    /// The same under the refitted rotation.
    pub refit: RefitQuality,
    /// The depth error the change causes, percent at 1, 2, 5 and 10 m.
    pub depth_error_pct: DepthErrors,
    /// The disparity shift behind it (root mean square over the image), pixels.
    pub disparity_shift_px: f64,
    /// The intrinsics test (`None`: its normal matrix was singular).
    pub intrinsics_change: Option<IntrinsicsChange>,
    /// The measured noise of a Sampson distance, pixels.
    pub noise_px: f64,
    /// The sigmas' factor for the pairs' scatter (1 when they agree; module docs).
    pub scatter_ratio: f64,
    /// Matches over all pairs, and those kept.
    pub matches: [usize; 2],
    /// Each pair.
    pub pairs: Vec<PairReport>,
    /// Views left out as of another rig state, each with the reason.
    pub skipped: Vec<String>,
    /// The given calibration with the refitted rotation (`T` turned with it); `None`
    /// with the reason in `update_refused` when the refit does not validate.
    #[serde(skip)]
    pub updated: Option<StereoCalibration>,
    /// Why no update is offered (`None` when one is).
    pub update_refused: Option<String>,
}

/// Check `given` against `views` (module docs).
pub fn check_views(
    views: StereoViews<'_>,
    given: &StereoCalibration,
    options: &CheckOptions,
) -> Result<CheckReport, CheckError> {
    options.validate()?;
    let baseline_m = metric_baseline(given, options)?;
    let (tracked, skipped) = match views {
        StereoViews::Images(images) => {
            let (rig, skipped) = one_rig(images, |(n, v)| (n.as_str(), v.encoders));
            (stereo_only(&rig, &options.front_end)?, skipped)
        }
        StereoViews::Tracked(t) => one_rig(t, |v| (v.name.as_str(), v.capture.encoders)),
    };
    let lenses = [
        LensModel { k: given.left, distortion: given.distortion[0] },
        LensModel { k: given.right, distortion: given.distortion[1] },
    ];
    let pairs = pair_matches(&undistort_views(&tracked, &lenses));
    let mut report = check_matches(&pairs, given, baseline_m, options)?;
    report.skipped = skipped;
    Ok(report)
}

/// The baseline in metres: the calibration's, or the options' for one in baselines.
pub(crate) fn metric_baseline(given: &StereoCalibration, options: &CheckOptions) -> Result<f64, CheckError> {
    let norm = given.right_from_left.translation.vector.norm();
    if !(norm.is_finite() && norm > 0.0) {
        return Err(CheckError::Calibration("the given calibration has no baseline".into()));
    }
    match (options.baseline_m, given.unit) {
        (Some(b), _) => Ok(b),
        (None, crate::calibration::TranslationUnit::Metres) => Ok(norm),
        (None, crate::calibration::TranslationUnit::Baselines) => Err(CheckError::Calibration(
            "the calibration's translation is in baselines: give the baseline in metres for the depth error"
                .into(),
        )),
    }
}

/// The epipolar model of a calibration.
pub fn epipolar_model(c: &StereoCalibration) -> Result<EpipolarModel, CheckError> {
    let inv = |k: &Intrinsics| {
        (k.is_finite() && k.fx > 0.0 && k.fy > 0.0)
            .then(|| k.inverse_matrix())
            .ok_or_else(|| CheckError::Calibration(format!("bad intrinsics {k:?}")))
    };
    let t = c.right_from_left.translation.vector;
    let essential = so3::skew(&t) * c.rotation();
    if !essential.iter().all(|v| v.is_finite()) {
        return Err(CheckError::Calibration("non-finite rig pose".into()));
    }
    Ok(EpipolarModel { essential, kl_inv: inv(&c.left)?, kr_inv: inv(&c.right)?, kr: c.right.matrix() })
}

/// The calibration `c` with its right camera turned by `dr` about its centre.
pub fn turned(c: &StereoCalibration, dr: &Rotation3<f64>) -> StereoCalibration {
    let q = UnitQuaternion::from_rotation_matrix(dr);
    let t = q * c.right_from_left.translation.vector;
    StereoCalibration {
        right_from_left: Isometry3::from_parts(Translation3::from(t), q * c.right_from_left.rotation),
        ..c.clone()
    }
}

/// The robust pooled refit of all pairs' matches (module docs, steps 2-4 before the
/// scatter).
fn pooled_fit(model: &EpipolarModel, all: &[Match], options: &CheckOptions) -> Result<RobustFit, CheckError> {
    let too_few = |got| CheckError::TooFewMatches { got, needed: options.min_matches, pairs: 0 };
    if all.len() < options.min_matches {
        return Err(too_few(all.len()));
    }
    let estimator = refit::RotationChange { model };
    let r = ransac(&estimator, all, &options.ransac).map_err(|_| too_few(0))?;
    select_by_noise(model, all, (r.model, r.inliers.clone()), options.inlier_sigmas, options.min_matches)
        .ok_or_else(|| too_few(r.inliers.len()))
}

/// One pair's own refit: the change `w` and its covariance, radians.
type PairFit = (Vector3<f64>, Matrix3<f64>);

/// Each pair's report and its own refit `(w, covariance)` (radians; pairs with fewer than
/// 10 kept matches have none), on the pooled fit's selection and noise.
fn pair_reports(
    model: &EpipolarModel,
    rect: &headalign_geometry::rectify::Rectification,
    pairs: &[PairMatches],
    fit: &RobustFit,
) -> (Vec<PairReport>, Vec<PairFit>) {
    let k_inv = [&model.kl_inv, &model.kr_inv];
    let mut pair_reports = Vec::new();
    let mut offset = 0;
    let mut per_pair = Vec::new();
    for p in pairs {
        let range = offset..offset + p.matches.len();
        offset = range.end;
        let sel: Vec<usize> =
            fit.selected.iter().filter(|i| range.contains(i)).map(|i| i - range.start).collect();
        let one =
            refit_rotation(model, &p.matches, &sel, &fit.fit.dr).filter(|_| sel.len() >= 10).and_then(|f| {
                let cov = f.jtj.try_inverse()? * fit.sigma_px.powi(2);
                Some((so3::log(&f.dr), cov))
            });
        if let Some(o) = one {
            per_pair.push(o);
        }
        pair_reports.push(PairReport {
            name: p.name.clone(),
            matches: p.matches.len(),
            inliers: sel.len(),
            rotation_change_deg: one.map(|(w, _)| Angles::from_rad(&w)),
            rotation_change_sigma_deg: one.map(|(_, c)| sigmas_deg(&c)),
            vertical_disparity_px: Spread::of(vertical_disparity(rect, k_inv, &p.matches, &sel)),
            sampson_px: Spread::of(model.residuals(&Rotation3::identity(), &p.matches, &sel)),
        });
    }
    (pair_reports, per_pair)
}

/// The check on undistorted matches (module docs).
pub fn check_matches(
    pairs: &[PairMatches],
    given: &StereoCalibration,
    baseline_m: f64,
    options: &CheckOptions,
) -> Result<CheckReport, CheckError> {
    let model = epipolar_model(given)?;
    let all: Vec<Match> = pairs.iter().flat_map(|p| p.matches.iter().copied()).collect();
    let fit = pooled_fit(&model, &all, options).map_err(|e| match e {
        CheckError::TooFewMatches { got, needed, .. } => {
            CheckError::TooFewMatches { got, needed, pairs: pairs.len() }
        }
        e => e,
    })?;
    let rect = given.rectification()?;
    let k_inv = [&model.kl_inv, &model.kr_inv];
    let (pair_reports, per_pair) = pair_reports(&model, &rect, pairs, &fit);
    let w = so3::log(&fit.fit.dr);
    let scatter_ratio = scatter_ratio(&w, &per_pair);
    let covariance = fit.covariance * scatter_ratio.powi(2);
    let shift = disparity_shift_px(&rect, given.image_size, &fit.fit.dr);
    let focal = rect.p_left[(0, 0)];
    let depth = DepthErrors::of_shift(shift, focal, baseline_m);
    let intr = intrinsics::intrinsics_change(
        &model,
        &all,
        &fit.selected,
        &fit.fit.dr,
        fit.fit.cost,
        fit.sigma_px * scatter_ratio,
        options.significance_sigmas,
    );
    let sigma_w = Vector3::from_fn(|i, _| covariance[(i, i)].max(0.0).sqrt());
    let (verdict, conclusive) = verdict(&w, &sigma_w, intr.as_ref(), options, |w| {
        DepthErrors::of_shift(disparity_shift_px(&rect, given.image_size, &so3::exp(w)), focal, baseline_m)
            .at(options.reference_depth_m)
    });
    let updated = turned(given, &fit.fit.dr);
    let refit_quality = RefitQuality {
        vertical_disparity_px: Spread::of(match updated.rectification() {
            Ok(r) => vertical_disparity(&r, k_inv, &all, &fit.selected),
            Err(_) => Vec::new(),
        }),
        sampson_px: Spread::of(model.residuals(&fit.fit.dr, &all, &fit.selected)),
    };
    let given_r = model.residuals(&Rotation3::identity(), &all, &fit.selected);
    let given_rms = (given_r.iter().map(|r| r * r).sum::<f64>() / given_r.len().max(1) as f64).sqrt();
    let given_sampson = Spread::of(given_r);
    let update_refused = validate_update(&fit, given_rms, options);
    Ok(CheckReport {
        verdict,
        conclusive,
        rotation_change_deg: Angles::from_rad(&w),
        rotation_change_sigma_deg: Angles::from_rad(&sigma_w),
        vertical_disparity_px: Spread::of(vertical_disparity(&rect, k_inv, &all, &fit.selected)),
        sampson_px: given_sampson,
        refit: refit_quality,
        depth_error_pct: depth,
        disparity_shift_px: shift,
        intrinsics_change: intr,
        noise_px: fit.sigma_px,
        scatter_ratio,
        matches: [all.len(), fit.selected.len()],
        pairs: pair_reports,
        skipped: Vec::new(),
        updated: update_refused.is_none().then_some(updated),
        update_refused,
    })
}

/// The standard deviations of a covariance of radians, in degrees.
fn sigmas_deg(c: &Matrix3<f64>) -> Angles {
    Angles::from_rad(&Vector3::from_fn(|i, _| c[(i, i)].max(0.0).sqrt()))
}

/// Birge's ratio of the pairs' changes about the pooled one: `max(1, sqrt(chi2 / dof))`,
/// `dof = 3 (pairs - 1)`; 1 with fewer than two pairs.
fn scatter_ratio(pooled: &Vector3<f64>, pairs: &[PairFit]) -> f64 {
    if pairs.len() < 2 {
        return 1.0;
    }
    let chi2: f64 = pairs
        .iter()
        .filter_map(|(w, c)| {
            let d = w - pooled;
            c.try_inverse().map(|ci| (d.transpose() * ci * d)[0])
        })
        .sum();
    let dof = 3.0 * (pairs.len() - 1) as f64;
    let r = (chi2 / dof).sqrt();
    if r.is_finite() { r.max(1.0) } else { 1.0 }
}

/// The verdict and whether it is conclusive (module docs): `depth_at_reference(w)` is
/// the depth error of a change `w` (radians) at the reference depth, percent.
pub fn verdict(
    w: &Vector3<f64>,
    sigma: &Vector3<f64>,
    intrinsics: Option<&IntrinsicsChange>,
    options: &CheckOptions,
    depth_at_reference: impl Fn(&Vector3<f64>) -> f64,
) -> (Verdict, bool) {
    let significant =
        Vector3::from_fn(
            |i, _| if w[i].abs() >= options.significance_sigmas * sigma[i] { w[i] } else { 0.0 },
        );
    let e = depth_at_reference(&significant);
    if e > options.depth_limit_pct {
        return (Verdict::Recalibrate, true);
    }
    let bound = w.abs() + sigma * options.bound_sigmas;
    let worst = (0..8)
        .map(|c| {
            let corner = Vector3::from_fn(|i, _| if c >> i & 1 == 1 { bound[i] } else { -bound[i] });
            depth_at_reference(&corner)
        })
        .fold(0.0, f64::max);
    let conclusive = worst <= options.depth_limit_pct;
    let worth = e > options.improve_fraction * options.depth_limit_pct;
    if worth || intrinsics.is_some_and(|c| c.significant) {
        (Verdict::CanImprove, conclusive)
    } else {
        (Verdict::Good, conclusive)
    }
}

/// Why the refitted calibration is not offered (`None`: it is): too few matches kept, a
/// non-finite sigma, or a refit whose root-mean-square Sampson distance on the kept
/// matches is not below the given calibration's.
fn validate_update(fit: &RobustFit, given_rms_px: f64, options: &CheckOptions) -> Option<String> {
    if fit.selected.len() < options.min_matches {
        return Some(format!("{} matches kept, need {}", fit.selected.len(), options.min_matches));
    }
    if !fit.covariance.iter().all(|v| v.is_finite()) || !fit.sigma_px.is_finite() {
        return Some("the refit's sigmas are not finite".into());
    }
    let rms = (fit.fit.cost / fit.selected.len() as f64).sqrt();
    if rms.partial_cmp(&given_rms_px) != Some(std::cmp::Ordering::Less) && rms != given_rms_px {
        return Some(format!(
            "the refit's RMS Sampson distance {rms:.4} px is not below the given calibration's {given_rms_px:.4} px"
        ));
    }
    None
}
