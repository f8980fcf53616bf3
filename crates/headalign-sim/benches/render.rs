//! Rendering one 768x576 view of the default scenario (textures baked beforehand).
//!
//! `cargo bench -p headalign-sim --bench render`

use criterion::{Criterion, criterion_group, criterion_main};
use headalign_geometry::distortion::Distortion;
use headalign_platform::Encoders;
use headalign_sim::render::{CameraView, RenderOptions, render_view};
use headalign_sim::{Scenario, SimulatedHead};

fn bench_render(c: &mut Criterion) {
    let Ok(mut head) = SimulatedHead::new(Scenario::default()) else { return };
    let scene = head.textured_scene();
    let (world_from_left, _) = head.world_from_cameras(&Encoders::default());
    let k = head.truth().left;
    let mut group = c.benchmark_group("render");
    group.sample_size(20);
    for (name, options) in [
        ("768x576_default_ss2_blur_noise", RenderOptions::default()),
        ("768x576_ss1_clean", RenderOptions { supersampling: 1, ..RenderOptions::clean() }),
        (
            "768x576_ss2_distorted",
            RenderOptions { distortion: Distortion::radial(-0.2, 0.05), ..RenderOptions::default() },
        ),
        (
            "768x576_ss2_equidistant",
            RenderOptions {
                distortion: Distortion::equidistant([0.0035, 0.0007, -0.0021, 0.0002]),
                ..RenderOptions::default()
            },
        ),
    ] {
        let view = CameraView {
            k: &k,
            distortion: &options.distortion,
            world_from_cam: &world_from_left,
            image_size: [768, 576],
        };
        group.bench_function(name, |b| b.iter(|| render_view(&scene.quads, &view, &options, 7)));
    }
    group.finish();
    let mut bake = c.benchmark_group("bake");
    bake.sample_size(10);
    let scenario = head.scenario().clone();
    bake.bench_function("textures_default_room", |b| {
        b.iter(|| SimulatedHead::new(scenario.clone()).map(|mut fresh| fresh.textured_scene().report.texels))
    });
    bake.finish();
}

criterion_group!(benches, bench_render);
criterion_main!(benches);
