//! The verge/tilt procedure over any [`StereoHead`] (`docs/how-it-works.md#the-procedure`, paper
//! section 3.2): capture an initial view; rotate elevation, capture; rotate pan (from the
//! initial position), capture — by default each both ways (+r and -r), which doubles the
//! angular span per axis; rotate both vergences, capture; return. Estimate the rig and head
//! ([`crate::verge_tilt`]), measure the vergence axes by resection, compute the aligned
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
//! (`f = fx` pooled over both cameras, default room, 8 seeds, a past
//! measurement) is 1.76 % with 3 deg single-joint views, 0.71 % at
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
//! With a lens model ([`EstimationOptions::lens`]) the vergence view and the check views
//! are resected on their pixels undistorted with the estimated lens
//! ([`pinhole_capture`]); the axes' uncertainty then holds those pixels fixed (a
//! perturbation of the lens terms moves the calibration's points, not the resected
//! pixels).
//!
//! The run judges itself (the `verdict` module docs): each move to aligned readings more
//! than [`MAX_ALIGNING_MOVE_DEG`] (30 deg, or the plan's largest turn if larger) from the
//! reference view's on any joint is refused before it is sent ([`check_move`]), and the last check's three correctable
//! errors are held against [`CHECK_SIGMAS`] (5) times `sqrt(sigma_aligned^2 + sigma_check^2
//! + sigma_move^2)` ([`check_verdict`], the outcome's `verdict`; each check's own sigma in
//! [`CheckStep::sigma`]). The caller adds the estimate's fit to the images
//! ([`CheckVerdict::judge_fit`]) where it has the front end's noise.
//!
//! Every captured view is kept in the outcome (and in the error path the caller still has
//! them through [`VergeTiltRun::views`]). Angles in degrees.
//!
//! Code layout: `rotation` (the rotation choice), `sigmas` (the aligned readings'
//! uncertainty), `axes` (the vergence axes' measurement and its uncertainty), `offline`
//! (the same estimate from a recorded session, without moving the head:
//! [`align_session`]); the procedure itself, its options and the capture plan here.

mod axes;
mod offline;
mod rotation;
mod sigmas;
#[cfg(test)]
mod tests;
mod verdict;

use std::time::Instant;

use headalign_geometry::so3::Line;
use headalign_platform::{Encoders, Joint, StereoHead};
use serde::Serialize;

pub use axes::{
    AXIS_BOOTSTRAP_DRAWS, AxisMeasurement, AxisPerturbations, AxisSources, AxisStep, axis_perturbations,
    resection_pose_covariance, resection_pose_covariance_bootstrap,
};
pub use offline::{
    PlanarSessionAlignment, SessionAlignment, SessionRoute, align_session, align_session_detecting,
    session_model_fit,
};
pub use rotation::{RotationChoice, choose_rotations, resolve_rotation, shared_stereo_tracks};
pub use sigmas::{alignment_sigmas, alignment_sigmas_measured, fixation_sigmas};
pub use verdict::{
    CHECK_SIGMAS, CheckComponent, CheckVerdict, FitJudgement, MAX_ALIGNING_MOVE_DEG, check_move,
    check_sigmas, check_verdict,
};

pub use crate::alignment::{AlignmentSigmas, PROPAGATION_STEP_SIGMAS};
use crate::alignment::{
    AlignmentSolution, MeasuredErrors, VergeAxes, head_motion, measure_cameras, measured_errors,
    solve_alignment, verge_axes_from_motion,
};
use crate::error::AlignError;
use crate::observations::View;
use crate::plan::CapturePlan;
use crate::verge_tilt::{EstimationOptions, RigCalibration, estimate_rig};

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
        let plan = CapturePlan::default();
        Self {
            rotation_deg: plan.rotation_deg,
            verge_rotation_deg: plan.verge_rotation_deg,
            both_directions: plan.both_directions,
            estimation: EstimationOptions::default(),
            check_tolerance_deg: 0.2,
            max_corrections: 2,
            diagonal_rotation_deg: plan.diagonal_rotation_deg,
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
    /// The check's own 1-sigma of each measured error, degrees ([`check_sigmas`]; `None`
    /// when the resections' covariance could not be formed).
    pub sigma: Option<MeasuredErrors>,
}

/// 1-sigma uncertainties of the fixation points (where each camera sees the target
/// direction, [`AlignmentSolution::fixation_px_left`]), pixels per image axis, propagated
/// from the bundle adjustment's covariance ([`fixation_sigmas`]). Not the aligned
/// readings' sigmas: a reading's error is the fixation point's less the principal
/// point's (`sigmas.rs` module docs).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct FixationSigmas {
    /// Left image, `[x, y]`.
    pub left_px: [f64; 2],
    /// Right image, `[x, y]`.
    pub right_px: [f64; 2],
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
    /// The last check against the reported sigmas ([`check_verdict`]).
    pub verdict: CheckVerdict,
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

/// What [`VergeTiltRun::run_detecting`] did: the general route, or the planar one.
#[derive(Debug, Clone)]
pub enum RouteOutcome {
    /// The scene had depth: the general route's outcome, and the detection's numbers.
    General(Box<VergeTiltOutcome>, crate::facing_plane::SceneCheck),
    /// The scene was planar or far: the planar route's outcome.
    Planar(Box<PlanarOutcome>),
}

/// The planar route's outcome ([`crate::facing_plane`]): the head is moved to the aligned
/// readings and one check view is captured there and measured against each camera's
/// planar model ([`crate::facing_plane::check_alignment`]: what it cannot check, it names). No
/// corrective move follows: the planar model already holds the vergence axes.
#[derive(Debug, Clone)]
pub struct PlanarOutcome {
    /// The planar calibration (scene verdict, each camera, what is undetermined).
    pub calibration: crate::facing_plane::PlanarCalibration,
    /// The alignment solution.
    pub solution: AlignmentSolution,
    /// Uncertainty of the aligned readings.
    pub sigmas: AlignmentSigmas,
    /// The check after the move (empty when it failed: [`PlanarOutcome::check_failure`]).
    pub checks: Vec<crate::facing_plane::PlanarCheck>,
    /// Why the check could not be made, if it could not (the alignment stands).
    pub check_failure: Option<String>,
    /// The check against the reported sigmas ([`check_verdict`]; `unchecked` when the
    /// check could not be made).
    pub verdict: CheckVerdict,
    /// Final encoder readings (aligned).
    pub final_encoders: Encoders,
    /// Elevation/pan rotation used, degrees.
    pub rotation_deg: f64,
    /// Diagonal rotation used, degrees (0 if none).
    pub diagonal_rotation_deg: f64,
    /// Vergence move used, degrees.
    pub verge_rotation_deg: f64,
    /// Seconds spent estimating.
    pub estimation_seconds: f64,
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

    /// Run the procedure on `head` (the general route only: a planar or depth-less scene
    /// fails at the estimation; [`VergeTiltRun::run_detecting`] switches to
    /// [`crate::facing_plane`] instead).
    pub fn run<H: StereoHead>(
        &mut self,
        head: &mut H,
        options: &VergeTiltOptions,
    ) -> Result<VergeTiltOutcome, AlignError> {
        let (options, plan) = self.capture_views(head, options)?;
        self.finish_general(head, &options, &plan)
    }

    /// Run the procedure on `head`, and after the captures detect a planar or depth-less
    /// scene from the reference view's stereo matches ([`crate::facing_plane::detect_scene`]):
    /// then the planar route aligns instead ([`PlanarOutcome`]); otherwise exactly
    /// [`VergeTiltRun::run`] (the detection only reads the captured views).
    pub fn run_detecting<H: StereoHead>(
        &mut self,
        head: &mut H,
        options: &VergeTiltOptions,
    ) -> Result<RouteOutcome, AlignError> {
        let (options, plan) = self.capture_views(head, options)?;
        let rig_views = plan.len() - 1;
        let scene =
            crate::facing_plane::detect_scene(&self.views[..rig_views], &options.estimation.fundamental);
        if scene.kind == crate::facing_plane::SceneKind::General {
            return self
                .finish_general(head, &options, &plan)
                .map(|o| RouteOutcome::General(Box::new(o), scene));
        }
        let t0 = Instant::now();
        let (calibration, solution, sigmas) = planar_alignment(&self.views, scene, &options.estimation)?;
        let mut estimation_seconds = t0.elapsed().as_secs_f64();
        check_move(&calibration.reference_encoders, &solution.aligned_encoders, planned_turn_deg(&options))?;
        head.move_to(&solution.aligned_encoders)?;
        let idx = self.capture(head, "check-1")?;
        let t1 = Instant::now();
        let check = crate::facing_plane::check_alignment(
            &calibration,
            &self.views[0].capture,
            &self.views[idx].capture,
        );
        estimation_seconds += t1.elapsed().as_secs_f64();
        let move_sigma_deg = options.estimation.bundle.angle_prior_sigma.map_or(0.0, f64::to_degrees);
        let (checks, check_failure, verdict) = match check {
            Ok(c) => {
                let v = check_verdict("check-1", &c.measured, &sigmas, Some(&c.sigma), move_sigma_deg);
                (vec![c], None, v)
            }
            Err(e) => (Vec::new(), Some(e.to_string()), CheckVerdict::unchecked("check-1")),
        };
        let final_encoders = head.read_encoders()?;
        Ok(RouteOutcome::Planar(Box::new(PlanarOutcome {
            calibration,
            solution,
            sigmas,
            checks,
            check_failure,
            verdict,
            final_encoders,
            rotation_deg: options.rotation_deg,
            diagonal_rotation_deg: options.diagonal_rotation_deg,
            verge_rotation_deg: options.verge_rotation_deg,
            estimation_seconds,
        })))
    }

    /// The captures of the plan (after choosing the rotation), the head back at the start.
    fn capture_views<H: StereoHead>(
        &mut self,
        head: &mut H,
        options: &VergeTiltOptions,
    ) -> Result<(VergeTiltOptions, Vec<(String, Encoders)>), AlignError> {
        options.validate()?;
        let options = resolve_rotation(head, options)?;
        let e0 = head.read_encoders()?;
        let plan = capture_plan(&e0, &options);
        for (name, encoders) in &plan {
            head.move_to(encoders)?;
            self.capture(head, name)?;
        }
        head.move_to(&e0)?;
        Ok((options, plan))
    }

    /// The general route after the captures: estimation, vergence axes, alignment, moves
    /// and checks.
    fn finish_general<H: StereoHead>(
        &mut self,
        head: &mut H,
        options: &VergeTiltOptions,
        plan: &[(String, Encoders)],
    ) -> Result<VergeTiltOutcome, AlignError> {
        let (rotation_deg, diagonal_rotation_deg) = (options.rotation_deg, options.diagonal_rotation_deg);
        // Every view of the plan but the last (the vergence move) keeps the rig rigid.
        let rig_views = plan.len() - 1;
        let verge_view = rig_views;

        let t0 = Instant::now();
        let calibration = estimate_rig(&self.views[..rig_views], &options.estimation)?;
        let reference = self.views[0].capture.encoders;
        let mut axes = self.measure_verge_axes(&calibration, verge_view, &reference)?;
        let mut estimation_seconds = t0.elapsed().as_secs_f64();

        let (checks, check_seconds) =
            self.move_and_check(head, options, &calibration, &reference, &mut axes)?;
        estimation_seconds += check_seconds;
        let AlignedAxes { verge_axes, axis_sources, solution } = axes;
        let reading_sigma_deg = options.estimation.bundle.angle_prior_sigma.map_or(0.0, f64::to_degrees);
        let sigmas = alignment_sigmas_measured(&calibration, &verge_axes, &axis_sources, &reference, None)?
            .with_reading_noise(reading_sigma_deg);
        let verdict = checks.last().map_or_else(
            || CheckVerdict::unchecked("none"),
            |c| {
                let name = format!("check-{}", checks.len());
                check_verdict(&name, &c.measured, &sigmas, c.sigma.as_ref(), reading_sigma_deg)
            },
        );
        let final_encoders = head.read_encoders()?;
        Ok(VergeTiltOutcome {
            calibration,
            verge_axes,
            axis_sources,
            solution,
            sigmas,
            checks,
            verdict,
            final_encoders,
            rotation_deg,
            diagonal_rotation_deg,
            verge_rotation_deg: options.verge_rotation_deg,
            estimation_seconds,
        })
    }

    /// The vergence axes measured by resection in the vergence view (`verge_view`, the
    /// plan's last) against the calibration's reference poses, and the alignment they give.
    fn measure_verge_axes(
        &self,
        calibration: &RigCalibration,
        verge_view: usize,
        reference: &Encoders,
    ) -> Result<AlignedAxes, AlignError> {
        let state = &calibration.bundle.state;
        let left0 = nalgebra::Isometry3::identity();
        let right0 = state.right_from_left.inverse();
        let verge_capture = pinhole_capture(calibration, &self.views[verge_view].capture);
        let measured = measure_cameras(calibration, &verge_capture, &left0, &right0)?;
        let verge_axes = verge_axes_from_motion(state, reference, &verge_capture.encoders, &measured)?;
        let source = AxisMeasurement { capture: verge_capture, measured };
        let axis_sources = AxisSources {
            left: verge_axes.left.map(|_| source.clone()),
            right: verge_axes.right.map(|_| source.clone()),
        };
        let solution = solve_alignment(state, &verge_axes, reference)?;
        Ok(AlignedAxes { verge_axes, axis_sources, solution })
    }

    /// Move to the aligned readings and check by vision; while a correctable error exceeds
    /// the tolerance, re-measure the vergence axes from that move and correct (at most
    /// `max_corrections` times; module docs). `axes` ends at the last correction. Returns
    /// the checks and the seconds spent computing (captures and moves aside).
    fn move_and_check<H: StereoHead>(
        &mut self,
        head: &mut H,
        options: &VergeTiltOptions,
        calibration: &RigCalibration,
        reference: &Encoders,
        axes: &mut AlignedAxes,
    ) -> Result<(Vec<CheckStep>, f64), AlignError> {
        let state = &calibration.bundle.state;
        let reference = *reference;
        let (mut checks, mut seconds) = (Vec::new(), 0.0);
        for round in 0..=options.max_corrections {
            let target = axes.solution.aligned_encoders;
            check_move(&reference, &target, planned_turn_deg(options))?;
            head.move_to(&target)?;
            let idx = self.capture(head, &format!("check-{}", round + 1))?;
            let t1 = Instant::now();
            let enc = self.views[idx].capture.encoders;
            let d = |j: Joint| (enc.get(j) - reference.get(j)).to_radians();
            let (pl, pr) = predicted_poses(calibration, &axes.verge_axes, &reference, &enc)?;
            let check_capture = pinhole_capture(calibration, &self.views[idx].capture);
            let measured = measure_cameras(calibration, &check_capture, &pl, &pr)?;
            let errors = measured_errors(state, &measured, d(Joint::Pan))
                .ok_or_else(|| AlignError::MissingMotion("pan and elevation axes".into()))?;
            let sigma = check_sigmas(calibration, &check_capture, &measured, d(Joint::Pan));
            checks.push(CheckStep { encoders: enc, measured: errors, sigma });
            // The right camera's elevation error is not correctable; the other three are.
            let worst = errors
                .verge_err_l_deg
                .abs()
                .max(errors.verge_err_r_deg.abs())
                .max(errors.elev_err_l_deg.abs());
            if worst <= options.check_tolerance_deg || round == options.max_corrections {
                seconds += t1.elapsed().as_secs_f64();
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
                seconds += t1.elapsed().as_secs_f64();
                break;
            }
            let source = AxisMeasurement { capture: check_capture, measured };
            if left.is_some() {
                axes.axis_sources.left = Some(source.clone());
            }
            if right.is_some() {
                axes.axis_sources.right = Some(source);
            }
            axes.verge_axes =
                VergeAxes { left: left.or(axes.verge_axes.left), right: right.or(axes.verge_axes.right) };
            axes.solution = solve_alignment(state, &axes.verge_axes, &reference)?;
            seconds += t1.elapsed().as_secs_f64();
        }
        Ok((checks, seconds))
    }
}

/// The vergence axes the general route uses, the captures that measured them, and the
/// alignment they give.
struct AlignedAxes {
    verge_axes: VergeAxes,
    axis_sources: AxisSources,
    solution: AlignmentSolution,
}

/// The planar route's options from the estimation's: its RANSAC seed, and its angle prior
/// (the encoder prior of the bundle adjustment, [`crate::verge_tilt::ENCODER_SIGMA_DEG`]
/// without one).
pub fn planar_options(estimation: &EstimationOptions) -> crate::facing_plane::PlanarOptions {
    crate::facing_plane::PlanarOptions {
        homography: headalign_geometry::ransac::RansacOptions {
            seed: estimation.seed,
            ..crate::facing_plane::PlanarOptions::default().homography
        },
        angle_prior_sigma_deg: estimation
            .bundle
            .angle_prior_sigma
            .map_or(crate::verge_tilt::ENCODER_SIGMA_DEG, f64::to_degrees),
        ..crate::facing_plane::PlanarOptions::default()
    }
}

/// The planar route's alignment of `views` (the first is the reference): the planar
/// estimate, the aligned readings from each camera's own axes, and their sigmas with the
/// readings' own noise (the estimation's angle prior).
pub(crate) fn planar_alignment(
    views: &[View],
    scene: crate::facing_plane::SceneCheck,
    estimation: &EstimationOptions,
) -> Result<(crate::facing_plane::PlanarCalibration, AlignmentSolution, AlignmentSigmas), AlignError> {
    let calibration = crate::facing_plane::estimate_planar(views, scene, &planar_options(estimation))?;
    let solution = crate::alignment::solve_alignment_axes(
        &calibration.left.axes(),
        &calibration.right.axes(),
        &calibration.reference_encoders,
    )?;
    let reading_sigma_deg = estimation.bundle.angle_prior_sigma.map_or(0.0, f64::to_degrees);
    let sigmas = crate::facing_plane::alignment_sigmas(&calibration)?.with_reading_noise(reading_sigma_deg);
    Ok((calibration, solution, sigmas))
}

/// The largest turn of any joint in the procedure's own plan, degrees (the move rule of
/// [`check_move`]).
fn planned_turn_deg(options: &VergeTiltOptions) -> f64 {
    options.rotation_deg.abs().max(options.diagonal_rotation_deg.abs()).max(options.verge_rotation_deg.abs())
}

/// The views the procedure captures, in order, from the initial readings `e0`
/// ([`CapturePlan::views`] with the options' rotations).
pub fn capture_plan(e0: &Encoders, options: &VergeTiltOptions) -> Vec<(String, Encoders)> {
    CapturePlan {
        rotation_deg: options.rotation_deg,
        verge_rotation_deg: options.verge_rotation_deg,
        both_directions: options.both_directions,
        diagonal_rotation_deg: options.diagonal_rotation_deg,
    }
    .views(e0)
}

/// The capture with every pixel undistorted by the calibration's estimated lenses
/// ([`crate::verge_tilt::EstimationOptions::lens`]), so that the pinhole resections of the
/// vergence axes and the checks see the cameras the calibration describes; the capture
/// itself for pinhole cameras. A pixel outside the lens model's valid range is dropped.
pub fn pinhole_capture(
    calib: &RigCalibration,
    capture: &headalign_platform::StereoCapture,
) -> headalign_platform::StereoCapture {
    let state = &calib.bundle.state;
    if state.left_distortion.is_zero() && state.right_distortion.is_zero() {
        return capture.clone();
    }
    let lenses = [
        crate::rig::LensModel { k: state.left, distortion: state.left_distortion },
        crate::rig::LensModel { k: state.right, distortion: state.right_distortion },
    ];
    let view = View { name: String::new(), capture: capture.clone() };
    crate::rig::undistort_views(std::slice::from_ref(&view), &lenses)
        .pop()
        .map_or_else(|| capture.clone(), |v| v.capture)
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
