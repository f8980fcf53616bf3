//! The corner density of self-calibration from images ([`Density`]): a first detection,
//! and a denser retry when its calibration is weak ([`weak_data`]) or fails; the choice
//! between the two results ([`prefer_denser`]) and the report of it ([`DensityReport`]).
//!
//! What it compares: each result's focal lengths (pixels) and their sigmas (percent of
//! `f`, from the adjustment's covariance); two results disagree when their focal lengths
//! differ by more than [`DISAGREEMENT_SIGMAS`] combined sigmas, and then the principal
//! points' distance from the image centre (pixels) decides. No estimation happens here:
//! the caller runs detection, tracking and [`calibrate_rig`](super::calibrate_rig) per
//! density.
//!
//! Pitfalls (measured, see [`Density`] and [`prefer_denser`]): denser is not better
//! everywhere (one motion with the distortion estimated diverged at 3000 corners from
//! starts that converged at 1500), and a detector's localisation errors are not
//! independent of the image content, so two detections of the same images can disagree
//! beyond their sigmas.

use headalign_geometry::camera::Intrinsics;
use serde::Serialize;

use super::report::{fmt_pct, weak_data, worst_focal_sigma_pct};
use super::{CalibrateOptions, MotionCalibration};
use crate::error::AlignError;

/// Corners per image for self-calibration from images: a first detection with `corners`
/// and, when its calibration is weak ([`weak_data`]) or fails, a second one with
/// `retry_corners` from the same images; [`prefer_denser`] keeps one of the two.
///
/// Why (measured on rendered one-general-motion sessions, 0.5 px, seeds 1-20, and
/// two-rotation barrel-lens sessions, seeds 1-8): one motion calibrates only from the
/// points seen in both views, and where one textured wall fills the views the strongest
/// corners all lie on it; twice the corners puts enough off it (seed 20: f 19.7 % off
/// with sigma 0.93 % at 1500, -0.16 % with sigma 0.30 % at 3000), and with `k1, k2`
/// estimated it halves the focal error of two small rotations. But denser is not better
/// everywhere (one motion with the distortion estimated: 2 of 10 seeds diverged at 3000
/// from starts that converged at 1500, f +301 % with a sigma of 15 %, and +7.4 % with
/// 1.5 %), and it costs 2-10x the time, so the dense run is only a retry of a weak
/// result, and its own sigma decides, unless the two results disagree beyond their
/// sigmas ([`prefer_denser`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Density {
    /// Corners per image of the first detection (default 1500, the front end's).
    pub corners: usize,
    /// Corners per image of the retry (default 3000); equal to `corners`: no retry.
    pub retry_corners: usize,
}

impl Default for Density {
    fn default() -> Self {
        Self { corners: 1500, retry_corners: 3000 }
    }
}

impl Density {
    /// One detection with `corners` per image, no retry (what the user asked for).
    pub fn fixed(corners: usize) -> Self {
        Self { corners, retry_corners: corners }
    }

    /// Check the counts.
    pub fn validate(&self) -> Result<(), AlignError> {
        if self.corners == 0 || self.retry_corners < self.corners {
            return Err(AlignError::InvalidOption(format!(
                "corners per image must be positive and the retry's at least as many (got {} and {})",
                self.corners, self.retry_corners
            )));
        }
        Ok(())
    }

    /// True if the first trial (weak or failed) calls for the denser retry.
    pub fn retry(&self, first: &DensityTrial) -> bool {
        self.retry_corners > self.corners && (first.weak || first.error.is_some())
    }
}

/// One calibration of a [`Density`] choice.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DensityTrial {
    /// Corners per image.
    pub corners: usize,
    /// Left and right focal length `fx`, pixels (NaN if the run failed).
    pub focal_px: [f64; 2],
    /// Their sigmas, percent ([`CalibrateReport::focal_sigma_pct`](super::CalibrateReport::focal_sigma_pct)).
    pub focal_sigma_pct: [Option<f64>; 2],
    /// The result carries a warning about its data ([`weak_data`]).
    pub weak: bool,
    /// Mean over the two cameras of the principal point's distance from the image centre
    /// `((w - 1) / 2, (h - 1) / 2)`, pixels (`None` if the run failed).
    pub principal_point_offset_px: Option<f64>,
    /// Why the run failed, if it did.
    pub error: Option<String>,
    /// Wall time of detection, tracking and calibration, seconds.
    pub seconds: f64,
}

impl DensityTrial {
    /// The trial of a calibration.
    pub fn new(corners: usize, cal: &MotionCalibration, options: &CalibrateOptions, seconds: f64) -> Self {
        let st = &cal.bundle.state;
        let centre = Intrinsics::rough_guess(cal.image_size[0], cal.image_size[1]);
        let offset = |k: &Intrinsics| (k.cx - centre.cx).hypot(k.cy - centre.cy);
        // The choice sees the sigmas without the widening of the check against the images'
        // noise (`image_noise`): that check says the model does not fit, whichever density
        // is kept, and must not change which estimate is.
        let undo = cal.report.image_noise.as_ref().map_or(1.0, |n| n.sigma_widening.max(1.0));
        let mut report = cal.report.clone();
        report.focal_sigma_pct = report.focal_sigma_pct.map(|s| s.map(|v| v / undo));
        Self {
            corners,
            focal_px: [st.left.fx, st.right.fx],
            focal_sigma_pct: report.focal_sigma_pct,
            weak: weak_data(&report, options),
            principal_point_offset_px: Some(0.5 * (offset(&st.left) + offset(&st.right))),
            error: None,
            seconds,
        }
    }

    /// The trial of a failed run.
    pub fn failed(corners: usize, error: String, seconds: f64) -> Self {
        Self {
            corners,
            focal_px: [f64::NAN; 2],
            focal_sigma_pct: [None; 2],
            weak: true,
            principal_point_offset_px: None,
            error: Some(error),
            seconds,
        }
    }
}

/// Keep the denser of two calibrations of the same images? Yes if the first failed and
/// the denser did not. If both ran and their focal lengths agree within
/// [`DISAGREEMENT_SIGMAS`] combined sigmas, yes if the denser one's worse focal sigma is
/// smaller (an unknown sigma counts as infinite): the sigma is the calibration's own
/// measure of how well its data fix it; a wrong minimum reached from a poor start shows
/// as a wide sigma (the diverged dense runs above: 15 % and 1.5 % against 0.44 % and
/// 0.39 %), and more observations of the same scene narrow it where the data agree.
///
/// If they disagree beyond that, the sigmas do not measure the errors (the first run's
/// corners are mostly among the denser run's, so the two should agree better than
/// independent runs), and the smaller sigma is no guide: the one whose principal points
/// lie nearer the image centre is kept ([`DensityTrial::principal_point_offset_px`]).
/// Why: the sigmas count independent pixel noise only, but a detector's localisation
/// errors are not independent of the image content, and where the scene barely fixes the
/// calibration (one motion, the points both views share on one wall) they shift the
/// solution along the calibration's weak direction, in which the focal length and the
/// principal point move together; twice the corners halve the variance but not that
/// shift. Measured once on rendered one-motion sessions (as `bench/onegen.py
/// --procedural` renders them, truth known): procedural seed 14 gives f +0.63 %
/// (sigma 0.46 %) at 1500 corners and
/// +2.84 % (sigma 0.31 %, 4.5 combined sigmas apart) at 3000; the same tracks at their
/// true pixels with independent 0.4 px noise give +0.78 % and +0.95 %, so the denser
/// result's error is the detector's, not noise or the estimator. Its principal points
/// are 10.6 px from the centre on average against 7.5 px (truth 5.9 px). On the sessions
/// where the denser run is right and disagrees (photographs, seeds 14 and 20) the first
/// run's were 11.1 and 38.9 px against 6.5 and 5.7 px. Those numbers are without the
/// front end's patch refinement ([`crate::tracking::FrontEndOptions::refine`], on by
/// default since), which removes that localisation error: with it no measured session
/// reaches the disagreeing branch (the re-detected one-motion sessions, seeds 1-20 with
/// photographs and procedural textures, differ by 0.1-0.6 combined sigmas, 0.2-1.0 with
/// the stereo partners refined too; the barrel-lens two-rotation sessions are no longer
/// weak), so the rule is kept only as a guard.
pub fn prefer_denser(first: &DensityTrial, denser: &DensityTrial) -> bool {
    match (&first.error, &denser.error) {
        (_, Some(_)) => false,
        (Some(_), None) => true,
        (None, None) => {
            if disagreement_sigmas(first, denser).is_some_and(|z| z > DISAGREEMENT_SIGMAS)
                && let (Some(a), Some(b)) =
                    (first.principal_point_offset_px, denser.principal_point_offset_px)
            {
                return b < a;
            }
            worst_focal_sigma_pct(&denser.focal_sigma_pct) < worst_focal_sigma_pct(&first.focal_sigma_pct)
        }
    }
}

/// How far apart two trials' focal lengths are, in combined sigmas (the larger over the
/// two cameras); `None` if either failed or lacks a sigma.
pub fn disagreement_sigmas(a: &DensityTrial, b: &DensityTrial) -> Option<f64> {
    let mut worst: Option<f64> = None;
    for i in 0..2 {
        let (sa, sb) =
            (a.focal_sigma_pct[i]? * a.focal_px[i] / 100.0, b.focal_sigma_pct[i]? * b.focal_px[i] / 100.0);
        let z = (a.focal_px[i] - b.focal_px[i]).abs() / (sa * sa + sb * sb).sqrt();
        if !z.is_finite() {
            return None;
        }
        worst = Some(worst.map_or(z, |w: f64| w.max(z)));
    }
    worst
}

/// Above this many combined sigmas two detections' focal lengths disagree (a warning).
pub const DISAGREEMENT_SIGMAS: f64 = 3.0;

/// What [`Density`] did: every trial, the kept one, and the sentence that says so.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DensityReport {
    /// True if the corner count was chosen (no `--corners`).
    pub automatic: bool,
    /// The runs in order.
    pub trials: Vec<DensityTrial>,
    /// Index of the kept trial.
    pub kept: usize,
    /// Focal disagreement of the two trials, combined sigmas ([`disagreement_sigmas`]).
    pub disagreement_sigmas: Option<f64>,
    /// What was done, for the user (empty with one trial).
    pub note: String,
    /// True if the note is a warning: the two trials disagree by more than
    /// [`DISAGREEMENT_SIGMAS`], or the first failed.
    pub warn: bool,
}

impl DensityReport {
    /// The choice between a first trial and, if run, a denser one.
    pub fn choose(automatic: bool, first: DensityTrial, denser: Option<DensityTrial>) -> Self {
        let Some(denser) = denser else {
            return Self {
                automatic,
                trials: vec![first],
                kept: 0,
                disagreement_sigmas: None,
                note: String::new(),
                warn: false,
            };
        };
        let keep_denser = prefer_denser(&first, &denser);
        let z = disagreement_sigmas(&first, &denser);
        let describe = |t: &DensityTrial| match &t.error {
            Some(e) => format!("failed ({e})"),
            None => format!(
                "f {:.1} / {:.1} px, sigma {} / {}",
                t.focal_px[0],
                t.focal_px[1],
                fmt_pct(t.focal_sigma_pct[0]),
                fmt_pct(t.focal_sigma_pct[1])
            ),
        };
        let mut note = format!(
            "{} with {} corners per image{}: re-detected with {}: {}; kept the {} corners result ({})",
            describe(&first),
            first.corners,
            if first.error.is_none() { " (a weak calibration)" } else { "" },
            denser.corners,
            describe(&denser),
            if keep_denser { denser.corners } else { first.corners },
            if first.error.is_some() || denser.error.is_some() {
                "the other failed"
            } else if z.is_some_and(|z| z > DISAGREEMENT_SIGMAS) {
                "principal points nearer the image centre: the two disagree beyond their sigmas"
            } else {
                "smaller focal sigma"
            },
        );
        let disagree = z.is_some_and(|z| z > DISAGREEMENT_SIGMAS);
        if let Some(z) = z {
            note.push_str(&format!("; the two focal lengths differ by {z:.1} combined sigmas"));
        }
        if disagree {
            note.push_str(": the scene supports more than one solution, and the kept one can be off by more than its sigma; record a second motion, or a scene with more depth");
        }
        let warn = disagree || first.error.is_some();
        Self {
            automatic,
            trials: vec![first, denser],
            kept: usize::from(keep_denser),
            disagreement_sigmas: z,
            note,
            warn,
        }
    }
}
