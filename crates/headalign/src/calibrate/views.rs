//! The one `calibrate` entry point for a list of stereo views ([`calibrate_views`]): the
//! views of one rig chosen ([`select_rig`]: a recorded session changes its rig with every
//! vergence reading; the others named in the report's `skipped`), a known lens removed
//! first ([`undistort_views`]), the lens model of [`CalibrateOptions::lens`] estimated
//! (its terms: [`super::lens_terms`]), and for images the corner density chosen
//! ([`Density`]: a second detection at a higher count when the first calibration is weak
//! or fails, the better kept, both reported in [`DensityReport`]).
//!
//! Images ([`StereoViews::Images`]) are first checked for scene depth on each view's own
//! stereo matches ([`require_depth`]; a planar target fails there with the degeneracy
//! named, not later in matching across views; a long sequence checks its keyframes
//! instead), then tracked ([`super::track_views_reporting`]) and self-calibrated
//! ([`calibrate_tracked`]) at each corner count. Each view's corners and stereo matches
//! are found once at the first corner count: the tracking takes the depth check's (the
//! same front end finds the same ones), and the first view's tracking is the depth
//! check's own; the denser retry detects anew. Tracked points
//! ([`StereoViews::Tracked`], a point-mode session) have no corner density: one
//! [`super::calibrate_rig`]. The result carries the call's seconds per stage
//! ([`crate::timing`]). Units and thresholds: those of the steps called.

use std::time::Instant;

use headalign_platform::{Encoders, StereoImages};
use rayon::prelude::*;

use super::route::{OwnMatching, track_views_sharing};
use super::{
    CalibrateOptions, Density, DensityReport, DensityTrial, LensModel, MotionCalibration,
    REFERENCE_ROUTE_MAX_VIEWS, TrackingProgress, calibrate_rig, calibrate_tracked, require_depth, select_rig,
    undistort_views,
};
use crate::error::AlignError;
use crate::observations::View;
use crate::timing::StageTimes;
use crate::tracking::{FrontEndOptions, StereoCorners, Tracker, ViewTracking};

/// The views to calibrate from.
#[derive(Clone, Copy)]
pub enum StereoViews<'a> {
    /// Named stereo images (a folder, a session, a recording), in order.
    Images(&'a [(String, StereoImages)]),
    /// Tracked points (a point-mode session): no front end, no corner density.
    Tracked(&'a [View]),
}

/// The options of [`calibrate_views`].
#[derive(Debug, Clone, Default)]
pub struct CalibrateViewsOptions {
    /// The self-calibration (constraints, lens model, estimation). Default
    /// [`CalibrateOptions::default`].
    pub calibrate: CalibrateOptions,
    /// The front end for images; its corner count is set by `density`. Default
    /// [`FrontEndOptions::default`].
    pub front_end: FrontEndOptions,
    /// The corner counts tried on images. Default [`Density::default`] (1500, then 3000).
    pub density: Density,
    /// The density was not fixed by the user (reported; the retry's choice is made
    /// either way). Default false.
    pub automatic_density: bool,
    /// A known lens per camera, removed from the observations first. Default none.
    pub lenses: Option<[LensModel; 2]>,
}

impl CalibrateViewsOptions {
    /// An error for bad corner counts or a bad guided-matching radius.
    pub fn validate(&self) -> Result<(), AlignError> {
        self.density.validate()?;
        let r = self.front_end.guided_radius_px;
        if !(r.is_finite() && r > 0.0) {
            return Err(AlignError::InvalidOption(format!(
                "guided matching radius must be positive, got {r}"
            )));
        }
        Ok(())
    }

    /// The front end at `corners` per image.
    fn front_end_at(&self, corners: usize) -> FrontEndOptions {
        let mut f = self.front_end.clone();
        f.features.max_features = corners;
        f
    }
}

/// What a step of [`calibrate_views`] on images is doing (for a progress display).
#[derive(Debug, Clone, Copy)]
pub enum ViewsProgress {
    /// Tracking at `corners` per image.
    Tracking {
        /// Corners per image.
        corners: usize,
        /// The tracker's progress.
        progress: TrackingProgress,
    },
    /// The tracking at `corners` is done.
    Tracked {
        /// Corners per image.
        corners: usize,
    },
    /// Self-calibrating `views` tracked views.
    Solving {
        /// Views.
        views: usize,
    },
    /// The self-calibration is done.
    Solved,
}

/// What [`calibrate_views`] found.
pub struct ViewsCalibration {
    /// The self-calibration (its report's `skipped` starts with the views of other rigs).
    pub calibration: MotionCalibration,
    /// The corner counts tried and the one kept (images only).
    pub density: Option<DensityReport>,
    /// The views left out as of another rig, each with the reason.
    pub other_rigs: Vec<String>,
    /// Image size of the views, pixels.
    pub image_size: [u32; 2],
    /// The seconds and calls per stage of this call ([`crate::timing`]: thread-seconds,
    /// counted process-wide over the call's span).
    pub timing: StageTimes,
    /// The call's wall time, seconds.
    pub wall_seconds: f64,
}

impl ViewsCalibration {
    /// A result with no other rigs and no timing yet ([`calibrate_views`] sets them).
    fn new(calibration: MotionCalibration, density: Option<DensityReport>, image_size: [u32; 2]) -> Self {
        Self {
            calibration,
            density,
            other_rigs: Vec::new(),
            image_size,
            timing: StageTimes::default(),
            wall_seconds: 0.0,
        }
    }
}

/// The views of one rig among `views` ([`select_rig`]) and the reasons of the others.
pub fn one_rig<T: Clone>(
    views: &[T],
    name_encoders: impl Fn(&T) -> (&str, Encoders),
) -> (Vec<T>, Vec<String>) {
    let pairs: Vec<(&str, Encoders)> = views.iter().map(name_encoders).collect();
    let choice = select_rig(&pairs);
    let rig = choice.used.iter().map(|&i| views[i].clone()).collect();
    (rig, choice.left_out.into_iter().map(|(_, why)| why).collect())
}

/// Each view's own stereo matches (a fresh tracker per view: no matching across views,
/// the views in parallel), for the scene-depth check and the known-intrinsics route.
pub fn stereo_only(
    views: &[(String, StereoImages)],
    front: &FrontEndOptions,
) -> Result<Vec<View>, AlignError> {
    Ok(stereo_only_keeping(views, front)?.0)
}

/// [`stereo_only`], also keeping what the tracking of the same views with the same front
/// end can take from it ([`OwnMatching`]: each view's corners and stereo matches, and the
/// first view's tracking).
pub(super) fn stereo_only_keeping(
    views: &[(String, StereoImages)],
    front: &FrontEndOptions,
) -> Result<(Vec<View>, OwnMatching), AlignError> {
    // The views on their own (in parallel); the first error in the views' order.
    type Own = (View, StereoCorners, Option<(Tracker, ViewTracking)>);
    let own: Vec<Result<Own, AlignError>> = views
        .par_iter()
        .enumerate()
        .map(|(i, (name, images))| {
            let mut t = Tracker::new(front.clone())?;
            let (capture, report, corners) = t
                .track_keeping_corners(images, name)
                .map_err(|e| e.in_step(&format!("stereo matching of '{name}'")))?;
            let first = (i == 0).then_some((t, report));
            Ok((View { name: name.clone(), capture }, corners, first))
        })
        .collect();
    let mut out = Vec::with_capacity(own.len());
    let mut kept = OwnMatching { front: front.clone(), names: Vec::new(), corners: Vec::new(), first: None };
    for o in own {
        let (view, corners, first) = o?;
        kept.names.push(view.name.clone());
        kept.corners.push(corners);
        if let Some((tracker, report)) = first {
            kept.first = Some((tracker, view.capture.clone(), report));
        }
        out.push(view);
    }
    Ok((out, kept))
}

/// Self-calibrate a stereo rig from `views` (module docs); `progress` hears each step on
/// images.
pub fn calibrate_views(
    views: StereoViews<'_>,
    options: &CalibrateViewsOptions,
    progress: &mut dyn FnMut(ViewsProgress),
) -> Result<ViewsCalibration, AlignError> {
    options.validate()?;
    let (t0, before) = (Instant::now(), StageTimes::now());
    let (mut result, other_rigs) = match views {
        StereoViews::Images(images) => {
            let (rig, other_rigs) = one_rig(images, |(n, v)| (n.as_str(), v.encoders));
            (calibrate_images(&rig, options, progress)?, other_rigs)
        }
        StereoViews::Tracked(tracked) => {
            let (rig, other_rigs) = one_rig(tracked, |v| (v.name.as_str(), v.capture.encoders));
            let Some(image_size) = rig.first().map(|v| v.capture.image_size) else {
                return Err(AlignError::Observations("no views".into()));
            };
            let rig = match &options.lenses {
                Some(l) => undistort_views(&rig, l),
                None => rig,
            };
            let calibration = calibrate_rig(&rig, &options.calibrate)?;
            (ViewsCalibration::new(calibration, None, image_size), other_rigs)
        }
    };
    result.calibration.report.skipped.splice(0..0, other_rigs.iter().cloned());
    result.other_rigs = other_rigs;
    result.timing = StageTimes::since(&before);
    result.wall_seconds = t0.elapsed().as_secs_f64();
    Ok(result)
}

/// One density trial: track at `corners` and self-calibrate.
fn density_trial(
    views: &[(String, StereoImages)],
    corners: usize,
    options: &CalibrateViewsOptions,
    own: Option<&OwnMatching>,
    progress: &mut dyn FnMut(ViewsProgress),
) -> (Result<MotionCalibration, AlignError>, DensityTrial) {
    let t = Instant::now();
    let opts = &options.calibrate;
    let result = (|| {
        let tracked = track_views_sharing(views, &options.front_end_at(corners), opts, own, &mut |p| {
            progress(ViewsProgress::Tracking { corners, progress: p })
        });
        progress(ViewsProgress::Tracked { corners });
        progress(ViewsProgress::Solving { views: views.len() });
        let cal = calibrate_tracked(tracked?, options.lenses.as_ref(), opts);
        progress(ViewsProgress::Solved);
        cal
    })();
    let seconds = t.elapsed().as_secs_f64();
    let trial = match &result {
        Ok(c) => DensityTrial::new(corners, c, opts, seconds),
        Err(e) => DensityTrial::failed(corners, chain(e), seconds),
    };
    (result, trial)
}

/// An error and its sources joined by ": " (as `anyhow`'s alternate display).
fn chain(e: &AlignError) -> String {
    let mut text = e.to_string();
    let mut source = std::error::Error::source(e);
    while let Some(s) = source {
        text.push_str(&format!(": {s}"));
        source = s.source();
    }
    text
}

/// [`calibrate_views`] on the images of one rig: the depth check, then the density
/// trials.
fn calibrate_images(
    views: &[(String, StereoImages)],
    options: &CalibrateViewsOptions,
    progress: &mut dyn FnMut(ViewsProgress),
) -> Result<ViewsCalibration, AlignError> {
    let density = options.density;
    let Some((_, first)) = views.first() else { return Err(AlignError::Observations("no views".into())) };
    let image_size = first.image_size();
    let mut kept = None;
    if views.len() <= REFERENCE_ROUTE_MAX_VIEWS {
        let (own, matching) = stereo_only_keeping(views, &options.front_end_at(density.corners))?;
        let own = match &options.lenses {
            Some(l) => undistort_views(&own, l),
            None => own,
        };
        require_depth(&own, &options.calibrate)?;
        kept = Some(matching);
    }
    // The first density's tracking takes the corners the depth check found (the same
    // front end); the retry's detects its own.
    let (first_result, first_trial) = density_trial(views, density.corners, options, kept.as_ref(), progress);
    // A missing motion or a bad option is not a matter of density.
    let structural =
        matches!(&first_result, Err(AlignError::MissingMotion(_) | AlignError::InvalidOption(_)));
    let automatic = options.automatic_density;
    let (mut cal, report) = if density.retry(&first_trial) && !structural {
        let (denser_result, denser_trial) =
            density_trial(views, density.retry_corners, options, None, progress);
        let report = DensityReport::choose(automatic, first_trial, Some(denser_trial));
        let cal = match (first_result, denser_result) {
            (Ok(first), Ok(denser)) => {
                if report.kept == 1 {
                    denser
                } else {
                    first
                }
            }
            (Ok(first), Err(_)) => first,
            (Err(_), Ok(denser)) => denser,
            (Err(first), Err(denser)) => {
                return Err(first.in_step(&format!(
                    "self-calibration failed with {} and with {} corners per image (with {}: {})",
                    density.corners,
                    density.retry_corners,
                    density.retry_corners,
                    chain(&denser)
                )));
            }
        };
        (cal, report)
    } else {
        (first_result?, DensityReport::choose(automatic, first_trial, None))
    };
    if report.warn {
        cal.report.warnings.push(report.note.clone());
    }
    Ok(ViewsCalibration::new(cal, Some(report), image_size))
}
