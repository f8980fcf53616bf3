//! Experiment: the front end's time per view with and without patch refinement, measured
//! alternately in one process (so the machine's load affects both alike).
//! `cargo run --release -p headalign --example frontend_time -- [SEED] [REPEATS]`
//!
//! Renders the default scenario's reference view and the view after a pan rotation
//! (procedural textures), then tracks the pair `REPEATS` times (default 5) with each
//! setting (`refine: None`, the default (later views), with stereo partners) and prints the median seconds per
//! tracked pair and the observations handed on.
use std::time::Instant;

use headalign::frontend::{FrontEndOptions, Tracker};
use headalign_platform::{ImagingHead, Joint, StereoHead};
use headalign_sim::{Scenario, SimulatedHead};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let seed: u64 = args.get(1).map_or(Ok(1), |s| s.parse())?;
    let repeats: usize = args.get(2).map_or(Ok(5), |s| s.parse())?;
    let mut s = Scenario { seed, ..Scenario::default() };
    s.render.use_photos = false;
    let mut head = SimulatedHead::new(s.clone())?;
    let e0 = head.read_encoders()?;
    let first = head.capture_images()?;
    head.move_to(&e0.moved(Joint::Pan, s.rotation_deg))?;
    let second = head.capture_images()?;
    let settings: [(&str, FrontEndOptions); 3] = [
        ("off", FrontEndOptions { refine: None, ..FrontEndOptions::default() }),
        ("temporal (default)", FrontEndOptions::default()),
        ("stereo", FrontEndOptions { refine_stereo: true, ..FrontEndOptions::default() }),
    ];
    let mut times: Vec<Vec<f64>> = vec![Vec::new(); settings.len()];
    let mut counts = vec![[0usize; 2]; settings.len()];
    for _ in 0..repeats {
        for (k, (_, o)) in settings.iter().enumerate() {
            let t = Instant::now();
            let mut tracker = Tracker::new(o.clone())?;
            tracker.track(&first, "reference")?;
            let (_, report) = tracker.track(&second, "rotated")?;
            times[k].push(t.elapsed().as_secs_f64());
            counts[k] = report.observations;
        }
    }
    for (k, (name, _)) in settings.iter().enumerate() {
        times[k].sort_by(f64::total_cmp);
        println!(
            "{name}: median {:.3} s per two stereo views, second view's observations L/R {}/{}",
            times[k][times[k].len() / 2],
            counts[k][0],
            counts[k][1]
        );
    }
    Ok(())
}
