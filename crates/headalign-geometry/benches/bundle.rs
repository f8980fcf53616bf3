//! Time of one rig bundle adjustment on the default problem: 3 views (reference,
//! elevation +3 deg, pan +3 deg), Joints model, 200 points, ~1200 observations, 1 px
//! noise, 10 % outliers, Huber loss, started from the truth perturbed (1.5 % on K, 1 deg
//! on the rig and axes, 5 cm on points).

use criterion::{Criterion, criterion_group, criterion_main};
use headalign_geometry::bundle::{
    BundleObservation, BundleOptions, Motions, RigState, Side, bundle_adjust, residual_pixels,
};
use headalign_geometry::camera::Intrinsics;
use headalign_geometry::so3::Line;
use nalgebra::{Isometry3, Point2, Point3, Translation3, Unit, UnitQuaternion, Vector2, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

fn gauss(rng: &mut ChaCha8Rng) -> f64 {
    rng.sample(StandardNormal)
}

fn rand_vec(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    Vector3::new(gauss(rng), gauss(rng), gauss(rng))
}

fn small_rot(rng: &mut ChaCha8Rng, angle: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_scaled_axis(rand_vec(rng).normalize() * angle)
}

fn problem(seed: u64) -> (RigState, Vec<BundleObservation>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let deg = 1.0_f64.to_radians();
    let r_rl = small_rot(&mut rng, deg);
    let right_from_left =
        Isometry3::from_parts(Translation3::from(-(r_rl * Vector3::new(0.25, 0.0, 0.0))), r_rl);
    let pan = Line::new(
        Unit::new_normalize(small_rot(&mut rng, deg) * -Vector3::y()),
        Point3::new(0.125, 0.0, -0.03),
    );
    let elev = Line::new(
        Unit::new_normalize(small_rot(&mut rng, deg) * Vector3::x()),
        Point3::new(0.0, 0.06, -0.03),
    );
    let a = 3.0_f64.to_radians();
    let angles = vec![vec![0.0, 0.0], vec![0.0, a], vec![a, 0.0]];
    let left = Intrinsics::new(700.0, 720.0, 390.0, 284.0);
    let points = (0..200)
        .map(|_| {
            let px = Point2::new(rng.random_range(160.0..720.0), rng.random_range(50.0..526.0));
            Point3::from(left.unproject(&px) * rng.random_range(1.5..6.0))
        })
        .collect();
    let truth = RigState {
        left,
        right: Intrinsics::new(705.0, 716.0, 380.0, 290.0),
        right_from_left,
        motions: Motions::Joints { axes: vec![pan, elev], angles: angles.clone(), commanded: angles },
        points,
    };
    let mut obs = Vec::new();
    for point in 0..200 {
        for view in 0..3 {
            for side in [Side::Left, Side::Right] {
                let o = BundleObservation { point, view, side, pixel: Point2::origin() };
                let Some(r) = residual_pixels(&truth, &o) else { continue };
                let mut pixel = Point2::from(r) + Vector2::new(gauss(&mut rng), gauss(&mut rng));
                if rng.random::<f64>() < 0.1 {
                    pixel += Vector2::new(gauss(&mut rng), gauss(&mut rng)).normalize() * 60.0;
                }
                obs.push(BundleObservation { pixel, ..o });
            }
        }
    }
    let mut start = truth.clone();
    for k in [&mut start.left, &mut start.right] {
        k.fx *= 1.015;
        k.fy *= 0.985;
    }
    start.right_from_left.rotation = small_rot(&mut rng, deg) * start.right_from_left.rotation;
    if let Motions::Joints { axes, .. } = &mut start.motions {
        for l in axes.iter_mut() {
            *l = Line::new(Unit::new_normalize(small_rot(&mut rng, deg) * l.direction.into_inner()), l.point);
        }
    }
    for p in start.points.iter_mut() {
        *p += rand_vec(&mut rng).normalize() * 0.05;
    }
    (start, obs)
}

fn bench(c: &mut Criterion) {
    let (start, obs) = problem(1);
    let opts = BundleOptions::default();
    if let Ok(r) = bundle_adjust(&start, &obs, &opts) {
        eprintln!("{} observations, {:?}", obs.len(), r.report);
    }
    c.bench_function("bundle_adjust 3 views 200 points joints huber", |b| {
        b.iter(|| bundle_adjust(std::hint::black_box(&start), &obs, &opts))
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
