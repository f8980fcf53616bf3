//! The simulated robot: a tricycle AGV carrying the simulated head, implementing
//! [`StereoHead`] and [`ImagingHead`] (delegated to [`SimulatedHead`]: point observations,
//! or renders of the textured room seen from the robot's current pose) and [`Vehicle`].
//!
//! Geometry (robot frame = the frame of [`crate::HeadTruth`]: origin on the pan axis at
//! the ground, x right, y down, z forward; `docs/conventions.md#the-robot-and-steering`):
//! - the rear axle is the line `z = -rear_axle_behind_pan_m` on the ground, along x;
//!   its centre `a = (0, 0, -rear_axle_behind_pan_m)`;
//! - the steered front wheel stands `wheelbase_m` in front of the rear-axle centre; the
//!   robot's direction of travel with the wheel straight is `+z`;
//! - the true steering angle is `sigma = encoder - steer_zero_deg` (positive turns left,
//!   the pan joint's sign); the robot then turns about the vertical line through
//!   `c = a + (-wheelbase / tan sigma, 0, 0)`, the intersection of the rear-axle line and
//!   the front wheel's axle line, by `phi = d tan(sigma) / wheelbase` (right-handed about
//!   up, `-y`) when the rear-axle centre travels the arc length `d`. `sigma = 0` is a
//!   straight translation by `d` along `+z`.
//!
//! **The floor** is tilted against the head: the floor's normal in the robot frame is
//! `head_from_floor * up`, the pan axis tilted `pan_tilt_deg` ([`crate::Scenario`]) from
//! it about a horizontal axis of azimuth drawn uniformly (robot stream, after the steering
//! zero). Everything above (rear axle, forward direction `+z`, turning centres, `up`) is
//! stated in the floor frame, which shares the origin (the pan axis' foot) and is carried
//! into the robot frame by that rotation: a drive is `head_from_floor * M *
//! head_from_floor^-1` with `M` the planar motion above, a rotation about the floor normal
//! and a translation perpendicular to it; the direction of travel with the wheel straight
//! is `head_from_floor * z`. The pan error is measured from that direction
//! ([`SimulatedRobot::pan_err_deg`]).
//!
//! The head rides on the robot: its pose in the scene is `world_from_robot` composed with
//! the head's kinematics. The robot starts at the identity, so every capture before the
//! first drive is exactly what a bare [`SimulatedHead`] gives (the verge/tilt stage is
//! unchanged). The steering zero offset is drawn from its own random stream (4), so the
//! head, scene and captures are those of the same seed without a robot. Motion is exact
//! (no wheel slip); reading the steering encoder is exact.

use headalign_geometry::so3::{Line, rotation_about_line};
use headalign_platform::{
    Encoders, ImagingHead, PlatformError, StereoCapture, StereoHead, StereoImages, Vehicle,
};
use nalgebra::{Isometry3, Point3, Translation3, Unit, UnitQuaternion, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::SimError;
use crate::head::SimulatedHead;
use crate::scenario::Scenario;

const STREAM_ROBOT: u64 = 4;

/// Steering commands must lie in `+-STEER_RANGE_DEG` (encoder degrees).
pub const STEER_RANGE_DEG: f64 = 60.0;
/// A single drive may not exceed this distance, metres.
pub const MAX_DRIVE_M: f64 = 5.0;

/// The true robot: what steering alignment tries to find.
#[derive(Clone, Debug, PartialEq)]
pub struct RobotTruth {
    /// Steering encoder reading at which the wheel is truly straight, degrees.
    pub steer_zero_deg: f64,
    /// Rear-axle line to front wheel, metres.
    pub wheelbase_m: f64,
    /// Rear-axle centre behind the pan axis, metres.
    pub rear_axle_behind_pan_m: f64,
    /// The floor frame in the robot (head) frame (module docs): the identity when the pan
    /// axis is the floor normal.
    pub head_from_floor: UnitQuaternion<f64>,
}

impl RobotTruth {
    /// The rigid motion `robot_before_from_robot_after` of a drive of `distance_m` (arc
    /// length of the rear-axle centre) at true steering angle `sigma_deg`, robot frame.
    pub fn motion(&self, sigma_deg: f64, distance_m: f64) -> Isometry3<f64> {
        let q = Isometry3::from_parts(Translation3::identity(), self.head_from_floor);
        q * self.floor_motion(sigma_deg, distance_m) * q.inverse()
    }

    /// The drive of [`RobotTruth::motion`] in the floor frame (module docs).
    fn floor_motion(&self, sigma_deg: f64, distance_m: f64) -> Isometry3<f64> {
        let tan_s = sigma_deg.to_radians().tan();
        if tan_s.abs() < 1e-12 {
            return Isometry3::from_parts(Translation3::new(0.0, 0.0, distance_m), Default::default());
        }
        let centre = self.floor_turning_centre(sigma_deg).unwrap_or_else(Point3::origin);
        let phi = distance_m * tan_s / self.wheelbase_m;
        rotation_about_line(&Line::new(-Vector3::y_axis(), centre), phi)
    }

    /// The turning centre (on the ground) of true steering angle `sigma_deg`, robot frame;
    /// `None` when the wheel is straight (centre at infinity).
    pub fn turning_centre(&self, sigma_deg: f64) -> Option<Point3<f64>> {
        self.floor_turning_centre(sigma_deg).map(|c| self.head_from_floor * c)
    }

    fn floor_turning_centre(&self, sigma_deg: f64) -> Option<Point3<f64>> {
        let tan_s = sigma_deg.to_radians().tan();
        (tan_s.abs() >= 1e-12)
            .then(|| Point3::new(-self.wheelbase_m / tan_s, 0.0, -self.rear_axle_behind_pan_m))
    }

    /// The floor's normal in the robot frame (up).
    pub fn floor_normal(&self) -> Unit<Vector3<f64>> {
        self.head_from_floor * -Vector3::y_axis()
    }

    /// Angle of the pan axis (`-y`) from the floor's normal, degrees.
    pub fn pan_tilt_deg(&self) -> f64 {
        self.floor_normal().angle(&-Vector3::y_axis()).to_degrees()
    }

    /// The robot's direction of travel with the wheel straight, robot frame (unit).
    pub fn travel_direction(&self) -> Vector3<f64> {
        self.head_from_floor * Vector3::z()
    }
}

/// The rotation that tilts the floor frame `tilt_deg` against the robot frame about the
/// horizontal axis at azimuth `azimuth_rad` (from `+x` towards `+z`).
fn floor_tilt(tilt_deg: f64, azimuth_rad: f64) -> UnitQuaternion<f64> {
    let axis = Unit::new_normalize(Vector3::new(azimuth_rad.cos(), 0.0, azimuth_rad.sin()));
    UnitQuaternion::from_axis_angle(&axis, tilt_deg.to_radians())
}

/// A simulated robot carrying the simulated head.
#[derive(Clone, Debug)]
pub struct SimulatedRobot {
    head: SimulatedHead,
    truth: RobotTruth,
    steering_deg: f64,
    odometer_m: f64,
}

impl SimulatedRobot {
    /// Build the robot and its head from a scenario; steering encoder at zero, robot at
    /// the identity pose.
    pub fn new(scenario: Scenario) -> Result<Self, SimError> {
        let head = SimulatedHead::new(scenario.clone())?;
        let mut rng = ChaCha8Rng::seed_from_u64(scenario.seed);
        rng.set_stream(STREAM_ROBOT);
        let steer_zero_deg = scenario.steer_zero_max_deg * (2.0 * rng.random::<f64>() - 1.0);
        // Drawn after the steering zero, so that zero is the same with or without a tilt.
        let azimuth = std::f64::consts::TAU * rng.random::<f64>();
        let truth = RobotTruth {
            steer_zero_deg,
            wheelbase_m: scenario.wheelbase_m,
            rear_axle_behind_pan_m: scenario.rear_axle_behind_pan_m,
            head_from_floor: floor_tilt(scenario.pan_tilt_deg, azimuth),
        };
        Ok(Self { head, truth, steering_deg: 0.0, odometer_m: 0.0 })
    }

    /// The head (ground truth, metrics).
    pub fn head(&self) -> &SimulatedHead {
        &self.head
    }

    /// The head, mutably.
    pub fn head_mut(&mut self) -> &mut SimulatedHead {
        &mut self.head
    }

    /// The true robot.
    pub fn truth(&self) -> &RobotTruth {
        &self.truth
    }

    /// Current steering encoder reading (exact).
    pub fn steering_encoder_deg(&self) -> f64 {
        self.steering_deg
    }

    /// Total distance driven (absolute), metres.
    pub fn odometer_m(&self) -> f64 {
        self.odometer_m
    }

    /// Steering error at an encoder reading: the true steering angle left, degrees.
    pub fn steer_err_deg(&self, encoder_deg: f64) -> f64 {
        encoder_deg - self.truth.steer_zero_deg
    }

    /// Pan error of the head at the given head readings: the angle about the pan axis from
    /// the robot's direction of travel with the wheel straight
    /// ([`RobotTruth::travel_direction`], projected onto the plane perpendicular to the
    /// pan axis) to the head's forward direction ([`SimulatedHead::pan_err_from_deg`]).
    pub fn pan_err_deg(&self, enc: &Encoders) -> f64 {
        self.head.pan_err_from_deg(enc, &self.truth.travel_direction())
    }
}

impl StereoHead for SimulatedRobot {
    fn image_size(&self) -> [u32; 2] {
        self.head.image_size()
    }
    fn read_encoders(&mut self) -> Result<Encoders, PlatformError> {
        self.head.read_encoders()
    }
    fn move_to(&mut self, target: &Encoders) -> Result<(), PlatformError> {
        self.head.move_to(target)
    }
    fn capture(&mut self) -> Result<StereoCapture, PlatformError> {
        self.head.capture()
    }
}

impl ImagingHead for SimulatedRobot {
    /// Renders both cameras of the head where the robot now stands (the renderer draws the
    /// same room, near panels included, from the robot pose composed with the head's
    /// kinematics; [`SimulatedHead::capture_images`]).
    fn capture_images(&mut self) -> Result<StereoImages, PlatformError> {
        self.head.capture_images()
    }
}

impl Vehicle for SimulatedRobot {
    fn drive(&mut self, distance_m: f64) -> Result<(), PlatformError> {
        if !distance_m.is_finite() || distance_m.abs() > MAX_DRIVE_M {
            return Err(PlatformError::InvalidCommand(format!(
                "drive distance must be finite and at most {MAX_DRIVE_M} m, got {distance_m}"
            )));
        }
        let sigma = self.steering_deg - self.truth.steer_zero_deg;
        let motion = self.truth.motion(sigma, distance_m);
        let pose = self.head.world_from_robot() * motion;
        self.head.set_world_from_robot(pose);
        self.odometer_m += distance_m.abs();
        Ok(())
    }

    fn steer_to(&mut self, encoder_deg: f64) -> Result<(), PlatformError> {
        if !encoder_deg.is_finite() || encoder_deg.abs() > STEER_RANGE_DEG {
            return Err(PlatformError::InvalidCommand(format!(
                "steering target must be finite and within +-{STEER_RANGE_DEG} deg, got {encoder_deg}"
            )));
        }
        self.steering_deg = encoder_deg;
        Ok(())
    }

    fn read_steering(&mut self) -> Result<f64, PlatformError> {
        Ok(self.steering_deg)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn truth(b: f64) -> RobotTruth {
        RobotTruth {
            steer_zero_deg: 2.0,
            wheelbase_m: 0.6,
            rear_axle_behind_pan_m: b,
            head_from_floor: UnitQuaternion::identity(),
        }
    }

    proptest! {
        /// The rear-axle centre moves tangentially to the forward direction at the start,
        /// the turn is about the vertical through the turning centre, and the turning
        /// centre lies on the rear-axle line (exact to rounding).
        #[test]
        fn drive_kinematics(sigma in -40.0..40.0f64, d in -1.0..1.0f64, b in -0.3..0.3f64) {
            prop_assume!(sigma.abs() > 0.5);
            let t = truth(b);
            let m = t.motion(sigma, d);
            let a = Point3::new(0.0, 0.0, -b);
            let c = t.turning_centre(sigma).unwrap();
            // Centre fixed by the motion, on the rear-axle line, on the ground.
            prop_assert!((m * c - c).norm() < 1e-12);
            prop_assert!((c.z + b).abs() < 1e-12 && c.y.abs() < 1e-15);
            // Rotation about up by d tan(s) / L.
            let phi = d * sigma.to_radians().tan() / 0.6;
            let w = m.rotation.scaled_axis();
            prop_assert!((w + Vector3::y() * phi).norm() < 1e-12);
            // Rear-axle centre travels a chord of the arc at half the heading change.
            let disp = m * a - a;
            let expected = Vector3::new(-(phi / 2.0).sin(), 0.0, (phi / 2.0).cos()) * disp.norm() * d.signum();
            prop_assert!((disp - expected).norm() < 1e-12);
        }
    }

    /// On a tilted floor every drive is a rotation about the floor normal (not the pan
    /// axis, `-y`) and a translation perpendicular to it, the turning centre is fixed by
    /// it, and the travel direction is perpendicular to the normal: exact to rounding.
    #[test]
    fn drives_are_planar_about_the_tilted_floor() {
        let t = RobotTruth { head_from_floor: floor_tilt(3.0, 1.0), ..truth(0.2) };
        let n = t.floor_normal();
        assert!((n.angle(&-Vector3::y_axis()).to_degrees() - 3.0).abs() < 1e-12);
        assert!(t.travel_direction().dot(&n).abs() < 1e-15);
        for (sigma, d) in [(10.0, 0.3), (-25.0, 0.2), (0.0, 0.1)] {
            let m = t.motion(sigma, d);
            let w = m.rotation.scaled_axis();
            assert!((w - n.into_inner() * w.dot(&n)).norm() < 1e-12, "{sigma}");
            let p = Point3::new(0.1, -1.1, 0.2);
            assert!((m * p - p).dot(&n).abs() < 1e-12, "{sigma}");
            if let Some(c) = t.turning_centre(sigma) {
                assert!((m * c - c).norm() < 1e-12);
            }
        }
        let straight = t.motion(0.0, 0.1).translation.vector;
        assert!((straight - t.travel_direction() * 0.1).norm() < 1e-15);
    }

    #[test]
    fn straight_drive_and_commands() {
        let mut r = SimulatedRobot::new(Scenario { pan_tilt_deg: 0.0, ..Scenario::default() }).unwrap();
        assert!(r.truth().steer_zero_deg.abs() <= 5.0);
        let z = r.truth().steer_zero_deg;
        r.steer_to(z).unwrap();
        let now = r.read_steering().unwrap();
        assert_eq!(r.steer_err_deg(now), 0.0);
        r.drive(0.1).unwrap();
        let p = r.head().world_from_robot();
        assert!((p.translation.vector - Vector3::new(0.0, 0.0, 0.1)).norm() < 1e-15);
        assert!(p.rotation.angle() < 1e-15);
        r.steer_by(3.0).unwrap();
        assert!((r.read_steering().unwrap() - z - 3.0).abs() < 1e-12);
        assert!(r.drive(f64::NAN).is_err());
        assert!(r.drive(10.0).is_err());
        assert!(r.steer_to(90.0).is_err());
        assert!((r.odometer_m() - 0.1).abs() < 1e-15);
    }

    #[test]
    fn captures_before_driving_equal_the_bare_head() {
        let s = Scenario::default().with_seed(3);
        let mut bare = SimulatedHead::new(s.clone()).unwrap();
        let mut robot = SimulatedRobot::new(s).unwrap();
        assert_eq!(bare.capture().unwrap(), robot.capture().unwrap());
        robot.drive(0.1).unwrap();
        assert_ne!(bare.capture().unwrap(), robot.capture().unwrap());
    }
}
