//! The simulated head: [`SimulatedHead`], implementing [`StereoHead`].
//!
//! It holds the scenario, the true head ([`HeadTruth`]), the scene points (world frame)
//! and the current commanded encoder readings (initially all zero). The head moves
//! exactly to the commanded readings; what is read back carries Gaussian encoder noise
//! (`encoder_noise_deg`, zero by default).
//!
//! A capture observes every scene point each camera sees (in front, inside the image,
//! between `scene_min_m` (or [`Scenario::min_range_m`] with near panels) and `scene_max_m`
//! from that camera; each camera independently).
//! Each observation is, with probability `outlier_fraction`, replaced by a uniformly
//! random pixel of the image (keeping its track id: a wrong match); otherwise Gaussian
//! noise of `noise_px` is added to each coordinate. Observations that noise pushes out of
//! the image are dropped.
//!
//! Images: [`SimulatedHead::render_stereo`] renders both cameras at the current (true)
//! pose with the textured version of the same room ([`crate::render`]); the textures are
//! baked on the first render. With a lens in `scenario.render.distortion` (the geometry
//! crate's `Distortion`, either model), the point captures use the same distorted
//! projection as the images ([`crate::render::project`]).
//!
//! Randomness: independent ChaCha8 streams, all seeded from `scenario.seed`: head
//! geometry (0), scene (1), captures (2), encoder readings (3), image noise (4),
//! textures (5). The capture stream
//! advances with each capture, so the same seed and the same sequence of calls give the
//! same captures, bit for bit; reading encoders does not disturb the captures.

use headalign_geometry::camera::Intrinsics;
use headalign_platform::{
    Encoders, ImagingHead, Joint, PlatformError, StereoCapture, StereoHead, StereoImages, TrackObservation,
};
use headalign_vision::GrayImage;
use nalgebra::{Isometry3, Point2, Point3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use std::sync::Arc;

use crate::SimError;
use crate::kinematics::HeadTruth;
use crate::render::{CameraView, RenderOptions, project, render_view};
use crate::scenario::Scenario;
use crate::scene::{Room, ScenePoint, generate_room_and_scene, pixel_in_image, visible_pixel};
use crate::texture::{TexturedScene, bake_textures_scaled};

/// Commanded encoder readings must lie in `+-JOINT_RANGE_DEG`.
pub const JOINT_RANGE_DEG: f64 = 180.0;

const STREAM_GEOMETRY: u64 = 0;
const STREAM_SCENE: u64 = 1;
const STREAM_CAPTURE: u64 = 2;
const STREAM_ENCODERS: u64 = 3;
const STREAM_RENDER: u64 = 4;
const STREAM_TEXTURE: u64 = 5;

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
    room: Room,
    textured: Option<Arc<TexturedScene>>,
    encoders: Encoders,
    capture_rng: ChaCha8Rng,
    encoder_rng: ChaCha8Rng,
    render_rng: ChaCha8Rng,
    /// Pose of the robot (the frame of [`HeadTruth`]) in the scene's world frame;
    /// identity until a [`crate::robot::SimulatedRobot`] drives it.
    world_from_robot: Isometry3<f64>,
}

impl SimulatedHead {
    /// Build the head of a scenario: validate it, draw the head geometry and zero offsets,
    /// build the scene. Initial encoder readings are all zero.
    pub fn new(scenario: Scenario) -> Result<Self, SimError> {
        scenario.validate()?;
        let truth = HeadTruth::draw(&scenario, &mut rng_stream(scenario.seed, STREAM_GEOMETRY));
        let (room, scene) =
            generate_room_and_scene(&scenario, &truth, &mut rng_stream(scenario.seed, STREAM_SCENE))?;
        Ok(Self {
            capture_rng: rng_stream(scenario.seed, STREAM_CAPTURE),
            encoder_rng: rng_stream(scenario.seed, STREAM_ENCODERS),
            render_rng: rng_stream(scenario.seed, STREAM_RENDER),
            scenario,
            truth,
            scene,
            room,
            textured: None,
            encoders: Encoders::default(),
            world_from_robot: Isometry3::identity(),
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

    /// Camera poses `(world_from_left, world_from_right)` at the given readings, in the
    /// robot frame (the scene's world frame while the robot has not moved).
    pub fn world_from_cameras(&self, enc: &Encoders) -> (Isometry3<f64>, Isometry3<f64>) {
        self.truth.world_from_cameras(enc)
    }

    /// Pose of the robot frame (the frame of [`HeadTruth`] and of
    /// [`Self::world_from_cameras`]) in the scene's world frame; identity initially.
    pub fn world_from_robot(&self) -> Isometry3<f64> {
        self.world_from_robot
    }

    /// The rendered views of a calibration session (`headalign simulate --images`): the
    /// initial view, then either the elevation and pan moved by `rotation_deg` degrees
    /// (`general` false; views `initial`, `elevation`, `pan`) or the whole rig moved by
    /// [`crate::rigmotion::general_rig_motion`] (`general`; views `initial`, `moved`).
    pub fn calibration_views(
        &mut self,
        general: bool,
        rotation_deg: f64,
    ) -> Result<Vec<(String, StereoImages)>, PlatformError> {
        let e0 = self.read_encoders()?;
        let mut views = vec![("initial".to_string(), self.capture_images()?)];
        if general {
            self.set_world_from_robot(crate::rigmotion::general_rig_motion());
            views.push(("moved".to_string(), self.capture_images()?));
        } else {
            for (name, joint) in [("elevation", Joint::Elevation), ("pan", Joint::Pan)] {
                self.move_to(&e0.moved(joint, rotation_deg))?;
                views.push((name.to_string(), self.capture_images()?));
            }
        }
        Ok(views)
    }

    /// Move the robot (and the head on it) to a new pose in the scene's world frame.
    /// Captures see the scene from there; the head's own geometry and every metric,
    /// which live in the robot frame, are unchanged.
    pub fn set_world_from_robot(&mut self, world_from_robot: Isometry3<f64>) {
        self.world_from_robot = world_from_robot;
    }

    /// Camera poses `(world_from_left, world_from_right)` in the scene's world frame (the
    /// robot pose composed with the head's kinematics).
    pub fn scene_from_cameras(&self, enc: &Encoders) -> (Isometry3<f64>, Isometry3<f64>) {
        let (l, r) = self.truth.world_from_cameras(enc);
        (self.world_from_robot * l, self.world_from_robot * r)
    }

    /// The scene points with their track ids, world frame.
    pub fn scene_points(&self) -> &[ScenePoint] {
        &self.scene
    }

    /// Exact (noise-free, outlier-free) observations at the given readings; the RNG is not
    /// touched. For tests and experiments.
    pub fn exact_capture(&self, enc: &Encoders) -> StereoCapture {
        let (world_from_left, world_from_right) = self.scene_from_cameras(enc);
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
        let distortion = &s.render.distortion;
        if distortion.is_zero() {
            return visible_pixel(k, cam_from_world, p, s.image_size, s.min_range_m(), s.scene_max_m);
        }
        let point_in_cam = cam_from_world * p;
        let distance = point_in_cam.coords.norm();
        if !(distance >= s.min_range_m() && distance <= s.scene_max_m) {
            return None;
        }
        let pixel = project(k, distortion, &point_in_cam)?;
        pixel_in_image(&pixel, s.image_size).then_some(pixel)
    }

    /// Exact pixels `(left, right)` of a world point at the given readings, through the
    /// true intrinsics and the scenario's distortion; `None` where the point is behind the
    /// camera or outside its image (no distance limits, no occlusion test). This is the
    /// projection the rendered images agree with.
    pub fn exact_pixels(
        &self,
        enc: &Encoders,
        point_in_world: &Point3<f64>,
    ) -> (Option<Point2<f64>>, Option<Point2<f64>>) {
        let (world_from_left, world_from_right) = self.scene_from_cameras(enc);
        let size = self.scenario.image_size;
        let distortion = &self.scenario.render.distortion;
        let pixel = |k: &Intrinsics, world_from_cam: &Isometry3<f64>| {
            project(k, distortion, &(world_from_cam.inverse() * point_in_world))
                .filter(|px| pixel_in_image(px, size))
        };
        (pixel(&self.truth.left, &world_from_left), pixel(&self.truth.right, &world_from_right))
    }

    /// The room the scene points lie on (walls, floor, ceiling, boxes).
    pub fn room(&self) -> &Room {
        &self.room
    }

    /// The textured room, baked on first use from the texture stream and
    /// `scenario.render` (photographs or the procedural fallback: see its report).
    pub fn textured_scene(&mut self) -> Arc<TexturedScene> {
        if let Some(t) = &self.textured {
            return t.clone();
        }
        let r = &self.scenario.render;
        let data_dir = r.resolved_data_dir();
        let scales: Vec<f64> = self
            .room
            .near_quads()
            .into_iter()
            .map(|near| if near { r.near_metres_per_texel } else { r.metres_per_texel })
            .collect();
        let mut rng = rng_stream(self.scenario.seed, STREAM_TEXTURE);
        let (quads, report) =
            bake_textures_scaled(&self.room.quads(), &scales, data_dir.as_deref(), &mut rng);
        let t = Arc::new(TexturedScene { quads, report });
        self.textured = Some(t.clone());
        t
    }

    /// Render both cameras at the current (true, commanded) pose with
    /// `scenario.render`; the noise seeds come from the image-noise stream, which advances
    /// with each call (same seed, same calls: same images).
    pub fn render_stereo(&mut self) -> Result<(GrayImage, GrayImage), SimError> {
        let seed = self.render_rng.random::<u64>();
        let (enc, options) = (self.encoders, self.scenario.render.clone());
        self.render_stereo_with(&enc, &options, seed)
    }

    /// Render both cameras at the given readings with the given options and noise seed
    /// (the left image uses `noise_seed`, the right `noise_seed + 1`); no RNG of the head
    /// advances. The textures are those of `scenario.render` (the texture fields of
    /// `options` are ignored once baked).
    pub fn render_stereo_with(
        &mut self,
        enc: &Encoders,
        options: &RenderOptions,
        noise_seed: u64,
    ) -> Result<(GrayImage, GrayImage), SimError> {
        let scene = self.textured_scene();
        let (world_from_left, world_from_right) = self.scene_from_cameras(enc);
        let size = self.scenario.image_size;
        let view = |k, world_from_cam| CameraView {
            k,
            distortion: &options.distortion,
            world_from_cam,
            image_size: size,
        };
        let left = render_view(&scene.quads, &view(&self.truth.left, &world_from_left), options, noise_seed)?;
        let right = render_view(
            &scene.quads,
            &view(&self.truth.right, &world_from_right),
            options,
            noise_seed.wrapping_add(1),
        )?;
        Ok((left, right))
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

impl ImagingHead for SimulatedHead {
    /// Renders both cameras at the current joint angles (the renderer's noise advances its
    /// own seeded stream); the readings come from [`StereoHead::read_encoders`].
    fn capture_images(&mut self) -> Result<StereoImages, PlatformError> {
        let encoders = self.read_encoders()?;
        let (left, right) =
            self.render_stereo().map_err(|e| PlatformError::Device(format!("renderer: {e}")))?;
        StereoImages::new(encoders, left, right)
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
        let (world_from_left, world_from_right) = self.scene_from_cameras(&self.encoders);
        let (k_left, k_right) = (self.truth.left, self.truth.right);
        let left = self.observe_noisy(&k_left, &world_from_left);
        let right = self.observe_noisy(&k_right, &world_from_right);
        Ok(StereoCapture { encoders, image_size: self.scenario.image_size, left, right })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::count_visible_in_both;
    use headalign_geometry::camera::ProjectiveCamera;
    use nalgebra::Vector4;

    fn quiet(seed: u64) -> Scenario {
        Scenario { seed, noise_px: 0.0, outlier_fraction: 0.0, ..Scenario::default() }
    }

    #[test]
    fn same_seed_same_captures() {
        let mut a = SimulatedHead::new(Scenario::default()).unwrap();
        let mut b = SimulatedHead::new(Scenario::default()).unwrap();
        let mut c = SimulatedHead::new(Scenario::default().with_seed(2)).unwrap();
        let moved = Encoders { pan: 3.0, ..Encoders::default() };
        for head in [&mut a, &mut b, &mut c] {
            let first = head.capture().unwrap();
            head.move_to(&moved).unwrap();
            let second = head.capture().unwrap();
            assert_ne!(first, second);
        }
        let (ca, cb) = (a.capture().unwrap(), b.capture().unwrap());
        assert_eq!(ca, cb);
        assert_ne!(ca, c.capture().unwrap());
        // Captures advance the RNG: the same view captured again differs in its noise.
        assert_ne!(ca, a.capture().unwrap());
    }

    #[test]
    fn noise_free_capture_is_exact_projection() {
        let mut head = SimulatedHead::new(quiet(3)).unwrap();
        let enc = Encoders { pan: -5.0, elevation: 2.0, verge_left: 1.0, verge_right: -1.0 };
        head.move_to(&enc).unwrap();
        let cap = head.capture().unwrap();
        assert_eq!(cap.encoders, enc);
        assert_eq!(cap, head.exact_capture(&enc));
        let (world_from_left, world_from_right) = head.world_from_cameras(&enc);
        let by_id: std::collections::HashMap<u64, Point3<f64>> =
            head.scene_points().iter().copied().collect();
        let truth = head.truth().clone();
        for (obs, k, pose) in
            [(&cap.left, &truth.left, &world_from_left), (&cap.right, &truth.right, &world_from_right)]
        {
            assert!(obs.len() > 100);
            let p = ProjectiveCamera::from_pose(k, &pose.inverse());
            for o in obs {
                let x = by_id[&o.track];
                let px = p.project(&Vector4::new(x.x, x.y, x.z, 1.0)).unwrap();
                assert!((px - o.pixel).norm() < 1e-9);
            }
        }
    }

    #[test]
    fn noise_has_its_standard_deviation_and_stays_in_the_image() {
        let s = Scenario { noise_px: 1.5, outlier_fraction: 0.0, ..Scenario::default() };
        let mut head = SimulatedHead::new(s).unwrap();
        let exact = head.exact_capture(&Encoders::default());
        let exact_by_id: std::collections::HashMap<u64, Point2<f64>> =
            exact.left.iter().map(|o| (o.track, o.pixel)).collect();
        let mut sum_sq = 0.0;
        let mut n = 0usize;
        for _ in 0..5 {
            let cap = head.capture().unwrap();
            for o in cap.left.iter().chain(&cap.right) {
                assert!(pixel_in_image(&o.pixel, cap.image_size));
            }
            for o in &cap.left {
                let d = o.pixel - exact_by_id[&o.track];
                sum_sq += d.norm_squared();
                n += 2;
            }
        }
        let sigma = (sum_sq / n as f64).sqrt();
        assert!((sigma - 1.5).abs() < 0.1, "{sigma}");
    }

    #[test]
    fn outlier_fraction_is_honoured() {
        let s = Scenario { noise_px: 0.0, outlier_fraction: 0.3, ..Scenario::default() };
        let mut head = SimulatedHead::new(s).unwrap();
        let exact = head.exact_capture(&Encoders::default());
        let exact_by_id: std::collections::HashMap<u64, Point2<f64>> =
            exact.left.iter().map(|o| (o.track, o.pixel)).collect();
        let (mut outliers, mut total) = (0usize, 0usize);
        for _ in 0..10 {
            let cap = head.capture().unwrap();
            assert_eq!(cap.left.len(), exact.left.len(), "uniform outliers never leave the image");
            for o in &cap.left {
                total += 1;
                if (o.pixel - exact_by_id[&o.track]).norm() > 1e-9 {
                    outliers += 1;
                }
            }
        }
        let frac = outliers as f64 / total as f64;
        assert!((frac - 0.3).abs() < 0.03, "{frac} of {total}");
    }

    #[test]
    fn move_to_validates_and_encoder_noise() {
        let mut head = SimulatedHead::new(Scenario::default()).unwrap();
        let nan = Encoders { pan: f64::NAN, ..Encoders::default() };
        assert!(matches!(head.move_to(&nan), Err(PlatformError::InvalidCommand(_))));
        let far = Encoders { elevation: 181.0, ..Encoders::default() };
        assert!(matches!(head.move_to(&far), Err(PlatformError::OutOfRange { joint: Joint::Elevation, .. })));
        assert_eq!(head.encoders(), Encoders::default());
        let ok = Encoders { pan: 180.0, elevation: -180.0, verge_left: 1.0, verge_right: 2.0 };
        head.move_to(&ok).unwrap();
        assert_eq!(head.read_encoders().unwrap(), ok);
        assert_eq!(head.image_size(), [768, 576]);

        let mut noisy =
            SimulatedHead::new(Scenario { encoder_noise_deg: 0.1, ..Scenario::default() }).unwrap();
        let r1 = noisy.read_encoders().unwrap();
        let r2 = noisy.read_encoders().unwrap();
        assert_ne!(r1, r2);
        assert!(r1.pan.abs() < 1.0 && r1.pan != 0.0);
        assert_eq!(noisy.encoders(), Encoders::default());
    }

    #[test]
    fn scene_density_matches_points_for_seeds_1_to_10() {
        for seed in 1..=10 {
            let head = SimulatedHead::new(Scenario::default().with_seed(seed)).unwrap();
            let (s, t, pts) = (head.scenario(), head.truth(), head.scene_points());
            let initial = count_visible_in_both(s, t, &Encoders::default(), pts);
            assert!((150..=250).contains(&initial), "seed {seed}: {initial} visible initially");
            for pan in [-20.0, 20.0] {
                let enc = Encoders { pan, ..Encoders::default() };
                let n = count_visible_in_both(s, t, &enc, pts);
                assert!(n >= 100, "seed {seed}, pan {pan}: {n} visible");
            }
            // Also after the procedure's elevation move and at the aligned readings.
            let n = count_visible_in_both(s, t, &Encoders { elevation: 3.0, ..Encoders::default() }, pts);
            assert!(n >= 100, "seed {seed}: {n} after elevation");
            let n = count_visible_in_both(s, t, &head.aligned_encoders(), pts);
            assert!(n >= 100, "seed {seed}: {n} when aligned");
        }
    }

    #[test]
    fn scene_points_in_range_and_ids_unique() {
        let head = SimulatedHead::new(Scenario::default()).unwrap();
        let s = head.scenario();
        let centre = Point3::new(0.0, -(s.head_height_m + s.elevation_below_cameras_m), 0.0);
        let mut ids: Vec<u64> = head.scene_points().iter().map(|(id, _)| *id).collect();
        for (_, p) in head.scene_points() {
            let r = (p - centre).norm();
            assert!(r >= s.scene_min_m && r <= s.scene_max_m);
            assert!(p.y <= 1e-12, "nothing below the floor");
        }
        let n = ids.len();
        ids.sort_unstable();
        ids.dedup();
        assert_eq!(ids.len(), n);
        // The room surrounds the head: points in every horizontal quadrant.
        for (sx, sz) in [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
            assert!(head.scene_points().iter().any(|(_, p)| p.x * sx > 0.5 && p.z * sz > 0.5));
        }
    }

    #[test]
    fn invalid_scenario_is_rejected() {
        assert!(matches!(
            SimulatedHead::new(Scenario { noise_px: -1.0, ..Scenario::default() }),
            Err(SimError::InvalidScenario(_))
        ));
    }
}
