//! Time of one rig bundle adjustment on the default synthetic problem
//! ([`headalign_geometry::synthetic`]): 3 views (reference, elevation +3 deg, pan +3 deg),
//! Joints model, 200 points, ~1200 observations, 1 px noise, 10 % outliers, Huber loss,
//! started from the truth perturbed (~1.5 % on K, ~1 deg on the rig and axes, 5 cm on
//! points).

use criterion::{Criterion, criterion_group, criterion_main};
use headalign_geometry::bundle::{BundleOptions, bundle_adjust};
use headalign_geometry::synthetic::{perturb, synth};

fn bench(c: &mut Criterion) {
    let problem = synth(1, 200, 1.0, 0.10, false);
    let start = perturb(&problem.truth, 10);
    let opts = BundleOptions::default();
    if let Ok(r) = bundle_adjust(&start, &problem.obs, &opts) {
        eprintln!("{} observations, {:?}", problem.obs.len(), r.report);
    }
    c.bench_function("bundle_adjust 3 views 200 points joints huber", |b| {
        b.iter(|| bundle_adjust(std::hint::black_box(&start), &problem.obs, &opts))
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
