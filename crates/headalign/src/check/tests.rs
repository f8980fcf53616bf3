//! Tests of the check on synthetic matches with a known rotation change.

use headalign_geometry::camera::Intrinsics;
use headalign_geometry::distortion::Distortion;
use nalgebra::{Isometry3, Point2, Point3, Translation3, UnitQuaternion};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use super::*;
use crate::calibration::{IntrinsicSigmas, TranslationUnit};

/// An EuRoC-like rig: 752 x 480, f = 458 px, 0.11 m baseline, a 0.8 deg rotation.
fn rig() -> StereoCalibration {
    StereoCalibration {
        image_size: [752, 480],
        left: Intrinsics::new(458.654, 457.296, 367.215, 248.375),
        right: Intrinsics::new(457.587, 456.134, 379.999, 255.238),
        sigmas: [IntrinsicSigmas::default(); 2],
        right_from_left: Isometry3::from_parts(
            Translation3::new(-0.11, 0.0002, -0.0009),
            UnitQuaternion::from_euler_angles(-0.014, 0.0004, -0.0023),
        ),
        unit: TranslationUnit::Metres,
        distortion: [Distortion::default(); 2],
    }
}

/// Matches of `n` points at 1.5-20 m seen by the rig `truth`, pixel noise `noise` (0: none).
fn matches(truth: &StereoCalibration, n: usize, noise: f64, seed: u64) -> Vec<Match> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let u = rand_distr::Uniform::new(0.0, 1.0).unwrap();
    let g = Normal::new(0.0, noise.max(1e-300)).unwrap();
    let mut out = Vec::new();
    while out.len() < n {
        let (x, y, z) = (u.sample(&mut rng), u.sample(&mut rng), 1.5 + 18.5 * u.sample(&mut rng));
        let pl = Point2::new(x * 752.0, y * 480.0);
        let ray = truth.left.inverse_matrix() * nalgebra::Vector3::new(pl.x, pl.y, 1.0);
        let xl = Point3::from(ray * z);
        let Some(pr) = truth.right.project(&(truth.right_from_left * xl)) else { continue };
        if !(0.0..752.0).contains(&pr.x) || !(0.0..480.0).contains(&pr.y) {
            continue;
        }
        let mut jitter = || if noise > 0.0 { g.sample(&mut rng) } else { 0.0 };
        out.push((
            Point2::new(pl.x + jitter(), pl.y + jitter()),
            Point2::new(pr.x + jitter(), pr.y + jitter()),
        ));
    }
    out
}

fn w_deg(p: f64, y: f64, r: f64) -> Vector3<f64> {
    Vector3::new(p, y, r).map(f64::to_radians)
}

/// Noise-free matches of a rig turned by a known `dR`: the refit finds it to rounding
/// (1e-10 deg: the Sampson distance is exact at a zero-residual minimum, and the cost
/// is at the level of 1e-20 px^2).
#[test]
fn refit_finds_a_known_change_noise_free() {
    let given = rig();
    let w = w_deg(0.1, -0.3, 0.05);
    let truth = turned(&given, &so3::exp(&w));
    let m = matches(&truth, 300, 0.0, 1);
    let model = epipolar_model(&given).unwrap();
    let all: Vec<usize> = (0..m.len()).collect();
    let fit = refit_rotation(&model, &m, &all, &Rotation3::identity()).unwrap();
    let err = (so3::log(&fit.dr) - w).abs().max().to_degrees();
    assert!(err < 1e-10, "error {err} deg");
}

/// The analytic Jacobian of the Sampson distances in `delta` against central differences
/// (step 1e-7 rad; agreement to 1e-6 relative, the differences' truncation and rounding).
#[test]
fn jacobian_matches_finite_differences() {
    let given = rig();
    let m = matches(&turned(&given, &so3::exp(&w_deg(0.2, 0.1, -0.1))), 50, 0.3, 2);
    let model = epipolar_model(&given).unwrap();
    let all: Vec<usize> = (0..m.len()).collect();
    let at = so3::exp(&w_deg(0.05, -0.02, 0.03));
    let rows = model.jacobian(&at, &m, &all);
    let h = 1e-7;
    for k in 0..3 {
        let d = Vector3::ith(k, h);
        let plus = model.residuals(&(so3::exp(&d) * at), &m, &all);
        let minus = model.residuals(&(so3::exp(&-d) * at), &m, &all);
        for (i, (_, row)) in rows.iter().enumerate() {
            let numeric = (plus[i] - minus[i]) / (2.0 * h);
            let scale = row.norm().max(1.0);
            assert!((numeric - row[k]).abs() < 1e-6 * scale, "match {i} axis {k}: {numeric} vs {}", row[k]);
        }
    }
}

/// With noise and 10 % gross outliers, the robust check finds the change within 4 of its
/// sigmas on every axis, measures the noise to 10 %, and says recalibrate (0.3 deg of yaw
/// is a 24 % depth error at 5 m).
#[test]
fn check_finds_a_change_with_noise_and_outliers() {
    let given = rig();
    let w = w_deg(0.0, 0.3, 0.0);
    let mut m = matches(&turned(&given, &so3::exp(&w)), 1000, 0.5, 3);
    for (i, x) in m.iter_mut().enumerate().filter(|(i, _)| i % 10 == 0) {
        x.1.y += 5.0 + (i % 7) as f64;
    }
    let pairs = vec![PairMatches { name: "a".into(), matches: m }];
    let r = check_matches(&pairs, &given, 0.11, &CheckOptions::default()).unwrap();
    let found = r.rotation_change_deg.to_rad();
    let sigma = r.rotation_change_sigma_deg.to_rad();
    for i in 0..3 {
        assert!((found[i] - w[i]).abs() < 4.0 * sigma[i], "axis {i}: {found:?} vs {w:?} sigma {sigma:?}");
    }
    // The Sampson distance of a match with independent noise sigma in each coordinate
    // has sigma sigma (first order); 10 % from 900 residuals is > 4 standard errors.
    assert!((r.noise_px - 0.5).abs() < 0.05, "noise {}", r.noise_px);
    assert_eq!(r.verdict, Verdict::Recalibrate);
    // f * 0.3 deg = 2.40 px at the image centre over the 10.1 px disparity at 5 m is 24 %;
    // the shift grows as 1 + x^2 / f^2 towards the sides (x^2 / f^2 up to 0.67 here, 0.22
    // on average): its RMS over the image is 24 % times about 1.25-1.3.
    assert!(r.depth_error_pct.at_5m > 28.0 && r.depth_error_pct.at_5m < 33.0, "{:?}", r.depth_error_pct);
    assert!(r.updated.is_some());
}

/// No change: the verdict is good and the change is within 4 sigmas of zero (3000
/// matches at 0.25 px, about what four real pairs give).
#[test]
fn unchanged_rig_is_good() {
    let given = rig();
    let m = matches(&given, 3000, 0.25, 4);
    let pairs = vec![PairMatches { name: "a".into(), matches: m }];
    let r = check_matches(&pairs, &given, 0.11, &CheckOptions::default()).unwrap();
    let found = r.rotation_change_deg.to_rad();
    let sigma = r.rotation_change_sigma_deg.to_rad();
    for i in 0..3 {
        assert!(found[i].abs() < 4.0 * sigma[i], "axis {i}: {found:?} sigma {sigma:?}");
    }
    assert_eq!(r.verdict, Verdict::Good, "{r:?}");
}

#[test]
fn truncated_variance_and_left_jacobian() {
    assert!((refit::truncated_normal_variance(3.0) - 0.973_337_2).abs() < 1e-6);
    assert_eq!(refit::truncated_normal_variance(f64::INFINITY), 1.0);
    // exp(delta) exp(w) = exp(w + J^-1 delta) to second order.
    let w = Vector3::new(0.3, -0.2, 0.1);
    let d = Vector3::new(1e-6, -2e-6, 0.5e-6);
    let lhs = so3::log(&(so3::exp(&d) * so3::exp(&w)));
    let rhs = w + refit::left_jacobian_inverse(&w) * d;
    assert!((lhs - rhs).norm() < 1e-11, "{}", (lhs - rhs).norm());
}

#[test]
fn bad_options_are_errors() {
    let o = CheckOptions { inlier_sigmas: -1.0, ..CheckOptions::default() };
    assert!(matches!(o.validate(), Err(CheckError::InvalidOption(_))));
    let o = CheckOptions { min_matches: 2, ..CheckOptions::default() };
    assert!(o.validate().is_err());
}

/// The minimal solver is exact on three noise-free matches of a change of 0.5 deg (its
/// Newton steps converge quadratically: 1e-12 rad after three).
#[test]
fn minimal_solver_is_exact_noise_free() {
    let given = rig();
    let w = w_deg(0.2, -0.5, 0.3);
    let m = matches(&turned(&given, &so3::exp(&w)), 3, 0.0, 5);
    let model = epipolar_model(&given).unwrap();
    let dr = refit::minimal_rotation(&model, &m).unwrap();
    // Three matches fix three angles; the perspective terms that carry yaw are small, so
    // the sample's conditioning costs digits: 1e-9 rad is far below any noise.
    assert!((so3::log(&dr) - w).abs().max() < 1e-9, "{} vs {w}", so3::log(&dr));
}

/// A right camera whose `fy` grew by 0.5 % (and no rotation): the intrinsics test finds it
/// within 4 sigmas and calls it significant; with `fy` unchanged it is not.
#[test]
fn intrinsics_test_finds_a_focal_change() {
    let given = rig();
    for (change_pct, expect) in [(0.5, true), (0.0, false)] {
        let mut truth = given.clone();
        truth.right.fy *= 1.0 + change_pct / 100.0;
        let m = matches(&truth, 2000, 0.25, 6);
        let pairs = vec![PairMatches { name: "a".into(), matches: m }];
        let r = check_matches(&pairs, &given, 0.11, &CheckOptions::default()).unwrap();
        let i = r.intrinsics_change.unwrap();
        assert!((i.fy_pct.value - change_pct).abs() < 4.0 * i.fy_pct.sigma, "{i:?}");
        assert_eq!(i.significant, expect, "{i:?}");
    }
}

/// Too few matches: an error naming the counts, never a report.
#[test]
fn too_few_matches_is_an_error() {
    let given = rig();
    let pairs = vec![PairMatches { name: "a".into(), matches: matches(&given, 12, 0.25, 7) }];
    let e = check_matches(&pairs, &given, 0.11, &CheckOptions::default()).unwrap_err();
    assert!(matches!(e, CheckError::TooFewMatches { got: 12, needed: 30, pairs: 1 }), "{e}");
}

/// A calibration in baselines needs the baseline in metres for the depth error.
#[test]
fn baselines_need_a_metric_baseline() {
    let mut given = rig();
    given.unit = TranslationUnit::Baselines;
    assert!(matches!(metric_baseline(&given, &CheckOptions::default()), Err(CheckError::Calibration(_))));
    let o = CheckOptions { baseline_m: Some(0.11), ..CheckOptions::default() };
    assert_eq!(metric_baseline(&given, &o).unwrap(), 0.11);
}
