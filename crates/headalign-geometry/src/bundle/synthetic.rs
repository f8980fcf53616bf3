//! Synthetic rig bundle-adjustment problems with known truth, for tests, benchmarks and
//! experiments: a stereo rig moved by rotations about two offset axes, seen in three
//! views ([`synth`]), or carried along a wall in a sequence of views that each overlap
//! only their neighbours, in disconnected segments ([`sequence`]); Gaussian noise and
//! optional gross outliers (pixels). Seeded: the same seed gives the same problem bit for
//! bit.

use nalgebra::{Isometry3, Point2, Point3, Translation3, Unit, UnitQuaternion, Vector2, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crate::bundle::{BundleObservation, Motions, RigState, Side, residual_pixels};
use crate::camera::Intrinsics;
use crate::distortion::Distortion;
use crate::so3::Line;

/// Image width of the synthetic cameras, pixels.
pub const WIDTH: f64 = 768.0;
/// Image height of the synthetic cameras, pixels.
pub const HEIGHT: f64 = 576.0;

/// A standard normal draw.
pub fn gauss(rng: &mut ChaCha8Rng) -> f64 {
    rng.sample(StandardNormal)
}

/// A vector of three standard normal draws.
pub fn rand_vec(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    Vector3::new(gauss(rng), gauss(rng), gauss(rng))
}

/// A random rotation of exactly `angle` radians about a random axis.
pub fn small_rot(rng: &mut ChaCha8Rng, angle: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_scaled_axis(rand_vec(rng).normalize() * angle)
}

/// `d` rotated by exactly `angle` radians about a random axis.
pub fn tilt(rng: &mut ChaCha8Rng, d: Vector3<f64>, angle: f64) -> Unit<Vector3<f64>> {
    Unit::new_normalize(small_rot(rng, angle) * d)
}

/// A problem with known truth.
pub struct Synth {
    /// The true state.
    pub truth: RigState,
    /// Noisy observations (with outliers if asked).
    pub obs: Vec<BundleObservation>,
}

/// A stereo rig (baseline 0.25, ~1 deg relative rotation) in 3 views: reference, +3 deg
/// about an elevation-like axis, +3 deg about a pan-like axis (both offset from the camera,
/// tilted ~1 deg); `n_points` points 1.5-6 units ahead; Gaussian noise `noise_px`; each
/// observation displaced by 30-100 px with probability `outlier_frac`; `free` gives the
/// same motions as a Free model.
pub fn synth(seed: u64, n_points: usize, noise_px: f64, outlier_frac: f64, free: bool) -> Synth {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let left = Intrinsics::new(700.0, 720.0, 390.0, 284.0);
    let right = Intrinsics::new(705.0, 716.0, 380.0, 290.0);
    let r_rl = small_rot(&mut rng, 1.0_f64.to_radians());
    let c_r = Vector3::new(0.25, 0.0, 0.0) + rand_vec(&mut rng) * 0.002;
    let right_from_left = Isometry3::from_parts(Translation3::from(-(r_rl * c_r)), r_rl);
    let pan = Line::new(
        tilt(&mut rng, -Vector3::y(), 1.0_f64.to_radians()),
        Point3::new(0.125, 0.0, -0.03) + rand_vec(&mut rng) * 0.005,
    );
    let elev = Line::new(
        tilt(&mut rng, Vector3::x(), 1.5_f64.to_radians()),
        Point3::new(0.0, 0.06, -0.03) + rand_vec(&mut rng) * 0.005,
    );
    let deg3 = 3.0_f64.to_radians();
    let angles = vec![vec![0.0, 0.0], vec![0.0, deg3], vec![deg3, 0.0]];
    let joints = Motions::Joints { axes: vec![pan, elev], angles: angles.clone(), commanded: angles };
    let motions = if free {
        Motions::Free { ref_from_cam: (0..3).map(|k| joints.ref_from_cam(k)).collect() }
    } else {
        joints
    };
    let mut points = Vec::with_capacity(n_points);
    for _ in 0..n_points {
        let u = rng.random_range(160.0..720.0);
        let v = rng.random_range(50.0..526.0);
        let depth = rng.random_range(1.5..6.0);
        points.push(Point3::from(left.unproject(&Point2::new(u, v)) * depth));
    }
    let truth = RigState {
        left,
        right,
        left_distortion: Distortion::default(),
        right_distortion: Distortion::default(),
        right_from_left,
        motions,
        points,
    };
    let mut obs = Vec::new();
    for (p, _) in truth.points.iter().enumerate() {
        for view in 0..3 {
            for side in [Side::Left, Side::Right] {
                let o = BundleObservation { point: p, view, side, pixel: Point2::origin() };
                let Some(r) = residual_pixels(&truth, &o) else { continue };
                let px = Point2::from(r);
                if !(0.0..WIDTH).contains(&px.x) || !(0.0..HEIGHT).contains(&px.y) {
                    continue;
                }
                let mut pixel = px + Vector2::new(gauss(&mut rng), gauss(&mut rng)) * noise_px;
                if rng.random::<f64>() < outlier_frac {
                    let a = rng.random_range(0.0..std::f64::consts::TAU);
                    let m = rng.random_range(30.0..100.0);
                    pixel += Vector2::new(a.cos(), a.sin()) * m;
                }
                obs.push(BundleObservation { pixel, ..o });
            }
        }
    }
    Synth { truth, obs }
}

/// Truth perturbed: ~1.5 % on K, ~1 deg on poses and axes, ~5 cm on points; the
/// baseline length is kept (scale gauge).
pub fn perturb(truth: &RigState, seed: u64) -> RigState {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut s = truth.clone();
    for k in [&mut s.left, &mut s.right] {
        k.fx *= 1.0 + 0.015 * gauss(&mut rng).clamp(-1.3, 1.3);
        k.fy *= 1.0 + 0.015 * gauss(&mut rng).clamp(-1.3, 1.3);
        k.cx += 5.0 * gauss(&mut rng);
        k.cy += 5.0 * gauss(&mut rng);
    }
    let deg = 1.0_f64.to_radians();
    let t = s.right_from_left.translation.vector;
    let t_new = small_rot(&mut rng, deg) * t;
    s.right_from_left = Isometry3::from_parts(
        Translation3::from(t_new),
        small_rot(&mut rng, deg) * s.right_from_left.rotation,
    );
    match &mut s.motions {
        Motions::Free { ref_from_cam } => {
            for p in ref_from_cam.iter_mut().skip(1) {
                let step = Isometry3::from_parts(
                    Translation3::from(rand_vec(&mut rng) * 0.01),
                    small_rot(&mut rng, deg),
                );
                *p = step * *p;
            }
        }
        Motions::Joints { axes, .. } => {
            for l in axes.iter_mut() {
                *l = Line::new(
                    tilt(&mut rng, l.direction.into_inner(), deg),
                    l.point + rand_vec(&mut rng) * 0.01,
                );
            }
        }
    }
    for p in s.points.iter_mut() {
        *p += rand_vec(&mut rng).normalize() * 0.05;
    }
    s
}

/// A sequence ([`sequence`]): the problem, and the first view of every segment after the
/// first (the gauge views the adjustment must hold, `BundleOptions::gauge_views`).
pub struct SequenceSynth {
    /// The problem (views of all segments in order; each segment's points in the frame of
    /// its first view, which is at the identity).
    pub synth: Synth,
    /// The first view of each segment after the first.
    pub gauge_views: Vec<usize>,
    /// The segment of each point.
    pub point_segment: Vec<usize>,
}

/// The rig of [`synth`] carried sideways along a textured wall: `views` views split into
/// `segments` contiguous segments (at least one view each) that share no point, each a
/// walk of 0.3 units per view (the baseline is 0.25) with the yaw swinging by +-6 deg and
/// the pitch by +-4 deg about varied axes; `points_per_segment` points 3-6 units ahead
/// spread over the walk (an image spans about 5 units at that depth, so a view overlaps
/// some 15 neighbours either side and no more). Each segment's poses and points are in
/// the frame of its first view (the identity). Gaussian noise `noise_px`, no outliers.
pub fn sequence(
    seed: u64,
    views: usize,
    segments: usize,
    points_per_segment: usize,
    noise_px: f64,
) -> SequenceSynth {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let base = synth(seed, 1, 0.0, 0.0, true).truth;
    let segments = segments.clamp(1, views.max(1));
    let mut ref_from_cam = Vec::with_capacity(views);
    let (mut points, mut point_segment, mut gauge_views) = (Vec::new(), Vec::new(), Vec::new());
    for s in 0..segments {
        let (a, b) = (s * views / segments, (s + 1) * views / segments);
        if s > 0 {
            gauge_views.push(a);
        }
        let phase = rng.random_range(0.0..std::f64::consts::TAU);
        let world: Vec<Isometry3<f64>> = (0..b - a)
            .map(|j| {
                let t = j as f64;
                let yaw = 6.0_f64.to_radians() * (0.4 * t + phase).sin();
                let pitch = 4.0_f64.to_radians() * (0.27 * t + 2.0 * phase).sin();
                let roll = 2.0_f64.to_radians() * (0.19 * t).sin();
                Isometry3::from_parts(
                    Translation3::new(0.3 * t, 0.1 * (0.3 * t).sin(), 0.05 * (0.23 * t).cos()),
                    UnitQuaternion::from_euler_angles(pitch, yaw, roll),
                )
            })
            .collect();
        let gauge = world[0].inverse();
        ref_from_cam.extend(world.iter().map(|w| gauge * w));
        let span = 0.3 * (b - a - 1) as f64;
        for _ in 0..points_per_segment {
            let p = Point3::new(
                rng.random_range(-2.5..span + 2.5),
                rng.random_range(-1.2..1.2),
                rng.random_range(3.0..6.0),
            );
            points.push(gauge * p);
            point_segment.push(s);
        }
    }
    let truth = RigState { motions: Motions::Free { ref_from_cam }, points, ..base };
    let segment_of_view = |k: usize| (0..segments).rfind(|&s| s * views / segments <= k).unwrap_or(0);
    let mut obs = Vec::new();
    for (p, &s) in point_segment.iter().enumerate() {
        for view in (0..views).filter(|&k| segment_of_view(k) == s) {
            for side in [Side::Left, Side::Right] {
                let o = BundleObservation { point: p, view, side, pixel: Point2::origin() };
                let Some(r) = residual_pixels(&truth, &o) else { continue };
                let px = Point2::from(r);
                if !(0.0..WIDTH).contains(&px.x) || !(0.0..HEIGHT).contains(&px.y) {
                    continue;
                }
                let pixel = px + Vector2::new(gauss(&mut rng), gauss(&mut rng)) * noise_px;
                obs.push(BundleObservation { pixel, ..o });
            }
        }
    }
    // Only the points seen in two views (both cameras) stay.
    let mut count = vec![0usize; truth.points.len()];
    for o in &obs {
        count[o.point] += 1;
    }
    let mut index = vec![usize::MAX; count.len()];
    let mut truth = truth;
    let (mut kept, mut kept_segment) = (Vec::new(), Vec::new());
    for (i, &c) in count.iter().enumerate() {
        if c >= 4 {
            index[i] = kept.len();
            kept.push(truth.points[i]);
            kept_segment.push(point_segment[i]);
        }
    }
    truth.points = kept;
    obs.retain(|o| index[o.point] != usize::MAX);
    for o in &mut obs {
        o.point = index[o.point];
    }
    SequenceSynth { synth: Synth { truth, obs }, gauge_views, point_segment: kept_segment }
}
