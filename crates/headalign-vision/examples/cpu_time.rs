//! Process CPU time per call of the three benchmarked operations (same image and crops as
//! `benches/vision.rs`): on a loaded machine a fairer cross-check of the criterion wall
//! times, comparable with the CPU line of `bench/opencv_compare.py`. Linux only (reads
//! `/proc/self/stat`, 10 ms ticks, so many repetitions are averaged).
//!
//! `RAYON_NUM_THREADS=1 cargo run --release -p headalign-vision --example cpu_time [REPS]`

use std::path::PathBuf;

use headalign_vision::{
    FeatureOptions, GrayImage, MatchOptions, RegistrationOptions, detect_and_describe, match_descriptors,
    register_translation,
};

fn crop(img: &GrayImage, x0: u32, y0: u32, w: u32, h: u32) -> Result<GrayImage, Box<dyn std::error::Error>> {
    let data = (y0..y0 + h).flat_map(|y| img.row(y)[x0 as usize..(x0 + w) as usize].to_vec()).collect();
    Ok(GrayImage::new(w, h, data)?)
}

/// User + system time of this process, ms.
fn cpu_ms() -> Result<f64, Box<dyn std::error::Error>> {
    let stat = std::fs::read_to_string("/proc/self/stat")?;
    let rest = stat.rsplit_once(')').ok_or("bad /proc/self/stat")?.1;
    let f: Vec<&str> = rest.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the line, 11 and 12 after the command name.
    Ok((f[11].parse::<f64>()? + f[12].parse::<f64>()?) * 10.0)
}

fn per_call<R>(reps: usize, mut f: impl FnMut() -> R) -> Result<f64, Box<dyn std::error::Error>> {
    std::hint::black_box(f());
    let t = cpu_ms()?;
    for _ in 0..reps {
        std::hint::black_box(f());
    }
    Ok((cpu_ms()? - t) / reps as f64)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let reps: usize = std::env::args().nth(1).map(|s| s.parse()).transpose()?.unwrap_or(300);
    let path = std::env::var("HEADALIGN_BENCH_IMAGE")
        .map(PathBuf::from)
        .unwrap_or("/work/shared/data/opencv_samples/textures/building.jpg".into());
    let full = GrayImage::load(&path)?;
    let (a, b) = (crop(&full, 60, 20, 768, 576)?, crop(&full, 40, 8, 768, 576)?);
    let fo = FeatureOptions::default();
    let (fa, fb) = (detect_and_describe(&a, &fo)?, detect_and_describe(&b, &fo)?);
    let ro = RegistrationOptions::default();
    let mo = MatchOptions::default();
    let det = per_call(reps, || detect_and_describe(&a, &fo))?;
    let mat = per_call(reps, || match_descriptors(&fa.descriptors, &fb.descriptors, &mo))?;
    let reg = per_call(reps, || register_translation(&a, &b, &ro))?;
    println!(
        "CPU per call (process time, mean of {reps}): detect+describe {det:.2} ms, match {mat:.2} ms, \
         registration {reg:.2} ms"
    );
    Ok(())
}
