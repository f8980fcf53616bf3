//! Render the default scenario's stereo pair at the initial readings and save it as PNG.
//!
//! `cargo run --release -p headalign-sim --example render_pair -- [seed] [out_dir]`
//! writes `left.png` and `right.png` (default: seed 1, the current directory).

use std::path::PathBuf;

use headalign_sim::{Scenario, SimulatedHead};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let seed: u64 = args.next().map(|s| s.parse()).transpose()?.unwrap_or(1);
    let dir = PathBuf::from(args.next().unwrap_or_else(|| ".".to_string()));
    std::fs::create_dir_all(&dir)?;
    let mut head = SimulatedHead::new(Scenario::default().with_seed(seed))?;
    let t = std::time::Instant::now();
    let report = head.textured_scene().report.clone();
    println!(
        "baked {} texels in {:.2?}; photos {}; procedural fallback {}",
        report.texels,
        t.elapsed(),
        report.photos_loaded.len(),
        report.procedural_fallback
    );
    let t = std::time::Instant::now();
    let (left, right) = head.render_stereo()?;
    println!("rendered the pair in {:.2?}", t.elapsed());
    left.save(&dir.join("left.png"))?;
    right.save(&dir.join("right.png"))?;
    println!("wrote {}", dir.display());
    Ok(())
}
