//! Benchmark of the estimation core: F, frame, two 3D homographies, linear
//! self-calibration and the rig bundle adjustment, on the default simulated scenario
//! (1 px noise, 200 points, 10 % outliers, 3 deg rotations both ways: five rig views).

use criterion::{Criterion, criterion_group, criterion_main};
use headalign::observations::View;
use headalign::procedure::{VergeTiltOptions, capture_plan};
use headalign::verge_tilt::{EstimationOptions, estimate_rig};
use headalign_platform::StereoHead;
use headalign_sim::{Scenario, SimulatedHead};

fn views() -> Vec<View> {
    let mut head = SimulatedHead::new(Scenario::default()).expect("default scenario is valid");
    let e0 = head.read_encoders().expect("simulator reads");
    let mut out = Vec::new();
    for (name, enc) in capture_plan(&e0, &VergeTiltOptions::default()) {
        head.move_to(&enc).expect("simulator moves");
        out.push(View { name, capture: head.capture().expect("simulator captures") });
    }
    out.pop(); // the vergence view is not part of the rig estimation
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
