//! The image front end: turns the stereo images of successive views into the tracked
//! point observations that the estimation core consumes (`docs/how-it-works.md#2-estimation` items 1-3,
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
//! 5. patch refinement ([`FrontEndOptions::refine`], on by default): every observation of a
//!    track in a later view is aligned, by sub-pixel Lucas-Kanade
//!    ([`headalign_vision::refine_point_against_patch`]: translation plus gain and bias,
//!    a Gaussian-weighted 15x15 window), against the patch of the same track in the same
//!    camera's earlier image (the reference, or the previous view), warped by the local
//!    affine map fitted to the track's nearest matches (least squares on up to
//!    `refine_neighbours` correspondences, refitted without those off by more than 2 px;
//!    the affine of all correspondences where the neighbours are too few or too
//!    clustered). With [`FrontEndOptions::refine_stereo`] (on by default) the
//!    first view's (and, in [`TrackingMode::Previous`], each unlinked pair's) right
//!    corner is aligned in the same way against its left partner's patch. An observation
//!    whose alignment fails (window at the border, no texture, no convergence, moved more
//!    than `max_shift_px`, ZNCC below `min_zncc`) is dropped. Why: corners are detected
//!    independently per image, so a track's pixels in two images are each the detector's
//!    own sub-pixel fit, not the same physical point (on rendered images 20-26 % of
//!    observations were more than 1 px off the truth, a heavy tail that biased
//!    self-calibration by 1-3 %); aligned patches make every observation in a camera
//!    that camera's reference corner's point (with `refine_stereo`, the left one's).
//!
//! Localisation noise ([`ViewTracking::localisation`]): every patch alignment reports
//! its own localisation sigma ([`headalign_vision::Refinement::sigma_px`]: the
//! least-squares precision of the two windows, measured from their grey-level residual;
//! no geometry). A track is defined by the corner that starts it (a fresh pair's left
//! corner: variance 0, the surface point under that pixel is the track's point); an
//! aligned corner inherits the variance of the corner it was aligned against and adds its
//! alignment's sigma squared (errors along a chain of alignments add up: in
//! [`TrackingMode::Previous`] a track's variance grows with its length). A corner that was
//! not aligned (refinement off, a later view's fresh right corner in
//! [`TrackingMode::Reference`]) has none. Self-calibration compares its reprojection
//! residuals with these ([`crate::rig::image_noise`]).
//!
//! Two tracking modes ([`TrackingMode`]):
//! - [`TrackingMode::Reference`] (the verge/tilt procedure): every view is matched to the
//!   first, as in step 3 above; the head only rotates about a fixed rig, so the plane
//!   homography predicts every match to within the axis-offset parallax.
//! - [`TrackingMode::Previous`] (robot drives): every view is matched to the view just
//!   before it, and a later view inherits that view's ids, so the captures before and
//!   after a drive share track ids. A drive translates the rig: the image motion is an
//!   expansion from the epipole whose size depends on each point's depth (a 0.10 m drive
//!   towards panels 1 m away moves their corners by 10-50 px, the room behind by a few),
//!   so no homography and no encoder-based prediction holds. Instead, per camera, free
//!   descriptor matches (mutual, ratio test) and the fundamental matrix of the two images
//!   by RANSAC (7 degrees of freedom, Sampson pixels; a drive with any turn is a general
//!   motion); then the stereo pairs of the two views are matched *as units*: a previous
//!   pair and a current pair are candidates when both cameras' drive `F` accept them
//!   (Sampson distance within the threshold in the left and in the right image), the
//!   cost is the sum of the two Hamming distances, and the best candidate is kept when
//!   it is mutual and passes the ratio test. One camera's wrong match slides along its
//!   epipolar line, which its own `F` cannot catch; the other camera's `F` and
//!   descriptor rarely agree with it (seed 1, a 0.10 m drive: 319 linked pairs, 4 off by
//!   more than 3 px against the truth; matching each camera separately and letting
//!   either link a pair left 16 % wrong, some by hundreds of pixels). Unlinked pairs
//!   start fresh tracks, unpaired corners carry none; a view that cannot be linked (too
//!   few matches, no `F`: e.g. after a large pan move) starts fresh tracks and reports
//!   zero temporal matches: nothing uses tracks across such a gap.
//!
//! Stereo prior ([`TrackingHead::with_stereo_prior`], [`Tracker::track_with_prior`]): a
//! calibrated rig predicts the stereo `F` at any readings; stereo matching then starts
//! from matches within `prior_band_px` of its epipolar lines instead of free ones. With
//! parallel cameras and a scene 1 m away, disparities reach 200 px and the two views
//! differ enough that free matching returned mostly wrong pairs (reprojection median
//! 11.8 px against the truth, seed 1) where the prior gives 0.15 px.
//!
//! Units: thresholds in pixels. Degrees of freedom: `F` 7, plane homography 8.
//! Pitfalls: without patch refinement a track's pixel is only as consistent as the
//! detector's sub-pixel refinement (about 0.2-0.4 px on rendered images, with a heavy
//! tail); a wrong temporal match gives a wrong observation, which the patch alignment
//! mostly rejects (low ZNCC) and the estimation's robust adjustment and re-selection
//! remove. The local affine map assumes the neighbours lie on the same surface; at a
//! depth edge it is wrong at the window's rim, which the centre weighting tolerates.

use headalign_geometry::fundamental::{FundamentalMatrix, estimate_fundamental};
use headalign_geometry::homography2d::{Homography2, Homography2Estimator};
use headalign_geometry::ransac::{RansacOptions, ransac};
use headalign_platform::{
    Encoders, ImagingHead, PlatformError, StereoCapture, StereoHead, StereoImages, TrackObservation, Vehicle,
};
use headalign_vision::{
    FeatureOptions, Features, GrayImage, MatchOptions, PatchRefineOptions, detect_and_describe,
    match_descriptors, match_epipolar, match_homography, refine_point_against_patch,
};
use nalgebra::{Matrix3, Point2};
use serde::Serialize;

use crate::AlignError;

/// Which earlier view a new view is matched to (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum TrackingMode {
    /// Every view against the first (head rotations: plane homography, guided matching).
    #[default]
    Reference,
    /// Every view against the one before (robot drives: `F` by RANSAC, epipolar-guided
    /// matching; an unlinked view starts fresh tracks).
    Previous,
}

/// Options of the [`Tracker`].
#[derive(Debug, Clone, PartialEq)]
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
    /// Which earlier view each view is matched to (default [`TrackingMode::Reference`]).
    pub mode: TrackingMode,
    /// Band around the epipolar lines of a predicted stereo `F` (a calibrated rig's,
    /// [`TrackingHead::with_stereo_prior`]) for the first stereo matches (default 4 px: a
    /// self-calibrated rig predicts the lines to about a pixel; the `F` re-estimated from
    /// these matches then guides with `epipolar_band_px`).
    pub prior_band_px: f64,
    /// [`TrackingMode::Previous`]: RANSAC for the temporal `F` of one camera across a
    /// drive; Sampson threshold (default 2 px, as the stereo `F`: both relate two views of
    /// a rigid scene through the same detector).
    pub drive: RansacOptions,
    /// Patch refinement of later observations against the earlier patch of their track
    /// (module docs, step 5); `None` keeps the detector's pixels. Default: on, with the
    /// vision crate's defaults (15x15 window, gain and bias, reject beyond 2 px or below
    /// ZNCC 0.8).
    pub refine: Option<PatchRefineOptions>,
    /// Also align each new stereo pair's right corner against its left partner's patch
    /// (default true: it brings the right camera's observations to the left reference
    /// corner's point too; on rendered sessions observations over 1 px off the truth
    /// 10 % -> 1 %, verge/tilt RMS verge 0.019 / 0.014 -> 0.008 / 0.008 deg, z-score
    /// coverage 87 -> 93 %; on the real Middlebury motorcycle pair, against its
    /// ground-truth disparities, right corners over 1 px off in x 13 -> 7 %, y RMS
    /// 0.52 -> 0.31 px; docs/real-data.md. `false` keeps the right reference corners as
    /// detected).
    pub refine_stereo: bool,
    /// Correspondences nearest a track (in the earlier image) that its local affine map
    /// is fitted to (default 12).
    pub refine_neighbours: usize,
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
            mode: TrackingMode::Reference,
            prior_band_px: 4.0,
            drive: RansacOptions { threshold: 2.0, min_iterations: 500, ..RansacOptions::default() },
            refine: Some(PatchRefineOptions::default()),
            refine_stereo: true,
            refine_neighbours: 12,
        }
    }
}

impl FrontEndOptions {
    /// True if trackers with `self` and with `other` find the same [`StereoCorners`] in
    /// the same images without a stereo prior (module docs, steps 1-2): the same corner
    /// detection, descriptor matching, stereo RANSAC, epipolar band and fewest matches
    /// (the tracking mode, the temporal and drive matching and the refinement do not
    /// enter them).
    pub fn detects_like(&self, other: &Self) -> bool {
        self.features == other.features
            && self.matching == other.matching
            && self.stereo == other.stereo
            && self.epipolar_band_px == other.epipolar_band_px
            && self.min_matches == other.min_matches
    }

    /// Check every option.
    pub fn validate(&self) -> Result<(), AlignError> {
        let bad = |m: String| Err(AlignError::InvalidOption(m));
        self.features.validate().map_err(|e| AlignError::InvalidOption(format!("features: {e}")))?;
        self.matching.validate().map_err(|e| AlignError::InvalidOption(format!("matching: {e}")))?;
        self.stereo.validate().map_err(|e| AlignError::InvalidOption(format!("stereo RANSAC: {e}")))?;
        self.motion.validate().map_err(|e| AlignError::InvalidOption(format!("motion RANSAC: {e}")))?;
        self.drive.validate().map_err(|e| AlignError::InvalidOption(format!("drive RANSAC: {e}")))?;
        for (name, v) in [
            ("epipolar_band_px", self.epipolar_band_px),
            ("guided_radius_px", self.guided_radius_px),
            ("prior_band_px", self.prior_band_px),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return bad(format!("{name} must be positive, got {v}"));
            }
        }
        if let Some(r) = &self.refine {
            r.validate().map_err(|e| AlignError::InvalidOption(format!("refine: {e}")))?;
        }
        if self.refine_neighbours < 3 {
            return bad(format!("refine_neighbours must be at least 3, got {}", self.refine_neighbours));
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
    /// Observations moved by patch refinement (left, right).
    pub refined: [usize; 2],
    /// Observations dropped because their patch refinement failed (left, right).
    pub refine_rejected: [usize; 2],
    /// Median localisation sigma of this view's patch alignments, pixels per coordinate
    /// (left, right; module docs, "Localisation noise"); `None` where none was aligned.
    pub alignment_sigma_px: [Option<f64>; 2],
    /// Each observation's localisation noise (module docs, "Localisation noise"), by track
    /// id (left, right); observations of unknown noise are absent. Not serialised.
    #[serde(skip)]
    pub localisation: [std::collections::HashMap<u64, Localisation>; 2],
}

/// The localisation noise of one observation (module docs, "Localisation noise").
#[derive(Debug, Clone, PartialEq)]
pub struct Localisation {
    /// Variance relative to the track's defining observation, pixels^2 per coordinate.
    pub var: f64,
    /// The observation it was aligned against: view name and side (0 left, 1 right);
    /// `None` for the defining observation. Two observations of a track share the error
    /// of their deepest common ancestor: its variance is their covariance.
    pub parent: Option<(String, usize)>,
}

/// Where a corner's alignment reference is: the earlier view's corner (`true`) or this
/// view's (`false`), and its side.
type ParentSlot = (bool, usize);

/// The reference view's corners and their track ids.
#[derive(Debug, Clone)]
struct Reference {
    left: Features,
    right: Features,
    left_ids: Vec<Option<u64>>,
    right_ids: Vec<Option<u64>>,
    /// The stereo pairs `(left index, right index)`.
    stereo: Vec<(usize, usize)>,
    /// Each corner's localisation variance ([`ViewCorners::left_var`]).
    left_var: Vec<Option<f64>>,
    right_var: Vec<Option<f64>>,
    /// The view's name.
    name: String,
    /// The images (patch refinement).
    left_image: GrayImage,
    right_image: GrayImage,
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

/// Why [`epipolar_guided`] failed.
enum GuidedError {
    Geometry(headalign_geometry::GeometryError),
    Vision(headalign_vision::VisionError),
}

impl GuidedError {
    fn in_step(self, step: &str) -> AlignError {
        match self {
            GuidedError::Geometry(cause) => AlignError::Geometry { step: step.to_string(), cause },
            GuidedError::Vision(e) => AlignError::Images(format!("{step}: guided matching: {e}")),
        }
    }
}

/// `F` by RANSAC from the descriptor matches `m` of `a` to `b`, then guided matching in
/// a band of `band_px` around each epipolar line, kept within the RANSAC threshold
/// (Sampson pixels): the pairs `(a index, b index)`.
fn epipolar_guided(
    a: &Features,
    b: &Features,
    m: &[headalign_vision::Match],
    ransac_options: &RansacOptions,
    band_px: f64,
    matching: &MatchOptions,
) -> Result<Vec<(usize, usize)>, GuidedError> {
    let pairs: Vec<_> = m.iter().map(|x| (point(a, x.a), point(b, x.b))).collect();
    let f: FundamentalMatrix =
        estimate_fundamental(&pairs, ransac_options).map_err(GuidedError::Geometry)?.model;
    let guided = match_epipolar(a, b, &rows(&f.0), band_px, matching).map_err(GuidedError::Vision)?;
    Ok(guided
        .iter()
        .filter(|x| f.sampson_distance(&point(a, x.a), &point(b, x.b)) <= ransac_options.threshold)
        .map(|x| (x.a, x.b))
        .collect())
}

/// Pairs `(earlier index, current index)` of corners that carry the same track id.
fn shared(earlier: &[Option<u64>], current: &[Option<u64>]) -> Vec<(usize, usize)> {
    let by_id: std::collections::HashMap<u64, usize> =
        earlier.iter().enumerate().filter_map(|(i, id)| id.map(|t| (t, i))).collect();
    current.iter().enumerate().filter_map(|(j, id)| id.and_then(|t| by_id.get(&t)).map(|&i| (i, j))).collect()
}

/// The current corners' side of a refinement: their ids, localisation variances and
/// alignment parents, and where the earlier corners are.
struct Refined<'a> {
    ids: &'a mut [Option<u64>],
    var: &'a mut [Option<f64>],
    parent: &'a mut [Option<ParentSlot>],
    earlier: ParentSlot,
}

/// Count refined / rejected observations of `side`, drop the rejected ones' ids, and give
/// each refined corner its localisation variance: the earlier corner's (`earlier_var`)
/// plus its alignment's sigma squared (`sigmas`, one per pair; `None`: rejected).
fn tally(
    pairs: &[(usize, usize)],
    sigmas: &[Option<f64>],
    earlier_var: &[Option<f64>],
    current: Refined<'_>,
    report: &mut ViewTracking,
    side: usize,
) {
    for (&(i, j), sigma) in pairs.iter().zip(sigmas) {
        match sigma {
            Some(s) => {
                report.refined[side] += 1;
                current.var[j] =
                    earlier_var.get(i).copied().flatten().map(|v| v + s * s).filter(|v| v.is_finite());
                current.parent[j] = current.var[j].map(|_| current.earlier);
            }
            None => {
                current.ids[j] = None;
                report.refine_rejected[side] += 1;
            }
        }
    }
}

/// The median of the finite `values`, `None` if there are none.
fn median(mut values: Vec<f64>) -> Option<f64> {
    values.retain(|v| v.is_finite());
    if values.is_empty() {
        return None;
    }
    let mid = values.len() / 2;
    values.select_nth_unstable_by(mid, f64::total_cmp);
    Some(values[mid])
}

/// Least-squares affine map (its 2x2 part) of the correspondences `idx` of `pairs`
/// (`(earlier pixel, current pixel)`), refitted once without those off by more than 2 px;
/// `None` when the earlier points are too few or too clustered (the smaller eigenvalue of
/// their scatter below 4 px^2 per point) or the map is implausible (determinant outside
/// [1/4, 4]).
fn affine_of(pairs: &[(Point2<f64>, Point2<f64>)], idx: &[usize]) -> Option<[[f64; 2]; 2]> {
    // The 2x2 part and the two centroids.
    type Fit = ([[f64; 2]; 2], Point2<f64>, Point2<f64>);
    let fit = |use_: &[usize]| -> Option<Fit> {
        if use_.len() < 3 {
            return None;
        }
        let n = use_.len() as f64;
        let ms = use_.iter().fold(nalgebra::Vector2::zeros(), |a, &i| a + pairs[i].0.coords) / n;
        let md = use_.iter().fold(nalgebra::Vector2::zeros(), |a, &i| a + pairs[i].1.coords) / n;
        let (mut sss, mut sds) = (nalgebra::Matrix2::<f64>::zeros(), nalgebra::Matrix2::<f64>::zeros());
        for &i in use_ {
            let (ds, dd) = (pairs[i].0.coords - ms, pairs[i].1.coords - md);
            sss += ds * ds.transpose();
            sds += dd * ds.transpose();
        }
        let eig = sss.symmetric_eigenvalues();
        if eig.min() < 4.0 * n {
            return None;
        }
        let a = sds * sss.try_inverse()?;
        let det = a.determinant();
        if !(0.25..=4.0).contains(&det) {
            return None;
        }
        Some(([[a[(0, 0)], a[(0, 1)]], [a[(1, 0)], a[(1, 1)]]], Point2::from(ms), Point2::from(md)))
    };
    let (a, ms, md) = fit(idx)?;
    let kept: Vec<usize> = idx
        .iter()
        .copied()
        .filter(|&i| {
            let ds = pairs[i].0 - ms;
            let pred =
                md + nalgebra::Vector2::new(a[0][0] * ds.x + a[0][1] * ds.y, a[1][0] * ds.x + a[1][1] * ds.y);
            (pairs[i].1 - pred).norm() <= 2.0
        })
        .collect();
    if kept.len() == idx.len() { Some(a) } else { fit(&kept).map(|f| f.0) }
}

/// Refine each current corner `pairs[k].1` against the earlier corner `pairs[k].0`'s patch
/// (module docs, step 5), moving the corner in `current`; per pair, the alignment's
/// localisation sigma (pixels), or `None` if it failed.
fn refine_against(
    earlier_image: &GrayImage,
    earlier: &Features,
    current_image: &GrayImage,
    current: &mut Features,
    pairs: &[(usize, usize)],
    options: &PatchRefineOptions,
    neighbours: usize,
) -> Vec<Option<f64>> {
    let pts: Vec<(Point2<f64>, Point2<f64>)> =
        pairs.iter().map(|&(i, j)| (point(earlier, i), point(current, j))).collect();
    let all: Vec<usize> = (0..pts.len()).collect();
    let global = affine_of(&pts, &all).unwrap_or([[1.0, 0.0], [0.0, 1.0]]);
    // Earlier points bucketed in square cells; a track's neighbours are searched in the
    // 3x3 cells around it, then 5x5 if too few.
    const CELL_PX: f64 = 40.0;
    let cell = |p: &Point2<f64>| ((p.x / CELL_PX).floor() as i64, (p.y / CELL_PX).floor() as i64);
    let mut grid: std::collections::HashMap<(i64, i64), Vec<usize>> = std::collections::HashMap::new();
    for (m, (s, _)) in pts.iter().enumerate() {
        grid.entry(cell(s)).or_default().push(m);
    }
    let mut dist: Vec<(f64, usize)> = Vec::new();
    let moved: Vec<Option<([f64; 2], f64)>> = pts
        .iter()
        .map(|(s, d)| {
            let (cx, cy) = cell(s);
            for reach in [1i64, 2] {
                dist.clear();
                for gx in cx - reach..=cx + reach {
                    for gy in cy - reach..=cy + reach {
                        if let Some(list) = grid.get(&(gx, gy)) {
                            dist.extend(list.iter().map(|&m| ((pts[m].0 - s).norm_squared(), m)));
                        }
                    }
                }
                if dist.len() >= neighbours {
                    break;
                }
            }
            let k = neighbours.min(dist.len());
            if k < dist.len() {
                dist.select_nth_unstable_by(k, |a, b| a.0.total_cmp(&b.0));
            }
            let near: Vec<usize> = dist[..k].iter().map(|e| e.1).collect();
            let a = affine_of(&pts, &near).unwrap_or(global);
            refine_point_against_patch(earlier_image, [s.x, s.y], current_image, [d.x, d.y], a, options)
                .ok()
                .map(|r| (r.point, r.sigma_px))
        })
        .collect();
    for (&(_, j), m) in pairs.iter().zip(&moved) {
        if let Some((p, _)) = m {
            current.keypoints[j].x = p[0] as f32;
            current.keypoints[j].y = p[1] as f32;
        }
    }
    moved.iter().map(|m| m.map(|(_, s)| s)).collect()
}

impl Tracker {
    /// A tracker with no reference yet.
    pub fn new(options: FrontEndOptions) -> Result<Self, AlignError> {
        options.validate()?;
        Ok(Self { options, reference: None, next_id: 0 })
    }

    /// Stereo matches `(left index, right index)` of one view; with a predicted stereo
    /// `F` (`prior`), the first matches are those within `prior_band_px` of its epipolar
    /// lines instead of free ones.
    fn stereo(
        &self,
        left: &Features,
        right: &Features,
        view: &str,
        prior: Option<&Matrix3<f64>>,
    ) -> Result<Vec<(usize, usize)>, AlignError> {
        let o = &self.options;
        let m = match prior {
            Some(f) => match_epipolar(left, right, &rows(f), o.prior_band_px, &o.matching),
            None => match_descriptors(&left.descriptors, &right.descriptors, &o.matching),
        }
        .map_err(vision("stereo matching"))?;
        if m.len() < o.min_matches {
            return Err(AlignError::TooFewTracks {
                what: format!("matched between the left and right images of view '{view}'"),
                needed: o.min_matches,
                got: m.len(),
            });
        }
        epipolar_guided(left, right, &m, &o.stereo, o.epipolar_band_px, &o.matching)
            .map_err(|e| e.in_step(&format!("stereo F of view '{view}'")))
    }

    /// [`TrackingMode::Previous`]: the fundamental matrix of one camera across a drive
    /// (`x_current^T F x_previous = 0`) from free descriptor matches by RANSAC, with its
    /// inlier count; `None` when the views cannot be linked.
    fn across_drive(&self, previous: &Features, current: &Features) -> Option<(FundamentalMatrix, usize)> {
        let o = &self.options;
        let m = match_descriptors(&previous.descriptors, &current.descriptors, &o.matching).ok()?;
        if m.len() < o.min_matches {
            return None;
        }
        let pairs: Vec<_> = m.iter().map(|x| (point(previous, x.a), point(current, x.b))).collect();
        let rep = estimate_fundamental(&pairs, &o.drive).ok()?;
        (rep.inliers.len() >= o.min_matches).then_some((rep.model, rep.inliers.len()))
    }

    /// [`TrackingMode::Previous`]: stereo pairs of the previous view matched to stereo
    /// pairs of the current one, as units (`(previous pair, current pair)` indices). A
    /// candidate must satisfy both cameras' drive `F` (Sampson distance within the drive
    /// RANSAC threshold in the left and in the right image); its cost is the sum of the
    /// two Hamming distances; the best candidate is kept if it is mutual, each distance is
    /// at most `matching.max_distance` and the cost beats the second best by the ratio.
    fn link_pairs(
        &self,
        previous: &Reference,
        left: &Features,
        right: &Features,
        stereo: &[(usize, usize)],
        f_left: &FundamentalMatrix,
        f_right: &FundamentalMatrix,
    ) -> Vec<(usize, usize)> {
        let o = &self.options;
        let thr = o.drive.threshold;
        let max_d = o.matching.max_distance;
        let n_cur = stereo.len();
        // Best and second-best cost per previous pair, and best per current pair.
        let mut best_prev: Vec<(u32, u32, usize)> =
            vec![(u32::MAX, u32::MAX, usize::MAX); previous.stereo.len()];
        let mut best_cur: Vec<(u32, usize)> = vec![(u32::MAX, usize::MAX); n_cur];
        for (i, &(pa, pb)) in previous.stereo.iter().enumerate() {
            let (pl, pr) = (point(&previous.left, pa), point(&previous.right, pb));
            for (j, &(ca, cb)) in stereo.iter().enumerate() {
                let dl = previous.left.descriptors[pa].hamming(&left.descriptors[ca]);
                let dr = previous.right.descriptors[pb].hamming(&right.descriptors[cb]);
                if dl > max_d || dr > max_d {
                    continue;
                }
                if f_left.sampson_distance(&pl, &point(left, ca)) > thr
                    || f_right.sampson_distance(&pr, &point(right, cb)) > thr
                {
                    continue;
                }
                let cost = dl + dr;
                let b = &mut best_prev[i];
                if cost < b.0 {
                    *b = (cost, b.0, j);
                } else if cost < b.1 {
                    b.1 = cost;
                }
                if cost < best_cur[j].0 {
                    best_cur[j] = (cost, i);
                }
            }
        }
        best_prev
            .iter()
            .enumerate()
            .filter(|&(i, &(cost, second, j))| {
                j < n_cur
                    && best_cur[j].1 == i
                    && (second == u32::MAX || (cost as f32) < o.matching.ratio * second as f32)
            })
            .map(|(i, &(_, _, j))| (i, j))
            .collect()
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
        self.track_with_prior(images, view, None)
    }

    /// [`Self::track`] with the stereo `F` predicted for this view (`x_right^T F x_left =
    /// 0`, pixels), e.g. by a calibrated rig ([`crate::robot::stereo_fundamental`]):
    /// stereo matching starts from matches near its epipolar lines.
    pub fn track_with_prior(
        &mut self,
        images: &StereoImages,
        view: &str,
        stereo_prior: Option<&Matrix3<f64>>,
    ) -> Result<(StereoCapture, ViewTracking), AlignError> {
        crate::timing::time(crate::timing::Stage::FrontEnd, || {
            let corners = self.detect(images, view, stereo_prior)?;
            self.track_detected(images, view, corners)
        })
    }

    /// [`Self::track`] that also hands back the view's [`StereoCorners`] (as detected and
    /// stereo-matched, before track ids and patch refinement), so that another tracker
    /// whose options detect alike ([`FrontEndOptions::detects_like`]) can track the same
    /// images from them ([`Self::track_corners`]) instead of detecting again.
    pub fn track_keeping_corners(
        &mut self,
        images: &StereoImages,
        view: &str,
    ) -> Result<(StereoCapture, ViewTracking, StereoCorners), AlignError> {
        crate::timing::time(crate::timing::Stage::FrontEnd, || {
            let corners = self.detect(images, view, None)?;
            let (capture, report) = self.track_detected(images, view, corners.clone())?;
            Ok((capture, report, corners))
        })
    }

    /// [`Self::track`] from the view's corners and stereo matches as another tracker
    /// detected them in the same images ([`Self::track_keeping_corners`]; its options must
    /// detect like this tracker's, [`FrontEndOptions::detects_like`]): the same result as
    /// [`Self::track`], without detecting again.
    pub fn track_corners(
        &mut self,
        images: &StereoImages,
        view: &str,
        corners: StereoCorners,
    ) -> Result<(StereoCapture, ViewTracking), AlignError> {
        crate::timing::time(crate::timing::Stage::FrontEnd, || self.track_detected(images, view, corners))
    }

    /// Steps 1-2 of the module docs for one view: both images' corners (in parallel) and
    /// their stereo matches.
    fn detect(
        &self,
        images: &StereoImages,
        view: &str,
        stereo_prior: Option<&Matrix3<f64>>,
    ) -> Result<StereoCorners, AlignError> {
        let o = &self.options;
        let (left, right) = rayon::join(
            || detect_and_describe(&images.left, &o.features),
            || detect_and_describe(&images.right, &o.features),
        );
        let left = left.map_err(vision("left image"))?;
        let right = right.map_err(vision("right image"))?;
        let stereo = self.stereo(&left, &right, view, stereo_prior)?;
        Ok(StereoCorners { left, right, stereo })
    }

    /// Steps 3-5 of the module docs for one view from its [`StereoCorners`]: track ids,
    /// patch refinement, the capture and the report; the first view (and every view in
    /// [`TrackingMode::Previous`]) becomes the reference.
    fn track_detected(
        &mut self,
        images: &StereoImages,
        view: &str,
        detected: StereoCorners,
    ) -> Result<(StereoCapture, ViewTracking), AlignError> {
        let StereoCorners { left, right, stereo } = detected;
        let mut report = ViewTracking {
            corners: [left.len(), right.len()],
            stereo_matches: stereo.len(),
            ..ViewTracking::default()
        };
        let mut corners = ViewCorners::new(left, right, stereo);
        // Track ids (module docs, step 4): fresh for the first view, else inherited.
        self.next_id = match &self.reference {
            None => first_view_ids(self.next_id, &mut corners),
            Some(r) if self.options.mode == TrackingMode::Previous => {
                self.ids_across_drive(r, &mut corners, &mut report)
            }
            Some(r) => self.ids_from_reference(r, &mut corners, view, &mut report)?,
        };
        if let Some(ro) = &self.options.refine {
            self.refine_view(ro, images, &mut corners, &mut report);
        }
        let capture = corners.capture(images);
        report.observations = [capture.left.len(), capture.right.len()];
        let earlier = self.reference.as_ref().map(|r| r.name.as_str());
        report.localisation = corners.localisation(view, earlier);
        if self.reference.is_none() || self.options.mode == TrackingMode::Previous {
            let ViewCorners { left, right, stereo, left_ids, right_ids, left_var, right_var, .. } = corners;
            self.reference = Some(Reference {
                left,
                right,
                left_ids,
                right_ids,
                stereo,
                left_var,
                right_var,
                name: view.to_string(),
                left_image: images.left.clone(),
                right_image: images.right.clone(),
            });
        }
        Ok((capture, report))
    }

    /// [`TrackingMode::Previous`] (module docs): the track ids of a view after a drive.
    /// Across a drive, stereo pairs are matched as units under both cameras' drive F (a
    /// wrong match of one camera slides along its epipolar line, which its own F cannot
    /// catch; the other camera's F and descriptor rarely agree with it). Unlinked pairs
    /// start fresh tracks; unpaired corners carry none. Returns the next free id.
    fn ids_across_drive(&self, r: &Reference, view: &mut ViewCorners, report: &mut ViewTracking) -> u64 {
        let (left, right, stereo) = (&view.left, &view.right, &view.stereo);
        let (fl, fr) = (self.across_drive(&r.left, left), self.across_drive(&r.right, right));
        let links = match (&fl, &fr) {
            (Some((fl, nl)), Some((fr, nr))) => {
                report.temporal_matches = [*nl, *nr];
                self.link_pairs(r, left, right, stereo, fl, fr)
            }
            _ => Vec::new(),
        };
        let mut ids: Vec<Option<u64>> = vec![None; stereo.len()];
        for (i, j) in links {
            ids[j] = r.left_ids[r.stereo[i].0];
        }
        let mut fresh = self.next_id;
        for (k, &(a, b)) in stereo.iter().enumerate() {
            let id = ids[k].unwrap_or_else(|| {
                view.left_var[a] = Some(0.0);
                fresh += 1;
                fresh - 1
            });
            view.left_ids[a] = Some(id);
            view.right_ids[b] = Some(id);
        }
        fresh
    }

    /// [`TrackingMode::Reference`] (module docs, steps 3-4): each camera's corners matched
    /// to the same camera's reference image inherit its ids; a stereo pair shares an id
    /// or gets a fresh one, and a pair whose two ids disagree goes. Returns the next free
    /// id.
    fn ids_from_reference(
        &self,
        r: &Reference,
        view: &mut ViewCorners,
        name: &str,
        report: &mut ViewTracking,
    ) -> Result<u64, AlignError> {
        let tl = self.temporal(
            &r.left,
            &view.left,
            &format!("between the left images of the reference and '{name}'"),
        )?;
        let tr = self.temporal(
            &r.right,
            &view.right,
            &format!("between the right images of the reference and '{name}'"),
        )?;
        report.temporal_matches = [tl.len(), tr.len()];
        let (left_ids, right_ids) = (&mut view.left_ids, &mut view.right_ids);
        for &(a, b) in &tl {
            left_ids[b] = r.left_ids[a];
        }
        for &(a, b) in &tr {
            right_ids[b] = r.right_ids[a];
        }
        let mut fresh = self.next_id;
        // Stereo pairs: share an id, or get a fresh one; disagreeing pairs go.
        for &(a, b) in &view.stereo {
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
                    view.left_var[a] = Some(0.0);
                    fresh += 1;
                }
                _ => {}
            }
        }
        Ok(fresh)
    }

    /// Patch refinement of a tracked view (module docs, step 5): with a reference, each
    /// camera's observations against the same camera's earlier image, by shared id (and,
    /// with `refine_stereo` in [`TrackingMode::Previous`], each unlinked pair's right
    /// corner against its left partner); for the first view, with `refine_stereo`, each
    /// right corner against its left partner. A failed alignment drops the observation's
    /// id; the report counts both.
    fn refine_view(
        &self,
        ro: &PatchRefineOptions,
        images: &StereoImages,
        view: &mut ViewCorners,
        report: &mut ViewTracking,
    ) {
        let o = &self.options;
        let k = o.refine_neighbours;
        let ViewCorners {
            left,
            right,
            stereo,
            left_ids,
            right_ids,
            left_var,
            right_var,
            left_parent,
            right_parent,
        } = view;
        let mut sigmas: [Vec<f64>; 2] = [Vec::new(), Vec::new()];
        match &self.reference {
            Some(r) => {
                // Each camera against the same camera's earlier image, by shared id.
                let [pl, pr] =
                    [(&r.left_ids, &*left_ids), (&r.right_ids, &*right_ids)].map(|(a, b)| shared(a, b));
                let (okl, okr) = (
                    refine_against(&r.left_image, &r.left, &images.left, left, &pl, ro, k),
                    refine_against(&r.right_image, &r.right, &images.right, right, &pr, ro, k),
                );
                for (side, (pairs, ok, earlier, current)) in [
                    (
                        &pl,
                        okl,
                        &r.left_var,
                        Refined {
                            ids: &mut *left_ids,
                            var: &mut *left_var,
                            parent: &mut *left_parent,
                            earlier: (true, 0),
                        },
                    ),
                    (
                        &pr,
                        okr,
                        &r.right_var,
                        Refined {
                            ids: &mut *right_ids,
                            var: &mut *right_var,
                            parent: &mut *right_parent,
                            earlier: (true, 1),
                        },
                    ),
                ]
                .into_iter()
                .enumerate()
                {
                    tally(pairs, &ok, earlier, current, report, side);
                    sigmas[side].extend(ok.iter().flatten());
                }
                if o.refine_stereo && o.mode == TrackingMode::Previous {
                    // Unlinked pairs start fresh tracks here: right against left.
                    let linked: std::collections::HashSet<usize> = pr.iter().map(|p| p.1).collect();
                    let fresh: Vec<(usize, usize)> = stereo
                        .iter()
                        .copied()
                        .filter(|&(a, b)| {
                            !linked.contains(&b) && left_ids[a].is_some() && left_ids[a] == right_ids[b]
                        })
                        .collect();
                    let ok = refine_against(&images.left, left, &images.right, right, &fresh, ro, k);
                    let current =
                        Refined { ids: right_ids, var: right_var, parent: right_parent, earlier: (false, 0) };
                    tally(&fresh, &ok, left_var, current, report, 1);
                    sigmas[1].extend(ok.iter().flatten());
                }
            }
            None if o.refine_stereo => {
                let pairs: Vec<(usize, usize)> = stereo
                    .iter()
                    .copied()
                    .filter(|&(a, b)| left_ids[a].is_some() && left_ids[a] == right_ids[b])
                    .collect();
                let ok = refine_against(&images.left, left, &images.right, right, &pairs, ro, k);
                let current =
                    Refined { ids: right_ids, var: right_var, parent: right_parent, earlier: (false, 0) };
                tally(&pairs, &ok, left_var, current, report, 1);
                sigmas[1].extend(ok.iter().flatten());
            }
            None => {}
        }
        report.alignment_sigma_px = sigmas.map(median);
    }
}

/// One view's corners in both images and their stereo matches `(left index, right index)`,
/// as detected (module docs, steps 1-2), before track ids and patch refinement
/// ([`Tracker::track_keeping_corners`], [`Tracker::track_corners`]).
#[derive(Debug, Clone)]
pub struct StereoCorners {
    left: Features,
    right: Features,
    stereo: Vec<(usize, usize)>,
}

/// One view's corners while they are tracked: both images' features, the stereo pairs
/// `(left index, right index)` and each corner's track id.
struct ViewCorners {
    left: Features,
    right: Features,
    stereo: Vec<(usize, usize)>,
    left_ids: Vec<Option<u64>>,
    right_ids: Vec<Option<u64>>,
    /// Each corner's localisation variance relative to its track's defining observation,
    /// pixels^2 per coordinate (module docs, "Localisation noise"): 0 for the corner that
    /// starts a track (a fresh pair's left corner), the earlier corner's plus the
    /// alignment's sigma squared for a refined one, `None` when unknown (not aligned).
    left_var: Vec<Option<f64>>,
    right_var: Vec<Option<f64>>,
    /// Each aligned corner's alignment reference (`None`: not aligned).
    left_parent: Vec<Option<ParentSlot>>,
    right_parent: Vec<Option<ParentSlot>>,
}

impl ViewCorners {
    /// Both images' features and their stereo pairs, no corner tracked or aligned yet.
    fn new(left: Features, right: Features, stereo: Vec<(usize, usize)>) -> Self {
        let (nl, nr) = (left.len(), right.len());
        Self {
            left,
            right,
            stereo,
            left_ids: vec![None; nl],
            right_ids: vec![None; nr],
            left_var: vec![None; nl],
            right_var: vec![None; nr],
            left_parent: vec![None; nl],
            right_parent: vec![None; nr],
        }
    }

    /// [`ViewTracking::localisation`]: the known noise of the corners with a track, in the
    /// view `name` tracked against the view `earlier`.
    fn localisation(
        &self,
        name: &str,
        earlier: Option<&str>,
    ) -> [std::collections::HashMap<u64, Localisation>; 2] {
        let of = |ids: &[Option<u64>], var: &[Option<f64>], parent: &[Option<ParentSlot>]| {
            ids.iter()
                .zip(var)
                .zip(parent)
                .filter_map(|((id, v), p)| {
                    let parent = match p {
                        None => None,
                        Some((true, side)) => Some((earlier?.to_string(), *side)),
                        Some((false, side)) => Some((name.to_string(), *side)),
                    };
                    id.zip(*v).map(|(t, var)| (t, Localisation { var, parent }))
                })
                .collect()
        };
        [
            of(&self.left_ids, &self.left_var, &self.left_parent),
            of(&self.right_ids, &self.right_var, &self.right_parent),
        ]
    }

    /// The tracked observations of the view: every corner with a track id.
    fn capture(&self, images: &StereoImages) -> StereoCapture {
        let observe = |f: &Features, ids: &[Option<u64>]| -> Vec<TrackObservation> {
            ids.iter()
                .enumerate()
                .filter_map(|(i, id)| id.map(|track| TrackObservation { track, pixel: point(f, i) }))
                .collect()
        };
        StereoCapture {
            encoders: images.encoders,
            image_size: images.image_size(),
            left: observe(&self.left, &self.left_ids),
            right: observe(&self.right, &self.right_ids),
        }
    }
}

/// The first view's track ids (module docs, step 4): each stereo pair a fresh id, from
/// `next_id` on. Returns the next free id.
fn first_view_ids(mut next_id: u64, view: &mut ViewCorners) -> u64 {
    for &(a, b) in &view.stereo {
        let id = next_id;
        next_id += 1;
        view.left_var[a] = Some(0.0);
        view.left_ids[a] = Some(id);
        view.right_ids[b] = Some(id);
    }
    next_id
}

/// A predicted stereo fundamental matrix (`x_right^T F x_left = 0`) at given readings.
pub type StereoPrior<'a> = Box<dyn Fn(&Encoders) -> Option<Matrix3<f64>> + 'a>;

/// An [`ImagingHead`] seen as a [`StereoHead`]: every capture takes images, keeps them,
/// and hands on the tracked observations. The first capture is the tracking reference.
pub struct TrackingHead<'a, H: ImagingHead> {
    head: &'a mut H,
    tracker: Tracker,
    stereo_prior: Option<StereoPrior<'a>>,
    /// Every captured image pair, in order (nothing captured is lost).
    pub images: Vec<StereoImages>,
    /// The front end's report per capture.
    pub tracking: Vec<ViewTracking>,
}

impl<'a, H: ImagingHead> TrackingHead<'a, H> {
    /// Wrap a head.
    pub fn new(head: &'a mut H, options: FrontEndOptions) -> Result<Self, AlignError> {
        Ok(Self {
            head,
            tracker: Tracker::new(options)?,
            stereo_prior: None,
            images: Vec::new(),
            tracking: Vec::new(),
        })
    }

    /// Guide stereo matching by the stereo `F` that `prior` predicts from each capture's
    /// encoder readings (`None`: match freely), as a calibrated rig does
    /// ([`crate::robot::stereo_fundamental`]). Free matching fails where the two views of
    /// a near scene differ much (parallel cameras, 1 m away: disparities near 200 px).
    pub fn with_stereo_prior(mut self, prior: StereoPrior<'a>) -> Self {
        self.stereo_prior = Some(prior);
        self
    }

    /// The wrapped head.
    pub fn inner(&mut self) -> &mut H {
        self.head
    }
}

/// A vehicle under the front end drives as the vehicle (track with
/// [`TrackingMode::Previous`] so the captures around a drive share track ids).
impl<H: ImagingHead + Vehicle> Vehicle for TrackingHead<'_, H> {
    fn drive(&mut self, distance_m: f64) -> Result<(), PlatformError> {
        self.head.drive(distance_m)
    }

    fn steer_to(&mut self, encoder_deg: f64) -> Result<(), PlatformError> {
        self.head.steer_to(encoder_deg)
    }

    fn read_steering(&mut self) -> Result<f64, PlatformError> {
        self.head.read_steering()
    }

    fn last_odometry(&self) -> Option<headalign_platform::Odometry> {
        self.head.last_odometry()
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
        let name = tracked_view_name(self.images.len() - 1);
        let prior = self.stereo_prior.as_ref().and_then(|p| p(&images.encoders));
        let (capture, report) = self
            .tracker
            .track_with_prior(images, &name, prior.as_ref())
            .map_err(|e| PlatformError::FrontEnd(e.to_string()))?;
        self.tracking.push(report);
        Ok(capture)
    }
}

/// The name a [`TrackingHead`] gives its `index`-th capture (0-based) in the front end's
/// reports ([`ViewTracking::localisation`]'s parents): `view N`, `N = index + 1`.
pub fn tracked_view_name(index: usize) -> String {
    format!("view {}", index + 1)
}
