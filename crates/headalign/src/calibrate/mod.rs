//! Self-calibration of a stereo rig from rigid motions of the whole rig (head rotations,
//! robot drives, a hand-held rig): both cameras' intrinsics, the rig's relative pose and
//! every view's motion, with covariances (issue 6 part 2; paper section 3.1; Hartley &
//! Zisserman 2nd ed., sections 10.4, 19.5-19.6).
//!
//! Input: tracked point observations of stereo views (the first is the reference), the
//! rig fixed between them (views whose vergence readings differ from the first view's are
//! left out: their rig changed). Views that do not all overlap the first (hundreds of
//! views of a moving rig, disconnected pieces) take the sequence chain instead
//! ([`calibrate_sequence`]: keyframes, a view graph, one gauge per segment);
//! [`track_views`] tracks a folder of images for the one or the other ([`Route`]). The
//! reference chain, each step a pure function of the previous:
//! 1. a scene-depth check per view: if one plane homography explains nearly all stereo
//!    matches of a view (default 90 % within 2 px), its projective reconstruction is a
//!    plane and no 3D homography relates it to another view: the view is left out, and if
//!    no moved view remains (a chessboard) the error names the degeneracy;
//! 2. one fundamental matrix from the stereo matches of all views (DEGENSAC, Sampson
//!    refinement), the quasi-Euclidean projective frame and optimal triangulation
//!    (as [`crate::verge_tilt`]);
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
//!    [`crate::verge_tilt`] (shared code);
//! 6. per start, an adjustment over every point seen at least twice (also the points
//!    seen by one stereo view only), robust first, then least squares on the re-selected
//!    observations (`rig_bundle::every_point_pass`); the start with the lower truncated cost over
//!    all observations is kept;
//! 7. the report: each motion's screw after the adjustment (if none turned by
//!    `min_rotation_deg` there the run fails: a noisy 3D homography can pass step 4's
//!    test although the rig never turned), the focal lengths' sigmas, and warnings about
//!    data that determine the calibration poorly.
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
//! everything after is pinhole. Alternatively [`CalibrateOptions::lens`] adds a lens
//! model's coefficients (radial-tangential or equidistant; `k1, k2` by default, see
//! [`CalibrateOptions::lens_terms`]) of each camera to the final adjustment (step 5;
//! [`BundleOptions::estimate_distortion`](headalign_geometry::bundle::BundleOptions)), or
//! chooses the model and its terms ([`LensChoice::Auto`], [`crate::rig::lens_choice`]):
//! steps 1-4 then see distorted pixels (a pinhole approximation, fine for the moderate
//! distortion of the start), and the result is in `bundle.state.{left,right}_distortion`
//! with sigmas `left.k1` ... in the covariance. The chain also runs on pixels undistorted
//! by a lens chosen on a grid of corner displacements (`two_pass`); that run's result is a
//! third start of the first chain's adjustment (the lowest truncated cost wins: the
//! linear and rigid starts on distorted pixels can end in another minimum of the f-k1
//! valley), and it is reported itself when the first chain fails or ends outside the
//! plausible focal range (a strong lens in 10 deg views). With
//! small rotations `k1` correlates with the focal length: without it a barrel lens biases
//! `f` (see README); the focal-length and lens sigmas are widened to the bootstrap spread
//! over tracks (`lens_sigmas`, [`CalibrateReport::lens_sigmas`]).
//!
//! Pitfalls: a pure rotation, or a planar motion (translation perpendicular to the axis),
//! fixes a pencil of planes: with one such motion the plane at infinity is undetermined
//! (an error naming it). One rotation also leaves the conic a pencil: it needs at least
//! zero skew. A planar scene is degenerate for projective reconstruction (step 1). The
//! conditioning of one general motion depends on its translation along the axis: report
//! `plane_conditioning` and trust the sigmas.
//!
//! Code layout, one file per step: `depth` (step 1), `rig_stereo` (step 2, and the rig
//! from known intrinsics), `motion` (step 3), `bundle_starts` (the point set and the two
//! starts: step 4 and the rigid start), `rig_bundle` (steps 5-6), `report` (step 7),
//! `two_pass` (the start of a lens estimate when the chain fails), `lens_auto`
//! ([`LensChoice::Auto`] over either chain), `fit_checks` (the residual structure and
//! image-noise checks applied to a calibration), `lens_sigmas` (the bootstrap of the lens
//! and focal sigmas), `density` (the corner density of self-calibration from images),
//! `fits` (steps 2-3 fitted once when runs of several lens models repeat them); the
//! lens models, their choice and the checks themselves are [`crate::rig`]'s, shared with
//! the verge/tilt route;
//! `calibrate_once` chains them; `views` is the one entry point for a list of stereo
//! views ([`calibrate_views`]: rig selection, known lenses, corner density). Sequences: `route` (which tracking and chain a folder
//! gets), `graph` (keyframes, view graph, segments, spanning trees), `sequence` (the
//! sequence chain, reusing the steps above).

mod bundle_starts;
mod density;
mod depth;
mod fit_checks;
mod fits;
mod graph;
mod lens_auto;
pub mod lens_sigmas;
mod motion;
mod report;
mod rig_bundle;
mod rig_stereo;
mod route;
mod sequence;
#[cfg(test)]
mod tests;
mod two_pass;
pub mod views;
mod wide;

use headalign_geometry::GeometryError;
use headalign_geometry::bundle::{BundleObservation, BundleResult};
use headalign_geometry::camera::Intrinsics;
use headalign_geometry::distortion::DistortionTerms;
use headalign_geometry::selfcal::IntrinsicConstraints;
use serde::Serialize;

pub use density::{
    DISAGREEMENT_SIGMAS, Density, DensityReport, DensityTrial, disagreement_sigmas, prefer_denser,
};
pub use depth::{PlaneCheck, RigChoice, check_planarity, require_depth, select_rig};
pub use fit_checks::{check_against_images, image_noise_check};
pub use graph::{END_FLOW_FRACTION, SegmentReport, SequenceOptions};
pub use report::weak_data;
pub use rig_stereo::{KnownIntrinsicsRig, rig_from_known_intrinsics};
pub use route::{
    REFERENCE_ROUTE_MAX_VIEWS, Route, SEQUENCE_RANSAC_MIN_ITERATIONS, TrackedViews, TrackingProgress,
    calibrate_tracked, track_views, track_views_reporting,
};
pub use sequence::{RANSAC_PAIRS, SequenceReport, calibrate_sequence};
pub use views::{CalibrateViewsOptions, StereoViews, ViewsCalibration, ViewsProgress, calibrate_views};

use crate::error::AlignError;
use crate::observations::View;
pub use crate::rig::{
    FailedCandidate, ImageNoiseCheck, LensCandidate, LensChoice, LensModel, LensSelection, LensSpec,
    MeasuredVariances, image_noise, lens_terms, read_opencv_lenses, residuals, undistort_views,
};
use crate::verge_tilt::EstimationOptions;

/// Options of [`calibrate_rig`].
#[derive(Debug, Clone)]
pub struct CalibrateOptions {
    /// F, 3D homography RANSAC, bundle adjustment, re-selection, minimum tracks and seed
    /// (defaults of [`EstimationOptions`]; the bundle's intrinsic constraints are set from
    /// the three flags below, and its angle prior is unused: the poses are free).
    pub estimation: EstimationOptions,
    /// Hold both skews at zero (default true: real cameras have none, and OpenCV, Kalibr
    /// and COLMAP fix it; false estimates it).
    pub zero_skew: bool,
    /// `fx = fy` in both cameras (default false).
    pub square_pixels: bool,
    /// Hold both principal points at the image centre (default false).
    pub fix_principal_point: bool,
    /// The lens model the adjustment estimates for each camera (default
    /// [`LensChoice::Pinhole`]: no distortion, or a known lens removed beforehand with
    /// [`undistort_views`]); [`LensChoice::Auto`] chooses the model and its terms by the
    /// criterion of [`crate::rig::lens_choice`] and reports it (the CLI's default for images).
    pub lens: LensChoice,
    /// Which coefficients of the model are estimated (default
    /// [`DistortionTerms::Radial2`]: `k1, k2`); with [`LensChoice::Auto`] the richest
    /// terms its candidates may have ([`crate::rig::LensSpec::candidates`]:
    /// [`DistortionTerms::Full5`] lets it choose among all of them).
    pub lens_terms: DistortionTerms,
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
    /// Keyframes and links of the sequence route ([`calibrate_sequence`]; defaults of
    /// [`SequenceOptions`]).
    pub sequence: SequenceOptions,
}

impl Default for CalibrateOptions {
    fn default() -> Self {
        Self {
            estimation: EstimationOptions::default(),
            zero_skew: true,
            square_pixels: false,
            fix_principal_point: false,
            lens: LensChoice::Pinhole,
            lens_terms: DistortionTerms::Radial2,
            min_rotation_deg: 0.5,
            planar_threshold_px: 2.0,
            planar_fraction: 0.98,
            warn_focal_sigma_pct: 0.5,
            warn_plane_fraction: 0.85,
            restarts: 3,
            sequence: SequenceOptions::default(),
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
        self.sequence.validate()
    }

    fn constraints(&self) -> IntrinsicConstraints {
        IntrinsicConstraints {
            zero_skew: self.zero_skew,
            square_pixels: self.square_pixels,
            principal_point_at_origin: self.fix_principal_point,
        }
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
    /// The view the motion is relative to when it is not the first view: a sequence's
    /// segment gauge ([`calibrate_sequence`]); absent otherwise.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub relative_to: Option<String>,
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
    /// The start the adjustment kept: "linear", "rigid", or "lens grid" (the lens-grid
    /// run's result, `two_pass`).
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
    /// How the lens model was chosen ([`LensChoice::Auto`]; `None` otherwise).
    pub lens_selection: Option<LensSelection>,
    /// Structure in the final residuals by image radius and region ([`residuals`]), and
    /// the sigma widening it caused.
    pub residual_structure: Option<residuals::ResidualStructure>,
    /// The bootstrap widening of the focal-length and lens sigmas when a lens model is
    /// estimated ([`lens_sigmas`]); absent otherwise.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lens_sigmas: Option<lens_sigmas::LensSigmaReport>,
    /// The reprojection residuals against the localisation noise measured from the
    /// images ([`image_noise`]), or why that check was skipped.
    pub image_noise: Option<ImageNoiseCheck>,
    /// The sequence route's segments and keyframes ([`calibrate_sequence`]); absent on
    /// the reference route.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sequence: Option<SequenceReport>,
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

/// Self-calibrate the rig from its views (module docs). Views whose vergence readings
/// differ from the first view's are left out (the rig changed).
pub fn calibrate_rig(views: &[View], options: &CalibrateOptions) -> Result<MotionCalibration, AlignError> {
    options.validate()?;
    let mut result = if options.lens == LensChoice::Auto {
        lens_auto::calibrate_choosing_lens(views, options)?
    } else {
        two_pass::calibrate_two_pass(views, options, None)?
    };
    widen_lens_sigmas(&mut result, options);
    fit_checks::check_and_widen(&mut result);
    result.report.image_noise = Some(ImageNoiseCheck::skipped(image_noise::NO_IMAGES));
    Ok(result)
}

/// The bootstrap widening of the focal-length and lens sigmas ([`lens_sigmas`]) of a
/// result of `options`, for the model estimated: the options' own, or the one
/// [`LensChoice::Auto`] chose (none for the pinhole).
fn widen_lens_sigmas(result: &mut MotionCalibration, options: &CalibrateOptions) {
    crate::timing::time(crate::timing::Stage::Covariance, || {
        let (lens, lens_terms) = match (&options.lens, &result.report.lens_selection) {
            (LensChoice::Auto, Some(s)) => (s.spec.choice(), s.spec.terms),
            (lens, _) => (*lens, options.lens_terms),
        };
        let estimated = CalibrateOptions { lens, lens_terms, ..options.clone() };
        result.report.lens_sigmas = lens_sigmas::bootstrap_lens_sigmas(result, &estimated);
    })
}

/// [`calibrate_rig`] with a fixed lens model: the chain, retried with the next
/// estimation seeds when it fails in a seeded stage.
fn calibrate_with_restarts(
    views: &[View],
    options: &CalibrateOptions,
) -> Result<MotionCalibration, AlignError> {
    with_restarts(options, |o, seeded| calibrate_once(views, o, seeded))
}

/// Run a chain (`once`: [`calibrate_once`], or the sequence's) with the options' seed, and
/// again with the next seeds while it fails in a seeded stage
/// ([`CalibrateOptions::restarts`]); the report names the seed that gave the result.
fn with_restarts(
    options: &CalibrateOptions,
    once: impl Fn(&CalibrateOptions, &mut Option<Seeded>) -> Result<MotionCalibration, AlignError>,
) -> Result<MotionCalibration, AlignError> {
    let mut failures = Vec::new();
    for restart in 0..=options.restarts {
        let mut o = options.clone();
        o.estimation.seed = options.estimation.seed.wrapping_add(restart as u64);
        let mut seeded = None;
        match once(&o, &mut seeded) {
            Ok(mut c) => {
                c.report.restarts = restart;
                if restart > 0 {
                    c.report.warnings.push(format!(
                        "the run with estimation seed {} failed ({}); estimation seed {} gave this result: the robust stages are close to their limits (few tracks common to the views?)",
                        options.estimation.seed,
                        failures.first().map_or(String::new(), |(_, e, _): &(u64, AlignError, Seeded)| e.to_string()),
                        o.estimation.seed
                    ));
                }
                return Ok(c);
            }
            Err(error) => match seeded {
                Some(s) => failures.push((o.estimation.seed, error, s)),
                None => return Err(error),
            },
        }
    }
    Err(restarts_failed(&failures))
}

/// The error of [`with_restarts`] when every estimation seed failed: one line,
/// the likely causes first, then the first seed's failure in short (its last clause) and
/// the tracks it had.
fn restarts_failed(failures: &[(u64, AlignError, Seeded)]) -> AlignError {
    let first = failures.first().map_or(String::new(), |(seed, e, s)| {
        let text = e.to_string();
        let last = text.rsplit(": ").next().unwrap_or(&text).to_string();
        format!(
            "; seed {seed}: {last}, {} tracks in the reference and a moved view, {} fitting its 3D homography",
            s.common_tracks, s.fitting
        )
    });
    AlignError::Geometry {
        step: "self-calibration".into(),
        cause: GeometryError::Degenerate(format!(
            "failed with {} estimation seeds: too few points seen in both views, points near one plane, or a lens model that does not fit (try --lens auto){first}",
            failures.len(),
        )),
    }
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

/// One run of the chain with the options' estimation seed ([`calibrate_rig`]): the steps
/// of the module docs in order, each a function of its own file.
fn calibrate_once(
    views: &[View],
    options: &CalibrateOptions,
    seeded: &mut Option<Seeded>,
) -> Result<MotionCalibration, AlignError> {
    calibrate_once_from(views, options, seeded, None, None, None)
}

/// [`calibrate_once`] with an optional lens start ([`two_pass`]): steps 2-4 then run on
/// the rig views' pixels undistorted by its lenses, the adjustment on the original pixels
/// from starts that carry its distortion; an optional third start of the adjustment,
/// another run's result `other` (its cameras, lenses and motions; [`two_pass`]); and the
/// steps 2-3 other runs on the same views fitted (`fits`, [`fits`]).
fn calibrate_once_from(
    views: &[View],
    options: &CalibrateOptions,
    seeded: &mut Option<Seeded>,
    lens_start: Option<&two_pass::LensStart>,
    other: Option<&headalign_geometry::bundle::RigState>,
    fits: Option<&fits::ChainFits>,
) -> Result<MotionCalibration, AlignError> {
    // 1. The views of the rig.
    let depth::RigViews { rig, skipped, planarity, image_size } = depth::select_views(views, options)?;
    let [w, h] = image_size;
    // The pixels' conditioning and the rigid start's K: the lens start's (the image-size
    // guess for the narrow models' grid, the grid lens's own K for a wide model).
    let k0 = lens_start.map_or_else(|| Intrinsics::rough_guess(w, h), |l| l.chain[0].k);
    let est = &options.estimation;
    // 2-3. F from all views, frame, triangulation; 3D homographies from the reference.
    let fitted = fit_stereo_motions(&rig, &k0, options, seeded, lens_start, fits)?;
    let (stereo, motions) = (&fitted.stereo, fitted.motions.as_slice());
    // The point set and the observations (as in estimate).
    let points = bundle_starts::point_set(&rig, &stereo.recon, motions);
    let problem = bundle_starts::Problem {
        recon: &stereo.recon,
        point_tracks: &points.point_tracks,
        origin_slot: &points.origin_slot,
        min_tracks: est.min_tracks,
    };
    // 4. The linear self-calibration, and the rigid start.
    let linear = bundle_starts::linear_start(motions, &stereo.frame, &k0, &problem, options);
    let rigid = bundle_starts::rigid_start(motions, &stereo.frame, &k0, &problem, options);
    let (linear_k, linear_error) = match bundle_starts::linear_summary(&linear.state) {
        // With a lens estimated and no lens start, the 3D homographies of distorted pixels
        // are not conjugate to rigid motions and their angle readings (from the trace)
        // can clamp to 0 deg: the rigid start carries the run, and the adjusted motions
        // decide whether the rig turned (step 7).
        Err(AlignError::MissingMotion(m)) if options.lens.kind().is_some() && lens_start.is_none() => {
            (None, Some(m))
        }
        other => other?,
    };
    // 5-6. The adjustment from both starts (on the original pixels: the stereo matches'
    // pixels too, for the points the adjustment triangulates itself).
    let (start_lens, raw_recon) = match lens_start {
        Some(l) => (Some(l.distortion), Some(two_pass::original_pixels(&stereo.recon, &rig))),
        None => (None, None),
    };
    let recon = raw_recon.as_deref().unwrap_or(&stereo.recon);
    let adjusted =
        rig_bundle::adjust_starts([linear.state, rigid], &points, recon, options, start_lens, other)
            .inspect_err(|_| *seeded = motion::weakest_motion(motions))?;
    // 7. The report: final motions, the rotation test, sigmas, warnings.
    let motion_reports = report::adjusted_motions(motions, &linear.used, &adjusted.last.state);
    report::require_rotation(motions, &motion_reports, options)?;
    let report = report::chain_report(
        report::ChainRun {
            views: rig.iter().map(|v| v.name.clone()).collect(),
            skipped,
            planarity,
            stereo,
            motions: motion_reports,
            motions_fitted: motions.len(),
            plane_conditioning: linear.plane_conditioning,
            conic_uniqueness: linear.conic_uniqueness,
            linear_k,
            linear_error,
            adjusted: &adjusted,
            points: points.point_tracks.len(),
            sequence: None,
        },
        options,
    );
    Ok(MotionCalibration {
        bundle: adjusted.last,
        point_tracks: points.point_tracks,
        observations: adjusted.observations,
        image_size: [w, h],
        report,
    })
}

/// Steps 2-3 of [`calibrate_once_from`] on the rig views `rig` conditioned by `k0`: those
/// the lens grid fitted with this seed under the lens start, or (no lens start) those
/// another run on the same views fitted with the same inputs (`fits`), or fitted here (on
/// the pixels undistorted by the lens start's lenses, if any).
fn fit_stereo_motions(
    rig: &[View],
    k0: &Intrinsics,
    options: &CalibrateOptions,
    seeded: &mut Option<Seeded>,
    lens_start: Option<&two_pass::LensStart>,
    fits: Option<&fits::ChainFits>,
) -> Result<std::sync::Arc<two_pass::GridFit>, AlignError> {
    let est = &options.estimation;
    if let Some(f) = lens_start.and_then(|l| l.fitted.as_ref()).filter(|f| f.seed == est.seed) {
        return Ok(f.clone());
    }
    let mut fit = || {
        let chain_rig = lens_start.map(|l| l.chain_views(rig));
        let chain: &[View] = chain_rig.as_deref().unwrap_or(rig);
        let stereo = rig_stereo::stereo_geometry(chain, k0, est)?;
        let motions = motion::fit_motions(chain, &stereo.recon, &stereo.frame, options, seeded)?;
        Ok(two_pass::GridFit { seed: est.seed, stereo, motions })
    };
    match fits.filter(|_| lens_start.is_none()) {
        Some(kept) => kept.get_or_fit(fits::FitKey::of(options, k0), fit),
        None => fit().map(std::sync::Arc::new),
    }
}
