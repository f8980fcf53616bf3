//! Benchmark of the estimation core: F, frame, two 3D homographies, linear
//! self-calibration and the rig bundle adjustment, on the default simulated scenario
//! (1 px noise, 200 points, 10 % outliers, 3 deg rotations).

use criterion::{Criterion, criterion_group, criterion_main};
use headalign::estimate::{EstimationOptions, estimate_rig};
use headalign::observations::View;
use headalign_platform::{Joint, StereoHead};
use headalign_sim::{Scenario, SimulatedHead};

fn views() -> Vec<View> {
    let mut head = SimulatedHead::new(Scenario::default()).expect("default scenario is valid");
    let e0 = head.read_encoders().expect("simulator reads");
    let mut out = Vec::new();
    for (name, enc) in
        [("initial", e0), ("elevation", e0.moved(Joint::Elevation, 3.0)), ("pan", e0.moved(Joint::Pan, 3.0))]
    {
        head.move_to(&enc).expect("simulator moves");
        out.push(View { name: name.into(), capture: head.capture().expect("simulator captures") });
    }
    out
}

fn bench(c: &mut Criterion) {
    let v = views();
    let options = EstimationOptions::default();
    c.bench_function("estimate_rig default scenario", |b| {
        b.iter(|| estimate_rig(std::hint::black_box(&v), &options).expect("estimation succeeds"))
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
