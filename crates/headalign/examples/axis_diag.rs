//! Diagnostic (not a test): where the aligned readings' error comes from, split by cause,
//! against the sigma each propagation predicts. For seeds A..=B at pixel noise N (initial
//! head position `seed mod 3` of `experiment fig5-verge-tilt`'s three, which that
//! experiment assigns by trial, `(seed - 1) mod 3` from `--seed 1`), each line gives, for
//! the aligned elevation, left and right vergence (degrees):
//! - `fixed`: error with the estimated calibration and the TRUE vergence axes (what
//!   `alignment_sigmas` describes: axes exact);
//! - `clean`: error with the estimated calibration and the axes re-measured from a
//!   noise-free capture at the axis source's readings (calibration part, axes following);
//! - `total`: the procedure's error;
//! - the sigmas: `alignment_sigmas` (main), `alignment_sigmas_measured` with the pose
//!   noise at ~0 (calibration part) and as reported (total).
//!
//! `cargo run --release -p headalign --example axis_diag -- A B N` (CSV on stdout).
//! `... -- A B N crb`: the Cramer-Rao bound's elevation parts at N px as `experiment`
//! would evaluate them with the axes' measurement (axes held, calibration part, total) and
//! where the noise-free run's axes came from.
use headalign::alignment::{VergeAxes, measure_cameras, solve_alignment, verge_axes_from_motion};
use headalign::estimate::EstimationOptions;
use headalign::procedure::{VergeTiltOutcome, alignment_sigmas, alignment_sigmas_measured};
use headalign_platform::Encoders;
use headalign_sim::{Scenario, SimulatedHead};

mod common;

fn run(s: &Scenario, initial: &Encoders) -> Option<(SimulatedHead, VergeTiltOutcome)> {
    common::verge_tilt_trial(s, initial, s.seed)
}

fn line(seed: u64, noise: f64) -> Option<String> {
    let positions = [
        Encoders::default(),
        Encoders { pan: 4.0, elevation: 4.0, verge_left: 2.0, verge_right: -2.0 },
        Encoders { pan: -4.0, elevation: -4.0, verge_left: -2.0, verge_right: 2.0 },
    ];
    let initial = positions[(seed % 3) as usize];
    let sc = Scenario { seed, noise_px: noise, ..Scenario::default() };
    let (head, noisy) = run(&sc, &initial)?;
    let (_, clean) = run(&Scenario { noise_px: 1e-300, ..sc.clone() }, &initial)?;
    let c = &noisy.calibration;
    let st = &c.bundle.state;
    let reference = c.reference_encoders;
    let aligned = head.aligned_encoders();
    let truth = [
        aligned.elevation - reference.elevation,
        aligned.verge_left - reference.verge_left,
        aligned.verge_right - reference.verge_right,
    ];
    let err = |s: &headalign::alignment::AlignmentSolution| {
        [
            s.delta_elevation_deg - truth[0],
            s.delta_verge_left_deg - truth[1],
            s.delta_verge_right_deg - truth[2],
        ]
    };
    let total = err(&noisy.solution);
    let fixed = err(&solve_alignment(st, &clean.verge_axes, &reference).ok()?);
    // Axes re-measured from noise-free captures at the sources' readings.
    let remeasure = |src: &Option<headalign::procedure::AxisMeasurement>, left: bool| {
        let src = src.as_ref()?;
        let exact = head.exact_capture(&src.capture.encoders);
        let m = measure_cameras(c, &exact, &src.measured.ref_from_left, &src.measured.ref_from_right).ok()?;
        let a = verge_axes_from_motion(st, &reference, &exact.encoders, &m).ok()?;
        if left { a.left } else { a.right }
    };
    let axes = VergeAxes {
        left: remeasure(&noisy.axis_sources.left, true).or(noisy.verge_axes.left),
        right: remeasure(&noisy.axis_sources.right, false).or(noisy.verge_axes.right),
    };
    let cleanview = err(&solve_alignment(st, &axes, &reference).ok()?);
    let main = alignment_sigmas(c, &noisy.verge_axes, &reference).ok()?;
    let calib_part =
        alignment_sigmas_measured(c, &noisy.verge_axes, &noisy.axis_sources, &reference, Some(1e-9)).ok()?;
    let rep = noisy.sigmas;
    let s3 =
        |s: &headalign::procedure::AlignmentSigmas| [s.elevation_deg, s.verge_left_deg, s.verge_right_deg];
    let src_elev = |src: &Option<headalign::procedure::AxisMeasurement>| {
        src.as_ref().map_or(f64::NAN, |s| s.capture.encoders.elevation - reference.elevation)
    };
    let mut out = format!(
        "{seed},{:.3},{:.3},{}",
        src_elev(&noisy.axis_sources.left),
        src_elev(&noisy.axis_sources.right),
        noisy.checks.len()
    );
    for v in [total, fixed, cleanview, s3(&main), s3(&calib_part), s3(&rep)] {
        for x in v {
            out += &format!(",{x:.6}");
        }
    }
    Some(out)
}

/// The Cramer-Rao bound's parts as `experiment` evaluates them (noise-free run, covariance
/// at its state for `noise` px; position `(seed - 1) mod 3` as trial `seed - 1` of
/// `fig5-verge-tilt --seed 1`): axes held, calibration part, total.
fn crb_line(seed: u64, noise: f64) -> Option<String> {
    let positions = [
        Encoders::default(),
        Encoders { pan: 4.0, elevation: 4.0, verge_left: 2.0, verge_right: -2.0 },
        Encoders { pan: -4.0, elevation: -4.0, verge_left: -2.0, verge_right: 2.0 },
    ];
    let initial = positions[((seed - 1) % 3) as usize];
    let sc = Scenario { seed, noise_px: 1e-300, ..Scenario::default() };
    let (_, clean) = run(&sc, &initial)?;
    let calib = &clean.calibration;
    let mut options = EstimationOptions::default().bundle;
    options.max_iterations = 0;
    options.robust = headalign_geometry::bundle::RobustLoss::None;
    options.noise_sigma_px = Some(noise);
    let bundle =
        headalign_geometry::bundle::bundle_adjust(&calib.bundle.state, &calib.observations, &options).ok()?;
    let at = headalign::estimate::RigCalibration { bundle, ..calib.clone() };
    let r = calib.reference_encoders;
    let held = alignment_sigmas(&at, &clean.verge_axes, &r).ok()?;
    let part = alignment_sigmas_measured(&at, &clean.verge_axes, &clean.axis_sources, &r, Some(1e-9)).ok()?;
    let total =
        alignment_sigmas_measured(&at, &clean.verge_axes, &clean.axis_sources, &r, Some(noise)).ok()?;
    let src = |s: &Option<headalign::procedure::AxisMeasurement>| {
        s.as_ref().map_or(f64::NAN, |s| s.capture.encoders.elevation - r.elevation)
    };
    Some(format!(
        "{seed},{:.3},{:.3},{},{:.6},{:.6},{:.6}",
        src(&clean.axis_sources.left),
        src(&clean.axis_sources.right),
        clean.checks.len(),
        held.elevation_deg,
        part.elevation_deg,
        total.elevation_deg
    ))
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    if a.get(4).is_some_and(|m| m == "crb") {
        let noise: f64 = a[3].parse().unwrap();
        println!("seed,src_el_l,src_el_r,checks,held_el,calib_el,total_el");
        for sd in a[1].parse::<u64>().unwrap()..=a[2].parse().unwrap() {
            if let Some(l) = crb_line(sd, noise) {
                println!("{l}");
            }
        }
        return;
    }
    let (from, to): (u64, u64) = (a[1].parse().unwrap(), a[2].parse().unwrap());
    let noise: f64 = a[3].parse().unwrap();
    let names = ["total", "fixed", "clean", "sig_main", "sig_calib", "sig_rep"];
    let mut header = "seed,src_el_l,src_el_r,checks".to_string();
    for n in names {
        for q in ["el", "vl", "vr"] {
            header += &format!(",{n}_{q}");
        }
    }
    println!("{header}");
    let seeds: Vec<u64> = (from..=to).collect();
    let threads = 2;
    let lines: Vec<Vec<String>> = std::thread::scope(|s| {
        let hs: Vec<_> = (0..threads)
            .map(|t| {
                let seeds = &seeds;
                s.spawn(move || {
                    seeds
                        .iter()
                        .skip(t)
                        .step_by(threads)
                        .filter_map(|&sd| line(sd, noise))
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        hs.into_iter().map(|h| h.join().unwrap()).collect()
    });
    for l in lines.into_iter().flatten() {
        println!("{l}");
    }
}
