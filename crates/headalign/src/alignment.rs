//! Verge/tilt alignment from a calibrated head (`docs/how-it-works.md#the-exact-alignment-solve`; paper
//! section 3.2 steps 5-7, computed exactly instead of by iterative fixation).
//!
//! Aligned means: each optical axis perpendicular to the elevation axis and to the pan
//! axis. The target direction is `d = a_e x a_p` (sign: forward), the vanishing point
//! where the invariant lines of the two rotations meet. The joints that can reach it:
//! elevation (shared) and each camera's vergence. With the camera chain
//! `ref_from_cam = Rot(a_p, dp) Rot(a_e, de) Rot(a_v, dv)` (axes in the reference left
//! camera frame at the reference configuration, directed like their encoders), and only
//! directions mattering for a point at infinity (so axis offsets drop out exactly):
//! 1. choose `dv` so that `Rot(a_v, dv) z` is perpendicular to `a_e`: `A cos dv + B sin dv
//!    + C = 0` in closed form, the root of smallest magnitude (the verge error is zero);
//! 2. choose `de` to rotate that direction about `a_e` onto `d` (the elevation error is
//!    zero for the left camera).
//!
//! The right camera gets its own `dv` by step 1; elevation is shared, so its elevation
//! error is what remains: it is predicted and reported, not hidden. Camera roll (the angle
//! of the image x axis out of the plane perpendicular to the pan axis) is reported too.
//!
//! Axis directions come from the bundle adjustment; vergence axes from resection of the
//! cameras after a vergence move ([`measure_cameras`]), or, if no such move was made, the
//! nominal assumption (perpendicular to the elevation axis, in the plane of the camera's
//! y axis, positive encoder turning about the camera's down direction `+y`: a positive
//! vergence turns the camera to the right, the sign of a positive vergence error), flagged in
//! the result. The data cannot tell that sign (no vergence joint moved), nor the camera's
//! mounting rotation on its axis: readings from a nominal axis carry both assumptions,
//! which their sigmas do not include. Angles in degrees at the interface, radians inside.
//!
//! The aligned readings' sigmas ([`AlignmentSigmas`]) are propagated by each route
//! ([`crate::procedure::alignment_sigmas`], [`crate::facing_plane::alignment_sigmas`]) with
//! the central-difference step [`PROPAGATION_STEP_SIGMAS`].

use headalign_geometry::bundle::RigState;
use headalign_geometry::camera::Intrinsics;
use headalign_geometry::resection::{ResectionOptions, resect};
use headalign_geometry::so3::{Line, rotation_about_line, screw_from_isometry};
use headalign_platform::{Encoders, Joint, StereoCapture};
use nalgebra::{Isometry3, Point2, Point3, Unit, Vector3};
use serde::Serialize;

use crate::error::{AlignError, StepContext};
use crate::verge_tilt::{MOVED_DEG, RigCalibration, axes_of};

/// Vergence axes in the reference left camera frame at the reference configuration,
/// directed like their encoders.
#[derive(Debug, Clone, Copy, Default)]
pub struct VergeAxes {
    /// Left vergence axis, if measured.
    pub left: Option<Line>,
    /// Right vergence axis, if measured.
    pub right: Option<Line>,
}

/// The aligned encoder readings and what alignment leaves.
#[derive(Debug, Clone, Serialize)]
pub struct AlignmentSolution {
    /// Target optical-axis direction in the reference left camera frame (unit).
    pub target_direction: [f64; 3],
    /// Encoder readings at which the head is aligned (pan unchanged: the pan stage sets it).
    pub aligned_encoders: Encoders,
    /// Joint changes from the reference view, degrees.
    pub delta_elevation_deg: f64,
    /// Left vergence change, degrees.
    pub delta_verge_left_deg: f64,
    /// Right vergence change, degrees.
    pub delta_verge_right_deg: f64,
    /// The right camera's elevation error that the shared elevation joint cannot remove,
    /// degrees (sign: along the pan axis as directed by its encoder).
    pub predicted_elev_err_r_deg: f64,
    /// Left camera roll after alignment, degrees.
    pub roll_left_deg: f64,
    /// Right camera roll after alignment, degrees.
    pub roll_right_deg: f64,
    /// The fixation point in the reference view's left image: the intersection of the
    /// invariant lines (the vanishing point of `d`); with an estimated lens, mapped
    /// through it into the captured image (the invariant lines stay in the undistorted
    /// one, where they are lines).
    pub fixation_px_left: [f64; 2],
    /// ... and in its right image.
    pub fixation_px_right: [f64; 2],
    /// The invariant lines whose intersections are the fixation points.
    pub invariant_lines: InvariantLines,
    /// False if the vergence axes were assumed nominal rather than measured.
    pub verge_axes_measured: bool,
}

/// What a solution with nominal vergence axes (`verge_axes_measured` false) must say: no
/// view moved a vergence joint, so the readings carry the nominal axes' assumptions.
pub const NOMINAL_VERGE_WARNING: &str = "no view moved the vergence joints: the vergence readings assume axes perpendicular to the elevation axis with a positive vergence turning each camera right, and their sigmas exclude the cameras' mounting on those axes; add a view with both vergences moved";

/// The images of the invariant lines at infinity of the pan and elevation rotations in the
/// reference view (paper section 3.2 steps 5-6), each a unit homogeneous line.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct InvariantLines {
    /// Pan rotation's line (the horizon) in the left image.
    pub pan_left: [f64; 3],
    /// Elevation rotation's line in the left image.
    pub elevation_left: [f64; 3],
    /// Pan rotation's line in the right image.
    pub pan_right: [f64; 3],
    /// Elevation rotation's line in the right image.
    pub elevation_right: [f64; 3],
}

/// A pinhole pixel of camera `k` mapped through its lens `d` into the captured image
/// (unchanged for a pinhole camera, bit for bit).
fn through_lens(d: &headalign_geometry::distortion::Distortion, k: &Intrinsics, px: [f64; 2]) -> [f64; 2] {
    if d.is_zero() {
        return px;
    }
    let p = d.distort_pixel(k, &Point2::new(px[0], px[1]));
    [p.x, p.y]
}

/// Invariant lines of the calibrated head's pan and elevation rotations, from the complex
/// eigenvectors of each rotation's 4x4 motion (the Euclidean frame's 3D homography),
/// projected by both cameras; and their intersections, the fixation point in the left and
/// right images (pixels). A unit test checks them against the closed form `K (a_e x a_p)`.
pub fn invariant_lines(state: &RigState) -> Result<(InvariantLines, [f64; 2], [f64; 2]), AlignError> {
    let (pan, elev) =
        axes_of(state).ok_or_else(|| AlignError::MissingMotion("pan and elevation axes".into()))?;
    let p_l = headalign_geometry::camera::ProjectiveCamera::from_pose(&state.left, &Isometry3::identity()).0;
    let p_r = headalign_geometry::camera::ProjectiveCamera::from_pose(&state.right, &state.right_from_left).0;
    // Any nonzero angle gives the same invariant line; 3 deg keeps the complex pair clear.
    let angle = 3f64.to_radians();
    let line = |axis: &Line, p: &nalgebra::Matrix3x4<f64>| {
        let h = rotation_about_line(axis, angle).inverse().to_homogeneous();
        headalign_geometry::invariant::invariant_image_line(&h, p).step("invariant line")
    };
    let (pl, el, pr, er) = (line(&pan, &p_l)?, line(&elev, &p_l)?, line(&pan, &p_r)?, line(&elev, &p_r)?);
    let meet = |a: &Vector3<f64>, b: &Vector3<f64>| -> Result<[f64; 2], AlignError> {
        let x = headalign_geometry::invariant::intersect_lines(a, b).step("fixation point")?;
        if x.z.abs() < 1e-12 {
            return Err(AlignError::Geometry {
                step: "fixation point".into(),
                cause: headalign_geometry::GeometryError::Degenerate(
                    "the invariant lines meet at infinity".into(),
                ),
            });
        }
        Ok([x.x / x.z, x.y / x.z])
    };
    let lines = InvariantLines {
        pan_left: [pl.x, pl.y, pl.z],
        elevation_left: [el.x, el.y, el.z],
        pan_right: [pr.x, pr.y, pr.z],
        elevation_right: [er.x, er.y, er.z],
    };
    Ok((lines, meet(&pl, &el)?, meet(&pr, &er)?))
}

/// Rotate direction `v` by `angle` about unit `a`.
fn rotate(a: &Unit<Vector3<f64>>, angle: f64, v: &Vector3<f64>) -> Vector3<f64> {
    nalgebra::UnitQuaternion::from_axis_angle(a, angle) * v
}

/// The smallest-magnitude `g` with `n . Rot(a, g) z = 0`, or `None` if no rotation about
/// `a` can make `z` perpendicular to `n`.
fn zero_crossing(a: &Unit<Vector3<f64>>, n: &Vector3<f64>, z: &Vector3<f64>) -> Option<f64> {
    // Rot(a,g) z = z cos g + (a x z) sin g + a (a.z)(1 - cos g)
    let az = a.dot(z);
    let big_a = n.dot(z) - n.dot(a) * az;
    let big_b = n.dot(&a.cross(z));
    let big_c = n.dot(a) * az;
    let r = big_a.hypot(big_b);
    if r < 1e-12 || (big_c / r).abs() > 1.0 {
        return None;
    }
    let phi = big_b.atan2(big_a);
    let delta = (-big_c / r).acos();
    let wrap =
        |x: f64| (x + std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI) - std::f64::consts::PI;
    let (g1, g2) = (wrap(phi + delta), wrap(phi - delta));
    Some(if g1.abs() <= g2.abs() { g1 } else { g2 })
}

/// The nominal vergence axis of a camera whose optical frame in the reference frame has
/// rotation `ref_from_cam`: the camera's down direction (`+y`) made perpendicular to
/// `a_e`, so that a positive vergence turns the camera to the right (module docs).
fn nominal_verge_axis(ref_from_cam: &Isometry3<f64>, a_e: &Vector3<f64>) -> Unit<Vector3<f64>> {
    let down = ref_from_cam.rotation * Vector3::new(0.0, 1.0, 0.0);
    Unit::new_normalize(down - a_e * a_e.dot(&down))
}

/// Solve for the aligned readings (module docs). `reference` are the encoder readings of
/// the reference view.
pub fn solve_alignment(
    state: &RigState,
    verge: &VergeAxes,
    reference: &Encoders,
) -> Result<AlignmentSolution, AlignError> {
    let (pan, elev) =
        axes_of(state).ok_or_else(|| AlignError::MissingMotion("pan and elevation axes".into()))?;
    let (a_p, a_e) = (pan.direction, elev.direction);
    let left_from_right = state.right_from_left.inverse();
    let z = Vector3::z();
    let z_l = z;
    let z_r = left_from_right.rotation * z;
    let mut d = a_e.cross(&a_p);
    let n = d.norm();
    if n < 1e-6 {
        return Err(AlignError::Geometry {
            step: "alignment".into(),
            cause: headalign_geometry::GeometryError::Degenerate(
                "pan and elevation axes are parallel".into(),
            ),
        });
    }
    d /= n;
    if d.dot(&z_l) < 0.0 {
        d = -d;
    }
    let v_l =
        verge.left.map(|l| l.direction).unwrap_or_else(|| nominal_verge_axis(&Isometry3::identity(), &a_e));
    let v_r = verge.right.map(|l| l.direction).unwrap_or_else(|| nominal_verge_axis(&left_from_right, &a_e));
    let no_solution = |side: &str| AlignError::Geometry {
        step: "alignment".into(),
        cause: headalign_geometry::GeometryError::Degenerate(format!(
            "the {side} vergence axis cannot bring the optical axis perpendicular to the elevation axis"
        )),
    };
    let g_l = zero_crossing(&v_l, &a_e, &z_l).ok_or_else(|| no_solution("left"))?;
    let g_r = zero_crossing(&v_r, &a_e, &z_r).ok_or_else(|| no_solution("right"))?;
    let u_l = rotate(&v_l, g_l, &z_l);
    let de = a_e.dot(&u_l.cross(&d)).atan2(u_l.dot(&d));
    let final_r = rotate(&a_e, de, &rotate(&v_r, g_r, &z_r));
    let elev_err_r = final_r.dot(&a_p).clamp(-1.0, 1.0).asin();
    let roll = |x_cam: Vector3<f64>, g: f64, v: &Unit<Vector3<f64>>| {
        let x = rotate(&a_e, de, &rotate(v, g, &x_cam));
        x.dot(&a_p).clamp(-1.0, 1.0).asin().to_degrees()
    };
    let roll_l = roll(Vector3::x(), g_l, &v_l);
    let roll_r = roll(left_from_right.rotation * Vector3::x(), g_r, &v_r);
    let (lines, fixation_left, fixation_right) = invariant_lines(state)?;
    let mut aligned = *reference;
    aligned.elevation += de.to_degrees();
    aligned.verge_left += g_l.to_degrees();
    aligned.verge_right += g_r.to_degrees();
    Ok(AlignmentSolution {
        target_direction: [d.x, d.y, d.z],
        aligned_encoders: aligned,
        delta_elevation_deg: de.to_degrees(),
        delta_verge_left_deg: g_l.to_degrees(),
        delta_verge_right_deg: g_r.to_degrees(),
        predicted_elev_err_r_deg: elev_err_r.to_degrees(),
        roll_left_deg: roll_l,
        roll_right_deg: roll_r,
        fixation_px_left: through_lens(&state.left_distortion, &state.left, fixation_left),
        fixation_px_right: through_lens(&state.right_distortion, &state.right, fixation_right),
        invariant_lines: lines,
        verge_axes_measured: verge.left.is_some() && verge.right.is_some(),
    })
}

/// One camera's intrinsics and the head's axes in that camera's frame at the reference
/// view, directed like their encoders: what alignment needs, without a baseline or the
/// rig's pose (the planar route estimates each camera on its own, [`crate::facing_plane`]).
#[derive(Debug, Clone, Copy)]
pub struct CameraAxes {
    /// Intrinsics.
    pub intrinsics: Intrinsics,
    /// Pan axis direction.
    pub pan: Unit<Vector3<f64>>,
    /// Elevation axis direction.
    pub elevation: Unit<Vector3<f64>>,
    /// This camera's vergence axis direction, if measured (else the nominal one).
    pub verge: Option<Unit<Vector3<f64>>>,
}

/// [`solve_alignment`] from each camera's own axes ([`CameraAxes`]): the same steps, the
/// right camera's in its own frame (every quantity is a dot product of directions, so the
/// rig rotation drops out); the invariant lines are `K^-T a` and the fixation points
/// `K (a_e x a_p)` (paper section 3.2 steps 5-7; section 3.3 for a plane). `reference`:
/// the reference view's encoder readings.
pub fn solve_alignment_axes(
    left: &CameraAxes,
    right: &CameraAxes,
    reference: &Encoders,
) -> Result<AlignmentSolution, AlignError> {
    let z = Vector3::z();
    let degenerate = |why: String| AlignError::Geometry {
        step: "alignment".into(),
        cause: headalign_geometry::GeometryError::Degenerate(why),
    };
    let target = |c: &CameraAxes| -> Result<Vector3<f64>, AlignError> {
        let d = c.elevation.cross(&c.pan);
        let n = d.norm();
        if n < 1e-6 {
            return Err(degenerate("pan and elevation axes are parallel".into()));
        }
        Ok(if d.dot(&z) < 0.0 { -d / n } else { d / n })
    };
    let (d_l, d_r) = (target(left)?, target(right)?);
    let verge_axis =
        |c: &CameraAxes| c.verge.unwrap_or_else(|| nominal_verge_axis(&Isometry3::identity(), &c.elevation));
    let (v_l, v_r) = (verge_axis(left), verge_axis(right));
    let no_solution = |side: &str| {
        degenerate(format!(
            "the {side} vergence axis cannot bring the optical axis perpendicular to the elevation axis"
        ))
    };
    let g_l = zero_crossing(&v_l, &left.elevation, &z).ok_or_else(|| no_solution("left"))?;
    let g_r = zero_crossing(&v_r, &right.elevation, &z).ok_or_else(|| no_solution("right"))?;
    let u_l = rotate(&v_l, g_l, &z);
    let a_e = left.elevation;
    let de = a_e.dot(&u_l.cross(&d_l)).atan2(u_l.dot(&d_l));
    let final_r = rotate(&right.elevation, de, &rotate(&v_r, g_r, &z));
    let elev_err_r = final_r.dot(&right.pan).clamp(-1.0, 1.0).asin();
    let roll = |c: &CameraAxes, g: f64, v: &Unit<Vector3<f64>>| {
        let x = rotate(&c.elevation, de, &rotate(v, g, &Vector3::x()));
        x.dot(&c.pan).clamp(-1.0, 1.0).asin().to_degrees()
    };
    let line = |c: &CameraAxes, a: &Unit<Vector3<f64>>| {
        let l = c.intrinsics.inverse_matrix().transpose() * a.into_inner();
        let l = l / l.norm();
        [l.x, l.y, l.z]
    };
    let fixation = |c: &CameraAxes, d: &Vector3<f64>| -> Result<[f64; 2], AlignError> {
        let x = c.intrinsics.matrix() * d;
        if x.z.abs() < 1e-12 {
            return Err(degenerate("the invariant lines meet at infinity".into()));
        }
        Ok([x.x / x.z, x.y / x.z])
    };
    let mut aligned = *reference;
    aligned.elevation += de.to_degrees();
    aligned.verge_left += g_l.to_degrees();
    aligned.verge_right += g_r.to_degrees();
    Ok(AlignmentSolution {
        target_direction: [d_l.x, d_l.y, d_l.z],
        aligned_encoders: aligned,
        delta_elevation_deg: de.to_degrees(),
        delta_verge_left_deg: g_l.to_degrees(),
        delta_verge_right_deg: g_r.to_degrees(),
        predicted_elev_err_r_deg: elev_err_r.to_degrees(),
        roll_left_deg: roll(left, g_l, &v_l),
        roll_right_deg: roll(right, g_r, &v_r),
        fixation_px_left: fixation(left, &d_l)?,
        fixation_px_right: fixation(right, &d_r)?,
        invariant_lines: InvariantLines {
            pan_left: line(left, &left.pan),
            elevation_left: line(left, &left.elevation),
            pan_right: line(right, &right.pan),
            elevation_right: line(right, &right.elevation),
        },
        verge_axes_measured: left.verge.is_some() && right.verge.is_some(),
    })
}

/// The chain's pose change for pan/elevation differences (radians) from the reference:
/// `Rot(a_p, dp) Rot(a_e, de)`.
pub fn head_motion(state: &RigState, d_pan: f64, d_elev: f64) -> Option<Isometry3<f64>> {
    let (pan, elev) = axes_of(state)?;
    Some(rotation_about_line(&pan, d_pan) * rotation_about_line(&elev, d_elev))
}

/// Poses of both cameras of a capture in the reference frame, measured by resection
/// against the calibrated scene, plus the RMS residuals. `predicted` are initial guesses
/// (`ref_from_cam` for left and right).
#[derive(Debug, Clone, Copy)]
pub struct MeasuredCameras {
    /// Left camera pose in the reference frame.
    pub ref_from_left: Isometry3<f64>,
    /// Right camera pose in the reference frame.
    pub ref_from_right: Isometry3<f64>,
    /// RMS residual of the left resection, pixels.
    pub rms_left_px: f64,
    /// RMS residual of the right resection, pixels.
    pub rms_right_px: f64,
}

/// Resect both cameras of `capture` against the calibration's points.
pub fn measure_cameras(
    calib: &RigCalibration,
    capture: &StereoCapture,
    predicted_left: &Isometry3<f64>,
    predicted_right: &Isometry3<f64>,
) -> Result<MeasuredCameras, AlignError> {
    let state = &calib.bundle.state;
    let points: std::collections::HashMap<u64, Point3<f64>> = calib.points().into_iter().collect();
    let side = |obs: &[headalign_platform::TrackObservation],
                k: &Intrinsics,
                predicted: &Isometry3<f64>,
                name: &str| {
        let (mut p3, mut p2): (Vec<Point3<f64>>, Vec<Point2<f64>>) = (Vec::new(), Vec::new());
        for o in obs {
            if let Some(p) = points.get(&o.track) {
                p3.push(*p);
                p2.push(o.pixel);
            }
        }
        resect(k, &p3, &p2, &predicted.inverse(), &ResectionOptions::default())
            .step(&format!("resection of the {name} camera"))
            .map(|r| (r.cam_from_world.inverse(), r.rms_px))
    };
    let (ref_from_left, rms_left_px) = side(&capture.left, &state.left, predicted_left, "left")?;
    let (ref_from_right, rms_right_px) = side(&capture.right, &state.right, predicted_right, "right")?;
    Ok(MeasuredCameras { ref_from_left, ref_from_right, rms_left_px, rms_right_px })
}

/// Vergence axes from a view where the vergences moved (by `capture.encoders - reference`),
/// given the measured camera poses. An axis whose joint moved less than 0.2 deg is not
/// returned.
///
/// The pan and elevation turns between the two views are taken from the readings and
/// removed before the screw of each camera's motion is taken; a joint whose reading
/// changed by less than [`MOVED_DEG`] did not move (read jitter) and counts as 0. Its
/// jitter would otherwise tilt the axis by about jitter / vergence turn: readings with
/// 0.01 deg Gaussian noise and noise-free images gave vergence axes some 0.27 deg off
/// for a 3 deg turn, and aligned elevations up to 0.08 deg off (`fig5-pan-tilt
/// --encoder-noise 0.01` at 0 px).
pub fn verge_axes_from_motion(
    state: &RigState,
    reference: &Encoders,
    capture_encoders: &Encoders,
    measured: &MeasuredCameras,
) -> Result<VergeAxes, AlignError> {
    let d = |j: Joint| {
        let turn = capture_encoders.get(j) - reference.get(j);
        if turn.abs() < MOVED_DEG { 0.0 } else { turn.to_radians() }
    };
    let chain = head_motion(state, d(Joint::Pan), d(Joint::Elevation))
        .ok_or_else(|| AlignError::MissingMotion("pan and elevation axes".into()))?;
    let chain_inv = chain.inverse();
    let right0 = state.right_from_left.inverse();
    let one = |verge: Isometry3<f64>, angle: f64| -> Option<Line> {
        if angle.abs() < 0.2f64.to_radians() {
            return None;
        }
        let s = screw_from_isometry(&verge, 1e-6)?;
        Some(if s.angle * angle < 0.0 { s.axis.reversed() } else { s.axis })
    };
    let left = one(chain_inv * measured.ref_from_left, d(Joint::VergeLeft));
    // Right: ref_from_right = chain * Rot(v_r) * right0  =>  Rot(v_r) = chain^-1 ref_from_right right0^-1.
    let right = one(chain_inv * measured.ref_from_right * right0.inverse(), d(Joint::VergeRight));
    Ok(VergeAxes { left, right })
}

/// Alignment errors measured by vision: signed angles (degrees) of each optical axis out of
/// the planes perpendicular to the elevation and pan axes (our axis directions).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct MeasuredErrors {
    /// Left verge error, degrees.
    pub verge_err_l_deg: f64,
    /// Right verge error, degrees.
    pub verge_err_r_deg: f64,
    /// Left elevation error, degrees.
    pub elev_err_l_deg: f64,
    /// Right elevation error, degrees.
    pub elev_err_r_deg: f64,
}

/// Alignment errors of measured cameras, with the elevation axis moved by the pan
/// difference `d_pan` (radians) from the reference.
pub fn measured_errors(state: &RigState, measured: &MeasuredCameras, d_pan: f64) -> Option<MeasuredErrors> {
    let (pan, elev) = axes_of(state)?;
    let a_p = pan.direction.into_inner();
    let a_e = rotation_about_line(&pan, d_pan).rotation * elev.direction.into_inner();
    let zl = measured.ref_from_left.rotation * Vector3::z();
    let zr = measured.ref_from_right.rotation * Vector3::z();
    let ang = |v: Vector3<f64>, a: &Vector3<f64>| v.dot(a).clamp(-1.0, 1.0).asin().to_degrees();
    Some(MeasuredErrors {
        verge_err_l_deg: ang(zl, &a_e),
        verge_err_r_deg: ang(zr, &a_e),
        elev_err_l_deg: ang(zl, &a_p),
        elev_err_r_deg: ang(zr, &a_p),
    })
}

/// 1-sigma uncertainties of the aligned readings, degrees, propagated from the bundle
/// adjustment's covariance and, in the procedure ([`crate::procedure::alignment_sigmas_measured`]), from the
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

/// Central-difference step of the uncertainty propagations ([`crate::procedure::alignment_sigmas`],
/// [`crate::procedure::alignment_sigmas_measured`], [`crate::procedure::AxisPerturbations`],
/// [`crate::facing_plane::alignment_sigmas`] and [`crate::robot`]'s), in
/// standard deviations of the parameter moved (or units of a unit-variance mode). The
/// propagation is linear, so the step must be small against the curvature of what is
/// differentiated, yet large against the solvers' tolerances. The re-derived vergence
/// axes bend within half a sigma of some calibrations: with 0.5 (the earlier step)
/// `experiment calibration --only 3 --trials 1 --seed 273` reported an elevation sigma
/// of 2.17 deg against a bound of 0.73; with 0.25, 0.1, 0.02 and 0.005 it is 0.868,
/// 0.752, 0.751 and 0.752 deg. Over seeds 1-150 at 2 and 3 px 0.1 moved 7 of 900
/// aligned sigmas by more than 5 % and none of the RMS or coverage figures.
pub const PROPAGATION_STEP_SIGMAS: f64 = 0.1;

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// The closed-form vergence root makes the direction exactly perpendicular
        /// (1e-12: one trigonometric solve).
        #[test]
        fn zero_crossing_is_a_root(ax in -0.2..0.2f64, az in -0.2..0.2f64, zx in -0.3..0.3f64, zy in -0.3..0.3f64, ny in -0.1..0.1f64) {
            let a = Unit::new_normalize(Vector3::new(ax, -1.0, az));
            let n = Vector3::new(1.0, ny, 0.05).normalize();
            let z = Vector3::new(zx, zy, 1.0).normalize();
            let g = zero_crossing(&a, &n, &z).unwrap();
            prop_assert!(n.dot(&rotate(&a, g, &z)).abs() < 1e-12);
            prop_assert!(g.abs() < 1.0);
        }
    }

    /// The eigenvector route (invariant lines, their intersection) agrees with the closed
    /// form `K (a_e x a_p)` to 1e-6 px (4x4 eigenvectors to ~1e-15, pixels ~1e3).
    #[test]
    fn fixation_point_matches_closed_form() {
        use headalign_geometry::bundle::Motions;
        use nalgebra::{Translation3, UnitQuaternion};
        let pan = Line::new(Unit::new_normalize(Vector3::new(0.02, -1.0, 0.15)), Point3::new(0.5, 0.1, -0.2));
        let elev = Line::new(Unit::new_normalize(Vector3::new(1.0, 0.03, -0.1)), Point3::new(0.0, 0.3, -0.1));
        let state = RigState {
            left: Intrinsics::new(700.0, 720.0, 390.0, 284.0),
            right: Intrinsics::new(705.0, 716.0, 380.0, 290.0),
            left_distortion: Default::default(),
            right_distortion: Default::default(),
            right_from_left: Isometry3::from_parts(
                Translation3::new(-1.0, 0.01, 0.02),
                UnitQuaternion::from_euler_angles(0.01, 0.1, -0.02),
            ),
            motions: Motions::Joints {
                axes: vec![pan, elev],
                angles: vec![vec![0.0, 0.0]],
                commanded: vec![vec![0.0, 0.0]],
            },
            points: Vec::new(),
        };
        let (_, left, right) = invariant_lines(&state).unwrap();
        let mut d = elev.direction.cross(&pan.direction).normalize();
        if d.z < 0.0 {
            d = -d;
        }
        let l = state.left.project_unchecked(&Point3::from(d));
        let r = state.right.project_unchecked(&Point3::from(state.right_from_left.rotation * d));
        assert!((l.x - left[0]).abs() < 1e-6 && (l.y - left[1]).abs() < 1e-6, "{left:?} vs {l}");
        assert!((r.x - right[0]).abs() < 1e-6 && (r.y - right[1]).abs() < 1e-6, "{right:?} vs {r}");
        let sol = solve_alignment(&state, &VergeAxes::default(), &Encoders::default()).unwrap();
        assert_eq!(sol.fixation_px_left, left);
    }

    #[test]
    fn no_root_when_axis_is_the_normal() {
        let a = Unit::new_normalize(Vector3::new(1.0, 0.0, 0.0));
        assert!(zero_crossing(&a, &Vector3::x(), &Vector3::new(0.5, 0.0, 1.0).normalize()).is_none());
    }
}
