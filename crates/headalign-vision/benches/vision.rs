//! Benchmarks of the vision hot paths on a real texture, for comparison with OpenCV
//! (`bench/opencv_compare.py` runs the same three operations on the same crops):
//! - `detect_describe_768x576`: FAST-9 + Harris + bucketing + BRIEF-256, 1000 features;
//! - `match_1000x1000`: brute-force Hamming, mutual check + ratio test;
//! - `pyramid_register`: coarse-to-fine ZNCC registration of two 768x576 crops shifted by
//!   (+20, +12) px, pyramids included.
//!
//! Image: OpenCV sample `textures/building.jpg` (868x600, Apache-2.0/BSD-3-Clause, see
//! `data/opencv_samples/README.md`), cropped to 768x576 at (60, 20) for the reference and
//! at (40, 8) for the moved image. Default path: `data/opencv_samples/textures/building.jpg`
//! in the repository; override it with `HEADALIGN_BENCH_IMAGE`. An unreadable image stops
//! the benchmark with the reason. Thread count: set `RAYON_NUM_THREADS=1` for one thread.

use std::hint::black_box;
use std::path::PathBuf;

use criterion::{Criterion, criterion_group, criterion_main};
use headalign_vision::{
    FeatureOptions, GrayImage, MatchOptions, RegistrationOptions, detect_and_describe, match_descriptors,
    register_translation,
};

/// The default image, in the repository's `data/` folder.
const DEFAULT_IMAGE: &str =
    concat!(env!("CARGO_MANIFEST_DIR"), "/../../data/opencv_samples/textures/building.jpg");

fn crop(img: &GrayImage, x0: u32, y0: u32, w: u32, h: u32) -> GrayImage {
    let data = (y0..y0 + h).flat_map(|y| img.row(y)[x0 as usize..(x0 + w) as usize].to_vec()).collect();
    GrayImage::new(w, h, data).expect("crop inside the image")
}

/// The reference and moved crops, or why there are none.
fn images() -> Result<(GrayImage, GrayImage), String> {
    let path = std::env::var("HEADALIGN_BENCH_IMAGE")
        .map(PathBuf::from)
        .unwrap_or_else(|_| PathBuf::from(DEFAULT_IMAGE));
    if !path.is_file() {
        return Err(format!(
            "{} is absent (the repository's data/ folder, or set HEADALIGN_BENCH_IMAGE)",
            path.display()
        ));
    }
    let full = GrayImage::load(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    if full.width() < 828 || full.height() < 596 {
        return Err(format!("{}: the bench image must be at least 828x596", path.display()));
    }
    Ok((crop(&full, 60, 20, 768, 576), crop(&full, 40, 8, 768, 576)))
}

fn bench(c: &mut Criterion) {
    let (reference, moved) = match images() {
        Ok(crops) => crops,
        Err(why) => panic!("vision benchmarks: {why}"),
    };
    let fo = FeatureOptions::default();
    c.bench_function("detect_describe_768x576", |b| {
        b.iter(|| detect_and_describe(black_box(&reference), &fo).expect("features"))
    });
    let fa = detect_and_describe(&reference, &fo).expect("features");
    let fb = detect_and_describe(&moved, &fo).expect("features");
    let mo = MatchOptions::default();
    let m = match_descriptors(&fa.descriptors, &fb.descriptors, &mo).expect("match");
    let ok = m
        .iter()
        .filter(|m| {
            let (ka, kb) = (fa.keypoints[m.a], fb.keypoints[m.b]);
            (kb.x - ka.x - 20.0).hypot(kb.y - ka.y - 12.0) < 1.5
        })
        .count();
    eprintln!("features {} / {}, matches {} ({} at the true shift)", fa.len(), fb.len(), m.len(), ok);
    c.bench_function("match_1000x1000", |b| {
        b.iter(|| {
            match_descriptors(black_box(&fa.descriptors), black_box(&fb.descriptors), &mo).expect("match")
        })
    });
    let ro = RegistrationOptions::default();
    let r = register_translation(&reference, &moved, &ro).expect("registration");
    eprintln!("registration shift {:?} (true [20, 12]), score {:.4}", r.shift, r.score);
    c.bench_function("pyramid_register", |b| {
        b.iter(|| register_translation(black_box(&reference), black_box(&moved), &ro).expect("registration"))
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(30).measurement_time(std::time::Duration::from_secs(3));
    targets = bench
}
criterion_main!(benches);
