//! Self-calibration of a stereo rig from rigid motions of the whole rig (head rotations,
//! robot drives, a hand-held rig): both cameras' intrinsics, the rig's relative pose and
//! every view's motion, with covariances (issue 6 part 2; paper section 3.1; Hartley &
//! Zisserman 2nd ed., sections 10.4, 19.5-19.6).
//!
//! Input: tracked point observations of stereo views (the first is the reference), the
//! rig fixed between them (views whose vergence readings differ from the first view's are
//! left out: their rig changed). Chain, each step a pure function of the previous:
//! 1. a scene-depth check per view: if one plane homography explains nearly all stereo
//!    matches of a view (default 90 % within 2 px), its projective reconstruction is a
//!    plane and no 3D homography relates it to another view: the view is left out, and if
//!    no moved view remains (a chessboard) the error names the degeneracy;
//! 2. one fundamental matrix from the stereo matches of all views (DEGENSAC, Sampson
//!    refinement), the quasi-Euclidean projective frame and optimal triangulation
//!    (as [`crate::estimate`]);
//! 3. per moved view, the 3D homography from the reference: 3-point rigid RANSAC in the
//!    quasi-Euclidean frame (robust to the large motions of a hand-held rig; the 5-point
//!    DLT RANSAC as fallback), polished on symmetric transfer error, guided re-selection
//!    until the inlier set is stable;
//! 4. the linear self-calibration: the plane at infinity fixed by all motions whose
//!    rotation exceeds `min_rotation_deg` (two rotations about different axes, or ONE
//!    general screw motion, a rotation with a translation along its axis), the infinite
//!    homographies, and `K` from the image of the absolute conic with the user's linear
//!    constraints (zero skew, square pixels, principal point at the image centre); the
//!    right camera by decomposition, the motions `D_i`;
//! 5. the maximum-likelihood rig bundle adjustment with free 6-dof view poses (the
//!    constraints held exactly), robust loss, re-selection, covariance, from each of two
//!    starts (the linear chain, and `K = K0` with the rigid motions of step 3), as in
//!    [`crate::estimate`] (shared code);
//! 6. per start, an adjustment over every point seen at least twice (also the points
//!    seen by one stereo view only), robust first, then least squares on the re-selected
//!    observations (`every_point_pass`); the start with the lower truncated cost over
//!    all observations is kept.
//!
//! Steps 3 and 5 are seeded (RANSAC samples): when no 3D homography fits or the
//! adjustment fails from every start, steps 1-6 run again with the next estimation seeds
//! ([`CalibrateOptions::restarts`]); the report names the seed used, and the final error
//! the seeds tried and the tracks the views share.
//!
//! Degrees of freedom: per camera 5 intrinsics minus the constraints; rig 5 (the baseline
//! length is the scale gauge: the scene is in baselines); 6 per moved view; 3 per point.
//! Units: pixels for thresholds and residuals, degrees in reports, baselines for lengths.
//!
//! Lens distortion: a known model ([`LensModel`], e.g. read from an OpenCV YAML file with
//! [`read_opencv_lenses`]) is removed from the observations first ([`undistort_views`]);
//! everything after is pinhole. Alternatively `estimate_distortion` adds the radial
//! coefficients `k1, k2` of each camera to the final adjustment (step 5;
//! [`BundleOptions::estimate_distortion`](headalign_geometry::bundle::BundleOptions)):
//! steps 1-4 then see distorted pixels (a pinhole approximation, fine for the moderate
//! distortion of the start), and the result is in `bundle.state.{left,right}_distortion`
//! with sigmas `left.k1` ... in the covariance. With small rotations `k1` correlates with
//! the focal length: without it a barrel lens biases `f` (see README).
//!
//! Pitfalls: a pure rotation, or a planar motion (translation perpendicular to the axis),
//! fixes a pencil of planes: with one such motion the plane at infinity is undetermined
//! (an error naming it). One rotation also leaves the conic a pencil: it needs at least
//! zero skew. A planar scene is degenerate for projective reconstruction (step 1). The
//! conditioning of one general motion depends on its translation along the axis: report
//! `plane_conditioning` and trust the sigmas.

use std::collections::BTreeMap;

use headalign_geometry::GeometryError;
use headalign_geometry::bundle::{
    BundleObservation, BundleOptions, BundleResult, Motions, RigState, RobustLoss, Side, bundle_adjust,
    residual_pixels,
};
use headalign_geometry::camera::{Intrinsics, ProjectiveCamera, dehomogenise3};
use headalign_geometry::distortion::Distortion;
use headalign_geometry::frame::{StereoFrame, quasi_euclidean_frame};
use headalign_geometry::fundamental::{FundamentalMatrix, estimate_fundamental};
use headalign_geometry::homography2d::Homography2Estimator;
use headalign_geometry::homography3d::{
    Homography3, Homography3Estimator, Quadruplet, TransferModel, symmetric_transfer_error,
};
use headalign_geometry::ransac::{RansacOptions, RansacReport, ransac};
use headalign_geometry::registration::RigidFrameEstimator;
use headalign_geometry::selfcal::{
    IntrinsicConstraints, calibrate_from_infinite_homographies, decompose_camera, euclidean_upgrade,
    infinite_homography, motion_from_homography, plane_at_infinity_general,
};
use headalign_geometry::so3::screw_from_isometry;
use headalign_geometry::triangulation::{triangulate_linear, triangulate_optimal};
use headalign_platform::{Joint, StereoCapture, TrackObservation};
use nalgebra::{Isometry3, Point2, Point3, UnitQuaternion};
use serde::Serialize;

use crate::error::{AlignError, StepContext};
use crate::estimate::{
    DEPTH_RATIO, EstimationOptions, FINAL_ITERATIONS, MOVED_DEG, PolishedHomography, Reconstruction,
    StereoMatch, adjust_from_starts, points_in_ref, polish, rms, stereo_matches,
};
use crate::observations::View;

/// Options of [`calibrate_rig`].
#[derive(Debug, Clone)]
pub struct CalibrateOptions {
    /// F, 3D homography RANSAC, bundle adjustment, re-selection, minimum tracks and seed
    /// (defaults of [`EstimationOptions`]; the bundle's intrinsic constraints are set from
    /// the three flags below, and its angle prior is unused: the poses are free).
    pub estimation: EstimationOptions,
    /// Hold both skews at zero (default false).
    pub zero_skew: bool,
    /// `fx = fy` in both cameras (default false).
    pub square_pixels: bool,
    /// Hold both principal points at the image centre (default false).
    pub fix_principal_point: bool,
    /// Estimate each camera's radial distortion `k1, k2` in the adjustment (default false:
    /// pinhole, or a known lens removed beforehand with [`undistort_views`]).
    pub estimate_distortion: bool,
    /// Motions rotating less than this (degrees) do not enter the linear
    /// self-calibration (default 0.5: below it `H - I` is mostly noise); they still enter
    /// the adjustment.
    pub min_rotation_deg: f64,
    /// Transfer threshold of the scene-depth check, pixels (default 2).
    pub planar_threshold_px: f64,
    /// Fraction of a view's stereo matches on one plane above which the view counts as
    /// planar (default 0.98: the simulated rooms put up to 92 % of a view's matches on
    /// one wall and still calibrate).
    pub planar_fraction: f64,
    /// Relative sigma of either focal length, percent, above which the report carries a
    /// warning that the motions and scene determine the calibration poorly (default 0.5:
    /// on the one-general-motion session at 0.5 px the well-conditioned seeds give
    /// 0.14-0.44 %; near-critical motions gave 0.9-1.0 % with errors of 2.5 %: there the
    /// linearised sigma is itself optimistic).
    pub warn_focal_sigma_pct: f64,
    /// With one motion, the mean fraction of the views' stereo matches on one plane above
    /// which the report warns that the scene is close to degenerate (default 0.85: the
    /// one-motion failures seen were at 0.88-0.92; the well-conditioned seeds mostly
    /// below 0.8).
    pub warn_plane_fraction: f64,
    /// When the adjustment fails from every start (or no 3D homography fits), the chain
    /// runs again from step 2 with the next estimation seeds (`seed + 1`, ...), at most
    /// this many more times (default 3). The robust stages are seeded: with one motion and
    /// few common tracks (rendered seed 19: 82 points seen in both views) the 3-point
    /// RANSAC's rigid motion, the rigid start's only input, can be poor enough that its
    /// screening adjustment diverges while the linear start's conic is not positive
    /// definite; other seeds converge to the same minimum (estimation seeds 1 and 2:
    /// f 701.2 for a true 700).
    pub restarts: usize,
}

impl Default for CalibrateOptions {
    fn default() -> Self {
        Self {
            estimation: EstimationOptions::default(),
            zero_skew: false,
            square_pixels: false,
            fix_principal_point: false,
            estimate_distortion: false,
            min_rotation_deg: 0.5,
            planar_threshold_px: 2.0,
            planar_fraction: 0.98,
            warn_focal_sigma_pct: 0.5,
            warn_plane_fraction: 0.85,
            restarts: 3,
        }
    }
}

impl CalibrateOptions {
    /// Check every option.
    pub fn validate(&self) -> Result<(), AlignError> {
        self.estimation.validate()?;
        if !(self.min_rotation_deg.is_finite() && self.min_rotation_deg > 0.0) {
            return Err(AlignError::InvalidOption("min_rotation_deg must be positive".into()));
        }
        if !(self.planar_threshold_px.is_finite() && self.planar_threshold_px > 0.0) {
            return Err(AlignError::InvalidOption("planar_threshold_px must be positive".into()));
        }
        if !(self.planar_fraction > 0.0 && self.planar_fraction <= 1.0) {
            return Err(AlignError::InvalidOption("planar_fraction must be in (0, 1]".into()));
        }
        if !(self.warn_plane_fraction > 0.0 && self.warn_plane_fraction <= 1.0) {
            return Err(AlignError::InvalidOption("warn_plane_fraction must be in (0, 1]".into()));
        }
        if !(self.warn_focal_sigma_pct.is_finite() && self.warn_focal_sigma_pct > 0.0) {
            return Err(AlignError::InvalidOption("warn_focal_sigma_pct must be positive".into()));
        }
        Ok(())
    }

    fn constraints(&self) -> IntrinsicConstraints {
        IntrinsicConstraints {
            zero_skew: self.zero_skew,
            square_pixels: self.square_pixels,
            principal_point_at_origin: self.fix_principal_point,
        }
    }
}

/// A camera's known lens: the intrinsics its distortion coefficients belong to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensModel {
    /// Intrinsics the coefficients were estimated with (they normalise the pixels).
    pub k: Intrinsics,
    /// The distortion.
    pub distortion: Distortion,
}

/// The views with every observation undistorted (`lenses[0]` left, `[1]` right); an
/// observation that cannot be undistorted (outside the lens model's valid range) is
/// dropped.
pub fn undistort_views(views: &[View], lenses: &[LensModel; 2]) -> Vec<View> {
    let fix = |list: &[TrackObservation], lens: &LensModel| -> Vec<TrackObservation> {
        list.iter()
            .filter_map(|o| {
                let pixel = lens.distortion.undistort_pixel(&lens.k, &o.pixel).ok()?;
                (pixel.x.is_finite() && pixel.y.is_finite())
                    .then_some(TrackObservation { track: o.track, pixel })
            })
            .collect()
    };
    views
        .iter()
        .map(|v| View {
            name: v.name.clone(),
            capture: StereoCapture {
                left: fix(&v.capture.left, &lenses[0]),
                right: fix(&v.capture.right, &lenses[1]),
                ..v.capture.clone()
            },
        })
        .collect()
}

/// Parse the numbers of an OpenCV FileStorage matrix `name: !!opencv-matrix ... data: [...]`
/// (or an inline `name: [ ... ]`).
fn opencv_matrix(text: &str, name: &str) -> Option<Vec<f64>> {
    let key = format!("{name}:");
    let start = text.lines().scan(0usize, |pos, line| {
        let here = *pos;
        *pos += line.len() + 1;
        Some((here, line))
    });
    let (offset, _) = start.into_iter().find(|(_, line)| line.trim_start().starts_with(&key))?;
    let rest = &text[offset..];
    let open = rest.find('[')?;
    // The data must belong to this key: no other top-level key before the bracket.
    let before = &rest[key.len()..open];
    if before.lines().skip(1).any(|l| !l.starts_with(' ') && !l.trim().is_empty()) {
        return None;
    }
    let close = rest[open..].find(']')? + open;
    rest[open + 1..close].split(',').map(|v| v.trim().parse::<f64>().ok()).collect()
}

/// Both cameras' lens models from an OpenCV FileStorage YAML: `M1 D1 M2 D2` (OpenCV's
/// stereo sample and headalign's `opencv_stereo.yaml`), or a single camera's
/// `camera_matrix` and `distortion_coefficients` (used for both). `origin` names the file
/// in messages.
pub fn read_opencv_lenses(text: &str, origin: &str) -> Result<[LensModel; 2], AlignError> {
    let bad = |m: String| AlignError::InvalidOption(format!("{origin}: {m}"));
    let lens = |m: &str, d: &str| -> Result<Option<LensModel>, AlignError> {
        let (Some(mv), Some(dv)) = (opencv_matrix(text, m), opencv_matrix(text, d)) else {
            return Ok(None);
        };
        if mv.len() != 9 {
            return Err(bad(format!("{m} has {} numbers, a 3x3 matrix has 9", mv.len())));
        }
        let k = Intrinsics::from_matrix(&nalgebra::Matrix3::from_row_slice(&mv))
            .map_err(|e| bad(format!("{m}: {e}")))?;
        let distortion = Distortion::from_opencv(&dv).map_err(|e| bad(format!("{d}: {e}")))?;
        Ok(Some(LensModel { k, distortion }))
    };
    if let (Some(l), Some(r)) = (lens("M1", "D1")?, lens("M2", "D2")?) {
        return Ok([l, r]);
    }
    if let Some(one) = lens("camera_matrix", "distortion_coefficients")? {
        return Ok([one, one]);
    }
    Err(bad("no lens found: expected M1, D1, M2, D2 or camera_matrix and distortion_coefficients (OpenCV FileStorage matrices)".into()))
}

/// The scene-depth check of one view.
#[derive(Debug, Clone, Serialize)]
pub struct PlaneCheck {
    /// The view.
    pub view: String,
    /// Its stereo matches.
    pub stereo_matches: usize,
    /// How many of them one plane homography explains.
    pub on_one_plane: usize,
    /// True if that is at least `planar_fraction` of them.
    pub planar: bool,
}

/// Step 1 of the module docs for every view.
pub fn check_planarity(views: &[View], options: &CalibrateOptions) -> Vec<PlaneCheck> {
    views
        .iter()
        .map(|v| {
            let pairs: Vec<(Point2<f64>, Point2<f64>)> =
                stereo_matches(&v.capture).iter().map(|m| (m.1, m.2)).collect();
            let ransac_options = RansacOptions {
                threshold: options.planar_threshold_px,
                seed: options.estimation.seed,
                ..RansacOptions::default()
            };
            let on_plane = if pairs.len() >= 8 {
                ransac(&Homography2Estimator, &pairs, &ransac_options).map_or(0, |r| r.inliers.len())
            } else {
                0
            };
            PlaneCheck {
                view: v.name.clone(),
                stereo_matches: pairs.len(),
                on_one_plane: on_plane,
                planar: pairs.len() >= 8 && on_plane as f64 >= options.planar_fraction * pairs.len() as f64,
            }
        })
        .collect()
}

/// The error of a scene with no depth, naming the planar views.
fn planar_error(checks: &[PlaneCheck]) -> AlignError {
    let named: Vec<String> = checks
        .iter()
        .filter(|c| c.planar)
        .take(4)
        .map(|c| format!("'{}' ({} of {})", c.view, c.on_one_plane, c.stereo_matches))
        .collect();
    AlignError::Geometry {
        step: "scene depth".into(),
        cause: GeometryError::Degenerate(format!(
            "all stereo matches lie on one plane in views {}{}: a plane has no projective reconstruction, so no 3D homography relates the views and the rig cannot self-calibrate from them; record a scene with depth (a planar target still gives the fundamental matrix from several poses, and the rig with known intrinsics)",
            named.join(", "),
            if checks.iter().filter(|c| c.planar).count() > 4 { ", ..." } else { "" }
        )),
    }
}

/// One motion of the rig relative to the reference view.
#[derive(Debug, Clone, Serialize)]
pub struct MotionReport {
    /// View name.
    pub view: String,
    /// Quadruplets (points triangulated in both views).
    pub candidates: usize,
    /// Inliers of the 3D homography.
    pub inliers: usize,
    /// RMS symmetric transfer error of the inliers, pixels.
    pub rms_transfer_px: f64,
    /// Rotation angle of the 3D homography, degrees (a similarity invariant).
    pub homography_rotation_deg: f64,
    /// True if the motion entered the linear self-calibration.
    pub linear: bool,
    /// Rotation angle after the adjustment, degrees.
    pub rotation_deg: f64,
    /// Rotation axis direction (reference left camera frame).
    pub axis: [f64; 3],
    /// Translation of the camera centre, baselines.
    pub translation_baselines: f64,
    /// Translation along the rotation axis (screw pitch times angle), baselines.
    pub along_axis_baselines: f64,
}

/// Diagnostics of [`calibrate_rig`].
#[derive(Debug, Clone, Serialize)]
pub struct CalibrateReport {
    /// Views used, in order (the first is the reference).
    pub views: Vec<String>,
    /// Views left out, with the reason.
    pub skipped: Vec<String>,
    /// The scene-depth check of every view.
    pub planarity: Vec<PlaneCheck>,
    /// Stereo matches over all views.
    pub stereo_matches: usize,
    /// Inliers of F.
    pub stereo_inliers: usize,
    /// RMS Sampson distance of the inliers, pixels.
    pub stereo_rms_px: f64,
    /// One per moved view.
    pub motions: Vec<MotionReport>,
    /// Second-smallest over largest singular value of the plane-at-infinity system.
    pub plane_conditioning: Option<f64>,
    /// Uniqueness of the conic solution (square root of the eigenvalue ratio).
    pub conic_uniqueness: Option<f64>,
    /// Left / right intrinsics of the linear chain.
    pub linear: Option<[Intrinsics; 2]>,
    /// Why the linear chain failed, if it did.
    pub linear_error: Option<String>,
    /// The start the adjustment kept: "linear" or "rigid".
    pub start: String,
    /// Observations of the final adjustment.
    pub bundle_observations: usize,
    /// Points of the final adjustment.
    pub bundle_points: usize,
    /// Iterations of the final adjustment.
    pub bundle_iterations: usize,
    /// RMS reprojection error of the kept start, pixels.
    pub initial_rms_px: f64,
    /// Final RMS reprojection error, pixels.
    pub final_rms_px: f64,
    /// Estimated image noise, pixels.
    pub sigma_px: f64,
    /// Sigma of the focal length (`fx`) of the left and right camera, percent of it.
    pub focal_sigma_pct: [Option<f64>; 2],
    /// Mean fraction of the used views' stereo matches on one plane (the scene-depth
    /// check's `on_one_plane / stereo_matches`, averaged over the views not left out).
    pub plane_share: f64,
    /// The estimation seed of the run that gave this result (the options' seed plus
    /// [`CalibrateReport::restarts`]).
    pub estimation_seed: u64,
    /// Runs that failed before this one with earlier seeds ([`CalibrateOptions::restarts`]).
    pub restarts: usize,
    /// Warnings: a poorly determined calibration (focal sigma above
    /// [`CalibrateOptions::warn_focal_sigma_pct`]), one motion in a mostly planar scene
    /// ([`CalibrateOptions::warn_plane_fraction`]), with what to do about it.
    pub warnings: Vec<String>,
}

/// The calibrated rig and its motions, in the reference view's left camera frame.
#[derive(Debug, Clone)]
pub struct MotionCalibration {
    /// The bundle adjustment (state with free view poses, covariance, report).
    pub bundle: BundleResult,
    /// Track id of each bundle point.
    pub point_tracks: Vec<u64>,
    /// Observations of the final adjustment (`view` indexes [`CalibrateReport::views`]).
    pub observations: Vec<BundleObservation>,
    /// Image size of the views.
    pub image_size: [u32; 2],
    /// Diagnostics.
    pub report: CalibrateReport,
}

/// Rotation angle (radians) of a 3D homography conjugate to a rigid motion, from its
/// trace at determinant 1 (`tr D = 2 + 2 cos theta`).
fn homography_angle(h: &Homography3) -> Option<f64> {
    let n = h.normalized_det().ok()?;
    Some(((n.0.trace() - 2.0) / 2.0).clamp(-1.0, 1.0).acos())
}

/// A 3D homography between the reference and one view (module docs, step 3).
struct ViewMotion {
    model: TransferModel,
    rigid: Option<Isometry3<f64>>,
    inlier_tracks: Vec<u64>,
    report: MotionReport,
}

fn fit_motion(
    quads: &[Quadruplet],
    tracks: &[u64],
    frame: &StereoFrame,
    options: &CalibrateOptions,
    view: &str,
    seed: u64,
) -> Result<ViewMotion, AlignError> {
    let (p_l, p_r) = (frame.left_camera(), frame.right_camera());
    let threshold = options.estimation.homography.threshold;
    let opts = RansacOptions { seed, ..options.estimation.homography };
    let rigid_estimator = RigidFrameEstimator { p_left: p_l, p_right: p_r };
    let all: Vec<usize> = (0..quads.len()).collect();
    let select = |m: &TransferModel| -> Vec<usize> {
        all.iter()
            .copied()
            .filter(|&i| symmetric_transfer_error(m, &p_l, &p_r, &quads[i]) <= threshold)
            .collect()
    };
    let mut best: Option<(TransferModel, usize)> = None;
    let mut rigid = None;
    if let Ok(rep) = ransac(&rigid_estimator, quads, &opts) {
        rigid = Some(rep.model);
        let start = polish(&rep.model, quads, &rep.inliers, &p_l, &p_r).unwrap_or(rep.model);
        let n = select(&start).len();
        best = Some((start, n));
    }
    if best.as_ref().is_none_or(|(_, n)| *n * 2 < quads.len()) {
        let estimator = Homography3Estimator { p_left: p_l, p_right: p_r };
        if let Ok(rep) = ransac(&PolishedHomography(&estimator), quads, &opts) {
            let n = select(&rep.model).len();
            if best.as_ref().is_none_or(|(_, b)| n > *b) {
                best = Some((rep.model, n));
            }
        }
    }
    let Some((mut model, _)) = best else {
        return Err(AlignError::NotARotation {
            view: view.to_string(),
            why: "no 3D homography fits its matches with the reference view".into(),
        });
    };
    let mut inliers = select(&model);
    for _ in 0..10 {
        let Some(refit) = polish(&model, quads, &inliers, &p_l, &p_r) else { break };
        let next = select(&refit);
        if next.len() < inliers.len() {
            break;
        }
        model = refit;
        if next == inliers {
            break;
        }
        inliers = next;
    }
    if inliers.len() < options.estimation.min_tracks {
        return Err(AlignError::TooFewTracks {
            what: format!("fitting the 3D homography of view '{view}'"),
            needed: options.estimation.min_tracks,
            got: inliers.len(),
        });
    }
    let rigid_motion = rigid.map(|m| {
        let h = m.h.0 / m.h.0[(3, 3)];
        let r = headalign_geometry::so3::nearest_rotation(&h.fixed_view::<3, 3>(0, 0).into_owned());
        let t = h.fixed_view::<3, 1>(0, 3).into_owned();
        r.map(|r| Isometry3::from_parts(t.into(), UnitQuaternion::from_rotation_matrix(&r)))
    });
    let angle = homography_angle(&model.h).unwrap_or(f64::NAN);
    Ok(ViewMotion {
        model,
        rigid: rigid_motion.flatten(),
        inlier_tracks: inliers.iter().map(|&i| tracks[i]).collect(),
        report: MotionReport {
            view: view.to_string(),
            candidates: quads.len(),
            inliers: inliers.len(),
            rms_transfer_px: rms(inliers
                .iter()
                .map(|&i| symmetric_transfer_error(&model, &p_l, &p_r, &quads[i]))),
            homography_rotation_deg: angle.to_degrees(),
            linear: false,
            rotation_deg: f64::NAN,
            axis: [f64::NAN; 3],
            translation_baselines: f64::NAN,
            along_axis_baselines: f64::NAN,
        },
    })
}

/// The error of views that show the scene from (nearly) the same rig pose.
/// `largest`: the largest rotation found (deg), by the 3D homographies or by the
/// adjustment.
fn no_rotation(motions: &[ViewMotion], largest: f64, options: &CalibrateOptions) -> AlignError {
    AlignError::MissingMotion(format!(
        "no view is rotated by {} deg or more relative to the first (largest {largest:.2} deg over {} views): the matches between views see the scene from the same rig pose. A fixed rig looking at a moving target sees a static background, and a planar target (a chessboard) has no projective reconstruction to relate between views: self-calibration needs the rig itself to move in a scene with depth (with known intrinsics, --intrinsics gives the rig from the fundamental matrix)",
        options.min_rotation_deg,
        motions.len()
    ))
}

/// Everything the starts need.
struct Problem<'a> {
    recon: &'a [Reconstruction],
    point_tracks: &'a [u64],
    origin_slot: &'a [usize],
    min_tracks: usize,
}

impl Problem<'_> {
    /// A free-motion state from per-view poses and points given in the frame of the view
    /// that reconstructed them.
    fn state(
        &self,
        left: Intrinsics,
        right: Intrinsics,
        right_from_left: Isometry3<f64>,
        ref_from_cam: Vec<Isometry3<f64>>,
        point_in_cam: impl Fn(usize, u64) -> Option<Point3<f64>>,
    ) -> Result<RigState, AlignError> {
        let points =
            points_in_ref(self.point_tracks, self.origin_slot, &ref_from_cam, self.min_tracks, point_in_cam)?;
        Ok(RigState {
            left,
            right,
            left_distortion: Distortion::default(),
            right_distortion: Distortion::default(),
            right_from_left,
            motions: Motions::Free { ref_from_cam },
            points,
        })
    }
}

/// Apply the constraints to a start (the adjustment holds them from there).
fn constrain(k: &Intrinsics, options: &CalibrateOptions, k0: &Intrinsics) -> Intrinsics {
    let mut k = *k;
    if options.zero_skew {
        k.skew = 0.0;
    }
    if options.square_pixels {
        let f = k.mean_focal();
        k.fx = f;
        k.fy = f;
    }
    if options.fix_principal_point {
        k.cx = k0.cx;
        k.cy = k0.cy;
    }
    k
}

/// Self-calibrate the rig from its views (module docs). Views whose vergence readings
/// differ from the first view's are left out (the rig changed).
pub fn calibrate_rig(views: &[View], options: &CalibrateOptions) -> Result<MotionCalibration, AlignError> {
    options.validate()?;
    let mut failures = Vec::new();
    for restart in 0..=options.restarts {
        let mut o = options.clone();
        o.estimation.seed = options.estimation.seed.wrapping_add(restart as u64);
        let mut seeded = None;
        match calibrate_once(views, &o, &mut seeded) {
            Ok(mut c) => {
                c.report.restarts = restart;
                if restart > 0 {
                    c.report.warnings.push(format!(
                        "the run with estimation seed {} failed ({}); estimation seed {} gave this result: the robust stages are close to their limits (few tracks common to the views?)",
                        options.estimation.seed,
                        failures.first().map_or("", String::as_str),
                        o.estimation.seed
                    ));
                }
                return Ok(c);
            }
            Err(error) => match seeded {
                Some(Seeded { common_tracks, fitting }) => failures.push(format!(
                    "seed {}: {error} ({common_tracks} tracks seen in the reference and a moved view, {fitting} fitting its 3D homography)",
                    o.estimation.seed
                )),
                None => return Err(error),
            },
        }
    }
    Err(AlignError::Geometry {
        step: "self-calibration".into(),
        cause: GeometryError::Degenerate(format!(
            "self-calibration failed in its robust stages with {} estimation seeds: {}. Too few points are seen in both views, or they lie close to one plane: record views that overlap more (turn the rig less, 15-25 deg), in a textured scene with depth, or add a motion",
            failures.len(),
            failures.join("; ")
        )),
    })
}

/// Set by [`calibrate_once`] when it failed in a seeded stage (the 3D homography RANSAC,
/// the adjustment from its starts), which another seed may pass: the fewest tracks common
/// to the reference and a moved view, and the fewest fitting that view's 3D homography
/// (0 if none fits). Other failures (planar scene, missing motion, options) leave it unset.
#[derive(Debug, Clone, Copy)]
struct Seeded {
    common_tracks: usize,
    fitting: usize,
}

/// One run of the chain with the options' estimation seed ([`calibrate_rig`]).
fn calibrate_once(
    views: &[View],
    options: &CalibrateOptions,
    seeded: &mut Option<Seeded>,
) -> Result<MotionCalibration, AlignError> {
    let Some(first) = views.first() else {
        return Err(AlignError::Observations("no views".into()));
    };
    let mut skipped = Vec::new();
    let mut used: Vec<&View> = Vec::new();
    let e0 = first.capture.encoders;
    for v in views {
        let changed = [Joint::VergeLeft, Joint::VergeRight]
            .iter()
            .any(|&j| (v.capture.encoders.get(j) - e0.get(j)).abs() > MOVED_DEG);
        if changed {
            skipped.push(format!("{}: vergence moved (the rig changed)", v.name));
        } else {
            used.push(v);
        }
    }
    let owned: Vec<View> = used.iter().map(|v| (*v).clone()).collect();
    let planarity = check_planarity(&owned, options);
    if planarity.first().is_some_and(|c| c.planar) || planarity.iter().skip(1).all(|c| c.planar) {
        if owned.len() < 2 {
            return Err(AlignError::MissingMotion(format!(
                "{} usable view(s): self-calibration needs the rig in at least two positions",
                owned.len()
            )));
        }
        return Err(planar_error(&planarity));
    }
    let mut rig: Vec<&View> = Vec::new();
    for (v, c) in owned.iter().zip(&planarity) {
        if c.planar {
            skipped.push(format!("{}: all stereo matches on one plane", v.name));
        } else {
            rig.push(v);
        }
    }
    let [w, h] = first.capture.image_size;
    let k0 = Intrinsics::rough_guess(w, h);
    let est = &options.estimation;

    // --- 2. F from all views, frame, triangulation.
    let per_view: Vec<Vec<StereoMatch>> = rig.iter().map(|v| stereo_matches(&v.capture)).collect();
    let pairs: Vec<(Point2<f64>, Point2<f64>)> = per_view.iter().flatten().map(|m| (m.1, m.2)).collect();
    let f_report = stereo_fundamental(&pairs, est)?;
    let f: FundamentalMatrix = f_report.model;
    let inlier_pairs: Vec<(Point2<f64>, Point2<f64>)> = f_report.inliers.iter().map(|&i| pairs[i]).collect();
    let stereo_rms = rms(inlier_pairs.iter().map(|(l, r)| f.sampson_distance(l, r)));
    let frame = quasi_euclidean_frame(&f.0, &k0, &inlier_pairs).step("projective frame")?;
    let (p_l, p_r) = (frame.left_camera(), frame.right_camera());
    let recon: Vec<Reconstruction> = per_view
        .iter()
        .map(|matches| {
            matches
                .iter()
                .filter(|(_, l, r)| f.sampson_distance(l, r) <= est.fundamental.threshold)
                .filter_map(|&(t, l, r)| {
                    triangulate_optimal(&f, &p_l, &p_r, &l, &r).ok().map(|x| (t, (x, l, r)))
                })
                .collect()
        })
        .collect();

    // --- 3. 3D homographies from the reference.
    let mut motions: Vec<ViewMotion> = Vec::new();
    for (slot, v) in rig.iter().enumerate().skip(1) {
        let (mut tracks, mut quads) = (Vec::new(), Vec::new());
        for (track, (x, l0, r0)) in &recon[0] {
            if let Some((y, l1, r1)) = recon[slot].get(track) {
                tracks.push(*track);
                quads.push(Quadruplet { x: *x, y: *y, left0: *l0, right0: *r0, left1: *l1, right1: *r1 });
            }
        }
        if quads.len() < est.min_tracks {
            return Err(AlignError::TooFewTracks {
                what: format!("seen in both stereo views '{}' and '{}'", rig[0].name, v.name),
                needed: est.min_tracks,
                got: quads.len(),
            });
        }
        let common = quads.len();
        let fitted =
            fit_motion(&quads, &tracks, &frame, options, &v.name, est.seed.wrapping_add(slot as u64))
                .inspect_err(|_| *seeded = Some(Seeded { common_tracks: common, fitting: 0 }))?;
        motions.push(fitted);
    }
    if motions.is_empty() {
        return Err(AlignError::MissingMotion(
            "one usable view: self-calibration needs the rig in at least two positions".into(),
        ));
    }

    // --- The point set and the observations (as in estimate).
    let mut point_tracks: Vec<u64> = recon[0].keys().copied().collect();
    let mut origin_slot: Vec<usize> = vec![0; point_tracks.len()];
    let mut seen: std::collections::HashSet<u64> = point_tracks.iter().copied().collect();
    for (slot, map) in recon.iter().enumerate().skip(1) {
        for &track in map.keys() {
            if seen.insert(track) {
                point_tracks.push(track);
                origin_slot.push(slot);
            }
        }
    }
    let point_index: BTreeMap<u64, usize> = point_tracks.iter().enumerate().map(|(i, &t)| (t, i)).collect();
    let mut all_obs = Vec::new();
    for (slot, v) in rig.iter().enumerate() {
        for (side, list) in [(Side::Left, &v.capture.left), (Side::Right, &v.capture.right)] {
            for o in list {
                if let Some(&pi) = point_index.get(&o.track) {
                    all_obs.push(BundleObservation { point: pi, view: slot, side, pixel: o.pixel });
                }
            }
        }
    }
    let mut quad_inliers: Vec<Vec<u64>> = vec![Vec::new()];
    for m in &motions {
        let mut t = m.inlier_tracks.clone();
        t.sort_unstable();
        quad_inliers.push(t);
    }
    let first_obs: Vec<BundleObservation> = all_obs
        .iter()
        .copied()
        .filter(|o| {
            let track = point_tracks[o.point];
            recon[o.view].contains_key(&track)
                && (o.view == 0
                    || !recon[0].contains_key(&track)
                    || quad_inliers[o.view].binary_search(&track).is_ok())
        })
        .collect();
    let problem = Problem {
        recon: &recon,
        point_tracks: &point_tracks,
        origin_slot: &origin_slot,
        min_tracks: est.min_tracks,
    };

    // --- 4. The linear self-calibration.
    let mut plane_conditioning = None;
    let mut conic_uniqueness = None;
    let linear_used: Vec<bool> =
        motions.iter().map(|m| m.report.homography_rotation_deg >= options.min_rotation_deg).collect();
    let linear = (|| -> Result<RigState, AlignError> {
        let hs: Vec<Homography3> = motions
            .iter()
            .zip(&linear_used)
            .filter(|(_, u)| **u)
            .map(|(m, _)| m.model.h.normalized_det())
            .collect::<Result<_, _>>()
            .step("3D homography")?;
        if hs.is_empty() {
            let largest = motions.iter().map(|m| m.report.homography_rotation_deg).fold(0.0, f64::max);
            return Err(no_rotation(&motions, largest, options));
        }
        let (plane, cond) = plane_at_infinity_general(&hs).step("plane at infinity")?;
        plane_conditioning = Some(cond);
        let ms = hs
            .iter()
            .map(|h| infinite_homography(h, &plane))
            .collect::<Result<Vec<_>, _>>()
            .step("infinite homography")?;
        let (k_c, uniq) =
            calibrate_from_infinite_homographies(&ms, &options.constraints()).step("self-calibration")?;
        conic_uniqueness = Some(uniq);
        let k_left = Intrinsics::from_matrix(&(k0.matrix() * k_c.matrix())).step("left intrinsics")?;
        let h_pe = euclidean_upgrade(&k_c, &plane).step("Euclidean upgrade")?;
        let h_pe_inv = h_pe.try_inverse().ok_or_else(|| AlignError::Geometry {
            step: "Euclidean upgrade".into(),
            cause: GeometryError::Numerical("H_PE is singular".into()),
        })?;
        let (k_right, right_from_left) = decompose_camera(&(p_r.0 * h_pe_inv)).step("right camera")?;
        let baseline = right_from_left.translation.vector.norm();
        if !(baseline.is_finite() && baseline > 0.0) {
            return Err(AlignError::Geometry {
                step: "right camera".into(),
                cause: GeometryError::Degenerate("zero baseline".into()),
            });
        }
        let scale = 1.0 / baseline;
        let scaled =
            |m: &Isometry3<f64>| Isometry3::from_parts((m.translation.vector * scale).into(), m.rotation);
        let mut ref_from_cam = vec![Isometry3::identity()];
        for m in &motions {
            let d = motion_from_homography(&m.model.h, &h_pe).step("rigid motion")?;
            ref_from_cam.push(scaled(&d.inverse()));
        }
        problem.state(
            constrain(&k_left, options, &k0),
            constrain(&k_right, options, &k0),
            scaled(&right_from_left),
            ref_from_cam,
            |slot, track| {
                let (x, _, _) = problem.recon[slot].get(&track)?;
                dehomogenise3(&(h_pe * x)).map(|p| Point3::from(p.coords * scale))
            },
        )
    })();
    let (linear_k, linear_error) = match &linear {
        Ok(s) => (Some([s.left, s.right]), None),
        // Too few motions or constraints is structural: no start can fix it.
        Err(e @ AlignError::Geometry { cause: GeometryError::Degenerate(_), .. }) => {
            return Err(AlignError::MissingMotion(e.to_string()));
        }
        Err(AlignError::MissingMotion(m)) => return Err(AlignError::MissingMotion(m.clone())),
        Err(e) => (None, Some(e.to_string())),
    };
    // The rigid start: K = K0, the frame's rig, each view's rigid motion in the frame.
    let rigid = (|| -> Result<RigState, AlignError> {
        let t = frame.right_conditioned.column(3).into_owned();
        let rot = headalign_geometry::so3::nearest_rotation(&frame.rotation_guess).ok_or_else(|| {
            AlignError::Geometry {
                step: "rigid start".into(),
                cause: GeometryError::Numerical("SVD failed".into()),
            }
        })?;
        let right_from_left = Isometry3::from_parts(t.into(), UnitQuaternion::from_rotation_matrix(&rot));
        let mut ref_from_cam = vec![Isometry3::identity()];
        for m in &motions {
            let d = m.rigid.ok_or_else(|| AlignError::NotARotation {
                view: m.report.view.clone(),
                why: "no rigid motion fits its matches in the quasi-Euclidean frame".into(),
            })?;
            ref_from_cam.push(d.inverse());
        }
        problem.state(
            constrain(&k0, options, &k0),
            constrain(&k0, options, &k0),
            right_from_left,
            ref_from_cam,
            |slot, track| problem.recon[slot].get(&track).and_then(|(x, _, _)| dehomogenise3(x)),
        )
    })();

    // --- 5. The adjustment.
    let mut adjust_options = options.estimation.clone();
    adjust_options.bundle.zero_skew = options.zero_skew;
    adjust_options.bundle.square_pixels = options.square_pixels;
    adjust_options.bundle.fix_principal_point = options.fix_principal_point;
    adjust_options.bundle.estimate_distortion = options.estimate_distortion;
    // Each start is adjusted to convergence; the two results are compared on the same
    // observations (all of them, each squared residual truncated at the re-selection gate
    // of the noisier result), since each adjustment re-selects its own inliers and a
    // result that keeps fewer of them would look better by its own RMS. With one general
    // motion the cost has shallow valleys: a start that screens better after a few
    // iterations can end in the worse minimum.
    let mut results: Vec<crate::estimate::Adjustment> = Vec::new();
    let mut last_error = None;
    for (index, start) in [linear, rigid].into_iter().enumerate() {
        match adjust_from_starts(
            vec![start],
            &first_obs,
            &all_obs,
            &point_tracks,
            &origin_slot,
            &recon,
            &adjust_options,
        ) {
            Ok(mut a) => {
                a.start_index = index;
                results.push(a);
            }
            Err(e) => last_error = Some(e),
        }
    }
    let sources = PointSources { point_tracks: &point_tracks, origin_slot: &origin_slot, recon: &recon };
    let results: Vec<crate::estimate::Adjustment> =
        results.into_iter().map(|a| every_point_pass(a, &all_obs, &sources, &adjust_options)).collect();
    let gate = est.reselect_sigmas * results.iter().map(|a| a.last.report.sigma_px).fold(0.05, f64::max);
    let truncated_cost = |a: &crate::estimate::Adjustment| -> f64 {
        all_obs
            .iter()
            .map(|o| {
                residual_pixels(&a.last.state, o).map_or(gate * gate, |r| r.norm_squared().min(gate * gate))
            })
            .sum()
    };
    let adjusted = results.into_iter().min_by(|a, b| truncated_cost(a).total_cmp(&truncated_cost(b)));
    let Some(adjusted) = adjusted else {
        *seeded = motions
            .iter()
            .map(|m| Seeded { common_tracks: m.report.candidates, fitting: m.report.inliers })
            .min_by_key(|x| x.fitting);
        return Err(last_error.unwrap_or_else(|| AlignError::MissingMotion("no initialisation".into())));
    };

    // Final motions in the report.
    let state = &adjusted.last.state;
    let mut motion_reports = Vec::new();
    for (i, (m, used)) in motions.iter().zip(&linear_used).enumerate() {
        let mut r = m.report.clone();
        r.linear = *used;
        let pose = state.motions.ref_from_cam(i + 1);
        r.translation_baselines = pose.translation.vector.norm();
        if let Some(screw) = screw_from_isometry(&pose, 1e-9) {
            r.rotation_deg = screw.angle.to_degrees();
            r.axis = [screw.axis.direction.x, screw.axis.direction.y, screw.axis.direction.z];
            r.along_axis_baselines = pose.translation.vector.dot(&screw.axis.direction);
        }
        motion_reports.push(r);
    }
    // A noisy 3D homography can pass the rotation test although the rig never turned (a
    // fixed rig and a moving chessboard: one homography passed the test, 0.03-0.15 deg
    // after the adjustment, with a meaningless K). The adjusted motions decide.
    let largest = motion_reports.iter().map(|r| r.rotation_deg).filter(|a| a.is_finite()).fold(0.0, f64::max);
    if largest < options.min_rotation_deg {
        return Err(no_rotation(&motions, largest, options));
    }
    let cov = &adjusted.last.covariance;
    let focal_sigma_pct = [("left", &state.left), ("right", &state.right)]
        .map(|(side, k)| cov.sigma(&format!("{side}.fx")).map(|s| 100.0 * s / k.fx));
    let mut warnings = Vec::new();
    if focal_sigma_weak(&focal_sigma_pct, options) {
        warnings.push(format!(
            "the focal length is poorly determined: sigma {} (left) / {} (right) of f, above {} %. These motions and this scene are close to a critical configuration, where the estimate can be off by several sigmas. Add a motion about another axis, or turn the rig 20-30 deg about an axis perpendicular to both the baseline and the optical axis (the vertical, for a side-by-side rig) while moving it 0.2-0.3 m along that axis, in a scene with depth (not one wall); avoid turning about the baseline or the optical axis",
            fmt_pct(focal_sigma_pct[0]),
            fmt_pct(focal_sigma_pct[1]),
            options.warn_focal_sigma_pct
        ));
        if options.estimate_distortion {
            warnings.push(
                "the lens distortion is estimated: k1 correlates with f (one motion, 0.5 px: the bound of f grows from 0.14-0.40 % to 0.32-0.65 %); a known lens (a lens file) or a second motion tightens it".into(),
            );
        }
    }
    // One motion in a scene that is mostly one plane: the cost can have its minimum far
    // from the truth, further than the linearised sigma says (rendered seed 20: 92 % and
    // 87 % of the matches on one wall, f 20 % off with a sigma of 0.9 %).
    let used_checks: Vec<&PlaneCheck> = planarity.iter().filter(|c| !c.planar).collect();
    let plane_share =
        used_checks.iter().map(|c| c.on_one_plane as f64 / c.stereo_matches.max(1) as f64).sum::<f64>()
            / used_checks.len().max(1) as f64;
    if plane_weak(motions.len(), plane_share, options) {
        warnings.push(format!(
            "one motion in a scene that is mostly one plane ({:.0} % of the stereo matches on one plane, on average over the views): self-calibration is close to degenerate and the focal length can be off by far more than its sigma; record a second motion, or a scene with more depth",
            100.0 * plane_share
        ));
    }
    let report = CalibrateReport {
        views: rig.iter().map(|v| v.name.clone()).collect(),
        skipped,
        planarity,
        stereo_matches: pairs.len(),
        stereo_inliers: f_report.inliers.len(),
        stereo_rms_px: stereo_rms,
        motions: motion_reports,
        plane_conditioning,
        conic_uniqueness,
        linear: linear_k,
        linear_error,
        start: if adjusted.start_index == 0 { "linear" } else { "rigid" }.to_string(),
        bundle_observations: adjusted.observations.len(),
        bundle_points: point_tracks.len(),
        bundle_iterations: adjusted.last.report.iterations,
        initial_rms_px: adjusted.first.report.initial_rms_px,
        final_rms_px: adjusted.last.report.final_rms_px,
        sigma_px: adjusted.last.report.sigma_px,
        focal_sigma_pct,
        plane_share,
        estimation_seed: est.seed,
        restarts: 0,
        warnings,
    };
    Ok(MotionCalibration {
        bundle: adjusted.last,
        point_tracks,
        observations: adjusted.observations,
        image_size: [w, h],
        report,
    })
}

/// Where each bundle point came from: its track, the rig view that first reconstructed
/// it, and the per-view stereo reconstructions.
struct PointSources<'a> {
    point_tracks: &'a [u64],
    origin_slot: &'a [usize],
    recon: &'a [Reconstruction],
}

/// A point the adjustment did not use, triangulated (linear, undistorted pixels) from the
/// stereo match of the view that first reconstructed it with the calibrated rig of
/// `state`, in the reference frame; `None` if it does not lie in front of both cameras.
fn triangulate_in_state(state: &RigState, src: &PointSources<'_>, i: usize) -> Option<Point3<f64>> {
    let slot = *src.origin_slot.get(i)?;
    let (_, l, r) = src.recon.get(slot)?.get(src.point_tracks.get(i)?)?;
    let l = state.left_distortion.undistort_pixel(&state.left, l).ok()?;
    let r = state.right_distortion.undistort_pixel(&state.right, r).ok()?;
    let p_l = ProjectiveCamera::from_pose(&state.left, &Isometry3::identity());
    let p_r = ProjectiveCamera::from_pose(&state.right, &state.right_from_left);
    let x = triangulate_linear(&p_l, &p_r, &l, &r).ok()?;
    let p = dehomogenise3(&x)?;
    (p.z > 0.0 && (state.right_from_left * p).z > 0.0).then(|| state.motions.ref_from_cam(slot) * p)
}

/// Width of the first gate of [`every_point_pass`], in re-selection gates (about 14
/// sigmas, 7 px at 0.5 px noise). Measured: 3, 4 and 6 give the same one-motion results
/// (seeds 1-20, point mode) and keep the rendered barrel-lens session within 0.5 %.
const FIRST_PASS_GATE: f64 = 4.0;

/// Step 6 (module docs): the adjustment over the observations of every point seen at
/// least twice. The shared adjustment ([`adjust_from_starts`]) keeps only points seen in
/// at least four images, which for one motion of a rig leaves out the points seen by one
/// stereo view only (more than half of the observations, and with them the rig's
/// epipolar geometry over the whole image), and its re-selection gate, applied at a
/// solution in a wrong valley of the shallow one-motion cost, drops exactly the
/// observations that disagree with that valley. So: the points it left out are
/// triangulated with its calibration, one adjustment under the robust loss takes every
/// observation within [`FIRST_PASS_GATE`] re-selection gates (points with at least 2,
/// depths within `DEPTH_RATIO` of the median), then
/// plain least squares on those within `reselect_sigmas` of it, re-selected until stable
/// (at most 3 times). Measured on the one-general-motion session (point mode, 0.5 px,
/// seeds 1-20): the sigma of f falls by up to 2x, and seed 17 (the robust stage 7.2 %
/// off, bound 0.26 %) ends at 0.41 %, the minimum an adjustment started at the truth
/// reaches. Stereo-only points cannot bend to a wrong match beyond the epipolar residual
/// F already checked. A failed adjustment keeps the previous result.
fn every_point_pass(
    adjusted: crate::estimate::Adjustment,
    all_obs: &[BundleObservation],
    src: &PointSources<'_>,
    options: &EstimationOptions,
) -> crate::estimate::Adjustment {
    let mut state = adjusted.last.state.clone();
    let mut used = vec![false; state.points.len()];
    for o in &adjusted.observations {
        if let Some(u) = used.get_mut(o.point) {
            *u = true;
        }
    }
    for (i, u) in used.iter().enumerate() {
        if !u && let Some(p) = triangulate_in_state(&state, src, i) {
            state.points[i] = p;
        }
    }
    let ls = BundleOptions {
        robust: RobustLoss::None,
        noise_sigma_px: None,
        max_iterations: options.bundle.max_iterations.max(FINAL_ITERATIONS),
        ..options.bundle.clone()
    };
    let key = |o: &BundleObservation| (o.point, o.view, o.side == Side::Left);
    let mut best = adjusted;
    let mut sigma = best.last.report.sigma_px;
    let mut previous: Vec<(usize, usize, bool)> = Vec::new();
    for pass in 0..4 {
        // The first pass takes the observations within FIRST_PASS_GATE re-selection gates
        // under the robust loss, so that those that disagree with a solution in a wrong
        // valley can pull it out (the re-selection gate at once would drop exactly those
        // and keep the valley); gross outliers stay out (with every observation under the
        // Huber loss, the rendered barrel-lens session moved f by 2.3 %).
        let gate = options.reselect_sigmas * sigma.max(0.05) * if pass == 0 { FIRST_PASS_GATE } else { 1.0 };
        let gated: Vec<BundleObservation> = all_obs
            .iter()
            .copied()
            .filter(|o| residual_pixels(&state, o).is_some_and(|r| r.norm() <= gate))
            .collect();
        let mut counts = vec![0usize; state.points.len()];
        for o in &gated {
            counts[o.point] += 1;
        }
        let mut dist: Vec<f64> = (0..state.points.len())
            .filter(|&i| counts[i] >= 2)
            .map(|i| state.points[i].coords.norm())
            .collect();
        dist.sort_by(f64::total_cmp);
        let Some(&median) = dist.get(dist.len() / 2) else { break };
        let tame = |i: usize| {
            let d = state.points[i].coords.norm();
            d.is_finite() && d <= median * DEPTH_RATIO && d >= median / DEPTH_RATIO
        };
        let obs: Vec<BundleObservation> =
            gated.into_iter().filter(|o| counts[o.point] >= 2 && tame(o.point)).collect();
        let keys: Vec<(usize, usize, bool)> = obs.iter().map(key).collect();
        if (keys == previous && pass > 1) || obs.len() < options.min_tracks {
            break;
        }
        let robust = BundleOptions { robust: options.bundle.robust, ..ls.clone() };
        let Ok(result) = bundle_adjust(&state, &obs, if pass == 0 { &robust } else { &ls }) else { break };
        sigma = result.report.sigma_px;
        state = result.state.clone();
        previous = keys;
        best = crate::estimate::Adjustment { last: result, observations: obs, ..best };
    }
    best
}

/// Either focal sigma above [`CalibrateOptions::warn_focal_sigma_pct`] (the warning of a
/// poorly determined focal length).
fn focal_sigma_weak(focal_sigma_pct: &[Option<f64>; 2], options: &CalibrateOptions) -> bool {
    focal_sigma_pct.iter().flatten().copied().fold(0.0, f64::max) > options.warn_focal_sigma_pct
}

/// The larger of the two focal sigmas, percent; infinite if either is unknown (a singular
/// covariance determines nothing).
fn worst_focal_sigma_pct(focal_sigma_pct: &[Option<f64>; 2]) -> f64 {
    focal_sigma_pct.iter().map(|s| s.filter(|v| v.is_finite()).unwrap_or(f64::INFINITY)).fold(0.0, f64::max)
}

/// One motion in a scene mostly on one plane (the warning of
/// [`CalibrateOptions::warn_plane_fraction`]).
fn plane_weak(motions: usize, plane_share: f64, options: &CalibrateOptions) -> bool {
    motions == 1 && plane_share > options.warn_plane_fraction
}

/// True if a calibration carries a warning about its data (the focal length poorly
/// determined, or one motion in a mostly planar scene; not the note that a restart was
/// needed): the data may give more if the images are read more densely ([`Density`]).
pub fn weak_data(report: &CalibrateReport, options: &CalibrateOptions) -> bool {
    focal_sigma_weak(&report.focal_sigma_pct, options)
        || plane_weak(report.motions.len(), report.plane_share, options)
}

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
    /// Their sigmas, percent ([`CalibrateReport::focal_sigma_pct`]).
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
        Self {
            corners,
            focal_px: [st.left.fx, st.right.fx],
            focal_sigma_pct: cal.report.focal_sigma_pct,
            weak: weak_data(&cal.report, options),
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
/// shift. Measured on rendered one-motion sessions (the removed `examples/onegen_diag.rs`, truth
/// known): procedural seed 14 gives f +0.63 % (sigma 0.46 %) at 1500 corners and
/// +2.84 % (sigma 0.31 %, 4.5 combined sigmas apart) at 3000; the same tracks at their
/// true pixels with independent 0.4 px noise give +0.78 % and +0.95 %, so the denser
/// result's error is the detector's, not noise or the estimator. Its principal points
/// are 10.6 px from the centre on average against 7.5 px (truth 5.9 px). On the sessions
/// where the denser run is right and disagrees (photographs, seeds 14 and 20) the first
/// run's were 11.1 and 38.9 px against 6.5 and 5.7 px. Those numbers are without the
/// front end's patch refinement ([`crate::frontend::FrontEndOptions::refine`], on by
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

fn fmt_pct(v: Option<f64>) -> String {
    v.map_or_else(|| "unknown".to_string(), |v| format!("{v:.2} %"))
}

/// Whether a set of views can be calibrated by general-motion self-calibration at all
/// (used by callers that want the scene-depth error before tracking across views):
/// the scene-depth check of step 1 on each view's own stereo matches.
pub fn require_depth(views: &[View], options: &CalibrateOptions) -> Result<Vec<PlaneCheck>, AlignError> {
    let checks = check_planarity(views, options);
    if !checks.is_empty() && checks.iter().all(|c| c.planar) {
        return Err(planar_error(&checks));
    }
    Ok(checks)
}

/// The rig from known intrinsics (no self-calibration): what a planar target or a single
/// stereo pair still gives. The views' observations must already be undistorted.
#[derive(Debug, Clone)]
pub struct KnownIntrinsicsRig {
    /// The fundamental matrix of the refined rig, `K_R^-T [t]x R K_L^-1` (pixels,
    /// `x_R^T F x_L = 0`).
    pub fundamental: FundamentalMatrix,
    /// `right_from_left` with a unit translation: decomposed from `E = K_R^T F K_L` of
    /// the RANSAC `F`, then refined on its 5 dof over F's inliers (Sampson distance).
    pub right_from_left: Isometry3<f64>,
    /// Stereo matches over all views.
    pub stereo_matches: usize,
    /// Inliers of F.
    pub stereo_inliers: usize,
    /// RMS Sampson distance of the inliers under the refined rig, pixels.
    pub stereo_rms_px: f64,
    /// The inlier matches (left, right).
    pub inlier_pairs: Vec<(Point2<f64>, Point2<f64>)>,
}

/// F by RANSAC (the estimation's options and seed) from the stereo matches `pairs`
/// (left, right) of all views together; too few matches is an error.
fn stereo_fundamental(
    pairs: &[(Point2<f64>, Point2<f64>)],
    options: &EstimationOptions,
) -> Result<RansacReport<FundamentalMatrix>, AlignError> {
    if pairs.len() < options.min_tracks {
        return Err(AlignError::TooFewTracks {
            what: "matched between left and right".into(),
            needed: options.min_tracks,
            got: pairs.len(),
        });
    }
    estimate_fundamental(pairs, &RansacOptions { seed: options.seed, ..options.fundamental })
        .step("fundamental matrix")
}

/// F by RANSAC from the stereo matches of every view (the rig is fixed, so matches on
/// different board poses together are not planar), then the rig from `E` with the known
/// intrinsics `k_left`, `k_right` (cheirality vote over the inliers).
pub fn rig_from_known_intrinsics(
    views: &[View],
    k_left: &Intrinsics,
    k_right: &Intrinsics,
    options: &EstimationOptions,
) -> Result<KnownIntrinsicsRig, AlignError> {
    options.validate()?;
    let pairs: Vec<(Point2<f64>, Point2<f64>)> =
        views.iter().flat_map(|v| stereo_matches(&v.capture)).map(|m| (m.1, m.2)).collect();
    let f_report = stereo_fundamental(&pairs, options)?;
    let f = f_report.model;
    let inlier_pairs: Vec<(Point2<f64>, Point2<f64>)> = f_report.inliers.iter().map(|&i| pairs[i]).collect();
    let decomposed = headalign_geometry::frame::relative_pose(&f.0, k_left, k_right, &inlier_pairs)
        .step("relative pose from E")?;
    // The 5-dof ML refinement on the inliers: decomposing the 7-dof F alone lets noise in
    // its two surplus degrees of freedom leak into the pose (measured on the Middlebury
    // motorcycle pair, docs/real-data.md).
    let (right_from_left, stereo_rms_px) =
        headalign_geometry::frame::refine_relative_pose(&decomposed, k_left, k_right, &inlier_pairs, 100)
            .step("relative pose refinement")?;
    let f =
        FundamentalMatrix(headalign_geometry::frame::fundamental_of_pose(&right_from_left, k_left, k_right));
    Ok(KnownIntrinsicsRig {
        stereo_rms_px,
        fundamental: f,
        right_from_left,
        stereo_matches: pairs.len(),
        stereo_inliers: inlier_pairs.len(),
        inlier_pairs,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A trial with focal lengths `f` (px) and sigmas `sigma` (percent), principal points
    /// 6 px from the image centre.
    fn trial(corners: usize, f: [f64; 2], sigma: [f64; 2], weak: bool) -> DensityTrial {
        DensityTrial {
            corners,
            focal_px: f,
            focal_sigma_pct: sigma.map(Some),
            weak,
            principal_point_offset_px: Some(6.0),
            error: None,
            seconds: 1.0,
        }
    }

    /// Trials that disagree beyond their sigmas: the principal points decide, not the
    /// smaller sigma. The three re-detected one-motion sessions whose two results disagree
    /// (docs/real-data.md; focal lengths, sigmas and mean principal-point distances from
    /// the image centre as measured): procedural seed 14 keeps 1500 corners (+0.63 %, where
    /// the denser +2.84 % has the smaller sigma), photographs seeds 14 and 20 keep 3000
    /// (+1.18 % and -0.15 %, against +4.04 % and +19.7 %). Trials that agree still go by
    /// the sigma.
    #[test]
    fn disagreeing_densities_are_decided_by_the_principal_points() {
        let with = |t: DensityTrial, pp: f64| DensityTrial { principal_point_offset_px: Some(pp), ..t };
        let cases = [
            // (first f, sigma, pp; denser f, sigma, pp; keep the denser?)
            ([704.39, 707.69], [0.456, 0.445], 7.45, [719.45, 725.05], [0.315, 0.311], 10.6, false),
            ([728.28, 730.44], [0.59, 0.57], 11.1, [708.25, 711.54], [0.40, 0.40], 6.45, true),
            ([838.1, 841.2], [0.93, 0.90], 38.9, [699.56, 703.91], [0.30, 0.29], 5.65, true),
        ];
        for (f1, s1, p1, f2, s2, p2, keep) in cases {
            let first = with(trial(1500, f1, s1, true), p1);
            let denser = with(trial(3000, f2, s2, true), p2);
            assert!(disagreement_sigmas(&first, &denser).is_some_and(|z| z > DISAGREEMENT_SIGMAS));
            assert_eq!(prefer_denser(&first, &denser), keep, "{f1:?} vs {f2:?}");
            let r = DensityReport::choose(true, first, Some(denser));
            assert!(r.warn && r.note.contains("principal points nearer"), "{}", r.note);
        }
        // Agreeing trials: the smaller sigma, wherever the principal points are.
        let first = with(trial(1500, [701.0, 706.0], [0.5, 0.5], true), 3.0);
        let denser = with(trial(3000, [702.0, 707.0], [0.3, 0.3], true), 12.0);
        assert!(prefer_denser(&first, &denser));
        // A failed run has no principal point.
        assert_eq!(DensityTrial::failed(1500, "x".into(), 1.0).principal_point_offset_px, None);
    }

    /// The density choice on the trials measured on rendered sessions (docs/real-data.md):
    /// seed 20 (one wall) is retried and the dense result kept, with the 17-sigma
    /// disagreement as a warning; a sound first result is not retried; a dense run that
    /// diverged (one motion with k1, k2 estimated, seed 1 at 3000: f 2805 px, sigma 15 %)
    /// loses to the first; a failed first run is retried and a failed retry never kept;
    /// `--corners N` never retries.
    #[test]
    fn density_retries_weak_results_and_keeps_the_better_determined() {
        let d = Density::default();
        d.validate().unwrap();
        // Measured principal points: 38.9 px from the image centre (cy +31.7 px), and 5.7 px.
        let weak = DensityTrial {
            principal_point_offset_px: Some(38.9),
            ..trial(1500, [838.1, 841.2], [0.93, 0.90], true)
        };
        let dense = DensityTrial {
            principal_point_offset_px: Some(5.7),
            ..trial(3000, [699.6, 703.9], [0.30, 0.29], true)
        };
        assert!(d.retry(&weak));
        assert!(!Density::fixed(1500).retry(&weak));
        assert!(!d.retry(&trial(1500, [700.6, 705.5], [0.44, 0.44], false)));
        let z = disagreement_sigmas(&weak, &dense).unwrap();
        // (838.1 - 699.6) / hypot(0.0093 * 838.1, 0.0030 * 699.6) = 17.1; the right
        // camera's (841.2 - 703.9) / hypot(7.57, 2.04) = 17.5.
        assert!((z - 17.5).abs() < 0.1, "{z}");
        let r = DensityReport::choose(true, weak.clone(), Some(dense.clone()));
        assert_eq!(r.kept, 1);
        assert!(r.warn && r.note.contains("17.") && r.note.contains("3000"), "{}", r.note);
        // Agreeing trials: the denser kept by its sigma, and only a note.
        let agree = trial(3000, [839.0, 842.0], [0.60, 0.60], true);
        let r = DensityReport::choose(true, weak.clone(), Some(agree));
        assert_eq!(r.kept, 1);
        assert!(!r.warn && r.disagreement_sigmas.is_some_and(|z| z < 1.0), "{r:?}");
        // The diverged dense run loses.
        let first = trial(1500, [701.3, 706.2], [0.50, 0.50], true);
        let diverged = trial(3000, [2805.3, 2830.0], [15.4, 15.4], true);
        assert!(!prefer_denser(&first, &diverged));
        assert_eq!(DensityReport::choose(true, first.clone(), Some(diverged)).kept, 0);
        // An unknown sigma counts as infinite.
        let unknown = DensityTrial { focal_sigma_pct: [Some(0.1), None], ..dense.clone() };
        assert!(!prefer_denser(&first, &unknown));
        assert!(disagreement_sigmas(&first, &unknown).is_none());
        // Failures.
        let failed = DensityTrial::failed(1500, "not enough data".into(), 2.0);
        assert!(d.retry(&failed));
        assert!(prefer_denser(&failed, &dense));
        let r = DensityReport::choose(true, failed.clone(), Some(dense.clone()));
        assert!(r.kept == 1 && r.warn && r.note.contains("failed (not enough data)"), "{}", r.note);
        assert!(!prefer_denser(&first, &DensityTrial::failed(3000, "x".into(), 2.0)));
        // One trial: nothing to say.
        let r = DensityReport::choose(false, first, None);
        assert!(r.kept == 0 && !r.warn && r.note.is_empty() && r.trials.len() == 1);
        assert!(Density { corners: 1500, retry_corners: 1000 }.validate().is_err());
        assert!(Density::fixed(0).validate().is_err());
    }

    #[test]
    fn reads_opencv_lenses() {
        let text = "%YAML:1.0\nM1: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 5.3e+02, 0., 3.3e+02, 0.,\n       5.3e+02, 2.4e+02, 0., 0., 1. ]\nD1: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ 0.29, -1.03, 0., 0., 0. ]\nM2: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 5.3e+02, 0., 3.2e+02, 0., 5.3e+02, 2.4e+02, 0., 0., 1. ]\nD2: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ -0.17, -0.11, 0., 0., 0. ]\n";
        let [l, r] = read_opencv_lenses(text, "t").unwrap();
        assert_eq!(l.k.fx, 530.0);
        assert_eq!(l.k.cy, 240.0);
        assert_eq!(l.distortion, Distortion::radial(0.29, -1.03));
        assert_eq!(r.k.cx, 320.0);
        assert_eq!(r.distortion, Distortion::radial(-0.17, -0.11));
        let single = "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 500., 0., 320., 0., 500., 240., 0., 0., 1. ]\ndistortion_coefficients: !!opencv-matrix\n   rows: 5\n   cols: 1\n   dt: d\n   data: [ -0.2, 0.01, 0., 0., 0. ]\n";
        let [a, b] = read_opencv_lenses(single, "s").unwrap();
        assert_eq!(a, b);
        for (bad, expect) in [
            ("nothing: 1\n", "no lens found"),
            ("camera_matrix: [ 1., 2. ]\ndistortion_coefficients: [ 0., 0., 0., 0. ]\n", "9"),
            (
                "camera_matrix: [ 500., 0., 320., 0., 500., 240., 0., 0., 1. ]\ndistortion_coefficients: [ 0., x ]\n",
                "no lens",
            ),
            (
                "camera_matrix: [ 500., 0., 320., 0., 500., 240., 0., 0., 1. ]\ndistortion_coefficients: [ 0., 1e999, 0., 0. ]\n",
                "finite",
            ),
        ] {
            let e = read_opencv_lenses(bad, "f.yml").unwrap_err().to_string();
            assert!(e.contains("f.yml") && e.contains(expect), "{e}");
        }
    }

    /// The OpenCV YAML our export writes is a lens file `--distortion` reads back exactly
    /// (shortest round-trip number formatting).
    #[test]
    fn reads_back_our_own_export() {
        let d = [
            Distortion { k1: -0.25, k2: 0.125, p1: 0.001, p2: -0.002, k3: 0.01 },
            Distortion::radial(0.1, 0.0),
        ];
        let stereo = crate::export::StereoCalibration {
            image_size: [768, 576],
            left: Intrinsics { fx: 700.25, fy: 720.5, skew: 0.0, cx: 390.125, cy: 284.0 },
            right: Intrinsics::new(705.0, 716.0, 380.0, 290.0),
            sigmas: Default::default(),
            right_from_left: Isometry3::translation(-0.25, 0.0, 0.0),
            unit: crate::export::TranslationUnit::Metres,
            distortion: d,
        };
        let [l, r] = read_opencv_lenses(&stereo.opencv_yaml().unwrap(), "ours").unwrap();
        assert_eq!((l.k, l.distortion, r.k, r.distortion), (stereo.left, d[0], stereo.right, d[1]));
    }

    #[test]
    fn options_validate() {
        assert!(CalibrateOptions::default().validate().is_ok());
        assert!(CalibrateOptions { min_rotation_deg: 0.0, ..Default::default() }.validate().is_err());
        assert!(CalibrateOptions { planar_fraction: 1.5, ..Default::default() }.validate().is_err());
        assert!(CalibrateOptions { planar_threshold_px: f64::NAN, ..Default::default() }.validate().is_err());
    }

    use headalign_geometry::so3::{Line, rotation_about_line};
    use headalign_platform::{Encoders, StereoHead};
    use headalign_sim::rigmotion::general_rig_motion;
    use headalign_sim::{Scenario, SimulatedHead};
    use nalgebra::{Unit, Vector3};

    /// The oblique screw motion `simulate --motion general` used before: 20 deg about
    /// `(0.8, -1, 0.3)` with 0.3 m along it (its axis has a large component along the
    /// baseline: near-critical on some scenes, see `headalign_sim::rigmotion`).
    fn oblique_motion() -> Isometry3<f64> {
        headalign_sim::rigmotion::screw_motion(Vector3::new(0.8, -1.0, 0.3), 20.0, 0.3)
    }

    /// Square-pixel cameras, no outliers; the reference view and the moved one.
    fn general_session(seed: u64, noise_px: f64) -> (Vec<View>, Intrinsics, Intrinsics) {
        session_with_motion(seed, noise_px, &headalign_sim::rigmotion::general_rig_motion())
    }

    fn session_with_motion(
        seed: u64,
        noise_px: f64,
        motion: &Isometry3<f64>,
    ) -> (Vec<View>, Intrinsics, Intrinsics) {
        let scenario = Scenario {
            seed,
            noise_px,
            points: 400,
            outlier_fraction: 0.0,
            left: Intrinsics::new(700.0, 700.0, 390.0, 284.0),
            right: Intrinsics::new(705.0, 705.0, 380.0, 290.0),
            ..Scenario::default()
        };
        let mut head = SimulatedHead::new(scenario).unwrap();
        let v0 = View { name: "initial".into(), capture: head.capture().unwrap() };
        head.set_world_from_robot(*motion);
        let v1 = View { name: "moved".into(), capture: head.capture().unwrap() };
        let t = head.truth();
        (vec![v0, v1], t.left, t.right)
    }

    fn f_err_pct(est: &Intrinsics, truth: &Intrinsics) -> f64 {
        100.0 * (est.mean_focal() - truth.mean_focal()).abs() / truth.mean_focal()
    }

    /// The oblique motion on seed 2 (its Cramer-Rao bound of f at the truth is 4.1 %;
    /// the estimate is 2.5 % off with a sigma of 0.94 %) is flagged with warnings that
    /// say what to do; the default general motion on seed 1 is not (sigma 0.16 %).
    #[test]
    fn near_critical_motion_is_flagged() {
        let options = CalibrateOptions { zero_skew: true, square_pixels: true, ..Default::default() };
        let (views, _, _) = session_with_motion(2, 0.5, &oblique_motion());
        let cal = calibrate_rig(&views, &options).unwrap();
        let s = cal.report.focal_sigma_pct[0].unwrap();
        assert!(s > 0.5, "sigma {s} %");
        assert!(cal.report.warnings[0].contains("poorly determined"), "{:?}", cal.report.warnings);
        // A weak result: an image front end retries it denser (Density).
        assert!(weak_data(&cal.report, &options));
        let (views, _, _) = general_session(1, 0.5);
        let cal = calibrate_rig(&views, &options).unwrap();
        assert!(cal.report.warnings.is_empty(), "{:?}", cal.report.warnings);
        assert!(!weak_data(&cal.report, &options));
    }

    #[test]
    fn one_general_motion_noise_free_is_exact() {
        let (views, l, r) = general_session(1, 0.0);
        let options = CalibrateOptions { zero_skew: true, square_pixels: true, ..Default::default() };
        let cal = calibrate_rig(&views, &options).unwrap();
        let st = &cal.bundle.state;
        // 1e-6 relative: noise-free, the adjustment converges to rounding.
        assert!(
            f_err_pct(&st.left, &l) < 1e-4 && f_err_pct(&st.right, &r) < 1e-4,
            "{:?} {:?}",
            st.left,
            st.right
        );
        assert!((st.left.cx - l.cx).abs() < 1e-3 && (st.right.cy - r.cy).abs() < 1e-3);
        assert!(cal.report.linear.is_some(), "{:?}", cal.report.linear_error);
        // Without a constraint one motion leaves the calibration undetermined: the error
        // names the missing constraint.
        let e = calibrate_rig(&views, &CalibrateOptions::default()).unwrap_err().to_string();
        assert!(e.contains("missing motion") && e.contains("constraint"), "{e}");
    }

    /// The bar of issue 6: one general motion (`headalign_sim::rigmotion`: 25 deg about
    /// the vertical, 0.3 m along it), zero skew and square pixels, 0.5 px noise, 400
    /// points: focal length within 1 %. Seeds 1-20 all pass (measured 0.001-0.85 %, the
    /// worst seed 14 with a sigma of 0.44 %; `general_motion_seeds`); the test runs the
    /// first 8 and seed 14 (time), and checks that none of them has the sigma warning
    /// and that seeds 2 and 14 (88 % and 92 % of the matches on one wall) have the
    /// scene warning.
    #[test]
    fn one_general_motion_half_pixel_within_one_percent() {
        for seed in [1, 2, 3, 4, 5, 6, 7, 8, 14] {
            let (views, l, r) = general_session(seed, 0.5);
            let options = CalibrateOptions { zero_skew: true, square_pixels: true, ..Default::default() };
            let cal = calibrate_rig(&views, &options).unwrap();
            let st = &cal.bundle.state;
            let (el, er) = (f_err_pct(&st.left, &l), f_err_pct(&st.right, &r));
            assert!(el < 1.0 && er < 1.0, "seed {seed}: f errors {el:.3} % / {er:.3} %");
            let sigma_warning = cal.report.warnings.iter().any(|w| w.contains("poorly determined"));
            assert!(!sigma_warning, "seed {seed}: {:?}", cal.report.warnings);
            // Seed 14 has 89 % and 94 % of its views' matches on one wall: the scene
            // warning (it is still within 1 %, at 0.85 %, its worst).
            let plane_warning = cal.report.warnings.iter().any(|w| w.contains("mostly one plane"));
            assert_eq!(plane_warning, seed == 14 || seed == 2, "seed {seed}: {:?}", cal.report.warnings);
            // weak_data is exactly the data warnings (no restart here).
            assert_eq!(weak_data(&cal.report, &options), plane_warning, "seed {seed}");
        }
    }

    /// The Monte-Carlo behind the numbers in docs/real-data.md (seeds 1-20, 0.5 px):
    /// `cargo test --release -p headalign --lib calibrate::tests::general_motion_seeds -- --ignored --nocapture`.
    #[test]
    #[ignore = "experiment: prints statistics over 20 seeds"]
    fn general_motion_seeds() {
        let mut errs = Vec::new();
        for seed in 1..=20 {
            let (views, l, r) = general_session(seed, 0.5);
            let options = CalibrateOptions { zero_skew: true, square_pixels: true, ..Default::default() };
            match calibrate_rig(&views, &options) {
                Ok(cal) => {
                    let st = &cal.bundle.state;
                    let s = cal.bundle.covariance.sigma("left.fx").unwrap_or(f64::NAN);
                    let (el, er) = (f_err_pct(&st.left, &l), f_err_pct(&st.right, &r));
                    let plane = cal
                        .report
                        .planarity
                        .iter()
                        .map(|c| format!("{:.2}", c.on_one_plane as f64 / c.stereo_matches as f64))
                        .collect::<Vec<_>>()
                        .join("/");
                    eprintln!(
                        "seed {seed}: f err L {el:.3} % R {er:.3} % (sigma L {:.3} %), rms {:.3} px, start {}, on one plane {plane}, quads {}",
                        100.0 * s / l.fx,
                        cal.report.final_rms_px,
                        cal.report.start,
                        cal.report.motions[0].inliers
                    );
                    errs.push(el.max(er));
                }
                Err(e) => eprintln!("seed {seed}: {e}"),
            }
        }
        let rms = (errs.iter().map(|e| e * e).sum::<f64>() / errs.len() as f64).sqrt();
        let worst = errs.iter().copied().fold(0.0, f64::max);
        eprintln!(
            "{} of 20 ran; RMS of the worse camera's f error {rms:.3} %, worst {worst:.3} %",
            errs.len()
        );
    }

    /// The Cramer-Rao bound of the focal length for one rig motion: the marginal
    /// covariance of the bundle adjustment at the true state with exact observations and
    /// the given noise (the adjustment starts at its minimum, so the covariance is
    /// `sigma^2 (J^T J)^-1` at the truth). Returns (sigma of left f in %, of left k1 if
    /// `distortion`).
    pub(crate) fn crb_one_motion(
        scenario: &Scenario,
        motion: &Isometry3<f64>,
        noise_px: f64,
        distortion: bool,
    ) -> (f64, f64) {
        use headalign_geometry::bundle::{BundleOptions, RobustLoss, bundle_adjust};
        let mut head = SimulatedHead::new(scenario.clone()).unwrap();
        let enc = head.encoders();
        let (wl0, wr0) = head.scene_from_cameras(&enc);
        let c0 = head.exact_capture(&enc);
        head.set_world_from_robot(*motion);
        let (wl1, _) = head.scene_from_cameras(&enc);
        let c1 = head.exact_capture(&enc);
        let index: BTreeMap<u64, usize> =
            head.scene_points().iter().enumerate().map(|(i, (t, _))| (*t, i)).collect();
        let points: Vec<Point3<f64>> = head.scene_points().iter().map(|(_, p)| wl0.inverse() * p).collect();
        let mut obs = Vec::new();
        for (view, c) in [&c0, &c1].into_iter().enumerate() {
            for (side, list) in [(Side::Left, &c.left), (Side::Right, &c.right)] {
                for o in list {
                    obs.push(BundleObservation { point: index[&o.track], view, side, pixel: o.pixel });
                }
            }
        }
        let t = head.truth();
        let state = RigState {
            left: t.left,
            right: t.right,
            left_distortion: Distortion::default(),
            right_distortion: Distortion::default(),
            right_from_left: wr0.inverse() * wl0,
            motions: Motions::Free { ref_from_cam: vec![Isometry3::identity(), wl0.inverse() * wl1] },
            points,
        };
        let options = BundleOptions {
            robust: RobustLoss::None,
            zero_skew: true,
            square_pixels: true,
            estimate_distortion: distortion,
            angle_prior_sigma: None,
            noise_sigma_px: Some(noise_px),
            ..BundleOptions::default()
        };
        let r = bundle_adjust(&state, &obs, &options).unwrap();
        let c = &r.covariance;
        (100.0 * c.sigma("left.fx").unwrap_or(f64::NAN) / t.left.fx, c.sigma("left.k1").unwrap_or(f64::NAN))
    }

    /// The scene of the bound experiments: 400 points, no outliers, two distinct cameras.
    fn bound_scenario(seed: u64) -> Scenario {
        Scenario {
            seed,
            points: 400,
            outlier_fraction: 0.0,
            left: Intrinsics::new(700.0, 700.0, 390.0, 284.0),
            right: Intrinsics::new(705.0, 705.0, 380.0, 290.0),
            ..Scenario::default()
        }
    }

    /// The Cramer-Rao bound per seed of the one-general-motion session:
    /// `cargo test --release -p headalign --lib calibrate::tests::general_motion_bound -- --ignored --nocapture`.
    #[test]
    #[ignore = "experiment: prints the bound over 20 seeds"]
    fn general_motion_bound() {
        for seed in 1..=20 {
            let scenario = bound_scenario(seed);
            let (sf, _) = crb_one_motion(&scenario, &general_rig_motion(), 0.5, false);
            let (sfd, sk) = crb_one_motion(&scenario, &general_rig_motion(), 0.5, true);
            eprintln!("seed {seed}: CRB f {sf:.3} %, with k1 k2: f {sfd:.3} % k1 {sk:.4}");
        }
    }

    #[test]
    #[ignore = "experiment"]
    fn general_motion_grid() {
        let first: u64 = std::env::var("FIRST").ok().and_then(|s| s.parse().ok()).unwrap_or(1);
        let last: u64 = std::env::var("LAST").ok().and_then(|s| s.parse().ok()).unwrap_or(20);
        let axes = [
            ("obl", Vector3::new(0.8, -1.0, 0.3)),
            ("vert", Vector3::new(0.0, -1.0, 0.0)),
            ("vert+x", Vector3::new(0.3, -1.0, 0.0)),
            ("vert+z", Vector3::new(0.0, -1.0, 0.3)),
        ];
        for (name, axis_dir) in axes {
            for (angle, along) in
                [(20.0, 0.3), (25.0, 0.3), (30.0, 0.3), (25.0, 0.2), (30.0, 0.2), (30.0, 0.4)]
            {
                let mut out = Vec::new();
                for seed in first..=last {
                    let scenario = bound_scenario(seed);
                    let axis = Line::new(Unit::new_normalize(axis_dir), Point3::new(0.0, -1.2, 0.0));
                    let r = rotation_about_line(&axis, f64::to_radians(angle));
                    let m = Isometry3::from_parts(
                        (r.translation.vector + axis.direction.into_inner() * along).into(),
                        r.rotation,
                    );
                    let (sf, _) = crb_one_motion(&scenario, &m, 0.5, false);
                    out.push(sf);
                }
                let mut sorted = out.clone();
                sorted.sort_by(f64::total_cmp);
                let n = sorted.len();
                eprintln!(
                    "{name} {angle} deg {along} m: median {:.3} %, 90th {:.3} %, worst {:.3} %, above 0.5 %: {}",
                    sorted[n / 2],
                    sorted[n * 9 / 10],
                    sorted[n - 1],
                    out.iter().filter(|v| **v > 0.5).count()
                );
            }
        }
    }

    /// One point-mode view per `(name, encoders)`, captured after moving there.
    fn capture_views(head: &mut SimulatedHead, at: &[(&str, Encoders)]) -> Vec<View> {
        at.iter()
            .map(|(name, enc)| {
                head.move_to(enc).unwrap();
                View { name: (*name).into(), capture: head.capture().unwrap() }
            })
            .collect()
    }

    /// Two head rotations about different axes need no constraint (noise-free: exact);
    /// the vergence view (rig changed) is left out and said so.
    #[test]
    fn two_rotations_calibrate_without_constraints() {
        let scenario = Scenario { noise_px: 0.0, outlier_fraction: 0.0, ..Scenario::default() };
        let mut head = SimulatedHead::new(scenario).unwrap();
        let e0 = head.encoders();
        let views = capture_views(
            &mut head,
            &[
                ("initial", e0),
                ("elevation", e0.moved(Joint::Elevation, 5.0)),
                ("pan", e0.moved(Joint::Pan, 5.0)),
                ("verge", Encoders { verge_left: e0.verge_left + 3.0, ..e0 }),
            ],
        );
        let cal = calibrate_rig(&views, &CalibrateOptions::default()).unwrap();
        let (st, t) = (&cal.bundle.state, head.truth());
        // 1e-4 % and 1e-3 px: noise-free, the adjustment converges to rounding.
        assert!(f_err_pct(&st.left, &t.left) < 1e-4, "{:?} vs {:?}", st.left, t.left);
        assert!((st.left.fy - t.left.fy).abs() < 1e-3 && (st.right.fx - t.right.fx).abs() < 1e-3);
        assert_eq!(cal.report.views, ["initial", "elevation", "pan"]);
        assert!(cal.report.skipped[0].contains("verge"));
    }

    /// A scene that is one plane (every point on z = 3 m) is refused by the scene-depth
    /// check, naming the views and the degeneracy.
    #[test]
    fn planar_scene_is_named() {
        let k = Intrinsics::new(700.0, 700.0, 384.0, 288.0);
        let right_from_left = Isometry3::translation(-0.25, 0.0, 0.0);
        let motion = headalign_sim::rigmotion::screw_motion(Vector3::new(0.8, -1.0, 0.3), 10.0, 0.2);
        let view = |name: &str, cam_from_world: Isometry3<f64>| {
            let (mut left, mut right) = (Vec::new(), Vec::new());
            for i in 0..400u64 {
                let p = Point3::new(
                    -1.5 + 3.0 * ((i * 37) % 100) as f64 / 100.0,
                    -1.0 + 2.0 * (i / 20) as f64 / 20.0,
                    3.0,
                );
                let pc = cam_from_world * p;
                if let (Some(l), Some(r)) = (k.project(&pc), k.project(&(right_from_left * pc))) {
                    left.push(TrackObservation { track: i, pixel: l });
                    right.push(TrackObservation { track: i, pixel: r });
                }
            }
            View {
                name: name.into(),
                capture: StereoCapture { encoders: Encoders::default(), image_size: [768, 576], left, right },
            }
        };
        let views = [view("a", Isometry3::identity()), view("b", motion.inverse())];
        let e = calibrate_rig(&views, &CalibrateOptions::default()).unwrap_err().to_string();
        assert!(e.contains("one plane") && e.contains("'a'") && e.contains("'b'"), "{e}");
        assert!(require_depth(&views, &CalibrateOptions::default()).is_err());
    }

    /// Known lens distortion (barrel, k1 = -0.2, k2 = 0.05, as a lens file would give it)
    /// is removed before self-calibration: noise-free, K comes out exact; ignoring the
    /// lens costs percent.
    #[test]
    fn known_distortion_is_removed() {
        let mut scenario = Scenario { noise_px: 0.0, outlier_fraction: 0.0, ..Scenario::default() };
        scenario.render.distortion = headalign_sim::RadialDistortion { k1: -0.2, k2: 0.05 };
        let mut head = SimulatedHead::new(scenario).unwrap();
        let e0 = head.encoders();
        let views = capture_views(
            &mut head,
            &[
                ("initial", e0),
                ("elevation", e0.moved(Joint::Elevation, 5.0)),
                ("pan", e0.moved(Joint::Pan, 5.0)),
            ],
        );
        let t = head.truth().clone();
        let lens = |k: Intrinsics| LensModel { k, distortion: Distortion::radial(-0.2, 0.05) };
        let undistorted = undistort_views(&views, &[lens(t.left), lens(t.right)]);
        let cal = calibrate_rig(&undistorted, &CalibrateOptions::default()).unwrap();
        // 1e-4 %: noise-free (undistortion is exact to 1e-9 px).
        assert!(f_err_pct(&cal.bundle.state.left, &t.left) < 1e-4, "{:?}", cal.bundle.state.left);
        let ignored = calibrate_rig(&views, &CalibrateOptions::default());
        let off = ignored.map_or(f64::INFINITY, |c| f_err_pct(&c.bundle.state.left, &t.left));
        assert!(off > 0.5, "ignoring the lens only cost {off} %");
    }

    #[test]
    fn too_few_views_is_an_error() {
        assert!(calibrate_rig(&[], &CalibrateOptions::default()).is_err());
    }

    /// A failure of the seeded stages is retried with the next seeds, and when every seed
    /// fails the error says how many were tried, how many tracks the views share and what
    /// to record instead. Here the moved view's track ids are rotated among its stereo
    /// pairs except for 8, so every pair is a good stereo match but at most 8 are the same
    /// point as in the reference: no 3D homography has the 12 inliers it needs, whatever
    /// the seed.
    #[test]
    fn seeded_failures_are_retried_and_named() {
        let (mut views, _, _) = general_session(3, 0.5);
        let ids: std::collections::BTreeSet<u64> = views[1].capture.left.iter().map(|o| o.track).collect();
        let both: Vec<u64> =
            views[1].capture.right.iter().map(|o| o.track).filter(|t| ids.contains(t)).collect();
        let moved = &both[8..];
        let relabel: BTreeMap<u64, u64> =
            moved.iter().zip(moved.iter().cycle().skip(1)).map(|(&a, &b)| (a, b)).collect();
        let capture = &mut views[1].capture;
        for o in capture.left.iter_mut().chain(capture.right.iter_mut()) {
            if let Some(&t) = relabel.get(&o.track) {
                o.track = t;
            }
        }
        for (restarts, tried) in [(3, "4 estimation seeds"), (0, "1 estimation seeds")] {
            let options = CalibrateOptions {
                zero_skew: true,
                square_pixels: true,
                restarts,
                ..CalibrateOptions::default()
            };
            let e = calibrate_rig(&views, &options).unwrap_err().to_string();
            assert!(
                e.contains(tried) && e.contains("tracks seen in the reference") && e.contains("overlap"),
                "{e}"
            );
        }
        // The intact session needs no restart and reports the seed it used.
        let (views, _, _) = general_session(3, 0.5);
        let options =
            CalibrateOptions { zero_skew: true, square_pixels: true, ..CalibrateOptions::default() };
        let c = calibrate_rig(&views, &options).unwrap();
        assert_eq!((c.report.restarts, c.report.estimation_seed), (0, options.estimation.seed));
    }
}
