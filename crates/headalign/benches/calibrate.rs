//! Where `calibrate` spends its time (issue 47, item 1): the whole self-calibration of
//! [`calibrate_views`] (what `headalign calibrate FOLDER` runs on images), per stage, on
//! the shared EuRoC pairs and on a rendered 10-view sequence, at each thread count asked.
//!
//! The cases:
//! - `pairs-auto`, `pairs-radtan`, `pairs-equidistant`: pairs 3 and 2 of
//!   `data/euroc_v101_pairs` (752x480, raw: the dataset's barrel lens), in that order as
//!   `docs/results-real.md` copies them (`two/left00.png` is pair 3), with the command's
//!   default flags (`auto` is the default lens for images) or `--lens radtan` /
//!   `--lens equidistant`;
//! - `rendered-10`: the first 10 views of the sequence benchmark's path (`benches/sequence.rs`:
//!   the same simulated rig, 752x480, no lens distortion, 2 deg further about the vertical
//!   per view, the pitch swinging +-6 deg and the height +-0.15 m), rendered once into
//!   `$CARGO_TARGET_TMPDIR/calibrate-rendered-10/`, default flags.
//!
//! The stage times are the library's own ([`headalign::timing`]: thread-seconds per
//! stage, exclusive of the stages nested in it); "reading" is the PNG decoding of this
//! program, timed by the same counters; "other" is the call's wall time less the timed
//! stages (rig selection, the depth check's plane fits, the reports), meaningful with one
//! thread only. Each case runs in a rayon pool of the thread count given (the front end's
//! corner detection and the parallel loops of the chain use it).
//!
//! `cargo bench -p headalign --bench calibrate` (add `-- --threads 1,2` for the thread
//! counts, default `1,2`, and `--cases pairs-auto,rendered-10` to choose cases).

use std::path::{Path, PathBuf};
use std::time::Instant;

use headalign::calibrate::{
    CalibrateOptions, CalibrateViewsOptions, LensChoice, StereoViews, calibrate_views,
};
use headalign::timing::{Stage, StageTimes, time};
use headalign_geometry::distortion::LensKind;
use headalign_platform::{GrayImage, StereoImages};

#[path = "shared/rendered_path.rs"]
mod rendered_path;
use rendered_path::{Error, render};

/// Views of the rendered case.
const RENDERED: usize = 10;

/// Stereo pairs `(left, right)` read as named views, timed as [`Stage::Reading`].
fn read(files: &[(PathBuf, PathBuf)]) -> Result<Vec<(String, StereoImages)>, Error> {
    time(Stage::Reading, || {
        files
            .iter()
            .enumerate()
            .map(|(i, (l, r))| {
                let images = StereoImages::new(Default::default(), GrayImage::load(l)?, GrayImage::load(r)?)?;
                Ok((format!("left{i:02}"), images))
            })
            .collect()
    })
}

/// The files and the lens of a case.
fn case(name: &str, rendered: &Path) -> Result<(Vec<(PathBuf, PathBuf)>, LensChoice), Error> {
    let pairs = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../data/euroc_v101_pairs");
    let euroc = |lens| {
        let files = [3, 2]
            .iter()
            .map(|j| (pairs.join(format!("left_img_{j}.png")), pairs.join(format!("right_img_{j}.png"))))
            .collect();
        Ok((files, lens))
    };
    match name {
        "pairs-auto" => euroc(LensChoice::Auto),
        "pairs-radtan" => euroc(LensChoice::Model(LensKind::RadialTangential)),
        "pairs-equidistant" => euroc(LensChoice::Model(LensKind::Equidistant)),
        "rendered-10" => {
            render(rendered, RENDERED, 2)?;
            let files = (0..RENDERED)
                .map(|i| {
                    (rendered.join(format!("left{i:02}.png")), rendered.join(format!("right{i:02}.png")))
                })
                .collect();
            Ok((files, LensChoice::Auto))
        }
        _ => Err(format!("unknown case {name}").into()),
    }
}

/// The command's options for images with `lens` (`headalign calibrate` without flags, or
/// with `--lens`).
fn options(lens: LensChoice) -> CalibrateViewsOptions {
    let calibrate = CalibrateOptions {
        lens,
        lens_terms: headalign::calibrate::lens_terms(lens, None),
        ..CalibrateOptions::default()
    };
    CalibrateViewsOptions { calibrate, automatic_density: true, ..CalibrateViewsOptions::default() }
}

/// One case at `threads` threads: the table's rows.
fn run(name: &str, threads: usize, rendered: &Path) -> Result<(), Error> {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
    pool.install(|| -> Result<(), Error> {
        let (files, lens) = case(name, rendered)?;
        let before = StageTimes::now();
        let views = read(&files)?;
        let reading = StageTimes::since(&before);
        let t0 = Instant::now();
        let r = calibrate_views(StereoViews::Images(&views), &options(lens), &mut |_| {})?;
        let wall = t0.elapsed().as_secs_f64();
        let t = r.timing;
        let s = &r.calibration.bundle.state;
        println!(
            "{name}, {threads} thread(s): wall {wall:.2} s (calibrate_views), reading {:.2} s; f {:.1} / {:.1} px; lens {}",
            reading.seconds_of(Stage::Reading),
            s.left.fx,
            s.right.fx,
            r.calibration.report.lens_selection.as_ref().map_or_else(|| format!("{lens:?}"), |l| l.spec.label())
        );
        println!("| stage | seconds | calls |");
        println!("| --- | ---: | ---: |");
        println!(
            "| {} | {:.2} | {} |",
            Stage::Reading.label(),
            reading.seconds_of(Stage::Reading),
            reading.calls_of(Stage::Reading)
        );
        for stage in Stage::ALL.into_iter().filter(|&s| s != Stage::Reading) {
            println!("| {} | {:.2} | {} |", stage.label(), t.seconds_of(stage), t.calls_of(stage));
        }
        println!("| other (wall less the stages) | {:.2} | |", wall - t.total());
        println!("| calibrate_views wall | {wall:.2} | |\n");
        Ok(())
    })
}

fn main() -> Result<(), Error> {
    let args: Vec<String> = std::env::args().collect();
    let list = |flag: &str, default: &str| -> Vec<String> {
        args.iter()
            .position(|a| a == flag)
            .and_then(|i| args.get(i + 1))
            .map_or(default, String::as_str)
            .split(',')
            .map(str::to_string)
            .collect()
    };
    let threads: Vec<usize> = list("--threads", "1,2").iter().map(|t| t.parse()).collect::<Result<_, _>>()?;
    let cases = list("--cases", "pairs-auto,pairs-radtan,pairs-equidistant,rendered-10");
    let rendered = Path::new(env!("CARGO_TARGET_TMPDIR")).join("calibrate-rendered-10");
    for name in &cases {
        for &n in &threads {
            run(name, n, &rendered)?;
        }
    }
    Ok(())
}
