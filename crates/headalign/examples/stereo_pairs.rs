//! Stereo matches of one image pair as the front end delivers them (track id, left pixel,
//! right pixel; one line each), with patch refinement as `REFINE` says (`off`, `stereo`,
//! default temporal): to compare the right corners with and without stereo refinement
//! against a ground-truth disparity map.
//!
//! `cargo run --release -p headalign --example stereo_pairs -- LEFT.png RIGHT.png`

mod common;

use headalign::frontend::Tracker;
use headalign_platform::{Encoders, StereoImages};
use headalign_vision::GrayImage;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let [_, l, r] = args.as_slice() else { return Err("usage: stereo_pairs LEFT RIGHT".into()) };
    let images = StereoImages::new(
        Encoders::default(),
        GrayImage::load(std::path::Path::new(l))?,
        GrayImage::load(std::path::Path::new(r))?,
    )?;
    let mut tracker = Tracker::new(common::front_end_options())?;
    let (capture, report) = tracker.track(&images, "pair")?;
    eprintln!("{report:?}");
    let right: std::collections::HashMap<u64, _> = capture.right.iter().map(|o| (o.track, o.pixel)).collect();
    for o in &capture.left {
        if let Some(p) = right.get(&o.track) {
            println!("{} {:.4} {:.4} {:.4} {:.4}", o.track, o.pixel.x, o.pixel.y, p.x, p.y);
        }
    }
    Ok(())
}
