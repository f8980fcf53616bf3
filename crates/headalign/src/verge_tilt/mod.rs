//! The verge/tilt estimation core (`docs/how-it-works.md#2-estimation`; paper section 3.2
//! steps 1-4): from stereo views related by pan and elevation rotations of the head,
//! recover both cameras' intrinsics, the rig, the pan and elevation axes and the scene,
//! with covariances.
//!
//! [`estimate_rig`] runs the pipeline below, each step a function of the results of the
//! steps before it, one file per step group (`verge_tilt/<file>.rs`, each with its own
//! docs: what it computes, degrees of freedom, units, pitfalls):
//! 1. **view roles** (`roles.rs`, [`classify_views`]): classify views by which joints
//!    moved relative to the first ("reference") view; one rotation about pan alone and one
//!    about elevation alone are needed (paper section 3.1);
//! 2. **stereo geometry** (`stereo.rs`; paper section 3.2 step 1): one fundamental matrix
//!    from the stereo matches of all rig views (the rig does not change while only pan and
//!    elevation move), RANSAC + Sampson refinement;
//! 3. **projective frame** (`frame.rs`; paper sections 2 and 3.2 step 1): a
//!    quasi-Euclidean projective frame ([`headalign_geometry::frame`]) and optimal
//!    triangulation of every stereo match;
//! 4. **3D homographies** (`homographies.rs`; paper section 3.2 steps 2-4(c)): per rotated
//!    view, quadruplets screened by plane homographies (a head rotation maps each image
//!    almost by `K R K^-1`), then the 3D homography: polished on symmetric transfer error
//!    from a rigid or DLT start (the 5-point DLT RANSAC as fallback), and guided
//!    re-selection of quadruplets until the set is stable;
//! 5. **starts** (`starts.rs`, `linear.rs`; paper section 3.1): five starts for the
//!    adjustment: the linear self-calibration chain (plane at infinity, `w*`, `K_L`, the
//!    right camera, motions); each camera's `K` by rotating-camera self-calibration from
//!    its plane homographies with the rig from `E`; a rough guess; with those `K`s, the rig
//!    pose estimated directly (5 dof, [`headalign_geometry::essential`]), not from `F`,
//!    whose epipole nearly parallel cameras and walls leave ill-determined; and the same
//!    from the rough guess and the stereo-head prior (baseline along x) alone. Each is
//!    screened by a short adjustment, the best MSAC score over one common set of
//!    observations wins (not the RMS: each start fits its own subset);
//! 6. **adjustment** (`adjust.rs`; `docs/how-it-works.md#the-rig-bundle-adjustment`): the rig bundle
//!    adjustment, motions modelled as rotations about two fixed axes with the commanded
//!    encoder differences as priors, robust loss; re-selection of every observation by its
//!    residual; a final adjustment; points at implausible depth (wrong tracks) removed and
//!    adjusted once more; with [`EstimationOptions::depth_step`] (image mode) the tracks
//!    at depth steps are left out too ([`near_depth_step`]);
//! 7. **maximum likelihood** (`likelihood.rs`): the Huber loss of step 6 is robust but
//!    not the likelihood of Gaussian pixel noise (with its fixed 2 px scale, at 2-3 px of
//!    noise most inliers are down-weighted), and its angle prior is weighted as if the
//!    noise were 1 px (at 3 px the prior is then 9 times too weak against the pixels). So
//!    the noise is estimated from the robust solution (median residual norm), the
//!    observations within `reselect_sigmas` of it are kept, and plain least squares runs
//!    with the prior weighted by that noise; then the observations are re-classified at
//!    the least-squares solution (studentised residuals within `reselect_sigmas` of the
//!    unbiased, truncation-corrected noise estimate) and the adjustment repeated until the
//!    set is stable: the ML estimate under the Gaussian model, whose covariance is the one
//!    reported. Measured effect in `docs/accuracy.md` (RMS error / Cramer-Rao bound).
//!    With [`EstimationOptions::image_border`] these passes model the image border: an
//!    observation near it was kept only if its noise pointed inward, so its residual is
//!    taken against the expected measurement of the truncated Gaussian. A point seen only
//!    once by one camera takes its depth from that observation alone, so a wrong one is
//!    fitted exactly at a wrong depth; such a point is left out when that depth is off its
//!    neighbours' by more than its own stereo noise and the scene's roughness allow
//!    ([`EstimationOptions::lone_depth_gate`], [`lone_depth_outliers`]). All of them can
//!    be left out ([`EstimationOptions::min_camera_observations`], off by default), but
//!    the points go with their information.
//! 8. **depth-reversed restart** (`restart.rs`): the scene is far against the baseline,
//!    so the rig with its baseline reversed (x component, or all of it) is a second
//!    least-squares minimum with the points' depth order reversed; the least squares is
//!    restarted from it (points re-triangulated) and the lower cost wins
//!    ([`EstimationOptions::reversed_rig_restart`]; seed 39 at 2-3 px had right cx 6 sigma
//!    off in the wrong minimum); likewise from the baseline with its y and z components
//!    reversed (a forward component's sign is weakly determined too: fig5 seeds 1119,
//!    1130, 1211 at 3 px, `docs/accuracy.md`); and, when the estimated baseline is more
//!    than 45 deg from the right camera's x axis (no stereo head's cameras are so placed),
//!    from the baseline along that axis, both ways (calibration seed 368 at 3 px had it
//!    along the optical axis, left fx 3.7 sigma off);
//! 9. **depth-scale profile** (`sigmas.rs`, [`profile_depth_scale`],
//!    [`EstimationOptions::depth_profile`]): the scene's distance in baselines is the badly
//!    determined direction and the linearised sigmas follow it, so each camera sigma is the
//!    largest of those at the estimate and at the estimate re-adjusted with the depth scale
//!    held one sigma either side; the estimate itself is unchanged. On by default:
//!    measured, it mends the principal points' and right.fy's coverage at 3 px (option
//!    docs).
//! 10. **bootstrap** (`sigmas.rs`, optional: [`bootstrap_covariance`],
//!     [`EstimationOptions::bootstrap`], off by default): the maximum-likelihood pass
//!     re-run on point tracks drawn with replacement (and the encoder readings redrawn
//!     from the angle prior), each camera sigma the larger of the linearised one and the
//!     replicates' spread. Where the likelihood is not quadratic (near scenes at a few
//!     pixels) the linearised sigmas are too small; this mends that at about one
//!     warm-started adjustment per replicate.
//!
//! Lens models (`lens.rs`, [`EstimationOptions::lens`], default the pinhole): the lens
//! coefficients of both cameras are freed in steps 6-10; the steps 1-5 run first on the
//! captured pixels, then again on pixels undistorted by that first estimate, and the
//! adjustments on the captured pixels (`lens.rs` module docs).
//!
//! This file holds the options ([`EstimationOptions`] and its gates), the reports and the
//! result ([`RigCalibration`]), and [`estimate_rig`], which calls the steps in order and
//! leaves out a rotated view whose 3D homography fails when the rest still suffice, and
//! failing that keeps every view, those without a 3D homography included
//! ([`EstimationOptions::views_without_homography`]).
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
//! `docs/accuracy.md`, with the remaining heavy-tailed trials).
//!
//! Units: pixels for thresholds, radians inside, the scene in baselines (|t_rig| = 1)
//! (a known baseline only rescales the scene). Frames: everything in the reference view's left
//! camera frame ("ref").

mod adjust;
mod fit;
mod frame;
mod homographies;
mod lens;
mod likelihood;
mod linear;
mod restart;
mod roles;
mod sigmas;
pub(crate) mod starts;
mod stereo;
#[cfg(test)]
mod tests;

use std::borrow::Cow;

use headalign_geometry::bootstrap::BootstrapOptions;
use headalign_geometry::bundle::{BundleObservation, BundleOptions, BundleResult, Motions, RigState, Side};
use headalign_geometry::camera::Intrinsics;
use headalign_geometry::distortion::DistortionTerms;
use headalign_geometry::ransac::RansacOptions;
use headalign_geometry::so3::Line;
use headalign_platform::Encoders;
use nalgebra::Point3;
use serde::Serialize;

pub(crate) use adjust::{Adjustment, adjust_from_starts};
pub use adjust::{DEPTH_RATIO, FINAL_ITERATIONS, MIN_POINT_OBSERVATIONS, SCREEN_ITERATIONS, near_depth_step};
pub(crate) use frame::Reconstruction;
pub(crate) use homographies::{PolishedHomography, guided_reselection, polish};
pub use likelihood::{
    ML_ROUNDS, lone_depth_outliers, residual_scale, truncated_noise_estimate, truncated_variance_factor,
};
pub use roles::{MOVED_DEG, ViewRole, classify_views};
pub use sigmas::{MAX_END_WIDENING, PROFILE_END_ITERATIONS, bootstrap_covariance, profile_depth_scale};
pub(crate) use starts::points_in_ref;

use adjust::{PointSources, first_selection, rig_observations};
use frame::projective_frame;
use homographies::{HomographyMode, rotation_homographies};
use restart::reversed_rig_restart;
use starts::{InitContext, commanded_angles, initial_states, point_set};
use stereo::stereo_geometry;

use crate::error::AlignError;
use crate::observations::View;
use crate::rig::{LensChoice, undistort_views};
pub use fit::{MISFIT_FAIL_RATIO, ModelFit, model_fit, observation_view_names};
pub use lens::LensReport;
use lens::LensStart;

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
    /// When the estimate fails at a rotated view's 3D homography even after
    /// [`EstimationOptions::drop_weak_views`], run the chain once more with every view, a
    /// view whose 3D homography fails keeping its observations without one (listed in
    /// [`EstimationReport::views_without_homography`]; the linear start is then lost, the
    /// other starts and the adjustment use the view; `homographies.rs` module docs).
    /// Default true. Why: the 3D homography needs tracks right in all four images of a
    /// rotation, `(1 - e)^4` of them with a fraction `e` of wrong observations (some 5 of
    /// 200 at `e` = 60 %), while the rest of the chain needs only stereo pairs and single
    /// observations. Estimates that succeed without it are unchanged.
    pub views_without_homography: bool,
    /// After the maximum-likelihood pass, restart the least squares from the
    /// depth-reversed rig (`reversed_rig_restart`, module docs step 8) and keep the
    /// solution of lower cost (default true; needs `final_least_squares`).
    pub reversed_rig_restart: bool,
    /// Leave out the tracks at depth steps before the maximum-likelihood pass
    /// ([`near_depth_step`]; default `None`, off, also in image mode: see
    /// [`DepthStepGate::IMAGES`]). A corner where a near edge crosses the background is no
    /// fixed scene point, and its structured error moves the calibration coherently
    /// (measured: [`near_depth_step`]).
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
    /// (`docs/accuracy.md`): the coverage experiment's fixed group at 3 px
    /// 90.7-97.0 % (right.cx 88.7 % off), at 0.5 px 92.7-98.0 %; +2 % CPU in
    /// `experiment fig5-verge-tilt --trials 100`. `None`: the linearised covariance at
    /// the estimate.
    pub depth_profile: Option<DepthProfile>,
    /// The bootstrap of the covariance (module docs step 10, [`bootstrap_covariance`]):
    /// `Some` re-runs the maximum-likelihood pass on `replicates` resamplings of the point
    /// tracks (seeded by `seed` plus [`EstimationOptions::seed`]) and widens each camera
    /// sigma to the replicates' spread where that is larger (after the depth profile).
    /// Default `None`: it costs about one warm-started adjustment per replicate (30
    /// replicates: measured in `docs/accuracy.md`, with the coverage
    /// it buys in the near scene).
    pub bootstrap: Option<BootstrapOptions>,
    /// Model the image border in the maximum-likelihood passes (module docs step 7): a
    /// point is observed only if its measured position lies in the image, so near the
    /// border the noise of the observations that remain points inward; the least
    /// squares then fits each residual against the expected measurement under that
    /// truncation (`BundleOptions::measurement_window` = the whole image). Default
    /// true. Measured once (2400 adjustments at 3 px, no command reproduces it): the truncation
    /// put the focal lengths +0.08 to +0.14 sigma high (fy most: the image is 576 px high)
    /// and the window takes them back to the untruncated values; in `experiment
    /// calibration` (`--image-border on` against `off`, seeds 1-250 and 251-500) it halves
    /// the focal lengths' bias, the ratios move by less than their sampling noise, and
    /// `experiment coverage` stays within 90.7-97.3 % (`docs/accuracy.md`). Noise-free
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
    /// a wrong depth and no residual test can see it: at 3 px (a past measurement,
    /// seeds 1-200) the final adjustment keeps 0.585 outliers per trial, 116 of 117 of
    /// this kind, and the focal lengths come out up to +0.25 sigma high. 2 removes them
    /// (0.005 per trial) but those points, about 5 % of the observations and often near
    /// the image edge, carry much of the focal lengths' information: on `experiment all`
    /// (same seeds) the RMS errors grew by up to 17 % (focal lengths at 3 px 6-17 %, alignment
    /// 4-9 %) and the Cramer-Rao bound with them (f at 3 px 1.86 -> 2.00 %), so the
    /// ratios fell (calibration grid worst 1.154 -> 1.09) while every estimate got worse
    /// (`docs/accuracy.md`). Kept as an option for data with many such outliers.
    pub min_camera_observations: usize,
    /// Test of the points seen once by one camera against their neighbours' depth
    /// ([`lone_depth_outliers`]): such a point's depth rests on that one observation, so
    /// a wrong one near the epipolar line puts it at a wrong depth that no residual shows,
    /// but usually far from the surface around it. `None` keeps every such point. Default
    /// [`LoneDepthGate::DEFAULT`]. Measured once (no command reproduces it; seeds 1-200 at
    /// 3 px): kept outliers 0.585 -> 0.115 per trial, the focal lengths' mean error +0.13 /
    /// +0.26 / +0.06 / +0.16 -> +0.10 / +0.12 / +0.04 / +0.05 sigma; `experiment
    /// calibration` (seeds 1-250, paired, `--lone-depth-gate off` against the default): the
    /// focal lengths' RMS errors -5 to -12 % at 0.5 px, -7 to +1 % at 1-2 px, +1 to +5 %
    /// at 3 px (its tail trials move either way), reconstruction error 2.43 -> 1.27 % at
    /// 0.5 px. On rendered images (`bench/seeds.py 1 24 --images`) it changes almost
    /// nothing (f 0.035 / 0.043 % with it, 0.035 / 0.043 % without, seeds 1-8 / 9-24).
    pub lone_depth_gate: Option<LoneDepthGate>,
    /// The lens model [`estimate_rig`] estimates for both cameras (default
    /// [`LensChoice::Pinhole`]: none, the pipeline exactly as without lenses). A model
    /// frees its coefficients `lens_terms` of each camera in the adjustments, from a start
    /// whose linear chain ran on pixels undistorted by a first estimate (`lens.rs`, module
    /// docs "Lens models"); [`LensChoice::Auto`] chooses the model and its terms by the
    /// criterion of [`crate::rig::lens_choice`] and reports it (the CLI's image
    /// commands default to it). [`crate::calibrate`] takes its own
    /// [`crate::calibrate::CalibrateOptions::lens`] and ignores this one.
    pub lens: LensChoice,
    /// Which coefficients of the model are estimated (default [`DistortionTerms::Radial2`]:
    /// `k1, k2`); with [`LensChoice::Auto`] the richest terms its candidates may have
    /// ([`DistortionTerms::Full5`]: all of them).
    pub lens_terms: DistortionTerms,
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
    /// The default (field docs). Chosen on a past measurement (no command reproduces it) with
    /// the gate off (lone observations more than 5 noise sigmas from their exact pixel
    /// count as outliers): beyond 5 deviations lie 97 of 116 lone outliers and 24 of 3843
    /// lone inliers at 3 px (200 seeds), 44 of 56 and 77 of 3963 at 1 px, 20 of 27 and 28 of
    /// 941 with 50 points at 1.5 px; z = 6 flags half as many of those inliers and lets 0-9 %
    /// more outliers through, a roughness of 0 flags 1.4-2 times as many inliers.
    pub const DEFAULT: LoneDepthGate = LoneDepthGate { z: 5.0, roughness: 0.1, neighbours: 10 };

    /// Check every field: a positive finite `z`, a finite `roughness >= 0`, at least 3
    /// neighbours.
    pub fn validate(&self) -> Result<(), AlignError> {
        let ok = self.z.is_finite()
            && self.z > 0.0
            && self.roughness.is_finite()
            && self.roughness >= 0.0
            && self.neighbours >= 3;
        ok.then_some(()).ok_or_else(|| {
            AlignError::InvalidOption(
                "lone_depth_gate needs a positive finite z, a finite roughness >= 0 and at least 3 neighbours".into(),
            )
        })
    }
}

/// How [`profile_depth_scale`] widens the reported covariance: the estimate is
/// re-adjusted with its depth scale `s` (log harmonic-mean point distance in baselines,
/// [`log_depth_scale`](headalign_geometry::bundle::log_depth_scale)) held at `s_hat -+ z sigma_s`, and each camera parameter's sigma
/// becomes the largest of its sigmas at the estimate and at the two ends.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthProfile {
    /// Where the ends lie, in sigmas of `s` (default 1.0, measured: 1.96, the 95 %
    /// interval of `s`, over-covers the focal lengths at 3 px because each sigma takes the
    /// maximum over the two ends; [`EstimationOptions::depth_profile`]).
    pub z: f64,
    /// Profile only when `sigma_s` exceeds this (default 0.01: the intrinsics' sigmas
    /// widen by about `0.3-0.6 z sigma_s` where `sigma_s < 0.2` (a past measurement,
    /// seeds 1001-1040: 0.5 px sigma_s 0.033-0.066, widening 0.9-3.4 %; 1 px 0.065-0.16,
    /// 3.6-8.2 %), so below it by well under 1 %; it skips the noise-free runs, whose
    /// sigma_s is below 1e-6, and keeps every trial at 0.5 px and above).
    pub min_sigma_log_depth: f64,
}

impl DepthProfile {
    /// The default: ends at 1 sigma of the depth scale, profiled when its sigma exceeds
    /// 0.01 (field docs).
    pub const DEFAULT: DepthProfile = DepthProfile { z: 1.0, min_sigma_log_depth: 0.01 };

    /// Check every field: a positive finite `z`, a finite `min_sigma_log_depth >= 0`.
    pub fn validate(&self) -> Result<(), AlignError> {
        let ok = self.z.is_finite()
            && self.z > 0.0
            && self.min_sigma_log_depth.is_finite()
            && self.min_sigma_log_depth >= 0.0;
        ok.then_some(()).ok_or_else(|| {
            AlignError::InvalidOption(
                "depth_profile needs a positive finite z and a finite min_sigma_log_depth >= 0".into(),
            )
        })
    }
}

/// What [`profile_depth_scale`] did.
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct DepthProfileReport {
    /// The estimate's depth scale `s`: `-ln` of the mean inverse point distance, in
    /// baselines ([`log_depth_scale`](headalign_geometry::bundle::log_depth_scale)).
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
    /// without the flagged tracks (a past measurement, seeds 1-40): z-score RMS of
    /// the 8 intrinsics 1.29 -> 1.15 (seeds 1-20) and 2.27 -> 1.45 (seeds 21-40, three
    /// seeds at 3-7); radius 25 px and ratio 1.2 flagged fewer tracks and did less (1.17,
    /// 1.90); dropping as many random tracks changed nothing (1.28, 2.18). In the full
    /// pipeline (gate before the maximum-likelihood pass, `bench/seeds.py 1 20 --images`
    /// with it set in `image_mode::tracked_estimation`) it did not pay: the z-scores hardly
    /// moved and the focal and elevation errors grew (README), so nothing sets it by
    /// default.
    pub const IMAGES: DepthStepGate = DepthStepGate { radius_px: 40.0, ratio: 1.15 };

    /// Check every field: a positive finite radius, a finite ratio above 1.
    pub fn validate(&self) -> Result<(), AlignError> {
        let ok =
            self.radius_px.is_finite() && self.radius_px > 0.0 && self.ratio.is_finite() && self.ratio > 1.0;
        ok.then_some(()).ok_or_else(|| {
            AlignError::InvalidOption(
                "depth_step needs a positive finite radius and a finite ratio above 1".into(),
            )
        })
    }
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
            views_without_homography: true,
            reversed_rig_restart: true,
            depth_step: None,
            depth_profile: Some(DepthProfile::DEFAULT),
            bootstrap: None,
            image_border: true,
            min_camera_observations: 1,
            lone_depth_gate: Some(LoneDepthGate::DEFAULT),
            lens: LensChoice::Pinhole,
            lens_terms: DistortionTerms::Radial2,
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
        self.depth_step.as_ref().map_or(Ok(()), DepthStepGate::validate)?;
        self.lone_depth_gate.as_ref().map_or(Ok(()), LoneDepthGate::validate)?;
        if self.min_tracks < 8 {
            return Err(AlignError::InvalidOption("min_tracks must be at least 8".into()));
        }
        self.depth_profile.as_ref().map_or(Ok(()), DepthProfile::validate)?;
        if let Some(b) = self.bootstrap {
            b.validate().map_err(|e| match e {
                headalign_geometry::GeometryError::InvalidOption(m) => AlignError::InvalidOption(m),
                other => AlignError::InvalidOption(other.to_string()),
            })?;
        }
        Ok(())
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
    /// Rotated views used without a 3D homography
    /// ([`EstimationOptions::views_without_homography`]), with the error of its fit;
    /// empty when every view had one.
    pub views_without_homography: Vec<DroppedView>,
    /// The depth-scale profile of the covariance ([`EstimationOptions::depth_profile`]);
    /// `None` when off or when `s` or its sigma could not be computed.
    pub depth_profile: Option<DepthProfileReport>,
    /// The bootstrap of the covariance ([`EstimationOptions::bootstrap`]); `None` when off
    /// or when fewer than 3 replicates converged.
    pub bootstrap: Option<BootstrapReport>,
    /// The lens estimate's start and choice ([`EstimationOptions::lens`]); `None` for the
    /// pinhole (and then absent from the JSON).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lens: Option<LensReport>,
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

/// A rig view [`estimate_rig`] left out (or used without its 3D homography), and why.
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

/// Run the whole chain on the views (the first is the reference; verge views are
/// ignored here). A rotated view whose 3D homography fails is left out and the chain run
/// again without it while a pan-only and an elevation-only rotation remain
/// ([`EstimationOptions::drop_weak_views`]); if that does not succeed either, the chain
/// runs once more on every view, views without a 3D homography included
/// ([`EstimationOptions::views_without_homography`]); otherwise the first error is returned.
pub fn estimate_rig(views: &[View], options: &EstimationOptions) -> Result<RigCalibration, AlignError> {
    options.validate()?;
    let (error, at_homography) = match estimate_dropping_views(views, options) {
        Ok(calibration) => return Ok(calibration),
        Err(e) => e,
    };
    if !(at_homography && options.views_without_homography) {
        return Err(error);
    }
    let mut at_view = None;
    lens::estimate_with_lens(views, options, HomographyMode::Optional, &mut at_view).map_err(|_| error)
}

/// [`estimate_rig`] with every 3D homography required, weak views left out
/// ([`EstimationOptions::drop_weak_views`]). The error says whether a 3D homography step
/// failed on the way (then the fallback may run).
fn estimate_dropping_views(
    views: &[View],
    options: &EstimationOptions,
) -> Result<RigCalibration, (AlignError, bool)> {
    let mut kept: Vec<View> = Vec::new();
    let mut dropped: Vec<DroppedView> = Vec::new();
    loop {
        let current: &[View] = if dropped.is_empty() { views } else { &kept };
        let mut at_view = None;
        let error = match lens::estimate_with_lens(current, options, HomographyMode::Required, &mut at_view) {
            Ok(mut calibration) => {
                calibration.report.dropped_views = dropped;
                return Ok(calibration);
            }
            Err(e) => e,
        };
        let at_homography = at_view.is_some() || !dropped.is_empty();
        let Some(vi) = at_view.filter(|_| options.drop_weak_views) else {
            return Err((error, at_homography));
        };
        let rest: Vec<View> =
            current.iter().enumerate().filter(|&(i, _)| i != vi).map(|(_, v)| v.clone()).collect();
        if classify_views(&rest).is_err() {
            return Err((error, true));
        }
        dropped.push(DroppedView { view: current[vi].name.clone(), reason: error.to_string() });
        kept = rest;
    }
}

/// [`estimate_rig`] on exactly these views: the steps of the module docs, in order;
/// `at_view` names the view (index into `views`) whose 3D homography step failed, if
/// that is where it failed (with [`HomographyMode::Required`]).
fn estimate_rig_once(
    original: &[View],
    options: &EstimationOptions,
    mode: HomographyMode,
    at_view: &mut Option<usize>,
    lens: Option<&LensStart>,
) -> Result<RigCalibration, AlignError> {
    // With a lens start, steps 1-5 run on the pixels undistorted by its first estimate
    // and the adjustments (6-10) on the original pixels (`lens.rs`).
    let chain_views = lens.and_then(|l| l.chain.as_ref()).map(|m| undistort_views(original, m));
    let views: &[View] = chain_views.as_deref().unwrap_or(original);
    // 1. View roles; the rig views are all but the verge views, slot 0 the reference.
    let roles = classify_views(views)?;
    let rig: Vec<usize> = (0..views.len()).filter(|&i| !matches!(roles[i], ViewRole::Verge)).collect();
    let [w, h] = views[0].capture.image_size;
    let k0 = Intrinsics::rough_guess(w, h);
    let options = &*with_image_border(options, w, h);
    // 2. Stereo geometry: one F from all rig views together.
    let stereo = stereo_geometry(views, &rig, options)?;
    // 3. Projective frame and triangulation per rig view: track -> (X, left, right).
    let structure = projective_frame(&stereo, &k0, options.fundamental.threshold)?;
    let recon = &structure.recon;
    // 4. 3D homographies, screening + polished starts + guided re-selection.
    let mut rotations = rotation_homographies(views, &rig, &structure, options, mode, at_view)?;
    // 5. The point set and the starts.
    let (point_tracks, origin_slot) = point_set(recon);
    let commanded = commanded_angles(&roles, &rig);
    let ctx = InitContext {
        views,
        rig: &rig,
        recon,
        point_tracks: &point_tracks,
        origin_slot: &origin_slot,
        commanded: &commanded,
        min_tracks: options.min_tracks,
    };
    let linear_blocked = rotations.linear_blocked.take();
    let threshold = options.fundamental.threshold;
    let mut starts = initial_states(&ctx, linear_blocked, &rotations, &stereo, &structure, &k0, threshold);
    if let Some(l) = lens {
        for s in starts.iter_mut().flatten() {
            [s.left_distortion, s.right_distortion] = l.distortion;
        }
    }
    // 6-7. Screening, robust adjustment, maximum-likelihood pass.
    let all_obs = rig_observations(original, &rig, &point_tracks);
    let first_obs = first_selection(&all_obs, &point_tracks, recon, &rotations.quad_inliers);
    let adjusted =
        adjust_from_starts(starts, &first_obs, &all_obs, &point_tracks, &origin_slot, recon, options)?;
    let Adjustment { first, last: final_result, observations: second_obs, linear_focal, .. } = adjusted;
    // 8-10. Restarts, depth-scale profile, bootstrap.
    let sources = PointSources { point_tracks: &point_tracks, origin_slot: &origin_slot, recon };
    let (final_result, second_obs, depth_profile, bootstrap) =
        after_adjustment(final_result, second_obs, &all_obs, &sources, options)?;
    let report = EstimationReport {
        stereo_matches: stereo.pairs.len(),
        stereo_inliers: stereo.inliers,
        stereo_rms_px: stereo.rms_px,
        homographies: rotations.reports,
        linear_focal,
        bundle_observations: second_obs.len(),
        bundle_points: point_tracks.len(),
        bundle_iterations: final_result.report.iterations,
        initial_rms_px: first.report.initial_rms_px,
        final_rms_px: final_result.report.final_rms_px,
        sigma_px: final_result.report.sigma_px,
        sigma_inflation: final_result.report.sigma_inflation,
        dropped_views: Vec::new(),
        views_without_homography: rotations.without_homography,
        depth_profile,
        bootstrap,
        lens: None,
    };
    let point_observations =
        reconstructed_point_observations(&final_result.state, &second_obs, point_tracks.len());
    Ok(RigCalibration {
        bundle: final_result,
        point_tracks,
        point_observations,
        observations: second_obs,
        reference_encoders: views[0].capture.encoders,
        report,
    })
}

/// What steps 8-10 leave: the adjustment, its observations, the depth-scale profile's
/// and the bootstrap's reports.
type AfterAdjustment =
    (BundleResult, Vec<BundleObservation>, Option<DepthProfileReport>, Option<BootstrapReport>);

/// Steps 8-10 of [`estimate_rig`] (module docs) after the maximum-likelihood pass, each
/// only with [`EstimationOptions::final_least_squares`] and its own option: the restarts
/// from the depth-reversed rigs, the depth-scale profile and the bootstrap of the
/// covariance. `all_obs` are every raw observation (the restarts re-select from them).
fn after_adjustment(
    final_result: BundleResult,
    second_obs: Vec<BundleObservation>,
    all_obs: &[BundleObservation],
    sources: &PointSources<'_>,
    options: &EstimationOptions,
) -> Result<AfterAdjustment, AlignError> {
    // 8. The restarts from the depth-reversed rigs.
    let (final_result, second_obs) = if options.final_least_squares && options.reversed_rig_restart {
        reversed_rig_restart(final_result, second_obs, all_obs, sources, options)?
    } else {
        (final_result, second_obs)
    };
    // 9. The depth-scale profile of the covariance.
    let (final_result, depth_profile) = match options.depth_profile {
        Some(p) if options.final_least_squares => {
            let (r, rep) = profile_depth_scale(final_result, &second_obs, &p, options);
            (r, rep)
        }
        _ => (final_result, None),
    };
    // 10. The bootstrap of the covariance.
    let (final_result, bootstrap) = match options.bootstrap {
        Some(b) if options.final_least_squares => {
            bootstrap_covariance(final_result, &second_obs, &b, options)
        }
        _ => (final_result, None),
    };
    Ok((final_result, second_obs, depth_profile, bootstrap))
}

/// The options with the image border as the adjustment's measurement window
/// (`[-0.5, -0.5, w - 0.5, h - 0.5]`: pixel centres at integers) when
/// [`EstimationOptions::image_border`] is on and no window is set; otherwise unchanged.
fn with_image_border(options: &EstimationOptions, w: u32, h: u32) -> Cow<'_, EstimationOptions> {
    if options.image_border && options.bundle.measurement_window.is_none() {
        let (wf, hf) = (f64::from(w), f64::from(h));
        let bundle = BundleOptions {
            measurement_window: Some([-0.5, -0.5, wf - 0.5, hf - 0.5]),
            ..options.bundle.clone()
        };
        Cow::Owned(EstimationOptions { bundle, ..options.clone() })
    } else {
        Cow::Borrowed(options)
    }
}

/// [`RigCalibration::point_observations`]: the observations of each point of `state` in
/// the final adjustment `obs` (`n_points` of them), zero for a point not seen by both cameras or not finite
/// within [`DEPTH_RATIO`] times the median distance of the others.
fn reconstructed_point_observations(
    state: &RigState,
    obs: &[BundleObservation],
    n_points: usize,
) -> Vec<usize> {
    let mut point_observations = vec![0usize; n_points];
    let mut point_sides = vec![[false; 2]; n_points];
    for o in obs {
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
    let mut dist: Vec<f64> = (0..n_points)
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
    point_observations
}
