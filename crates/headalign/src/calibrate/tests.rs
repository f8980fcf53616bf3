//! Tests of self-calibration from rig motions ([`super`]): the density choice, the lens
//! files, the options, and the chain on simulated sessions (one general motion, two
//! rotations, a planar scene, a known lens, seeded failures), with the Cramer-Rao bound
//! experiments behind the numbers in the docs (ignored: run them by name). Units as in
//! the module: pixels, percent of `f`, degrees, baselines.

use std::collections::BTreeMap;

use headalign_geometry::bundle::{BundleObservation, Motions, RigState, Side};
use headalign_geometry::distortion::Distortion;
use headalign_platform::{Joint, StereoCapture, TrackObservation};
use nalgebra::{Isometry3, Point3};

use super::*;

/// A trial with focal lengths `f` (px) and sigmas `sigma` (percent), principal points
/// 6 px from the image centre.
fn trial(corners: usize, f: [f64; 2], sigma: [f64; 2], weak: bool) -> DensityTrial {
    DensityTrial {
        corners,
        focal_px: f,
        focal_sigma_pct: sigma.map(Some),
        weak,
        principal_point_offset_px: Some(6.0),
        error: None,
        seconds: 1.0,
    }
}

/// Trials that disagree beyond their sigmas: the principal points decide, not the
/// smaller sigma. The three re-detected one-motion sessions whose two results disagree
/// (docs/results-real.md; focal lengths, sigmas and mean principal-point distances from
/// the image centre as measured): procedural seed 14 keeps 1500 corners (+0.63 %, where
/// the denser +2.84 % has the smaller sigma), photographs seeds 14 and 20 keep 3000
/// (+1.18 % and -0.15 %, against +4.04 % and +19.7 %). Trials that agree still go by
/// the sigma.
#[test]
fn disagreeing_densities_are_decided_by_the_principal_points() {
    let with = |t: DensityTrial, pp: f64| DensityTrial { principal_point_offset_px: Some(pp), ..t };
    let cases = [
        // (first f, sigma, pp; denser f, sigma, pp; keep the denser?)
        ([704.39, 707.69], [0.456, 0.445], 7.45, [719.45, 725.05], [0.315, 0.311], 10.6, false),
        ([728.28, 730.44], [0.59, 0.57], 11.1, [708.25, 711.54], [0.40, 0.40], 6.45, true),
        ([838.1, 841.2], [0.93, 0.90], 38.9, [699.56, 703.91], [0.30, 0.29], 5.65, true),
    ];
    for (f1, s1, p1, f2, s2, p2, keep) in cases {
        let first = with(trial(1500, f1, s1, true), p1);
        let denser = with(trial(3000, f2, s2, true), p2);
        assert!(disagreement_sigmas(&first, &denser).is_some_and(|z| z > DISAGREEMENT_SIGMAS));
        assert_eq!(prefer_denser(&first, &denser), keep, "{f1:?} vs {f2:?}");
        let r = DensityReport::choose(true, first, Some(denser));
        assert!(r.warn && r.note.contains("principal points nearer"), "{}", r.note);
    }
    // Agreeing trials: the smaller sigma, wherever the principal points are.
    let first = with(trial(1500, [701.0, 706.0], [0.5, 0.5], true), 3.0);
    let denser = with(trial(3000, [702.0, 707.0], [0.3, 0.3], true), 12.0);
    assert!(prefer_denser(&first, &denser));
    // A failed run has no principal point.
    assert_eq!(DensityTrial::failed(1500, "x".into(), 1.0).principal_point_offset_px, None);
}

/// The density choice on the trials measured on rendered sessions (docs/results-real.md):
/// seed 20 (one wall) is retried and the dense result kept, with the 17-sigma
/// disagreement as a warning; a sound first result is not retried; a dense run that
/// diverged (one motion with k1, k2 estimated, seed 1 at 3000: f 2805 px, sigma 15 %)
/// loses to the first; a failed first run is retried and a failed retry never kept;
/// `--corners N` never retries.
#[test]
fn density_retries_weak_results_and_keeps_the_better_determined() {
    let d = Density::default();
    d.validate().unwrap();
    // Measured principal points: 38.9 px from the image centre (cy +31.7 px), and 5.7 px.
    let weak = DensityTrial {
        principal_point_offset_px: Some(38.9),
        ..trial(1500, [838.1, 841.2], [0.93, 0.90], true)
    };
    let dense = DensityTrial {
        principal_point_offset_px: Some(5.7),
        ..trial(3000, [699.6, 703.9], [0.30, 0.29], true)
    };
    assert!(d.retry(&weak));
    assert!(!Density::fixed(1500).retry(&weak));
    assert!(!d.retry(&trial(1500, [700.6, 705.5], [0.44, 0.44], false)));
    let z = disagreement_sigmas(&weak, &dense).unwrap();
    // (838.1 - 699.6) / hypot(0.0093 * 838.1, 0.0030 * 699.6) = 17.1; the right
    // camera's (841.2 - 703.9) / hypot(7.57, 2.04) = 17.5.
    assert!((z - 17.5).abs() < 0.1, "{z}");
    let r = DensityReport::choose(true, weak.clone(), Some(dense.clone()));
    assert_eq!(r.kept, 1);
    assert!(r.warn && r.note.contains("17.") && r.note.contains("3000"), "{}", r.note);
    // Agreeing trials: the denser kept by its sigma, and only a note.
    let agree = trial(3000, [839.0, 842.0], [0.60, 0.60], true);
    let r = DensityReport::choose(true, weak.clone(), Some(agree));
    assert_eq!(r.kept, 1);
    assert!(!r.warn && r.disagreement_sigmas.is_some_and(|z| z < 1.0), "{r:?}");
    // The diverged dense run loses.
    let first = trial(1500, [701.3, 706.2], [0.50, 0.50], true);
    let diverged = trial(3000, [2805.3, 2830.0], [15.4, 15.4], true);
    assert!(!prefer_denser(&first, &diverged));
    assert_eq!(DensityReport::choose(true, first.clone(), Some(diverged)).kept, 0);
    // An unknown sigma counts as infinite.
    let unknown = DensityTrial { focal_sigma_pct: [Some(0.1), None], ..dense.clone() };
    assert!(!prefer_denser(&first, &unknown));
    assert!(disagreement_sigmas(&first, &unknown).is_none());
    // Failures.
    let failed = DensityTrial::failed(1500, "not enough data".into(), 2.0);
    assert!(d.retry(&failed));
    assert!(prefer_denser(&failed, &dense));
    let r = DensityReport::choose(true, failed.clone(), Some(dense.clone()));
    assert!(r.kept == 1 && r.warn && r.note.contains("failed (not enough data)"), "{}", r.note);
    assert!(!prefer_denser(&first, &DensityTrial::failed(3000, "x".into(), 2.0)));
    // One trial: nothing to say.
    let r = DensityReport::choose(false, first, None);
    assert!(r.kept == 0 && !r.warn && r.note.is_empty() && r.trials.len() == 1);
    assert!(Density { corners: 1500, retry_corners: 1000 }.validate().is_err());
    assert!(Density::fixed(0).validate().is_err());
}

#[test]
fn reads_opencv_lenses() {
    let text = "%YAML:1.0\nM1: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 5.3e+02, 0., 3.3e+02, 0.,\n       5.3e+02, 2.4e+02, 0., 0., 1. ]\nD1: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ 0.29, -1.03, 0., 0., 0. ]\nM2: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 5.3e+02, 0., 3.2e+02, 0., 5.3e+02, 2.4e+02, 0., 0., 1. ]\nD2: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ -0.17, -0.11, 0., 0., 0. ]\n";
    let [l, r] = read_opencv_lenses(text, "t").unwrap();
    assert_eq!(l.k.fx, 530.0);
    assert_eq!(l.k.cy, 240.0);
    assert_eq!(l.distortion, Distortion::radial(0.29, -1.03));
    assert_eq!(r.k.cx, 320.0);
    assert_eq!(r.distortion, Distortion::radial(-0.17, -0.11));
    let single = "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 500., 0., 320., 0., 500., 240., 0., 0., 1. ]\ndistortion_coefficients: !!opencv-matrix\n   rows: 5\n   cols: 1\n   dt: d\n   data: [ -0.2, 0.01, 0., 0., 0. ]\n";
    let [a, b] = read_opencv_lenses(single, "s").unwrap();
    assert_eq!(a, b);
    for (bad, expect) in [
        ("nothing: 1\n", "no lens found"),
        ("camera_matrix: [ 1., 2. ]\ndistortion_coefficients: [ 0., 0., 0., 0. ]\n", "9"),
        (
            "camera_matrix: [ 500., 0., 320., 0., 500., 240., 0., 0., 1. ]\ndistortion_coefficients: [ 0., x ]\n",
            "no lens",
        ),
        (
            "camera_matrix: [ 500., 0., 320., 0., 500., 240., 0., 0., 1. ]\ndistortion_coefficients: [ 0., 1e999, 0., 0. ]\n",
            "finite",
        ),
    ] {
        let e = read_opencv_lenses(bad, "f.yml").unwrap_err().to_string();
        assert!(e.contains("f.yml") && e.contains(expect), "{e}");
    }
}

#[test]
fn options_validate() {
    assert!(CalibrateOptions::default().validate().is_ok());
    assert!(CalibrateOptions { min_rotation_deg: 0.0, ..Default::default() }.validate().is_err());
    assert!(CalibrateOptions { planar_fraction: 1.5, ..Default::default() }.validate().is_err());
    assert!(CalibrateOptions { planar_threshold_px: f64::NAN, ..Default::default() }.validate().is_err());
}

use headalign_geometry::so3::{Line, rotation_about_line};
use headalign_platform::{Encoders, StereoHead};
use headalign_sim::rigmotion::general_rig_motion;
use headalign_sim::{Scenario, SimulatedHead};
use nalgebra::{Unit, Vector3};

/// The oblique screw motion `simulate --motion general` used before: 20 deg about
/// `(0.8, -1, 0.3)` with 0.3 m along it (its axis has a large component along the
/// baseline: near-critical on some scenes, see `headalign_sim::rigmotion`).
fn oblique_motion() -> Isometry3<f64> {
    headalign_sim::rigmotion::screw_motion(Vector3::new(0.8, -1.0, 0.3), 20.0, 0.3)
}

/// Square-pixel cameras, no outliers; the reference view and the moved one.
fn general_session(seed: u64, noise_px: f64) -> (Vec<View>, Intrinsics, Intrinsics) {
    session_with_motion(seed, noise_px, &headalign_sim::rigmotion::general_rig_motion())
}

fn session_with_motion(
    seed: u64,
    noise_px: f64,
    motion: &Isometry3<f64>,
) -> (Vec<View>, Intrinsics, Intrinsics) {
    let scenario = Scenario {
        seed,
        noise_px,
        points: 400,
        outlier_fraction: 0.0,
        left: Intrinsics::new(700.0, 700.0, 390.0, 284.0),
        right: Intrinsics::new(705.0, 705.0, 380.0, 290.0),
        ..Scenario::default()
    };
    let mut head = SimulatedHead::new(scenario).unwrap();
    let v0 = View { name: "initial".into(), capture: head.capture().unwrap() };
    head.set_world_from_robot(*motion);
    let v1 = View { name: "moved".into(), capture: head.capture().unwrap() };
    let t = head.truth();
    (vec![v0, v1], t.left, t.right)
}

fn f_err_pct(est: &Intrinsics, truth: &Intrinsics) -> f64 {
    100.0 * (est.mean_focal() - truth.mean_focal()).abs() / truth.mean_focal()
}

/// The oblique motion on seed 2 (its Cramer-Rao bound of f at the truth is 4.1 %;
/// the estimate is 2.5 % off with a sigma of 0.94 %) is flagged with warnings that
/// say what to do; the default general motion on seed 1 is not (sigma 0.16 %).
#[test]
fn near_critical_motion_is_flagged() {
    let options = CalibrateOptions { zero_skew: true, square_pixels: true, ..Default::default() };
    let (views, _, _) = session_with_motion(2, 0.5, &oblique_motion());
    let cal = calibrate_rig(&views, &options).unwrap();
    let s = cal.report.focal_sigma_pct[0].unwrap();
    assert!(s > 0.5, "sigma {s} %");
    assert!(cal.report.warnings[0].contains("poorly determined"), "{:?}", cal.report.warnings);
    // A weak result: an image front end retries it denser (Density).
    assert!(weak_data(&cal.report, &options));
    let (views, _, _) = general_session(1, 0.5);
    let cal = calibrate_rig(&views, &options).unwrap();
    assert!(cal.report.warnings.is_empty(), "{:?}", cal.report.warnings);
    assert!(!weak_data(&cal.report, &options));
}

#[test]
fn one_general_motion_noise_free_is_exact() {
    let (views, l, r) = general_session(1, 0.0);
    let options = CalibrateOptions { zero_skew: true, square_pixels: true, ..Default::default() };
    let cal = calibrate_rig(&views, &options).unwrap();
    let st = &cal.bundle.state;
    // 1e-6 relative: noise-free, the adjustment converges to rounding.
    assert!(
        f_err_pct(&st.left, &l) < 1e-4 && f_err_pct(&st.right, &r) < 1e-4,
        "{:?} {:?}",
        st.left,
        st.right
    );
    assert!((st.left.cx - l.cx).abs() < 1e-3 && (st.right.cy - r.cy).abs() < 1e-3);
    assert!(cal.report.linear.is_some(), "{:?}", cal.report.linear_error);
    // Without a constraint (the skew free too) one motion leaves the calibration
    // undetermined: the error names the missing constraint.
    let free = CalibrateOptions { zero_skew: false, ..CalibrateOptions::default() };
    let e = calibrate_rig(&views, &free).unwrap_err().to_string();
    assert!(e.contains("missing motion") && e.contains("constraint"), "{e}");
}

/// The bar of issue 6: one general motion (`headalign_sim::rigmotion`: 25 deg about
/// the vertical, 0.3 m along it), zero skew and square pixels, 0.5 px noise, 400
/// points: focal length within 1 %. Seeds 1-20 all pass (measured 0.001-0.85 %, the
/// worst seed 14 with a sigma of 0.44 %; `general_motion_seeds`); the test runs the
/// first 8 and seed 14 (time), and checks that none of them has the sigma warning
/// and that seeds 2 and 14 (88 % and 92 % of the matches on one wall) have the
/// scene warning.
#[test]
fn one_general_motion_half_pixel_within_one_percent() {
    for seed in [1, 2, 3, 4, 5, 6, 7, 8, 14] {
        let (views, l, r) = general_session(seed, 0.5);
        let options = CalibrateOptions { zero_skew: true, square_pixels: true, ..Default::default() };
        let cal = calibrate_rig(&views, &options).unwrap();
        let st = &cal.bundle.state;
        let (el, er) = (f_err_pct(&st.left, &l), f_err_pct(&st.right, &r));
        assert!(el < 1.0 && er < 1.0, "seed {seed}: f errors {el:.3} % / {er:.3} %");
        let sigma_warning = cal.report.warnings.iter().any(|w| w.contains("poorly determined"));
        assert!(!sigma_warning, "seed {seed}: {:?}", cal.report.warnings);
        // Seed 14 has 89 % and 94 % of its views' matches on one wall: the scene
        // warning (it is still within 1 %, at 0.85 %, its worst).
        let plane_warning = cal.report.warnings.iter().any(|w| w.contains("mostly one plane"));
        assert_eq!(plane_warning, seed == 14 || seed == 2, "seed {seed}: {:?}", cal.report.warnings);
        // weak_data is exactly the data warnings (no restart here).
        assert_eq!(weak_data(&cal.report, &options), plane_warning, "seed {seed}");
    }
}

/// The Monte-Carlo behind the numbers in docs/results-real.md (seeds 1-20, 0.5 px):
/// `cargo test --release -p headalign --lib calibrate::tests::general_motion_seeds -- --ignored --nocapture`.
#[test]
#[ignore = "experiment: prints statistics over 20 seeds"]
fn general_motion_seeds() {
    let mut errs = Vec::new();
    for seed in 1..=20 {
        let (views, l, r) = general_session(seed, 0.5);
        let options = CalibrateOptions { zero_skew: true, square_pixels: true, ..Default::default() };
        match calibrate_rig(&views, &options) {
            Ok(cal) => {
                let st = &cal.bundle.state;
                let s = cal.bundle.covariance.sigma("left.fx").unwrap_or(f64::NAN);
                let (el, er) = (f_err_pct(&st.left, &l), f_err_pct(&st.right, &r));
                let plane = cal
                    .report
                    .planarity
                    .iter()
                    .map(|c| format!("{:.2}", c.on_one_plane as f64 / c.stereo_matches as f64))
                    .collect::<Vec<_>>()
                    .join("/");
                eprintln!(
                    "seed {seed}: f err L {el:.3} % R {er:.3} % (sigma L {:.3} %), rms {:.3} px, start {}, on one plane {plane}, quads {}",
                    100.0 * s / l.fx,
                    cal.report.final_rms_px,
                    cal.report.start,
                    cal.report.motions[0].inliers
                );
                errs.push(el.max(er));
            }
            Err(e) => eprintln!("seed {seed}: {e}"),
        }
    }
    let rms = (errs.iter().map(|e| e * e).sum::<f64>() / errs.len() as f64).sqrt();
    let worst = errs.iter().copied().fold(0.0, f64::max);
    eprintln!("{} of 20 ran; RMS of the worse camera's f error {rms:.3} %, worst {worst:.3} %", errs.len());
}

/// The Cramer-Rao bound of the focal length for one rig motion: the marginal
/// covariance of the bundle adjustment at the true state with exact observations and
/// the given noise (the adjustment starts at its minimum, so the covariance is
/// `sigma^2 (J^T J)^-1` at the truth). Returns (sigma of left f in %, of left k1 if
/// `distortion`).
pub(crate) fn crb_one_motion(
    scenario: &Scenario,
    motion: &Isometry3<f64>,
    noise_px: f64,
    distortion: bool,
) -> (f64, f64) {
    use headalign_geometry::bundle::{BundleOptions, RobustLoss, bundle_adjust};
    let mut head = SimulatedHead::new(scenario.clone()).unwrap();
    let enc = head.encoders();
    let (wl0, wr0) = head.scene_from_cameras(&enc);
    let c0 = head.exact_capture(&enc);
    head.set_world_from_robot(*motion);
    let (wl1, _) = head.scene_from_cameras(&enc);
    let c1 = head.exact_capture(&enc);
    let index: BTreeMap<u64, usize> =
        head.scene_points().iter().enumerate().map(|(i, (t, _))| (*t, i)).collect();
    let points: Vec<Point3<f64>> = head.scene_points().iter().map(|(_, p)| wl0.inverse() * p).collect();
    let mut obs = Vec::new();
    for (view, c) in [&c0, &c1].into_iter().enumerate() {
        for (side, list) in [(Side::Left, &c.left), (Side::Right, &c.right)] {
            for o in list {
                obs.push(BundleObservation { point: index[&o.track], view, side, pixel: o.pixel });
            }
        }
    }
    let t = head.truth();
    let state = RigState {
        left: t.left,
        right: t.right,
        left_distortion: Distortion::default(),
        right_distortion: Distortion::default(),
        right_from_left: wr0.inverse() * wl0,
        motions: Motions::Free { ref_from_cam: vec![Isometry3::identity(), wl0.inverse() * wl1] },
        points,
    };
    let options = BundleOptions {
        robust: RobustLoss::None,
        zero_skew: true,
        square_pixels: true,
        estimate_distortion: distortion,
        angle_prior_sigma: None,
        noise_sigma_px: Some(noise_px),
        ..BundleOptions::default()
    };
    let r = bundle_adjust(&state, &obs, &options).unwrap();
    let c = &r.covariance;
    (100.0 * c.sigma("left.fx").unwrap_or(f64::NAN) / t.left.fx, c.sigma("left.k1").unwrap_or(f64::NAN))
}

/// The scene of the bound experiments: 400 points, no outliers, two distinct cameras.
fn bound_scenario(seed: u64) -> Scenario {
    Scenario {
        seed,
        points: 400,
        outlier_fraction: 0.0,
        left: Intrinsics::new(700.0, 700.0, 390.0, 284.0),
        right: Intrinsics::new(705.0, 705.0, 380.0, 290.0),
        ..Scenario::default()
    }
}

/// The Cramer-Rao bound per seed of the one-general-motion session:
/// `cargo test --release -p headalign --lib calibrate::tests::general_motion_bound -- --ignored --nocapture`.
#[test]
#[ignore = "experiment: prints the bound over 20 seeds"]
fn general_motion_bound() {
    for seed in 1..=20 {
        let scenario = bound_scenario(seed);
        let (sf, _) = crb_one_motion(&scenario, &general_rig_motion(), 0.5, false);
        let (sfd, sk) = crb_one_motion(&scenario, &general_rig_motion(), 0.5, true);
        eprintln!("seed {seed}: CRB f {sf:.3} %, with k1 k2: f {sfd:.3} % k1 {sk:.4}");
    }
}

#[test]
#[ignore = "experiment"]
fn general_motion_grid() {
    let first: u64 = std::env::var("FIRST").ok().and_then(|s| s.parse().ok()).unwrap_or(1);
    let last: u64 = std::env::var("LAST").ok().and_then(|s| s.parse().ok()).unwrap_or(20);
    let axes = [
        ("obl", Vector3::new(0.8, -1.0, 0.3)),
        ("vert", Vector3::new(0.0, -1.0, 0.0)),
        ("vert+x", Vector3::new(0.3, -1.0, 0.0)),
        ("vert+z", Vector3::new(0.0, -1.0, 0.3)),
    ];
    for (name, axis_dir) in axes {
        for (angle, along) in [(20.0, 0.3), (25.0, 0.3), (30.0, 0.3), (25.0, 0.2), (30.0, 0.2), (30.0, 0.4)] {
            let mut out = Vec::new();
            for seed in first..=last {
                let scenario = bound_scenario(seed);
                let axis = Line::new(Unit::new_normalize(axis_dir), Point3::new(0.0, -1.2, 0.0));
                let r = rotation_about_line(&axis, f64::to_radians(angle));
                let m = Isometry3::from_parts(
                    (r.translation.vector + axis.direction.into_inner() * along).into(),
                    r.rotation,
                );
                let (sf, _) = crb_one_motion(&scenario, &m, 0.5, false);
                out.push(sf);
            }
            let mut sorted = out.clone();
            sorted.sort_by(f64::total_cmp);
            let n = sorted.len();
            eprintln!(
                "{name} {angle} deg {along} m: median {:.3} %, 90th {:.3} %, worst {:.3} %, above 0.5 %: {}",
                sorted[n / 2],
                sorted[n * 9 / 10],
                sorted[n - 1],
                out.iter().filter(|v| **v > 0.5).count()
            );
        }
    }
}

/// One point-mode view per `(name, encoders)`, captured after moving there.
fn capture_views(head: &mut SimulatedHead, at: &[(&str, Encoders)]) -> Vec<View> {
    at.iter()
        .map(|(name, enc)| {
            head.move_to(enc).unwrap();
            View { name: (*name).into(), capture: head.capture().unwrap() }
        })
        .collect()
}

/// Two head rotations about different axes need no constraint (noise-free: exact);
/// the vergence view (rig changed) is left out and said so.
#[test]
fn two_rotations_calibrate_without_constraints() {
    let scenario = Scenario { noise_px: 0.0, outlier_fraction: 0.0, ..Scenario::default() };
    let mut head = SimulatedHead::new(scenario).unwrap();
    let e0 = head.encoders();
    let views = capture_views(
        &mut head,
        &[
            ("initial", e0),
            ("elevation", e0.moved(Joint::Elevation, 5.0)),
            ("pan", e0.moved(Joint::Pan, 5.0)),
            ("verge", Encoders { verge_left: e0.verge_left + 3.0, ..e0 }),
        ],
    );
    // The skew free too (the default holds it at zero).
    let free = CalibrateOptions { zero_skew: false, ..CalibrateOptions::default() };
    let cal = calibrate_rig(&views, &free).unwrap();
    let (st, t) = (&cal.bundle.state, head.truth());
    // 1e-4 % and 1e-3 px: noise-free, the adjustment converges to rounding.
    assert!(f_err_pct(&st.left, &t.left) < 1e-4, "{:?} vs {:?}", st.left, t.left);
    assert!((st.left.fy - t.left.fy).abs() < 1e-3 && (st.right.fx - t.right.fx).abs() < 1e-3);
    assert_eq!(cal.report.views, ["initial", "elevation", "pan"]);
    assert!(cal.report.skipped[0].contains("verge"));
}

/// A scene that is one plane (every point on z = 3 m) is refused by the scene-depth
/// check, naming the views and the degeneracy.
#[test]
fn planar_scene_is_named() {
    let k = Intrinsics::new(700.0, 700.0, 384.0, 288.0);
    let right_from_left = Isometry3::translation(-0.25, 0.0, 0.0);
    let motion = headalign_sim::rigmotion::screw_motion(Vector3::new(0.8, -1.0, 0.3), 10.0, 0.2);
    let view = |name: &str, cam_from_world: Isometry3<f64>| {
        let (mut left, mut right) = (Vec::new(), Vec::new());
        for i in 0..400u64 {
            let p = Point3::new(
                -1.5 + 3.0 * ((i * 37) % 100) as f64 / 100.0,
                -1.0 + 2.0 * (i / 20) as f64 / 20.0,
                3.0,
            );
            let pc = cam_from_world * p;
            if let (Some(l), Some(r)) = (k.project(&pc), k.project(&(right_from_left * pc))) {
                left.push(TrackObservation { track: i, pixel: l });
                right.push(TrackObservation { track: i, pixel: r });
            }
        }
        View {
            name: name.into(),
            capture: StereoCapture { encoders: Encoders::default(), image_size: [768, 576], left, right },
        }
    };
    let views = [view("a", Isometry3::identity()), view("b", motion.inverse())];
    let e = calibrate_rig(&views, &CalibrateOptions::default()).unwrap_err().to_string();
    assert!(e.contains("one plane") && e.contains("'a'") && e.contains("'b'"), "{e}");
    assert!(require_depth(&views, &CalibrateOptions::default()).is_err());
}

/// Known lens distortion (barrel, k1 = -0.2, k2 = 0.05, as a lens file would give it)
/// is removed before self-calibration: noise-free, K comes out exact; ignoring the
/// lens costs percent.
#[test]
fn known_distortion_is_removed() {
    let mut scenario = Scenario { noise_px: 0.0, outlier_fraction: 0.0, ..Scenario::default() };
    scenario.render.distortion = Distortion::radial(-0.2, 0.05);
    let mut head = SimulatedHead::new(scenario).unwrap();
    let e0 = head.encoders();
    let views = capture_views(
        &mut head,
        &[
            ("initial", e0),
            ("elevation", e0.moved(Joint::Elevation, 5.0)),
            ("pan", e0.moved(Joint::Pan, 5.0)),
        ],
    );
    let t = head.truth().clone();
    let lens = |k: Intrinsics| LensModel { k, distortion: Distortion::radial(-0.2, 0.05) };
    let undistorted = undistort_views(&views, &[lens(t.left), lens(t.right)]);
    let cal = calibrate_rig(&undistorted, &CalibrateOptions::default()).unwrap();
    // 1e-4 %: noise-free (undistortion is exact to 1e-9 px).
    assert!(f_err_pct(&cal.bundle.state.left, &t.left) < 1e-4, "{:?}", cal.bundle.state.left);
    // The pinhole keeps its linearised sigmas: no lens bootstrap.
    assert!(cal.report.lens_sigmas.is_none());
    let ignored = calibrate_rig(&views, &CalibrateOptions::default());
    let off = ignored.map_or(f64::INFINITY, |c| f_err_pct(&c.bundle.state.left, &t.left));
    assert!(off > 0.5, "ignoring the lens only cost {off} %");
}

/// `calibrate` with a radial-tangential lens estimated (zero skew) on the simulated head
/// of `seed` at 0.25 px with `lens` in both cameras: the initial view and views after
/// `rotation_deg` of elevation and of pan. Returns the calibration and the truth.
fn calibrate_strong_lens(
    lens: Distortion,
    seed: u64,
    rotation_deg: f64,
) -> (MotionCalibration, headalign_sim::HeadTruth) {
    let mut scenario = Scenario { seed, noise_px: 0.25, rotation_deg, ..Scenario::default() };
    scenario.render.distortion = lens;
    let mut head = SimulatedHead::new(scenario).unwrap();
    let e0 = head.encoders();
    let views = capture_views(
        &mut head,
        &[
            ("initial", e0),
            ("elevation", e0.moved(Joint::Elevation, rotation_deg)),
            ("pan", e0.moved(Joint::Pan, rotation_deg)),
        ],
    );
    let options = CalibrateOptions {
        estimation: EstimationOptions::scaled_for_noise(0.25, seed),
        zero_skew: true,
        lens: LensChoice::Model(headalign_geometry::distortion::LensKind::RadialTangential),
        ..CalibrateOptions::default()
    };
    (calibrate_rig(&views, &options).unwrap(), head.truth().clone())
}

/// A strong barrel lens (radial-tangential `k1 = -0.3, k2 = 0.08`, `experiment lens`'s)
/// seen in 10 deg views at 0.25 px, lens estimated: estimation seeds 1 and 21, where the
/// chain on the distorted pixels alone drifted to f = 50,000 px (seed 1) or stopped at a
/// 3D homography whose angle reading clamps to 0 deg (seed 21), calibrate with the
/// two-pass start (`two_pass`). Tolerances: f within 1 % (the reported sigma is 0.2 %)
/// and k1 within 0.01 (sigma about 0.002); every error within 4 reported sigmas; the
/// bootstrap widening (`lens_sigmas`) at least 1 for every focal length and lens term.
#[test]
fn a_strong_lens_in_ten_degree_views_starts_well() {
    let lens = Distortion::radial(-0.3, 0.08);
    for seed in [1, 21] {
        let (cal, truth) = calibrate_strong_lens(lens, seed, 10.0);
        let (st, t) = (&cal.bundle.state, &truth);
        assert!(f_err_pct(&st.left, &t.left) < 1.0, "seed {seed}: {:?} vs {:?}", st.left, t.left);
        assert!(f_err_pct(&st.right, &t.right) < 1.0, "seed {seed}: {:?} vs {:?}", st.right, t.right);
        assert!(
            (st.left_distortion.param("k1").unwrap() - lens.param("k1").unwrap()).abs() < 0.01,
            "seed {seed}: {:?}",
            st.left_distortion
        );
        let cov = &cal.bundle.covariance;
        for (name, err) in [
            ("left.fx", st.left.fx - t.left.fx),
            ("right.fx", st.right.fx - t.right.fx),
            ("left.k1", st.left_distortion.param("k1").unwrap() - lens.param("k1").unwrap()),
        ] {
            let sigma = cov.sigma(name).unwrap();
            assert!(err.abs() < 4.0 * sigma, "seed {seed}: {name} error {err} sigma {sigma}");
        }
        let boot = cal.report.lens_sigmas.as_ref().unwrap();
        assert!(boot.replicates >= 3 && boot.widening.len() == 8, "{boot:?}");
        assert!(boot.widening.iter().all(|(_, w)| (1.0..=lens_sigmas::MAX_WIDENING).contains(w)));
    }
}

/// A strong barrel lens (`k1 = -0.3, k2 = 0.08`) in the procedure's 3 deg views at
/// 0.25 px, seed 6 of `experiment lens`: the chain on the captured pixels ends in another
/// minimum of the f-k1 valley (measured: f +78 %, `k1` -0.254, truncated cost 693 px^2
/// against 477 px^2 on the same observations from the lens-grid run's result), so the
/// lowest-cost start is the lens grid's (`two_pass`). Tolerances: f within 2 % and `k1`
/// within 0.01 (measured 0.08 % and 0.001; the reported sigmas are 0.9 % and 0.002).
#[test]
fn a_strong_lens_in_three_degree_views_keeps_the_lowest_minimum() {
    let lens = Distortion::radial(-0.3, 0.08);
    let seed = 6;
    let (cal, truth) = calibrate_strong_lens(lens, seed, 3.0);
    let (st, t) = (&cal.bundle.state, &truth);
    assert!(f_err_pct(&st.left, &t.left) < 2.0, "{:?} vs {:?}", st.left, t.left);
    assert!(f_err_pct(&st.right, &t.right) < 2.0, "{:?} vs {:?}", st.right, t.right);
    assert!(
        (st.left_distortion.param("k1").unwrap() - lens.param("k1").unwrap()).abs() < 0.01,
        "{:?}",
        st.left_distortion
    );
    assert_eq!(cal.report.start, "lens grid");
}

#[test]
fn too_few_views_is_an_error() {
    assert!(calibrate_rig(&[], &CalibrateOptions::default()).is_err());
}

/// A failure of the seeded stages is retried with the next seeds, and when every seed
/// fails the error says how many were tried, how many tracks the views share and what
/// to record instead. Here the moved view's track ids are rotated among its stereo
/// pairs except for 8, so every pair is a good stereo match but at most 8 are the same
/// point as in the reference: no 3D homography has the 12 inliers it needs, whatever
/// the seed.
#[test]
fn seeded_failures_are_retried_and_named() {
    let (mut views, _, _) = general_session(3, 0.5);
    let ids: std::collections::BTreeSet<u64> = views[1].capture.left.iter().map(|o| o.track).collect();
    let both: Vec<u64> = views[1].capture.right.iter().map(|o| o.track).filter(|t| ids.contains(t)).collect();
    let moved = &both[8..];
    let relabel: BTreeMap<u64, u64> =
        moved.iter().zip(moved.iter().cycle().skip(1)).map(|(&a, &b)| (a, b)).collect();
    let capture = &mut views[1].capture;
    for o in capture.left.iter_mut().chain(capture.right.iter_mut()) {
        if let Some(&t) = relabel.get(&o.track) {
            o.track = t;
        }
    }
    for (restarts, tried) in [(3, "4 estimation seeds"), (0, "1 estimation seeds")] {
        let options = CalibrateOptions {
            zero_skew: true,
            square_pixels: true,
            restarts,
            ..CalibrateOptions::default()
        };
        let e = calibrate_rig(&views, &options).unwrap_err().to_string();
        assert!(
            e.contains(tried)
                && e.contains("tracks in the reference")
                && e.contains("too few points seen in both views"),
            "{e}"
        );
    }
    // The intact session needs no restart and reports the seed it used.
    let (views, _, _) = general_session(3, 0.5);
    let options = CalibrateOptions { zero_skew: true, square_pixels: true, ..CalibrateOptions::default() };
    let c = calibrate_rig(&views, &options).unwrap();
    assert_eq!((c.report.restarts, c.report.estimation_seed), (0, options.estimation.seed));
}

/// The views of a robot session's rigs: two verging captures (the second at the
/// verge/tilt rig), the verge/tilt views, the verge view, and the views after alignment
/// (one rig, moved by pan and drives only). The verge/tilt rig is kept although smaller;
/// every other view is named with the reason. One rig alone is used whole.
#[test]
fn the_rig_turned_about_two_joints_is_chosen() {
    let e = |pan: f64, elevation: f64, verge_left: f64, verge_right: f64| Encoders {
        pan,
        elevation,
        verge_left,
        verge_right,
    };
    let mut views = vec![
        ("verging-1", e(0.0, 0.0, 0.0, 0.0)),
        ("verging-2", e(0.0, 0.0, 0.0, -18.0)),
        ("initial", e(0.0, 0.0, 0.0, -18.0)),
        ("elevation+", e(0.0, 3.0, 0.0, -18.0)),
        ("pan+", e(3.0, 0.0, 0.0, -18.05)),
        ("verge", e(0.0, 0.0, 3.0, -15.0)),
    ];
    for k in 0..8 {
        views.push(("pan-k", e(4.8 + 0.01 * f64::from(k), -7.8, -4.25, -9.0)));
    }
    let choice = select_rig(&views);
    assert_eq!(choice.used, [1, 2, 3, 4]);
    let out: Vec<usize> = choice.left_out.iter().map(|(i, _)| *i).collect();
    assert_eq!(out, [0, 5, 6, 7, 8, 9, 10, 11, 12, 13]);
    assert!(choice.left_out[0].1.starts_with("verging-1: another rig"), "{:?}", choice.left_out[0]);
    assert!(choice.left_out[0].1.contains("'verging-2'"), "{:?}", choice.left_out[0]);
    // Without the two-joint group the larger wins; one rig is used whole.
    let choice = select_rig(&views[5..]);
    assert_eq!(choice.used, (1..9).collect::<Vec<_>>());
    let zero: Vec<(&str, Encoders)> = (0..3).map(|_| ("pair", Encoders::default())).collect();
    assert_eq!(select_rig(&zero), RigChoice { used: vec![0, 1, 2], left_out: Vec::new() });
    assert!(select_rig(&[]).used.is_empty());
}

/// A rig carried around the simulated room (point mode): per view 12 deg further about the
/// vertical, the pitch swinging by +-8 deg and the height by +-0.1 m, so that a view
/// overlaps only its four or so neighbours (the field of view is 57 deg wide); `views`
/// views starting at yaw `start_deg`, named `name{i}`.
fn carried_views(head: &mut SimulatedHead, name: &str, start_deg: f64, views: usize) -> Vec<View> {
    (0..views)
        .map(|i| {
            let yaw = start_deg + 12.0 * i as f64;
            let pitch = 8.0 * (1.3 * i as f64).sin();
            let turn =
                headalign_sim::rigmotion::screw_motion(-Vector3::y(), yaw, 0.1 * (0.9 * i as f64).sin());
            let tilt = headalign_sim::rigmotion::screw_motion(Vector3::x(), pitch, 0.0);
            head.set_world_from_robot(turn * tilt);
            View { name: format!("{name}{i:02}"), capture: head.capture().unwrap() }
        })
        .collect()
}

/// Issue 32 item 1, in point mode: 20 views in two disconnected segments (12 views from
/// yaw 0 deg, 8 from 200 deg: no view of one sees a point of the other), each view
/// overlapping only its neighbours, 0.5 px noise and 5 % outliers, no constraint. Every
/// view moves by 12 deg, so every view is a keyframe; each segment is chained through its
/// neighbours, both add their motions to one adjustment (20 views: the sparse Schur
/// complement), and the mean focal lengths come out within 0.5 % (measured 0.00 % and
/// 0.06 %, with a sigma of 0.04 %: the bound is ten sigmas). The report names both
/// segments, their gauges and links, and every motion relative to its gauge.
#[test]
fn a_sequence_in_two_segments_calibrates() {
    let scenario =
        Scenario { seed: 3, noise_px: 0.5, outlier_fraction: 0.05, points: 300, ..Scenario::default() };
    let mut head = SimulatedHead::new(scenario).unwrap();
    let mut views = carried_views(&mut head, "a", 0.0, 12);
    views.extend(carried_views(&mut head, "b", 200.0, 8));
    // Not a folder the reference chain could take: view a05 shares nothing with a00.
    let shared = graph::ViewTracks::of(&views[0]).shared(&graph::ViewTracks::of(&views[5]));
    assert_eq!(shared, 0);
    let cal = calibrate_sequence(&views, &CalibrateOptions::default()).unwrap();
    let (st, t) = (&cal.bundle.state, head.truth());
    for (est, truth) in [(&st.left, &t.left), (&st.right, &t.right)] {
        let sigma = cal.report.focal_sigma_pct[0].unwrap_or(f64::NAN);
        eprintln!("f error {:.3} % (sigma of left fx {sigma:.3} %)", f_err_pct(est, truth));
        assert!(f_err_pct(est, truth) < 0.5, "{est:?} vs {truth:?}");
    }
    let seq = cal.report.sequence.as_ref().unwrap();
    assert_eq!((seq.views, seq.keyframes, seq.segments.len()), (20, 20, 2), "{seq:?}");
    assert_eq!((seq.segments[0].gauge.as_str(), seq.segments[1].gauge.as_str()), ("a00", "b00"));
    assert_eq!(seq.segments[1].keyframes.len(), 8);
    assert_eq!(cal.report.motions.len(), 18);
    for m in &cal.report.motions {
        let gauge = if m.view.starts_with('a') { "a00" } else { "b00" };
        assert_eq!(m.relative_to.as_deref(), Some(gauge), "{m:?}");
    }
    assert!(cal.report.motions.iter().any(|m| m.linear && m.view.starts_with('b')));
    assert!(cal.report.skipped.is_empty() && cal.report.warnings.is_empty(), "{:?}", cal.report);
    // Without the second segment's gauge held the adjustment would have no minimum: its
    // views are free in the report's covariance, the gauge's are not.
    let cov = &cal.bundle.covariance;
    assert!(cov.index("view12.rot0").is_none() && cov.index("view13.rot0").is_some());
}

/// Issue 31 item 1 on the sequence route: `LensChoice::Auto` on a short carried sequence
/// in two segments (8 + 6 views, point mode, 0.5 px, a barrel lens `k1 = -0.2, k2 = 0.05`
/// that the simulator applies to the points). The criterion compares the three models on
/// the radial-tangential run's observations (segment gauges held in the refits), keeps a
/// distorted model and says why; the same sequence without a lens keeps the pinhole
/// (BIC's `ln n` penalty per coefficient). The lensed focal lengths within 1 % (the
/// issue's bar; the two-segment test above reaches 0.06 % without a lens, and `k1`
/// correlates with f). Measured: with the lens the equidistant model by 3.7 BIC units
/// over the radial-tangential (a narrow lens fits either; pinhole 100,000 above), without
/// it the pinhole by 33.
#[test]
fn a_sequence_chooses_its_lens() {
    for (k1, k2) in [(-0.2, 0.05), (0.0, 0.0)] {
        let mut scenario = Scenario { seed: 3, noise_px: 0.5, points: 300, ..Scenario::default() };
        scenario.render.distortion = Distortion::radial(k1, k2);
        let mut head = SimulatedHead::new(scenario).unwrap();
        let mut views = carried_views(&mut head, "a", 0.0, 8);
        views.extend(carried_views(&mut head, "b", 200.0, 6));
        let options = CalibrateOptions { lens: LensChoice::Auto, ..CalibrateOptions::default() };
        let cal = calibrate_sequence(&views, &options).unwrap();
        let sel = cal.report.lens_selection.as_ref().unwrap();
        eprintln!("k1 {k1}: {} ({})", sel.chosen, sel.reason);
        let models: Vec<&str> = sel.candidates.iter().map(|c| c.model.as_str()).collect();
        assert_eq!(models, ["pinhole", "radtan", "equidistant"]);
        assert!(sel.reason.contains("BIC"), "{}", sel.reason);
        assert_eq!(cal.report.sequence.as_ref().map(|s| s.segments.len()), Some(2));
        let (st, t) = (&cal.bundle.state, head.truth());
        if k1 == 0.0 {
            assert_eq!(sel.chosen, "pinhole", "{}", sel.reason);
            assert!(cal.report.lens_sigmas.is_none(), "the pinhole keeps its linearised sigmas");
        } else {
            assert_ne!(sel.chosen, "pinhole", "{}", sel.reason);
            assert!(st.left_distortion.param("k1").unwrap() < -0.1, "{:?}", st.left_distortion);
            // The chosen lens's sigmas are bootstrapped, the segment gauges held.
            let boot = cal.report.lens_sigmas.as_ref().expect("lens bootstrap of a sequence");
            assert!(boot.replicates >= 3 && boot.widening.iter().all(|(_, w)| *w >= 1.0), "{boot:?}");
        }
        for (est, truth) in [(&st.left, &t.left), (&st.right, &t.right)] {
            assert!(f_err_pct(est, truth) < 1.0, "k1 {k1}: {est:?} vs {truth:?}");
        }
        // Point observations carry no measured image noise: the check says so.
        assert_eq!(cal.report.image_noise.as_ref().map(|n| n.status.as_str()), Some("skipped"));
    }
}

/// The 180-deg double-sphere camera of the issue-45 bar: `xi = -0.15, alpha = 0.55`
/// (w2 = 0.76: rays up to 139 deg project) with `fx = fy = 188` on a 768 x 576 image,
/// so that the image's horizontal edges are 90 deg off the axis (180 deg across) and its
/// corners about 115 deg. The right camera's focal length differs by 2 %.
pub(crate) fn wide_scenario(seed: u64, noise_px: f64) -> Scenario {
    let mut scenario = Scenario {
        seed,
        noise_px,
        points: 400,
        outlier_fraction: 0.0,
        left: Intrinsics::new(188.0, 188.0, 383.5, 287.5),
        right: Intrinsics::new(191.0, 191.0, 381.0, 290.0),
        ..Scenario::default()
    };
    scenario.render.distortion = Distortion::double_sphere(-0.15, 0.55);
    scenario
}

/// `calibrate` with the double sphere on the simulated head of `wide_scenario(seed)`:
/// the initial view and views after `rotation_deg` of elevation and of pan (point mode).
pub(crate) fn calibrate_wide(
    seed: u64,
    noise_px: f64,
    rotation_deg: f64,
) -> Result<(MotionCalibration, headalign_sim::HeadTruth), AlignError> {
    let scenario = Scenario { rotation_deg, ..wide_scenario(seed, noise_px) };
    let mut head = SimulatedHead::new(scenario).map_err(|e| AlignError::InvalidOption(e.to_string()))?;
    let e0 = head.encoders();
    let views = capture_views(
        &mut head,
        &[
            ("initial", e0),
            ("elevation", e0.moved(Joint::Elevation, rotation_deg)),
            ("pan", e0.moved(Joint::Pan, rotation_deg)),
        ],
    );
    let options = CalibrateOptions {
        estimation: EstimationOptions::scaled_for_noise(noise_px, seed),
        zero_skew: true,
        lens: LensChoice::Model(headalign_geometry::distortion::LensKind::DoubleSphere),
        ..CalibrateOptions::default()
    };
    Ok((calibrate_rig(&views, &options)?, head.truth().clone()))
}

/// The issue-45 bar in point mode: the 180-deg double sphere in 15-deg views at 0.5 px,
/// seed 1: focal lengths within 1 %, and `xi`, `alpha` of both cameras within 3 reported
/// sigmas. Observations beyond 90 deg enter the adjustment.
#[test]
fn a_180_degree_double_sphere_calibrates() {
    let (cal, truth) = calibrate_wide(1, 0.5, 15.0).unwrap();
    let (st, t) = (&cal.bundle.state, &truth);
    assert!(f_err_pct(&st.left, &t.left) < 1.0, "{:?} vs {:?}", st.left, t.left);
    assert!(f_err_pct(&st.right, &t.right) < 1.0, "{:?} vs {:?}", st.right, t.right);
    let cov = &cal.bundle.covariance;
    for (name, err) in [
        ("left.xi", st.left_distortion.param("xi").unwrap() + 0.15),
        ("left.alpha", st.left_distortion.param("alpha").unwrap() - 0.55),
        ("right.xi", st.right_distortion.param("xi").unwrap() + 0.15),
        ("right.alpha", st.right_distortion.param("alpha").unwrap() - 0.55),
    ] {
        let sigma = cov.sigma(name).unwrap();
        assert!(err.abs() < 3.0 * sigma, "{name}: error {err:.5}, sigma {sigma:.5}");
    }
    let behind = cal.observations.iter().filter(|o| {
        let (k, d) = if o.side == Side::Left {
            (&st.left, &st.left_distortion)
        } else {
            (&st.right, &st.right_distortion)
        };
        d.unproject_pixel(k, &o.pixel).is_ok_and(|b| b.z < 0.0)
    });
    assert!(behind.count() > 0, "no observation beyond 90 deg entered the adjustment");
}

/// The bar's measurement over seeds (issue 45): the 180-deg double sphere in 15-deg views
/// at 0.5 px, seeds 1-20, point mode: per seed the focal errors (percent) and the lens
/// errors in reported sigmas; `cargo test --release -p headalign --lib
/// calibrate::tests::wide_double_sphere_seeds -- --ignored --nocapture`.
#[test]
#[ignore = "experiment: prints the 180-deg double-sphere bar over 20 seeds"]
fn wide_double_sphere_seeds() {
    use headalign_geometry::bundle::BundleOptions;
    let (mut worst_f, mut worst_z, mut failed) = (0.0f64, 0.0f64, 0);
    for seed in 1..=20 {
        match calibrate_wide(seed, 0.5, 15.0) {
            Ok((cal, t)) => {
                let st = &cal.bundle.state;
                let cov = &cal.bundle.covariance;
                let f = f_err_pct(&st.left, &t.left).max(f_err_pct(&st.right, &t.right));
                let z = [
                    ("left.xi", st.left_distortion.param("xi").unwrap() + 0.15),
                    ("left.alpha", st.left_distortion.param("alpha").unwrap() - 0.55),
                    ("right.xi", st.right_distortion.param("xi").unwrap() + 0.15),
                    ("right.alpha", st.right_distortion.param("alpha").unwrap() - 0.55),
                ]
                .map(|(n, e)| cov.sigma(n).map_or(f64::INFINITY, |s| e.abs() / s));
                let zmax = z.iter().copied().fold(0.0, f64::max);
                // The least squares from the truth on the same observations: its sum of
                // squares against the estimate's tells a start problem (truth lower) from
                // a minimum the data prefer (truth higher).
                let mut from_truth = st.clone();
                (from_truth.left, from_truth.right) = (t.left, t.right);
                from_truth.left_distortion = Distortion::double_sphere(-0.15, 0.55);
                from_truth.right_distortion = from_truth.left_distortion;
                let ls = BundleOptions {
                    zero_skew: true,
                    estimate_distortion: true,
                    max_iterations: 100,
                    ..BundleOptions::default()
                };
                let ssr = |s: &RigState| -> f64 {
                    cal.observations
                        .iter()
                        .map(|o| {
                            headalign_geometry::bundle::residual_pixels(s, o)
                                .map_or(1e6, |r| r.norm_squared())
                        })
                        .sum()
                };
                let truth_ssr =
                    headalign_geometry::bundle::bundle_adjust(&from_truth, &cal.observations, &ls)
                        .map_or(f64::NAN, |r| ssr(&r.state));
                println!(
                    "seed {seed:2}: f error {f:.3} %, lens errors / sigma {z:.2?}, rms {:.3} px, start {}, SSR {:.1} (from the truth {truth_ssr:.1})",
                    cal.report.final_rms_px,
                    cal.report.start,
                    ssr(st)
                );
                (worst_f, worst_z) = (worst_f.max(f), worst_z.max(zmax));
            }
            Err(e) => {
                failed += 1;
                println!("seed {seed:2}: failed: {e}");
            }
        }
    }
    println!("worst f error {worst_f:.3} %, worst lens error {worst_z:.2} sigma, {failed} failed");
}

/// The 180-deg views of [`wide_scenario`] rendered (procedural textures, the renderer's
/// default blur and grey noise): the initial view and views after `rotation_deg` of
/// elevation and of pan.
pub(crate) fn wide_rendered_views(
    seed: u64,
    rotation_deg: f64,
) -> Vec<(String, headalign_platform::StereoImages)> {
    use headalign_platform::ImagingHead;
    let mut s = Scenario { rotation_deg, ..wide_scenario(seed, 0.5) };
    s.render.use_photos = false;
    let mut head = SimulatedHead::new(s).unwrap();
    let e0 = head.encoders();
    [
        ("initial", e0),
        ("elevation", e0.moved(Joint::Elevation, rotation_deg)),
        ("pan", e0.moved(Joint::Pan, rotation_deg)),
    ]
    .into_iter()
    .map(|(name, enc)| {
        head.move_to(&enc).unwrap();
        (name.to_string(), head.capture_images().unwrap())
    })
    .collect()
}

/// The issue-45 bar on rendered images: the 180-deg double sphere of `wide_scenario`
/// (seed 1) in 15-deg views, tracked by the front end (0.05 px RMS) and calibrated with the
/// double sphere: focal lengths within 1 %, `xi` and `alpha` within 3 reported sigmas, and
/// the sum of squares no higher than the least squares started at the truth reaches on
/// the same observations (the other end of the f-xi valley, `calibrate::wide`, fits the
/// profile within 0.5 px out to 110 deg: this run ended there, f +42 %, before the valley
/// candidates were compared on common observations).
#[test]
fn a_180_degree_double_sphere_calibrates_from_rendered_images() {
    let images = wide_rendered_views(1, 15.0);
    let options = CalibrateOptions {
        zero_skew: true,
        lens: LensChoice::Model(headalign_geometry::distortion::LensKind::DoubleSphere),
        ..CalibrateOptions::default()
    };
    let tracked = track_views(&images, &crate::tracking::FrontEndOptions::default(), &options).unwrap();
    let cal = calibrate_tracked(tracked, None, &options).unwrap();
    let st = &cal.bundle.state;
    let truth = wide_scenario(1, 0.5);
    let lens = truth.render.distortion;
    assert!(f_err_pct(&st.left, &truth.left) < 1.0, "{:?} {:?}", st.left, st.left_distortion);
    assert!(f_err_pct(&st.right, &truth.right) < 1.0, "{:?} {:?}", st.right, st.right_distortion);
    let cov = &cal.bundle.covariance;
    for (name, err) in [
        ("left.xi", st.left_distortion.param("xi").unwrap() - lens.param("xi").unwrap()),
        ("left.alpha", st.left_distortion.param("alpha").unwrap() - lens.param("alpha").unwrap()),
        ("right.xi", st.right_distortion.param("xi").unwrap() - lens.param("xi").unwrap()),
        ("right.alpha", st.right_distortion.param("alpha").unwrap() - lens.param("alpha").unwrap()),
    ] {
        let sigma = cov.sigma(name).unwrap();
        eprintln!("rendered {name}: error {err:.5}, sigma {sigma:.5}");
        assert!(err.abs() < 3.0 * sigma, "{name}: error {err:.5}, sigma {sigma:.5}");
    }
    let mut from_truth = st.clone();
    (from_truth.left, from_truth.right) = (truth.left, truth.right);
    (from_truth.left_distortion, from_truth.right_distortion) = (lens, lens);
    let ls = headalign_geometry::bundle::BundleOptions {
        estimate_distortion: true,
        max_iterations: 100,
        ..Default::default()
    };
    let ssr = |s: &RigState| -> f64 {
        cal.observations
            .iter()
            .map(|o| headalign_geometry::bundle::residual_pixels(s, o).map_or(1e6, |r| r.norm_squared()))
            .sum()
    };
    let at_truth =
        ssr(&headalign_geometry::bundle::bundle_adjust(&from_truth, &cal.observations, &ls).unwrap().state);
    eprintln!(
        "rendered: f {:.2} xi {:.4} alpha {:.4}; SSR {:.4} px^2, from the truth {at_truth:.4}",
        st.left.fx,
        st.left_distortion.param("xi").unwrap(),
        st.left_distortion.param("alpha").unwrap(),
        ssr(st)
    );
    assert!(ssr(st) <= at_truth * 1.01, "SSR {} against {at_truth} from the truth", ssr(st));
}

/// The calibration is the same at any thread count (issue 47): the lens grid, the starts,
/// the views' 3D homographies, the lens candidates and the bootstrap run in parallel and
/// are reduced in a fixed order from per-task seeds. A strong barrel lens in 10 deg
/// views (two moved views) with the lens chosen (`auto`: the grid, three starts, the
/// candidates' refits and the bootstrap all run), in a 1-thread and in a 2-thread pool:
/// the adjusted state, the covariance, the observations and the whole report must be
/// equal bit for bit (compared through their exact text: Rust prints the shortest
/// decimal that reads back to the same `f64`, and serde_json keeps every bit).
#[test]
fn the_result_is_the_same_at_any_thread_count() {
    let mut scenario = Scenario { seed: 1, noise_px: 0.25, rotation_deg: 10.0, ..Scenario::default() };
    scenario.render.distortion = Distortion::radial(-0.3, 0.08);
    let mut head = SimulatedHead::new(scenario).unwrap();
    let e0 = head.encoders();
    let views = capture_views(
        &mut head,
        &[
            ("initial", e0),
            ("elevation", e0.moved(Joint::Elevation, 10.0)),
            ("pan", e0.moved(Joint::Pan, 10.0)),
        ],
    );
    let options = CalibrateOptions {
        estimation: EstimationOptions::scaled_for_noise(0.25, 1),
        lens: LensChoice::Auto,
        lens_terms: lens_terms(LensChoice::Auto, None),
        ..CalibrateOptions::default()
    };
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        let c = pool.install(|| calibrate_rig(&views, &options)).unwrap();
        (
            format!("{:?}", c.bundle.state),
            format!("{:?}", c.bundle.covariance),
            format!("{:?}", c.observations),
            serde_json::to_string(&c.report).unwrap(),
        )
    };
    let (one, two) = (run(1), run(2));
    assert!(one.0 == two.0, "states differ:\n{}\n{}", one.0, two.0);
    assert!(one.1 == two.1, "covariances differ");
    assert!(one.2 == two.2, "observations differ");
    assert!(one.3 == two.3, "reports differ:\n{}\n{}", one.3, two.3);
}

/// The reference tracking that takes the depth check's corners, stereo matches and first
/// view (`route::OwnMatching`) gives exactly the tracks, pixels and reports of tracking
/// from the images alone (the same detector settings find the same corners), and a front
/// end that detects otherwise (another corner count) does not take them.
#[test]
fn tracking_from_the_depth_checks_matching_is_tracking_anew() {
    use headalign_platform::ImagingHead;
    let mut head =
        SimulatedHead::new(Scenario { seed: 3, rotation_deg: 3.0, ..Scenario::default() }).unwrap();
    let e0 = head.encoders();
    let images: Vec<(String, headalign_platform::StereoImages)> =
        [("initial", e0), ("elevation", e0.moved(Joint::Elevation, 3.0)), ("pan", e0.moved(Joint::Pan, 3.0))]
            .into_iter()
            .map(|(name, enc)| {
                head.move_to(&enc).unwrap();
                (name.to_string(), head.capture_images().unwrap())
            })
            .collect();
    let front = crate::tracking::FrontEndOptions::default();
    let options = CalibrateOptions::default();
    let (own, kept) = views::stereo_only_keeping(&images, &front).unwrap();
    assert_eq!(own.len(), images.len());
    let anew = track_views(&images, &front, &options).unwrap();
    let shared = route::track_views_sharing(&images, &front, &options, Some(&kept), &mut |_| {}).unwrap();
    assert_eq!(anew.route, Route::Reference);
    assert_eq!(anew.views, shared.views);
    assert_eq!(anew.tracking.len(), shared.tracking.len());
    for (a, b) in anew.tracking.iter().zip(&shared.tracking) {
        // The localisation maps compared as maps (their Debug order is the hasher's).
        assert_eq!(a.localisation, b.localisation);
        let without = |t: &crate::tracking::ViewTracking| {
            format!("{:?}", crate::tracking::ViewTracking { localisation: Default::default(), ..t.clone() })
        };
        assert_eq!(without(a), without(b));
    }
    assert_eq!(own[0], shared.views[0]);
    let mut denser = front.clone();
    denser.features.max_features = 2 * front.features.max_features;
    assert!(!kept.front.detects_like(&denser));
}
