//! A seeded room of 3D points with track ids, and the visibility test shared with the
//! captures.
//!
//! The room (world frame: x right, y down, z forward, metres, origin on the pan axis at
//! the ground) is an axis-aligned box around the head: floor at `y = 0`, a ceiling, four
//! walls, and a few boxes standing on the floor, rotated about the vertical, at random
//! bearings all around the head. Wall distances and box sizes scale with
//! `scene_max_m`, and the whole room is drawn from the seed.
//!
//! Points are made by casting rays from the head centre in directions uniform on the
//! sphere and keeping the first surface hit if it lies between `scene_min_m` and
//! `scene_max_m` from the head. Uniform in solid angle means about the same number of
//! points per image whatever the pointing, and first hits mean no point hides behind
//! another as seen from the head (occlusion is not modelled otherwise: from a camera a few
//! centimetres away a point may in truth be hidden by a box edge; that is ignored).
//!
//! Near structure (`near_panels > 0`): tall boxes standing on the floor at about
//! `near_distance_m` in front of the robot (bearings spread over +-70 deg, each turned
//! to face the head), drawn from their own random stream (6) after the room, so that a
//! scenario without them gives exactly the room and points it gave before they existed.
//! Points are then observed from [`Scenario::min_range_m`] on.
//!
//! The `wall` scene ([`SceneKind::Wall`]): one rectangle instead of the room, its centre
//! straight ahead of the head centre (world +z) at a distance drawn uniformly in
//! [`Scenario::WALL_DISTANCE_M`], its normal turned up to 15 deg about the vertical and up
//! to 10 deg about the horizontal from facing the head, 8 x 4 times its distance wide and
//! high (a camera panned 20 deg and turned 10 deg more still sees only wall: 74 deg off the
//! normal at most sideways, `tan 74 = 3.5`), drawn from its own random stream (7), so
//! that no other scene changes. It is the only surface: rays that miss it see nothing.
//!
//! The `far` scene ([`SceneKind::Far`]): a cube centred on the head centre, half edge
//! drawn uniformly in `[1, 1.2] x scene_min_m` from its own random stream (8), nothing
//! else: the room's floor, ceiling and boxes are gone (at hundreds of metres they would
//! crowd into a thin band about the horizon).
//!
//! Density: after casting, the points visible in both cameras at the initial encoder
//! readings (all zero) are counted, and every point is kept with probability
//! `points / visible`, so that about `points` are seen by both cameras in the initial
//! view (a binomial count). If too few are visible, more rays are cast.

use headalign_geometry::camera::Intrinsics;
use nalgebra::{Isometry3, Point2, Point3, Rotation3, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, UnitSphere};

use crate::SimError;
use crate::kinematics::HeadTruth;
use crate::quad::PlanarQuad;
use crate::scenario::{Scenario, SceneKind};
use headalign_platform::Encoders;

/// Random stream of the near panels (the head uses 0-5).
const STREAM_NEAR: u64 = 6;

/// Random stream of the `wall` scene's plane.
const STREAM_WALL: u64 = 7;

/// Random stream of the `far` scene's box.
const STREAM_FAR: u64 = 8;

/// A scene point: track id and position in the world frame.
pub type ScenePoint = (u64, Point3<f64>);

/// True if a pixel lies inside an image of the given size (pixel centres at integers,
/// (0, 0) the top-left one, so the image spans `[-0.5, w - 0.5] x [-0.5, h - 0.5]`).
pub fn pixel_in_image(pixel: &Point2<f64>, image_size: [u32; 2]) -> bool {
    let (w, h) = (f64::from(image_size[0]), f64::from(image_size[1]));
    pixel.x >= -0.5 && pixel.x <= w - 0.5 && pixel.y >= -0.5 && pixel.y <= h - 0.5
}

/// Exact pixel of a world point in a camera, if the camera sees it: in front, between
/// `min_m` and `max_m` from the camera centre, and projecting inside the image.
pub fn visible_pixel(
    k: &Intrinsics,
    cam_from_world: &Isometry3<f64>,
    point_in_world: &Point3<f64>,
    image_size: [u32; 2],
    min_m: f64,
    max_m: f64,
) -> Option<Point2<f64>> {
    let point_in_cam = cam_from_world * point_in_world;
    let distance = point_in_cam.coords.norm();
    if !(distance >= min_m && distance <= max_m) {
        return None;
    }
    let pixel = k.project(&point_in_cam)?;
    pixel_in_image(&pixel, image_size).then_some(pixel)
}

/// An oriented box standing on the floor.
#[derive(Clone, Copy, Debug)]
struct FloorBox {
    /// Centre, world frame.
    centre: Point3<f64>,
    /// Half extents along the box's own x, y, z.
    half: Vector3<f64>,
    /// box_from_world rotation (about the vertical).
    box_from_world: Rotation3<f64>,
}

impl FloorBox {
    /// Ray parameter of the entry point of `origin + t dir`, if the ray enters the box
    /// at `t > 0` (slab method in the box frame).
    fn entry(&self, origin: &Point3<f64>, dir: &Vector3<f64>) -> Option<f64> {
        let o = self.box_from_world * (origin - self.centre);
        let d = self.box_from_world * dir;
        let mut t_near = f64::NEG_INFINITY;
        let mut t_far = f64::INFINITY;
        for i in 0..3 {
            if d[i].abs() < 1e-15 {
                if o[i].abs() > self.half[i] {
                    return None;
                }
                continue;
            }
            let t1 = (-self.half[i] - o[i]) / d[i];
            let t2 = (self.half[i] - o[i]) / d[i];
            t_near = t_near.max(t1.min(t2));
            t_far = t_far.min(t1.max(t2));
        }
        (t_near <= t_far && t_near > 0.0).then_some(t_near)
    }
}

/// The room: an axis-aligned box `[x_min, x_max] x [y_min, 0] x [z_min, z_max]` (y_min is
/// the ceiling, negative) and boxes on the floor. Drawn once per scenario from the scene
/// stream; the point scene and the rendered images see the same room.
#[derive(Clone, Debug)]
pub struct Room {
    min: Vector3<f64>,
    max: Vector3<f64>,
    boxes: Vec<FloorBox>,
    /// The last `near` boxes are the near panels.
    near: usize,
    /// The `wall` scene: this rectangle is the only surface (module docs).
    wall: Option<PlanarQuad>,
}

impl Room {
    fn draw(scenario: &Scenario, head_centre: &Point3<f64>, rng: &mut ChaCha8Rng) -> Self {
        let d = scenario.scene_max_m;
        let lo = scenario.scene_min_m * 1.2;
        let mut u = |a: f64, b: f64| a + (b - a) * rng.random::<f64>();
        let front = (u(0.65, 0.8) * d).max(lo);
        let back = (u(0.6, 0.75) * d).max(lo);
        let left = (u(0.5, 0.65) * d).max(lo);
        let right = (u(0.5, 0.65) * d).max(lo);
        let ceiling = -head_centre.y + u(1.4, 1.9);
        let nearest_wall = front.min(back).min(left).min(right);
        let mut boxes = Vec::new();
        for _ in 0..8 {
            let bearing = u(0.0, std::f64::consts::TAU);
            let r_min = scenario.scene_min_m + 0.6;
            let r = u(r_min, (0.85 * nearest_wall).max(r_min));
            let half = Vector3::new(u(0.15, 0.5), u(0.2, 0.7), u(0.15, 0.5));
            let yaw = u(0.0, std::f64::consts::PI);
            boxes.push(FloorBox {
                centre: Point3::new(r * bearing.sin(), -half.y, r * bearing.cos()),
                half,
                box_from_world: Rotation3::from_axis_angle(&Vector3::y_axis(), -yaw),
            });
        }
        Self {
            min: Vector3::new(-left, -ceiling, -back),
            max: Vector3::new(right, 0.0, front),
            boxes,
            near: 0,
            wall: None,
        }
    }

    /// The `wall` scene's rectangle (module docs), drawn from `rng`, facing `head_centre`.
    fn draw_wall(head_centre: &Point3<f64>, rng: &mut ChaCha8Rng) -> PlanarQuad {
        let mut u = |a: f64, b: f64| a + (b - a) * rng.random::<f64>();
        let [lo, hi] = Scenario::WALL_DISTANCE_M;
        let distance = u(lo, hi);
        let yaw = u(-15.0, 15.0).to_radians();
        let pitch = u(-10.0, 10.0).to_radians();
        let turn = Rotation3::from_axis_angle(&Vector3::y_axis(), yaw)
            * Rotation3::from_axis_angle(&Vector3::x_axis(), pitch);
        let centre = head_centre + Vector3::z() * distance;
        // Visible side faces the head (-z before the turn): y cross x = -z.
        let half_u = turn * Vector3::y() * (2.0 * distance);
        let half_v = turn * Vector3::x() * (4.0 * distance);
        PlanarQuad::centred(centre, half_u, half_v)
    }

    /// The `wall` scene's plane, if this is one (module docs).
    pub fn wall(&self) -> Option<&PlanarQuad> {
        self.wall.as_ref()
    }

    /// Add `scenario.near_panels` tall panels about `near_distance_m` in front of the pan
    /// axis (module docs), drawn from `rng`.
    fn add_near_panels(&mut self, scenario: &Scenario, rng: &mut ChaCha8Rng) {
        let n = scenario.near_panels;
        let mut u = |a: f64, b: f64| a + (b - a) * rng.random::<f64>();
        let span = 70f64.to_radians();
        for i in 0..n {
            let slot = 2.0 * span / n as f64;
            let bearing = -span + slot * (i as f64 + u(0.3, 0.7));
            let half = Vector3::new(u(0.15, 0.25), u(0.8, 1.1), u(0.08, 0.15));
            let r = scenario.near_distance_m * u(1.0, 1.25) + half.z;
            let yaw = bearing + u(-0.3, 0.3);
            self.boxes.push(FloorBox {
                centre: Point3::new(r * bearing.sin(), -half.y, r * bearing.cos()),
                half,
                box_from_world: Rotation3::from_axis_angle(&Vector3::y_axis(), -yaw),
            });
            self.near += 1;
        }
    }

    /// For each quad of [`Self::quads`], in order: true for the faces of the near panels
    /// (the renderer textures them finer: they are seen from about 1 m).
    pub fn near_quads(&self) -> Vec<bool> {
        if self.wall.is_some() {
            return vec![true];
        }
        let far_boxes = self.boxes.len() - self.near;
        let mut v = vec![false; 6 + 5 * far_boxes];
        v.resize(6 + 5 * self.boxes.len(), true);
        v
    }

    /// The surfaces as visible-side-oriented quads: floor, ceiling, the four walls (in
    /// that order), then for each box its top and four sides (the bottom stands on the
    /// floor and is never seen).
    pub fn quads(&self) -> Vec<PlanarQuad> {
        if let Some(w) = self.wall {
            return vec![w];
        }
        let (lo, hi) = (self.min, self.max);
        let c = (lo + hi) * 0.5;
        let h = (hi - lo) * 0.5;
        let (x, y, z) = (Vector3::x(), Vector3::y(), Vector3::z());
        let at = |v: Vector3<f64>| Point3::from(v);
        let mut quads = vec![
            // Floor (y = max.y = 0), seen from above (-y): x cross z = -y.
            PlanarQuad::centred(at(Vector3::new(c.x, hi.y, c.z)), x * h.x, z * h.z),
            // Ceiling, seen from below (+y): z cross x = +y.
            PlanarQuad::centred(at(Vector3::new(c.x, lo.y, c.z)), z * h.z, x * h.x),
            // Right wall x = max.x, normal -x: z cross y = -x.
            PlanarQuad::centred(at(Vector3::new(hi.x, c.y, c.z)), z * h.z, y * h.y),
            // Left wall, normal +x: y cross z = +x.
            PlanarQuad::centred(at(Vector3::new(lo.x, c.y, c.z)), y * h.y, z * h.z),
            // Front wall z = max.z, normal -z: y cross x = -z.
            PlanarQuad::centred(at(Vector3::new(c.x, c.y, hi.z)), y * h.y, x * h.x),
            // Back wall, normal +z: x cross y = +z.
            PlanarQuad::centred(at(Vector3::new(c.x, c.y, lo.z)), x * h.x, y * h.y),
        ];
        for b in &self.boxes {
            let world_from_box = b.box_from_world.inverse();
            let (bx, by, bz) =
                (world_from_box * x * b.half.x, world_from_box * y * b.half.y, world_from_box * z * b.half.z);
            // (offset to the face centre, half edges) with hu x hv along the offset.
            let faces = [(-by, bx, bz), (bx, by, bz), (-bx, bz, by), (bz, bx, by), (-bz, by, bx)];
            for (offset, hu, hv) in faces {
                quads.push(PlanarQuad::centred(b.centre + offset, hu, hv));
            }
        }
        quads
    }

    /// First surface hit by the ray `origin + t dir` (origin inside the room, `t > 0`),
    /// world frame: what a camera at `origin` sees in direction `dir`.
    pub fn cast(&self, origin: &Point3<f64>, dir: &Vector3<f64>) -> Option<Point3<f64>> {
        if let Some(w) = &self.wall {
            return cast_quad(w, origin, dir);
        }
        let mut t_hit = f64::INFINITY;
        for i in 0..3 {
            if dir[i] > 1e-15 {
                t_hit = t_hit.min((self.max[i] - origin[i]) / dir[i]);
            } else if dir[i] < -1e-15 {
                t_hit = t_hit.min((self.min[i] - origin[i]) / dir[i]);
            }
        }
        for b in &self.boxes {
            if let Some(t) = b.entry(origin, dir) {
                t_hit = t_hit.min(t);
            }
        }
        t_hit.is_finite().then(|| origin + dir * t_hit)
    }
}

/// Where the ray `origin + t dir` (`t > 0`) meets the quad's visible side, if it does.
fn cast_quad(q: &PlanarQuad, origin: &Point3<f64>, dir: &Vector3<f64>) -> Option<Point3<f64>> {
    let n = q.normal();
    let along = dir.dot(&n);
    if along > -1e-12 {
        return None;
    }
    let t = (q.corner - origin).dot(&n) / along;
    let hit = origin + dir * t;
    let d = hit - q.corner;
    let (a, b) = (d.dot(&q.u), d.dot(&q.v));
    (t > 0.0 && (0.0..=q.size_m[0]).contains(&a) && (0.0..=q.size_m[1]).contains(&b)).then_some(hit)
}

/// Number of scene points visible in both cameras at the given encoders.
pub fn count_visible_in_both(
    scenario: &Scenario,
    truth: &HeadTruth,
    enc: &Encoders,
    points: &[ScenePoint],
) -> usize {
    let (world_from_left, world_from_right) = truth.world_from_cameras(enc);
    let (left_from_world, right_from_world) = (world_from_left.inverse(), world_from_right.inverse());
    let (min, max) = (scenario.min_range_m(), scenario.scene_max_m);
    points
        .iter()
        .filter(|(_, p)| {
            visible_pixel(&truth.left, &left_from_world, p, scenario.image_size, min, max).is_some()
                && visible_pixel(&truth.right, &right_from_world, p, scenario.image_size, min, max).is_some()
        })
        .count()
}

/// Build the scene of a scenario: a room drawn from `rng`, thinned so that about
/// `scenario.points` points are visible in both cameras at zero encoder readings. Track
/// ids are `0..n` in generation order.
pub fn generate_scene(
    scenario: &Scenario,
    truth: &HeadTruth,
    rng: &mut ChaCha8Rng,
) -> Result<Vec<ScenePoint>, SimError> {
    generate_room_and_scene(scenario, truth, rng).map(|(_, points)| points)
}

/// [`generate_scene`], also returning the room the points lie on (for the renderer).
pub fn generate_room_and_scene(
    scenario: &Scenario,
    truth: &HeadTruth,
    rng: &mut ChaCha8Rng,
) -> Result<(Room, Vec<ScenePoint>), SimError> {
    let head_centre = Point3::new(0.0, -(scenario.head_height_m + scenario.elevation_below_cameras_m), 0.0);
    let mut room = Room::draw(scenario, &head_centre, rng);
    if scenario.scene == SceneKind::Far {
        let mut far_rng = ChaCha8Rng::seed_from_u64(scenario.seed);
        far_rng.set_stream(STREAM_FAR);
        let half = scenario.scene_min_m * (1.0 + 0.2 * far_rng.random::<f64>());
        let h = Vector3::new(half, half, half);
        room = Room {
            min: head_centre.coords - h,
            max: head_centre.coords + h,
            boxes: Vec::new(),
            near: 0,
            wall: None,
        };
    }
    if scenario.scene == SceneKind::Wall {
        let mut wall_rng = ChaCha8Rng::seed_from_u64(scenario.seed);
        wall_rng.set_stream(STREAM_WALL);
        room.wall = Some(Room::draw_wall(&head_centre, &mut wall_rng));
    }
    if scenario.near_panels > 0 {
        let mut near_rng = ChaCha8Rng::seed_from_u64(scenario.seed);
        near_rng.set_stream(STREAM_NEAR);
        room.add_near_panels(scenario, &mut near_rng);
    }
    let initial = Encoders::default();
    // About 1/16 of the sphere is seen by both cameras; aim for 4x the wanted count.
    let mut rays = (scenario.points.saturating_mul(64)).clamp(4096, 1 << 22);
    const ATTEMPTS: usize = 6;
    for _ in 0..ATTEMPTS {
        let mut dense = Vec::with_capacity(rays);
        for _ in 0..rays {
            let [x, y, z]: [f64; 3] = UnitSphere.sample(rng);
            let dir = Vector3::new(x, y, z);
            if let Some(p) = room.cast(&head_centre, &dir) {
                let r = (p - head_centre).norm();
                if r >= scenario.min_range_m() && r <= scenario.scene_max_m {
                    dense.push((0u64, p));
                }
            }
        }
        let visible = count_visible_in_both(scenario, truth, &initial, &dense);
        let wanted = scenario.points as f64;
        if (visible as f64) >= 2.0 * wanted {
            let keep = wanted / visible as f64;
            let mut out = Vec::new();
            for (_, p) in dense {
                if rng.random::<f64>() < keep {
                    out.push((out.len() as u64, p));
                }
            }
            return Ok((room, out));
        }
        if rays >= 1 << 22 {
            break;
        }
        let factor = if visible == 0 { 8.0 } else { (3.0 * wanted / visible as f64).ceil().max(2.0) };
        rays = ((rays as f64) * factor).min((1u64 << 22) as f64) as usize;
    }
    Err(SimError::Scene(format!(
        "could not place {} points visible in both cameras at the initial pointing (check \
         scene_min_m/scene_max_m, image size and zero offsets)",
        scenario.points
    )))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quads_face_the_head_side_and_carry_every_point() {
        for seed in 1..=6 {
            // Seeds 4-6 with the robot's near panels.
            let near = if seed > 3 { Scenario::ROBOT_NEAR_PANELS } else { 0 };
            let scenario = Scenario { near_panels: near, ..Scenario::default().with_seed(seed) };
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let truth = HeadTruth::draw(&scenario, &mut rng);
            let (room, points) = generate_room_and_scene(&scenario, &truth, &mut rng).unwrap();
            let quads = room.quads();
            assert_eq!(quads.len(), 6 + 5 * room.boxes.len());
            assert_eq!(room.boxes.len(), 8 + near);
            for q in &quads[..6] {
                // Walls face the room's centre.
                let centre = Point3::from((room.min + room.max) * 0.5);
                assert!(q.normal().dot(&(centre - q.corner)) > 0.0);
                assert!((q.u.dot(&q.v)).abs() < 1e-12 && (q.normal().norm() - 1.0).abs() < 1e-12);
            }
            for (b, faces) in room.boxes.iter().zip(quads[6..].chunks(5)) {
                for q in faces {
                    // Box faces face away from the box centre.
                    assert!(q.normal().dot(&(q.corner - b.centre)) > 0.0);
                }
            }
            // Every scene point lies on (within 1e-9 m of) some quad.
            for (_, p) in &points {
                let on = quads.iter().any(|q| {
                    let d = p - q.corner;
                    let (a, c) = (d.dot(&q.u), d.dot(&q.v));
                    d.dot(&q.normal()).abs() < 1e-9
                        && (-1e-9..=q.size_m[0] + 1e-9).contains(&a)
                        && (-1e-9..=q.size_m[1] + 1e-9).contains(&c)
                });
                assert!(on, "seed {seed}: point {p} on no quad");
            }
        }
    }

    /// The `wall` scene: every point on the one plane, 1-4 m ahead, and the room of the
    /// default scene unchanged by the new field.
    #[test]
    fn wall_scene_is_one_plane_ahead() {
        for seed in 1..=3 {
            let s = Scenario::wall().with_seed(seed);
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let truth = HeadTruth::draw(&s, &mut rng);
            let (room, points) = generate_room_and_scene(&s, &truth, &mut rng).unwrap();
            let quads = room.quads();
            assert_eq!((quads.len(), room.near_quads().len()), (1, 1));
            let q = quads[0];
            // Signed distance of the head centre in front of the visible side: 1-4 m
            // (the wall turns by at most 15 deg about its own centre line).
            let head = Point3::new(0.0, -(s.head_height_m + s.elevation_below_cameras_m), 0.0);
            let dist = (head - q.corner).dot(&q.normal());
            assert!((0.9..=4.0).contains(&dist), "seed {seed}: {dist}");
            assert!(points.len() > 100, "{}", points.len());
            for (_, p) in &points {
                assert!((p - q.corner).dot(&q.normal()).abs() < 1e-9);
            }
        }
    }

    /// Near panels: many of the initially seen points lie about 1 m away, and without
    /// panels the room and points are exactly those of a scenario that never had them.
    #[test]
    fn near_panels_put_points_at_one_metre_and_leave_the_room_alone() {
        let base = Scenario::default().with_seed(2);
        let near = Scenario { near_panels: Scenario::ROBOT_NEAR_PANELS, ..base.clone() };
        let draw = |s: &Scenario| {
            let mut rng = ChaCha8Rng::seed_from_u64(s.seed);
            let truth = HeadTruth::draw(s, &mut rng);
            let (_, pts) = generate_room_and_scene(s, &truth, &mut rng).unwrap();
            (truth, pts)
        };
        let (truth, pts) = draw(&near);
        // The renderer textures exactly the panels' faces finer: the last 5 per panel.
        let mut rng = ChaCha8Rng::seed_from_u64(near.seed);
        let (room, _) = generate_room_and_scene(&near, &HeadTruth::draw(&near, &mut rng), &mut rng).unwrap();
        let flags = room.near_quads();
        assert_eq!(flags.len(), room.quads().len());
        let n_near = 5 * Scenario::ROBOT_NEAR_PANELS;
        assert!(
            flags[..flags.len() - n_near].iter().all(|f| !f)
                && flags[flags.len() - n_near..].iter().all(|f| *f)
        );
        let (left, _) = truth.world_from_cameras(&Encoders::default());
        let close = pts
            .iter()
            .filter(|(_, p)| {
                let q = left.inverse() * p;
                q.z > 0.0 && q.coords.norm() < 1.6 && truth.left.project(&q).is_some()
            })
            .count();
        assert!(close >= 40, "{close} points within 1.6 m in view");
        let explicit_zero = Scenario { near_panels: 0, near_distance_m: 2.0, ..base.clone() };
        assert_eq!(draw(&base).1, draw(&explicit_zero).1);
    }
}
