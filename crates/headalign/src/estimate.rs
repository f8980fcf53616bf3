//! The verge/tilt estimation core (DESIGN.md section 2 steps 1-4; paper section 3.2
//! steps 1-4): from stereo views related by pan and elevation rotations of the head,
//! recover both cameras' intrinsics, the rig, the pan and elevation axes and the scene,
//! with covariances.
//!
//! Chain, each step a pure function of the previous:
//! 1. classify views by which joints moved relative to the first ("reference") view;
//! 2. one fundamental matrix from the stereo matches of all rig views (the rig does not
//!    change while only pan and elevation move), RANSAC + Sampson refinement;
//! 3. a quasi-Euclidean projective frame ([`headalign_geometry::frame`]) and optimal
//!    triangulation of every stereo match;
//! 4. per rotated view, quadruplets screened by plane homographies (a head rotation maps
//!    each image almost by `K R K^-1`), then the 3D homography: polished on symmetric
//!    transfer error from a rigid or DLT start (the 5-point DLT RANSAC as fallback), and
//!    guided re-selection of quadruplets until the set is stable;
//! 5. five starts for the adjustment: the linear self-calibration chain (plane at
//!    infinity, `w*`, `K_L`, the right camera, motions); each camera's `K` by
//!    rotating-camera self-calibration from its plane homographies with the rig from
//!    `E`; a rough guess; with those `K`s, the rig pose estimated directly (5 dof,
//!    [`headalign_geometry::essential`]), not from `F`, whose epipole nearly parallel
//!    cameras and walls leave ill-determined; and the same from the rough guess and the
//!    stereo-head prior (baseline along x) alone. Each is screened by a short adjustment, the best MSAC score
//!    over one common set of observations wins (not the RMS: each start fits its own subset);
//! 6. the rig bundle adjustment, motions modelled as rotations about two fixed axes with
//!    the commanded encoder differences as priors, robust loss; re-selection of every
//!    observation by its residual; a final adjustment; points at implausible depth (wrong
//!    tracks) removed and adjusted once more; with [`EstimationOptions::depth_step`]
//!    (image mode) the tracks at depth steps are left out too ([`near_depth_step`]);
//! 7. the maximum-likelihood pass: the Huber loss of step 6 is robust but not the
//!    likelihood of Gaussian pixel noise (with its fixed 2 px scale, at 2-3 px of noise
//!    most inliers are down-weighted), and its angle prior is weighted as if the noise
//!    were 1 px (at 3 px the prior is then 9 times too weak against the pixels). So the
//!    noise is estimated from the robust solution (median residual norm), the
//!    observations within `reselect_sigmas` of it are kept, and plain least squares runs
//!    with the prior weighted by that noise; then the observations are re-classified at
//!    the least-squares solution (studentised residuals within `reselect_sigmas` of the
//!    unbiased, truncation-corrected noise estimate) and the adjustment repeated until the
//!    set is stable: the ML estimate under the Gaussian model, whose covariance is the one
//!    reported. Measured effect in `docs/efficiency.md` (RMS error / Cramer-Rao bound).
//!    With [`EstimationOptions::image_border`] these passes model the image border: an
//!    observation near it was kept only if its noise pointed inward, so its residual is
//!    taken against the expected measurement of the truncated Gaussian. A point seen only
//!    once by one camera takes its depth from that observation alone, so a wrong one is
//!    fitted exactly at a wrong depth; such a point is left out when that depth is off its
//!    neighbours' by more than its own stereo noise and the scene's roughness allow
//!    ([`EstimationOptions::lone_depth_gate`], [`lone_depth_outliers`]). All of them can
//!    be left out ([`EstimationOptions::min_camera_observations`], off by default), but
//!    the points go with their information.
//! 8. the depth-reversed restart: the scene is far against the baseline, so the rig with
//!    its baseline reversed (x component, or all of it) is a second least-squares minimum
//!    with the points' depth order reversed; the least squares is restarted from it (points
//!    re-triangulated) and the lower cost wins ([`EstimationOptions::reversed_rig_restart`];
//!    seed 39 at 2-3 px had right cx 6 sigma off in the wrong minimum); likewise from the
//!    baseline with its y and z components reversed (a forward component's sign is weakly
//!    determined too: fig5 seeds 1119, 1130, 1211 at 3 px, `docs/ratio-tail.md`); and, when
//!    the estimated baseline is more than 45 deg from the right camera's x axis (no stereo
//!    head's cameras are so placed), from the baseline along that axis, both ways
//!    (calibration seed 368 at 3 px had it along the optical axis, left fx 3.7 sigma off);
//! 9. the depth-scale profile of the covariance ([`profile_depth_scale`],
//!    [`EstimationOptions::depth_profile`]): the scene's distance in baselines is the badly
//!    determined direction and the linearised sigmas follow it, so each camera sigma is the
//!    largest of those at the estimate and at the estimate re-adjusted with the depth scale
//!    held one sigma either side; the estimate itself is unchanged. On by default: measured,
//!    it mends the principal points' and right.fy's coverage at 3 px (option docs).
//! 10. optionally, the bootstrap of the covariance ([`bootstrap_covariance`],
//!     [`EstimationOptions::bootstrap`], off by default): the maximum-likelihood pass
//!     re-run on point tracks drawn with replacement (and the encoder readings redrawn
//!     from the angle prior), each camera sigma the larger of the linearised one and the
//!     replicates' spread. Where the likelihood is not quadratic (near scenes at a few
//!     pixels) the linearised sigmas are too small; this mends that at about one
//!     warm-started adjustment per replicate.
//!
//! Pitfalls: with 3 deg rotations the linear chain is noisy (focal lengths off by tens of
//! percent are common), hence several starts; a point can start behind the cameras when
//! the frame's plane at infinity cuts a deep scene, hence re-triangulation after the first
//! adjustment; the stereo F decides the basin of everything after it (a wrong F, one
//! fitted to a dominant plane or stopped early by RANSAC, shifted the relative yaw against
//! depth and cost up to 7 % in focal length), hence DEGENSAC and at least 500 samples.
//! Reported sigmas are calibrated at 1 px: RMS z-scores 0.97-1.3 over 60 seeds with 10 %
//! outliers. Classifying the inliers once, at the robust solution, biased the noise
//! estimate 5 % low at 2-3 px (true inliers with 2-4 sigma errors were dropped); the
//! iterated classification at the least-squares solution fixes that (measured in
//! `docs/efficiency.md`, with the remaining heavy-tailed trials).
//!
//! Units: pixels for thresholds, radians inside, the scene in baselines (|t_rig| = 1)
//! (a known baseline only rescales the scene). Frames: everything in the reference view's left
//! camera frame ("ref").

use std::collections::{BTreeMap, HashMap, HashSet};

use headalign_geometry::bootstrap::{BootstrapOptions, bootstrap_spread};
use headalign_geometry::bundle::{
    BundleCheckpoint, BundleObservation, BundleOptions, BundleResult, Motions, RigState, RobustLoss, Side,
    bundle_adjust, bundle_adjust_at_depth_scale, bundle_adjust_with_checkpoint, log_depth_scale,
    residual_pixels, residual_pixels_at,
};
use headalign_geometry::camera::{Intrinsics, ProjectiveCamera, dehomogenise3};
use headalign_geometry::frame::{StereoFrame, quasi_euclidean_frame, relative_pose};
use headalign_geometry::fundamental::{FundamentalMatrix, estimate_fundamental};
use headalign_geometry::homography2d::Homography2Estimator;
use headalign_geometry::homography3d::{
    Homography3Estimator, Quadruplet, TransferModel, refine_transfer, symmetric_transfer_error,
};
use headalign_geometry::ransac::{Estimator, RansacOptions, ransac};
use headalign_geometry::registration::RigidFrameEstimator;
use headalign_geometry::selfcal::{decompose_camera, linear_self_calibration};
use headalign_geometry::so3::{Line, screw_from_isometry};
use headalign_geometry::triangulation::triangulate_optimal;
use headalign_platform::{Encoders, Joint, StereoCapture};
use nalgebra::{Isometry3, Matrix3, Point2, Point3, Vector3, Vector4};
use serde::Serialize;

use crate::error::{AlignError, StepContext};
use crate::observations::View;

/// A stereo match: track id, left pixel, right pixel.
pub(crate) type StereoMatch = (u64, Point2<f64>, Point2<f64>);
/// One view's reconstruction in the projective frame: track -> (X, left pixel, right pixel).
pub(crate) type Reconstruction = BTreeMap<u64, (Vector4<f64>, Point2<f64>, Point2<f64>)>;
/// The plane homographies (left, right) of one rotation.
type PlanePair = (Matrix3<f64>, Matrix3<f64>);

/// Encoder differences below this (degrees) count as "did not move": above the read jitter
/// of a joint at rest (a reading with Gaussian noise of [`ENCODER_SIGMA_DEG`] differs from
/// another by 0.014 deg RMS; 0.05 deg still failed 1 trial in 200 with "no view rotates the
/// pan joint alone"), far below any commanded rotation (1 deg and up).
pub const MOVED_DEG: f64 = 0.1;

/// Points farther than this many times the median point distance, or nearer than its
/// inverse, are treated as wrong tracks (a scene spans far less than a factor 100).
pub const DEPTH_RATIO: f64 = 10.0;

/// Observations a point needs to take part in the final adjustment (two views of both
/// cameras): with fewer, a wrong observation is absorbed by moving the point.
pub const MIN_POINT_OBSERVATIONS: usize = 4;

/// Iterations of the short adjustment that screens each initialisation.
pub const SCREEN_ITERATIONS: usize = 40;
/// Minimum iterations of the final adjustment (robust IRLS converges linearly).
pub const FINAL_ITERATIONS: usize = 300;

/// Default standard deviation of a commanded joint rotation, degrees: the resolution of a
/// typical head encoder. The prior on each rotation angle is what fixes the focal lengths
/// most strongly (a 3 deg rotation measured to 0.01 deg is 0.3 % of it).
pub const ENCODER_SIGMA_DEG: f64 = 0.01;

/// Options of [`estimate_rig`].
#[derive(Debug, Clone)]
pub struct EstimationOptions {
    /// RANSAC for F; threshold on Sampson distance (default 3 px: about 2 sigma of the
    /// distance at 1 px noise in both images) and at least 500 samples (default: the
    /// adaptive count, some 50 at 80 % inliers, assumes every clean sample gives the best
    /// model; with noise and a room of planes the best-supported F was missed in about
    /// one case in five, and a wrong F costs percent in the focal lengths).
    pub fundamental: RansacOptions,
    /// RANSAC for each 3D homography; threshold on the RMS symmetric transfer error over
    /// four images (default 4 px: the DLT homography transfers noisy triangulated points,
    /// so inlier errors are about twice the image noise).
    pub homography: RansacOptions,
    /// Threshold of the plane-homography screening of quadruplets, pixels (default 6: the
    /// image motion of a head rotation departs from a homography by the parallax of the
    /// axis offsets, about 3 px at 1.5 m for 3 deg, plus noise).
    pub prefilter_px: f64,
    /// The bundle adjustment (defaults of [`BundleOptions`], with the angle prior set to
    /// [`ENCODER_SIGMA_DEG`]).
    pub bundle: BundleOptions,
    /// After the first adjustment, observations whose residual exceeds this many robust
    /// standard deviations are dropped and the rest re-admitted (default 3.5).
    pub reselect_sigmas: f64,
    /// Minimum stereo matches / quadruplets / 3D points (default 12: a 3D homography
    /// needs 5; with 50 points and 10 % outliers 4 seeds in 100 had 18-19 quadruplets and
    /// failed at the former 20, and succeeded at 12).
    pub min_tracks: usize,
    /// Seed for every random choice (default 0).
    pub seed: u64,
    /// End with the maximum-likelihood pass (default true): plain least squares on the
    /// observations within `reselect_sigmas` of the robust solution, the angle prior
    /// weighted against the estimated pixel noise (module docs, step 7). Off, the result
    /// is the robust (Huber) adjustment with the prior weighted as if the noise were 1 px.
    pub final_least_squares: bool,
    /// Leave out a rotated rig view whose 3D homography cannot be estimated (too few
    /// tracks shared with the reference view, none consistent with a rotation, no fit)
    /// when the remaining views still contain a pan-only and an elevation-only rotation,
    /// instead of failing the whole estimate (default true). Each view left out is named
    /// with its reason in [`EstimationReport::dropped_views`]; its capture is untouched.
    /// Why: a large diagonal view of a 50-point scene can keep 11 usable tracks of the 12
    /// needed (1 trial in 150 with the procedure's own rotations) while the other nine
    /// views calibrate the head well.
    pub drop_weak_views: bool,
    /// After the maximum-likelihood pass, restart the least squares from the
    /// depth-reversed rig (`reversed_rig_restart`, module docs step 8) and keep the
    /// solution of lower cost (default true; needs `final_least_squares`).
    pub reversed_rig_restart: bool,
    /// Leave out the tracks at depth steps before the maximum-likelihood pass
    /// ([`near_depth_step`]; default `None`, off, also in image mode: see
    /// [`DepthStepGate::IMAGES`]). A corner where a near edge crosses the background is no
    /// fixed scene point, and its structured error moves the calibration coherently
    /// (the removed `examples/cluster_diag.rs`).
    pub depth_step: Option<DepthStepGate>,
    /// Profile the reported covariance along the scene's depth scale
    /// ([`profile_depth_scale`], module docs step 9; needs `final_least_squares`). Default
    /// `Some(`[`DepthProfile::DEFAULT`]`)`: ends at `z = 1` sigma of the depth scale,
    /// profiled when that sigma exceeds 0.01. Measured with `z = 1` (always profiled,
    /// ends run to convergence): `experiment calibration --only 1.5,3`, seeds 1001-1200
    /// and 2001-2080, every 95 % coverage 90-98 % (off: right.cx 88.0 % and right.fy 83.8 %
    /// at 3 px); with `z = 1.96` the focal lengths over-cover at 3 px (left.fx 99.0 %: each
    /// sigma takes the maximum over the two ends). The default (ends capped at
    /// [`PROFILE_END_ITERATIONS`], the threshold) on the docs' seeds 1-300
    /// (`docs/depth-profile-2001.md`): the coverage experiment's fixed group at 3 px
    /// 90.7-97.0 % (right.cx 88.7 % off), at 0.5 px 92.7-98.0 %; +2 % CPU in
    /// `experiment fig5-verge-tilt --trials 100`. `None`: the linearised covariance at
    /// the estimate.
    pub depth_profile: Option<DepthProfile>,
    /// The bootstrap of the covariance (module docs step 10, [`bootstrap_covariance`]):
    /// `Some` re-runs the maximum-likelihood pass on `replicates` resamplings of the point
    /// tracks (seeded by `seed` plus [`EstimationOptions::seed`]) and widens each camera
    /// sigma to the replicates' spread where that is larger (after the depth profile).
    /// Default `None`: it costs about one warm-started adjustment per replicate (30
    /// replicates: measured in `docs/efficiency.md`, twentieth session, with the coverage
    /// it buys in the near scene).
    pub bootstrap: Option<BootstrapOptions>,
    /// Model the image border in the maximum-likelihood passes (module docs step 7): a
    /// point is observed only if its measured position lies in the image, so near the
    /// border the noise of the observations that remain points inward; the least
    /// squares then fits each residual against the expected measurement under that
    /// truncation (`BundleOptions::measurement_window` = the whole image). Default
    /// true. Measured with the removed `examples/bias_mc.rs` (2400 adjustments at 3 px): the truncation
    /// put the focal lengths +0.08 to +0.14 sigma high (fy most: the image is 576 px high)
    /// and the window takes them back to the untruncated values; in `experiment
    /// calibration` (`--image-border on` against `off`, seeds 1-250 and 251-500) it halves
    /// the focal lengths' bias, the ratios move by less than their sampling noise, and
    /// `experiment coverage` stays within 90.7-97.3 % (`docs/ratio-tail.md`). Noise-free
    /// estimates are unchanged (no residual is near its window's edge in sigmas). A
    /// feature detector that keeps a margin (`headalign-vision`: 16 px) truncates there
    /// instead; the whole-image window then corrects nothing and changes almost nothing
    /// (a point 16 px inside is 5 sigma from the border at 3 px).
    pub image_border: bool,
    /// Observations a camera must have of a point for the point to take part in the
    /// maximum-likelihood passes, if that camera sees it at all (module docs step 7).
    /// Default 1 (every point). A point seen once by one camera takes its depth from that
    /// observation alone (the other camera's views, a few degrees apart, fix its
    /// direction only), so a wrong observation near the epipolar line is fitted exactly at
    /// a wrong depth and no residual test can see it: at 3 px (the removed `examples/bias_pipeline.rs`,
    /// seeds 1-200) the final adjustment keeps 0.585 outliers per trial, 116 of 117 of
    /// this kind, and the focal lengths come out up to +0.25 sigma high. 2 removes them
    /// (0.005 per trial) but those points, about 5 % of the observations and often near
    /// the image edge, carry much of the focal lengths' information: on `experiment all`
    /// (same seeds) the RMS errors grew by up to 17 % (focal lengths at 3 px 6-17 %, alignment
    /// 4-9 %) and the Cramer-Rao bound with them (f at 3 px 1.86 -> 2.00 %), so the
    /// ratios fell (calibration grid worst 1.154 -> 1.09) while every estimate got worse
    /// (`docs/ratio-tail.md`). Kept as an option for data with many such outliers.
    pub min_camera_observations: usize,
    /// Test of the points seen once by one camera against their neighbours' depth
    /// ([`lone_depth_outliers`]): such a point's depth rests on that one observation, so
    /// a wrong one near the epipolar line puts it at a wrong depth that no residual shows,
    /// but usually far from the surface around it. `None` keeps every such point. Default
    /// [`LoneDepthGate::DEFAULT`]. Measured (the removed `examples/bias_pipeline.rs`, seeds 1-200 at
    /// 3 px): kept outliers 0.585 -> 0.115 per trial, the focal lengths' mean error +0.13 /
    /// +0.26 / +0.06 / +0.16 -> +0.10 / +0.12 / +0.04 / +0.05 sigma; `experiment
    /// calibration` (seeds 1-250, paired, `--lone-depth-gate off` against the default): the
    /// focal lengths' RMS errors -5 to -12 % at 0.5 px, -7 to +1 % at 1-2 px, +1 to +5 %
    /// at 3 px (its tail trials move either way), reconstruction error 2.43 -> 1.27 % at
    /// 0.5 px. On rendered images (`bench/seeds.py 1 24 --images`) it changes almost
    /// nothing (f 0.035 / 0.043 % with it, 0.035 / 0.043 % without, seeds 1-8 / 9-24).
    pub lone_depth_gate: Option<LoneDepthGate>,
}

/// Which points [`lone_depth_outliers`] flags: a point seen once by one camera whose log
/// distance differs from the median of its `neighbours` nearest well-seen points (by
/// direction) by more than `z` standard deviations, the deviation's variance being that of
/// its own stereo depth (`sqrt 2` noise over the disparity), plus the neighbours' spread
/// (1.4826 MAD) and the surface's `roughness`, all in log distance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoneDepthGate {
    /// Threshold in standard deviations (default 5).
    pub z: f64,
    /// Log-distance spread a point may have about its neighbours' median on a smooth
    /// scene (default 0.1: 10 %).
    pub roughness: f64,
    /// Neighbours compared (default 10); with fewer well-seen points nothing is flagged.
    pub neighbours: usize,
}

impl LoneDepthGate {
    /// The default (field docs). Chosen on the removed `examples/bias_pipeline.rs` `DEPTHDIAG` with
    /// the gate off (lone observations more than 5 noise sigmas from their exact pixel
    /// count as outliers): beyond 5 deviations lie 97 of 116 lone outliers and 24 of 3843
    /// lone inliers at 3 px (200 seeds), 44 of 56 and 77 of 3963 at 1 px, 20 of 27 and 28 of
    /// 941 with 50 points at 1.5 px; z = 6 flags half as many of those inliers and lets 0-9 %
    /// more outliers through, a roughness of 0 flags 1.4-2 times as many inliers.
    pub const DEFAULT: LoneDepthGate = LoneDepthGate { z: 5.0, roughness: 0.1, neighbours: 10 };
}

/// How [`profile_depth_scale`] widens the reported covariance: the estimate is
/// re-adjusted with its depth scale `s` (log harmonic-mean point distance in baselines,
/// [`log_depth_scale`]) held at `s_hat -+ z sigma_s`, and each camera parameter's sigma
/// becomes the largest of its sigmas at the estimate and at the two ends.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthProfile {
    /// Where the ends lie, in sigmas of `s` (default 1.0, measured: 1.96, the 95 %
    /// interval of `s`, over-covers the focal lengths at 3 px because each sigma takes the
    /// maximum over the two ends; [`EstimationOptions::depth_profile`]).
    pub z: f64,
    /// Profile only when `sigma_s` exceeds this (default 0.01: the intrinsics' sigmas
    /// widen by about `0.3-0.6 z sigma_s` where `sigma_s < 0.2` (the removed `examples/profile_cost.rs`,
    /// seeds 1001-1040: 0.5 px sigma_s 0.033-0.066, widening 0.9-3.4 %; 1 px 0.065-0.16,
    /// 3.6-8.2 %), so below it by well under 1 %; it skips the noise-free runs, whose
    /// sigma_s is below 1e-6, and keeps every trial at 0.5 px and above).
    pub min_sigma_log_depth: f64,
}

impl DepthProfile {
    /// The default: ends at 1 sigma of the depth scale, profiled when its sigma exceeds
    /// 0.01 (field docs).
    pub const DEFAULT: DepthProfile = DepthProfile { z: 1.0, min_sigma_log_depth: 0.01 };
}

/// The largest sigma ratio, end over estimate, of a profile end that
/// [`profile_depth_scale`] uses; an end beyond it is skipped as degenerate.
pub const MAX_END_WIDENING: f64 = 10.0;

/// Levenberg-Marquardt iterations of each profile end of [`profile_depth_scale`]. The ends
/// start at the estimate, one depth-scale sigma away, and most converge in 5-9 iterations,
/// but the stiff depth-scale pseudo-residual makes some at 3 px creep along the curved
/// constraint to the 300-iteration limit (about 1 s each, most of the profile's former
/// +11 % CPU). Measured against ends run to 300 iterations: per end (16 ends, seeds
/// 1001-1008 at 3 px) the widening of every camera sigma agrees to a median 3e-7 and at
/// worst 7 % (a far scene whose end creeps at 300 iterations as well); on the reported
/// sigmas (`experiment calibration --only 3 --trials 60 --seed 1001 --depth-profile 1`,
/// 660 sigmas) the largest change is 0.93 % (seed 1008, 127 baselines away), 99 % are
/// within 0.52 %, and the estimates are identical.
pub const PROFILE_END_ITERATIONS: usize = 20;

/// What [`profile_depth_scale`] did.
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct DepthProfileReport {
    /// The estimate's depth scale `s`: `-ln` of the mean inverse point distance, in
    /// baselines ([`log_depth_scale`]).
    pub log_depth: f64,
    /// Its linearised standard deviation.
    pub sigma_log_depth: f64,
    /// Profile ends used (0-2; 0 when `sigma_s` was below the threshold; an end whose
    /// adjustment failed or widened a sigma beyond [`MAX_END_WIDENING`] is not used).
    pub ends: usize,
    /// The largest factor by which a camera parameter's sigma was widened (1: none).
    pub max_widening: f64,
}

/// Which tracks [`near_depth_step`] flags: those with an observation that has a
/// neighbour within `radius_px` in the same image whose point lies at a depth differing by
/// more than the factor `ratio`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthStepGate {
    /// Neighbourhood radius in each image, pixels (image mode: 40, about twice the
    /// spacing of the tracked corners at 1500 per image).
    pub radius_px: f64,
    /// Depth ratio of two neighbours beyond which they lie on different surfaces (image
    /// mode: 1.15; stereo depth at 0.3 px is good to a few percent).
    pub ratio: f64,
}

impl DepthStepGate {
    /// The image-mode setting (field docs). Measured with the final observations re-fitted
    /// without the flagged tracks (the removed `examples/cluster_diag.rs`, seeds 1-40): z-score RMS of
    /// the 8 intrinsics 1.29 -> 1.15 (seeds 1-20) and 2.27 -> 1.45 (seeds 21-40, three
    /// seeds at 3-7); radius 25 px and ratio 1.2 flagged fewer tracks and did less (1.17,
    /// 1.90); dropping as many random tracks changed nothing (1.28, 2.18). In the full
    /// pipeline (gate before the maximum-likelihood pass, `bench/seeds.py 1 20 --images`
    /// with it set in `images::tracked_estimation`) it did not pay: the z-scores hardly
    /// moved and the focal and elevation errors grew (README), so nothing sets it by
    /// default.
    pub const IMAGES: DepthStepGate = DepthStepGate { radius_px: 40.0, ratio: 1.15 };
}

impl Default for EstimationOptions {
    fn default() -> Self {
        Self {
            fundamental: RansacOptions { threshold: 3.0, min_iterations: 500, ..RansacOptions::default() },
            homography: RansacOptions { threshold: 4.0, ..RansacOptions::default() },
            prefilter_px: 6.0,
            bundle: BundleOptions {
                angle_prior_sigma: Some(ENCODER_SIGMA_DEG.to_radians()),
                function_tolerance: 1e-9,
                ..BundleOptions::default()
            },
            reselect_sigmas: 3.5,
            min_tracks: 12,
            seed: 0,
            final_least_squares: true,
            drop_weak_views: true,
            reversed_rig_restart: true,
            depth_step: None,
            depth_profile: Some(DepthProfile::DEFAULT),
            bootstrap: None,
            image_border: true,
            min_camera_observations: 1,
            lone_depth_gate: Some(LoneDepthGate::DEFAULT),
        }
    }
}

impl EstimationOptions {
    /// The defaults (tuned for about 1 px of noise) with `seed` and the RANSAC and
    /// prefilter thresholds scaled by `max(1, noise_px)`, as a user who knows the noise
    /// level would set them (at 3 px the 3-4 px defaults reject most inliers and the 3D
    /// homographies fail with too few tracks). The experiments use it.
    pub fn scaled_for_noise(noise_px: f64, seed: u64) -> Self {
        let d = Self::default();
        let s = noise_px.max(1.0);
        let mut o = Self { seed, prefilter_px: d.prefilter_px * s, ..d };
        o.fundamental.threshold *= s;
        o.homography.threshold *= s;
        o
    }

    /// Check every option.
    pub fn validate(&self) -> Result<(), AlignError> {
        self.fundamental
            .validate()
            .map_err(|e| AlignError::InvalidOption(format!("fundamental RANSAC: {e}")))?;
        self.homography
            .validate()
            .map_err(|e| AlignError::InvalidOption(format!("homography RANSAC: {e}")))?;
        self.bundle.validate().map_err(|e| AlignError::InvalidOption(format!("bundle adjustment: {e}")))?;
        if !self.prefilter_px.is_finite() || self.prefilter_px <= 0.0 {
            return Err(AlignError::InvalidOption("prefilter_px must be positive".into()));
        }
        if self.min_camera_observations == 0 {
            return Err(AlignError::InvalidOption("min_camera_observations must be at least 1".into()));
        }
        if !self.reselect_sigmas.is_finite() || self.reselect_sigmas <= 1.0 {
            return Err(AlignError::InvalidOption("reselect_sigmas must be a finite number above 1".into()));
        }
        if let Some(g) = self.depth_step
            && !(g.radius_px.is_finite() && g.radius_px > 0.0 && g.ratio.is_finite() && g.ratio > 1.0)
        {
            return Err(AlignError::InvalidOption(
                "depth_step needs a positive finite radius and a finite ratio above 1".into(),
            ));
        }
        if let Some(g) = self.lone_depth_gate
            && !(g.z.is_finite()
                && g.z > 0.0
                && g.roughness.is_finite()
                && g.roughness >= 0.0
                && g.neighbours >= 3)
        {
            return Err(AlignError::InvalidOption(
                "lone_depth_gate needs a positive finite z, a finite roughness >= 0 and at least 3 neighbours".into(),
            ));
        }
        if self.min_tracks < 8 {
            return Err(AlignError::InvalidOption("min_tracks must be at least 8".into()));
        }
        if let Some(p) = self.depth_profile
            && !(p.z.is_finite()
                && p.z > 0.0
                && p.min_sigma_log_depth.is_finite()
                && p.min_sigma_log_depth >= 0.0)
        {
            return Err(AlignError::InvalidOption(
                "depth_profile needs a positive finite z and a finite min_sigma_log_depth >= 0".into(),
            ));
        }
        if let Some(b) = self.bootstrap {
            b.validate().map_err(|e| match e {
                headalign_geometry::GeometryError::InvalidOption(m) => AlignError::InvalidOption(m),
                other => AlignError::InvalidOption(other.to_string()),
            })?;
        }
        Ok(())
    }
}

/// The role of a view, from its encoder differences to the reference view.
#[derive(Debug, Clone, PartialEq)]
pub enum ViewRole {
    /// The first view.
    Reference,
    /// Only pan and/or elevation moved: the rig is unchanged. Differences in degrees.
    Rig {
        /// Pan difference, degrees.
        pan_deg: f64,
        /// Elevation difference, degrees.
        elevation_deg: f64,
    },
    /// A vergence joint moved (the rig changed): used to measure the vergence axes.
    Verge,
}

/// Classify each view; errors for a view that did not move and for rotations that are all
/// about one joint.
pub fn classify_views(views: &[View]) -> Result<Vec<ViewRole>, AlignError> {
    let Some(first) = views.first() else {
        return Err(AlignError::Observations("no views".into()));
    };
    let e0 = first.capture.encoders;
    let mut roles = vec![ViewRole::Reference];
    for v in &views[1..] {
        let d = |j: Joint| v.capture.encoders.get(j) - e0.get(j);
        let moved: Vec<Joint> = Joint::ALL.iter().copied().filter(|&j| d(j).abs() > MOVED_DEG).collect();
        if moved.is_empty() {
            return Err(AlignError::NotARotation {
                view: v.name.clone(),
                why: format!("its encoder readings equal those of '{}': no rotation to measure", first.name),
            });
        }
        if moved.iter().any(|j| matches!(j, Joint::VergeLeft | Joint::VergeRight)) {
            roles.push(ViewRole::Verge);
        } else {
            roles.push(ViewRole::Rig { pan_deg: d(Joint::Pan), elevation_deg: d(Joint::Elevation) });
        }
    }
    // Single-joint rotations give the axes; at least one about each of pan and elevation.
    let single = |joint: Joint| -> Option<usize> {
        roles.iter().enumerate().find_map(|(i, r)| match (r, joint) {
            (ViewRole::Rig { pan_deg, elevation_deg }, Joint::Pan)
                if elevation_deg.abs() <= MOVED_DEG && pan_deg.abs() > MOVED_DEG =>
            {
                Some(i)
            }
            (ViewRole::Rig { pan_deg, elevation_deg }, Joint::Elevation)
                if pan_deg.abs() <= MOVED_DEG && elevation_deg.abs() > MOVED_DEG =>
            {
                Some(i)
            }
            _ => None,
        })
    };
    let rig_views: Vec<usize> =
        (0..roles.len()).filter(|&i| matches!(roles[i], ViewRole::Rig { .. })).collect();
    match (single(Joint::Pan), single(Joint::Elevation)) {
        (Some(_), Some(_)) => Ok(roles),
        (p, e) => {
            // Name the two views rotating about the same joint, if that is the problem.
            let joint = if p.is_some() { Joint::Pan } else { Joint::Elevation };
            let same: Vec<usize> = rig_views
                .iter()
                .copied()
                .filter(|&i| single(joint) == Some(i) || is_single(&roles[i], joint))
                .collect();
            if (p.is_some() || e.is_some()) && same.len() >= 2 {
                return Err(AlignError::SameAxis {
                    first: views[same[0]].name.clone(),
                    second: views[same[1]].name.clone(),
                    joint: joint.name().to_string(),
                });
            }
            let missing = if p.is_none() { "pan" } else { "elevation" };
            Err(AlignError::MissingMotion(format!(
                "no view rotates the {missing} joint alone; the procedure needs one rotation about pan and one about elevation"
            )))
        }
    }
}

fn is_single(role: &ViewRole, joint: Joint) -> bool {
    match role {
        ViewRole::Rig { pan_deg, elevation_deg } => match joint {
            Joint::Pan => elevation_deg.abs() <= MOVED_DEG && pan_deg.abs() > MOVED_DEG,
            Joint::Elevation => pan_deg.abs() <= MOVED_DEG && elevation_deg.abs() > MOVED_DEG,
            _ => false,
        },
        _ => false,
    }
}

/// Diagnostics of one 3D homography.
#[derive(Debug, Clone, Serialize)]
pub struct HomographyReport {
    /// View name.
    pub view: String,
    /// Candidate quadruplets.
    pub candidates: usize,
    /// Inliers after guided re-selection.
    pub inliers: usize,
    /// Iterations of the fallback 5-point RANSAC (0 when the screened set sufficed).
    pub ransac_iterations: usize,
    /// Guided re-selection rounds until the set was stable.
    pub guided_rounds: usize,
    /// RMS symmetric transfer error of the inliers, pixels.
    pub rms_transfer_px: f64,
}

/// Diagnostics of the whole estimation.
#[derive(Debug, Clone, Serialize)]
pub struct EstimationReport {
    /// Stereo matches over all rig views.
    pub stereo_matches: usize,
    /// Stereo inliers of F.
    pub stereo_inliers: usize,
    /// RMS Sampson distance of the stereo inliers, pixels.
    pub stereo_rms_px: f64,
    /// One per rotated view.
    pub homographies: Vec<HomographyReport>,
    /// Focal lengths of the linear initialisation (left fx, fy; right fx, fy).
    pub linear_focal: [f64; 4],
    /// Observations used by the final bundle adjustment.
    pub bundle_observations: usize,
    /// Points in the final bundle adjustment.
    pub bundle_points: usize,
    /// Iterations of the final bundle adjustment.
    pub bundle_iterations: usize,
    /// RMS reprojection error before / after the bundle adjustment, pixels.
    pub initial_rms_px: f64,
    /// Final RMS reprojection error, pixels.
    pub final_rms_px: f64,
    /// Estimated image noise, pixels.
    pub sigma_px: f64,
    /// How much the covariance model widened the sigmas over the Gaussian one
    /// ([`headalign_geometry::bundle::BundleReport::sigma_inflation`]; 1 with the default
    /// Gaussian model).
    pub sigma_inflation: f64,
    /// Rotated views left out of the estimate ([`EstimationOptions::drop_weak_views`]), in
    /// the order they were dropped; empty when every view was used.
    pub dropped_views: Vec<DroppedView>,
    /// The depth-scale profile of the covariance ([`EstimationOptions::depth_profile`]);
    /// `None` when off or when `s` or its sigma could not be computed.
    pub depth_profile: Option<DepthProfileReport>,
    /// The bootstrap of the covariance ([`EstimationOptions::bootstrap`]); `None` when off
    /// or when fewer than 3 replicates converged.
    pub bootstrap: Option<BootstrapReport>,
}

/// What [`bootstrap_covariance`] did.
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct BootstrapReport {
    /// Replicates that converged and entered the spread.
    pub replicates: usize,
    /// Replicates that failed (skipped).
    pub failed: usize,
    /// The largest factor by which a camera parameter's sigma was widened (1: none).
    pub max_widening: f64,
    /// The median over the camera parameters of bootstrap sigma / sigma before it.
    pub median_ratio: f64,
}

/// A rig view [`estimate_rig`] left out, and why.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct DroppedView {
    /// The view's name.
    pub view: String,
    /// The error its 3D homography gave.
    pub reason: String,
}

/// The calibrated rig and head, in the reference view's left camera frame.
#[derive(Debug, Clone)]
pub struct RigCalibration {
    /// The bundle adjustment result (state, covariance, report).
    pub bundle: BundleResult,
    /// Track id of each bundle point (same order as `bundle.state.points`).
    pub point_tracks: Vec<u64>,
    /// Observations of each point in the final adjustment (same order as the points); zero
    /// for points not seen by both cameras.
    pub point_observations: Vec<usize>,
    /// The observations the final adjustment used (the inliers); `view` indexes the rig
    /// views in input order (without those in `report.dropped_views`), `point` the points.
    pub observations: Vec<BundleObservation>,
    /// Encoder readings of the reference view.
    pub reference_encoders: Encoders,
    /// Diagnostics.
    pub report: EstimationReport,
}

impl RigCalibration {
    /// Pan axis in the reference left camera frame (directed so that a positive pan encoder
    /// change is a positive rotation).
    pub fn pan_axis(&self) -> Option<Line> {
        axes_of(&self.bundle.state).map(|a| a.0)
    }

    /// Elevation axis in the reference left camera frame (directed like the encoder).
    pub fn elevation_axis(&self) -> Option<Line> {
        axes_of(&self.bundle.state).map(|a| a.1)
    }

    /// Points by track id, reference left camera frame, in baselines: those the final
    /// adjustment constrains (observed at least three times after outlier rejection).
    pub fn points(&self) -> Vec<(u64, Point3<f64>)> {
        self.point_tracks
            .iter()
            .zip(&self.bundle.state.points)
            .zip(&self.point_observations)
            .filter(|(_, n)| **n >= 3)
            .map(|((t, p), _)| (*t, *p))
            .collect()
    }
}

/// (pan, elevation) axes of a Joints-model state.
pub fn axes_of(state: &RigState) -> Option<(Line, Line)> {
    match &state.motions {
        Motions::Joints { axes, .. } if axes.len() == 2 => Some((axes[0], axes[1])),
        _ => None,
    }
}

fn to_map(obs: &[headalign_platform::TrackObservation]) -> HashMap<u64, Point2<f64>> {
    obs.iter().map(|o| (o.track, o.pixel)).collect()
}

/// Stereo matches (track, left, right) of a capture, sorted by track id.
pub(crate) fn stereo_matches(c: &StereoCapture) -> Vec<StereoMatch> {
    let right = to_map(&c.right);
    let mut m: Vec<_> =
        c.left.iter().filter_map(|o| right.get(&o.track).map(|r| (o.track, o.pixel, *r))).collect();
    m.sort_by_key(|x| x.0);
    m
}

/// Run the whole chain on the views (the first is the reference; verge views are
/// ignored here). A rotated view whose 3D homography fails is left out and the chain run
/// again without it while a pan-only and an elevation-only rotation remain
/// ([`EstimationOptions::drop_weak_views`]); otherwise its error is returned.
pub fn estimate_rig(views: &[View], options: &EstimationOptions) -> Result<RigCalibration, AlignError> {
    options.validate()?;
    let mut kept: Vec<View> = Vec::new();
    let mut dropped: Vec<DroppedView> = Vec::new();
    loop {
        let current: &[View] = if dropped.is_empty() { views } else { &kept };
        let mut at_view = None;
        let error = match estimate_rig_once(current, options, &mut at_view) {
            Ok(mut calibration) => {
                calibration.report.dropped_views = dropped;
                return Ok(calibration);
            }
            Err(e) => e,
        };
        let Some(vi) = at_view.filter(|_| options.drop_weak_views) else { return Err(error) };
        let rest: Vec<View> =
            current.iter().enumerate().filter(|&(i, _)| i != vi).map(|(_, v)| v.clone()).collect();
        if classify_views(&rest).is_err() {
            return Err(error);
        }
        dropped.push(DroppedView { view: current[vi].name.clone(), reason: error.to_string() });
        kept = rest;
    }
}

/// [`estimate_rig`] on exactly these views; `at_view` names the view (index into
/// `views`) whose 3D homography step failed, if that is where it failed.
fn estimate_rig_once(
    views: &[View],
    options: &EstimationOptions,
    at_view: &mut Option<usize>,
) -> Result<RigCalibration, AlignError> {
    let roles = classify_views(views)?;
    let rig: Vec<usize> = (0..views.len()).filter(|&i| !matches!(roles[i], ViewRole::Verge)).collect();
    let [w, h] = views[0].capture.image_size;
    let k0 = Intrinsics::rough_guess(w, h);
    let bordered;
    let options = if options.image_border && options.bundle.measurement_window.is_none() {
        let (wf, hf) = (f64::from(w), f64::from(h));
        let bundle = BundleOptions {
            measurement_window: Some([-0.5, -0.5, wf - 0.5, hf - 0.5]),
            ..options.bundle.clone()
        };
        bordered = EstimationOptions { bundle, ..options.clone() };
        &bordered
    } else {
        options
    };

    // --- 1. Stereo F from all rig views together.
    let per_view: Vec<Vec<StereoMatch>> = rig.iter().map(|&i| stereo_matches(&views[i].capture)).collect();
    let pairs: Vec<(Point2<f64>, Point2<f64>)> = per_view.iter().flatten().map(|m| (m.1, m.2)).collect();
    if pairs.len() < options.min_tracks {
        return Err(AlignError::TooFewTracks {
            what: "matched between left and right".into(),
            needed: options.min_tracks,
            got: pairs.len(),
        });
    }
    let f_opts = RansacOptions { seed: options.seed, ..options.fundamental };
    let f_report = estimate_fundamental(&pairs, &f_opts).step("fundamental matrix")?;
    let f: FundamentalMatrix = f_report.model;
    let threshold_f = options.fundamental.threshold;
    let inlier_pairs: Vec<(Point2<f64>, Point2<f64>)> = f_report.inliers.iter().map(|&i| pairs[i]).collect();
    let stereo_rms = rms(inlier_pairs.iter().map(|(l, r)| f.sampson_distance(l, r)));

    // --- 2. Frame and triangulation per rig view: track -> (X, left, right).
    let frame: StereoFrame = quasi_euclidean_frame(&f.0, &k0, &inlier_pairs).step("projective frame")?;
    let (p_l, p_r) = (frame.left_camera(), frame.right_camera());
    let mut recon: Vec<Reconstruction> = Vec::new();
    for matches in &per_view {
        let mut map = BTreeMap::new();
        for &(track, l, r) in matches {
            if f.sampson_distance(&l, &r) > threshold_f {
                continue;
            }
            if let Ok(x) = triangulate_optimal(&f, &p_l, &p_r, &l, &r) {
                map.insert(track, (x, l, r));
            }
        }
        recon.push(map);
    }

    // --- 3. 3D homographies, RANSAC + guided re-selection.
    let estimator = Homography3Estimator { p_left: p_l, p_right: p_r };
    let mut h_reports = Vec::new();
    let mut homographies = Vec::new();
    // Why the linear start cannot run (a 3D homography without a rotation's eigenvalues).
    let mut linear_blocked: Option<AlignError> = None;
    let mut quad_inliers: Vec<Vec<u64>> = vec![Vec::new(); rig.len()];
    // Plane homographies (left, right) of each rotation, for the rotation-based start.
    let mut image_rotations: Vec<PlanePair> = Vec::new();
    for (slot, &vi) in rig.iter().enumerate().skip(1) {
        *at_view = Some(vi);
        let mut tracks = Vec::new();
        let mut quads = Vec::new();
        for (track, (x, l0, r0)) in &recon[0] {
            if let Some((y, l1, r1)) = recon[slot].get(track) {
                tracks.push(*track);
                quads.push(Quadruplet { x: *x, y: *y, left0: *l0, right0: *r0, left1: *l1, right1: *r1 });
            }
        }
        if quads.len() < options.min_tracks {
            return Err(AlignError::TooFewTracks {
                what: format!("seen in both stereo views '{}' and '{}'", views[0].name, views[vi].name),
                needed: options.min_tracks,
                got: quads.len(),
            });
        }
        let opts = RansacOptions { seed: options.seed.wrapping_add(vi as u64), ..options.homography };
        // Consensus: a head rotation maps each camera's image almost by K R K^-1, so
        // quadruplets are first screened by 4-point plane-homography RANSAC on
        // left0 -> left1 and right0 -> right1 (robust); then the 5-point 3D DLT RANSAC
        // (polished on transfer error) runs on the screened set, and guided re-selection
        // over all quadruplets with the 3D homography repeats until the set is stable.
        let (screened, plane_homographies) = screen_rotation(&quads, options.prefilter_px, opts.seed);
        if let Some(g) = plane_homographies {
            image_rotations.push(g);
        }
        if screened.len() < options.min_tracks {
            return Err(AlignError::TooFewTracks {
                what: format!(
                    "consistent with a rotation between '{}' and '{}'",
                    views[0].name, views[vi].name
                ),
                needed: options.min_tracks,
                got: screened.len(),
            });
        }
        let hview = format!("3D homography for view '{}'", views[vi].name);
        let count = |m: &TransferModel| {
            quads
                .iter()
                .filter(|q| symmetric_transfer_error(m, &p_l, &p_r, q) <= options.homography.threshold)
                .count()
        };
        // Starting models: the rigid fit in the quasi-Euclidean frame (always well
        // conditioned, a few pixels biased) and the DLT when it is a valid rigid conjugate
        // (with a 3 deg rotation H is close to the identity and the DLT over many noisy
        // points can come out near-singular); each is polished on transfer error.
        let rigid = RigidFrameEstimator { p_left: p_l, p_right: p_r };
        let mut best: Option<(TransferModel, usize)> = None;
        for start in [rigid.fit_inliers(&quads, &screened), estimator.fit_inliers(&quads, &screened)]
            .into_iter()
            .flatten()
        {
            if start.h.0.determinant() <= 0.0 {
                continue;
            }
            let Some(m) = polish(&start, &quads, &screened, &p_l, &p_r) else { continue };
            let n = count(&m);
            if best.as_ref().is_none_or(|(_, b)| n > *b) {
                best = Some((m, n));
            }
        }
        let mut ransac_iterations = 0;
        // Fallback: the 5-point DLT RANSAC with polished local optimisation.
        if best.as_ref().is_none_or(|(_, n)| *n * 2 < screened.len()) {
            let screened_quads: Vec<Quadruplet> = screened.iter().map(|&i| quads[i]).collect();
            let rep = ransac(&PolishedHomography(&estimator), &screened_quads, &opts).step(&hview)?;
            ransac_iterations = rep.iterations;
            let n = count(&rep.model);
            if best.as_ref().is_none_or(|(_, b)| n > *b) {
                best = Some((rep.model, n));
            }
        }
        let Some((mut model, _)) = best else {
            return Err(AlignError::NotARotation {
                view: views[vi].name.clone(),
                why: "no 3D homography fits its matches".into(),
            });
        };
        // Guided re-selection until the inlier set is stable.
        let select = |m: &TransferModel| -> Vec<usize> {
            (0..quads.len())
                .filter(|&i| {
                    symmetric_transfer_error(m, &p_l, &p_r, &quads[i]) <= options.homography.threshold
                })
                .collect()
        };
        let mut inliers = select(&model);
        let mut rounds = 0;
        for _ in 0..10 {
            rounds += 1;
            let Some(refit) = polish(&model, &quads, &inliers, &p_l, &p_r) else { break };
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
        if inliers.len() < options.min_tracks {
            return Err(AlignError::TooFewTracks {
                what: format!("fitting the 3D homography of view '{}'", views[vi].name),
                needed: options.min_tracks,
                got: inliers.len(),
            });
        }
        let rms_t = rms(inliers.iter().map(|&i| symmetric_transfer_error(&model, &p_l, &p_r, &quads[i])));
        h_reports.push(HomographyReport {
            view: views[vi].name.clone(),
            candidates: quads.len(),
            inliers: inliers.len(),
            ransac_iterations,
            guided_rounds: rounds,
            rms_transfer_px: rms_t,
        });
        let h = model.h.normalized_det().map_err(|e| AlignError::NotARotation {
            view: views[vi].name.clone(),
            why: format!("its 3D homography {e}"),
        })?;
        // A noisy 3D homography of a small rotation (50 points at 1.5 px in a scene about
        // 1 m away: 3 of 60 trials) can lose its complex eigenvalue pair. Only the linear
        // chain needs its eigenvectors: that start is then skipped with this reason, and
        // the other starts (image homographies, calibrated pose, rough) still run.
        if linear_blocked.is_none() && headalign_geometry::invariant::invariant_points(&h.0).is_err() {
            linear_blocked = Some(AlignError::NotARotation {
                view: views[vi].name.clone(),
                why: "its 3D homography has no complex eigenvalue pair (no measurable rotation)".into(),
            });
        }
        homographies.push(h);
        quad_inliers[slot] = inliers.iter().map(|&i| tracks[i]).collect();
    }

    *at_view = None;

    // --- 4. The point set: tracks reconstructed in the reference view, then those first
    // reconstructed in another rig view.
    let mut point_tracks: Vec<u64> = recon[0].keys().copied().collect();
    let mut origin_slot: Vec<usize> = vec![0; point_tracks.len()];
    for (slot, map) in recon.iter().enumerate().skip(1) {
        for &track in map.keys() {
            if !recon[0].contains_key(&track) && !point_tracks.contains(&track) {
                point_tracks.push(track);
                origin_slot.push(slot);
            }
        }
    }
    let commanded: Vec<[f64; 2]> = rig
        .iter()
        .map(|&i| match roles[i] {
            ViewRole::Rig { pan_deg, elevation_deg } => [pan_deg.to_radians(), elevation_deg.to_radians()],
            _ => [0.0, 0.0],
        })
        .collect();
    let ctx = InitContext {
        views,
        rig: &rig,
        recon: &recon,
        point_tracks: &point_tracks,
        origin_slot: &origin_slot,
        commanded: &commanded,
        min_tracks: options.min_tracks,
    };

    // --- 5. Three initialisations of the bundle adjustment: the linear self-calibration
    // chain (paper section 3.1); the image homographies of the rotations (each camera's K
    // by rotating-camera self-calibration, better conditioned than the 3D chain with small
    // rotations); and a rough one (K = image-width guess, motions by resection in the
    // quasi-Euclidean frame). The solution with the lowest MSAC score over the
    // first selection wins ([`start_score`]).
    let linear = match linear_blocked {
        Some(e) => Err(e),
        None => linear_initial_state(&ctx, &homographies, &k0, &p_r),
    };
    let rough = rough_initial_state(&ctx, &frame);
    let rotation = rotation_initial_state(&ctx, &f, &inlier_pairs, &image_rotations, &k0);
    let threshold = options.fundamental.threshold;
    let rotation_k = rotation_intrinsics(&image_rotations, &k0);
    let calibrated = calibrated_initial_state(&ctx, &f, &pairs, rotation_k, threshold, false);
    let lateral = calibrated_initial_state(&ctx, &f, &pairs, (k0, k0), threshold, true);
    let point_index: BTreeMap<u64, usize> = point_tracks.iter().enumerate().map(|(i, &t)| (t, i)).collect();

    // All raw observations of these tracks in the rig views.
    let mut all_obs = Vec::new();
    for (slot, &vi) in rig.iter().enumerate() {
        for (side, list) in [(Side::Left, &views[vi].capture.left), (Side::Right, &views[vi].capture.right)] {
            for o in list {
                if let Some(&pi) = point_index.get(&o.track) {
                    all_obs.push(BundleObservation { point: pi, view: slot, side, pixel: o.pixel });
                }
            }
        }
    }
    // First selection: stereo inliers of F, and quadruplet inliers where the point was
    // part of a quadruplet.
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

    let adjusted = adjust_from_starts(
        vec![linear, rotation, rough, calibrated, lateral],
        &first_obs,
        &all_obs,
        &point_tracks,
        &origin_slot,
        &recon,
        options,
    )?;
    let Adjustment { first, last: final_result, observations: second_obs, linear_focal, .. } = adjusted;
    let (final_result, second_obs) = if options.final_least_squares && options.reversed_rig_restart {
        let sources = PointSources { point_tracks: &point_tracks, origin_slot: &origin_slot, recon: &recon };
        reversed_rig_restart(final_result, second_obs, &all_obs, &sources, options)?
    } else {
        (final_result, second_obs)
    };
    let (final_result, depth_profile) = match options.depth_profile {
        Some(p) if options.final_least_squares => {
            let (r, rep) = profile_depth_scale(final_result, &second_obs, &p, options);
            (r, rep)
        }
        _ => (final_result, None),
    };
    let (final_result, bootstrap) = match options.bootstrap {
        Some(b) if options.final_least_squares => {
            bootstrap_covariance(final_result, &second_obs, &b, options)
        }
        _ => (final_result, None),
    };
    let report = EstimationReport {
        stereo_matches: pairs.len(),
        stereo_inliers: f_report.inliers.len(),
        stereo_rms_px: stereo_rms,
        homographies: h_reports,
        linear_focal,
        bundle_observations: second_obs.len(),
        bundle_points: point_tracks.len(),
        bundle_iterations: final_result.report.iterations,
        initial_rms_px: first.report.initial_rms_px,
        final_rms_px: final_result.report.final_rms_px,
        sigma_px: final_result.report.sigma_px,
        sigma_inflation: final_result.report.sigma_inflation,
        dropped_views: Vec::new(),
        depth_profile,
        bootstrap,
    };
    let mut point_observations = vec![0usize; point_tracks.len()];
    let mut point_sides = vec![[false; 2]; point_tracks.len()];
    for o in &second_obs {
        point_observations[o.point] += 1;
        point_sides[o.point][usize::from(o.side == Side::Right)] = true;
    }
    // A point seen by one camera only has its depth fixed by tiny rotation parallax: it is
    // not counted as reconstructed.
    for (n, sides) in point_observations.iter_mut().zip(&point_sides) {
        if !(sides[0] && sides[1]) {
            *n = 0;
        }
    }
    // Far points take part in the adjustment (their directions calibrate), but a point
    // beyond DEPTH_RATIO times the median distance has an undetermined depth (at 0.5-2 px
    // some lie near infinity) and is not reported as reconstructed: one such point made
    // the best similarity of the reconstruction metric, and its error, 27 % off (seed 8).
    let state = &final_result.state;
    let mut dist: Vec<f64> = (0..point_tracks.len())
        .filter(|&i| point_observations[i] > 0)
        .filter_map(|i| state.points.get(i).map(|p| p.coords.norm()))
        .collect();
    dist.sort_by(f64::total_cmp);
    if let Some(&median) = dist.get(dist.len() / 2) {
        for (i, n) in point_observations.iter_mut().enumerate() {
            let d = state.points.get(i).map_or(f64::NAN, |p| p.coords.norm());
            if !(d.is_finite() && d <= median * DEPTH_RATIO) {
                *n = 0;
            }
        }
    }
    Ok(RigCalibration {
        bundle: final_result,
        point_tracks,
        point_observations,
        observations: second_obs,
        reference_encoders: views[0].capture.encoders,
        report,
    })
}

/// What [`adjust_from_starts`] returns.
pub(crate) struct Adjustment {
    /// The screened adjustment of the best start.
    pub first: BundleResult,
    /// The final adjustment.
    pub last: BundleResult,
    /// The observations of the final adjustment.
    pub observations: Vec<BundleObservation>,
    /// Focal lengths of the first start that existed (left fx, fy; right fx, fy).
    pub linear_focal: [f64; 4],
    /// Index of the start that won.
    pub start_index: usize,
}

/// The adjustment stage (module docs, steps 5-6), shared with the calibration from
/// general rig motions ([`crate::calibrate`]): each start screened by a short adjustment
/// on `first_obs` (gross residuals left out), the best one re-selected over `all_obs` by
/// residual, adjusted to convergence, wild points removed and adjusted once more.
pub(crate) fn adjust_from_starts(
    starts: Vec<Result<RigState, AlignError>>,
    first_obs: &[BundleObservation],
    all_obs: &[BundleObservation],
    point_tracks: &[u64],
    origin_slot: &[usize],
    recon: &[Reconstruction],
    options: &EstimationOptions,
) -> Result<Adjustment, AlignError> {
    let mut linear_focal = [f64::NAN; 4];
    let mut best: Option<(BundleResult, f64)> = None;
    let mut last_err = None;
    let mut start_index = 0;
    for (index, init) in starts.into_iter().enumerate() {
        let state = match init {
            Ok(s) => s,
            Err(e) => {
                last_err = Some(e);
                continue;
            }
        };
        if linear_focal[0].is_nan() {
            linear_focal = [state.left.fx, state.left.fy, state.right.fx, state.right.fy];
        }
        // Gross residuals under this start (wrong matches that no quadruplet checked, points
        // placed badly by a rough start) are left out of its first adjustment: above 5 times
        // the median residual, and at least 10 px. The re-selection below re-admits them.
        let start_obs: Vec<BundleObservation> = {
            let mut r: Vec<f64> =
                first_obs.iter().filter_map(|o| residual_pixels(&state, o).map(|v| v.norm())).collect();
            r.sort_by(f64::total_cmp);
            let cut = r.get(r.len() / 2).map_or(f64::INFINITY, |m| (5.0 * m).max(10.0));
            first_obs
                .iter()
                .copied()
                .filter(|o| residual_pixels(&state, o).is_some_and(|v| v.norm() <= cut))
                .collect()
        };
        // A short adjustment screens each start; only the best continues to convergence.
        let screen = BundleOptions {
            max_iterations: options.bundle.max_iterations.min(SCREEN_ITERATIONS),
            ..options.bundle.clone()
        };
        match bundle_adjust(&state, &start_obs, &screen).step("bundle adjustment") {
            Ok(r) => {
                let score = start_score(&r.state, first_obs, options.fundamental.threshold);
                if best.as_ref().is_none_or(|(_, b)| score < *b) {
                    best = Some((r, score));
                    start_index = index;
                }
            }
            Err(e) => last_err = Some(e),
        }
    }
    let Some((first, _)) = best else {
        return Err(last_err.unwrap_or_else(|| AlignError::MissingMotion("no initialisation".into())));
    };

    // Points the first adjustment could not use (behind a camera under its start) are
    // re-triangulated with the calibrated rig, then every raw observation is re-selected
    // by its residual under the first solution.
    let mut first = first;
    retriangulate_lost_points(&mut first.state, point_tracks, origin_slot, recon);
    let sigma = robust_sigma(&first.state, first_obs).max(0.05);
    let gate = options.reselect_sigmas * sigma;
    let gated: Vec<BundleObservation> = all_obs
        .iter()
        .copied()
        .filter(|o| residual_pixels(&first.state, o).is_some_and(|r| r.norm() <= gate))
        .collect();
    // A point with fewer than MIN_POINT_OBSERVATIONS observations can bend to fit a wrong
    // one (its depth is weakly fixed by small rotations), so it does not take part.
    let mut counts = vec![0usize; point_tracks.len()];
    for o in &gated {
        counts[o.point] += 1;
    }
    let second_obs: Vec<BundleObservation> =
        gated.into_iter().filter(|o| counts[o.point] >= MIN_POINT_OBSERVATIONS).collect();
    let full = BundleOptions {
        max_iterations: options.bundle.max_iterations.max(FINAL_ITERATIONS),
        ..options.bundle.clone()
    };
    let mut final_result =
        bundle_adjust(&first.state, &second_obs, &full).step("bundle adjustment (re-selected)")?;
    // Wrong tracks can be "explained" by a point at an absurd depth (at the camera, or near
    // infinity): points farther than DEPTH_RATIO times the median distance, or nearer than
    // its inverse, are outliers; their observations go and the adjustment runs once more.
    let mut second_obs = second_obs;
    let mut dist: Vec<f64> = final_result.state.points.iter().map(|p| p.coords.norm()).collect();
    dist.sort_by(f64::total_cmp);
    if let Some(&median) = dist.get(dist.len() / 2) {
        let wild = |i: usize| {
            let d = final_result.state.points[i].coords.norm();
            !(d.is_finite() && d <= median * DEPTH_RATIO && d >= median / DEPTH_RATIO)
        };
        let kept: Vec<BundleObservation> = second_obs.iter().copied().filter(|o| !wild(o.point)).collect();
        if kept.len() < second_obs.len() {
            second_obs = kept;
            final_result = bundle_adjust(&final_result.state, &second_obs, &full)
                .step("bundle adjustment (wild points removed)")?;
        }
    }
    // Tracks at depth steps: out of the candidates and of the current selection.
    let mut candidates = std::borrow::Cow::Borrowed(all_obs);
    if let Some(gate) = options.depth_step {
        let flagged = near_depth_step(&final_result.state, &second_obs, &gate);
        let kept: Vec<BundleObservation> = second_obs.iter().copied().filter(|o| !flagged[o.point]).collect();
        if kept.len() < second_obs.len() && kept.len() >= options.min_tracks {
            candidates =
                std::borrow::Cow::Owned(all_obs.iter().copied().filter(|o| !flagged[o.point]).collect());
            second_obs = kept;
            final_result = bundle_adjust(&final_result.state, &second_obs, &full)
                .step("bundle adjustment (depth steps removed)")?;
        }
    }
    if options.final_least_squares {
        let sources = PointSources { point_tracks, origin_slot, recon };
        let (ml, ml_obs) =
            maximum_likelihood_pass(&final_result, &candidates, &second_obs, &sources, options)?;
        final_result = ml;
        second_obs = ml_obs;
    }

    Ok(Adjustment { first, last: final_result, observations: second_obs, linear_focal, start_index })
}

/// Points with an observation that has a neighbour (an observation of another point in
/// the same image, within `gate.radius_px`) whose distance from the reference camera
/// differs by more than the factor `gate.ratio`: tracks at a depth step (an occluding
/// edge). Indexed like `state.points`.
///
/// Why: a tracked corner where a near edge crosses the background texture is no fixed
/// point of the scene; it slides along the edge as the viewpoint moves, and its error is
/// structured by the motion, alike for all such tracks, so it moves the calibration
/// coherently where the per-track (clustered) covariance assumes independent tracks.
/// Measured with the simulator's truth (the removed `examples/cluster_diag.rs`): 2-5 % of the tracks
/// sit at true depth steps. Neighbours are found by bucketing each image into cells of
/// the radius (linear time). Pitfall: it also flags good tracks beside an edge (the data
/// lost is the price of not telling them apart).
pub fn near_depth_step(state: &RigState, obs: &[BundleObservation], gate: &DepthStepGate) -> Vec<bool> {
    let mut out = vec![false; state.points.len()];
    let r = gate.radius_px;
    let depth = |p: usize| state.points.get(p).map_or(f64::NAN, |x| x.coords.norm());
    let cell = |v: f64| (v / r).floor() as i64;
    let mut grid: HashMap<(usize, bool, i64, i64), Vec<usize>> = HashMap::new();
    for (i, o) in obs.iter().enumerate() {
        grid.entry((o.view, o.side == Side::Right, cell(o.pixel.x), cell(o.pixel.y))).or_default().push(i);
    }
    for o in obs {
        let da = depth(o.point);
        if !da.is_finite() || out.get(o.point).is_none_or(|&f| f) {
            continue;
        }
        let (cx, cy) = (cell(o.pixel.x), cell(o.pixel.y));
        let step = (cx - 1..=cx + 1).flat_map(|x| (cy - 1..=cy + 1).map(move |y| (x, y))).any(|(x, y)| {
            grid.get(&(o.view, o.side == Side::Right, x, y)).is_some_and(|list| {
                list.iter().filter_map(|&j| obs.get(j)).any(|b| {
                    let db = depth(b.point);
                    b.point != o.point
                        && (b.pixel - o.pixel).norm() <= r
                        && db.is_finite()
                        && da.max(db) > gate.ratio * da.min(db)
                })
            })
        });
        if step {
            out[o.point] = true;
        }
    }
    out
}

/// Score of a screened start, lower is better: the MSAC cost `mean min(|r|, tau)^2` over
/// the same observations for every start (the first selection), an observation that
/// does not project (its point behind a camera) costing `tau^2`. Each start's short
/// adjustment runs on its own subset (gross residuals under that start left out), so
/// their RMS values are not comparable: a bad start that kept 136 of 1628 observations
/// once won with an RMS of 3.0 px against 3.9 px over 1580 (seed 6 at 3 px, 30 % focal
/// error).
fn start_score(state: &RigState, obs: &[BundleObservation], tau: f64) -> f64 {
    let t2 = tau * tau;
    let sum: f64 =
        obs.iter().map(|o| residual_pixels(state, o).map_or(t2, |r| r.norm_squared().min(t2))).sum();
    sum / obs.len().max(1) as f64
}

/// The maximum-likelihood pass (module docs, step 7). The robust solution's noise is
/// estimated from the median residual norm (MAD-like, immune to the outliers still in
/// `candidates`) and gives the first classification: observations of `candidates` within
/// `reselect_sigmas` of it, points keeping at least [`MIN_POINT_OBSERVATIONS`] and of
/// plausible depth. Plain least squares then runs with the angle prior weighted by the
/// noise, and the classification is repeated at the least-squares solution itself until
/// it is stable ([`ML_ROUNDS`] at most):
/// - the noise is re-estimated by [`truncated_noise_estimate`]: `RSS / (m - p)` (`m`
///   residuals including the angle priors, `p` parameters including 3 per point: the
///   classical unbiased estimate) divided by the variance factor of the truncation to
///   `reselect_sigmas` ([`truncated_variance_factor`], 0.987 at 3.5);
/// - an observation is kept when its residual is within `reselect_sigmas` standard
///   deviations of *its own* distribution ([`residual_scale`]): a fitted residual is
///   smaller than the noise by its leverage, a residual of an observation left out of the
///   fit larger.
///
/// Measured cause (docs/efficiency.md): gating at the Huber solution once, where an
/// inlier with a large error keeps its full residual but the median-based scale is that of
/// fitted residuals (about 0.88 of the noise at 2 px), dropped 7-12 % of the true inliers
/// with errors of 2-3 sigma and 50-85 % of those at 3-4 sigma, so the least-squares noise
/// came out 0.95 of the truth and the reported sigmas 5 % small.
fn maximum_likelihood_pass(
    robust: &BundleResult,
    candidates: &[BundleObservation],
    fallback: &[BundleObservation],
    points: &PointSources<'_>,
    options: &EstimationOptions,
) -> Result<(BundleResult, Vec<BundleObservation>), AlignError> {
    let c = options.reselect_sigmas;
    let mut sigma = robust_sigma(&robust.state, fallback).max(1e-6);
    // Points the robust pass left out (their observations gated away under an early,
    // unconverged solution, or placed by a wrong stereo match) get a fresh position under
    // the final calibration, from the view whose stereo match agrees best with their
    // candidate observations ([`retriangulate_points_by_support`]), so that their good
    // observations can come back.
    let mut state = robust.state.clone();
    let mut adjusted = vec![false; state.points.len()];
    for o in fallback {
        adjusted[o.point] = true;
    }
    let redo: Vec<bool> = adjusted.iter().map(|a| !a).collect();
    retriangulate_points_by_support(&mut state, points, &redo, candidates, c * sigma.max(0.05));
    let gated: Vec<BundleObservation> = candidates
        .iter()
        .copied()
        .filter(|o| residual_pixels(&state, o).is_some_and(|r| r.norm() <= c * sigma.max(0.05)))
        .collect();
    let mut obs = plausible_points(&state, gated, options, sigma);
    if obs.len() < options.min_tracks {
        obs = fallback.to_vec();
        state = robust.state.clone();
    }
    let ls = |noise: f64| BundleOptions {
        max_iterations: options.bundle.max_iterations.max(FINAL_ITERATIONS),
        robust: RobustLoss::None,
        noise_sigma_px: Some(noise),
        ..options.bundle.clone()
    };
    let mut result =
        bundle_adjust(&state, &obs, &ls(sigma)).step("bundle adjustment (maximum likelihood)")?;
    let priors = prior_count(&result.state, &options.bundle);
    for _ in 1..ML_ROUNDS {
        let refit = truncated_noise_estimate(&result, priors, c).unwrap_or(sigma);
        // Re-classify every candidate at the least-squares solution with that noise.
        let in_fit: HashSet<(usize, usize, bool)> =
            obs.iter().map(|o| (o.point, o.view, o.side == Side::Right)).collect();
        let mut per_point = vec![0usize; result.state.points.len()];
        for o in &obs {
            per_point[o.point] += 1;
        }
        let camera_share = camera_parameter_share(&result);
        let next: Vec<BundleObservation> = candidates
            .iter()
            .copied()
            .filter(|o| {
                let fitted = in_fit.contains(&(o.point, o.view, o.side == Side::Right));
                let scale = residual_scale(per_point[o.point], camera_share, fitted);
                residual_pixels(&result.state, o).is_some_and(|r| r.norm() <= c * refit.max(0.05) * scale)
            })
            .collect();
        let next = plausible_points(&result.state, next, options, refit);
        let key = |o: &BundleObservation| (o.point, o.view, o.side == Side::Right);
        let stable = next.len() == obs.len() && next.iter().zip(&obs).all(|(a, b)| key(a) == key(b));
        let moved = (refit / sigma - 1.0).abs() > 0.01;
        if next.len() < options.min_tracks || (stable && !moved) {
            break;
        }
        // A re-classification that leaves a parameter unobservable (a 50-point trial at
        // 1.5 px in 150: its reduced camera system became singular) ends the rounds at the
        // last classification that fitted, instead of failing the whole estimate.
        let Ok(trial) = bundle_adjust(&result.state, &next, &ls(refit)) else { break };
        obs = next;
        sigma = refit;
        result = trial;
    }
    // The reported noise and covariance are those of the final classification.
    if let Some(refit) = truncated_noise_estimate(&result, priors, c)
        && (refit / sigma - 1.0).abs() > 0.01
    {
        result = bundle_adjust(&result.state, &obs, &ls(refit))
            .step("bundle adjustment (maximum likelihood, noise re-estimated)")?;
    }
    Ok((result, obs))
}

/// Module docs step 9: widen the covariance of a least-squares `result` for the
/// nonlinearity along the scene's depth scale. With small rotations the scene's distance
/// in baselines is the badly determined direction (at 3 px known to tens of percent) and
/// the linearised sigmas follow it: a receding maximum-likelihood scene (about 5 % of the
/// trials at 3 px) reports sigmas 0.5-0.9 of the Cramer-Rao bound while its principal
/// points move to absorb the disparity (the removed `examples/sigma_diag.rs`). So the covariance is
/// evaluated along the profile likelihood in `s`: at `s_hat -+ z sigma_s` (everything
/// else re-optimised, [`bundle_adjust_at_depth_scale`]); each camera parameter's sigma
/// becomes the largest of the three and the correlations stay those of the estimate
/// (`C' = D C D`, `D = diag(max(1, sigma_end / sigma))`). The point estimate is
/// unchanged. Where the depth is well determined the three covariances agree and nothing
/// widens. A failed end adjustment is skipped (the estimate's sigma stays).
pub fn profile_depth_scale(
    result: BundleResult,
    obs: &[BundleObservation],
    profile: &DepthProfile,
    options: &EstimationOptions,
) -> (BundleResult, Option<DepthProfileReport>) {
    let noise = result.report.sigma_px;
    let ls = BundleOptions {
        max_iterations: options.bundle.max_iterations.max(FINAL_ITERATIONS),
        robust: RobustLoss::None,
        noise_sigma_px: Some(noise),
        ..options.bundle.clone()
    };
    let Ok((s, sigma_s)) = log_depth_scale(&result.state, obs, &ls, noise) else { return (result, None) };
    let mut report =
        DepthProfileReport { log_depth: s, sigma_log_depth: sigma_s, ends: 0, max_widening: 1.0 };
    if !(sigma_s > profile.min_sigma_log_depth && sigma_s > 0.0) {
        return (result, Some(report));
    }
    let n = result.covariance.matrix.nrows();
    let mut widen = vec![1.0_f64; n];
    let end_ls = BundleOptions { max_iterations: PROFILE_END_ITERATIONS, ..ls.clone() };
    for sign in [-1.0, 1.0] {
        let target = s + sign * profile.z * sigma_s;
        let Ok(end) =
            bundle_adjust_at_depth_scale(&result.state, obs, &end_ls, target, 1e-3 * sigma_s / noise)
        else {
            continue;
        };
        if end.covariance.names != result.covariance.names {
            continue;
        }
        let ratios: Vec<f64> = (0..n)
            .map(|i| (end.covariance.matrix[(i, i)] / result.covariance.matrix[(i, i)]).sqrt())
            .collect();
        // An end where some parameter became (nearly) unobservable is no linearisation of
        // a plausible solution: skipped (measured at 3 px with the mean log distance as `s`:
        // one end in 12 trials widened a sigma 3e6-fold).
        if !ratios.iter().all(|r| r.is_finite() && *r <= MAX_END_WIDENING) {
            continue;
        }
        report.ends += 1;
        for (w, r) in widen.iter_mut().zip(&ratios) {
            *w = w.max(*r);
        }
    }
    let mut result = result;
    widen_covariance(&mut result, &widen);
    report.max_widening = widen.iter().copied().fold(1.0, f64::max);
    (result, Some(report))
}

/// `C' = D C D` with `D = diag(widen)`: each camera sigma of `result` times its factor,
/// the correlations unchanged ([`profile_depth_scale`], [`bootstrap_covariance`]).
fn widen_covariance(result: &mut BundleResult, widen: &[f64]) {
    let m = &mut result.covariance.matrix;
    for i in 0..m.nrows().min(widen.len()) {
        for j in 0..m.ncols().min(widen.len()) {
            m[(i, j)] *= widen[i] * widen[j];
        }
    }
}

/// Module docs step 10: widen the covariance of the maximum-likelihood `result` (fitted
/// to `obs`) to the bootstrap spread of that least squares
/// ([`headalign_geometry::bootstrap::bootstrap_spread`]: point tracks drawn with
/// replacement, the encoder readings redrawn from the angle prior, each replicate started
/// at the estimate). As in [`profile_depth_scale`], `C' = D C D` with
/// `D = diag(max(1, sigma_boot / sigma))`, capped at [`MAX_END_WIDENING`]: the
/// correlations stay the linearisation's and the point estimate is unchanged. Why: with
/// small rotations in a near scene at 3 px the least squares spreads 1.1-1.2 times its
/// linearised sigma for the focal lengths (the removed `examples/bootstrap_mc.rs`). If fewer than 3
/// replicates converge, the covariance is left as it was and the report is `None`.
pub fn bootstrap_covariance(
    result: BundleResult,
    obs: &[BundleObservation],
    boot: &BootstrapOptions,
    options: &EstimationOptions,
) -> (BundleResult, Option<BootstrapReport>) {
    let ls = BundleOptions {
        robust: RobustLoss::None,
        noise_sigma_px: Some(result.report.sigma_px),
        ..options.bundle.clone()
    };
    let seeded = BootstrapOptions { seed: boot.seed.wrapping_add(options.seed), ..*boot };
    let Ok(spread) = bootstrap_spread(&result, obs, &ls, &seeded) else { return (result, None) };
    let n = result.covariance.matrix.nrows();
    let mut ratios: Vec<f64> =
        (0..n).map(|i| spread.sigma(i).unwrap_or(0.0) / result.covariance.matrix[(i, i)].sqrt()).collect();
    let widen: Vec<f64> =
        ratios.iter().map(|r| if r.is_finite() { r.clamp(1.0, MAX_END_WIDENING) } else { 1.0 }).collect();
    let mut result = result;
    widen_covariance(&mut result, &widen);
    ratios.retain(|r| r.is_finite());
    ratios.sort_by(f64::total_cmp);
    let report = BootstrapReport {
        replicates: spread.replicates,
        failed: spread.failed,
        max_widening: widen.iter().copied().fold(1.0, f64::max),
        median_ratio: ratios.get(ratios.len() / 2).copied().unwrap_or(f64::NAN),
    };
    (result, Some(report))
}

/// Module docs step 8: the least squares restarted from the depth-reversed rig. The
/// scene is far compared with the baseline (median depth about 20 baselines), so the
/// horizontal disparity that the baseline adds to the vergence's is small and nearly
/// constant over the points: the rig with the baseline's x component (right camera
/// frame) reversed, plus a small change of relative yaw and principal point, fits the
/// images almost as well, with the depth order of the points reversed around the
/// fixation distance. Both are least-squares minima and the solver stays in the one its
/// start leads to. Measured (the removed `examples/ratio_diag.rs`, seed 39, position 2, at 2 and
/// 3 px): the estimate had t = (+0.98, -0.11, -0.13) against (-0.98, -0.00, -0.19) at the
/// truth, right cx 63 px (6 sigma) off, and its cost was 40 (chi-square units) above the
/// minimum reached from the truth; from the reversed start the least squares reaches that
/// minimum (right cx 14 px off). Three restarts ([`RESTART_BASELINE_FLIPS`]; two more,
/// the baseline along the x axis both ways, when the estimate's is more than 45 deg from it,
/// [`SIDEWAYS_RESTART_MAX_COS`]), each with
/// every point re-triangulated under the restarted rig from the stereo match that agrees
/// best with its fitted observations ([`retriangulate_points_by_support`]): the x
/// component reversed, the whole baseline reversed (the other sign of `E`), and the y and z
/// components reversed (fig5-verge-tilt seeds 1119, 1130, 1211 at 3 px ended 2.9-5.5
/// chi-square units above the minimum reached from the truth; this start reaches it,
/// `docs/ratio-tail.md`). A restart wins only if it keeps every
/// observation in front of the cameras and lowers the cost (prior included) at the same
/// noise; the maximum-likelihood pass then re-classifies the observations from it. No
/// ground truth is used: this is the lower of two likelihood minima.
fn reversed_rig_restart(
    current: BundleResult,
    obs: Vec<BundleObservation>,
    candidates: &[BundleObservation],
    points: &PointSources<'_>,
    options: &EstimationOptions,
) -> Result<(BundleResult, Vec<BundleObservation>), AlignError> {
    let noise = current.report.sigma_px;
    if !(noise.is_finite() && noise > 0.0) {
        return Ok((current, obs));
    }
    let ls = BundleOptions {
        max_iterations: options.bundle.max_iterations.max(FINAL_ITERATIONS),
        robust: RobustLoss::None,
        noise_sigma_px: Some(noise),
        ..options.bundle.clone()
    };
    let base = current.chi2(noise, &options.bundle);
    // Costs are non-negative: below the gain no restart can win (the noise-free runs of
    // the experiments' Cramer-Rao bound, where a restart ran up to 300 iterations in vain).
    if base < RESTART_MIN_GAIN {
        return Ok((current, obs));
    }
    let every = vec![true; current.state.points.len()];
    let mut best: Option<(BundleResult, f64)> = None;
    let t = current.state.right_from_left.translation.vector;
    let mut baselines: Vec<Vector3<f64>> =
        RESTART_BASELINE_FLIPS.iter().map(|f| t.component_mul(f)).collect();
    // A baseline far from the cameras' x axes is no stereo head's: restart side by side too.
    if t.x.abs() < SIDEWAYS_RESTART_MAX_COS * t.norm() {
        baselines.extend([-1.0, 1.0].map(|sign| Vector3::x() * (sign * t.norm())));
    }
    for baseline in baselines {
        let mut start = current.state.clone();
        start.right_from_left.translation.vector = baseline;
        retriangulate_points_by_support(&mut start, points, &every, &obs, options.reselect_sigmas * noise);
        // A restart that fails or loses observations (points behind a camera) is no
        // competitor: its cost is over fewer residuals.
        let Some(r) = restart_adjustment(&start, &obs, &ls, noise, base) else { continue };
        if r.report.observations != current.report.observations {
            continue;
        }
        let cost = r.chi2(noise, &options.bundle);
        if cost < base - RESTART_MIN_GAIN && best.as_ref().is_none_or(|(_, c)| cost < *c) {
            best = Some((r, cost));
        }
    }
    match best {
        Some((won, _)) => maximum_likelihood_pass(&won, candidates, &obs, points, options),
        None => Ok((current, obs)),
    }
}

/// The restarts' baseline sign changes (right camera frame, multiplied component-wise):
/// the x component reversed, the whole baseline reversed, and its y and z components
/// reversed (the product of the other two: with the estimate, the four form the group of
/// these sign changes). The third, measured (the removed `examples/ratio_diag.rs`, fig5-verge-tilt seed
/// 1211, position 0, 3 px): the estimate had t = (-0.74, +0.19, +0.64), the minimum the
/// least squares reaches from the truth t = (-0.73, -0.43, -0.53) at 3.2 chi-square units
/// lower cost; the y-z reversed start reaches it (57 iterations), the other two do not. A
/// forward baseline component adds a disparity nearly proportional to the image radius
/// over a far scene, which a focal-length ratio absorbs, so its sign is as weakly
/// determined as the depth order of step 8 (the two minima differ in left and right fx by
/// 2-3 sigma).
const RESTART_BASELINE_FLIPS: [Vector3<f64>; 3] =
    [Vector3::new(-1.0, 1.0, 1.0), Vector3::new(-1.0, -1.0, -1.0), Vector3::new(1.0, -1.0, -1.0)];

/// Cosine of the angle between the estimated baseline and the right camera's x axis below
/// which [`reversed_rig_restart`] also restarts with the baseline along that axis, both
/// ways (45 deg). A stereo head's cameras sit side by side: verged by up to 20 deg the
/// baseline is within about 20 deg of each camera's x axis. Measured (the removed `examples/ratio_diag.rs`,
/// calibration seed 368 at 3 px): the estimate's baseline was (0.01, -0.36, -0.93), 84 deg
/// from the truth's (-0.99, 0.00, -0.13), along the optical axis, with left fx 146 px
/// (3.7 sigma) off, 127 chi-square units above the minimum the least squares reaches from
/// the truth; no sign change of that baseline is near it.
const SIDEWAYS_RESTART_MAX_COS: f64 = std::f64::consts::FRAC_1_SQRT_2;

/// One restart's least squares ([`reversed_rig_restart`]) with an early exit for the
/// hopeless ones: one still unconverged after [`RESTART_PROBE_ITERATIONS`] and more than
/// [`RESTART_ABANDON_GAP`] above the estimate's cost `base` there is given up (`None`, no
/// competitor); any other goes on to the full iteration budget
/// ([`bundle_adjust_with_checkpoint`]: its result is exactly what the full run alone
/// gives; before, a probe of that many iterations was run and then the whole adjustment
/// again from `start`: `fig5-verge-tilt --trials 100` 38.4 -> 36.2 s). Measured
/// (`experiment coverage`/`fig5-verge-tilt`, 2-3 px): most restarts from the reversed rig
/// do not converge in 300 iterations (far points creep towards infinity) and end tens to
/// thousands of chi-square units above the estimate; they were most of the estimate's
/// time.
fn restart_adjustment(
    start: &RigState,
    obs: &[BundleObservation],
    ls: &BundleOptions,
    noise: f64,
    base: f64,
) -> Option<BundleResult> {
    let mut hopeful = |probe: &BundleCheckpoint<'_>| probe.chi2(noise, ls) <= base + RESTART_ABANDON_GAP;
    bundle_adjust_with_checkpoint(start, obs, ls, RESTART_PROBE_ITERATIONS, &mut hopeful).ok().flatten()
}

/// Iterations of a restart's first, probing least squares ([`restart_adjustment`]).
const RESTART_PROBE_ITERATIONS: usize = 50;

/// Cost above the estimate's (chi-square units) at which a restart still unconverged after
/// [`RESTART_PROBE_ITERATIONS`] is given up ([`restart_adjustment`]). Measured over 258
/// restarts at 1-3 px with noise (logged `experiment` runs: coverage, fig5-verge-tilt,
/// calibration): the 4 that won (by 0.6-1.6 units) were
/// between 1 below and 82 above the estimate there; of the 104 above 200, none came below
/// it in 300 iterations. Twice the largest winner's gap, for margin.
const RESTART_ABANDON_GAP: f64 = 200.0;

/// Smallest cost decrease (chi-square units) for which a restart replaces the estimate
/// ([`reversed_rig_restart`]): far below the 40 between the two minima of seed 39 and far
/// above the solver's tolerance, so a restart that re-converges to the same minimum never
/// replaces it.
const RESTART_MIN_GAIN: f64 = 0.5;

/// Rounds of classification and least squares in `maximum_likelihood_pass` (measured:
/// the set is stable after 2-3 at 1-3 px).
pub const ML_ROUNDS: usize = 5;

/// Observations of points that keep at least [`MIN_POINT_OBSERVATIONS`], at least
/// `min_camera_observations` in each camera that sees them, and are not nearer than the
/// median point distance over [`DEPTH_RATIO`]. Far points are kept: at
/// 2-3 px the depth of a far point is ill-determined and its least-squares position can
/// lie beyond `DEPTH_RATIO` times the median, or near infinity, with every residual
/// within the noise; dropping them (as the robust pass does, against wrong tracks)
/// removed 20-40 of 200 points in some trials at 3 px, selected by their noise. Wrong
/// tracks are left to the studentised gate.
fn plausible_points(
    state: &RigState,
    gated: Vec<BundleObservation>,
    options: &EstimationOptions,
    noise_px: f64,
) -> Vec<BundleObservation> {
    let per_camera = camera_counts(state.points.len(), &gated);
    let mut counts: Vec<usize> = per_camera.iter().map(|k| k[0] + k[1]).collect();
    // A point seen once by one camera takes its depth from that observation alone
    // (`EstimationOptions::min_camera_observations`, `lone_depth_gate`).
    let lone = match &options.lone_depth_gate {
        Some(g) => lone_depth_outliers(state, &gated, noise_px, g),
        None => vec![false; state.points.len()],
    };
    for ((c, k), lone) in counts.iter_mut().zip(&per_camera).zip(lone) {
        if lone || k.iter().any(|&n| n > 0 && n < options.min_camera_observations) {
            *c = 0;
        }
    }
    let mut dist: Vec<f64> = (0..state.points.len())
        .filter(|&i| counts[i] >= MIN_POINT_OBSERVATIONS)
        .map(|i| state.points[i].coords.norm())
        .collect();
    dist.sort_by(f64::total_cmp);
    let median = dist.get(dist.len() / 2).copied().unwrap_or(f64::NAN);
    let tame = |i: usize| {
        let d = state.points[i].coords.norm();
        !d.is_nan() && d >= median / DEPTH_RATIO
    };
    gated.into_iter().filter(|o| counts[o.point] >= MIN_POINT_OBSERVATIONS && tame(o.point)).collect()
}

/// Observations of each point by the left and the right camera.
fn camera_counts(points: usize, obs: &[BundleObservation]) -> Vec<[usize; 2]> {
    let mut per_camera = vec![[0usize; 2]; points];
    for o in obs {
        if let Some(k) = per_camera.get_mut(o.point) {
            k[usize::from(o.side == Side::Right)] += 1;
        }
    }
    per_camera
}

/// Points seen once by one camera (and at least [`MIN_POINT_OBSERVATIONS`] times in
/// all) whose depth disagrees with their neighbours' ([`LoneDepthGate`]), flagged per
/// point of `state`.
///
/// Why: the other camera's views, a few degrees apart, fix such a point's direction but
/// hardly its depth, so the one observation sets the depth; a wrong observation near the
/// epipolar line is fitted exactly at a wrong depth (the removed `examples/bias_pipeline.rs`: 116 of
/// the 117 outliers the final adjustment kept at 3 px). A wrong pixel anywhere along the
/// line is a wrong disparity, usually far from that of the surface around the point.
///
/// The neighbours are the `gate.neighbours` points nearest in direction (from the
/// reference origin) among those seen by no camera exactly once; the deviation is
/// `ln d - median ln d_j`, over `hypot(sqrt 2 sigma_ln_d, 1.4826 MAD, roughness)` with
/// `sigma_ln_d = noise d / (f |t|)` the log-depth noise of one stereo disparity (`f` the
/// lone camera's fx, `|t|` the baseline, `d` the distance). Units: `noise_px` pixels,
/// `state` in any length unit. Pitfall: a lone point on a near object in front of a
/// wall is flagged too (its information is lost, not its correctness).
pub fn lone_depth_outliers(
    state: &RigState,
    obs: &[BundleObservation],
    noise_px: f64,
    gate: &LoneDepthGate,
) -> Vec<bool> {
    let n = state.points.len();
    let per_camera = camera_counts(n, obs);
    let mut flags = vec![false; n];
    let baseline = state.right_from_left.translation.vector.norm();
    let usable = |i: usize| {
        let d = state.points[i].coords.norm();
        d.is_finite() && d > 0.0
    };
    let anchored: Vec<(nalgebra::Vector3<f64>, f64)> = (0..n)
        .filter(|&i| {
            let k = per_camera[i];
            k[0] != 1 && k[1] != 1 && k[0] + k[1] >= MIN_POINT_OBSERVATIONS && usable(i)
        })
        .map(|i| (state.points[i].coords.normalize(), state.points[i].coords.norm().ln()))
        .collect();
    if anchored.len() < gate.neighbours || baseline.is_nan() || baseline <= 0.0 {
        return flags;
    }
    for (i, k) in per_camera.iter().enumerate() {
        let lone_side = match k {
            [1, r] if *r + 1 >= MIN_POINT_OBSERVATIONS => Side::Left,
            [l, 1] if *l + 1 >= MIN_POINT_OBSERVATIONS => Side::Right,
            _ => continue,
        };
        if !usable(i) {
            continue;
        }
        let p = state.points[i].coords;
        let dir = p.normalize();
        let mut near: Vec<(f64, f64)> = anchored.iter().map(|(u, l)| (u.dot(&dir), *l)).collect();
        near.sort_by(|a, b| b.0.total_cmp(&a.0));
        let mut logs: Vec<f64> = near.iter().take(gate.neighbours).map(|x| x.1).collect();
        logs.sort_by(f64::total_cmp);
        let median = logs[logs.len() / 2];
        let mut spread: Vec<f64> = logs.iter().map(|l| (l - median).abs()).collect();
        spread.sort_by(f64::total_cmp);
        let mad = spread[spread.len() / 2];
        let f = match lone_side {
            Side::Left => state.left.fx,
            Side::Right => state.right.fx,
        };
        let sigma_ln_d = noise_px * p.norm() / (f.abs() * baseline);
        let scale = (2.0 * sigma_ln_d * sigma_ln_d + (1.4826 * mad).powi(2) + gate.roughness.powi(2)).sqrt();
        flags[i] = (p.norm().ln() - median).abs() > gate.z * scale;
    }
    flags
}

/// Number of angle-prior residuals of a state under `options` (one per free joint angle of
/// every view but the reference).
fn prior_count(state: &RigState, options: &BundleOptions) -> usize {
    match (&state.motions, options.angle_prior_sigma) {
        (Motions::Joints { angles, .. }, Some(_)) => angles.iter().skip(1).map(Vec::len).sum(),
        _ => 0,
    }
}

/// The camera (non-point) parameters' share of the leverage of one residual component:
/// `p_camera / (2 n)`.
fn camera_parameter_share(result: &BundleResult) -> f64 {
    let n = result.report.observations.max(1) as f64;
    let cameras = result.covariance.names.len() as f64;
    cameras / (2.0 * n)
}

/// Standard deviation of an observation's residual in units of the pixel noise, under the
/// average-leverage approximation: a point seen `k` times spends its 3 parameters over
/// `2 k` residual components (leverage `3 / 2k` each), the camera parameters theirs over
/// all of them (`camera_share`). A fitted residual has variance `(1 - h) sigma^2`, the
/// prediction error of an observation left out of the fit `(1 + h) sigma^2` (the classical
/// internally / externally studentised residuals). Clamped to [0.3, 2] (`k` = 2: the point
/// is fixed by that observation alone).
pub fn residual_scale(k: usize, camera_share: f64, fitted: bool) -> f64 {
    let h = 3.0 / (2.0 * k.max(2) as f64) + camera_share.max(0.0);
    let v = if fitted { 1.0 - h } else { 1.0 + h };
    v.clamp(0.09, 4.0).sqrt()
}

/// The fraction of its variance that a 2D isotropic Gaussian keeps when truncated to
/// `|r| <= c sigma`: `|r|^2 / sigma^2` is chi-square with 2 degrees of freedom
/// (exponential with mean 2), so `E[|r|^2 | |r| <= c sigma] / (2 sigma^2) =
/// 1 - (c^2 / 2) e^(-c^2/2) / (1 - e^(-c^2/2))` (0.987 at c = 3.5; 1 as c grows).
pub fn truncated_variance_factor(c: f64) -> f64 {
    if !(c.is_finite() && c > 0.0) {
        return 1.0;
    }
    let t = 0.5 * c * c;
    let tail = (-t).exp();
    1.0 - t * tail / (1.0 - tail)
}

/// Noise estimate of a least-squares solution whose observations were selected by
/// `|r| <= c sigma` (studentised): `sqrt(RSS / ((m - p) kappa(c)))` with `RSS` the sum of
/// squared pixel residuals, `m = 2 n + priors` the residual count, `p` the parameters
/// (points included) and `kappa` [`truncated_variance_factor`]. The angle priors, nearly
/// hard constraints, contribute about no residual but fix one parameter each, hence their
/// count in `m`. `None` without redundancy.
pub fn truncated_noise_estimate(result: &BundleResult, priors: usize, c: f64) -> Option<f64> {
    let r = &result.report;
    let m = 2 * r.observations + priors;
    let dof = m.checked_sub(r.parameters).filter(|&d| d > 0)? as f64;
    let rss = r.final_rms_px.powi(2) * r.observations as f64;
    let s = (rss / (dof * truncated_variance_factor(c))).sqrt();
    (s.is_finite() && s > 0.0).then_some(s.max(1e-9))
}

pub(crate) fn rms(values: impl Iterator<Item = f64>) -> f64 {
    let (mut s, mut n) = (0.0, 0usize);
    for v in values {
        s += v * v;
        n += 1;
    }
    if n == 0 { 0.0 } else { (s / n as f64).sqrt() }
}

/// Robust noise estimate: 1.4826 x median of the residual norms scaled for a 2D
/// Gaussian (the median of a Rayleigh variable is sigma sqrt(2 ln 2)).
fn robust_sigma(state: &RigState, obs: &[BundleObservation]) -> f64 {
    let mut r: Vec<f64> = obs.iter().filter_map(|o| residual_pixels(state, o).map(|v| v.norm())).collect();
    if r.is_empty() {
        return 1.0;
    }
    r.sort_by(f64::total_cmp);
    r[r.len() / 2] / (2.0 * std::f64::consts::LN_2).sqrt()
}

/// What both initialisations need.
struct InitContext<'a> {
    views: &'a [View],
    rig: &'a [usize],
    recon: &'a [Reconstruction],
    point_tracks: &'a [u64],
    origin_slot: &'a [usize],
    commanded: &'a [[f64; 2]],
    min_tracks: usize,
}

impl InitContext<'_> {
    /// `ref_from_cam` of every rig view by resection of its left camera (intrinsics `k`)
    /// against the reference view's points; the reference view is the identity.
    fn resect_views(
        &self,
        k: &Intrinsics,
        reference: &HashMap<u64, Point3<f64>>,
    ) -> Result<Vec<Isometry3<f64>>, AlignError> {
        let options =
            headalign_geometry::resection::ResectionOptions { outlier_px: 10.0, ..Default::default() };
        let mut ref_from_cam = vec![Isometry3::identity(); self.rig.len()];
        for (slot, &vi) in self.rig.iter().enumerate().skip(1) {
            let (mut p3, mut p2) = (Vec::new(), Vec::new());
            for o in &self.views[vi].capture.left {
                if let Some(p) = reference.get(&o.track) {
                    p3.push(*p);
                    p2.push(o.pixel);
                }
            }
            let r = headalign_geometry::resection::resect(k, &p3, &p2, &Isometry3::identity(), &options)
                .step(&format!("initial motion of view '{}'", self.views[vi].name))?;
            ref_from_cam[slot] = r.cam_from_world.inverse();
        }
        Ok(ref_from_cam)
    }

    /// The Joints-model state from per-view poses `ref_from_cam` and points given in the
    /// frame of the view that reconstructed them (`point_in_cam(slot, X)`).
    #[allow(clippy::needless_range_loop)] // slots index several parallel per-view arrays
    fn state(
        &self,
        left: Intrinsics,
        right: Intrinsics,
        right_from_left: Isometry3<f64>,
        ref_from_cam: &[Isometry3<f64>],
        point_in_cam: impl Fn(usize, u64) -> Option<Point3<f64>>,
    ) -> Result<RigState, AlignError> {
        // Axes from single-joint views, directed like the encoder; the largest move wins.
        let mut axes: [Option<(Line, f64)>; 2] = [None, None];
        let moved = |x: f64| x.abs() > MOVED_DEG.to_radians();
        for slot in 1..self.rig.len() {
            for j in 0..2 {
                if moved(self.commanded[slot][1 - j]) || !moved(self.commanded[slot][j]) {
                    continue;
                }
                let Some(screw) = screw_from_isometry(&ref_from_cam[slot], 1e-6) else {
                    return Err(AlignError::NotARotation {
                        view: self.views[self.rig[slot]].name.clone(),
                        why: "the recovered motion has no rotation".into(),
                    });
                };
                let line = if screw.angle * self.commanded[slot][j] < 0.0 {
                    screw.axis.reversed()
                } else {
                    screw.axis
                };
                if axes[j].is_none_or(|(_, a)| self.commanded[slot][j].abs() > a) {
                    axes[j] = Some((line, self.commanded[slot][j].abs()));
                }
            }
        }
        let (Some((pan_axis, _)), Some((elev_axis, _))) = (axes[0], axes[1]) else {
            return Err(AlignError::MissingMotion("single-joint rotations about pan and elevation".into()));
        };
        let points =
            points_in_ref(self.point_tracks, self.origin_slot, ref_from_cam, self.min_tracks, point_in_cam)?;
        let angles: Vec<Vec<f64>> = self.commanded.iter().map(|c| c.to_vec()).collect();
        Ok(RigState {
            left,
            right,
            left_distortion: Default::default(),
            right_distortion: Default::default(),
            right_from_left,
            motions: Motions::Joints {
                axes: vec![pan_axis, elev_axis],
                angles: angles.clone(),
                commanded: angles,
            },
            points,
        })
    }
}

/// The start's points in the reference frame: track `point_tracks[i]` as reconstructed
/// by the view in slot `origin_slot[i]` (`point_in_cam(slot, track)`, that view's camera
/// frame), moved by `ref_from_cam[slot]`. A point with no finite position keeps the index
/// layout and starts far ahead; fewer than `min_tracks` points in front of their camera
/// is [`AlignError::TooFewTracks`].
pub(crate) fn points_in_ref(
    point_tracks: &[u64],
    origin_slot: &[usize],
    ref_from_cam: &[Isometry3<f64>],
    min_tracks: usize,
    point_in_cam: impl Fn(usize, u64) -> Option<Point3<f64>>,
) -> Result<Vec<Point3<f64>>, AlignError> {
    let mut points = Vec::with_capacity(point_tracks.len());
    let mut in_front = 0;
    for (&track, &slot) in point_tracks.iter().zip(origin_slot) {
        let p = match point_in_cam(slot, track) {
            Some(p) if p.coords.iter().all(|v| v.is_finite()) => {
                if p.z > 0.0 {
                    in_front += 1;
                }
                p
            }
            _ => Point3::new(0.0, 0.0, 1e3),
        };
        points.push(ref_from_cam[slot] * p);
    }
    if in_front < min_tracks {
        return Err(AlignError::TooFewTracks {
            what: "reconstructed in front of the cameras".into(),
            needed: min_tracks,
            got: in_front,
        });
    }
    Ok(points)
}

/// Initial state from the linear self-calibration chain (module docs, step 5).
#[allow(clippy::needless_range_loop)] // slots index several parallel per-view arrays
fn linear_initial_state(
    ctx: &InitContext<'_>,
    homographies: &[headalign_geometry::homography3d::Homography3],
    k0: &Intrinsics,
    p_r: &headalign_geometry::camera::ProjectiveCamera,
) -> Result<RigState, AlignError> {
    let lin = linear_self_calibration(homographies).step("linear self-calibration")?;
    let k_left = Intrinsics::from_matrix(&(k0.matrix() * lin.left.matrix())).step("left intrinsics")?;
    let h_pe = lin.euclidean_from_projective;
    let h_pe_inv = h_pe.try_inverse().ok_or_else(|| AlignError::Geometry {
        step: "Euclidean upgrade".into(),
        cause: headalign_geometry::GeometryError::Numerical("H_PE is singular".into()),
    })?;
    let (k_right, right_from_left) =
        decompose_camera(&(p_r.0 * h_pe_inv)).step("right camera decomposition")?;
    let baseline = right_from_left.translation.vector.norm();
    if !baseline.is_finite() || baseline <= 0.0 {
        return Err(AlignError::Geometry {
            step: "right camera decomposition".into(),
            cause: headalign_geometry::GeometryError::Degenerate("zero baseline".into()),
        });
    }
    let scale = 1.0 / baseline;
    let right_from_left =
        Isometry3::from_parts((right_from_left.translation.vector * scale).into(), right_from_left.rotation);
    // ref_from_cam_k = D_k^-1 (D maps reference points to view k), scaled.
    let mut ref_from_cam = vec![Isometry3::identity(); ctx.rig.len()];
    for (m, d) in lin.motions.iter().enumerate() {
        let inv = d.inverse();
        ref_from_cam[m + 1] = Isometry3::from_parts((inv.translation.vector * scale).into(), inv.rotation);
    }
    ctx.state(k_left, k_right, right_from_left, &ref_from_cam, |slot, track| {
        let (x, _, _) = ctx.recon[slot].get(&track)?;
        dehomogenise3(&(h_pe * x)).map(|p| Point3::from(p.coords * scale))
    })
}

/// Initial state with `K = K0` for both cameras, the rig of the frame's essential-matrix
/// decomposition, and each view's motion by resection of its left camera against the
/// reference view's quasi-Euclidean points.
#[allow(clippy::needless_range_loop)] // slots index several parallel per-view arrays
fn rough_initial_state(ctx: &InitContext<'_>, frame: &StereoFrame) -> Result<RigState, AlignError> {
    let k0 = frame.k0;
    let t = frame.right_conditioned.column(3).into_owned();
    let rot = headalign_geometry::so3::nearest_rotation(&frame.rotation_guess).ok_or_else(|| {
        AlignError::Geometry {
            step: "rough initialisation".into(),
            cause: headalign_geometry::GeometryError::Numerical("SVD failed".into()),
        }
    })?;
    let right_from_left =
        Isometry3::from_parts(t.into(), nalgebra::UnitQuaternion::from_rotation_matrix(&rot));
    let reference: HashMap<u64, Point3<f64>> =
        ctx.recon[0].iter().filter_map(|(&track, (x, _, _))| dehomogenise3(x).map(|p| (track, p))).collect();
    let ref_from_cam = ctx.resect_views(&k0, &reference)?;
    ctx.state(k0, k0, right_from_left, &ref_from_cam, |slot, track| {
        let (x, _, _) = ctx.recon[slot].get(&track)?;
        dehomogenise3(x)
    })
}

/// `K` of a rotating camera from its image homographies `G_i ~ K R_i K^-1` (Hartley's
/// rotating-camera self-calibration: `G w* G^T = w*`, the solver of
/// [`headalign_geometry::selfcal::dual_image_of_absolute_conic`]), in coordinates
/// conditioned by `k0`. Falls back to `k0` if the conic is not positive definite.
fn k_from_rotations(gs: &[Matrix3<f64>], k0: &Intrinsics) -> Intrinsics {
    let (k, k_inv) = (k0.matrix(), k0.inverse_matrix());
    let ms: Vec<Matrix3<f64>> = gs
        .iter()
        .filter_map(|g| {
            let m = k_inv * g * k;
            let d = m.determinant();
            (d.is_finite() && d != 0.0).then(|| m / d.cbrt())
        })
        .collect();
    headalign_geometry::selfcal::dual_image_of_absolute_conic(&ms)
        .and_then(|w| headalign_geometry::selfcal::k_from_dual_conic(&w))
        .and_then(|kn| Intrinsics::from_matrix(&(k * kn.matrix())))
        .ok()
        .filter(|kk| kk.fx > 0.3 * k0.fx && kk.fx < 3.0 * k0.fx && kk.fy > 0.3 * k0.fy && kk.fy < 3.0 * k0.fy)
        .unwrap_or(*k0)
}

/// Initial state from the image homographies of the rotations: each camera's `K` by
/// rotating-camera self-calibration, the rig from `E = K_R^T F K_L`, Euclidean
/// triangulation, and each view's motion by resection of its left camera.
#[allow(clippy::needless_range_loop)] // slots index several parallel per-view arrays
fn rotation_initial_state(
    ctx: &InitContext<'_>,
    f: &FundamentalMatrix,
    matches: &[(Point2<f64>, Point2<f64>)],
    image_rotations: &[PlanePair],
    k0: &Intrinsics,
) -> Result<RigState, AlignError> {
    let (k_left, k_right) = rotation_intrinsics(image_rotations, k0);
    let right_from_left = relative_pose(&f.0, &k_left, &k_right, matches).step("relative pose of the rig")?;
    rig_start(ctx, f, k_left, k_right, right_from_left)
}

/// Each camera's `K` by rotating-camera self-calibration from its plane homographies.
fn rotation_intrinsics(image_rotations: &[PlanePair], k0: &Intrinsics) -> (Intrinsics, Intrinsics) {
    let gl: Vec<Matrix3<f64>> = image_rotations.iter().map(|g| g.0).collect();
    let gr: Vec<Matrix3<f64>> = image_rotations.iter().map(|g| g.1).collect();
    (k_from_rotations(&gl, k0), k_from_rotations(&gr, k0))
}

/// A start from intrinsics and a rig pose: points triangulated (optimal, under `f`) in
/// the view that first reconstructed them, views resected against the reference points.
fn rig_start(
    ctx: &InitContext<'_>,
    f: &FundamentalMatrix,
    k_left: Intrinsics,
    k_right: Intrinsics,
    right_from_left: Isometry3<f64>,
) -> Result<RigState, AlignError> {
    let p_l = ProjectiveCamera::from_pose(&k_left, &Isometry3::identity());
    let p_r = ProjectiveCamera::from_pose(&k_right, &right_from_left);
    let triangulate = |slot: usize, track: u64| -> Option<Point3<f64>> {
        let (_, l, r) = ctx.recon[slot].get(&track)?;
        dehomogenise3(&triangulate_optimal(f, &p_l, &p_r, l, r).ok()?)
    };
    let reference: Vec<(u64, Point3<f64>)> = ctx.recon[0]
        .keys()
        .filter_map(|&t| triangulate(0, t).filter(|p| p.z > 0.0).map(|p| (t, p)))
        .collect();
    let reference: HashMap<u64, Point3<f64>> = reference.into_iter().collect();
    let ref_from_cam = ctx.resect_views(&k_left, &reference)?;
    ctx.state(k_left, k_right, right_from_left, &ref_from_cam, triangulate)
}

/// The calibrated start: the rotation start's intrinsics, but the rig pose estimated
/// directly with them ([`headalign_geometry::essential::calibrated_relative_pose`], 5 dof,
/// MSAC over all stereo matches at the F threshold) from the pose decomposed from `F` and
/// from generic stereo-head poses (identity rotation, baseline along x or y), instead of
/// taken from `F`. With nearly parallel cameras `F`'s epipole is ill-determined: at 3 px
/// the best-supported `F` of some seeds had its epipole inside the image (true: thousands
/// of pixels outside), and every `F`-based start put the near points behind the cameras.
/// With `lateral_only`, the only start is the stereo-head prior (identity rotation,
/// baseline along x) and the rough intrinsics are used: a scene dominated by a wall facing
/// the head admits, like a plane homography, a second relative pose with the baseline
/// along the wall's normal, which the stereo matches alone cannot reject at 3 px (seed 87:
/// every stereo-only start ended with the baseline forward); the rotations in the
/// adjustment can, so this start goes to the screening whatever its stereo cost.
fn calibrated_initial_state(
    ctx: &InitContext<'_>,
    f: &FundamentalMatrix,
    matches: &[(Point2<f64>, Point2<f64>)],
    (k_left, k_right): (Intrinsics, Intrinsics),
    threshold_px: f64,
    lateral_only: bool,
) -> Result<RigState, AlignError> {
    use headalign_geometry::essential::{calibrated_relative_pose, fundamental_from_pose};
    use nalgebra::{Translation3, UnitQuaternion};
    let lateral = Isometry3::from_parts(Translation3::new(1.0, 0.0, 0.0), UnitQuaternion::identity());
    let mut starts = vec![lateral];
    if !lateral_only {
        starts.push(Isometry3::from_parts(Translation3::new(0.0, 1.0, 0.0), UnitQuaternion::identity()));
        if let Ok(p) = relative_pose(&f.0, &k_left, &k_right, matches) {
            starts.push(p);
            for t in [Translation3::new(1.0, 0.0, 0.0), Translation3::new(0.0, 1.0, 0.0)] {
                starts.push(Isometry3::from_parts(t, p.rotation));
            }
        }
    }
    let (right_from_left, _) = calibrated_relative_pose(&k_left, &k_right, &starts, matches, threshold_px)
        .step("calibrated relative pose of the rig")?;
    let f_cal = fundamental_from_pose(&k_left, &k_right, &right_from_left);
    rig_start(ctx, &f_cal, k_left, k_right, right_from_left)
}

/// RANSAC adapter for 3D homographies whose least-squares fit (used by local
/// optimisation and the guided loop) is the DLT polished by Levenberg-Marquardt on
/// transfer error: the algebraic DLT over-weights far points, whose triangulated depth is
/// poor, and under 1 px noise its consensus is only about half the true inliers.
pub(crate) struct PolishedHomography<'a>(pub(crate) &'a Homography3Estimator);

impl Estimator for PolishedHomography<'_> {
    type Datum = Quadruplet;
    type Model = TransferModel;

    fn sample_size(&self) -> usize {
        self.0.sample_size()
    }

    /// Minimal DLT models with `det H <= 0` are dropped: `det(lambda H) = lambda^4 det H`,
    /// so no scaling makes them conjugate to a rigid motion.
    fn fit_minimal(&self, data: &[Quadruplet], sample: &[usize]) -> Vec<TransferModel> {
        let mut models = self.0.fit_minimal(data, sample);
        models.retain(|m| m.h.0.determinant() > 0.0);
        models
    }

    fn fit_inliers(&self, data: &[Quadruplet], inliers: &[usize]) -> Option<TransferModel> {
        let dlt = self.0.fit_inliers(data, inliers)?;
        let subset: Vec<Quadruplet> = inliers.iter().map(|&i| data[i]).collect();
        let refined = refine_transfer(&dlt, &self.0.p_left, &self.0.p_right, &subset).unwrap_or(dlt);
        (refined.h.0.determinant() > 0.0).then_some(refined)
    }

    fn residual(&self, model: &TransferModel, datum: &Quadruplet) -> f64 {
        self.0.residual(model, datum)
    }
}

/// Indices of the quadruplets consistent with a plane homography in both the left and the
/// right image pair (4-point RANSAC, `threshold_px`). If a RANSAC fails (too few
/// quadruplets), every quadruplet passes and the 3D stage decides.
fn screen_rotation(quads: &[Quadruplet], threshold_px: f64, seed: u64) -> (Vec<usize>, Option<PlanePair>) {
    let options = RansacOptions { threshold: threshold_px, seed, ..RansacOptions::default() };
    let left: Vec<(Point2<f64>, Point2<f64>)> = quads.iter().map(|q| (q.left0, q.left1)).collect();
    let right: Vec<(Point2<f64>, Point2<f64>)> = quads.iter().map(|q| (q.right0, q.right1)).collect();
    let keep = |data: &[(Point2<f64>, Point2<f64>)]| -> (Vec<bool>, Option<Matrix3<f64>>) {
        match ransac(&Homography2Estimator, data, &options) {
            Ok(rep) => {
                let mut mask = vec![false; data.len()];
                for i in rep.inliers {
                    mask[i] = true;
                }
                (mask, Some(rep.model.0))
            }
            Err(_) => (vec![true; data.len()], None),
        }
    };
    let ((l, gl), (r, gr)) = (keep(&left), keep(&right));
    let kept = (0..quads.len()).filter(|&i| l[i] && r[i]).collect();
    (kept, gl.zip(gr))
}

/// `start` polished by Levenberg-Marquardt on the transfer error of `subset`; `None` if the
/// result is not a rigid conjugate (det <= 0).
pub(crate) fn polish(
    start: &TransferModel,
    quads: &[Quadruplet],
    subset: &[usize],
    p_l: &headalign_geometry::camera::ProjectiveCamera,
    p_r: &headalign_geometry::camera::ProjectiveCamera,
) -> Option<TransferModel> {
    let sub: Vec<Quadruplet> = subset.iter().map(|&i| quads[i]).collect();
    let m = refine_transfer(start, p_l, p_r, &sub).ok()?;
    (m.h.0.determinant() > 0.0).then_some(m)
}

/// Re-triangulate, with the calibrated rig of `state`, every point that lies behind the
/// reference camera or is not finite, from the stereo match of the view that first
/// reconstructed it; points that still do not triangulate in front are left as they are.
fn retriangulate_lost_points(
    state: &mut RigState,
    point_tracks: &[u64],
    origin_slot: &[usize],
    recon: &[Reconstruction],
) {
    let lost: Vec<bool> = (0..point_tracks.len())
        .map(|i| {
            let cam_from_ref = state.motions.ref_from_cam(origin_slot[i]).inverse();
            !state
                .points
                .get(i)
                .is_some_and(|p| p.coords.iter().all(|v| v.is_finite()) && (cam_from_ref * p).z > 0.0)
        })
        .collect();
    retriangulate_points(state, &PointSources { point_tracks, origin_slot, recon }, &lost);
}

/// Where each bundle point came from: its track, the rig view that first reconstructed
/// it, and the per-view stereo reconstructions.
struct PointSources<'a> {
    point_tracks: &'a [u64],
    origin_slot: &'a [usize],
    recon: &'a [Reconstruction],
}

/// Linear triangulation, with the calibrated rig of `state`, of the points flagged in
/// `which` from the stereo match of the view that first reconstructed them; points that do
/// not triangulate in front of both cameras are left as they are.
fn retriangulate_points(state: &mut RigState, src: &PointSources<'_>, which: &[bool]) {
    let p_l = ProjectiveCamera::from_pose(&state.left, &Isometry3::identity());
    let p_r = ProjectiveCamera::from_pose(&state.right, &state.right_from_left);
    let (point_tracks, origin_slot, recon) = (src.point_tracks, src.origin_slot, src.recon);
    for (i, track) in point_tracks.iter().enumerate() {
        if !which.get(i).copied().unwrap_or(false) {
            continue;
        }
        let slot = origin_slot[i];
        let Some((_, l, r)) = recon[slot].get(track) else { continue };
        let Ok(x) = headalign_geometry::triangulation::triangulate_linear(&p_l, &p_r, l, r) else { continue };
        let Some(p) = dehomogenise3(&x) else { continue };
        if p.z > 0.0 && (state.right_from_left * p).z > 0.0 {
            state.points[i] = state.motions.ref_from_cam(slot) * p;
        }
    }
}

/// [`retriangulate_points`] that does not trust the view the point was first
/// reconstructed in: each flagged point is triangulated from the stereo match of every rig
/// view that has one, and the position with the lowest truncated cost over the point's
/// `support` observations (squared residuals, each at most `gate_px^2`; MSAC) wins; then
/// the point is triangulated from all of its support within `gate_px` of that position
/// (N-view DLT), kept if that lowers the cost again. A point without support keeps the
/// first view's triangulation, as [`retriangulate_points`] gives it.
///
/// Why: an outlier can lie within the stereo threshold of its epipolar line, and in the
/// first view it makes a wrong stereo match that places the point at a wrong depth; every
/// good observation of the point then misses the re-selection gate and the point is lost
/// with all of them. Measured (the removed `examples/selection_loss.rs`, fig5 protocol, seed 5 at
/// 2 px): two points (9 good observations each, the reference view's left one 342 and
/// 167 px off) were lost that way, in the noise-free run too. Paired over 250 trials at 2
/// and 3 px nearly every trial changes a little, the bounds fall by 0.2-0.4 % and the
/// errors move by a few percent either way (`docs/efficiency.md`, nineteenth session).
fn retriangulate_points_by_support(
    state: &mut RigState,
    src: &PointSources<'_>,
    which: &[bool],
    support: &[BundleObservation],
    gate_px: f64,
) {
    retriangulate_points(state, src, which);
    let mut by_point: Vec<Vec<&BundleObservation>> = vec![Vec::new(); state.points.len()];
    for o in support {
        if which.get(o.point).copied().unwrap_or(false)
            && let Some(list) = by_point.get_mut(o.point)
        {
            list.push(o);
        }
    }
    let views = state.motions.view_count();
    let ref_from_cam: Vec<Isometry3<f64>> = (0..views).map(|v| state.motions.ref_from_cam(v)).collect();
    let p_l = ProjectiveCamera::from_pose(&state.left, &Isometry3::identity());
    let p_r = ProjectiveCamera::from_pose(&state.right, &state.right_from_left);
    // The cameras of every (view, side), for the N-view triangulation.
    let camera = |view: usize, side: Side| -> Option<ProjectiveCamera> {
        let cam_from_ref = ref_from_cam.get(view)?.inverse();
        Some(match side {
            Side::Left => ProjectiveCamera::from_pose(&state.left, &cam_from_ref),
            Side::Right => ProjectiveCamera::from_pose(&state.right, &(state.right_from_left * cam_from_ref)),
        })
    };
    let g2 = gate_px * gate_px;
    let residual = |p: &Point3<f64>, o: &BundleObservation| {
        ref_from_cam.get(o.view).and_then(|pose| residual_pixels_at(state, pose, p, o))
    };
    let cost = |p: &Point3<f64>, obs: &[&BundleObservation]| -> f64 {
        obs.iter().map(|o| residual(p, o).map_or(g2, |r| r.norm_squared().min(g2))).sum()
    };
    let (point_tracks, recon) = (src.point_tracks, src.recon);
    let mut moved: Vec<(usize, Point3<f64>)> = Vec::new();
    for (i, obs) in by_point.iter().enumerate() {
        let (Some(track), Some(current)) = (point_tracks.get(i), state.points.get(i)) else { continue };
        if obs.is_empty() {
            continue;
        }
        let mut best = (*current, cost(current, obs));
        for (slot, map) in recon.iter().enumerate().take(views) {
            let Some((_, l, r)) = map.get(track) else { continue };
            let Ok(x) = headalign_geometry::triangulation::triangulate_linear(&p_l, &p_r, l, r) else {
                continue;
            };
            let Some(p) = dehomogenise3(&x) else { continue };
            if !(p.z > 0.0 && (state.right_from_left * p).z > 0.0) {
                continue;
            }
            let p = ref_from_cam[slot] * p;
            let c = cost(&p, obs);
            if c < best.1 {
                best = (p, c);
            }
        }
        let inliers: Vec<&BundleObservation> = obs
            .iter()
            .copied()
            .filter(|o| residual(&best.0, o).is_some_and(|r| r.norm_squared() <= g2))
            .collect();
        let cams: Option<Vec<ProjectiveCamera>> = inliers.iter().map(|o| camera(o.view, o.side)).collect();
        if let Some(cams) = cams
            && cams.len() >= 3
        {
            let pixels: Vec<Point2<f64>> = inliers.iter().map(|o| o.pixel).collect();
            if let Some(p) = headalign_geometry::triangulation::triangulate_views(&cams, &pixels)
                .ok()
                .and_then(|x| dehomogenise3(&x))
            {
                let c = cost(&p, obs);
                if c < best.1 {
                    best = (p, c);
                }
            }
        }
        moved.push((i, best.0));
    }
    for (i, p) in moved {
        state.points[i] = p;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A state whose points lie at the given distances from the reference camera (only
    /// their norms matter to [`near_depth_step`]).
    fn state_at(depths: &[f64]) -> RigState {
        RigState {
            left: Intrinsics::new(700.0, 700.0, 400.0, 300.0),
            right: Intrinsics::new(700.0, 700.0, 400.0, 300.0),
            left_distortion: Default::default(),
            right_distortion: Default::default(),
            right_from_left: nalgebra::Isometry3::translation(-1.0, 0.0, 0.0),
            motions: Motions::Free { ref_from_cam: vec![nalgebra::Isometry3::identity()] },
            points: depths.iter().map(|&d| nalgebra::Point3::new(0.0, 0.0, d)).collect(),
        }
    }

    fn obs_at(point: usize, view: usize, side: Side, x: f64, y: f64) -> BundleObservation {
        BundleObservation { point, view, side, pixel: nalgebra::Point2::new(x, y) }
    }

    /// `min_camera_observations`: a point seen three times by the left camera and once by
    /// the right goes with 2 and stays with 1; a point seen by one camera only, or twice
    /// by each, stays; the depth rule is unaffected (all points at 5 m).
    #[test]
    fn points_seen_once_by_a_camera_are_left_out() {
        let state = state_at(&[5.0, 5.0, 5.0]);
        let mut obs = Vec::new();
        for v in 0..3 {
            obs.push(obs_at(0, v, Side::Left, 100.0, 100.0));
            obs.push(obs_at(1, v, Side::Left, 200.0, 100.0));
        }
        obs.push(obs_at(0, 0, Side::Right, 90.0, 100.0));
        obs.push(obs_at(1, 3, Side::Left, 200.0, 100.0));
        for v in 0..2 {
            obs.push(obs_at(2, v, Side::Left, 300.0, 100.0));
            obs.push(obs_at(2, v, Side::Right, 290.0, 100.0));
        }
        let points_of = |kept: Vec<BundleObservation>| -> Vec<usize> {
            let mut p: Vec<usize> = kept.iter().map(|o| o.point).collect();
            p.sort_unstable();
            p.dedup();
            p
        };
        let with = |k: usize| EstimationOptions { min_camera_observations: k, ..Default::default() };
        assert_eq!(points_of(plausible_points(&state, obs.clone(), &with(2), 1.0)), [1, 2]);
        assert_eq!(points_of(plausible_points(&state, obs.clone(), &with(1), 1.0)), [0, 1, 2]);
        assert_eq!(plausible_points(&state, obs.clone(), &with(1), 1.0).len(), obs.len());
    }

    /// `lone_depth_outliers`: on a wall at 10 baselines (35 points seen twice by each
    /// camera), points seen three times by the left camera and once by the right are
    /// flagged when their depth is off the wall beyond the gate (3: ln 0.3 = -1.2, about 12
    /// of its 0.10 deviations at 1 px) and kept near it (12: 1.8 deviations); a point seen
    /// once by each camera (too few observations) and the wall's points are never flagged;
    /// at 100 px of noise the near point's own stereo depth is too noisy to flag it (1.9
    /// deviations); with too few well-seen points nothing is flagged.
    #[test]
    fn lone_points_off_their_neighbours_depth_are_flagged() {
        let mut points = Vec::new();
        let mut obs = Vec::new();
        for i in 0..35 {
            let (x, y) = (f64::from(i % 7) - 3.0, f64::from(i / 7) - 2.0);
            points.push(nalgebra::Point3::new(x, y, 10.0));
            for v in 0..2 {
                obs.push(obs_at(i as usize, v, Side::Left, 0.0, 0.0));
                obs.push(obs_at(i as usize, v, Side::Right, 0.0, 0.0));
            }
        }
        // Lone points along the direction (0.5, 0.5, 10), at depths 3, 10 and 12, and one
        // seen once by each camera at depth 3.
        let dir = nalgebra::Vector3::new(0.5, 0.5, 10.0).normalize();
        for (k, d) in [3.0, 10.0, 12.0, 3.0].into_iter().enumerate() {
            points.push(nalgebra::Point3::from(dir * d));
            let views = if k == 3 { 1 } else { 3 };
            for v in 0..views {
                obs.push(obs_at(35 + k, v, Side::Left, 0.0, 0.0));
            }
            obs.push(obs_at(35 + k, 0, Side::Right, 0.0, 0.0));
        }
        let mut state = state_at(&[]);
        state.points = points;
        let gate = LoneDepthGate::DEFAULT;
        let flags = lone_depth_outliers(&state, &obs, 1.0, &gate);
        let flagged: Vec<usize> = (0..flags.len()).filter(|&i| flags[i]).collect();
        assert_eq!(flagged, [35]);
        assert!(lone_depth_outliers(&state, &obs, 100.0, &gate).iter().all(|f| !f));
        let few = LoneDepthGate { neighbours: 36, ..gate };
        assert!(lone_depth_outliers(&state, &obs, 1.0, &few).iter().all(|f| !f));
        // plausible_points drops the flagged point's observations and only those.
        let kept = plausible_points(&state, obs.clone(), &EstimationOptions::default(), 1.0);
        assert!(kept.iter().all(|o| o.point != 35));
        assert_eq!(kept.len(), obs.len() - 4 - 2);
        let off = EstimationOptions { lone_depth_gate: None, ..Default::default() };
        assert_eq!(plausible_points(&state, obs.clone(), &off, 1.0).len(), obs.len() - 2);
    }

    /// A step between two planes: exactly the points with a neighbour across the step
    /// within the radius are flagged (grid spacing 20 px, radius 40 px: two columns on
    /// each side); a plane alone flags nothing; neighbours in another image do not count.
    #[test]
    fn depth_step_flags_the_columns_beside_the_step() {
        let gate = DepthStepGate::IMAGES;
        let (mut depths, mut obs) = (Vec::new(), Vec::new());
        for i in 0..21 {
            for j in 0..21 {
                let x = 20.0 * f64::from(i);
                obs.push(obs_at(depths.len(), 0, Side::Left, x, 20.0 * f64::from(j)));
                depths.push(if x < 200.0 { 1.5 } else { 3.0 });
            }
        }
        let flags = near_depth_step(&state_at(&depths), &obs, &gate);
        for o in &obs {
            let expected = (160.0..=220.0).contains(&o.pixel.x);
            assert_eq!(flags[o.point], expected, "pixel {:?}", o.pixel);
        }
        let flat = vec![3.0; depths.len()];
        assert!(near_depth_step(&state_at(&flat), &obs, &gate).iter().all(|f| !f));
        // The same pixels, each point in its own image: nothing to compare with.
        let apart: Vec<BundleObservation> =
            obs.iter().enumerate().map(|(i, o)| BundleObservation { view: i, ..*o }).collect();
        assert!(near_depth_step(&state_at(&depths), &apart, &gate).iter().all(|f| !f));
        let bad = EstimationOptions {
            depth_step: Some(DepthStepGate { radius_px: 40.0, ratio: 1.0 }),
            ..EstimationOptions::default()
        };
        assert!(bad.validate().is_err());
        let bad = EstimationOptions {
            depth_step: Some(DepthStepGate { radius_px: f64::NAN, ratio: 1.2 }),
            ..EstimationOptions::default()
        };
        assert!(bad.validate().is_err());
    }

    proptest::proptest! {
        /// The bucketed search finds exactly what comparing every pair finds.
        #[test]
        fn depth_step_matches_brute_force(
            seed in 0u64..1000,
            n in 2usize..120,
            radius in 5.0f64..60.0,
        ) {
            use rand::{RngExt, SeedableRng};
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            let depths: Vec<f64> = (0..n).map(|_| 1.0 + 3.0 * rng.random::<f64>()).collect();
            let obs: Vec<BundleObservation> = (0..2 * n)
                .map(|i| {
                    let side = if rng.random::<bool>() { Side::Left } else { Side::Right };
                    let (x, y) = (-50.0 + 300.0 * rng.random::<f64>(), 200.0 * rng.random::<f64>());
                    obs_at(i % n, rng.random_range(0..2usize), side, x, y)
                })
                .collect();
            let gate = DepthStepGate { radius_px: radius, ratio: 1.3 };
            let fast = near_depth_step(&state_at(&depths), &obs, &gate);
            let mut slow = vec![false; n];
            for a in &obs {
                for b in &obs {
                    let (da, db) = (depths[a.point], depths[b.point]);
                    if a.point != b.point && a.view == b.view && a.side == b.side
                        && (a.pixel - b.pixel).norm() <= radius && da.max(db) > 1.3 * da.min(db)
                    {
                        slow[a.point] = true;
                    }
                }
            }
            proptest::prop_assert_eq!(fast, slow);
        }
    }

    proptest::proptest! {
        /// A point whose first stereo match holds an outlier (here the reference view's
        /// left pixel, tens to hundreds of pixels off) is placed by the views that agree
        /// with its other observations: noise-free, back at its true position to 1e-9 of
        /// its distance. A point with no support keeps the first view's triangulation.
        #[test]
        fn retriangulation_by_support_ignores_a_wrong_first_match(
            seed in 0u64..1000,
            offset_px in 20.0f64..300.0,
        ) {
            use rand::{RngExt, SeedableRng};
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            let mut u = |a: f64, b: f64| a + (b - a) * rng.random::<f64>();
            let k = Intrinsics::new(u(600.0, 900.0), u(600.0, 900.0), u(350.0, 420.0), u(260.0, 320.0));
            let rig = Isometry3::new(Vector3::new(-1.0, u(-0.05, 0.05), u(-0.1, 0.1)), Vector3::new(0.0, u(-0.2, 0.2), 0.0));
            let poses: Vec<Isometry3<f64>> = (0..4)
                .map(|v| if v == 0 {
                    Isometry3::identity()
                } else {
                    Isometry3::new(Vector3::new(u(-0.2, 0.2), u(-0.2, 0.2), u(-0.2, 0.2)), Vector3::new(u(-0.06, 0.06), u(-0.06, 0.06), 0.0))
                })
                .collect();
            let truth = Point3::new(u(-2.0, 2.0), u(-1.5, 1.5), u(4.0, 20.0));
            let mut state = RigState {
                left: k,
                right: k,
                left_distortion: Default::default(),
                right_distortion: Default::default(),
                right_from_left: rig,
                motions: Motions::Free { ref_from_cam: poses.clone() },
                points: vec![Point3::new(0.0, 0.0, 1.0); 2],
            };
            let pixel = |v: usize, side: Side| -> Point2<f64> {
                let probe = BundleObservation { point: 0, view: v, side, pixel: Point2::origin() };
                let r: nalgebra::Vector2<f64> = residual_pixels_at(&state, &poses[v], &truth, &probe).unwrap_or_default();
                Point2::from(r)
            };
            let wrong = pixel(0, Side::Left) + nalgebra::Vector2::new(offset_px, 0.5 * offset_px);
            let mut recon: Vec<Reconstruction> = vec![BTreeMap::new(); 4];
            let mut support = Vec::new();
            for (v, map) in recon.iter_mut().enumerate() {
                let (l, r) = (if v == 0 { wrong } else { pixel(v, Side::Left) }, pixel(v, Side::Right));
                map.insert(7, (Vector4::zeros(), l, r));
                map.insert(8, (Vector4::zeros(), l, r));
                support.push(BundleObservation { point: 0, view: v, side: Side::Left, pixel: l });
                support.push(BundleObservation { point: 0, view: v, side: Side::Right, pixel: r });
            }
            let src = PointSources { point_tracks: &[7, 8], origin_slot: &[0, 0], recon: &recon };
            let mut first_view_only = state.clone();
            retriangulate_points(&mut first_view_only, &src, &[true, true]);
            retriangulate_points_by_support(&mut state, &src, &[true, true], &support, 1.0);
            let err = (state.points[0] - truth).norm() / truth.coords.norm();
            proptest::prop_assert!(err < 1e-9, "relative error {err:e}");
            proptest::prop_assert_eq!(state.points[1], first_view_only.points[1]);
        }
    }

    fn view(name: &str, pan: f64, elevation: f64, verge: f64) -> View {
        View {
            name: name.into(),
            capture: StereoCapture {
                encoders: Encoders { pan, elevation, verge_left: verge, verge_right: verge },
                image_size: [768, 576],
                left: Vec::new(),
                right: Vec::new(),
            },
        }
    }

    #[test]
    fn classifies_rig_and_verge_views() {
        let views = [
            view("i", 0.0, 0.0, 0.0),
            view("e", 0.0, 3.0, 0.0),
            view("p", 3.0, 0.0, 0.0),
            view("v", 0.0, 0.0, 3.0),
        ];
        let roles = classify_views(&views).unwrap();
        assert_eq!(roles[0], ViewRole::Reference);
        assert_eq!(roles[1], ViewRole::Rig { pan_deg: 0.0, elevation_deg: 3.0 });
        assert_eq!(roles[3], ViewRole::Verge);
    }

    /// Read jitter of a joint at rest (0.02 deg, two encoder sigmas) is not a motion: the
    /// pan view stays a single-joint rotation and the elevation view is not a vergence.
    #[test]
    fn encoder_jitter_is_not_a_motion() {
        let mut e = view("e", 0.0, 3.0, 0.0);
        e.capture.encoders.verge_left = 0.02;
        let views = [view("i", 0.0, 0.0, 0.0), e, view("p", 3.0, 0.02, 0.0)];
        let roles = classify_views(&views).unwrap();
        assert_eq!(roles[1], ViewRole::Rig { pan_deg: 0.0, elevation_deg: 3.0 });
        assert!(matches!(roles[2], ViewRole::Rig { pan_deg, .. } if pan_deg == 3.0));
    }

    #[test]
    fn names_each_bad_motion() {
        let same = [view("i", 0.0, 0.0, 0.0), view("e1", 0.0, 3.0, 0.0), view("e2", 0.0, -3.0, 0.0)];
        let err = classify_views(&same).unwrap_err().to_string();
        assert!(err.contains("'e1'") && err.contains("'e2'") && err.contains("same axis"), "{err}");
        let still = [view("i", 0.0, 0.0, 0.0), view("e", 0.0, 3.0, 0.0), view("x", 0.0, 0.0, 0.0)];
        assert!(classify_views(&still).unwrap_err().to_string().contains("not a rotation"));
        let no_pan = [view("i", 0.0, 0.0, 0.0), view("e", 0.0, 3.0, 0.0), view("b", 3.0, 3.0, 0.0)];
        assert!(classify_views(&no_pan).unwrap_err().to_string().contains("pan joint alone"));
    }

    #[test]
    fn too_few_tracks_is_an_error() {
        let views = [view("i", 0.0, 0.0, 0.0), view("e", 0.0, 3.0, 0.0), view("p", 3.0, 0.0, 0.0)];
        let err = estimate_rig(&views, &EstimationOptions::default()).unwrap_err();
        assert!(matches!(err, AlignError::TooFewTracks { .. }), "{err}");
    }

    /// The rig views of a simulated session (the benchmark's capture plan, without the
    /// vergence view).
    fn sim_views(scenario: headalign_sim::Scenario) -> Vec<View> {
        use headalign_platform::StereoHead;
        let mut head = headalign_sim::SimulatedHead::new(scenario).unwrap();
        let e0 = head.read_encoders().unwrap();
        let plan = crate::procedure::capture_plan(&e0, &crate::procedure::VergeTiltOptions::default());
        let mut out = Vec::new();
        for (name, enc) in plan {
            head.move_to(&enc).unwrap();
            out.push(View { name, capture: head.capture().unwrap() });
        }
        out.pop();
        out
    }

    /// A rotated view with too few tracks (8 of the 12 needed) is left out, named, and the
    /// other four calibrate the rig (1 px: f within 2 %, about 5 times the sigma of this
    /// plan); without `drop_weak_views` its error stands; and a view the remaining plan
    /// cannot do without (both pan views weak: no pan-only rotation would remain) fails
    /// with the error of the first weak view.
    #[test]
    fn a_weak_rotated_view_is_left_out() {
        let scenario = headalign_sim::Scenario { seed: 5, ..Default::default() };
        let mut views = sim_views(scenario.clone());
        let names: Vec<String> = views.iter().map(|v| v.name.clone()).collect();
        let weaken = |v: &mut View| {
            v.capture.left.truncate(8);
            v.capture.right.truncate(8);
        };
        let elevation_down = names.iter().position(|n| n.contains("elevation-")).unwrap();
        weaken(&mut views[elevation_down]);
        let options = EstimationOptions { seed: 5, ..Default::default() };
        let calib = estimate_rig(&views, &options).unwrap();
        assert_eq!(calib.report.dropped_views.len(), 1);
        assert_eq!(calib.report.dropped_views[0].view, names[elevation_down]);
        assert!(calib.report.dropped_views[0].reason.contains("need at least 12"), "{:?}", calib.report);
        assert_eq!(calib.report.homographies.len(), views.len() - 2);
        assert!(calib.observations.iter().all(|o| o.view < views.len() - 1));
        let truth = headalign_sim::SimulatedHead::new(scenario).unwrap().truth().left.fx;
        let fx = calib.bundle.state.left.fx;
        assert!((fx / truth - 1.0).abs() < 0.02, "{fx} vs {truth}");
        let strict = EstimationOptions { drop_weak_views: false, ..options.clone() };
        assert!(matches!(estimate_rig(&views, &strict), Err(AlignError::TooFewTracks { .. })));
        for (i, n) in names.iter().enumerate() {
            if n.starts_with("pan") {
                weaken(&mut views[i]);
            }
        }
        let err = estimate_rig(&views, &options).unwrap_err().to_string();
        assert!(err.contains("need at least 12"), "{err}");
    }

    /// The maximum-likelihood pass at 2 px: the noise it weights the prior with and
    /// reports is the truncation-corrected least-squares estimate (measured 0.96-1.02 of
    /// the truth at 2-3 px over seeds, 1.98 px here, docs/efficiency.md; one seed's
    /// estimate over ~3800 residual components has a standard error of about 1.2 %, so
    /// 1.85-2.15 px leaves room for that and for the selection), it keeps
    /// the good observations (with 10 % outliers, at least 70 % of all of them: measured 77 %,
    /// the rest are outliers, tracks seen by one camera only and points with fewer than
    /// [`MIN_POINT_OBSERVATIONS`] observations), and its
    /// start score is MSAC: every residual beyond `tau` costs exactly `tau^2`.
    #[test]
    fn maximum_likelihood_pass_at_two_pixels() {
        let scenario = headalign_sim::Scenario { seed: 3, noise_px: 2.0, ..Default::default() };
        let views = sim_views(scenario);
        let mut options = EstimationOptions { seed: 3, prefilter_px: 12.0, ..Default::default() };
        options.fundamental.threshold *= 2.0;
        options.homography.threshold *= 2.0;
        let calib = estimate_rig(&views, &options).unwrap();
        let sigma = calib.bundle.report.sigma_px;
        assert!((1.85..2.15).contains(&sigma), "{sigma}");
        let total: usize = views.iter().map(|v| v.capture.left.len() + v.capture.right.len()).sum();
        assert!(
            calib.observations.len() as f64 >= 0.7 * total as f64,
            "{} of {total}",
            calib.observations.len()
        );
        let state = &calib.bundle.state;
        let own = start_score(state, &calib.observations, 6.0);
        assert!(own > 0.0 && own < 2.0 * sigma * sigma + 1e-9, "{own}");
        let far: Vec<BundleObservation> = calib
            .observations
            .iter()
            .map(|o| BundleObservation { pixel: o.pixel + nalgebra::Vector2::new(1e3, 0.0), ..*o })
            .collect();
        assert!((start_score(state, &far, 6.0) - 36.0).abs() < 1e-9);
        // Off, the result is the robust adjustment: a different estimate of the same rig.
        let robust =
            estimate_rig(&views, &EstimationOptions { final_least_squares: false, ..options }).unwrap();
        assert!((robust.bundle.state.left.fx - state.left.fx).abs() > 0.0);
        assert!((robust.bundle.state.left.fx / state.left.fx - 1.0).abs() < 0.05);
    }

    /// The truncation factor against a numerical integral of the chi-square(2) density
    /// (midpoint rule, 200000 steps: error about h^2 / 24 relative, below 1e-9, against
    /// a 1e-8 tolerance), its limits, and
    /// the value quoted in the docs.
    #[test]
    fn truncated_variance_factor_matches_the_integral() {
        for c in [0.5, 1.0, 2.0, 2.5, 3.0, 3.5, 5.0] {
            let t: f64 = c * c;
            let steps = 200_000;
            let (mut mass, mut second) = (0.0, 0.0);
            for i in 0..steps {
                let x = (i as f64 + 0.5) * t / steps as f64;
                let w = 0.5 * (-0.5 * x).exp() * t / steps as f64;
                mass += w;
                second += x * w;
            }
            let expected = second / mass / 2.0;
            assert!((truncated_variance_factor(c) - expected).abs() < 1e-8, "{c}");
        }
        assert!((truncated_variance_factor(3.5) - 0.98657).abs() < 1e-5);
        assert!((truncated_variance_factor(40.0) - 1.0).abs() < 1e-12);
        assert_eq!(truncated_variance_factor(f64::NAN), 1.0);
    }

    /// Studentised scales: a fitted residual is smaller than the noise, a left-out one
    /// larger, and both tend to 1 as the point gains observations.
    #[test]
    fn residual_scale_orders_fitted_and_left_out() {
        for k in 2..40 {
            let (a, b) = (residual_scale(k, 0.01, true), residual_scale(k, 0.01, false));
            assert!(a < 1.0 && b > 1.0 && a > 0.0, "{k}: {a} {b}");
        }
        assert!((residual_scale(6, 0.0, true) - 0.75f64.sqrt()).abs() < 1e-12);
        assert!((residual_scale(1000, 0.0, false) - 1.0).abs() < 1e-3);
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(64))]
        /// Monte Carlo of the truncated estimate: Gaussian 2D residuals of scale sigma
        /// truncated to `c sigma`, their mean square divided by `2 kappa(c)`, is sigma^2
        /// (4000 draws: relative standard error about 1.6 %, tolerance 8 %).
        #[test]
        fn truncated_estimate_is_unbiased_for_a_truncated_gaussian(
            seed in 0u64..1000, sigma in 0.3f64..5.0, c in 2.0f64..4.0,
        ) {
            use rand::{SeedableRng, RngExt};
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            let (mut ss, mut n) = (0.0, 0usize);
            for _ in 0..4000 {
                let x: f64 = rng.sample(rand_distr::StandardNormal);
                let y: f64 = rng.sample(rand_distr::StandardNormal);
                let r2 = (x * x + y * y) * sigma * sigma;
                if r2 <= c * c * sigma * sigma {
                    ss += r2;
                    n += 1;
                }
            }
            let est = (ss / (2.0 * n as f64 * truncated_variance_factor(c))).sqrt();
            proptest::prop_assert!((est / sigma - 1.0).abs() < 0.08, "{est} vs {sigma}");
        }
    }

    /// Noise free, the depth scale is known (sigma_s ~ 1e-10) and the profile changes
    /// nothing: the same state, and the covariance equal to 1e-6 relative (its entries
    /// are themselves ~1e-20, evaluated at states differing by rounding).
    /// The bootstrap (step 10) moves no estimate, only widens sigmas, reports its
    /// replicates, and is reproducible: a near scene (0.6-1.5 m) at 3 px, seed 1, 8
    /// replicates (few, to keep the test short: the widening itself is measured by
    /// `experiment calibration --scene paper --bootstrap 30`).
    #[test]
    fn the_bootstrap_widens_sigmas_and_moves_no_estimate() {
        let scenario =
            headalign_sim::Scenario { seed: 1, noise_px: 3.0, ..headalign_sim::Scenario::paper_lab() };
        let views = sim_views(scenario);
        let base = EstimationOptions::scaled_for_noise(3.0, 1);
        let boot = BootstrapOptions { replicates: 8, ..BootstrapOptions::default() };
        let with = EstimationOptions { bootstrap: Some(boot), ..base.clone() };
        let on = estimate_rig(&views, &with).unwrap();
        let off = estimate_rig(&views, &base).unwrap();
        let rep = on.report.bootstrap.unwrap();
        assert!(off.report.bootstrap.is_none());
        assert_eq!(rep.replicates + rep.failed, 8);
        assert!(rep.replicates >= 6, "{rep:?}");
        assert!(rep.max_widening >= 1.0 && rep.median_ratio.is_finite() && rep.median_ratio > 0.0, "{rep:?}");
        assert_eq!(on.bundle.state.left.fx, off.bundle.state.left.fx);
        assert_eq!(on.bundle.state.right.cy, off.bundle.state.right.cy);
        let (a, b) = (&on.bundle.covariance.matrix, &off.bundle.covariance.matrix);
        let mut widened = 0;
        for i in 0..a.nrows() {
            assert!(a[(i, i)] >= b[(i, i)] * (1.0 - 1e-12), "{i}: {} < {}", a[(i, i)], b[(i, i)]);
            widened += usize::from(a[(i, i)] > b[(i, i)] * 1.0001);
        }
        // 8 replicates' sigmas scatter +-25 % around the linearised ones: some widen.
        assert!(widened > 0, "no sigma widened");
        let again = estimate_rig(&views, &with).unwrap();
        assert_eq!(again.bundle.covariance.matrix, on.bundle.covariance.matrix);
        let bad = EstimationOptions { bootstrap: Some(BootstrapOptions { replicates: 1, ..boot }), ..base };
        assert!(matches!(bad.validate(), Err(AlignError::InvalidOption(_))));
    }

    #[test]
    fn depth_profile_leaves_noise_free_unchanged() {
        let scenario = headalign_sim::Scenario { seed: 4, noise_px: 0.0, ..Default::default() };
        let views = sim_views(scenario);
        let on = estimate_rig(
            &views,
            &EstimationOptions { seed: 4, depth_profile: Some(DepthProfile::DEFAULT), ..Default::default() },
        )
        .unwrap();
        let off =
            estimate_rig(&views, &EstimationOptions { seed: 4, depth_profile: None, ..Default::default() })
                .unwrap();
        let rep = on.report.depth_profile.unwrap();
        assert!(rep.sigma_log_depth < 1e-6, "{rep:?}");
        // Below the default threshold: not profiled.
        assert_eq!(rep.ends, 0, "{rep:?}");
        assert!((rep.max_widening - 1.0).abs() < 1e-6, "{rep:?}");
        assert!(off.report.depth_profile.is_none());
        assert_eq!(on.bundle.state.left.fx, off.bundle.state.left.fx);
        assert_eq!(on.bundle.state.right.cx, off.bundle.state.right.cx);
        let (a, b) = (&on.bundle.covariance.matrix, &off.bundle.covariance.matrix);
        for i in 0..a.nrows() {
            assert!((a[(i, i)] / b[(i, i)] - 1.0).abs() < 1e-6, "{i}: {} vs {}", a[(i, i)], b[(i, i)]);
        }
    }

    /// The image border (`image_border`) changes nothing without noise (no
    /// residual is then within reach of a border) and, at 2 px, moves the estimate by a
    /// small fraction of its sigma (only observations within 6 sigma of the border are
    /// refitted; this seed's focal lengths moved 0.07-0.20 sigma, the bar is 0.5).
    #[test]
    fn image_border_moves_only_noisy_estimates_and_only_a_little() {
        let clean = sim_views(headalign_sim::Scenario { seed: 4, noise_px: 0.0, ..Default::default() });
        let run = |views: &[View], image_border: bool| {
            estimate_rig(views, &EstimationOptions { seed: 4, image_border, ..Default::default() }).unwrap()
        };
        let (on, off) = (run(&clean, true), run(&clean, false));
        assert_eq!(on.bundle.state.left.fx, off.bundle.state.left.fx);
        assert_eq!(on.bundle.state.right.fy, off.bundle.state.right.fy);
        let noisy = sim_views(headalign_sim::Scenario { seed: 4, noise_px: 2.0, ..Default::default() });
        let (on, off) = (run(&noisy, true), run(&noisy, false));
        let mut moved = 0.0_f64;
        for (name, a, b) in [
            ("left.fx", on.bundle.state.left.fx, off.bundle.state.left.fx),
            ("left.fy", on.bundle.state.left.fy, off.bundle.state.left.fy),
            ("right.fx", on.bundle.state.right.fx, off.bundle.state.right.fx),
            ("right.fy", on.bundle.state.right.fy, off.bundle.state.right.fy),
        ] {
            let z = (a - b).abs() / off.bundle.covariance.sigma(name).unwrap();
            assert!(z < 0.5, "{name} moved {z} sigma");
            moved = moved.max(z);
        }
        assert!(moved > 1e-3, "the border model had no effect ({moved} sigma)");
    }

    /// A receding scene (the rig re-adjusted with its depth scale held 2 sigma_s beyond the
    /// estimate, the far solution of the removed examples/sigma_diag.rs in miniature: 80 points at
    /// 1 px) reports smaller sigmas than the estimate; profiling it widens them back (the
    /// near end lies near the estimate), never narrows any, and keeps the state.
    #[test]
    fn depth_profile_widens_a_receding_scene() {
        use headalign_geometry::synthetic::{perturb, synth};
        let base = synth(12, 80, 1.0, 0.0, false);
        let options = EstimationOptions::default();
        let ls =
            BundleOptions { robust: RobustLoss::None, noise_sigma_px: Some(1.0), ..options.bundle.clone() };
        let est = bundle_adjust(&perturb(&base.truth, 120), &base.obs, &ls).unwrap();
        let (s, sig) = log_depth_scale(&est.state, &base.obs, &ls, 1.0).unwrap();
        let far =
            bundle_adjust_at_depth_scale(&est.state, &base.obs, &ls, s + 2.0 * sig, 1e-3 * sig).unwrap();
        let i = far.covariance.index("right.cx").unwrap();
        let narrowed = (far.covariance.matrix[(i, i)] / est.covariance.matrix[(i, i)]).sqrt();
        let before = far.covariance.matrix.clone();
        // Ends at the 95 % interval (not the default 1 sigma): the near end then lies at the
        // estimate.
        let wide_profile = DepthProfile { z: 1.96, ..DepthProfile::DEFAULT };
        let (wide, rep) = profile_depth_scale(far.clone(), &base.obs, &wide_profile, &options);
        let rep = rep.unwrap();
        let widened = (wide.covariance.matrix[(i, i)] / before[(i, i)]).sqrt();
        eprintln!(
            "receding scene: right.cx sigma {narrowed:.3} of the estimate's, widened {widened:.3}, {rep:?}"
        );
        assert_eq!(rep.ends, 2);
        assert!(narrowed < 0.95, "{narrowed}");
        assert!(widened > 1.0 / narrowed - 0.05, "{widened} vs {narrowed}");
        for k in 0..before.nrows() {
            assert!(wide.covariance.matrix[(k, k)] >= before[(k, k)], "{k}");
        }
        assert_eq!(wide.state.right.cx, far.state.right.cx);
    }

    #[test]
    fn options_validate() {
        assert!(EstimationOptions::default().validate().is_ok());
        assert!(EstimationOptions { reselect_sigmas: 0.5, ..Default::default() }.validate().is_err());
        assert!(EstimationOptions { min_camera_observations: 0, ..Default::default() }.validate().is_err());
        for g in [
            LoneDepthGate { z: 0.0, ..LoneDepthGate::DEFAULT },
            LoneDepthGate { z: f64::NAN, ..LoneDepthGate::DEFAULT },
            LoneDepthGate { roughness: -0.1, ..LoneDepthGate::DEFAULT },
            LoneDepthGate { neighbours: 2, ..LoneDepthGate::DEFAULT },
        ] {
            assert!(EstimationOptions { lone_depth_gate: Some(g), ..Default::default() }.validate().is_err());
        }
        assert!(EstimationOptions { prefilter_px: f64::NAN, ..Default::default() }.validate().is_err());
        assert!(EstimationOptions { min_tracks: 3, ..Default::default() }.validate().is_err());
        let bad = DepthProfile { z: 0.0, ..DepthProfile::DEFAULT };
        assert!(EstimationOptions { depth_profile: Some(bad), ..Default::default() }.validate().is_err());
    }
}
