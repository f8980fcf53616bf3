//! Benchmarks of the hot paths of the geometry layer: 8-point F, Sampson refinement,
//! RANSAC for F, optimal triangulation and the 3D DLT.

use criterion::{Criterion, criterion_group, criterion_main};
use headalign_geometry::camera::{Intrinsics, ProjectiveCamera};
use headalign_geometry::fundamental::{FundamentalMatrix, estimate_fundamental};
use headalign_geometry::homography3d::Homography3;
use headalign_geometry::ransac::RansacOptions;
use headalign_geometry::triangulation::triangulate_optimal;
use nalgebra::{Isometry3, Matrix4, Point2, Point3, Translation3, UnitQuaternion, Vector4};
use std::hint::black_box;

type Pairs = Vec<(Point2<f64>, Point2<f64>)>;
type Scene = (ProjectiveCamera, ProjectiveCamera, Vec<Point3<f64>>, Pairs);

fn scene(n: usize) -> Scene {
    let k = Intrinsics::new(700.0, 720.0, 390.0, 284.0);
    let rl = Isometry3::from_parts(
        Translation3::new(-0.25, 0.0, 0.0),
        UnitQuaternion::from_euler_angles(0.0, 0.1, 0.0),
    );
    let pl = ProjectiveCamera::from_pose(&k, &Isometry3::identity());
    let pr = ProjectiveCamera::from_pose(&k, &rl);
    let mut pts = Vec::new();
    let mut pairs = Vec::new();
    for i in 0..n {
        let t = i as f64;
        let p =
            Point3::new((t * 0.37).sin() * 2.0, (t * 0.71).cos() * 1.5, 2.0 + (t * 0.13).sin().abs() * 4.0);
        let x = p.to_homogeneous();
        let jitter = Point2::new((t * 1.3).sin() * 0.5, (t * 2.1).cos() * 0.5).coords;
        pairs.push((
            pl.project(&x).unwrap_or_else(Point2::origin) + jitter,
            pr.project(&x).unwrap_or_else(Point2::origin),
        ));
        pts.push(p);
    }
    (pl, pr, pts, pairs)
}

fn benches(c: &mut Criterion) {
    let (pl, pr, pts, mut pairs) = scene(200);
    c.bench_function("eight_point_200", |b| b.iter(|| FundamentalMatrix::eight_point(black_box(&pairs))));
    if let Ok(f) = FundamentalMatrix::eight_point(&pairs) {
        c.bench_function("refine_sampson_200", |b| b.iter(|| f.refine_sampson(black_box(&pairs))));
        c.bench_function("triangulate_optimal", |b| {
            b.iter(|| triangulate_optimal(&f, &pl, &pr, black_box(&pairs[0].0), black_box(&pairs[0].1)))
        });
    }
    for (i, p) in pairs.iter_mut().enumerate().take(20) {
        p.1 = Point2::new(i as f64 * 37.0 % 768.0, i as f64 * 53.0 % 576.0);
    }
    let opts = RansacOptions { threshold: 2.0, ..Default::default() };
    c.bench_function("estimate_fundamental_200_10pct_outliers", |b| {
        b.iter(|| estimate_fundamental(black_box(&pairs), &opts))
    });
    let mut h = Matrix4::identity();
    h[(0, 3)] = 0.1;
    h[(1, 2)] = 0.05;
    let x: Vec<Vector4<f64>> = pts.iter().map(|p| p.to_homogeneous()).collect();
    let y: Vec<Vector4<f64>> = x.iter().map(|p| h * p).collect();
    c.bench_function("homography3_dlt_5", |b| {
        b.iter(|| Homography3::dlt(black_box(&x[..5]), black_box(&y[..5])))
    });
    c.bench_function("homography3_dlt_200", |b| b.iter(|| Homography3::dlt(black_box(&x), black_box(&y))));
}

criterion_group!(geometry, benches);
criterion_main!(geometry);
