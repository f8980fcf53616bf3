//! The time of `headalign check` on the four EuRoC pairs (data/euroc_v101_pairs) against
//! its bar (docs/check.md): reading the pairs, the front end of `calibrate` on them, and
//! the check ([`headalign::check::check_views`]: its stereo front end and its refit).
//! Prints the median of 5 runs of each, seconds.
//!
//! `cargo bench -p headalign-io --bench check`

use std::path::Path;
use std::time::Instant;

use headalign::calibrate::views::stereo_only;
use headalign::calibrate::{CalibrateOptions, StereoViews, track_views};
use headalign::check::{CheckOptions, check_views};
use headalign_io::folder::{FolderOptions, read_folder};
use headalign_io::import::read_calibration;

/// The median seconds of `runs` calls of `f`.
fn median_seconds(runs: usize, mut f: impl FnMut()) -> f64 {
    let mut t: Vec<f64> = (0..runs)
        .map(|_| {
            let t0 = Instant::now();
            f();
            t0.elapsed().as_secs_f64()
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let dir = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../../data/euroc_v101_pairs"));
    let given = read_calibration(&dir.join("opencv_stereo.yaml"))?;
    let read = || read_folder(dir, &FolderOptions::default(), &mut |_, _| {});
    let views = read()?;
    let options = CheckOptions::default();
    let runs = 5;
    let t_read = median_seconds(runs, || {
        let _ = read();
    });
    let t_calibrate_front = median_seconds(runs, || {
        let _ = track_views(&views, &options.front_end, &CalibrateOptions::default());
    });
    let t_one_view = median_seconds(runs, || {
        let _ = stereo_only(&views[..1], &options.front_end);
    });
    let t_stereo = median_seconds(runs, || {
        let _ = stereo_only(&views, &options.front_end);
    });
    let t_check = median_seconds(runs, || {
        let _ = check_views(StereoViews::Images(&views), &given, &options);
    });
    println!("check of {} pairs (median of {runs} runs, seconds):", views.len());
    println!("  reading the pairs                    {t_read:.3}");
    println!("  calibrate's front end on the pairs   {t_calibrate_front:.3}");
    println!("  one pair's stereo front end          {t_one_view:.3}");
    println!("  check: its stereo front end          {t_stereo:.3}");
    println!("  check: all (front end and refit)     {t_check:.3}");
    println!(
        "  bar: check {:.3} <= reading + calibrate's front end {:.3}: {}",
        t_check,
        t_read + t_calibrate_front,
        if t_check <= t_read + t_calibrate_front { "yes" } else { "no" }
    );
    Ok(())
}
