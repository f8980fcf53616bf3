//! How the stereo views of a folder are tracked for self-calibration ([`track_views`]):
//! against the first view, or through consecutive views as a sequence.
//!
//! - **Reference** ([`Route::Reference`], the chain of [`super::calibrate_rig`]): every
//!   view is matched to the first ([`TrackingMode::Reference`]: plane homography, guided
//!   matching) and every motion is fitted from it. Taken for at most
//!   [`REFERENCE_ROUTE_MAX_VIEWS`] views when each of them shares at least
//!   `estimation.min_tracks` tracks seen by both cameras with the first (the reference
//!   chain's own requirement): head rotations, a few hand-held views around one scene.
//! - **Sequence** ([`Route::Sequence`], [`super::calibrate_sequence`]): every view is
//!   matched to the one before ([`TrackingMode::Previous`]: the fundamental matrix of
//!   each camera across the motion, stereo pairs linked as units), so tracks chain along
//!   the sequence and a view that links to nothing starts fresh ones (a new segment).
//!   Taken for longer folders, and for those where tracking against the first failed or
//!   left a view with too few tracks in common with it. A view whose own stereo matching
//!   fails is left out with its reason; the next one is matched to the view before it.
//!
//! The reference attempt stops at the first view that does not overlap the first, so a
//! sequence pays for the tracking of the views before it twice (bounded by
//! [`REFERENCE_ROUTE_MAX_VIEWS`]). When the views' own stereo matching has run already
//! (the scene-depth check of [`super::calibrate_views`]) with a front end that detects
//! alike, the reference attempt takes each view's corners and stereo matches from it, and
//! the first view's tracking ([`OwnMatching`]): the same tracks as detecting again. Units: track counts. Pitfalls: tracking against the
//! first view can return a few wrong tracks for a view that shows another place; the
//! threshold is the reference chain's minimum, so such a view either calibrates on that
//! route as it always did or goes to the sequence route.
//!
//! [`TrackingMode::Reference`]: crate::tracking::TrackingMode::Reference
//! [`TrackingMode::Previous`]: crate::tracking::TrackingMode::Previous

use headalign_platform::{StereoCapture, StereoImages};
use serde::Serialize;

use super::graph::ViewTracks;
use super::{
    CalibrateOptions, LensModel, MeasuredVariances, MotionCalibration, calibrate_rig, calibrate_sequence,
    undistort_views,
};
use crate::error::AlignError;
use crate::observations::View;
use crate::tracking::{FrontEndOptions, StereoCorners, Tracker, TrackingMode, ViewTracking};

/// Folders of more views than this are tracked as sequences whatever their overlap
/// (module docs): the reference chain adjusts every view, and matching every view to the
/// first only works while the rig stays in one place.
pub const REFERENCE_ROUTE_MAX_VIEWS: usize = 20;

/// The sequence route's front end draws at most this many RANSAC samples for each view's
/// stereo `F` and each camera's `F` to the view before, unless its inlier ratio asks for
/// more (the adaptive count at confidence 0.999: 80 samples at 70 % inliers, 880 at 50 %);
/// the front end's own floor is 500. Three such fits per view were a third of the front
/// end's time; on the 50-view rendered sequence of `benches/sequence.rs` the floor of
/// 100 took `calibrate` from 19.4 to 13.2 s of user time, linked the same tracks to 1 % and gave the same
/// focal length to 0.001 px.
pub const SEQUENCE_RANSAC_MIN_ITERATIONS: usize = 100;

/// Which chain the tracked views are for (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Route {
    /// Every view against the first: [`super::calibrate_rig`].
    Reference,
    /// Every view against the one before: [`super::calibrate_sequence`].
    Sequence,
}

/// Views tracked for self-calibration.
#[derive(Debug, Clone)]
pub struct TrackedViews {
    /// The chain they are for.
    pub route: Route,
    /// The tracked views, in order (views whose tracking failed left out).
    pub views: Vec<View>,
    /// The front end's report per tracked view.
    pub tracking: Vec<ViewTracking>,
    /// Why the route was taken (empty for the reference route).
    pub notes: Vec<String>,
    /// Views whose tracking failed, with the reason (`NAME: reason`), left out.
    pub failed: Vec<String>,
}

/// Self-calibrate views tracked by [`track_views`] by the chain of their route, with a
/// known lens (`lenses`, left and right) removed from the observations first; a
/// sequence's report carries the tracking notes, and the views whose tracking failed
/// among those `skipped`. The residuals are checked against the localisation noise the
/// front end measured ([`crate::rig::image_noise`]).
pub fn calibrate_tracked(
    tracked: TrackedViews,
    lenses: Option<&[LensModel; 2]>,
    options: &CalibrateOptions,
) -> Result<MotionCalibration, AlignError> {
    let views = match lenses {
        Some(l) => undistort_views(&tracked.views, l),
        None => tracked.views,
    };
    let measured: MeasuredVariances =
        views.iter().zip(tracked.tracking).map(|(v, t)| (v.name.clone(), t.localisation)).collect();
    let mut c = match tracked.route {
        Route::Reference => calibrate_rig(&views, options)?,
        Route::Sequence => {
            let mut c = calibrate_sequence(&views, options)?;
            if let Some(s) = c.report.sequence.as_mut() {
                s.tracking_notes = tracked.notes;
            }
            c.report.skipped.extend(tracked.failed);
            c
        }
    };
    super::fit_checks::check_against_images(&mut c, &measured);
    Ok(c)
}

/// Track named stereo views for self-calibration (module docs): against the first while
/// that works for a folder of at most [`REFERENCE_ROUTE_MAX_VIEWS`], otherwise as a
/// sequence. `front.mode` is overridden by the route.
pub fn track_views(
    images: &[(String, StereoImages)],
    front: &FrontEndOptions,
    options: &CalibrateOptions,
) -> Result<TrackedViews, AlignError> {
    track_views_reporting(images, front, options, &mut |_| {})
}

/// What [`track_views_reporting`] tells its caller after each view.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TrackingProgress {
    /// The route being tracked (the reference attempt may give way to the sequence
    /// route, which starts again from the first view).
    pub route: Route,
    /// Views tracked (or failed) on this route so far.
    pub done: usize,
    /// Views in all.
    pub total: usize,
}

/// [`track_views`], calling `progress` after each view (the front end is most of a long
/// sequence's time: a progress bar).
pub fn track_views_reporting(
    images: &[(String, StereoImages)],
    front: &FrontEndOptions,
    options: &CalibrateOptions,
    progress: &mut dyn FnMut(TrackingProgress),
) -> Result<TrackedViews, AlignError> {
    track_views_sharing(images, front, options, None, progress)
}

/// The views' own stereo matching as the scene-depth check ran it
/// (`views::stereo_only`): the front end it ran with, each view's corners and stereo
/// matches, and the first view's tracking (the tracker after it, its capture and report).
/// The reference tracking of the same views with a front end that detects alike
/// ([`FrontEndOptions::detects_like`]) takes them instead of detecting again: the same
/// inputs, the same tracks.
pub(super) struct OwnMatching {
    pub(super) front: FrontEndOptions,
    pub(super) names: Vec<String>,
    pub(super) corners: Vec<StereoCorners>,
    pub(super) first: Option<(Tracker, StereoCapture, ViewTracking)>,
}

impl OwnMatching {
    /// The matching of `images` if it is theirs and `front` (the reference tracking's)
    /// detects like the one it ran with.
    fn of<'a>(
        own: Option<&'a Self>,
        images: &[(String, StereoImages)],
        front: &FrontEndOptions,
    ) -> Option<&'a Self> {
        own.filter(|o| {
            o.front.detects_like(front)
                && o.names.len() == images.len()
                && o.names.iter().zip(images).all(|(n, (name, _))| n == name)
        })
    }

    /// View `i` tracked by `tracker` (a tracker with options `front` that has tracked
    /// views `0..i`) from the kept matching: the first view's tracking itself when its
    /// tracker ran with the same options, else the view's corners tracked anew.
    fn track(
        &self,
        tracker: &mut Tracker,
        front: &FrontEndOptions,
        i: usize,
        images: &StereoImages,
        name: &str,
    ) -> Result<(StereoCapture, ViewTracking), AlignError> {
        match &self.first {
            Some((first, capture, report)) if i == 0 && self.front == *front => {
                *tracker = first.clone();
                Ok((capture.clone(), report.clone()))
            }
            _ => match self.corners.get(i) {
                Some(c) => tracker.track_corners(images, name, c.clone()),
                None => tracker.track(images, name),
            },
        }
    }
}

/// [`track_views_reporting`], the reference tracking taking the views' own stereo
/// matching `own` where it applies ([`OwnMatching`]).
pub(super) fn track_views_sharing(
    images: &[(String, StereoImages)],
    front: &FrontEndOptions,
    options: &CalibrateOptions,
    own: Option<&OwnMatching>,
    progress: &mut dyn FnMut(TrackingProgress),
) -> Result<TrackedViews, AlignError> {
    let mut notes = Vec::new();
    let total = images.len();
    if images.len() <= REFERENCE_ROUTE_MAX_VIEWS {
        let mut on_view = |done| progress(TrackingProgress { route: Route::Reference, done, total });
        match against_first(images, front, options.estimation.min_tracks, own, &mut on_view)? {
            Ok(tracked) => return Ok(tracked),
            Err(why) => notes.push(why),
        }
    } else {
        notes.push(format!("{} views: tracked as a sequence", images.len()));
    }
    let mut sequence = FrontEndOptions { mode: TrackingMode::Previous, ..front.clone() };
    for r in [&mut sequence.stereo, &mut sequence.drive] {
        r.min_iterations = r.min_iterations.min(SEQUENCE_RANSAC_MIN_ITERATIONS);
    }
    let mut tracker = Tracker::new(sequence)?;
    let (mut views, mut tracking, mut failed) = (Vec::new(), Vec::new(), Vec::new());
    for (i, (name, pair)) in images.iter().enumerate() {
        match tracker.track(pair, name) {
            Ok((capture, report)) => {
                views.push(View { name: name.clone(), capture });
                tracking.push(report);
            }
            Err(e) => failed.push(format!("{name}: tracking failed: {e}")),
        }
        progress(TrackingProgress { route: Route::Sequence, done: i + 1, total });
    }
    Ok(TrackedViews { route: Route::Sequence, views, tracking, notes, failed })
}

/// The reference route's tracking (module docs): `Ok(Err(why))` at the first view that
/// fails to track against the first or shares fewer than `min_tracks` stereo tracks with
/// it; an error only if the first view itself fails (as the reference chain always did).
fn against_first(
    images: &[(String, StereoImages)],
    front: &FrontEndOptions,
    min_tracks: usize,
    own: Option<&OwnMatching>,
    on_view: &mut dyn FnMut(usize),
) -> Result<Result<TrackedViews, String>, AlignError> {
    let front = FrontEndOptions { mode: TrackingMode::Reference, ..front.clone() };
    let own = OwnMatching::of(own, images, &front);
    let mut tracker = Tracker::new(front.clone())?;
    let (mut views, mut tracking): (Vec<View>, Vec<ViewTracking>) = (Vec::new(), Vec::new());
    let mut first: Option<ViewTracks> = None;
    for (i, (name, pair)) in images.iter().enumerate() {
        let tracked = match own {
            Some(o) => o.track(&mut tracker, &front, i, pair, name),
            None => tracker.track(pair, name),
        };
        let (capture, report) = match tracked {
            Ok(t) => t,
            Err(e) if first.is_some() => {
                return Ok(Err(format!("'{name}' does not track against the first view ({e}): a sequence")));
            }
            Err(e) => return Err(e),
        };
        let view = View { name: name.clone(), capture };
        let tracks = ViewTracks::of(&view);
        if let Some(f) = &first {
            let shared = f.shared(&tracks);
            if shared < min_tracks {
                return Ok(Err(format!(
                    "'{name}' shares {shared} tracks with the first view (fewer than {min_tracks}): a sequence"
                )));
            }
        } else {
            first = Some(tracks);
        }
        views.push(view);
        tracking.push(report);
        on_view(views.len());
    }
    Ok(Ok(TrackedViews { route: Route::Reference, views, tracking, notes: Vec::new(), failed: Vec::new() }))
}
