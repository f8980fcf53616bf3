//! The verge/tilt procedure over any [`StereoHead`] (DESIGN.md section 2 steps 1-5, paper
//! section 3.2): capture an initial view; rotate elevation, capture; rotate pan (from the
//! initial position), capture — by default each both ways (+r and -r), which doubles the
//! angular span per axis; rotate both vergences, capture; return. Estimate the rig and head
//! ([`crate::estimate`]), measure the vergence axes by resection, compute the aligned
//! readings exactly ([`crate::alignment`]), move there, capture again and check the result
//! by vision; if the measured error exceeds the tolerance, re-measure the vergence axes from
//! that larger move and correct (at most `max_corrections` times). A vergence axis is
//! re-measured only from a vergence turn at least as large as the procedure's own vergence
//! move: the axis is the screw of the measured pose against the modelled pan/elevation
//! chain, and a small turn on top of a large elevation turn measures mostly the chain's
//! error (one 3 px trial ended 8 deg off before this rule).
//!
//! Rotation size: fixed (`rotation_deg`, default 3 deg, the paper's protocol; optional
//! diagonal views `diagonal_rotation_deg`) or, with [`VergeTiltOptions::auto_rotation`],
//! chosen by the procedure "when the scene allows" ([`choose_rotations`], pure, and
//! [`resolve_rotation`], which probes the head): it probes the elevation and pan moves
//! (both ways) at candidate sizes (10, 6, 3 deg, largest first) and keeps the largest at which
//! every probed view still sees, in both cameras, at least `min_overlap_fraction` (0.5) of
//! the reference view's stereo tracks and at least `min_tracks` of them; then the diagonal
//! views (pan and elevation turned together, each by at most that size: 4 more views) and
//! the vergence move at the largest candidate that keeps the same overlap. Calibration
//! error falls roughly as 1/rotation (the plane at infinity is found from the rotations'
//! screws), so larger is better while enough of the scene stays in view; each joint still
//! turns at most 10 deg. Why diagonals: the Cramer-Rao bound of the focal length at 3 px
//! (`f = fx` pooled over both cameras, default room, 8 seeds, the removed
//! the removed `examples/crb_plans.rs`) is 1.76 % with 3 deg single-joint views, 0.71 % at
//! 10 deg, 0.56 % adding 5 deg single-joint views (9 views), 0.47 / 0.39 / 0.31 % adding
//! diagonals of 5 / 7 / 10 deg (9 views), 0.27-0.28 % with 13 views: a combined rotation
//! moves the image along both axes at once and decorrelates the focal lengths from the
//! axes, where more of the same single-joint views add little. The diagonal views keep
//! 56-70 % of the reference tracks at 10 deg (hence 0.5 rather than the former 0.6, which
//! only single-joint views had to meet; 0.5 of about 200 tracks is still 3 times
//! `min_tracks`). Why `min_tracks` = 30: a probed view's shared tracks are counted before
//! outlier rejection, and a track enters a 3D homography only if all four of its
//! observations are inliers (0.9^4 = 0.66 of them at 10 % outliers) and it survives the
//! rotation screen, which the estimator needs `EstimationOptions::min_tracks` (12) of. In a
//! 50-point scene at 1.5 px (`headalign experiment points --only 50`, 30 seeds) 20 let a
//! 10 deg diagonal keep 11 usable tracks (2 of 30 trials failed), 25 failed 1 of 30, 30
//! none (150 seeds: 1 failure, as many as the fixed 3 deg protocol), 40 settled at 5.6 deg
//! on average and 60 (the former value) never left 3 deg, since a 50-point scene never
//! shares 60 tracks. Probe captures are discarded (they are not in `views`); a recording
//! caller calls [`resolve_rotation`] itself to record them as their own stage. Pitfall: the
//! overlap is counted by track id, which in image mode means the tracker's matches; a
//! tracker that loses tracks at larger rotations shrinks the choice, as it should (seed 1
//! on rendered images: 10 deg single-joint views, 3 deg diagonals).
//!
//! Every captured view is kept in the outcome (and in the error path the caller still has
//! them through [`VergeTiltRun::views`]). Angles in degrees.

use std::time::Instant;

use headalign_geometry::bundle::RigState;
use headalign_geometry::so3::Line;
use headalign_platform::{Encoders, Joint, StereoHead};
use nalgebra::DVector;
use serde::Serialize;

use crate::alignment::{
    AlignmentSolution, MeasuredCameras, MeasuredErrors, VergeAxes, head_motion, measure_cameras,
    measured_errors, solve_alignment, verge_axes_from_motion,
};
use crate::error::AlignError;
use crate::estimate::{EstimationOptions, RigCalibration, estimate_rig};
use crate::observations::View;

/// Options of the verge/tilt procedure.
#[derive(Debug, Clone)]
pub struct VergeTiltOptions {
    /// Elevation and pan rotation for calibration, degrees (default 3, the paper's
    /// protocol; larger rotations give proportionally better accuracy).
    pub rotation_deg: f64,
    /// Vergence rotation used to measure the vergence axes, degrees (default 3).
    pub verge_rotation_deg: f64,
    /// Rotate each of elevation and pan both ways (+r and -r), five rig views instead of
    /// three (default true): twice the angular span per axis, about half the error.
    pub both_directions: bool,
    /// Estimation options.
    pub estimation: EstimationOptions,
    /// Correct again when a measured alignment error exceeds this, degrees (default 0.2:
    /// after the first move the measured error at 1 px noise is 0.02-0.2 deg of noise, and
    /// correcting below that only chases it; a wrong vergence-axis model shows above it).
    pub check_tolerance_deg: f64,
    /// Maximum number of corrective moves after the first (default 2).
    pub max_corrections: usize,
    /// Also rotate pan and elevation together by this much, degrees (default 0: no such
    /// views): the diagonal views `(pan, elevation) = (+d, +d), (+d, -d), (-d, +d), (-d, -d)`
    /// (only `(+d, +d)` without `both_directions`). Each joint still turns by at most `d`;
    /// the combined rotations add the most information per view (module docs). The auto
    /// mode sets it.
    pub diagonal_rotation_deg: f64,
    /// Let the procedure choose the elevation/pan rotation itself (default `None`: use
    /// `rotation_deg` and `diagonal_rotation_deg`).
    pub auto_rotation: Option<AutoRotation>,
}

/// How the procedure chooses its calibration rotation when the scene allows (see the
/// module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct AutoRotation {
    /// Candidate rotation sizes, degrees, tried in increasing order (default 3, 6, 10).
    /// The first one is used even if its overlap is insufficient (the fixed protocol).
    pub candidates_deg: Vec<f64>,
    /// Fraction of the reference view's stereo tracks that each probed view must still
    /// see in both cameras (default 0.6).
    pub min_overlap_fraction: f64,
    /// Minimum number of such shared tracks (default 30; module docs: why).
    pub min_tracks: usize,
    /// After choosing the single-joint rotation `r`, also add the four diagonal views
    /// (pan and elevation together, each by the largest candidate `d <= r` whose four
    /// probed views keep the overlap; none if the smallest candidate does not) (default
    /// true).
    pub diagonals: bool,
    /// Also choose the vergence move (both vergences together, which measures the
    /// vergence axes): the largest candidate `v <= r` whose view keeps the overlap; if
    /// none does, `verge_rotation_deg` stays (default true). The vergence axis is the screw
    /// of a measured pose, whose direction error is about the pose error over the turn:
    /// at 3 px with the auto rotations, a 10 deg move instead of 3 deg took the aligned
    /// elevation's RMS error from 1.61 to 1.27 times its bound (60 seeds).
    pub choose_verge: bool,
}

impl Default for AutoRotation {
    fn default() -> Self {
        Self {
            candidates_deg: vec![3.0, 6.0, 10.0],
            min_overlap_fraction: 0.5,
            min_tracks: 30,
            diagonals: true,
            choose_verge: true,
        }
    }
}

impl AutoRotation {
    /// Check the candidates (increasing, each 0.1-45 deg) and thresholds.
    pub fn validate(&self) -> Result<(), AlignError> {
        if self.candidates_deg.is_empty() {
            return Err(AlignError::InvalidOption("auto rotation needs at least one candidate".into()));
        }
        let mut last = 0.0;
        for &c in &self.candidates_deg {
            if !(c.is_finite() && (0.1..=45.0).contains(&c) && c > last) {
                return Err(AlignError::InvalidOption(format!(
                    "auto rotation candidates must increase within 0.1-45 degrees, got {:?}",
                    self.candidates_deg
                )));
            }
            last = c;
        }
        if !(self.min_overlap_fraction.is_finite() && (0.0..=1.0).contains(&self.min_overlap_fraction)) {
            return Err(AlignError::InvalidOption(format!(
                "min_overlap_fraction must be in [0, 1], got {}",
                self.min_overlap_fraction
            )));
        }
        Ok(())
    }
}

impl Default for VergeTiltOptions {
    fn default() -> Self {
        Self {
            rotation_deg: 3.0,
            verge_rotation_deg: 3.0,
            both_directions: true,
            estimation: EstimationOptions::default(),
            check_tolerance_deg: 0.2,
            max_corrections: 2,
            diagonal_rotation_deg: 0.0,
            auto_rotation: None,
        }
    }
}

impl VergeTiltOptions {
    /// Check every option.
    pub fn validate(&self) -> Result<(), AlignError> {
        for (name, v) in
            [("rotation_deg", self.rotation_deg), ("verge_rotation_deg", self.verge_rotation_deg)]
        {
            if !(v.abs() >= 0.1 && v.abs() <= 45.0) {
                return Err(AlignError::InvalidOption(format!(
                    "{name} must be between 0.1 and 45 degrees in magnitude, got {v}"
                )));
            }
        }
        let d = self.diagonal_rotation_deg;
        if !(d == 0.0 || (d.abs() >= 0.1 && d.abs() <= 45.0)) {
            return Err(AlignError::InvalidOption(format!(
                "diagonal_rotation_deg must be 0 or between 0.1 and 45 degrees in magnitude, got {d}"
            )));
        }
        if !self.check_tolerance_deg.is_finite() || self.check_tolerance_deg <= 0.0 {
            return Err(AlignError::InvalidOption("check_tolerance_deg must be positive".into()));
        }
        if let Some(auto) = &self.auto_rotation {
            auto.validate()?;
        }
        self.estimation.validate()
    }
}

/// One move to the aligned readings and its check by vision.
#[derive(Debug, Clone, Serialize)]
pub struct CheckStep {
    /// Readings moved to.
    pub encoders: Encoders,
    /// Errors measured by resection after the move.
    pub measured: MeasuredErrors,
}

/// 1-sigma uncertainties of the aligned readings, degrees, propagated from the bundle
/// adjustment's covariance and, in the procedure ([`alignment_sigmas_measured`]), from the
/// resections that measured the vergence axes.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct AlignmentSigmas {
    /// Elevation reading.
    pub elevation_deg: f64,
    /// Left vergence reading.
    pub verge_left_deg: f64,
    /// Right vergence reading.
    pub verge_right_deg: f64,
}

impl AlignmentSigmas {
    /// The sigmas with a reading noise of `sigma_deg` per joint added in quadrature: the
    /// aligned readings are the reference view's readings plus the solved turns, so that
    /// read's error is in each of them.
    pub fn with_reading_noise(self, sigma_deg: f64) -> Self {
        let add = |s: f64| s.hypot(sigma_deg);
        Self {
            elevation_deg: add(self.elevation_deg),
            verge_left_deg: add(self.verge_left_deg),
            verge_right_deg: add(self.verge_right_deg),
        }
    }
}

/// Everything the procedure produced.
#[derive(Debug, Clone)]
pub struct VergeTiltOutcome {
    /// The calibration.
    pub calibration: RigCalibration,
    /// Vergence axes measured by resection.
    pub verge_axes: VergeAxes,
    /// The views (and resected poses) each vergence axis was measured from.
    pub axis_sources: AxisSources,
    /// The final alignment solution.
    pub solution: AlignmentSolution,
    /// Uncertainty of the aligned readings.
    pub sigmas: AlignmentSigmas,
    /// Each move and its check.
    pub checks: Vec<CheckStep>,
    /// Final encoder readings (aligned).
    pub final_encoders: Encoders,
    /// Elevation/pan rotation used for calibration, degrees (chosen if auto).
    pub rotation_deg: f64,
    /// Diagonal (pan and elevation together) rotation used, degrees; 0 if none (chosen if
    /// auto).
    pub diagonal_rotation_deg: f64,
    /// Vergence move used to measure the vergence axes, degrees (chosen if auto).
    pub verge_rotation_deg: f64,
    /// Seconds spent estimating (excluding head motion and capture).
    pub estimation_seconds: f64,
}

impl VergeTiltOutcome {
    /// The vergence axes' uncertainty for the robot stages ([`axis_perturbations`] over
    /// this outcome's axes and their sources, the pixel noise the bundle adjustment's
    /// estimate: the axis views come from the same cameras, and the resections' own
    /// residuals, truncated at their 5 px outlier threshold, estimate it low at 3 px).
    pub fn axis_perturbations(&self) -> AxisPerturbations {
        let cal = &self.calibration;
        axis_perturbations(
            cal,
            &self.verge_axes,
            &self.axis_sources,
            &cal.reference_encoders,
            Some(cal.report.sigma_px),
        )
    }
}

/// A run of the procedure: the views captured so far survive any error.
#[derive(Debug, Default)]
pub struct VergeTiltRun {
    /// Every captured view, in order.
    pub views: Vec<View>,
}

impl VergeTiltRun {
    fn capture<H: StereoHead>(&mut self, head: &mut H, name: &str) -> Result<usize, AlignError> {
        let capture = head.capture()?;
        self.views.push(View { name: name.to_string(), capture });
        Ok(self.views.len() - 1)
    }

    /// Run the procedure on `head`.
    pub fn run<H: StereoHead>(
        &mut self,
        head: &mut H,
        options: &VergeTiltOptions,
    ) -> Result<VergeTiltOutcome, AlignError> {
        options.validate()?;
        let options = &resolve_rotation(head, options)?;
        let e0 = head.read_encoders()?;
        let (rotation_deg, diagonal_rotation_deg) = (options.rotation_deg, options.diagonal_rotation_deg);
        let plan = capture_plan(&e0, options);
        for (name, encoders) in &plan {
            head.move_to(encoders)?;
            self.capture(head, name)?;
        }
        // Every view of the plan but the last (the vergence move) keeps the rig rigid.
        let rig_views = plan.len() - 1;
        let verge_view = rig_views;
        head.move_to(&e0)?;

        let t0 = Instant::now();
        let calibration = estimate_rig(&self.views[..rig_views], &options.estimation)?;
        let state = &calibration.bundle.state;
        let reference = self.views[0].capture.encoders;
        let left0 = nalgebra::Isometry3::identity();
        let right0 = state.right_from_left.inverse();
        let measured = measure_cameras(&calibration, &self.views[verge_view].capture, &left0, &right0)?;
        let mut verge_axes =
            verge_axes_from_motion(state, &reference, &self.views[verge_view].capture.encoders, &measured)?;
        let source = AxisMeasurement { capture: self.views[verge_view].capture.clone(), measured };
        let mut axis_sources = AxisSources {
            left: verge_axes.left.map(|_| source.clone()),
            right: verge_axes.right.map(|_| source.clone()),
        };
        let mut solution = solve_alignment(state, &verge_axes, &reference)?;
        let mut estimation_seconds = t0.elapsed().as_secs_f64();

        let mut checks = Vec::new();
        for round in 0..=options.max_corrections {
            let target = solution.aligned_encoders;
            head.move_to(&target)?;
            let idx = self.capture(head, &format!("check-{}", round + 1))?;
            let t1 = Instant::now();
            let enc = self.views[idx].capture.encoders;
            let d = |j: Joint| (enc.get(j) - reference.get(j)).to_radians();
            let (pl, pr) = predicted_poses(&calibration, &verge_axes, &reference, &enc)?;
            let measured = measure_cameras(&calibration, &self.views[idx].capture, &pl, &pr)?;
            let errors = measured_errors(state, &measured, d(Joint::Pan))
                .ok_or_else(|| AlignError::MissingMotion("pan and elevation axes".into()))?;
            checks.push(CheckStep { encoders: enc, measured: errors });
            // The right camera's elevation error is not correctable; the other three are.
            let worst = errors
                .verge_err_l_deg
                .abs()
                .max(errors.verge_err_r_deg.abs())
                .max(errors.elev_err_l_deg.abs());
            if worst <= options.check_tolerance_deg || round == options.max_corrections {
                estimation_seconds += t1.elapsed().as_secs_f64();
                break;
            }
            // Re-measure a vergence axis from this move only if its vergence turned at
            // least as far as the procedure's own vergence move: the axis is the screw of
            // the measured pose against the modelled pan/elevation chain, so a small
            // vergence turn on top of a large elevation turn measures mostly the chain's
            // error (at 3 px, a 0.9 deg turn after 8 deg of elevation gave an axis 80 deg
            // off and an 8 deg alignment error). No axis re-measured: nothing to correct.
            let big = |j: Joint| (enc.get(j) - reference.get(j)).abs() >= options.verge_rotation_deg.abs();
            let better = verge_axes_from_motion(state, &reference, &enc, &measured)?;
            let left = better.left.filter(|_| big(Joint::VergeLeft));
            let right = better.right.filter(|_| big(Joint::VergeRight));
            if left.is_none() && right.is_none() {
                estimation_seconds += t1.elapsed().as_secs_f64();
                break;
            }
            let source = AxisMeasurement { capture: self.views[idx].capture.clone(), measured };
            if left.is_some() {
                axis_sources.left = Some(source.clone());
            }
            if right.is_some() {
                axis_sources.right = Some(source);
            }
            verge_axes = VergeAxes { left: left.or(verge_axes.left), right: right.or(verge_axes.right) };
            solution = solve_alignment(state, &verge_axes, &reference)?;
            estimation_seconds += t1.elapsed().as_secs_f64();
        }
        let reading_sigma_deg = options.estimation.bundle.angle_prior_sigma.map_or(0.0, f64::to_degrees);
        let sigmas = alignment_sigmas_measured(&calibration, &verge_axes, &axis_sources, &reference, None)?
            .with_reading_noise(reading_sigma_deg);
        let final_encoders = head.read_encoders()?;
        Ok(VergeTiltOutcome {
            calibration,
            verge_axes,
            axis_sources,
            solution,
            sigmas,
            checks,
            final_encoders,
            rotation_deg,
            diagonal_rotation_deg,
            verge_rotation_deg: options.verge_rotation_deg,
            estimation_seconds,
        })
    }
}

/// Track ids seen by both cameras of a capture.
fn stereo_tracks(capture: &headalign_platform::StereoCapture) -> std::collections::HashSet<u64> {
    let left: std::collections::HashSet<u64> = capture.left.iter().map(|o| o.track).collect();
    capture.right.iter().map(|o| o.track).filter(|t| left.contains(t)).collect()
}

/// How many of `reference`'s stereo tracks `capture` also sees in both cameras.
pub fn shared_stereo_tracks(
    reference: &headalign_platform::StereoCapture,
    capture: &headalign_platform::StereoCapture,
) -> (usize, usize) {
    let r = stereo_tracks(reference);
    let c = stereo_tracks(capture);
    (r.intersection(&c).count(), r.len())
}

/// The calibration rotations the procedure uses, degrees.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RotationChoice {
    /// Single-joint (elevation, pan) rotation.
    pub rotation_deg: f64,
    /// Diagonal rotation (pan and elevation together); 0 for none.
    pub diagonal_rotation_deg: f64,
    /// Vergence move (both vergences together), if chosen.
    pub verge_rotation_deg: Option<f64>,
}

/// The (pan, elevation) offsets of the single-joint views at rotation `r` (elevation
/// first), each both ways if `both_directions`.
fn single_joint_offsets(r: f64, both_directions: bool) -> Vec<(&'static str, f64, f64)> {
    if both_directions {
        vec![("elevation+", 0.0, r), ("elevation-", 0.0, -r), ("pan+", r, 0.0), ("pan-", -r, 0.0)]
    } else {
        vec![("elevation", 0.0, r), ("pan", r, 0.0)]
    }
}

/// The (pan, elevation) offsets of the diagonal views at rotation `d` (none if `d` is 0).
fn diagonal_offsets(d: f64, both_directions: bool) -> Vec<(&'static str, f64, f64)> {
    if d == 0.0 {
        Vec::new()
    } else if both_directions {
        vec![
            ("pan+elevation+", d, d),
            ("pan+elevation-", d, -d),
            ("pan-elevation+", -d, d),
            ("pan-elevation-", -d, -d),
        ]
    } else {
        vec![("pan+elevation+", d, d)]
    }
}

/// The choice logic of the auto mode, pure (module docs): `keeps_overlap(pan, elevation,
/// verge)` says whether the view at those offsets (degrees; `verge` turns both vergences)
/// from the initial readings keeps enough of the reference view's tracks. The single-joint
/// rotation is the largest candidate whose views all keep it, probing in decreasing order
/// (a view that fails moves on to the next smaller candidate; the first candidate is used
/// regardless, unprobed: the fixed protocol); largest first costs 4 probes when the scene
/// allows the largest (8 probing upwards, which matters on images, where each probe is a
/// capture and tracking); then, if `auto.diagonals`, the diagonal rotation is
/// the largest candidate not above it whose diagonal views all keep it, probing in
/// decreasing order (0 if none does); then, if `auto.choose_verge`, the vergence move
/// likewise (`None` if none does). Probes are requested in the order they are needed, and
/// none twice.
pub fn choose_rotations<E>(
    auto: &AutoRotation,
    both_directions: bool,
    mut keeps_overlap: impl FnMut(f64, f64, f64) -> Result<bool, E>,
) -> Result<RotationChoice, E> {
    let mut chosen = auto.candidates_deg.first().copied().unwrap_or(3.0);
    'candidates: for &r in auto.candidates_deg.iter().skip(1).rev() {
        for (_, pan, elevation) in single_joint_offsets(r, both_directions) {
            if !keeps_overlap(pan, elevation, 0.0)? {
                continue 'candidates;
            }
        }
        chosen = r;
        break;
    }
    let mut diagonal = 0.0;
    if auto.diagonals {
        'diagonals: for &d in auto.candidates_deg.iter().rev().filter(|&&d| d <= chosen) {
            for (_, pan, elevation) in diagonal_offsets(d, both_directions) {
                if !keeps_overlap(pan, elevation, 0.0)? {
                    continue 'diagonals;
                }
            }
            diagonal = d;
            break;
        }
    }
    let mut verge = None;
    if auto.choose_verge {
        for &v in auto.candidates_deg.iter().rev().filter(|&&v| v <= chosen) {
            if keeps_overlap(0.0, 0.0, v)? {
                verge = Some(v);
                break;
            }
        }
    }
    Ok(RotationChoice { rotation_deg: chosen, diagonal_rotation_deg: diagonal, verge_rotation_deg: verge })
}

/// The options with the auto mode resolved: if `options.auto_rotation` is set, probe the
/// head from its current readings ([`choose_rotations`]; the head returns there) and
/// return the options with the chosen `rotation_deg` and `diagonal_rotation_deg` and no
/// auto mode; otherwise a copy. [`VergeTiltRun::run`] calls it first; a caller that
/// records sessions calls it itself to record the probes as their own stage.
pub fn resolve_rotation<H: StereoHead>(
    head: &mut H,
    options: &VergeTiltOptions,
) -> Result<VergeTiltOptions, AlignError> {
    let Some(auto) = &options.auto_rotation else { return Ok(options.clone()) };
    auto.validate()?;
    let e0 = head.read_encoders()?;
    let c = choose_rotation(head, &e0, options.both_directions, auto)?;
    Ok(VergeTiltOptions {
        rotation_deg: c.rotation_deg,
        diagonal_rotation_deg: c.diagonal_rotation_deg,
        verge_rotation_deg: c.verge_rotation_deg.unwrap_or(options.verge_rotation_deg),
        auto_rotation: None,
        ..options.clone()
    })
}

/// Probe the head for [`choose_rotations`]: capture a reference view at `e0`, then each
/// requested view; count its shared stereo tracks. Returns to `e0`.
fn choose_rotation<H: StereoHead>(
    head: &mut H,
    e0: &Encoders,
    both_directions: bool,
    auto: &AutoRotation,
) -> Result<RotationChoice, AlignError> {
    head.move_to(e0)?;
    let reference = head.capture()?;
    let choice = choose_rotations(auto, both_directions, |pan, elevation, verge| {
        let target = e0
            .moved(Joint::Pan, pan)
            .moved(Joint::Elevation, elevation)
            .moved(Joint::VergeLeft, verge)
            .moved(Joint::VergeRight, verge);
        head.move_to(&target)?;
        let probe = head.capture()?;
        let (shared, total) = shared_stereo_tracks(&reference, &probe);
        Ok::<bool, AlignError>(
            shared >= auto.min_tracks && (shared as f64) >= auto.min_overlap_fraction * total as f64,
        )
    })?;
    head.move_to(e0)?;
    Ok(choice)
}

/// The views the procedure captures, in order, from the initial readings `e0`: the
/// initial view; elevation and pan rotations (each both ways if `both_directions`); the
/// diagonal views if `diagonal_rotation_deg` is not 0; and last, both vergences rotated
/// (to measure the vergence axes).
pub fn capture_plan(e0: &Encoders, options: &VergeTiltOptions) -> Vec<(String, Encoders)> {
    let mut plan = vec![("initial".to_string(), *e0)];
    let moves = single_joint_offsets(options.rotation_deg, options.both_directions)
        .into_iter()
        .chain(diagonal_offsets(options.diagonal_rotation_deg, options.both_directions));
    for (name, pan, elevation) in moves {
        plan.push((name.to_string(), e0.moved(Joint::Pan, pan).moved(Joint::Elevation, elevation)));
    }
    let v = options.verge_rotation_deg;
    plan.push(("verge".to_string(), e0.moved(Joint::VergeLeft, v).moved(Joint::VergeRight, v)));
    plan
}

/// Predicted `ref_from_cam` of both cameras at encoders `enc` from the kinematic model.
pub(crate) fn predicted_poses(
    calib: &RigCalibration,
    verge: &VergeAxes,
    reference: &Encoders,
    enc: &Encoders,
) -> Result<(nalgebra::Isometry3<f64>, nalgebra::Isometry3<f64>), AlignError> {
    let state = &calib.bundle.state;
    let d = |j: Joint| (enc.get(j) - reference.get(j)).to_radians();
    let chain = head_motion(state, d(Joint::Pan), d(Joint::Elevation))
        .ok_or_else(|| AlignError::MissingMotion("pan and elevation axes".into()))?;
    let rot = |axis: &Option<Line>, angle: f64| {
        axis.map(|l| headalign_geometry::so3::rotation_about_line(&l, angle))
            .unwrap_or_else(nalgebra::Isometry3::identity)
    };
    let left = chain * rot(&verge.left, d(Joint::VergeLeft));
    let right = chain * rot(&verge.right, d(Joint::VergeRight)) * state.right_from_left.inverse();
    Ok((left, right))
}

/// Central-difference step of the uncertainty propagations ([`alignment_sigmas`],
/// [`alignment_sigmas_measured`], [`AxisPerturbations`] and [`crate::robot`]'s), in
/// standard deviations of the parameter moved (or units of a unit-variance mode). The
/// propagation is linear, so the step must be small against the curvature of what is
/// differentiated, yet large against the solvers' tolerances. The re-derived vergence
/// axes bend within half a sigma of some calibrations: with 0.5 (the earlier step)
/// `experiment calibration --only 3 --trials 1 --seed 273` reported an elevation sigma
/// of 2.17 deg against a bound of 0.73; with 0.25, 0.1, 0.02 and 0.005 it is 0.868,
/// 0.752, 0.751 and 0.752 deg. Over seeds 1-150 at 2 and 3 px 0.1 moved 7 of 900
/// aligned sigmas by more than 5 % and none of the RMS or coverage figures.
pub const PROPAGATION_STEP_SIGMAS: f64 = 0.1;

/// Propagate the bundle adjustment's covariance to the aligned readings by central
/// differences of [`solve_alignment`] along each parameter's standard deviation, the
/// vergence axes held as given ([`alignment_sigmas_measured`] adds their measurement).
pub fn alignment_sigmas(
    calib: &RigCalibration,
    verge: &VergeAxes,
    reference: &Encoders,
) -> Result<AlignmentSigmas, AlignError> {
    let jac = calibration_jacobian(
        &calib.bundle.covariance,
        &[&|delta| held_axes_deltas(calib, verge, reference, delta)],
    );
    Ok(sigmas_of(&(&jac * &calib.bundle.covariance.matrix * jac.transpose())))
}

/// The aligned deltas with the bundle's parameters moved by `delta` (its tangent) and
/// the vergence axes held as given.
fn held_axes_deltas(
    calib: &RigCalibration,
    verge: &VergeAxes,
    reference: &Encoders,
    delta: &DVector<f64>,
) -> Option<[f64; 3]> {
    let st = calib.bundle.perturbed(delta).ok()?;
    solve_alignment(&st, verge, reference).ok().map(|s| aligned_deltas(&s))
}

/// The aligned joint changes (elevation, left and right vergence), degrees.
fn aligned_deltas(s: &AlignmentSolution) -> [f64; 3] {
    [s.delta_elevation_deg, s.delta_verge_left_deg, s.delta_verge_right_deg]
}

/// The aligned deltas under a perturbation of the bundle's parameters (its tangent, in
/// its covariance's order); `None` where they cannot be computed.
type AlignedDeltasAt<'a> = dyn Fn(&DVector<f64>) -> Option<[f64; 3]> + 'a;

/// Jacobian (3 x n, per unit of each parameter) of the aligned deltas under a
/// perturbation of the bundle's parameters (in its covariance's order) by central
/// differences at [`PROPAGATION_STEP_SIGMAS`] of each parameter's standard deviation
/// ([`AxisPerturbations::calibration_step`]). Each column comes from the first of `fs`
/// that succeeds on both sides (so a fallback is never mixed into one difference); a
/// column whose parameter has no positive variance, or where every one fails, is zero.
fn calibration_jacobian(
    cov: &headalign_geometry::bundle::Covariance,
    fs: &[&AlignedDeltasAt],
) -> nalgebra::DMatrix<f64> {
    let n = cov.matrix.nrows();
    let mut jac = nalgebra::DMatrix::<f64>::zeros(3, n);
    for i in 0..n {
        let h = AxisPerturbations::calibration_step(cov, i);
        if h.is_nan() || h <= 0.0 {
            continue;
        }
        let mut plus = DVector::zeros(n);
        plus[i] = h;
        let minus = -&plus;
        if let Some((p, m)) = fs.iter().find_map(|f| Some((f(&plus)?, f(&minus)?))) {
            for r in 0..3 {
                jac[(r, i)] = (p[r] - m[r]) / (2.0 * h);
            }
        }
    }
    jac
}

/// Square roots of the diagonal of a 3x3 covariance of the aligned deltas.
fn sigmas_of(cov: &nalgebra::DMatrix<f64>) -> AlignmentSigmas {
    AlignmentSigmas {
        elevation_deg: cov[(0, 0)].max(0.0).sqrt(),
        verge_left_deg: cov[(1, 1)].max(0.0).sqrt(),
        verge_right_deg: cov[(2, 2)].max(0.0).sqrt(),
    }
}

/// One measurement of the vergence axes: the capture after a vergence move and the
/// cameras resected from it.
#[derive(Debug, Clone)]
pub struct AxisMeasurement {
    /// The capture (its encoders give the joint turns).
    pub capture: headalign_platform::StereoCapture,
    /// Both cameras resected from it.
    pub measured: MeasuredCameras,
}

/// Where each vergence axis came from (`None`: not measured, nominal).
#[derive(Debug, Clone, Default)]
pub struct AxisSources {
    /// Source of the left vergence axis.
    pub left: Option<AxisMeasurement>,
    /// Source of the right vergence axis.
    pub right: Option<AxisMeasurement>,
}

/// The observations of `obs` that [`crate::alignment::measure_cameras`]' resection keeps:
/// tracks among `points` (the calibration's points seen three or more times,
/// [`RigCalibration::points`]) whose residual at `ref_from_cam` is within the resection's
/// outlier threshold (`ResectionOptions::outlier_px`), as (track, observed pixel). Chosen
/// once at the estimate and then held: a threshold re-applied under each finite-difference
/// perturbation would move observations in and out between the two sides of a difference.
fn resection_inliers(
    k: &headalign_geometry::camera::Intrinsics,
    points: &std::collections::HashMap<u64, nalgebra::Point3<f64>>,
    obs: &[headalign_platform::TrackObservation],
    ref_from_cam: &nalgebra::Isometry3<f64>,
) -> Vec<(u64, nalgebra::Vector2<f64>)> {
    let outlier_px = headalign_geometry::resection::ResectionOptions::default().outlier_px;
    obs.iter()
        .filter(|o| {
            points
                .get(&o.track)
                .and_then(|x| project_into(k, ref_from_cam, x))
                .is_some_and(|p| (p - o.pixel.coords).norm() <= outlier_px)
        })
        .map(|o| (o.track, o.pixel.coords))
        .collect()
}

/// The pose-only noise estimate from a resection's inliers (pixels): the residuals' RMS at
/// `ref_from_cam` with 6 degrees of freedom taken out. Needs at least 4 inliers.
fn residual_sigma(
    k: &headalign_geometry::camera::Intrinsics,
    points: &std::collections::HashMap<u64, nalgebra::Point3<f64>>,
    inliers: &[(u64, nalgebra::Vector2<f64>)],
    ref_from_cam: &nalgebra::Isometry3<f64>,
) -> f64 {
    let dof = (2 * inliers.len() - 6) as f64;
    let sum: f64 = inliers
        .iter()
        .filter_map(|(t, px)| project_into(k, ref_from_cam, points.get(t)?).map(|p| (p - px).norm_squared()))
        .sum();
    (sum / dof).sqrt()
}

/// Pixel of `x` (reference frame) in the camera at `ref_from_cam`.
fn project_into(
    k: &headalign_geometry::camera::Intrinsics,
    ref_from_cam: &nalgebra::Isometry3<f64>,
    x: &nalgebra::Point3<f64>,
) -> Option<nalgebra::Vector2<f64>> {
    k.project(&ref_from_cam.inverse_transform_point(x)).map(|p| p.coords)
}

/// Gauss-Newton normal equations `(J^T J, J^T r)` of a pose resected against `points` from
/// `inliers` (residual projected - observed, pixels; `J` by central differences along the
/// tangent `ref_from_cam * Exp([w; t])`, step 1e-6). `None` if a point leaves the image
/// plane under the step.
fn resection_normal_equations(
    k: &headalign_geometry::camera::Intrinsics,
    points: &std::collections::HashMap<u64, nalgebra::Point3<f64>>,
    inliers: &[(u64, nalgebra::Vector2<f64>)],
    ref_from_cam: &nalgebra::Isometry3<f64>,
) -> Option<(nalgebra::Matrix6<f64>, nalgebra::Vector6<f64>)> {
    let h = 1e-6;
    let mut jtj = nalgebra::Matrix6::<f64>::zeros();
    let mut jtr = nalgebra::Vector6::<f64>::zeros();
    for (track, pixel) in inliers {
        let Some(x) = points.get(track) else { continue };
        let r = project_into(k, ref_from_cam, x)? - pixel;
        let mut j = nalgebra::Matrix2x6::<f64>::zeros();
        for c in 0..6 {
            let mut d = nalgebra::Vector6::<f64>::zeros();
            d[c] = h;
            let plus = project_into(k, &(ref_from_cam * tangent_step(&d)), x)?;
            let minus = project_into(k, &(ref_from_cam * tangent_step(&-d)), x)?;
            j.set_column(c, &((plus - minus) / (2.0 * h)));
        }
        jtj += j.transpose() * j;
        jtr += j.transpose() * r;
    }
    Some((jtj, jtr))
}

/// Covariance (6x6, tangent `ref_from_cam * Exp([w; t])`, radians and scene units) of a
/// camera pose resected from `obs` against `points` by [`crate::alignment::measure_cameras`]:
/// `sigma^2 (J^T J)^-1` over the observations it keeps (`resection_inliers`), `J` by
/// central differences. `sigma` is `noise_px` or, if `None`, the residuals' own estimate
/// `sqrt(sum r^2 / (2n - 6))`. `None` if fewer than 4 points or `J^T J` is singular.
pub fn resection_pose_covariance(
    k: &headalign_geometry::camera::Intrinsics,
    points: &std::collections::HashMap<u64, nalgebra::Point3<f64>>,
    obs: &[headalign_platform::TrackObservation],
    ref_from_cam: &nalgebra::Isometry3<f64>,
    noise_px: Option<f64>,
) -> Option<nalgebra::Matrix6<f64>> {
    let inliers = resection_inliers(k, points, obs, ref_from_cam);
    if inliers.len() < 4 {
        return None;
    }
    let sigma = noise_px.unwrap_or_else(|| residual_sigma(k, points, &inliers, ref_from_cam));
    let (jtj, _) = resection_normal_equations(k, points, &inliers, ref_from_cam)?;
    jtj.try_inverse().map(|inv| inv * (sigma * sigma))
}

/// Draws of [`resection_pose_covariance_bootstrap`]: the covariance of a 6-vector from
/// 200 draws knows each standard deviation to about 5 %.
pub const AXIS_BOOTSTRAP_DRAWS: usize = 200;
/// Seed of the bootstrap's noise (left camera; the right one adds 1).
const AXIS_BOOTSTRAP_SEED: u64 = 0x5eed_a215;

/// Covariance (6x6, tangent as [`resection_pose_covariance`]) of a camera pose resected
/// by [`crate::alignment::measure_cameras`], as the spread of its own robust resection
/// re-run on [`AXIS_BOOTSTRAP_DRAWS`] synthetic draws
/// ([`headalign_geometry::resection::resection_bootstrap`]: the exact pixels, at the
/// estimate, of every point the capture observes, plus Gaussian noise of `noise_px` or, if `None`,
/// the residuals' estimate as [`resection_pose_covariance`]). Unlike the least-squares
/// covariance it includes the resection's Huber loss (2 px) and its outlier re-selection
/// (5 px), which at 3 px noise widen the pose's spread about 1.4x (standard deviation;
/// 1.0x at 1 px; the removed `examples/axis_mc.rs`). `None` with fewer than 6 points or 20 successful
/// draws.
pub fn resection_pose_covariance_bootstrap(
    k: &headalign_geometry::camera::Intrinsics,
    points: &std::collections::HashMap<u64, nalgebra::Point3<f64>>,
    obs: &[headalign_platform::TrackObservation],
    ref_from_cam: &nalgebra::Isometry3<f64>,
    noise_px: Option<f64>,
    seed: u64,
) -> Option<nalgebra::Matrix6<f64>> {
    use headalign_geometry::resection::{ResectionOptions, resection_bootstrap};
    let inliers = resection_inliers(k, points, obs, ref_from_cam);
    if inliers.len() < 6 {
        return None;
    }
    let sigma = noise_px.unwrap_or_else(|| residual_sigma(k, points, &inliers, ref_from_cam));
    // Every observed point, as the resection sees them (its inliers at 3 px are only about
    // 75 % of the true matches: a draw from the inliers alone would re-select a subset of
    // a subset and spread 12 % wider).
    let xs: Vec<nalgebra::Point3<f64>> = obs.iter().filter_map(|o| points.get(&o.track).copied()).collect();
    let cam_from_ref = ref_from_cam.inverse();
    let draws = resection_bootstrap(
        k,
        &xs,
        &cam_from_ref,
        sigma,
        AXIS_BOOTSTRAP_DRAWS,
        seed,
        &ResectionOptions::default(),
    )
    .ok()?;
    if draws.len() < 20 {
        return None;
    }
    // Tangent of each draw: ref_from_cam_draw = ref_from_cam * Exp([w; t]).
    let ds: Vec<nalgebra::Vector6<f64>> = draws
        .iter()
        .map(|c| {
            let d = cam_from_ref * c.inverse();
            let w = d.rotation.scaled_axis();
            let t = d.translation.vector;
            nalgebra::Vector6::new(w.x, w.y, w.z, t.x, t.y, t.z)
        })
        .collect();
    let n = ds.len() as f64;
    let mean: nalgebra::Vector6<f64> = ds.iter().sum::<nalgebra::Vector6<f64>>() / n;
    Some(ds.iter().map(|d| (d - mean) * (d - mean).transpose()).sum::<nalgebra::Matrix6<f64>>() / (n - 1.0))
}

/// The points of `state` moved by one Gauss-Newton step each against their bundle
/// observations `by_point` (indices into `state.points`): to first order the points'
/// conditional mean given the perturbed camera parameters (the covariance has the points
/// eliminated; they follow the cameras). Points with fewer than 2 observations are held,
/// and so is a point whose step would leave one of its observations unprojectable.
fn retriangulated(
    state: &RigState,
    by_point: &[Vec<&headalign_geometry::bundle::BundleObservation>],
) -> RigState {
    use headalign_geometry::bundle::residual_pixels_at;
    let mut out = state.clone();
    // Each view's pose once (the residuals' own, so the arithmetic is unchanged).
    let poses: Vec<nalgebra::Isometry3<f64>> =
        (0..state.motions.view_count()).map(|v| state.motions.ref_from_cam(v)).collect();
    let h = 1e-6;
    for (j, obs) in by_point.iter().enumerate() {
        if obs.len() < 2 || j >= out.points.len() {
            continue;
        }
        let x = state.points[j];
        let mut jtj = nalgebra::Matrix3::<f64>::zeros();
        let mut jtr = nalgebra::Vector3::<f64>::zeros();
        for o in obs {
            let Some(pose) = poses.get(o.view) else { continue };
            let Some(r) = residual_pixels_at(state, pose, &x, o) else { continue };
            let mut jm = nalgebra::Matrix2x3::<f64>::zeros();
            let mut ok = true;
            for c in 0..3 {
                let mut probe = x;
                probe[c] += h;
                let p = residual_pixels_at(state, pose, &probe, o);
                probe[c] -= 2.0 * h;
                let m = residual_pixels_at(state, pose, &probe, o);
                match (p, m) {
                    (Some(p), Some(m)) => jm.set_column(c, &((p - m) / (2.0 * h))),
                    _ => ok = false,
                }
            }
            if ok {
                jtj += jm.transpose() * jm;
                jtr += jm.transpose() * r;
            }
        }
        let Some(inv) = jtj.try_inverse() else { continue };
        let moved = x - inv * jtr;
        // A point near infinity has a nearly singular `J^T J`: its step may carry it
        // through infinity to behind its cameras, where nothing downstream can project it
        // (seed 72 at 3 px: one such point made every perturbation's re-resection fail and
        // the aligned sigmas collapse to the encoder prior's). Such a point is held: it
        // is seen along nearly the same ray either way.
        if obs.iter().all(|o| {
            poses.get(o.view).is_some_and(|pose| residual_pixels_at(state, pose, &moved, o).is_some())
        }) {
            out.points[j] = moved;
        }
    }
    out
}

/// One Gauss-Newton step of the resection of `ref_from_cam` against `points` over the
/// observations the resection kept at the estimate (`inliers`, [`resection_inliers`]): to
/// first order the pose [`crate::alignment::measure_cameras`] would return for these
/// intrinsics and points.
fn reresected(
    k: &headalign_geometry::camera::Intrinsics,
    points: &std::collections::HashMap<u64, nalgebra::Point3<f64>>,
    inliers: &[(u64, nalgebra::Vector2<f64>)],
    ref_from_cam: &nalgebra::Isometry3<f64>,
) -> Option<nalgebra::Isometry3<f64>> {
    let (jtj, jtr) = resection_normal_equations(k, points, inliers, ref_from_cam)?;
    let step = -(jtj.try_inverse()? * jtr);
    Some(ref_from_cam * tangent_step(&step))
}

/// `Exp([w; t])` as an isometry (rotation vector `w`, translation `t`).
fn tangent_step(d: &nalgebra::Vector6<f64>) -> nalgebra::Isometry3<f64> {
    nalgebra::Isometry3::new(
        nalgebra::Vector3::new(d[3], d[4], d[5]),
        nalgebra::Vector3::new(d[0], d[1], d[2]),
    )
}

/// The vergence axes re-measured under perturbations, linearised: what
/// [`alignment_sigmas_measured`] differentiates.
struct AxisFollow<'a> {
    calib: &'a RigCalibration,
    verge: &'a VergeAxes,
    sources: &'a AxisSources,
    reference: &'a Encoders,
    /// Every observation of the final adjustment, by point.
    by_point: Vec<Vec<&'a headalign_geometry::bundle::BundleObservation>>,
    /// The resections' inliers at the estimate ([`resection_inliers`]), left then right.
    inliers: [Vec<(u64, nalgebra::Vector2<f64>)>; 2],
    /// The resected poses: left camera of the left source, right camera of the right one.
    poses: [Option<nalgebra::Isometry3<f64>>; 2],
}

impl<'a> AxisFollow<'a> {
    /// Side `side`'s resection (0: the left camera of the left axis' source, 1: the right
    /// camera of the right one): its observations, its intrinsics in the calibration and
    /// its resected pose; `None` for an axis without a source or without a pose.
    fn resected(
        &self,
        side: usize,
    ) -> Option<(
        &'a [headalign_platform::TrackObservation],
        &'a headalign_geometry::camera::Intrinsics,
        nalgebra::Isometry3<f64>,
    )> {
        let state = &self.calib.bundle.state;
        let (obs, k) = if side == 0 {
            (self.sources.left.as_ref().map(|s| s.capture.left.as_slice()), &state.left)
        } else {
            (self.sources.right.as_ref().map(|s| s.capture.right.as_slice()), &state.right)
        };
        Some((obs?, k, self.poses.get(side).copied().flatten()?))
    }

    fn new(
        calib: &'a RigCalibration,
        verge: &'a VergeAxes,
        sources: &'a AxisSources,
        reference: &'a Encoders,
    ) -> Self {
        let mut by_point: Vec<Vec<&headalign_geometry::bundle::BundleObservation>> =
            vec![Vec::new(); calib.bundle.state.points.len()];
        for o in &calib.observations {
            if o.point < by_point.len() {
                by_point[o.point].push(o);
            }
        }
        let state = &calib.bundle.state;
        let points: std::collections::HashMap<u64, nalgebra::Point3<f64>> =
            calib.points().into_iter().collect();
        let poses = [
            sources.left.as_ref().map(|s| s.measured.ref_from_left),
            sources.right.as_ref().map(|s| s.measured.ref_from_right),
        ];
        let inliers = [
            match (&sources.left, poses[0]) {
                (Some(src), Some(p)) => resection_inliers(&state.left, &points, &src.capture.left, &p),
                _ => Vec::new(),
            },
            match (&sources.right, poses[1]) {
                (Some(src), Some(p)) => resection_inliers(&state.right, &points, &src.capture.right, &p),
                _ => Vec::new(),
            },
        ];
        Self { calib, verge, sources, reference, by_point, inliers, poses }
    }

    /// Aligned deltas with the calibration `state` and the axis-measuring poses `poses`
    /// (as [`Self::poses`]), the axes from [`Self::axes`].
    fn deltas(&self, state: &RigState, poses: [Option<&nalgebra::Isometry3<f64>>; 2]) -> Option<[f64; 3]> {
        let axes = self.axes(state, poses)?;
        solve_alignment(state, &axes, self.reference).ok().map(|s| aligned_deltas(&s))
    }

    /// The vergence axes with the calibration `state` and the axis-measuring poses `poses`
    /// (as [`Self::poses`]): each measured axis re-derived by [`verge_axes_from_motion`],
    /// an axis without a source held as given.
    fn axes(&self, state: &RigState, poses: [Option<&nalgebra::Isometry3<f64>>; 2]) -> Option<VergeAxes> {
        let axis = |src: &Option<AxisMeasurement>, pose: Option<&nalgebra::Isometry3<f64>>, is_left: bool| {
            let (Some(src), Some(pose)) = (src, pose) else {
                return Some(if is_left { self.verge.left } else { self.verge.right });
            };
            let mut m = src.measured;
            if is_left {
                m.ref_from_left = *pose;
            } else {
                m.ref_from_right = *pose;
            }
            let axes = verge_axes_from_motion(state, self.reference, &src.capture.encoders, &m).ok()?;
            Some(if is_left { axes.left } else { axes.right })
        };
        Some(VergeAxes {
            left: axis(&self.sources.left, poses[0], true)?,
            right: axis(&self.sources.right, poses[1], false)?,
        })
    }

    /// Aligned deltas under the calibration perturbation `delta` (the bundle's tangent):
    /// the points follow the cameras (one Gauss-Newton re-triangulation each, against all
    /// their adjustment observations) and each axis pose is re-resected (one Gauss-Newton
    /// step over its resection's inliers, held from the estimate).
    fn followed(&self, delta: &DVector<f64>) -> Option<[f64; 3]> {
        let (st, axes) = self.followed_axes(delta)?;
        solve_alignment(&st, &axes, self.reference).ok().map(|s| aligned_deltas(&s))
    }

    /// The perturbed calibration state and the vergence axes re-derived under it, as
    /// [`Self::followed`].
    fn followed_axes(&self, delta: &DVector<f64>) -> Option<(RigState, VergeAxes)> {
        let st = retriangulated(&self.calib.bundle.perturbed(delta).ok()?, &self.by_point);
        let pts: std::collections::HashMap<u64, nalgebra::Point3<f64>> =
            self.calib.point_tracks.iter().copied().zip(st.points.iter().copied()).collect();
        let left = match self.poses[0] {
            Some(p) => Some(reresected(&st.left, &pts, &self.inliers[0], &p)?),
            None => None,
        };
        let right = match self.poses[1] {
            Some(p) => Some(reresected(&st.right, &pts, &self.inliers[1], &p)?),
            None => None,
        };
        let axes = self.axes(&st, [left.as_ref(), right.as_ref()])?;
        Some((st, axes))
    }
}

/// The vergence axes at `+` and `-` one finite-difference step of one source of
/// uncertainty ([`AxisPerturbations`]).
#[derive(Debug, Clone, Copy)]
pub struct AxisStep {
    /// The axes re-derived at `+` the step.
    pub plus: VergeAxes,
    /// ... and at `-` the step.
    pub minus: VergeAxes,
}

/// The vergence axes' uncertainty as finite-difference steps, for propagating it, with
/// its correlation to the calibration, into anything predicted at other vergence
/// readings (the robot stages' stereo rig at a drive's readings,
/// [`crate::robot::align_pan`], [`crate::robot::zero_steering`]). The axes are a function
/// of the calibration (the pan/elevation chain, the stereo pose, and the scene points the
/// axis views are resected against) and of the resected poses' own pixel noise
/// (independent: the axis views are not in the bundle); the same linearisation as
/// [`alignment_sigmas_measured`] (`AxisFollow`). Built by [`axis_perturbations`].
#[derive(Debug, Clone, Default)]
pub struct AxisPerturbations {
    /// One entry per parameter of the bundle covariance (its order): the axes with the
    /// calibration moved along that parameter by `+-` [`Self::calibration_step`] (the
    /// step [`crate::robot`]'s calibration propagation uses), the points following and
    /// the axis poses re-resected; `None` where the parameter has no positive variance;
    /// the axes held as given (both steps `verge`) where they cannot be re-derived, so the
    /// parameter still counts through the rest of a computation.
    pub calibration: Vec<Option<AxisStep>>,
    /// The resected poses' own noise: independent modes of unit variance (the columns
    /// `l` of the Cholesky factor of each pose's covariance), each the axes with that
    /// pose moved by `+-` [`PROPAGATION_STEP_SIGMAS`] `l` (the calibration held): the
    /// central difference of a quantity over one mode, divided by
    /// `2 PROPAGATION_STEP_SIGMAS`, is its change per unit of the mode.
    pub pose: Vec<AxisStep>,
}

impl AxisPerturbations {
    /// The calibration parameter's step ([`PROPAGATION_STEP_SIGMAS`] of its standard
    /// deviation), as used for [`Self::calibration`].
    pub fn calibration_step(cov: &headalign_geometry::bundle::Covariance, i: usize) -> f64 {
        PROPAGATION_STEP_SIGMAS * cov.matrix[(i, i)].max(0.0).sqrt()
    }
}

/// Build [`AxisPerturbations`] for the axes `verge` measured from `sources` (an axis
/// without a source is held as given: both steps equal it). `noise_px` as
/// [`alignment_sigmas_measured`] (`None`: estimated from the resection residuals).
pub fn axis_perturbations(
    calib: &RigCalibration,
    verge: &VergeAxes,
    sources: &AxisSources,
    reference: &Encoders,
    noise_px: Option<f64>,
) -> AxisPerturbations {
    let follow = AxisFollow::new(calib, verge, sources, reference);
    let cov = &calib.bundle.covariance;
    let n = cov.matrix.nrows();
    let calibration = (0..n)
        .map(|i| {
            let h = AxisPerturbations::calibration_step(cov, i);
            if h.is_nan() || h <= 0.0 {
                return None;
            }
            let mut delta = DVector::zeros(n);
            delta[i] = h;
            let plus = follow.followed_axes(&delta).map(|f| f.1);
            delta[i] = -h;
            let minus = follow.followed_axes(&delta).map(|f| f.1);
            Some(match (plus, minus) {
                (Some(plus), Some(minus)) => AxisStep { plus, minus },
                _ => AxisStep { plus: *verge, minus: *verge },
            })
        })
        .collect();
    let state = &calib.bundle.state;
    let points: std::collections::HashMap<u64, nalgebra::Point3<f64>> = calib.points().into_iter().collect();
    let mut pose = Vec::new();
    for side in 0..2 {
        let Some((obs, k, pose0)) = follow.resected(side) else { continue };
        let seed = AXIS_BOOTSTRAP_SEED + side as u64;
        let Some(pcov) = resection_pose_covariance_bootstrap(k, &points, obs, &pose0, noise_px, seed) else {
            continue;
        };
        let Some(chol) = pcov.cholesky() else { continue };
        let l = chol.l();
        for c in 0..6 {
            let step: nalgebra::Vector6<f64> = l.column(c) * PROPAGATION_STEP_SIGMAS;
            let eval = |d: &nalgebra::Vector6<f64>| {
                let moved = pose0 * tangent_step(d);
                let mut poses = [follow.poses[0].as_ref(), follow.poses[1].as_ref()];
                poses[side] = Some(&moved);
                follow.axes(state, poses)
            };
            if let (Some(plus), Some(minus)) = (eval(&step), eval(&-step)) {
                pose.push(AxisStep { plus, minus });
            }
        }
    }
    AxisPerturbations { calibration, pose }
}

/// [`alignment_sigmas`] with the vergence axes' own measurement uncertainty: the aligned
/// readings are a function of the calibration (bundle covariance) and of the poses
/// resected after the vergence move (covariance [`resection_pose_covariance`], pixel noise
/// `noise_px` or the resection residuals' estimate), independent because the vergence
/// view is not in the bundle. Each axis is re-derived by [`verge_axes_from_motion`] from
/// the perturbed calibration (its pan/elevation chain and stereo pose) and the perturbed
/// resected pose, then [`solve_alignment`] is differentiated centrally. An axis without a
/// source is held as given. Under each calibration perturbation the scene points follow
/// the cameras (one Gauss-Newton re-triangulation each, their conditional mean: the
/// covariance has them eliminated) and the axis poses are re-resected (one Gauss-Newton
/// step), so the axes' dependence on the calibration is propagated with its correlations.
///
/// The re-resection must be the resection [`crate::alignment::measure_cameras`] ran: the
/// same points (seen three or more times) and the same inliers, chosen once at the
/// estimate. Points seen twice (one stereo pair) follow the calibration far more than the
/// rest; letting them into the linearised resection, or re-applying an outlier threshold
/// per perturbation, inflated the elevation sigma of runs whose axis was re-measured in a
/// check view after a large elevation move up to 2.7x, while their actual errors moved by
/// a few hundredths of a degree (the removed `examples/axis_diag.rs`). Measured there (150 seeds at
/// 2 px): the term raises the elevation sigma by 2 % where the axes come from the
/// procedure's vergence view, by 6 % where a check view re-measured them (a third of the
/// runs), and the vergence sigmas by under 0.1 %.
///
/// Pitfalls: the points' own conditional noise (given the cameras) is not propagated into
/// the resections; with `noise_px` `None` the pixel noise is estimated from residuals
/// truncated at the resection's 5 px outlier threshold (7 % low at 2 px), which only the
/// small pose part feels.
pub fn alignment_sigmas_measured(
    calib: &RigCalibration,
    verge: &VergeAxes,
    sources: &AxisSources,
    reference: &Encoders,
    noise_px: Option<f64>,
) -> Result<AlignmentSigmas, AlignError> {
    let follow = AxisFollow::new(calib, verge, sources, reference);
    let cov = &calib.bundle.covariance;
    // A parameter under which the axes cannot be re-derived (a re-resection that fails)
    // keeps at least its held-axes part rather than none.
    let jac = calibration_jacobian(
        cov,
        &[&|delta| follow.followed(delta), &|delta| held_axes_deltas(calib, verge, reference, delta)],
    );
    let mut out = &jac * &cov.matrix * jac.transpose();
    // The resected poses' own noise.
    let state = &calib.bundle.state;
    let points: std::collections::HashMap<u64, nalgebra::Point3<f64>> = calib.points().into_iter().collect();
    for side in 0..2 {
        let Some((obs, k, pose0)) = follow.resected(side) else { continue };
        let Some(pcov) = resection_pose_covariance(k, &points, obs, &pose0, noise_px) else { continue };
        let mut jp = nalgebra::Matrix3x6::<f64>::zeros();
        for c in 0..6 {
            let h = PROPAGATION_STEP_SIGMAS * pcov[(c, c)].max(0.0).sqrt();
            if h.is_nan() || h <= 0.0 {
                continue;
            }
            let mut d = nalgebra::Vector6::<f64>::zeros();
            d[c] = h;
            let eval = |d: &nalgebra::Vector6<f64>| {
                let moved = pose0 * tangent_step(d);
                let mut poses = [follow.poses[0].as_ref(), follow.poses[1].as_ref()];
                poses[side] = Some(&moved);
                follow.deltas(state, poses)
            };
            if let (Some(p), Some(m)) = (eval(&d), eval(&-d)) {
                for r in 0..3 {
                    jp[(r, c)] = (p[r] - m[r]) / (2.0 * h);
                }
            }
        }
        let add = jp * pcov * jp.transpose();
        for r in 0..3 {
            for c in 0..3 {
                out[(r, c)] += add[(r, c)];
            }
        }
    }
    Ok(sigmas_of(&out))
}

#[cfg(test)]
mod tests {
    use super::*;
    use headalign_sim::{Scenario, SimulatedHead, calibration_errors};

    fn run(scenario: Scenario) -> (SimulatedHead, VergeTiltOutcome) {
        let mut head = SimulatedHead::new(scenario.clone()).unwrap();
        let options = VergeTiltOptions {
            estimation: EstimationOptions { seed: scenario.seed, ..EstimationOptions::default() },
            ..VergeTiltOptions::default()
        };
        let mut run = VergeTiltRun::default();
        let outcome = run.run(&mut head, &options).unwrap();
        assert_eq!(run.views.len(), 6 + outcome.checks.len(), "every captured view is kept");
        (head, outcome)
    }

    /// Noise-free, no outliers: the correctable alignment errors vanish and the focal
    /// lengths are exact. 0.01 deg and 0.01 % are the bars; the solver reaches
    /// about 1e-6 here (its tolerances), so they leave a wide margin.
    #[test]
    fn noise_free_alignment_is_exact() {
        for seed in [1, 2] {
            let scenario = Scenario { seed, noise_px: 0.0, outlier_fraction: 0.0, ..Scenario::default() };
            let (head, outcome) = run(scenario);
            let e = head.alignment_errors(&head.encoders());
            for (name, v) in
                [("verge_l", e.verge_err_l_deg), ("verge_r", e.verge_err_r_deg), ("elev_l", e.elev_err_l_deg)]
            {
                assert!(v.abs() < 0.01, "seed {seed}: {name} = {v} deg");
            }
            // The right camera's elevation error is its mounting, which no joint removes:
            // it must equal the truth's residual and the calibration's prediction.
            let unavoidable = head.alignment_errors(&head.aligned_encoders()).elev_err_r_deg;
            assert!((e.elev_err_r_deg - unavoidable).abs() < 0.01, "seed {seed}");
            assert!(
                (outcome.solution.predicted_elev_err_r_deg.abs() - unavoidable.abs()).abs() < 0.01,
                "seed {seed}"
            );
            let st = &outcome.calibration.bundle.state;
            let cal = calibration_errors(&head.truth().left, &head.truth().right, &st.left, &st.right);
            assert!(cal.f_err_pct < 0.01 && cal.pp_err_pct < 0.01, "seed {seed}: {cal:?}");
        }
    }

    /// Encoder readings with Gaussian noise at the angle prior's sigma (0.01 deg, every
    /// read; the default simulator reads exactly): the procedure runs (it failed with "no
    /// view rotates the pan joint alone" while any encoder change counted as a motion) and,
    /// with noise-free pixels, aligns to within 4 of its stated sigmas, which include the
    /// reference read's noise (measured at most 2.0 over these seeds; before the unmoved
    /// joints' jitter was ignored in `verge_axes_from_motion` it tilted the vergence axes,
    /// and seed 3's elevation was 6.7 sigmas off) and to within 0.1 deg.
    #[test]
    fn noisy_encoder_readings_still_align() {
        for seed in [1, 2, 3, 4] {
            let scenario = Scenario {
                seed,
                noise_px: 0.0,
                outlier_fraction: 0.0,
                encoder_noise_deg: crate::estimate::ENCODER_SIGMA_DEG,
                ..Scenario::default()
            };
            let (head, outcome) = run(scenario);
            let e = head.alignment_errors(&head.encoders());
            let s = outcome.sigmas;
            for (v, sigma) in [
                (e.verge_err_l_deg, s.verge_left_deg),
                (e.verge_err_r_deg, s.verge_right_deg),
                (e.elev_err_l_deg, s.elevation_deg),
            ] {
                assert!(v.abs() < 0.1 && v.abs() <= 4.0 * sigma, "seed {seed}: {e:?} {s:?}");
            }
        }
    }

    /// Seed 39 from the experiments' third head position at 2 px (thresholds scaled as in
    /// `experiment`): without the depth-reversed restart the least squares ends in the
    /// minimum with the baseline's x component reversed, right cx about 6 sigma off
    /// (measured -5.8); with it, in the lower minimum (measured -1.2 sigma). The bounds 4
    /// and 3 sigma sit between the two with a margin for the solver's tolerance.
    #[test]
    fn reversed_rig_restart_leaves_the_wrong_minimum() {
        let scenario = Scenario { seed: 39, noise_px: 2.0, ..Scenario::default() };
        let z = |restart: bool| {
            let mut head = SimulatedHead::new(scenario.clone()).unwrap();
            head.move_to(&Encoders { pan: -4.0, elevation: -4.0, verge_left: -2.0, verge_right: 2.0 })
                .unwrap();
            let d = EstimationOptions::default();
            let mut estimation = EstimationOptions {
                seed: scenario.seed,
                prefilter_px: 2.0 * d.prefilter_px,
                reversed_rig_restart: restart,
                ..d
            };
            estimation.fundamental.threshold *= 2.0;
            estimation.homography.threshold *= 2.0;
            let options = VergeTiltOptions {
                rotation_deg: scenario.rotation_deg,
                verge_rotation_deg: 3.0,
                estimation,
                ..VergeTiltOptions::default()
            };
            let outcome = VergeTiltRun::default().run(&mut head, &options).unwrap();
            let bundle = &outcome.calibration.bundle;
            (bundle.state.right.cx - head.truth().right.cx) / bundle.covariance.sigma("right.cx").unwrap()
        };
        let (without, with) = (z(false), z(true));
        assert!(without.abs() > 4.0, "without the restart: {without}");
        assert!(with.abs() < 3.0, "with the restart: {with}");
    }

    /// One trial of `headalign experiment` at the paper's protocol (default scenario at
    /// `noise_px`, head position 0, the experiments' estimation options).
    fn experiment_trial(seed: u64, noise_px: f64) -> (SimulatedHead, VergeTiltOutcome) {
        let scenario = Scenario { seed, noise_px, ..Scenario::default() };
        let mut head = SimulatedHead::new(scenario.clone()).unwrap();
        let options = VergeTiltOptions {
            rotation_deg: scenario.rotation_deg,
            verge_rotation_deg: 3.0,
            estimation: EstimationOptions::scaled_for_noise(noise_px, seed),
            ..VergeTiltOptions::default()
        };
        let outcome = VergeTiltRun::default().run(&mut head, &options).unwrap();
        (head, outcome)
    }

    /// Seed 1211 of `experiment fig5-verge-tilt --seed 1001` (first head position, 3 px,
    /// the experiment's options): the restarts from the x-reversed and the fully reversed
    /// baseline end above the estimate, which has the baseline's forward component at +0.64
    /// (unit baseline); the minimum the least squares reaches from the truth has it at -0.53
    /// at 3.2 chi-square units lower cost, and the y-z reversed restart reaches it
    /// (`docs/ratio-tail.md`). The sign of that component tells the two minima apart.
    #[test]
    fn yz_reversed_restart_reaches_the_lower_minimum() {
        let (_, outcome) = experiment_trial(1211, 3.0);
        let t = outcome.calibration.bundle.state.right_from_left.translation.vector.normalize();
        assert!(t.z < -0.3, "baseline direction {t:?}");
    }

    /// Regression (calibration experiment, 3 px, seed 368): the estimate's baseline was
    /// (0.01, -0.36, -0.93), along the optical axis and 84 deg from the truth's, with left fx
    /// 146 px off, 127 chi-square units above the minimum the least squares reaches from
    /// the truth; the side-by-side restart reaches that minimum (left fx 45 px off, sigma
    /// 22; baseline (-0.56, -0.25, -0.79): at 3 px the baseline's forward component is
    /// weakly determined, the truth's minimum has -0.59). Limits: the baseline's x component
    /// above 0.3 (it was 0.01) and left fx within 90 px (4 of its sigmas; it was 6.6 off).
    #[test]
    fn sideways_restart_leaves_a_baseline_along_the_optical_axis() {
        let (head, outcome) = experiment_trial(368, 3.0);
        let st = &outcome.calibration.bundle.state;
        let t = st.right_from_left.translation.vector.normalize();
        assert!(t.x.abs() > 0.3, "baseline direction {t:?}");
        assert!((st.left.fx - head.truth().left.fx).abs() < 90.0, "left fx {}", st.left.fx);
    }

    /// Default scenario (1 px, 10 % outliers): one seed within generous single-run limits
    /// (the RMS bars over 20 seeds are 0.5 deg and 1.5 %; one run gets three times that),
    /// and the reported sigmas are not absurd.
    #[test]
    fn default_scenario_aligns() {
        let (head, outcome) = run(Scenario { seed: 11, ..Scenario::default() });
        let e = head.alignment_errors(&head.encoders());
        for v in [e.verge_err_l_deg, e.verge_err_r_deg, e.elev_err_l_deg] {
            assert!(v.abs() < 1.5, "{e:?}");
        }
        let st = &outcome.calibration.bundle.state;
        let cal = calibration_errors(&head.truth().left, &head.truth().right, &st.left, &st.right);
        assert!(cal.f_err_pct < 4.5, "{cal:?}");
        let s = outcome.sigmas;
        for v in [s.elevation_deg, s.verge_left_deg, s.verge_right_deg] {
            assert!(v > 0.01 && v < 2.0, "sigma {v}");
        }
    }

    /// The vergence axes' own measurement adds uncertainty: with no axis source the
    /// measured-axis sigmas equal [`alignment_sigmas`] (same finite differences, 1e-12 is
    /// rounding); with the procedure's sources the vergence sigmas change a little, and the pose
    /// variance scales with the pixel noise squared (resection covariance is sigma^2 (J^T J)^-1).
    #[test]
    fn measured_axes_add_their_own_uncertainty() {
        let (_, outcome) = run(Scenario { seed: 11, ..Scenario::default() });
        let calib = &outcome.calibration;
        let reference = calib.reference_encoders;
        let fixed = alignment_sigmas(calib, &outcome.verge_axes, &reference).unwrap();
        let none =
            alignment_sigmas_measured(calib, &outcome.verge_axes, &AxisSources::default(), &reference, None)
                .unwrap();
        assert!((fixed.verge_left_deg - none.verge_left_deg).abs() < 1e-12);
        assert!((fixed.elevation_deg - none.elevation_deg).abs() < 1e-12);
        let src = &outcome.axis_sources;
        assert!(src.left.is_some() && src.right.is_some());
        let measured = outcome.sigmas;
        // The axes' own measurement is a small part of the vergence sigmas (resection
        // against ~200 points; the points follow the calibration, which partly cancels):
        // they move, but by less than 5 % (measured: 0.05 %).
        for (m, f) in [
            (measured.verge_left_deg, fixed.verge_left_deg),
            (measured.verge_right_deg, fixed.verge_right_deg),
        ] {
            assert!(m != f && (m / f - 1.0).abs() < 0.05, "{measured:?} vs {fixed:?}");
        }
        // Variance = calibration part + pose part * sigma^2: (v3 - v2) / (v2 - v1) = 5/3
        // (the finite differences are at 0.5 sigma of a nearly linear map: 2 % is generous).
        let var = |px: f64| {
            alignment_sigmas_measured(calib, &outcome.verge_axes, src, &reference, Some(px))
                .unwrap()
                .verge_left_deg
                .powi(2)
        };
        let ratio = (var(3.0) - var(2.0)) / (var(2.0) - var(1.0));
        assert!((ratio - 5.0 / 3.0).abs() < 0.035, "ratio {ratio}");
    }

    /// The procedure as `experiment fig5-verge-tilt` runs it (3 deg vergence move, RANSAC
    /// thresholds scaled by the noise) from initial readings `initial`.
    fn run_as_experiment(scenario: Scenario, initial: Encoders) -> (SimulatedHead, VergeTiltOutcome) {
        let mut head = SimulatedHead::new(scenario.clone()).unwrap();
        head.move_to(&initial).unwrap();
        let estimation = EstimationOptions::scaled_for_noise(scenario.noise_px, scenario.seed);
        let options = VergeTiltOptions { verge_rotation_deg: 3.0, estimation, ..VergeTiltOptions::default() };
        let outcome = VergeTiltRun::default().run(&mut head, &options).unwrap();
        (head, outcome)
    }

    /// The verge-tilt procedure as the experiments run it, at 2 px from (pan 4, elevation 4,
    /// vergences 2 / -2) deg. Of seeds 1-30, seeds 4, 11, 13, 14, 15, 23 and 30 re-measure
    /// the left axis in a check view 6-14 deg of elevation from the reference, where the
    /// axis is most sensitive to the calibration (the removed `examples/axis_diag.rs`).
    fn check_view_case_at(seed: u64) -> (SimulatedHead, VergeTiltOutcome) {
        let initial = Encoders { pan: 4.0, elevation: 4.0, verge_left: 2.0, verge_right: -2.0 };
        run_as_experiment(Scenario { seed, noise_px: 2.0, ..Scenario::default() }, initial)
    }

    /// The linearised calibration part ([`AxisFollow::followed`]: one Gauss-Newton step for
    /// the points and for each axis pose, least squares over the inliers held) against the
    /// procedure's own computation under the same perturbations: points re-triangulated
    /// to convergence (4 steps), the axis poses resected by [`measure_cameras`] itself
    /// (robust, from its own inliers), the axes by [`verge_axes_from_motion`]. Both
    /// Jacobians are propagated through the bundle covariance. Seeds 1-12, the first
    /// twelve, unselected (seeds 4 and 11 re-measure the left axis in a check view). The
    /// agreement is a property of each seed: the real resection's Huber weights (2 px, at
    /// 2 px noise) and its own inlier choice make it a different estimator from least
    /// squares over fixed inliers. Over seeds 1-30 (`scan_check_view_seeds`) the elevation
    /// ratio is 0.79-1.08, median 1.001 (seed 9 lowest, seed 13 0.88; without
    /// `EstimationOptions::image_border` 0.86-1.02, median 0.997), the vergences'
    /// 0.99-1.01 (without it 0.96-1.01): each seed is held to 25 % on the elevation and 5 %
    /// on the vergences, the elevation's median to 3 %. Letting the points seen only twice
    /// into the linearised resection (as a first version did) gave 2.95x on the elevation
    /// at seed 13.
    #[test]
    fn axis_sensitivity_matches_the_real_resection() {
        let mut elevation = Vec::new();
        for seed in 1..=12 {
            let (_, outcome) = check_view_case_at(seed);
            let [a, b] = linearised_and_resected_sigmas(&outcome);
            for (name, x, y, tol) in [
                ("elevation", a.elevation_deg, b.elevation_deg, 0.25),
                ("verge left", a.verge_left_deg, b.verge_left_deg, 0.05),
                ("verge right", a.verge_right_deg, b.verge_right_deg, 0.05),
            ] {
                assert!((x / y - 1.0).abs() < tol, "seed {seed} {name}: linearised {x} vs resection {y}");
            }
            elevation.push(a.elevation_deg / b.elevation_deg);
        }
        elevation.sort_by(f64::total_cmp);
        let median = 0.5 * (elevation[5] + elevation[6]);
        assert!((median - 1.0).abs() < 0.03, "median elevation ratio {median}: {elevation:?}");
    }

    /// The calibration part of the alignment sigmas, linearised ([`AxisFollow::followed`])
    /// and through the procedure's own resection (see the test above).
    fn linearised_and_resected_sigmas(outcome: &VergeTiltOutcome) -> [AlignmentSigmas; 2] {
        let calib = &outcome.calibration;
        let reference = calib.reference_encoders;
        let sources = &outcome.axis_sources;
        let follow = AxisFollow::new(calib, &outcome.verge_axes, sources, &reference);
        let cov = &calib.bundle.covariance;
        let linear = calibration_jacobian(cov, &[&|d| follow.followed(d)]);
        let full = calibration_jacobian(
            cov,
            &[&|d| {
                let mut st = calib.bundle.perturbed(d).ok()?;
                for _ in 0..4 {
                    st = retriangulated(&st, &follow.by_point);
                }
                let moved = RigCalibration {
                    bundle: headalign_geometry::bundle::BundleResult {
                        state: st.clone(),
                        ..calib.bundle.clone()
                    },
                    ..calib.clone()
                };
                let axis = |src: &Option<AxisMeasurement>| -> Option<VergeAxes> {
                    let Some(src) = src else { return Some(outcome.verge_axes) };
                    let m = measure_cameras(
                        &moved,
                        &src.capture,
                        &src.measured.ref_from_left,
                        &src.measured.ref_from_right,
                    )
                    .ok()?;
                    verge_axes_from_motion(&st, &reference, &src.capture.encoders, &m).ok()
                };
                let axes = VergeAxes { left: axis(&sources.left)?.left, right: axis(&sources.right)?.right };
                solve_alignment(&st, &axes, &reference).ok().map(|s| aligned_deltas(&s))
            }],
        );
        [
            sigmas_of(&(&linear * &cov.matrix * linear.transpose())),
            sigmas_of(&(&full * &cov.matrix * full.transpose())),
        ]
    }

    /// Monte-Carlo of the pose part: the axis sources' captures re-drawn 300 times and run
    /// through [`measure_cameras`], [`verge_axes_from_motion`] and [`solve_alignment`] with
    /// the calibration held; the spread of the aligned deltas against the pose part of
    /// [`alignment_sigmas_measured`] (its variance at 1 px minus at ~0 px). Each draw is the
    /// model the prediction linearises: the tracks its resection holds, at the projections
    /// of the calibration's points through the measured poses, plus 1 px Gaussian noise.
    /// (Exact pixels of the true scene instead add the calibration's fixed misfit, which
    /// through the resection's Huber weights moved the spread by -8 % to +68 % of the
    /// prediction over seeds 1-30, seed 14 most; the model's draws 0.91-1.11.) 300 draws know a standard
    /// deviation to 4 %; tolerance 15 % (3.5 standard errors) of the pose part plus 0.3 % of
    /// the total sigma: the vergences' pose parts are a few thousandths of a degree (0.5-2 %
    /// of the total), where the second-order term is as large as the linear one (seed 4's
    /// left: 0.0023 deg against a linear 0.0017), and at that size a pose part changes the
    /// total by less than 0.02 %.
    /// Seeds 4 and 13 (check views 14 deg from the reference: the largest elevation pose
    /// parts, 0.12 deg) and 14.
    #[test]
    fn pose_part_matches_monte_carlo() {
        for seed in [4, 13, 14] {
            let (head, outcome) = check_view_case_at(seed);
            let [predicted, sd, total] = pose_part_and_monte_carlo(&head, &outcome, 300, true);
            for (i, name) in ["elevation", "verge left", "verge right"].iter().enumerate() {
                assert!(
                    (sd[i] - predicted[i]).abs() < 0.15 * predicted[i] + 0.003 * total[i],
                    "seed {seed} {name}: Monte-Carlo {} vs {} (total {})",
                    sd[i],
                    predicted[i],
                    total[i]
                );
            }
        }
    }

    /// The pose part of [`alignment_sigmas_measured`] at 1 px (elevation, verge left, verge
    /// right; degrees), the standard deviations of `draws` Monte-Carlo re-draws (see the
    /// test above; `consistent` false: exact pixels of the true scene), and the total
    /// sigmas at 1 px.
    fn pose_part_and_monte_carlo(
        head: &SimulatedHead,
        outcome: &VergeTiltOutcome,
        draws: usize,
        consistent: bool,
    ) -> [[f64; 3]; 3] {
        use rand::{RngExt, SeedableRng};
        let calib = &outcome.calibration;
        let reference = calib.reference_encoders;
        let sources = &outcome.axis_sources;
        let var = |px: f64| {
            let s =
                alignment_sigmas_measured(calib, &outcome.verge_axes, sources, &reference, Some(px)).unwrap();
            [s.elevation_deg.powi(2), s.verge_left_deg.powi(2), s.verge_right_deg.powi(2)]
        };
        let (v1, v0) = (var(1.0), var(1e-9));
        let predicted = [0, 1, 2].map(|i| (v1[i] - v0[i]).max(0.0).sqrt());
        let state = &calib.bundle.state;
        let points: std::collections::HashMap<u64, nalgebra::Point3<f64>> =
            calib.points().into_iter().collect();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut noisy = |c: &headalign_platform::StereoCapture| {
            let mut c = c.clone();
            for o in c.left.iter_mut().chain(c.right.iter_mut()) {
                o.pixel.x += rng.sample::<f64, _>(rand_distr::StandardNormal);
                o.pixel.y += rng.sample::<f64, _>(rand_distr::StandardNormal);
            }
            c
        };
        // The tracks the prediction's resections hold (left, right camera), from the real
        // capture of each axis source.
        let held = |src: &Option<AxisMeasurement>| -> [std::collections::HashSet<u64>; 2] {
            let Some(src) = src else { return Default::default() };
            let of =
                |k, obs, pose| resection_inliers(k, &points, obs, pose).into_iter().map(|(t, _)| t).collect();
            [
                of(&state.left, &src.capture.left, &src.measured.ref_from_left),
                of(&state.right, &src.capture.right, &src.measured.ref_from_right),
            ]
        };
        let held = [held(&sources.left), held(&sources.right)];
        let mut samples = Vec::with_capacity(draws);
        for _ in 0..draws {
            let mut axis = |src: &Option<AxisMeasurement>,
                            [left, right]: &[std::collections::HashSet<u64>; 2]| {
                let Some(src) = src else { return outcome.verge_axes };
                let mut capture = head.exact_capture(&src.capture.encoders);
                capture.left.retain(|o| left.contains(&o.track));
                capture.right.retain(|o| right.contains(&o.track));
                if consistent {
                    for (obs, k, pose) in [
                        (&mut capture.left, &state.left, &src.measured.ref_from_left),
                        (&mut capture.right, &state.right, &src.measured.ref_from_right),
                    ] {
                        for o in obs.iter_mut() {
                            if let Some(p) = points.get(&o.track).and_then(|x| project_into(k, pose, x)) {
                                o.pixel = nalgebra::Point2::from(p);
                            }
                        }
                    }
                }
                let capture = noisy(&capture);
                let m = measure_cameras(
                    calib,
                    &capture,
                    &src.measured.ref_from_left,
                    &src.measured.ref_from_right,
                )
                .unwrap();
                verge_axes_from_motion(state, &reference, &capture.encoders, &m).unwrap()
            };
            let axes = VergeAxes {
                left: axis(&sources.left, &held[0]).left,
                right: axis(&sources.right, &held[1]).right,
            };
            samples.push(aligned_deltas(&solve_alignment(state, &axes, &reference).unwrap()));
        }
        let sd = [0, 1, 2].map(|i| {
            let mean = samples.iter().map(|s| s[i]).sum::<f64>() / draws as f64;
            (samples.iter().map(|s| (s[i] - mean).powi(2)).sum::<f64>() / (draws - 1) as f64).sqrt()
        });
        [predicted, sd, v1.map(f64::sqrt)]
    }

    /// The two checks above over seeds 1-30, printed (a diagnostic, not a test: `cargo test
    /// --release -p headalign --lib scan_check_view_seeds -- --ignored --nocapture`); the
    /// Monte-Carlo both ways (`consistent` true and false).
    #[test]
    #[ignore]
    fn scan_check_view_seeds() {
        for seed in 1..=30 {
            let (head, outcome) = check_view_case_at(seed);
            let moved = outcome.axis_sources.left.as_ref().map_or(0.0, |src| {
                (src.capture.encoders.elevation - outcome.calibration.reference_encoders.elevation).abs()
            });
            let [a, b] = linearised_and_resected_sigmas(&outcome);
            let [p, model, _] = pose_part_and_monte_carlo(&head, &outcome, 200, true);
            let [_, scene, total] = pose_part_and_monte_carlo(&head, &outcome, 200, false);
            eprintln!(
                "seed {seed} check view {moved:.1} deg | calibration part linearised/resected: elevation \
                 {:.3} verge {:.3} {:.3} | pose part (deg) predicted / Monte-Carlo model / scene: \
                 elevation {:.4} {:.4} {:.4}, verge left {:.5} {:.5} {:.5}, right {:.5} {:.5} {:.5} \
                 | total {:.3} {:.3} {:.3}",
                a.elevation_deg / b.elevation_deg,
                a.verge_left_deg / b.verge_left_deg,
                a.verge_right_deg / b.verge_right_deg,
                p[0],
                model[0],
                scene[0],
                p[1],
                model[1],
                scene[1],
                p[2],
                model[2],
                scene[2],
                total[0],
                total[1],
                total[2]
            );
        }
    }

    #[test]
    fn capture_plan_has_both_directions_and_a_verge_view() {
        let e0 = Encoders::default();
        let plan = capture_plan(&e0, &VergeTiltOptions::default());
        let names: Vec<&str> = plan.iter().map(|p| p.0.as_str()).collect();
        assert_eq!(names, ["initial", "elevation+", "elevation-", "pan+", "pan-", "verge"]);
        assert_eq!(plan[2].1.elevation, -3.0);
        let short =
            capture_plan(&e0, &VergeTiltOptions { both_directions: false, ..VergeTiltOptions::default() });
        assert_eq!(short.len(), 4);
    }

    /// Auto rotation on the default scene grows past the fixed 3 deg (the simulated room
    /// fills the view), and a demanding overlap keeps the first candidate.
    #[test]
    fn auto_rotation_grows_when_the_scene_allows() {
        let scenario = Scenario { seed: 3, noise_px: 0.5, outlier_fraction: 0.0, ..Scenario::default() };
        let mut head = SimulatedHead::new(scenario.clone()).unwrap();
        let e0 = head.read_encoders().unwrap();
        let loose = AutoRotation::default();
        let c = choose_rotation(&mut head, &e0, true, &loose).unwrap();
        assert!(c.rotation_deg > 3.0 && c.diagonal_rotation_deg > 3.0, "chose {c:?}");
        assert_eq!(head.read_encoders().unwrap(), e0, "returns to the initial readings");
        let strict = AutoRotation { min_overlap_fraction: 1.0, ..AutoRotation::default() };
        let c = choose_rotation(&mut head, &e0, true, &strict).unwrap();
        assert_eq!(
            c,
            RotationChoice { rotation_deg: 3.0, diagonal_rotation_deg: 0.0, verge_rotation_deg: None }
        );
        let bad = AutoRotation { candidates_deg: vec![6.0, 3.0], ..AutoRotation::default() };
        assert!(bad.validate().is_err());
    }

    /// A field of view as the overlap test: a view keeps the overlap while each joint
    /// turns at most `joint_max` and pan and elevation together at most `sum_max` (degrees).
    fn field(joint_max: f64, sum_max: f64) -> impl Fn(f64, f64, f64) -> bool {
        move |p: f64, e: f64, v: f64| {
            p.abs() <= joint_max
                && e.abs() <= joint_max
                && v.abs() <= joint_max
                && p.abs() + e.abs() <= sum_max
        }
    }

    /// Run the pure choice on `keeps`, recording the probes.
    fn choose(
        auto: &AutoRotation,
        both: bool,
        keeps: impl Fn(f64, f64, f64) -> bool,
    ) -> (RotationChoice, Vec<(f64, f64, f64)>) {
        let mut probes = Vec::new();
        let c = choose_rotations(auto, both, |p, e, v| {
            probes.push((p, e, v));
            Ok::<bool, ()>(keeps(p, e, v))
        })
        .unwrap();
        (c, probes)
    }

    /// End to end with the auto mode (1 px, 10 % outliers): 10 deg each way and 10 deg
    /// diagonals on the default room, every view estimated. Limits: the bars of the
    /// issue's auto condition (0.15 deg, 0.5 %) with a factor 3 for one run.
    #[test]
    fn auto_rotation_with_diagonals_end_to_end() {
        let scenario = Scenario { seed: 4, ..Scenario::default() };
        let mut head = SimulatedHead::new(scenario.clone()).unwrap();
        let options = VergeTiltOptions {
            estimation: EstimationOptions { seed: scenario.seed, ..EstimationOptions::default() },
            auto_rotation: Some(AutoRotation::default()),
            ..VergeTiltOptions::default()
        };
        let mut run = VergeTiltRun::default();
        let outcome = run.run(&mut head, &options).unwrap();
        assert_eq!(
            (outcome.rotation_deg, outcome.diagonal_rotation_deg, outcome.verge_rotation_deg),
            (10.0, 10.0, 10.0)
        );
        assert_eq!(run.views.len(), 10 + outcome.checks.len(), "probes are not kept");
        assert_eq!(outcome.calibration.report.homographies.len(), 8, "every rotated view is estimated");
        let e = head.alignment_errors(&head.encoders());
        for v in [e.verge_err_l_deg, e.verge_err_r_deg, e.elev_err_l_deg] {
            assert!(v.abs() < 0.45, "{e:?}");
        }
        let st = &outcome.calibration.bundle.state;
        let cal = calibration_errors(&head.truth().left, &head.truth().right, &st.left, &st.right);
        assert!(cal.f_err_pct < 1.5, "{cal:?}");
    }

    /// A 50-point scene (1.5 px, the 50-point bar): the auto mode leaves the 3 deg
    /// protocol (with the former `min_tracks` of 60 it never did, since such a scene never
    /// shares 60 tracks) and every view is estimated. Limit 0.75 deg: three times the
    /// RMS elevation error of 150 such runs (0.25 deg, `headalign experiment points --only
    /// 50 --trials 300`), against 0.74 deg RMS with the fixed 3 deg protocol.
    #[test]
    fn auto_rotation_grows_in_a_fifty_point_scene() {
        let scenario = Scenario { seed: 2, points: 50, noise_px: 1.5, ..Scenario::default() };
        let mut head = SimulatedHead::new(scenario.clone()).unwrap();
        let options = VergeTiltOptions {
            estimation: EstimationOptions { seed: scenario.seed, ..EstimationOptions::default() },
            auto_rotation: Some(AutoRotation::default()),
            ..VergeTiltOptions::default()
        };
        let outcome = VergeTiltRun::default().run(&mut head, &options).unwrap();
        assert!(
            outcome.rotation_deg >= 6.0 && outcome.diagonal_rotation_deg >= 3.0,
            "{}",
            outcome.rotation_deg
        );
        let e = head.alignment_errors(&head.encoders());
        assert!(e.elev_err_l_deg.abs() < 0.75 && e.verge_err_l_deg.abs() < 0.75, "{e:?}");
    }

    /// Regression (calibration experiment, 3 px, seed 53): the re-selected adjustment
    /// explained a wrong track by a point at depth 1e-11, whose rounding noise made the
    /// reduced camera system indefinite, and the whole estimate failed ("a parameter is
    /// unobservable"); such a point now leaves the covariance and the depth filter after
    /// that adjustment removes it. Limit 2.2 deg: three times the RMS elevation and
    /// vergence errors of 250 such runs (0.72 deg); this run ends at 0.14 and 0.47 deg.
    #[test]
    fn a_point_collapsed_onto_a_camera_does_not_fail_the_estimate() {
        let (head, _) = experiment_trial(53, 3.0);
        let e = head.alignment_errors(&head.encoders());
        assert!(e.elev_err_l_deg.abs() < 2.2 && e.verge_err_l_deg.abs() < 2.2, "{e:?}");
    }

    /// Regression (50 points, 1.5 px, 3 deg, seed 97, the experiment's thresholds scaled
    /// by 1.5): a round of the maximum-likelihood re-classification left a parameter
    /// unobservable and the whole estimate failed ("reduced camera system is singular");
    /// the rounds now end at the last classification that fitted. Limit 2.2 deg: three
    /// times the RMS elevation error of 150 such runs (0.74 deg); this run ends at 0.73.
    #[test]
    fn a_singular_reclassification_keeps_the_last_fit() {
        let scenario = Scenario { seed: 97, points: 50, noise_px: 1.5, ..Scenario::default() };
        let mut head = SimulatedHead::new(scenario.clone()).unwrap();
        let estimation = EstimationOptions::scaled_for_noise(1.5, 97);
        let options = VergeTiltOptions { estimation, verge_rotation_deg: 3.0, ..VergeTiltOptions::default() };
        VergeTiltRun::default().run(&mut head, &options).unwrap();
        let e = head.alignment_errors(&head.encoders());
        assert!(e.elev_err_l_deg.abs() < 2.2, "{e:?}");
    }

    /// Regression (3 px, seed 29, the former auto plan without diagonals): the first check
    /// measured 0.41 deg, above the tolerance, and the correction re-measured the left
    /// vergence axis from a 0.9 deg vergence turn after 8 deg of elevation: the axis came
    /// out 80 deg off and the head ended 8 deg from aligned. Now an axis is re-measured only
    /// from a vergence turn at least as large as the procedure's own (3 deg). Limit 1 deg:
    /// this run ends at 0.04 deg elevation and 0.44 deg vergence (3 px).
    #[test]
    fn small_vergence_turns_do_not_remeasure_the_axis() {
        let scenario = Scenario { seed: 29, noise_px: 3.0, ..Scenario::default() };
        let mut head = SimulatedHead::new(scenario.clone()).unwrap();
        let estimation = EstimationOptions::scaled_for_noise(3.0, 29);
        let auto = AutoRotation {
            diagonals: false,
            choose_verge: false,
            min_overlap_fraction: 0.6,
            ..AutoRotation::default()
        };
        let options =
            VergeTiltOptions { estimation, auto_rotation: Some(auto), ..VergeTiltOptions::default() };
        let outcome = VergeTiltRun::default().run(&mut head, &options).unwrap();
        assert_eq!(outcome.rotation_deg, 10.0);
        let e = head.alignment_errors(&head.encoders());
        assert!(e.elev_err_l_deg.abs() < 1.0 && e.verge_err_l_deg.abs() < 1.0, "{e:?}");
    }

    #[test]
    fn choice_takes_the_largest_rotations_the_field_allows() {
        let auto = AutoRotation::default();
        let rc =
            |r, d, v| RotationChoice { rotation_deg: r, diagonal_rotation_deg: d, verge_rotation_deg: v };
        // Everything in view: 10 deg each way, 10 deg diagonals and vergence; 9 probes
        // (largest first), none twice.
        let (c, probes) = choose(&auto, true, field(90.0, 180.0));
        assert_eq!(c, rc(10.0, 10.0, Some(10.0)));
        assert_eq!(probes.len(), 9);
        let mut unique = probes.clone();
        unique.sort_by(|a, b| a.partial_cmp(b).unwrap());
        unique.dedup();
        assert_eq!(unique.len(), probes.len(), "no view probed twice");
        // Diagonals lose the corners first: 10 deg single-joint views, 6 deg diagonals.
        assert_eq!(choose(&auto, true, field(12.0, 14.0)).0, rc(10.0, 6.0, Some(10.0)));
        // A narrow field: 3 deg (the fixed protocol) and 3 deg diagonals.
        assert_eq!(choose(&auto, true, field(4.0, 6.0)).0, rc(3.0, 3.0, Some(3.0)));
        // Nothing in view: the first candidate, no diagonals, the vergence move unchanged.
        assert_eq!(choose(&auto, true, field(1.0, 1.0)).0, rc(3.0, 0.0, None));
        // One direction only fails: the elevation-down view at 10 deg.
        let (c, _) = choose(&auto, true, |p: f64, e: f64, v: f64| e > -8.0 && field(90.0, 180.0)(p, e, v));
        assert_eq!(c, rc(6.0, 6.0, Some(6.0)));
        // The vergence move alone is limited.
        let (c, _) = choose(&auto, true, |p: f64, e: f64, v: f64| v < 7.0 && field(90.0, 180.0)(p, e, v));
        assert_eq!(c, rc(10.0, 10.0, Some(6.0)));
        // Diagonals and vergence off: neither probed.
        let off = AutoRotation { diagonals: false, choose_verge: false, ..AutoRotation::default() };
        let (c, probes) = choose(&off, true, field(90.0, 180.0));
        assert_eq!(c, rc(10.0, 0.0, None));
        assert!(probes.iter().all(|(p, e, v)| (*p == 0.0 || *e == 0.0) && *v == 0.0));
        // One direction: only positive offsets are probed.
        let (c, probes) = choose(&auto, false, field(90.0, 180.0));
        assert_eq!(c, rc(10.0, 10.0, Some(10.0)));
        assert!(probes.iter().all(|(p, e, v)| *p >= 0.0 && *e >= 0.0 && *v >= 0.0));
        // A failing probe (the head) stops the choice with its error.
        let mut n = 0;
        let err = choose_rotations(&auto, true, |_, _, _| {
            n += 1;
            if n == 3 { Err("head") } else { Ok(true) }
        });
        assert_eq!(err, Err("head"));
    }

    proptest::proptest! {
        /// For any field of view: the chosen single-joint views all keep the overlap (or
        /// it is the first candidate) and the next candidate's do not; the chosen
        /// diagonals keep it and every larger candidate up to the rotation does not.
        #[test]
        fn choice_is_the_largest_allowed(joint_max in 0.0f64..20.0, sum_max in 0.0f64..30.0, both: bool) {
            let auto = AutoRotation::default();
            let keeps = field(joint_max, sum_max);
            let (c, _) = choose(&auto, both, &keeps);
            let cross_ok = |r: f64| single_joint_offsets(r, both).iter().all(|&(_, p, e)| keeps(p, e, 0.0));
            let diag_ok = |d: f64| diagonal_offsets(d, both).iter().all(|&(_, p, e)| keeps(p, e, 0.0));
            let cands = &auto.candidates_deg;
            let i = cands.iter().position(|&x| x == c.rotation_deg).unwrap();
            proptest::prop_assert!(i == 0 || cross_ok(c.rotation_deg));
            for &larger in &cands[i + 1..] {
                proptest::prop_assert!(!cross_ok(larger));
            }
            proptest::prop_assert!(c.diagonal_rotation_deg == 0.0 || diag_ok(c.diagonal_rotation_deg));
            proptest::prop_assert!(c.diagonal_rotation_deg <= c.rotation_deg);
            for &d in cands.iter().filter(|&&d| d > c.diagonal_rotation_deg && d <= c.rotation_deg) {
                proptest::prop_assert!(!diag_ok(d));
            }
            let v = c.verge_rotation_deg.unwrap_or(0.0);
            proptest::prop_assert!(v == 0.0 || (keeps(0.0, 0.0, v) && v <= c.rotation_deg));
            for &w in cands.iter().filter(|&&w| w > v && w <= c.rotation_deg) {
                proptest::prop_assert!(!keeps(0.0, 0.0, w));
            }
        }
    }

    #[test]
    fn capture_plan_adds_the_diagonals_before_the_verge_view() {
        let e0 = Encoders::default();
        let o = VergeTiltOptions {
            rotation_deg: 10.0,
            diagonal_rotation_deg: 6.0,
            ..VergeTiltOptions::default()
        };
        let plan = capture_plan(&e0, &o);
        let names: Vec<&str> = plan.iter().map(|p| p.0.as_str()).collect();
        assert_eq!(
            names,
            [
                "initial",
                "elevation+",
                "elevation-",
                "pan+",
                "pan-",
                "pan+elevation+",
                "pan+elevation-",
                "pan-elevation+",
                "pan-elevation-",
                "verge"
            ]
        );
        assert_eq!((plan[6].1.pan, plan[6].1.elevation), (6.0, -6.0));
        assert_eq!(plan[3].1.elevation, 0.0);
        let bad = VergeTiltOptions { diagonal_rotation_deg: 0.05, ..VergeTiltOptions::default() };
        assert!(bad.validate().is_err());
    }

    #[test]
    fn invalid_options_are_errors() {
        let bad = VergeTiltOptions { rotation_deg: 0.0, ..VergeTiltOptions::default() };
        assert!(bad.validate().is_err());
        let bad = VergeTiltOptions { check_tolerance_deg: f64::NAN, ..VergeTiltOptions::default() };
        assert!(bad.validate().is_err());
    }
}
