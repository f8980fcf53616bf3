//! The image front end: turns the stereo images of successive views into the tracked
//! point observations that the estimation core consumes (DESIGN.md section 2 steps 1-2,
//! paper section 3.2 steps 1-2), and an adapter that makes any [`ImagingHead`] a
//! [`StereoHead`] so the point-mode procedures run unchanged on pixels.
//!
//! What it computes, per view:
//! 1. corners with 256-bit binary descriptors in both images
//!    ([`headalign_vision::detect_and_describe`]);
//! 2. stereo matches: mutual nearest neighbours with a ratio test, `F` by RANSAC (the
//!    DEGENSAC estimator of the geometry crate), then guided matching in a band around
//!    each epipolar line;
//! 3. for every view after the first ("reference"), matches of each image to the same
//!    camera's reference image: descriptor matches, a plane homography by RANSAC (a small
//!    head rotation maps each image almost by `K R K^-1`; the threshold allows for the
//!    parallax of the axis offsets), then guided matching around the homography's
//!    prediction;
//! 4. track identities: a reference left corner `i` is track `i`; its stereo partner
//!    shares the id; a later view's corner inherits the id of the reference corner it
//!    matches; stereo pairs first seen in a later view get fresh ids. A stereo pair whose
//!    two temporal matches disagree is dropped (one of them is wrong).
//!
//! Units: thresholds in pixels. Degrees of freedom: `F` 7, plane homography 8.
//! Pitfalls: corners are detected independently per image, so a track's pixel is only as
//! consistent as the detector's sub-pixel refinement (about 0.2-0.4 px on rendered
//! images); a wrong temporal match gives a wrong observation, which the estimation's
//! robust adjustment and re-selection remove.

use headalign_geometry::fundamental::{FundamentalMatrix, estimate_fundamental};
use headalign_geometry::homography2d::{Homography2, Homography2Estimator};
use headalign_geometry::ransac::{RansacOptions, ransac};
use headalign_platform::{
    Encoders, ImagingHead, PlatformError, StereoCapture, StereoHead, StereoImages, TrackObservation,
};
use headalign_vision::{
    FeatureOptions, Features, MatchOptions, detect_and_describe, match_descriptors, match_epipolar,
    match_homography,
};
use nalgebra::{Matrix3, Point2};
use serde::Serialize;

use crate::AlignError;

/// Options of the [`Tracker`].
#[derive(Debug, Clone)]
pub struct FrontEndOptions {
    /// Corner detection and description (default: the vision crate's defaults, 1500
    /// corners per image).
    pub features: FeatureOptions,
    /// Descriptor matching (default: mutual nearest neighbours, ratio 0.8, at most 64 bits).
    pub matching: MatchOptions,
    /// RANSAC for the stereo `F`; Sampson threshold (default 2 px: detector noise is well
    /// under 1 px).
    pub stereo: RansacOptions,
    /// Band around the epipolar line for guided stereo matching (default 2 px).
    pub epipolar_band_px: f64,
    /// RANSAC for the plane homography between a view and the reference; transfer
    /// threshold (default 8 px: the parallax of offset axes under a few degrees, plus noise).
    pub motion: RansacOptions,
    /// Radius around the homography's prediction for guided temporal matching (default 8 px).
    pub guided_radius_px: f64,
    /// Fewest matches a step needs (default 20).
    pub min_matches: usize,
}

impl Default for FrontEndOptions {
    fn default() -> Self {
        Self {
            features: FeatureOptions { max_features: 1500, ..FeatureOptions::default() },
            matching: MatchOptions::default(),
            stereo: RansacOptions { threshold: 2.0, min_iterations: 500, ..RansacOptions::default() },
            epipolar_band_px: 2.0,
            motion: RansacOptions { threshold: 8.0, ..RansacOptions::default() },
            guided_radius_px: 8.0,
            min_matches: 20,
        }
    }
}

impl FrontEndOptions {
    /// Check every option.
    pub fn validate(&self) -> Result<(), AlignError> {
        let bad = |m: String| Err(AlignError::InvalidOption(m));
        self.features.validate().map_err(|e| AlignError::InvalidOption(format!("features: {e}")))?;
        self.matching.validate().map_err(|e| AlignError::InvalidOption(format!("matching: {e}")))?;
        self.stereo.validate().map_err(|e| AlignError::InvalidOption(format!("stereo RANSAC: {e}")))?;
        self.motion.validate().map_err(|e| AlignError::InvalidOption(format!("motion RANSAC: {e}")))?;
        for (name, v) in
            [("epipolar_band_px", self.epipolar_band_px), ("guided_radius_px", self.guided_radius_px)]
        {
            if !(v.is_finite() && v > 0.0) {
                return bad(format!("{name} must be positive, got {v}"));
            }
        }
        if self.min_matches < 8 {
            return bad(format!("min_matches must be at least 8, got {}", self.min_matches));
        }
        Ok(())
    }
}

/// What the front end found in one view.
#[derive(Debug, Clone, Serialize, Default)]
pub struct ViewTracking {
    /// Corners in the left and right image.
    pub corners: [usize; 2],
    /// Stereo matches (after guided matching).
    pub stereo_matches: usize,
    /// Matches of the left / right image to the reference's (zero for the reference).
    pub temporal_matches: [usize; 2],
    /// Observations handed on (left, right).
    pub observations: [usize; 2],
}

/// The reference view's corners and their track ids.
#[derive(Debug, Clone)]
struct Reference {
    left: Features,
    right: Features,
    left_ids: Vec<Option<u64>>,
    right_ids: Vec<Option<u64>>,
}

/// Tracks corners from the first view it sees (the reference) through later views.
#[derive(Debug, Clone)]
pub struct Tracker {
    options: FrontEndOptions,
    reference: Option<Reference>,
    next_id: u64,
}

fn point(f: &Features, i: usize) -> Point2<f64> {
    let k = &f.keypoints[i];
    Point2::new(f64::from(k.x), f64::from(k.y))
}

fn rows(m: &Matrix3<f64>) -> [[f64; 3]; 3] {
    [[m[(0, 0)], m[(0, 1)], m[(0, 2)]], [m[(1, 0)], m[(1, 1)], m[(1, 2)]], [m[(2, 0)], m[(2, 1)], m[(2, 2)]]]
}

fn vision(step: &str) -> impl Fn(headalign_vision::VisionError) -> AlignError + '_ {
    move |e| AlignError::Images(format!("{step}: {e}"))
}

impl Tracker {
    /// A tracker with no reference yet.
    pub fn new(options: FrontEndOptions) -> Result<Self, AlignError> {
        options.validate()?;
        Ok(Self { options, reference: None, next_id: 0 })
    }

    /// Stereo matches `(left index, right index)` of one view.
    fn stereo(
        &self,
        left: &Features,
        right: &Features,
        view: &str,
    ) -> Result<Vec<(usize, usize)>, AlignError> {
        let o = &self.options;
        let m = match_descriptors(&left.descriptors, &right.descriptors, &o.matching)
            .map_err(vision("stereo matching"))?;
        if m.len() < o.min_matches {
            return Err(AlignError::TooFewTracks {
                what: format!("matched between the left and right images of view '{view}'"),
                needed: o.min_matches,
                got: m.len(),
            });
        }
        let pairs: Vec<_> = m.iter().map(|x| (point(left, x.a), point(right, x.b))).collect();
        let f: FundamentalMatrix = estimate_fundamental(&pairs, &o.stereo)
            .map_err(|e| AlignError::Geometry { step: format!("stereo F of view '{view}'"), cause: e })?
            .model;
        let guided = match_epipolar(left, right, &rows(&f.0), o.epipolar_band_px, &o.matching)
            .map_err(vision("guided stereo matching"))?;
        Ok(guided
            .iter()
            .filter(|x| f.sampson_distance(&point(left, x.a), &point(right, x.b)) <= o.stereo.threshold)
            .map(|x| (x.a, x.b))
            .collect())
    }

    /// Matches `(reference index, current index)` of one camera's image to its reference.
    fn temporal(
        &self,
        reference: &Features,
        current: &Features,
        what: &str,
    ) -> Result<Vec<(usize, usize)>, AlignError> {
        let o = &self.options;
        let m = match_descriptors(&reference.descriptors, &current.descriptors, &o.matching)
            .map_err(vision("temporal matching"))?;
        let pairs: Vec<_> = m.iter().map(|x| (point(reference, x.a), point(current, x.b))).collect();
        if pairs.len() < o.min_matches {
            return Err(AlignError::TooFewTracks {
                what: format!("matched {what}"),
                needed: o.min_matches,
                got: pairs.len(),
            });
        }
        let g: Homography2 = ransac(&Homography2Estimator, &pairs, &o.motion)
            .map_err(|e| AlignError::Geometry { step: format!("image motion {what}"), cause: e })?
            .model;
        let guided = match_homography(reference, current, &rows(&g.0), o.guided_radius_px, &o.matching)
            .map_err(vision("guided temporal matching"))?;
        Ok(guided
            .iter()
            .filter(|x| g.transfer_error(&point(reference, x.a), &point(current, x.b)) <= o.motion.threshold)
            .map(|x| (x.a, x.b))
            .collect())
    }

    /// Detect, match and assign track ids in one view; the first view becomes the reference.
    pub fn track(
        &mut self,
        images: &StereoImages,
        view: &str,
    ) -> Result<(StereoCapture, ViewTracking), AlignError> {
        let o = &self.options;
        let left = detect_and_describe(&images.left, &o.features).map_err(vision("left image"))?;
        let right = detect_and_describe(&images.right, &o.features).map_err(vision("right image"))?;
        let stereo = self.stereo(&left, &right, view)?;
        let mut report = ViewTracking {
            corners: [left.len(), right.len()],
            stereo_matches: stereo.len(),
            ..ViewTracking::default()
        };
        let mut left_ids: Vec<Option<u64>> = vec![None; left.len()];
        let mut right_ids: Vec<Option<u64>> = vec![None; right.len()];
        match &self.reference {
            None => {
                for &(a, b) in &stereo {
                    let id = self.next_id;
                    self.next_id += 1;
                    left_ids[a] = Some(id);
                    right_ids[b] = Some(id);
                }
            }
            Some(r) => {
                let tl = self.temporal(
                    &r.left,
                    &left,
                    &format!("between the left images of the reference and '{view}'"),
                )?;
                let tr = self.temporal(
                    &r.right,
                    &right,
                    &format!("between the right images of the reference and '{view}'"),
                )?;
                report.temporal_matches = [tl.len(), tr.len()];
                for &(a, b) in &tl {
                    left_ids[b] = r.left_ids[a];
                }
                for &(a, b) in &tr {
                    right_ids[b] = r.right_ids[a];
                }
                // Stereo pairs: share an id, or get a fresh one; disagreeing pairs go.
                let mut fresh = self.next_id;
                for &(a, b) in &stereo {
                    match (left_ids[a], right_ids[b]) {
                        (Some(x), Some(y)) if x != y => {
                            left_ids[a] = None;
                            right_ids[b] = None;
                        }
                        (Some(x), None) => right_ids[b] = Some(x),
                        (None, Some(y)) => left_ids[a] = Some(y),
                        (None, None) => {
                            left_ids[a] = Some(fresh);
                            right_ids[b] = Some(fresh);
                            fresh += 1;
                        }
                        _ => {}
                    }
                }
                self.next_id = fresh;
            }
        }
        let observe = |f: &Features, ids: &[Option<u64>]| -> Vec<TrackObservation> {
            ids.iter()
                .enumerate()
                .filter_map(|(i, id)| id.map(|track| TrackObservation { track, pixel: point(f, i) }))
                .collect()
        };
        let capture = StereoCapture {
            encoders: images.encoders,
            image_size: images.image_size(),
            left: observe(&left, &left_ids),
            right: observe(&right, &right_ids),
        };
        report.observations = [capture.left.len(), capture.right.len()];
        if self.reference.is_none() {
            self.reference = Some(Reference { left, right, left_ids, right_ids });
        }
        Ok((capture, report))
    }
}

/// An [`ImagingHead`] seen as a [`StereoHead`]: every capture takes images, keeps them,
/// and hands on the tracked observations. The first capture is the tracking reference.
pub struct TrackingHead<'a, H: ImagingHead> {
    head: &'a mut H,
    tracker: Tracker,
    /// Every captured image pair, in order (nothing captured is lost).
    pub images: Vec<StereoImages>,
    /// The front end's report per capture.
    pub tracking: Vec<ViewTracking>,
}

impl<'a, H: ImagingHead> TrackingHead<'a, H> {
    /// Wrap a head.
    pub fn new(head: &'a mut H, options: FrontEndOptions) -> Result<Self, AlignError> {
        Ok(Self { head, tracker: Tracker::new(options)?, images: Vec::new(), tracking: Vec::new() })
    }

    /// The wrapped head.
    pub fn inner(&mut self) -> &mut H {
        self.head
    }
}

impl<H: ImagingHead> StereoHead for TrackingHead<'_, H> {
    fn image_size(&self) -> [u32; 2] {
        self.head.image_size()
    }

    fn read_encoders(&mut self) -> Result<Encoders, PlatformError> {
        self.head.read_encoders()
    }

    fn move_to(&mut self, target: &Encoders) -> Result<(), PlatformError> {
        self.head.move_to(target)
    }

    fn capture(&mut self) -> Result<StereoCapture, PlatformError> {
        let images = self.head.capture_images()?;
        self.images.push(images);
        let Some(images) = self.images.last() else {
            return Err(PlatformError::Device("no image captured".into()));
        };
        let name = format!("view {}", self.images.len());
        let (capture, report) =
            self.tracker.track(images, &name).map_err(|e| PlatformError::FrontEnd(e.to_string()))?;
        self.tracking.push(report);
        Ok(capture)
    }
}
