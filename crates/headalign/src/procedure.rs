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
//! (`f = fx` pooled over both cameras, default room, 8 seeds, `cargo run --release -p
//! headalign --example crb_plans`) is 1.76 % with 3 deg single-joint views, 0.71 % at
//! 10 deg, 0.56 % adding 5 deg single-joint views (9 views), 0.47 / 0.39 / 0.31 % adding
//! diagonals of 5 / 7 / 10 deg (9 views), 0.27-0.28 % with 13 views: a combined rotation
//! moves the image along both axes at once and decorrelates the focal lengths from the
//! axes, where more of the same single-joint views add little. The diagonal views keep
//! 56-70 % of the reference tracks at 10 deg (hence 0.5 rather than the former 0.6, which
//! only single-joint views had to meet; 0.5 of about 200 tracks is still 5 times
//! `min_tracks`). Probe captures are discarded (they are not in `views`); a recording
//! caller calls [`resolve_rotation`] itself to record them as their own stage. Pitfall: the
//! overlap is counted by track id, which in image mode means the tracker's matches; a
//! tracker that loses tracks at larger rotations shrinks the choice, as it should (seed 1
//! on rendered images: 10 deg single-joint views, 3 deg diagonals).
//!
//! Every captured view is kept in the outcome (and in the error path the caller still has
//! them through [`VergeTiltRun::views`]). Angles in degrees.

use std::time::Instant;

use headalign_geometry::so3::Line;
use headalign_platform::{Encoders, Joint, StereoHead};
use nalgebra::DVector;
use serde::Serialize;

use crate::alignment::{
    AlignmentSolution, MeasuredErrors, VergeAxes, head_motion, measure_cameras, measured_errors,
    solve_alignment, verge_axes_from_motion,
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
    /// Minimum number of such shared tracks (default 60).
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
            min_tracks: 60,
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
/// adjustment's covariance (vergence axes taken as exact: resection against hundreds of
/// points is far more precise than the calibration).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct AlignmentSigmas {
    /// Elevation reading.
    pub elevation_deg: f64,
    /// Left vergence reading.
    pub verge_left_deg: f64,
    /// Right vergence reading.
    pub verge_right_deg: f64,
}

/// Everything the procedure produced.
#[derive(Debug, Clone)]
pub struct VergeTiltOutcome {
    /// The calibration.
    pub calibration: RigCalibration,
    /// Vergence axes measured by resection.
    pub verge_axes: VergeAxes,
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
            verge_axes = VergeAxes { left: left.or(verge_axes.left), right: right.or(verge_axes.right) };
            solution = solve_alignment(state, &verge_axes, &reference)?;
            estimation_seconds += t1.elapsed().as_secs_f64();
        }
        let sigmas = alignment_sigmas(&calibration, &verge_axes, &reference)?;
        let final_encoders = head.read_encoders()?;
        Ok(VergeTiltOutcome {
            calibration,
            verge_axes,
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

/// Propagate the bundle adjustment's covariance to the aligned readings by central
/// differences of [`solve_alignment`] along each parameter's standard deviation.
pub fn alignment_sigmas(
    calib: &RigCalibration,
    verge: &VergeAxes,
    reference: &Encoders,
) -> Result<AlignmentSigmas, AlignError> {
    let cov = &calib.bundle.covariance;
    let n = cov.matrix.nrows();
    let mut jac = nalgebra::DMatrix::<f64>::zeros(3, n);
    for i in 0..n {
        let s = cov.matrix[(i, i)].max(0.0).sqrt();
        if s.is_nan() || s <= 0.0 {
            continue;
        }
        let h = 0.5 * s;
        let mut delta = DVector::zeros(n);
        delta[i] = h;
        let plus =
            calib.bundle.perturbed(&delta).ok().and_then(|st| solve_alignment(&st, verge, reference).ok());
        delta[i] = -h;
        let minus =
            calib.bundle.perturbed(&delta).ok().and_then(|st| solve_alignment(&st, verge, reference).ok());
        if let (Some(p), Some(m)) = (plus, minus) {
            jac[(0, i)] = (p.delta_elevation_deg - m.delta_elevation_deg) / (2.0 * h);
            jac[(1, i)] = (p.delta_verge_left_deg - m.delta_verge_left_deg) / (2.0 * h);
            jac[(2, i)] = (p.delta_verge_right_deg - m.delta_verge_right_deg) / (2.0 * h);
        }
    }
    let out = &jac * &cov.matrix * jac.transpose();
    Ok(AlignmentSigmas {
        elevation_deg: out[(0, 0)].max(0.0).sqrt(),
        verge_left_deg: out[(1, 1)].max(0.0).sqrt(),
        verge_right_deg: out[(2, 2)].max(0.0).sqrt(),
    })
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
        let d = EstimationOptions::default();
        let mut estimation = EstimationOptions { seed: 29, prefilter_px: d.prefilter_px * 3.0, ..d };
        estimation.fundamental.threshold *= 3.0;
        estimation.homography.threshold *= 3.0;
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
