//! The simulated head: [`SimulatedHead`], implementing [`StereoHead`].
//!
//! It holds the scenario, the true head ([`HeadTruth`]), the scene points (world frame)
//! and the current commanded encoder readings (initially all zero). The head moves
//! exactly to the commanded readings; what is read back carries Gaussian encoder noise
//! (`encoder_noise_deg`, zero by default).
//!
//! A capture observes every scene point each camera sees (in front, inside the image,
//! between `scene_min_m` and `scene_max_m` from that camera; each camera independently).
//! Each observation is, with probability `outlier_fraction`, replaced by a uniformly
//! random pixel of the image (keeping its track id: a wrong match); otherwise Gaussian
//! noise of `noise_px` is added to each coordinate. Observations that noise pushes out of
//! the image are dropped.
//!
//! Randomness: independent ChaCha8 streams, all seeded from `scenario.seed`: head
//! geometry (0), scene (1), captures (2), encoder readings (3). The capture stream
//! advances with each capture, so the same seed and the same sequence of calls give the
//! same captures, bit for bit; reading encoders does not disturb the captures.

use headalign_geometry::camera::Intrinsics;
use headalign_platform::{Encoders, Joint, PlatformError, StereoCapture, StereoHead, TrackObservation};
use nalgebra::{Isometry3, Point2, Point3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crate::SimError;
use crate::kinematics::HeadTruth;
use crate::scenario::Scenario;
use crate::scene::{ScenePoint, generate_scene, pixel_in_image, visible_pixel};

/// Commanded encoder readings must lie in `+-JOINT_RANGE_DEG`.
pub const JOINT_RANGE_DEG: f64 = 180.0;

const STREAM_GEOMETRY: u64 = 0;
const STREAM_SCENE: u64 = 1;
const STREAM_CAPTURE: u64 = 2;
const STREAM_ENCODERS: u64 = 3;

fn rng_stream(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(stream);
    rng
}

/// A simulated stereo pan-tilt-verge head with ground truth.
#[derive(Clone, Debug)]
pub struct SimulatedHead {
    scenario: Scenario,
    truth: HeadTruth,
    scene: Vec<ScenePoint>,
    encoders: Encoders,
    capture_rng: ChaCha8Rng,
    encoder_rng: ChaCha8Rng,
}

impl SimulatedHead {
    /// Build the head of a scenario: validate it, draw the head geometry and zero offsets,
    /// build the scene. Initial encoder readings are all zero.
    pub fn new(scenario: Scenario) -> Result<Self, SimError> {
        scenario.validate()?;
        let truth = HeadTruth::draw(&scenario, &mut rng_stream(scenario.seed, STREAM_GEOMETRY));
        let scene = generate_scene(&scenario, &truth, &mut rng_stream(scenario.seed, STREAM_SCENE))?;
        Ok(Self {
            capture_rng: rng_stream(scenario.seed, STREAM_CAPTURE),
            encoder_rng: rng_stream(scenario.seed, STREAM_ENCODERS),
            scenario,
            truth,
            scene,
            encoders: Encoders::default(),
        })
    }

    /// The scenario this head was built from.
    pub fn scenario(&self) -> &Scenario {
        &self.scenario
    }

    /// The ground truth (zero offsets, intrinsics, axes, camera mounting).
    pub fn truth(&self) -> &HeadTruth {
        &self.truth
    }

    /// The exact current (commanded) encoder readings, without reading noise.
    pub fn encoders(&self) -> Encoders {
        self.encoders
    }

    /// Camera poses `(world_from_left, world_from_right)` at the given readings.
    pub fn world_from_cameras(&self, enc: &Encoders) -> (Isometry3<f64>, Isometry3<f64>) {
        self.truth.world_from_cameras(enc)
    }

    /// The scene points with their track ids, world frame.
    pub fn scene_points(&self) -> &[ScenePoint] {
        &self.scene
    }

    /// Exact (noise-free, outlier-free) observations at the given readings; the RNG is not
    /// touched. For tests and experiments.
    pub fn exact_capture(&self, enc: &Encoders) -> StereoCapture {
        let (world_from_left, world_from_right) = self.world_from_cameras(enc);
        let observe = |k: &Intrinsics, world_from_cam: &Isometry3<f64>| {
            let cam_from_world = world_from_cam.inverse();
            self.scene
                .iter()
                .filter_map(|(track, p)| {
                    self.visible(k, &cam_from_world, p).map(|pixel| TrackObservation { track: *track, pixel })
                })
                .collect()
        };
        StereoCapture {
            encoders: *enc,
            image_size: self.scenario.image_size,
            left: observe(&self.truth.left, &world_from_left),
            right: observe(&self.truth.right, &world_from_right),
        }
    }

    fn visible(
        &self,
        k: &Intrinsics,
        cam_from_world: &Isometry3<f64>,
        p: &Point3<f64>,
    ) -> Option<Point2<f64>> {
        let s = &self.scenario;
        visible_pixel(k, cam_from_world, p, s.image_size, s.scene_min_m, s.scene_max_m)
    }

    /// Noisy observations of one camera, advancing the capture RNG.
    fn observe_noisy(&mut self, k: &Intrinsics, world_from_cam: &Isometry3<f64>) -> Vec<TrackObservation> {
        let cam_from_world = world_from_cam.inverse();
        let [w, h] = self.scenario.image_size;
        let (w, h) = (f64::from(w), f64::from(h));
        let sigma = self.scenario.noise_px;
        let outlier_fraction = self.scenario.outlier_fraction;
        let mut out = Vec::new();
        for i in 0..self.scene.len() {
            let (track, p) = self.scene[i];
            let Some(exact) = self.visible(k, &cam_from_world, &p) else { continue };
            let rng = &mut self.capture_rng;
            let pixel = if rng.random::<f64>() < outlier_fraction {
                Point2::new(rng.random::<f64>() * w - 0.5, rng.random::<f64>() * h - 0.5)
            } else if sigma > 0.0 {
                let dx: f64 = rng.sample(StandardNormal);
                let dy: f64 = rng.sample(StandardNormal);
                Point2::new(exact.x + sigma * dx, exact.y + sigma * dy)
            } else {
                exact
            };
            if pixel_in_image(&pixel, self.scenario.image_size) {
                out.push(TrackObservation { track, pixel });
            }
        }
        out
    }
}

impl StereoHead for SimulatedHead {
    fn image_size(&self) -> [u32; 2] {
        self.scenario.image_size
    }

    fn read_encoders(&mut self) -> Result<Encoders, PlatformError> {
        let sigma = self.scenario.encoder_noise_deg;
        let mut enc = self.encoders;
        if sigma > 0.0 {
            for joint in Joint::ALL {
                let n: f64 = self.encoder_rng.sample(StandardNormal);
                *enc.get_mut(joint) += sigma * n;
            }
        }
        Ok(enc)
    }

    fn move_to(&mut self, target: &Encoders) -> Result<(), PlatformError> {
        if !target.is_finite() {
            return Err(PlatformError::InvalidCommand(format!("non-finite encoder target {target:?}")));
        }
        for joint in Joint::ALL {
            let v = target.get(joint);
            if v.abs() > JOINT_RANGE_DEG {
                return Err(PlatformError::OutOfRange {
                    joint,
                    target_deg: v,
                    min_deg: -JOINT_RANGE_DEG,
                    max_deg: JOINT_RANGE_DEG,
                });
            }
        }
        self.encoders = *target;
        Ok(())
    }

    fn capture(&mut self) -> Result<StereoCapture, PlatformError> {
        let encoders = self.read_encoders()?;
        let (world_from_left, world_from_right) = self.world_from_cameras(&self.encoders);
        let (k_left, k_right) = (self.truth.left, self.truth.right);
        let left = self.observe_noisy(&k_left, &world_from_left);
        let right = self.observe_noisy(&k_right, &world_from_right);
        Ok(StereoCapture { encoders, image_size: self.scenario.image_size, left, right })
    }
}
