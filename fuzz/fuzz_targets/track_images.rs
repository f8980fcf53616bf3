//! Fuzz the image front end on small arbitrary images (what `align --images` runs on a
//! recorded session that passed the reader): two views of a stereo pair, each side
//! `w x h` with `w, h` in 1..=64 taken from the first two bytes and the pixels from the
//! rest (repeated to fill). Features, matching and tracking must give observations or a
//! typed error on any pixels and sizes, never a panic.
#![no_main]

use headalign::tracking::{FrontEndOptions, Tracker};
use headalign_platform::{Encoders, StereoImages};
use headalign_vision::GrayImage;
use libfuzzer_sys::fuzz_target;

fn image(w: u32, h: u32, pixels: &[u8], offset: usize) -> Option<GrayImage> {
    if pixels.is_empty() {
        return None;
    }
    let n = (w * h) as usize;
    let data = (0..n).map(|i| pixels[(i + offset) % pixels.len()]).collect();
    GrayImage::new(w, h, data).ok()
}

fuzz_target!(|data: &[u8]| {
    if data.len() < 3 {
        return;
    }
    let (w, h) = (u32::from(data[0] % 64) + 1, u32::from(data[1] % 64) + 1);
    let pixels = &data[2..];
    let Ok(mut tracker) = Tracker::new(FrontEndOptions::default()) else { return };
    for (k, elevation) in [0.0, 3.0].into_iter().enumerate() {
        let n = (w * h) as usize;
        let (Some(left), Some(right)) =
            (image(w, h, pixels, 2 * k * n), image(w, h, pixels, (2 * k + 1) * n))
        else {
            return;
        };
        let encoders = Encoders { elevation, ..Encoders::default() };
        let Ok(images) = StereoImages::new(encoders, left, right) else { return };
        if tracker.track(&images, &format!("view{k}")).is_err() {
            return;
        }
    }
});
