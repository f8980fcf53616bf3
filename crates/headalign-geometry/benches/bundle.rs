//! Time of one rig bundle adjustment on the default synthetic problem
//! ([`headalign_geometry::synthetic`]): 3 views (reference, elevation +3 deg, pan +3 deg),
//! Joints model, 200 points, ~1200 observations, 1 px noise, 10 % outliers, Huber loss,
//! started from the truth perturbed (~1.5 % on K, ~1 deg on the rig and axes, 5 cm on
//! points). And the adjustment of a sequence against its length
//! ([`headalign_geometry::synthetic::sequence`]: 25 to 200 free views along a wall, each
//! overlapping only its neighbours, 60 points per view, 0.5 px noise, Huber loss, from the
//! perturbed truth, ten iterations and the covariance): the sparse Schur complement and
//! the profile Cholesky make its time linear in the views (`sequence/N` in criterion's
//! report).

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

fn bench_sequence(c: &mut Criterion) {
    let mut group = c.benchmark_group("bundle_adjust sequence");
    group.sample_size(10);
    for views in [25, 50, 100, 200] {
        let seq = headalign_geometry::synthetic::sequence(1, views, 1, 60 * views, 0.5);
        let start = perturb(&seq.synth.truth, 10);
        // Ten iterations exactly (no tolerance stops them) and the covariance.
        let opts = BundleOptions {
            max_iterations: 10,
            function_tolerance: 0.0,
            parameter_tolerance: 0.0,
            ..BundleOptions::default()
        };
        if let Ok(r) = bundle_adjust(&start, &seq.synth.obs, &opts) {
            eprintln!(
                "{views} views: {} observations, {} points, {:?}",
                seq.synth.obs.len(),
                seq.synth.truth.points.len(),
                r.report
            );
        }
        group.bench_function(format!("{views}"), |b| {
            b.iter(|| bundle_adjust(std::hint::black_box(&start), &seq.synth.obs, &opts))
        });
    }
    group.finish();
}

criterion_group!(benches, bench, bench_sequence);
criterion_main!(benches);
