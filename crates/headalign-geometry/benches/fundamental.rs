//! Time of the fundamental-matrix RANSAC on a calibration-sized match set (no criterion:
//! a fixed number of repetitions, the median and minimum printed).
//!
//! The data: 1500 matches of a simulated stereo rig (752x480, focal 458 px, baseline
//! 0.11 m, 2 deg of relative yaw), 70 % of the points on one wall 3 m away (as the
//! EuRoC pairs' room is), the rest at 1.5-8 m, 0.5 px Gaussian noise, 30 % of the
//! right points replaced by uniform outliers. Two timings:
//! - `estimate_fundamental_1500`: [`estimate_fundamental`] with the default options
//!   (1.5 px threshold), as `calibrate` calls it;
//! - `fit_minimal_x1000`: [`FundamentalEstimator::fit_minimal`] on 1000 fixed random
//!   7-point samples of the same data.
//!
//! Each line also prints a checksum of the result (inliers, iterations, models), so two
//! builds can be checked to decide the same.
//!
//! `cargo bench -p headalign-geometry --bench fundamental` (add `-- REPS`, default 15).

use std::hint::black_box;
use std::time::Instant;

use headalign_geometry::camera::Intrinsics;
use headalign_geometry::fundamental::{FundamentalEstimator, estimate_fundamental};
use headalign_geometry::ransac::{Estimator, RansacOptions};
use nalgebra::{Isometry3, Point2, Point3, Translation3, UnitQuaternion, Vector2};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

type Pairs = Vec<(Point2<f64>, Point2<f64>)>;

fn matches(n: usize) -> Pairs {
    let mut rng = ChaCha8Rng::seed_from_u64(47);
    let k = Intrinsics::new(458.0, 457.0, 367.0, 248.0);
    let right_from_left = Isometry3::from_parts(
        Translation3::new(-0.11, 0.002, 0.001),
        UnitQuaternion::from_euler_angles(0.003, 0.035, -0.002),
    );
    let noise = Normal::new(0.0, 0.5).unwrap_or_else(|_| unreachable!());
    let inside = |p: &Point2<f64>| (0.0..752.0).contains(&p.x) && (0.0..480.0).contains(&p.y);
    let mut pairs = Vec::with_capacity(n);
    while pairs.len() < n {
        let (x, y) = (rng.random_range(-3.0..3.0), rng.random_range(-2.0..2.0));
        let z = if rng.random_range(0.0..1.0) < 0.7 { 3.0 + 0.1 * x } else { rng.random_range(1.5..8.0) };
        let p = Point3::new(x, y, z);
        let (Some(l), Some(r)) = (k.project(&p), k.project(&(right_from_left * p))) else { continue };
        if !inside(&l) || !inside(&r) {
            continue;
        }
        let mut jitter = || Vector2::new(noise.sample(&mut rng), noise.sample(&mut rng));
        let (l, r) = (l + jitter(), r + jitter());
        pairs.push((l, r));
    }
    let n_out = n * 3 / 10;
    for i in 0..n_out {
        let j = (i * 7919) % n;
        pairs[j].1 = Point2::new(rng.random_range(0.0..752.0), rng.random_range(0.0..480.0));
    }
    pairs
}

fn time<T>(reps: usize, mut f: impl FnMut() -> T) -> (f64, f64, T) {
    let mut times = Vec::with_capacity(reps);
    let mut last = None;
    for _ in 0..reps {
        let t0 = Instant::now();
        last = Some(black_box(f()));
        times.push(t0.elapsed().as_secs_f64());
    }
    times.sort_by(f64::total_cmp);
    let Some(last) = last else { unreachable!() };
    (times[times.len() / 2], times[0], last)
}

fn main() {
    let reps = std::env::args().skip(1).find_map(|a| a.parse::<usize>().ok()).unwrap_or(15);
    let pairs = matches(1500);
    let opts = RansacOptions::default();
    let (median, min, rep) = time(reps, || estimate_fundamental(black_box(&pairs), &opts));
    match rep {
        Ok(rep) => println!(
            "estimate_fundamental_1500  median {:.2} ms  min {:.2} ms  ({reps} runs)  inliers {} iterations {} \
             rms {:.9} F[0] {:.12e}",
            median * 1e3,
            min * 1e3,
            rep.inliers.len(),
            rep.iterations,
            rep.rms_inlier_residual,
            rep.model.0[(0, 0)]
        ),
        Err(e) => println!("estimate_fundamental_1500 failed: {e}"),
    }
    let est = FundamentalEstimator::default();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let samples: Vec<Vec<usize>> = (0..1000)
        .map(|_| {
            let mut s = Vec::with_capacity(7);
            while s.len() < 7 {
                let i = rng.random_range(0..pairs.len());
                if !s.contains(&i) {
                    s.push(i);
                }
            }
            s
        })
        .collect();
    let (median, min, models) =
        time(reps, || samples.iter().map(|s| est.fit_minimal(black_box(&pairs), s)).collect::<Vec<_>>());
    let count: usize = models.iter().map(Vec::len).sum();
    let sum: f64 = models.iter().flatten().map(|f| f.0[(2, 2)].abs()).sum();
    println!(
        "fit_minimal_x1000          median {:.2} ms  min {:.2} ms  ({reps} runs)  models {count} sum|F22| {sum:.12e}",
        median * 1e3,
        min * 1e3
    );
}
