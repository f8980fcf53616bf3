//! `headalign check SOURCE --calibration FILE`: the targetless health check of a stereo
//! calibration ([`headalign::check`]; the guide: docs/check.md). Maps the flags to
//! [`CheckOptions`], reads the calibration ([`headalign_io::import`]) and the views (as
//! `calibrate` does), prints the report (text, or one JSON object with `--json`) and, with
//! `--update OUT`, writes the corrected calibration in every format when the refit
//! validates.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;
use headalign::calibrate::{CalibrateViewsOptions, StereoViews};
use headalign::calibration::StereoCalibration;
use headalign::check::split::{SplitOptions, SplitReport, cross_validate};
use headalign::check::{Angles, CheckOptions, CheckReport, FullUpdate, check_views, update_full};
use headalign::observations::View;
use headalign_io::export::CalibrationFiles as _;
use serde_json::{Value, json};

use crate::recording::RecordingArgs;

/// Arguments of `headalign check`.
#[derive(Args)]
pub struct CheckArgs {
    /// The views: a folder of stereo pairs, an image or point session, a ROS 2 bag or an
    /// EuRoC folder (as `calibrate` reads them).
    pub source: PathBuf,
    /// The calibration to check: headalign's calibration.json, an OpenCV stereo YAML (M1 D1
    /// M2 D2 R T) or a Kalibr camchain.yaml.
    #[arg(long)]
    pub calibration: PathBuf,
    /// Write the corrected calibration here in every format, only when the refit validates
    /// (the rotation refitted, the intrinsics and lenses held unless --full).
    #[arg(long, value_name = "OUT")]
    pub update: Option<PathBuf>,
    /// With --update: refit the intrinsics and lenses too (self-calibration of the views,
    /// which needs rig motions between them; slow).
    #[arg(long, requires = "update")]
    pub full: bool,
    /// Also cross-validate: self-calibrate the first and the second half of the views and
    /// warn where the two differ by more than 3 of their sigmas (needs rig motions; slow).
    #[arg(long)]
    pub split: bool,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
    /// Baseline in metres, for a calibration whose translation is in baselines.
    #[arg(long)]
    pub baseline_m: Option<f64>,
    /// Corners detected per image (default 1500).
    #[arg(long)]
    pub corners: Option<usize>,
    /// Seed of the RANSAC.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Significance of a change, sigmas (verdict: recalibrate when a change is this
    /// significant and causes more than --depth-limit-pct at 5 m).
    #[arg(long, default_value_t = 5.0)]
    pub significance: f64,
    /// Depth error at 5 m that asks for recalibration, percent (a quarter of it: can-improve).
    #[arg(long, default_value_t = 1.0)]
    pub depth_limit_pct: f64,
    /// How a recording is read (bags, EuRoC folders).
    #[command(flatten)]
    pub recording: RecordingArgs,
}

/// The library's options from the flags.
fn options(args: &CheckArgs) -> CheckOptions {
    let mut o = CheckOptions {
        baseline_m: args.baseline_m,
        significance_sigmas: args.significance,
        depth_limit_pct: args.depth_limit_pct,
        ..CheckOptions::default()
    };
    if let Some(c) = args.corners {
        o.front_end.features.max_features = c;
    }
    o.ransac.seed = args.seed;
    o
}

/// The calibration file, its image size checked against (or taken from) the views'.
fn read_given(args: &CheckArgs, image_size: [u32; 2]) -> Result<StereoCalibration> {
    let mut given = headalign_io::import::read_calibration(&args.calibration)?;
    if given.image_size == [0, 0] {
        given.image_size = image_size;
    } else if given.image_size != image_size {
        bail!(
            "{} is a calibration of {}x{} images, the views are {}x{}",
            args.calibration.display(),
            given.image_size[0],
            given.image_size[1],
            image_size[0],
            image_size[1]
        );
    }
    Ok(given)
}

/// Run `headalign check`.
pub fn run(args: &CheckArgs) -> Result<()> {
    let options = options(args);
    options.validate()?;
    let split;
    let (mut report, full) = if headalign_io::session::is_point_session(&args.source) {
        let views: Vec<View> =
            headalign_io::session::read_point_session(&args.source)?.into_iter().map(|r| r.view).collect();
        let Some(size) = views.first().map(|v| v.capture.image_size) else { bail!("no views") };
        let given = read_given(args, size)?;
        split = split_of(StereoViews::Tracked(&views), args)?;
        checked(StereoViews::Tracked(&views), &given, &options, args)?
    } else {
        let views = crate::calibrate::load_views(&args.source, &args.recording)?;
        let Some(size) = views.first().map(|(_, v)| v.image_size()) else {
            bail!("no views in {}", args.source.display())
        };
        let given = read_given(args, size)?;
        let spinner =
            (!args.json).then(|| crate::progress::spinner(format!("checking {} pairs", views.len())));
        let r = checked(StereoViews::Images(&views), &given, &options, args)
            .with_context(|| format!("check of {}", args.source.display()));
        if let Some(s) = spinner {
            s.finish_and_clear();
        }
        split = split_of(StereoViews::Images(&views), args)?;
        r?
    };
    if let Some(f) = &full {
        report.updated = f.calibration.clone();
        report.update_refused = f.refused.clone();
    }
    let written = write_update(args, &report)?;
    if args.json {
        let mut v = json!({"schema": "headalign-check/1"});
        if let (Some(o), Value::Object(r)) = (v.as_object_mut(), serde_json::to_value(&report)?) {
            o.extend(r);
        }
        v["full_update"] =
            full.as_ref().map_or(Value::Null, |f| json!({"recheck": f.recheck, "refused": f.refused}));
        v["written"] = json!(written.iter().map(|p| p.display().to_string()).collect::<Vec<_>>());
        if let Some(s) = &split {
            v["split"] = serde_json::to_value(s)?;
        }
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        print_text(&report, &written);
        if let Some(s) = &split {
            print_split(s);
        }
    }
    Ok(())
}

/// `--split`: the cross-validation of the views ([`headalign::check::split`]).
fn split_of(views: StereoViews<'_>, args: &CheckArgs) -> Result<Option<SplitReport>> {
    if !args.split {
        return Ok(None);
    }
    let mut o = SplitOptions::default();
    if let Some(c) = args.corners {
        o.calibrate.front_end.features.max_features = c;
    }
    o.calibrate.calibrate.estimation.seed = args.seed;
    let spinner = (!args.json).then(|| crate::progress::spinner("cross-validating two halves".into()));
    let r = cross_validate(views, &o, &mut |_, _| {}).context("cross-validation (--split)");
    if let Some(s) = spinner {
        s.finish_and_clear();
    }
    Ok(Some(r?))
}

fn print_split(s: &SplitReport) {
    println!("cross-validation: halves {} | {}", s.halves[0].join(" "), s.halves[1].join(" "));
    for d in &s.differences {
        println!("  {}: {:+.4} +- {:.4} {} ({:.1} sigma)", d.name, d.difference, d.sigma, d.unit, d.z);
    }
    for w in &s.warnings {
        println!("warning: {w}");
    }
}

/// The check, and with `--full` the full update.
fn checked(
    views: StereoViews<'_>,
    given: &StereoCalibration,
    options: &CheckOptions,
    args: &CheckArgs,
) -> Result<(CheckReport, Option<FullUpdate>)> {
    let report = check_views(views, given, options)?;
    if !args.full {
        return Ok((report, None));
    }
    let mut calibrate = CalibrateViewsOptions { front_end: options.front_end.clone(), ..Default::default() };
    calibrate.calibrate.estimation.seed = args.seed;
    let full = update_full(views, given, &report, options, &calibrate)?;
    Ok((report, Some(full)))
}

/// `--update OUT`: the refitted calibration in every format, or a note on stderr why not.
fn write_update(args: &CheckArgs, report: &CheckReport) -> Result<Vec<PathBuf>> {
    let Some(dir) = &args.update else { return Ok(Vec::new()) };
    match (&report.updated, &report.update_refused) {
        (Some(c), _) => Ok(c.write_all(dir)?),
        (None, why) => {
            eprintln!("note: nothing written to {}: {}", dir.display(), why.as_deref().unwrap_or("no refit"));
            Ok(Vec::new())
        }
    }
}

fn angles(a: &Angles, s: &Angles) -> String {
    format!(
        "pitch {:+.4} +- {:.4}, yaw {:+.4} +- {:.4}, roll {:+.4} +- {:.4} deg",
        a.pitch, s.pitch, a.yaw, s.yaw, a.roll, s.roll
    )
}

/// The report as text (also `run --check-only`'s).
pub(crate) fn print_text(r: &CheckReport, written: &[PathBuf]) {
    let conclusive = if r.conclusive {
        ""
    } else {
        " (not conclusive: the sigmas allow a harmful change; check more pairs)"
    };
    println!("verdict: {}{conclusive}", r.verdict.name());
    println!("rotation change: {}", angles(&r.rotation_change_deg, &r.rotation_change_sigma_deg));
    let d = &r.depth_error_pct;
    println!(
        "depth error: {:.2} % at 1 m, {:.2} % at 2 m, {:.2} % at 5 m, {:.2} % at 10 m (disparity shift {:.3} px)",
        d.at_1m, d.at_2m, d.at_5m, d.at_10m, r.disparity_shift_px
    );
    println!(
        "vertical disparity |dy|: median {:.3} px, 90 % {:.3} px (refitted: {:.3}, {:.3})",
        r.vertical_disparity_px.median,
        r.vertical_disparity_px.p90,
        r.refit.vertical_disparity_px.median,
        r.refit.vertical_disparity_px.p90
    );
    println!(
        "Sampson distance: median {:.3} px, 90 % {:.3} px (refitted: {:.3}, {:.3}); noise {:.3} px",
        r.sampson_px.median, r.sampson_px.p90, r.refit.sampson_px.median, r.refit.sampson_px.p90, r.noise_px
    );
    if let Some(i) = &r.intrinsics_change {
        println!(
            "intrinsics (right vs left): fy {:+.3} +- {:.3} %, cy {:+.2} +- {:.2} px{}",
            i.fy_pct.value,
            i.fy_pct.sigma,
            i.cy_px.value,
            i.cy_px.sigma,
            if i.significant { " (changed)" } else { "" }
        );
    }
    println!(
        "matches: {} kept of {}; pairs' scatter factor {:.2}",
        r.matches[1], r.matches[0], r.scatter_ratio
    );
    for p in &r.pairs {
        let change = match (&p.rotation_change_deg, &p.rotation_change_sigma_deg) {
            (Some(a), Some(s)) => angles(a, s),
            _ => "too few matches".into(),
        };
        println!(
            "  {}: {} of {} matches, |dy| median {:.3} px; {change}",
            p.name, p.inliers, p.matches, p.vertical_disparity_px.median
        );
    }
    for s in &r.skipped {
        println!("skipped: {s}");
    }
    for p in written {
        println!("wrote {}", p.display());
    }
}
