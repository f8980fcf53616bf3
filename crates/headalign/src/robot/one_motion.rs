//! One-motion alignment (end of paper section 4): a single motion that drives the robot
//! forward and turns the elevation joint at the same time aligns the vergence, the
//! elevation and the pan together.
//!
//! **Model.** Let `cam1_from_cam2` be the rigid motion of the left camera (its pose after
//! the motion in its frame before), measured from the calibrated stereo reconstruction
//! (the same maximum-likelihood rig motion as the pan stage, [`crate::robot`]). The robot
//! translates by `d v` (`v` unit, the direction of travel, in the first camera frame) and
//! the elevation joint turns by `r` about its axis (direction `a`, through a point `o`):
//!
//! `cam1_from_cam2: x -> R x + t`, `R = Rot(a, r)`, `t = (I - R) o + d v`.
//!
//! So the rotation part alone gives the elevation axis direction (screw axis; its sign
//! from the commanded tilt), and the translation after removing the rotation about the
//! known axis point `o` (from the verge/tilt calibration; only its component
//! perpendicular to `a` matters) gives the drive direction `v = t - (I - R) o`. Six
//! measured degrees of freedom, of which three (`a`, `r`) and two (`v`'s direction) are
//! used; `d` (stereo baselines) is only checked against `min_displacement`.
//!
//! **Corrections** (all angles about axes directed like their encoders):
//! - *pan*: the signed angle about the pan axis `u` (calibrated) from the head's forward
//!   direction (mean of the optical axes) to `v`, as [`crate::robot::pan_step`];
//! - *elevation*: the angle about `a` that brings the left optical axis into the horizon
//!   (zero `elev_err_l`, as the verge/tilt stage's aligned elevation), solved exactly
//!   although `a` need not be perpendicular to `u`; the horizon ([`Horizon`]) is either
//!   the plane through `v` (the robot moves on the ground) with normal nearest `u`, or
//!   the plane perpendicular to `u`. The paper's horizon normal `a x v` assumes the
//!   elevation axis horizontal; the simulator mounts it a few degrees off, so its angle
//!   from `u` is only reported (`horizon_tilt_deg`). The heading is taken after the
//!   elevation correction (an elevation axis off the horizontal turns the head);
//! - *vergence*: the angle of each optical axis out of the plane perpendicular to `a` is
//!   reported (`verge_check_deg`, the sim's `verge_err`), and the turn of each camera
//!   about its calibrated vergence axis (direction `g`, fixed in its camera frame) that
//!   brings its optical axis into that plane is solved exactly (the paper: the motion's
//!   invariant line at infinity aligns the vergence axes). The elevation and the heading
//!   are then computed for the verge-corrected optical axes, so one motion's corrections
//!   are consistent (noise-free: exact together). After a verge/tilt stage the vergence
//!   correction is small (that stage zeroed it about the same calibrated axis).
//!
//! **A turning robot** (steering wheel not straight, as before the steering stage): the
//! rotation is then `Rot(u, phi) Rot(a, r)` (robot turn about the pan axis `u` after the
//! elevation turn); with the calibrated `a` and `u` it splits exactly (`phi` from
//! `Rot(u, -phi) R a = a`), the elevation turn is removed about its axis, and the pan
//! axis point's chord is turned back by `phi / 2` (as the pan stage). So the stage uses
//! the calibrated elevation axis direction; the free screw axis of the motion is
//! reported (`free_axis`) as the paper's estimate, exact only for a straight drive.
//!
//! **Degenerate input**: a rotation below `min_tilt_deg` is [`AlignError::NoTilt`] (the
//! axis direction is then undefined); a displacement `|v d|` below `min_displacement`
//! baselines is [`AlignError::NoDrive`]; a drive along the elevation axis (no horizon) is
//! [`AlignError::NotPlanar`].
//!
//! **Pitfalls**: the tilt moves the cameras much more than the drive for distant scenes;
//! the stereo triangulation after the tilt uses the rig at the readings before (the
//! elevation joint carries both cameras, so `left_from_right` does not change). An error
//! `δo` in the axis point shifts `v` by `(I - R) δo`, about `r δo`: keep the tilt small
//! (default 5 deg). The robot's turn is split off about the calibrated pan axis, not the
//! floor's normal (one motion cannot fit the normal, [`crate::robot`]'s "floor normal"):
//! on a floor tilted `tau` against the pan axis a turn `phi` leaves about `phi tau` of
//! rotation to the elevation turn and the chord (exact with a straight wheel, as after the
//! steering stage). Units: lengths in stereo baselines, angles in degrees in reports.

use headalign_geometry::ransac::RansacOptions;
use headalign_platform::{Encoders, Joint, StereoHead, Vehicle};
use nalgebra::{Isometry3, Matrix3, Point3, Unit, UnitQuaternion, Vector3};
use serde::Serialize;

use crate::alignment::VergeAxes;
use crate::error::{AlignError, StepContext};
use crate::robot::{
    DRIVE_MIN_ITERATIONS, RigCheck, angle_about, check_rig, drive_motion, head_forward, rig_at,
    threshold_scale,
};
use crate::verge_tilt::RigCalibration;

/// Known geometry of the head for [`one_motion_from_motion`], in the left camera frame
/// before the motion, stereo baselines.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeadFrame {
    /// A point of the elevation axis (calibrated).
    pub elevation_point: Point3<f64>,
    /// Elevation axis direction, directed like the elevation encoder (calibrated).
    pub elevation_axis: Unit<Vector3<f64>>,
    /// A point of the pan axis (calibrated; the robot's turn, if any, is undone about it).
    pub pan_point: Point3<f64>,
    /// Pan axis direction, directed like the pan encoder (calibrated; used for the pan
    /// angle and for orienting the horizon normal).
    pub pan_axis: Unit<Vector3<f64>>,
    /// Right optical axis (unit).
    pub right_optical_axis: Vector3<f64>,
    /// Left and right vergence axis directions, directed like their encoders (calibrated;
    /// `None`: that camera's vergence is not corrected).
    pub verge_axes: [Option<Unit<Vector3<f64>>>; 2],
}

/// Which horizon the elevation correction levels the left optical axis with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum Horizon {
    /// The plane containing the measured drive direction whose normal is nearest the
    /// calibrated pan axis (the one motion's own elevation: the paper's "angle between
    /// `t` and the xz-plane"). Its precision is that of the drive direction's vertical
    /// component: measured RMS `elev_err_l` 0.50 deg at 1 px, seeds 1-20.
    Drive,
    /// The plane perpendicular to the calibrated pan axis (the verge/tilt definition;
    /// measured RMS `elev_err_l` 0.28 deg, as the separate stages).
    PanAxis,
}

/// Thresholds of [`one_motion_from_motion`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OneMotionThresholds {
    /// Smallest rotation accepted, degrees. Default 1.
    pub min_tilt_deg: f64,
    /// Smallest displacement after removing the tilt, stereo baselines. Default 0.02
    /// (5 mm at a 0.25 m baseline).
    pub min_displacement: f64,
    /// Smallest sine of the angle between the drive and the elevation axis. Default 0.1.
    pub min_horizon_sine: f64,
}

impl Default for OneMotionThresholds {
    fn default() -> Self {
        Self { min_tilt_deg: 1.0, min_displacement: 0.02, min_horizon_sine: 0.1 }
    }
}

impl OneMotionThresholds {
    /// Check the thresholds.
    pub fn validate(&self) -> Result<(), AlignError> {
        let ok = |x: f64| x.is_finite() && x >= 0.0;
        if !(ok(self.min_tilt_deg) && ok(self.min_displacement) && ok(self.min_horizon_sine)) {
            return Err(AlignError::InvalidOption(format!(
                "one-motion thresholds must be finite and >= 0: {self:?}"
            )));
        }
        Ok(())
    }
}

/// What one combined drive + tilt motion tells.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct OneMotionEstimate {
    /// Direction of travel, left camera frame before the motion (unit).
    pub drive_direction: [f64; 3],
    /// Displacement, stereo baselines.
    pub displacement: f64,
    /// Screw axis of the whole motion, directed like the commanded tilt (unit): the
    /// elevation axis when the robot does not turn (a check on the calibration).
    pub free_axis: [f64; 3],
    /// Measured elevation turn, degrees.
    pub tilt_deg: f64,
    /// Measured turn of the robot about the pan axis, degrees.
    pub turn_deg: f64,
    /// Pan correction (move the pan joint by this), degrees.
    pub pan_correction_deg: f64,
    /// Elevation correction (move the elevation joint by this), degrees.
    pub elevation_correction_deg: f64,
    /// Angle of the drive out of the plane perpendicular to the pan axis, degrees.
    pub elevation_check_deg: f64,
    /// Angle of the left / right optical axis out of the plane perpendicular to the
    /// calibrated elevation axis before the motion's corrections (vergence errors),
    /// degrees.
    pub verge_check_deg: [f64; 2],
    /// Vergence corrections (move the left / right vergence joint by this), degrees;
    /// `None` where the vergence axis is unknown or no turn about it reaches the plane.
    pub verge_correction_deg: [Option<f64>; 2],
    /// Angle between the paper's horizon normal (elevation axis x drive) and the
    /// calibrated pan axis, degrees: zero when the elevation axis is perpendicular to the
    /// pan axis (the paper's assumption; the simulator mounts it up to a few degrees off).
    pub horizon_tilt_deg: f64,
}

/// Pan and elevation corrections from the measured motion `cam1_from_cam2` of a combined
/// drive and elevation turn (commanded `tilt_deg`, only its sign is used) (module docs).
pub fn one_motion_from_motion(
    cam1_from_cam2: &Isometry3<f64>,
    tilt_deg: f64,
    head: &HeadFrame,
    horizon: Horizon,
    thresholds: &OneMotionThresholds,
) -> Result<OneMotionEstimate, AlignError> {
    thresholds.validate()?;
    let w = cam1_from_cam2.rotation.scaled_axis();
    let angle = w.norm();
    if angle.to_degrees() < thresholds.min_tilt_deg
        || angle.is_nan()
        || tilt_deg == 0.0
        || !tilt_deg.is_finite()
    {
        return Err(AlignError::NoTilt { angle_deg: angle.to_degrees(), min_deg: thresholds.min_tilt_deg });
    }
    let up = head.pan_axis.into_inner();
    let a = head.elevation_axis.into_inner();
    // Free screw axis of the whole motion (the elevation axis when the robot does not
    // turn): reported as a check.
    let a_free = w * (tilt_deg.signum() / angle);
    // Split the rotation into the robot's turn about the pan axis after the elevation
    // turn: R = Rot(u, phi) Rot(a, r), so Rot(u, -phi) R a = a.
    let r_all = cam1_from_cam2.rotation;
    let phi = angle_about(&up, &a, &(r_all * a));
    let r_elev = UnitQuaternion::from_axis_angle(&head.pan_axis, -phi) * r_all;
    let tilt = r_elev.scaled_axis().dot(&a);
    if tilt.abs().to_degrees() < thresholds.min_tilt_deg || tilt.is_nan() {
        return Err(AlignError::NoTilt { angle_deg: tilt.to_degrees(), min_deg: thresholds.min_tilt_deg });
    }
    let re = r_elev.to_rotation_matrix().into_inner();
    let elevation =
        Isometry3::from_parts(((Matrix3::identity() - re) * head.elevation_point.coords).into(), r_elev);
    // The robot's own motion and the displacement of the pan axis point, turned back by
    // half the turn (chord of an arc; see [`crate::robot`]).
    let robot_motion = cam1_from_cam2 * elevation.inverse();
    let p = head.pan_point;
    let chord = robot_motion.transform_point(&p) - p;
    let moved = UnitQuaternion::from_axis_angle(&head.pan_axis, -0.5 * phi) * chord;
    let displacement = moved.norm();
    if displacement < thresholds.min_displacement || displacement.is_nan() {
        return Err(AlignError::NoDrive { displacement, min: thresholds.min_displacement });
    }
    let v = moved / displacement;
    let axv = a.cross(&v);
    if axv.norm() < thresholds.min_horizon_sine {
        return Err(AlignError::NotPlanar(format!(
            "one motion: the drive is {:.2} deg from the elevation axis: no horizon",
            axv.norm().clamp(0.0, 1.0).asin().to_degrees()
        )));
    }
    let paper_normal = axv.normalize() * axv.dot(&up).signum();
    // Horizon normal: the calibrated pan axis made perpendicular to the drive.
    let n = match horizon {
        Horizon::Drive => (up - v * v.dot(&up)).normalize(),
        Horizon::PanAxis => up,
    };
    // Vergence first: each optical axis into the plane perpendicular to the elevation axis
    // by a turn about its own vergence axis.
    let zl = Vector3::z();
    let zr = head.right_optical_axis.normalize();
    let verge_turn = |g: Option<Unit<Vector3<f64>>>, z: &Vector3<f64>| {
        let angle = g.and_then(|g| elevation_into_plane(&g, z, &a));
        let turned = match (g, angle) {
            (Some(g), Some(t)) => UnitQuaternion::from_axis_angle(&g, t) * z,
            _ => *z,
        };
        (angle, turned)
    };
    let (verge_l, zl_aligned) = verge_turn(head.verge_axes[0], &zl);
    let (verge_r, zr_aligned) = verge_turn(head.verge_axes[1], &zr);
    let elev = elevation_into_plane(&a, &zl_aligned, &n).ok_or_else(|| {
        AlignError::NotPlanar("one motion: no elevation brings the optical axis into the horizon".into())
    })?;
    // The elevation joint carries both cameras; its axis need not be perpendicular to the
    // pan axis, so the heading is taken after the elevation correction.
    let h = UnitQuaternion::from_axis_angle(&Unit::new_unchecked(a), elev) * (zl_aligned + zr_aligned);
    let pan = angle_about(&up, &h, &v);
    let asin_deg = |x: f64| x.clamp(-1.0, 1.0).asin().to_degrees();
    Ok(OneMotionEstimate {
        drive_direction: [v.x, v.y, v.z],
        displacement,
        free_axis: [a_free.x, a_free.y, a_free.z],
        tilt_deg: tilt.to_degrees(),
        turn_deg: phi.to_degrees(),
        pan_correction_deg: pan.to_degrees(),
        elevation_correction_deg: elev.to_degrees(),
        elevation_check_deg: asin_deg(v.dot(&up)),
        verge_check_deg: [asin_deg(a.z), asin_deg(zr.dot(&a))],
        verge_correction_deg: [verge_l.map(f64::to_degrees), verge_r.map(f64::to_degrees)],
        horizon_tilt_deg: paper_normal.angle(&up).to_degrees(),
    })
}

/// The rotation about `a` (unit) that brings `z` into the plane perpendicular to `n`
/// (unit), radians, the smaller of the two; `None` if no rotation about `a` does.
fn elevation_into_plane(a: &Vector3<f64>, z: &Vector3<f64>, n: &Vector3<f64>) -> Option<f64> {
    // z(e) = a (a.z) + cos e z_p + sin e (a x z_p); z(e).n = c + p cos e + q sin e.
    let zp = z - a * a.dot(z);
    let (c, p, q) = (a.dot(z) * a.dot(n), zp.dot(n), a.cross(&zp).dot(n));
    let rho = p.hypot(q);
    if rho.is_nan() || rho <= 0.0 || c.abs() > rho {
        return None;
    }
    let phi = q.atan2(p);
    let delta = (-c / rho).acos();
    let wrap =
        |x: f64| (x + std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI) - std::f64::consts::PI;
    let (e1, e2) = (wrap(phi + delta), wrap(phi - delta));
    Some(if e1.abs() <= e2.abs() { e1 } else { e2 })
}

/// Options of [`align_one_motion`].
#[derive(Debug, Clone, PartialEq)]
pub struct OneMotionOptions {
    /// Forward drive, metres. Default 0.10 (the pan stage's).
    pub drive_m: f64,
    /// Elevation turn during the drive, degrees. Default 5.
    pub tilt_deg: f64,
    /// Motions (each after correcting the last). Default 2.
    pub iterations: usize,
    /// Move the elevation joint too (else only the pan). Default true.
    pub correct_elevation: bool,
    /// Move the vergence joints too (where their axes are calibrated). Default true.
    pub correct_vergence: bool,
    /// Horizon of the elevation correction. Default [`Horizon::PanAxis`] (the more
    /// precise, see [`Horizon`]).
    pub horizon: Horizon,
    /// Degeneracy thresholds. Default [`OneMotionThresholds::default`].
    pub thresholds: OneMotionThresholds,
    /// Registration RANSAC (threshold: reprojection pixels). Default threshold 4 px, at
    /// least [`DRIVE_MIN_ITERATIONS`] samples.
    pub registration: RansacOptions,
    /// Multiply the registration threshold by the calibration's noise estimate when it
    /// exceeds 1 px, as [`crate::robot::PanOptions::scale_to_noise`]. Default true.
    pub scale_to_noise: bool,
}

impl Default for OneMotionOptions {
    fn default() -> Self {
        Self {
            drive_m: 0.10,
            tilt_deg: 5.0,
            iterations: 2,
            correct_elevation: true,
            correct_vergence: true,
            horizon: Horizon::PanAxis,
            thresholds: OneMotionThresholds::default(),
            registration: RansacOptions {
                threshold: 4.0,
                min_iterations: DRIVE_MIN_ITERATIONS,
                ..RansacOptions::default()
            },
            scale_to_noise: true,
        }
    }
}

impl OneMotionOptions {
    /// These options with the registration threshold scaled for the calibration's noise
    /// estimate `sigma_px` ([`OneMotionOptions::scale_to_noise`]).
    pub fn scaled_to_noise(&self, sigma_px: f64) -> OneMotionOptions {
        let mut o = self.clone();
        o.registration.threshold *= threshold_scale(self.scale_to_noise, sigma_px);
        o
    }

    /// Check the options.
    pub fn validate(&self) -> Result<(), AlignError> {
        if !(self.drive_m.is_finite() && self.tilt_deg.is_finite() && self.iterations >= 1) {
            return Err(AlignError::InvalidOption(format!(
                "one motion: drive_m and tilt_deg must be finite and iterations >= 1, got {} {} {}",
                self.drive_m, self.tilt_deg, self.iterations
            )));
        }
        self.thresholds.validate()?;
        self.registration.validate().step("one-motion options")
    }
}

/// One motion of the stage.
#[derive(Debug, Clone, Serialize)]
pub struct OneMotionStep {
    /// Head readings before the motion.
    pub encoders: Encoders,
    /// The estimate.
    pub estimate: OneMotionEstimate,
    /// Registration inliers.
    pub inliers: usize,
    /// The predicted stereo rig checked against this motion's captures (and corrected if
    /// it misfit them).
    pub rig_check: RigCheck,
}

/// Result of [`align_one_motion`].
#[derive(Debug, Clone, Serialize)]
pub struct OneMotionOutcome {
    /// Every motion.
    pub steps: Vec<OneMotionStep>,
    /// Head readings at the end.
    pub final_encoders: Encoders,
}

/// Drive forward while turning the elevation joint, measure the rigid motion of the
/// calibrated stereo reconstruction, and correct pan and elevation (module docs). The
/// robot and the head end where they started, then the corrections are applied.
pub fn align_one_motion<R: StereoHead + Vehicle>(
    robot: &mut R,
    calib: &RigCalibration,
    verge: &VergeAxes,
    options: &OneMotionOptions,
) -> Result<OneMotionOutcome, AlignError> {
    options.validate()?;
    let options = &options.scaled_to_noise(calib.report.sigma_px);
    let mut steps = Vec::new();
    // Moves are made from the last commanded readings (read once), not from fresh noisy
    // reads, which would move every joint by its read noise at each step; the rig is
    // predicted at the readings.
    let mut commanded = robot.read_encoders()?;
    for _ in 0..options.iterations {
        let enc = robot.read_encoders()?;
        let before = robot.capture()?;
        robot.move_to(&commanded.moved(Joint::Elevation, options.tilt_deg))?;
        robot.drive(options.drive_m)?;
        let after = robot.capture()?;
        robot.drive(-options.drive_m)?;
        robot.move_to(&commanded)?;
        let (rig, _, rig_check) =
            check_rig(rig_at(calib, verge, &enc)?, &[&before, &after], calib.report.sigma_px, &enc)?;
        let left_from_ref = rig.ref_from_left.inverse();
        let pan_axis = calib.pan_axis().ok_or_else(|| AlignError::MissingMotion("pan axis".into()))?;
        let elev_axis =
            calib.elevation_axis().ok_or_else(|| AlignError::MissingMotion("elevation axis".into()))?;
        // The calibrated elevation axis is at the reference readings: it turns with the
        // pan joint (about the fixed pan axis) before moving into the current frame.
        let dpan = (enc.get(Joint::Pan) - calib.reference_encoders.get(Joint::Pan)).to_radians();
        let q = UnitQuaternion::from_axis_angle(&pan_axis.direction, dpan);
        let about_pan = Isometry3::from_parts((pan_axis.point.coords - q * pan_axis.point.coords).into(), q);
        let elev_axis = elev_axis.transformed(&(left_from_ref * about_pan));
        let pan_axis = pan_axis.transformed(&left_from_ref);
        // A vergence axis is fixed in its camera's frame (the camera turns about it, pan and
        // elevation carry both): the left one as calibrated (reference left frame), the
        // right one through the right camera's frame at the reference readings.
        let right_from_ref = calib.bundle.state.right_from_left.rotation;
        let verge_axes = [
            verge.left.map(|l| l.direction),
            verge.right.map(|l| {
                Unit::new_normalize(
                    rig.left_from_right.rotation * (right_from_ref * l.direction.into_inner()),
                )
            }),
        ];
        let head = HeadFrame {
            elevation_point: elev_axis.point,
            elevation_axis: elev_axis.direction,
            pan_point: pan_axis.point,
            pan_axis: pan_axis.direction,
            right_optical_axis: head_forward(&rig) - Vector3::z(),
            verge_axes: if options.correct_vergence { verge_axes } else { [None, None] },
        };
        let motion = drive_motion(&rig, &before, &after, &options.registration)?;
        let estimate = one_motion_from_motion(
            &motion.cam2_from_cam1.inverse(),
            options.tilt_deg,
            &head,
            options.horizon,
            &options.thresholds,
        )?;
        commanded = commanded.moved(Joint::Pan, estimate.pan_correction_deg);
        if options.correct_elevation {
            commanded = commanded.moved(Joint::Elevation, estimate.elevation_correction_deg);
        }
        for (joint, c) in [Joint::VergeLeft, Joint::VergeRight].into_iter().zip(estimate.verge_correction_deg)
        {
            if let Some(c) = c {
                commanded = commanded.moved(joint, c);
            }
        }
        robot.move_to(&commanded)?;
        steps.push(OneMotionStep { encoders: enc, estimate, inliers: motion.inliers, rig_check });
    }
    Ok(OneMotionOutcome { steps, final_encoders: robot.read_encoders()? })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::procedure::{VergeTiltOptions, VergeTiltRun};
    use crate::verge_tilt::EstimationOptions;
    use headalign_sim::{Scenario, SimulatedRobot};
    use proptest::prelude::*;

    fn unit(x: [f64; 3]) -> Unit<Vector3<f64>> {
        Unit::new_normalize(Vector3::from(x))
    }

    /// The motion of the model in the module docs.
    fn motion(a: &Unit<Vector3<f64>>, r_deg: f64, o: &Point3<f64>, dv: &Vector3<f64>) -> Isometry3<f64> {
        let q = UnitQuaternion::from_axis_angle(a, r_deg.to_radians());
        let r = q.to_rotation_matrix().into_inner();
        Isometry3::from_parts(((Matrix3::identity() - r) * o.coords + dv).into(), q)
    }

    proptest! {
        /// Noise-free: the drive direction and the axis are recovered, and the corrections,
        /// applied as joint rotations (checked independently of the estimator's formulas),
        /// put the head's forward direction along the drive and the left optical axis in
        /// the horizon, to 1e-9 (double rounding through a few rotations; 1e-5 deg for an
        /// angle through acos, whose rounding near 0 is sqrt(eps)).
        #[test]
        fn noise_free_corrections_zero_the_errors(
            up0 in prop::array::uniform3(-1.0f64..1.0), a0 in prop::array::uniform3(-1.0f64..1.0),
            v_ang in 0.6f64..2.5, o in prop::array::uniform3(-2.0f64..2.0),
            r_deg in 2.0f64..10.0, neg in any::<bool>(), d in 0.05f64..1.0,
            zr in prop::array::uniform3(-0.2f64..0.2), turn_deg in -3.0f64..3.0,
            pp in prop::array::uniform3(-2.0f64..2.0),
            gl in prop::array::uniform3(-0.2f64..0.2), gr in prop::array::uniform3(-0.2f64..0.2),
            verge in any::<bool>(),
        ) {
            let up = unit(up0);
            prop_assume!(up.norm() > 0.0 && up.z.abs() < 0.7);
            let a_raw = Vector3::from(a0) - up.into_inner() * up.dot(&Vector3::from(a0));
            prop_assume!(a_raw.norm() > 0.1);
            let a = Unit::new_normalize(a_raw);
            // Drive horizontal, at v_ang from the elevation axis.
            let v = UnitQuaternion::from_axis_angle(&up, v_ang) * a.into_inner();
            let r = if neg { -r_deg } else { r_deg };
            // The robot turns by `turn_deg` about the pan axis through `pp` while its point
            // there moves along the chord at half the turn from the drive direction.
            let turn = UnitQuaternion::from_axis_angle(&up, turn_deg.to_radians());
            let half = UnitQuaternion::from_axis_angle(&up, 0.5 * turn_deg.to_radians());
            let p = Point3::from(pp);
            let robot = Isometry3::from_parts((p.coords - turn * p.coords + half * v * d).into(), turn);
            let m = robot * motion(&a, r, &Point3::from(o), &Vector3::zeros());
            let right = (Vector3::z() + Vector3::from(zr)).normalize();
            // Vergence axes near the pan axis (as on a head), a few degrees off.
            let g = |d: [f64; 3]| Unit::new_normalize(up.into_inner() + Vector3::from(d));
            let verge_axes = if verge { [Some(g(gl)), Some(g(gr))] } else { [None, None] };
            let head = HeadFrame {
                elevation_point: Point3::from(o), elevation_axis: a, pan_point: p, pan_axis: up,
                right_optical_axis: right, verge_axes,
            };
            let horizon = if neg { Horizon::Drive } else { Horizon::PanAxis };
            let e = one_motion_from_motion(&m, r, &head, horizon, &OneMotionThresholds::default()).unwrap();
            prop_assert!((Vector3::from(e.drive_direction) - v).norm() < 1e-9);
            prop_assert!((e.displacement - d).abs() < 1e-9 && (e.tilt_deg - r).abs() < 1e-7);
            prop_assert!((e.turn_deg - turn_deg).abs() < 1e-7);
            prop_assert!(e.elevation_check_deg.abs() < 1e-7 && e.horizon_tilt_deg < 1e-5);
            // The vergence turns, then elevation and pan, as joint rotations.
            let turn_about = |g: Option<Unit<Vector3<f64>>>, c: Option<f64>, z: Vector3<f64>| match (g, c) {
                (Some(g), Some(c)) => UnitQuaternion::from_axis_angle(&g, c.to_radians()) * z,
                (None, None) => z,
                _ => Vector3::from_element(f64::NAN),
            };
            let zl = turn_about(verge_axes[0], e.verge_correction_deg[0], Vector3::z());
            let zr = turn_about(verge_axes[1], e.verge_correction_deg[1], right);
            if verge {
                prop_assert!(zl.dot(&a).abs() < 1e-9 && zr.dot(&a).abs() < 1e-9);
            }
            let pan = UnitQuaternion::from_axis_angle(&up, e.pan_correction_deg.to_radians());
            let el = UnitQuaternion::from_axis_angle(&a, e.elevation_correction_deg.to_radians());
            let h = pan * el * (zl + zr);
            let hh = h - up.into_inner() * up.dot(&h);
            prop_assert!(hh.normalize().cross(&v).norm() < 1e-9 && hh.dot(&v) > 0.0);
            prop_assert!((el * zl).dot(&up).abs() < 1e-9);
        }
    }

    /// Each degenerate input gives its named error.
    #[test]
    fn degenerate_motions_are_named() {
        let a = Vector3::x_axis();
        let o = Point3::new(0.5, -0.2, -0.3);
        let head = HeadFrame {
            elevation_point: o,
            elevation_axis: a,
            pan_point: Point3::new(0.5, 0.1, -0.3),
            pan_axis: -Vector3::y_axis(),
            right_optical_axis: Vector3::z(),
            verge_axes: [None, None],
        };
        let th = OneMotionThresholds::default();
        let no_tilt = motion(&a, 0.2, &o, &Vector3::new(0.0, 0.0, 0.4));
        assert!(matches!(
            one_motion_from_motion(&no_tilt, 0.2, &head, Horizon::Drive, &th),
            Err(AlignError::NoTilt { .. })
        ));
        let no_drive = motion(&a, 5.0, &o, &Vector3::new(0.0, 0.0, 0.001));
        assert!(matches!(
            one_motion_from_motion(&no_drive, 5.0, &head, Horizon::Drive, &th),
            Err(AlignError::NoDrive { .. })
        ));
        let along_axis = motion(&a, 5.0, &o, &Vector3::new(0.4, 0.0, 0.0));
        assert!(matches!(
            one_motion_from_motion(&along_axis, 5.0, &head, Horizon::Drive, &th),
            Err(AlignError::NotPlanar(_))
        ));
        let bad = OneMotionOptions { tilt_deg: f64::NAN, ..OneMotionOptions::default() };
        assert!(matches!(bad.validate(), Err(AlignError::InvalidOption(_))));
    }

    /// Noise-free end to end after the verge/tilt stage: pan, left elevation and both
    /// vergence errors below 1e-3 deg (the verge/tilt calibration's convergence limit, as
    /// the pan stage's test); a 0.2 deg tilt is the named error. The floor is level with
    /// the pan axis (`pan_tilt_deg` 0): the stage turns the robot back about the pan axis
    /// (module docs, pitfalls).
    #[test]
    fn noise_free_stage_aligns_pan_elevation_and_vergence() {
        let s = Scenario {
            seed: 2,
            noise_px: 0.0,
            outlier_fraction: 0.0,
            pan_tilt_deg: 0.0,
            ..Scenario::default()
        };
        let mut robot = SimulatedRobot::new(s).unwrap();
        let opts = VergeTiltOptions {
            estimation: EstimationOptions { seed: 2, ..EstimationOptions::default() },
            ..VergeTiltOptions::default()
        };
        let vt = VergeTiltRun::default().run(robot.head_mut(), &opts).unwrap();
        // Spoil the elevation and vergence the verge/tilt stage aligned, so the stage has
        // work to do on every joint.
        let enc = robot.head().encoders().moved(Joint::Elevation, 3.0);
        let enc = enc.moved(Joint::VergeLeft, 2.0).moved(Joint::VergeRight, -1.5);
        robot.move_to(&enc).unwrap();
        let out = align_one_motion(&mut robot, &vt.calibration, &vt.verge_axes, &OneMotionOptions::default())
            .unwrap();
        let enc = robot.head().encoders();
        let errs = robot.head().alignment_errors(&enc);
        assert!(robot.pan_err_deg(&enc).abs() < 1e-3, "{out:?}");
        assert!(errs.elev_err_l_deg.abs() < 1e-3, "{errs:?} {out:?}");
        assert!(errs.verge_err_l_deg.abs() < 1e-3 && errs.verge_err_r_deg.abs() < 1e-3, "{errs:?} {out:?}");
        let small = OneMotionOptions { tilt_deg: 0.2, ..OneMotionOptions::default() };
        assert!(matches!(
            align_one_motion(&mut robot, &vt.calibration, &vt.verge_axes, &small),
            Err(AlignError::NoTilt { .. })
        ));
    }
}
