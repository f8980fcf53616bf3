//! True head geometry and forward kinematics.
//!
//! Frames: the world is the robot frame, origin on the pan axis at the ground, x right,
//! y down (gravity +y), z forward. Cameras are x right, y down, z forward; at zero joint
//! angles and without mounting errors a camera frame is parallel to the world frame.
//!
//! The chain (`docs/conventions.md#head-kinematics`), every axis stored as a directed [`Line`] in the world
//! frame at zero joint angles:
//! - **pan**: exactly vertical through the origin, direction **up** (`-y`);
//! - **elevation**: through `(0, -head_height_m, 0)`, direction nominally **right**
//!   (`+x`), tilted about the forward axis by up to `elevation_tilt_max_deg` out of the
//!   plane perpendicular to the pan axis;
//! - **left / right vergence**: through `(-+baseline_m/2, -(head_height_m +
//!   elevation_below_cameras_m), 0)`, direction nominally **down** in the head (`+y`,
//!   made exactly perpendicular to the elevation axis), then tilted towards the elevation
//!   axis by up to `verge_tilt_max_deg` (out of perpendicular) and leaned forward/back by
//!   up to the same angle (which keeps it perpendicular);
//! - **camera**: centre `camera_forward_offset_m` in front (+z) of its vergence axis at
//!   the cameras' height, rotated by a random mounting rotation (uniform axis, angle
//!   uniform in `[0, mount_rotation_max_deg]`).
//!
//! Forward kinematics is a product of exponentials:
//! `world_from_cam(enc) = Rot(L_pan, tp) Rot(L_elev, te) Rot(L_verge, tv) world_from_cam_at_zero`
//! with the true joint angle `t = encoder - zero_offset` (degrees in the API, radians
//! inside) and `Rot` right-handed about the stored direction.
//!
//! **Sign conventions** that follow from the stored directions (right-hand rule):
//! - positive **pan** turns the head to the **left** (counter-clockwise seen from above);
//! - positive **elevation** tilts the cameras **up**;
//! - positive **vergence** turns a camera to the **right** (so it converges the left
//!   camera and diverges the right one).
//!
//! With these, the error metrics (see [`crate::metrics`]) grow with their joint:
//! `verge_err = asin(optical . elevation_dir)` is positive when a camera looks right of
//! the plane perpendicular to the elevation axis, `elev_err = asin(optical . pan_dir)` is
//! positive when it looks up; to first order `err = angle - aligned angle`.
//!
//! Pitfall: the vergence error depends only on the vergence angle (pan and elevation move
//! the elevation axis with the camera), the elevation error on elevation and vergence;
//! [`HeadTruth::aligned_encoders`] solves them in that order, in closed form.

use headalign_geometry::camera::Intrinsics;
use headalign_geometry::so3::{Line, rotation_about_line};
use headalign_platform::{Encoders, Joint};
use nalgebra::{Isometry3, Point3, Translation3, Unit, UnitQuaternion, Vector3};
use rand::RngExt;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, UnitSphere};
use serde::{Deserialize, Serialize};

use crate::scenario::Scenario;

/// Everything true about the head that alignment tries to find. World frame, zero joint
/// angles; angles in degrees.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HeadTruth {
    /// Encoder readings at zero true joint angle (the unknowns of alignment).
    pub zero_offsets: Encoders,
    /// True left intrinsics.
    pub left: Intrinsics,
    /// True right intrinsics.
    pub right: Intrinsics,
    /// Pan axis, world frame (fixed): direction up.
    pub pan_axis: Line,
    /// Elevation axis in the world at zero joint angles: direction nominally right.
    pub elevation_axis: Line,
    /// Left vergence axis in the world at zero joint angles: direction nominally down.
    pub verge_left_axis: Line,
    /// Right vergence axis in the world at zero joint angles: direction nominally down.
    pub verge_right_axis: Line,
    /// Left camera pose at zero joint angles.
    pub world_from_left_at_zero: Isometry3<f64>,
    /// Right camera pose at zero joint angles.
    pub world_from_right_at_zero: Isometry3<f64>,
    /// Drawn tilt of the elevation axis out of perpendicular to the pan axis, degrees:
    /// the axis direction is `(cos a, sin a, 0)`, so positive tilts its right end down
    /// (`asin(elevation_dir . pan_dir) = -elevation_tilt_deg`).
    pub elevation_tilt_deg: f64,
    /// Drawn tilts of the vergence axes (left, right) out of perpendicular to the
    /// elevation axis, degrees: `asin(verge_dir . elevation_dir)`.
    pub verge_tilt_deg: [f64; 2],
    /// Angles of the mounting rotations (left, right), degrees.
    pub mount_rotation_deg: [f64; 2],
}

/// Uniform in `+-max` (no panic when `max` is zero).
fn symmetric(rng: &mut ChaCha8Rng, max: f64) -> f64 {
    max * (2.0 * rng.random::<f64>() - 1.0)
}

/// A random rotation: uniform axis, angle uniform in `[0, max_rad]`.
fn random_rotation(rng: &mut ChaCha8Rng, max_rad: f64) -> UnitQuaternion<f64> {
    let [x, y, z]: [f64; 3] = UnitSphere.sample(rng);
    let axis = Unit::new_normalize(Vector3::new(x, y, z));
    let angle = max_rad * rng.random::<f64>();
    UnitQuaternion::from_axis_angle(&axis, angle)
}

impl HeadTruth {
    /// Draw the head of a scenario (zero offsets, tilts, mounting) from `rng`.
    /// The scenario is assumed valid.
    pub fn draw(scenario: &Scenario, rng: &mut ChaCha8Rng) -> Self {
        let zero_offsets = Encoders {
            pan: symmetric(rng, scenario.pan_zero_max_deg),
            elevation: symmetric(rng, scenario.elevation_zero_max_deg),
            verge_left: symmetric(rng, scenario.verge_zero_max_deg),
            verge_right: symmetric(rng, scenario.verge_zero_max_deg),
        };
        let elevation_tilt_deg = symmetric(rng, scenario.elevation_tilt_max_deg);
        let mut verge_draws = [[0.0; 2]; 2];
        for d in &mut verge_draws {
            *d = [symmetric(rng, scenario.verge_tilt_max_deg), symmetric(rng, scenario.verge_tilt_max_deg)];
        }
        let mount_max = scenario.mount_rotation_max_deg.to_radians();
        let mount_left = random_rotation(rng, mount_max);
        let mount_right = random_rotation(rng, mount_max);

        let pan_axis = Line::new(-Vector3::y_axis(), Point3::origin());
        let a = elevation_tilt_deg.to_radians();
        let elev_dir = Unit::new_normalize(Vector3::new(a.cos(), a.sin(), 0.0));
        let elevation_axis = Line::new(elev_dir, Point3::new(0.0, -scenario.head_height_m, 0.0));

        let camera_y = -(scenario.head_height_m + scenario.elevation_below_cameras_m);
        let e = elev_dir.into_inner();
        let down = Vector3::y();
        let nominal = Unit::new_normalize(down - e * e.dot(&down));
        let verge_axis = |x: f64, [tilt_deg, lean_deg]: [f64; 2]| {
            let (b, g) = (tilt_deg.to_radians(), lean_deg.to_radians());
            // Lean about the elevation axis keeps perpendicularity; then tilt towards it.
            let leaned = UnitQuaternion::from_axis_angle(&elev_dir, g) * nominal.into_inner();
            let dir = Unit::new_normalize(leaned * b.cos() + e * b.sin());
            Line::new(dir, Point3::new(x, camera_y, 0.0))
        };
        let half = 0.5 * scenario.baseline_m;
        let verge_left_axis = verge_axis(-half, verge_draws[0]);
        let verge_right_axis = verge_axis(half, verge_draws[1]);
        let cam = |x: f64, mount: UnitQuaternion<f64>| {
            Isometry3::from_parts(Translation3::new(x, camera_y, scenario.camera_forward_offset_m), mount)
        };
        Self {
            zero_offsets,
            left: scenario.left,
            right: scenario.right,
            pan_axis,
            elevation_axis,
            verge_left_axis,
            verge_right_axis,
            world_from_left_at_zero: cam(-half, mount_left),
            world_from_right_at_zero: cam(half, mount_right),
            elevation_tilt_deg,
            verge_tilt_deg: [verge_draws[0][0], verge_draws[1][0]],
            mount_rotation_deg: [mount_left.angle().to_degrees(), mount_right.angle().to_degrees()],
        }
    }

    /// True joint angle of one joint, radians: `(encoder - zero_offset)` converted.
    pub fn joint_angle_rad(&self, enc: &Encoders, joint: Joint) -> f64 {
        (enc.get(joint) - self.zero_offsets.get(joint)).to_radians()
    }

    /// Camera poses `(world_from_left, world_from_right)` at the given encoder readings.
    pub fn world_from_cameras(&self, enc: &Encoders) -> (Isometry3<f64>, Isometry3<f64>) {
        let world_from_elev_moved =
            rotation_about_line(&self.pan_axis, self.joint_angle_rad(enc, Joint::Pan))
                * rotation_about_line(&self.elevation_axis, self.joint_angle_rad(enc, Joint::Elevation));
        let left = world_from_elev_moved
            * rotation_about_line(&self.verge_left_axis, self.joint_angle_rad(enc, Joint::VergeLeft))
            * self.world_from_left_at_zero;
        let right = world_from_elev_moved
            * rotation_about_line(&self.verge_right_axis, self.joint_angle_rad(enc, Joint::VergeRight))
            * self.world_from_right_at_zero;
        (left, right)
    }

    /// A joint's axis in the world frame at the given encoder readings (each axis is moved
    /// by the joints before it in the chain).
    pub fn axis_in_world(&self, joint: Joint, enc: &Encoders) -> Line {
        let pan = rotation_about_line(&self.pan_axis, self.joint_angle_rad(enc, Joint::Pan));
        let pan_elev =
            pan * rotation_about_line(&self.elevation_axis, self.joint_angle_rad(enc, Joint::Elevation));
        match joint {
            Joint::Pan => self.pan_axis,
            Joint::Elevation => self.elevation_axis.transformed(&pan),
            Joint::VergeLeft => self.verge_left_axis.transformed(&pan_elev),
            Joint::VergeRight => self.verge_right_axis.transformed(&pan_elev),
        }
    }

    /// The encoder readings at which the head is aligned as far as its joints allow:
    /// both optical axes perpendicular to the (current) elevation axis and the left one
    /// perpendicular to the pan axis; pan is left at its zero offset. The right camera's
    /// elevation error is then whatever its mounting leaves (no joint corrects it).
    ///
    /// Closed form, choosing the solution nearest zero joint angle. If an axis is tilted
    /// so far that no solution exists (impossible for tilts under 45 deg and mounting
    /// under 45 deg combined), the nearest angle is returned.
    pub fn aligned_encoders(&self) -> Encoders {
        let z = Vector3::z();
        let e = self.elevation_axis.direction.into_inner();
        let p = self.pan_axis.direction.into_inner();
        let optical_left = self.world_from_left_at_zero.rotation * z;
        let optical_right = self.world_from_right_at_zero.rotation * z;
        let vl = self.verge_left_axis.direction.into_inner();
        let vr = self.verge_right_axis.direction.into_inner();
        let theta_vl = angle_to_perpendicular(&vl, &optical_left, &e);
        let theta_vr = angle_to_perpendicular(&vr, &optical_right, &e);
        let optical_left_verged =
            UnitQuaternion::from_axis_angle(&self.verge_left_axis.direction, theta_vl) * optical_left;
        let theta_e = angle_to_perpendicular(&e, &optical_left_verged, &p);
        let z0 = &self.zero_offsets;
        Encoders {
            pan: z0.pan,
            elevation: z0.elevation + theta_e.to_degrees(),
            verge_left: z0.verge_left + theta_vl.to_degrees(),
            verge_right: z0.verge_right + theta_vr.to_degrees(),
        }
    }
}

/// The angle `t` nearest zero (radians, right-handed about the unit `axis`) for which the
/// rotated unit vector `R(axis, t) v` is perpendicular to `target`.
///
/// Rodrigues: `(R v) . target = A cos t + B sin t + C` with `A = v.t - (a.v)(a.t)`,
/// `B = (a x v).t`, `C = (a.v)(a.t)`; so `cos(t - phi) = -C / hypot(A, B)`.
pub(crate) fn angle_to_perpendicular(axis: &Vector3<f64>, v: &Vector3<f64>, target: &Vector3<f64>) -> f64 {
    let av = axis.dot(v);
    let at = axis.dot(target);
    let a = v.dot(target) - av * at;
    let b = axis.cross(v).dot(target);
    let c = av * at;
    let r = a.hypot(b);
    if r < 1e-300 {
        return 0.0;
    }
    let phi = b.atan2(a);
    let delta = (-c / r).clamp(-1.0, 1.0).acos();
    let wrap = |t: f64| {
        let t = (t + std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI) - std::f64::consts::PI;
        if t.is_finite() { t } else { 0.0 }
    };
    let (t1, t2) = (wrap(phi + delta), wrap(phi - delta));
    if t1.abs() <= t2.abs() { t1 } else { t2 }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::SeedableRng;

    /// A head with no axis tilts and no mounting rotation.
    pub(crate) fn ideal_scenario() -> Scenario {
        Scenario {
            mount_rotation_max_deg: 0.0,
            elevation_tilt_max_deg: 0.0,
            verge_tilt_max_deg: 0.0,
            ..Scenario::default()
        }
    }

    fn truth_of(s: &Scenario) -> HeadTruth {
        HeadTruth::draw(s, &mut ChaCha8Rng::seed_from_u64(s.seed))
    }

    #[test]
    fn ideal_head_at_zero_angles_looks_forward_and_level() {
        let s = ideal_scenario();
        let t = truth_of(&s);
        let (l, r) = t.world_from_cameras(&t.zero_offsets);
        let cam_y = -(s.head_height_m + s.elevation_below_cameras_m);
        assert!((l.translation.vector - Vector3::new(-0.125, cam_y, 0.03)).norm() < 1e-12);
        assert!((r.translation.vector - Vector3::new(0.125, cam_y, 0.03)).norm() < 1e-12);
        assert!(l.rotation.angle() < 1e-12 && r.rotation.angle() < 1e-12);
        assert_eq!(t.aligned_encoders(), t.zero_offsets);
    }

    #[test]
    fn joint_signs() {
        let t = truth_of(&ideal_scenario());
        let z0 = t.zero_offsets;
        let optical_left = |enc: &Encoders| t.world_from_cameras(enc).0.rotation * Vector3::z();
        // Positive pan turns left (-x).
        assert!(optical_left(&z0.moved(Joint::Pan, 10.0)).x < -0.17);
        // Positive elevation tilts up (-y).
        assert!(optical_left(&z0.moved(Joint::Elevation, 10.0)).y < -0.17);
        // Positive vergence turns right (+x), for both cameras.
        assert!(optical_left(&z0.moved(Joint::VergeLeft, 10.0)).x > 0.17);
        let optical_right =
            t.world_from_cameras(&z0.moved(Joint::VergeRight, 10.0)).1.rotation * Vector3::z();
        assert!(optical_right.x > 0.17);
        // Encoder minus zero offset is the joint angle.
        assert!(
            (t.joint_angle_rad(&z0.moved(Joint::Pan, 90.0), Joint::Pan) - std::f64::consts::FRAC_PI_2).abs()
                < 1e-15
        );
    }

    #[test]
    fn drawn_geometry_respects_the_scenario() {
        for seed in 1..=20 {
            let s = Scenario::default().with_seed(seed);
            let t = truth_of(&s);
            assert!(t.zero_offsets.pan.abs() <= s.pan_zero_max_deg);
            assert!(t.zero_offsets.elevation.abs() <= s.elevation_zero_max_deg);
            assert!(t.zero_offsets.verge_left.abs() <= s.verge_zero_max_deg);
            assert!(t.zero_offsets.verge_right.abs() <= s.verge_zero_max_deg);
            let p = t.pan_axis.direction.into_inner();
            let e = t.elevation_axis.direction.into_inner();
            assert!((p - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-15);
            // Elevation tilt out of perpendicular to pan, as drawn and bounded.
            let tilt = e.dot(&p).asin().to_degrees();
            assert!((tilt + t.elevation_tilt_deg).abs() < 1e-9, "{tilt} vs {}", t.elevation_tilt_deg);
            assert!(tilt.abs() <= s.elevation_tilt_max_deg + 1e-12);
            assert!((t.elevation_axis.distance_to(&Point3::new(0.0, -s.head_height_m, 0.0))).abs() < 1e-12);
            for (axis, drawn) in
                [(&t.verge_left_axis, t.verge_tilt_deg[0]), (&t.verge_right_axis, t.verge_tilt_deg[1])]
            {
                let v = axis.direction.into_inner();
                let out_of_perp = v.dot(&e).asin().to_degrees();
                assert!((out_of_perp - drawn).abs() < 1e-9);
                assert!(out_of_perp.abs() <= s.verge_tilt_max_deg + 1e-12);
                assert!(v.y > 0.99, "verge axes point down: {v}");
            }
            for m in t.mount_rotation_deg {
                assert!((0.0..=s.mount_rotation_max_deg).contains(&m));
            }
            // Camera centres are off their vergence axes, by about the forward offset.
            let cl = Point3::from(t.world_from_left_at_zero.translation.vector);
            let cr = Point3::from(t.world_from_right_at_zero.translation.vector);
            for d in [t.verge_left_axis.distance_to(&cl), t.verge_right_axis.distance_to(&cr)] {
                assert!((d - s.camera_forward_offset_m).abs() < 1e-3, "{d}");
            }
        }
    }

    #[test]
    fn joints_rotate_about_their_axes() {
        let t = truth_of(&Scenario::default().with_seed(3));
        let base = Encoders { pan: 5.0, elevation: -4.0, verge_left: 2.0, verge_right: -3.0 };
        let (l0, r0) = t.world_from_cameras(&base);
        // Moving a vergence joint keeps that camera's distance to its (current) axis.
        let axis_l = t.axis_in_world(Joint::VergeLeft, &base);
        let (l1, r1) = t.world_from_cameras(&base.moved(Joint::VergeLeft, 7.0));
        let c = |iso: &Isometry3<f64>| Point3::from(iso.translation.vector);
        assert!((axis_l.distance_to(&c(&l0)) - axis_l.distance_to(&c(&l1))).abs() < 1e-12);
        assert!((r0.to_homogeneous() - r1.to_homogeneous()).norm() < 1e-15, "right camera must not move");
        // Moving elevation rotates both cameras about the current elevation axis.
        let axis_e = t.axis_in_world(Joint::Elevation, &base);
        let (l2, r2) = t.world_from_cameras(&base.moved(Joint::Elevation, 7.0));
        assert!((axis_e.distance_to(&c(&l0)) - axis_e.distance_to(&c(&l2))).abs() < 1e-12);
        assert!((axis_e.distance_to(&c(&r0)) - axis_e.distance_to(&c(&r2))).abs() < 1e-12);
        let rel = l2 * l0.inverse();
        let w = rel.rotation.scaled_axis();
        assert!((w - axis_e.direction.into_inner() * 7f64.to_radians()).norm() < 1e-12);
    }

    proptest! {
        #[test]
        fn angle_to_perpendicular_solves(ax in -1.0..1.0f64, ay in 0.5..1.0f64, vx in -0.3..0.3f64, tz in -0.2..0.2f64) {
            let axis = Vector3::new(ax * 0.1, ay, 0.05).normalize();
            let v = Vector3::new(vx, 0.05, 1.0).normalize();
            let target = Vector3::new(1.0, 0.1, tz).normalize();
            let theta = angle_to_perpendicular(&axis, &v, &target);
            let rotated = UnitQuaternion::from_axis_angle(&Unit::new_normalize(axis), theta) * v;
            prop_assert!(rotated.dot(&target).abs() < 1e-12);
            prop_assert!(theta.abs() < 1.0);
        }
    }
}
