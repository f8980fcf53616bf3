//! The verge/tilt procedure end to end on the simulated head, through the public API
//! only: simulate, run [`headalign::procedure::VergeTiltRun`], check the truth.
//! Noise-free exactness, noisy readings, the restarts out of wrong minima, the measured
//! axes' share of the sigmas, the auto rotation and regressions of single experiment
//! trials. Units: degrees, pixels, percent. The tests that reach private items stay in
//! `crates/headalign/src/procedure/tests.rs`.

use headalign::procedure::{
    AutoRotation, AxisSources, VergeTiltOptions, VergeTiltOutcome, VergeTiltRun, alignment_sigmas,
    alignment_sigmas_measured,
};
use headalign::verge_tilt::{ENCODER_SIGMA_DEG, EstimationOptions};
use headalign_platform::{Encoders, StereoHead};
use headalign_sim::{Scenario, SimulatedHead, calibration_errors};

fn run(scenario: Scenario) -> (SimulatedHead, VergeTiltOutcome) {
    let mut head = SimulatedHead::new(scenario.clone()).unwrap();
    let options = VergeTiltOptions {
        estimation: EstimationOptions { seed: scenario.seed, ..EstimationOptions::default() },
        ..VergeTiltOptions::default()
    };
    let mut run = VergeTiltRun::default();
    let outcome = run.run(&mut head, &options).unwrap();
    assert_eq!(run.views.len(), 6 + outcome.checks.len(), "every captured view is kept");
    (head, outcome)
}

/// Noise-free, no outliers: the correctable alignment errors vanish and the focal
/// lengths are exact. 0.01 deg and 0.01 % are the bars; the solver reaches
/// about 1e-6 here (its tolerances), so they leave a wide margin.
#[test]
fn noise_free_alignment_is_exact() {
    for seed in [1, 2] {
        let scenario = Scenario { seed, noise_px: 0.0, outlier_fraction: 0.0, ..Scenario::default() };
        let (head, outcome) = run(scenario);
        let e = head.alignment_errors(&head.encoders());
        for (name, v) in
            [("verge_l", e.verge_err_l_deg), ("verge_r", e.verge_err_r_deg), ("elev_l", e.elev_err_l_deg)]
        {
            assert!(v.abs() < 0.01, "seed {seed}: {name} = {v} deg");
        }
        // The right camera's elevation error is its mounting, which no joint removes:
        // it must equal the truth's residual and the calibration's prediction.
        let unavoidable = head.alignment_errors(&head.aligned_encoders()).elev_err_r_deg;
        assert!((e.elev_err_r_deg - unavoidable).abs() < 0.01, "seed {seed}");
        assert!(
            (outcome.solution.predicted_elev_err_r_deg.abs() - unavoidable.abs()).abs() < 0.01,
            "seed {seed}"
        );
        let st = &outcome.calibration.bundle.state;
        let cal = calibration_errors(&head.truth().left, &head.truth().right, &st.left, &st.right);
        assert!(cal.f_err_pct < 0.01 && cal.pp_err_pct < 0.01, "seed {seed}: {cal:?}");
    }
}

/// Encoder readings with Gaussian noise at the angle prior's sigma (0.01 deg, every
/// read; the default simulator reads exactly): the procedure runs (it failed with "no
/// view rotates the pan joint alone" while any encoder change counted as a motion) and,
/// with noise-free pixels, aligns to within 4 of its stated sigmas, which include the
/// reference read's noise (measured at most 2.0 over these seeds; before the unmoved
/// joints' jitter was ignored in `verge_axes_from_motion` it tilted the vergence axes,
/// and seed 3's elevation was 6.7 sigmas off) and to within 0.1 deg.
#[test]
fn noisy_encoder_readings_still_align() {
    for seed in [1, 2, 3, 4] {
        let scenario = Scenario {
            seed,
            noise_px: 0.0,
            outlier_fraction: 0.0,
            encoder_noise_deg: ENCODER_SIGMA_DEG,
            ..Scenario::default()
        };
        let (head, outcome) = run(scenario);
        let e = head.alignment_errors(&head.encoders());
        let s = outcome.sigmas;
        for (v, sigma) in [
            (e.verge_err_l_deg, s.verge_left_deg),
            (e.verge_err_r_deg, s.verge_right_deg),
            (e.elev_err_l_deg, s.elevation_deg),
        ] {
            assert!(v.abs() < 0.1 && v.abs() <= 4.0 * sigma, "seed {seed}: {e:?} {s:?}");
        }
    }
}

/// Seed 39 from the experiments' third head position at 2 px (thresholds scaled as in
/// `experiment`): without the depth-reversed restart the least squares ends in the
/// minimum with the baseline's x component reversed, right cx about 6 sigma off
/// (measured -5.8); with it, in the lower minimum (measured -1.2 sigma). The bounds 4
/// and 3 sigma sit between the two with a margin for the solver's tolerance.
#[test]
fn reversed_rig_restart_leaves_the_wrong_minimum() {
    let scenario = Scenario { seed: 39, noise_px: 2.0, ..Scenario::default() };
    let z = |restart: bool| {
        let mut head = SimulatedHead::new(scenario.clone()).unwrap();
        head.move_to(&Encoders { pan: -4.0, elevation: -4.0, verge_left: -2.0, verge_right: 2.0 }).unwrap();
        let d = EstimationOptions::default();
        let mut estimation = EstimationOptions {
            seed: scenario.seed,
            prefilter_px: 2.0 * d.prefilter_px,
            reversed_rig_restart: restart,
            ..d
        };
        estimation.fundamental.threshold *= 2.0;
        estimation.homography.threshold *= 2.0;
        let options = VergeTiltOptions {
            rotation_deg: scenario.rotation_deg,
            verge_rotation_deg: 3.0,
            estimation,
            ..VergeTiltOptions::default()
        };
        let outcome = VergeTiltRun::default().run(&mut head, &options).unwrap();
        let bundle = &outcome.calibration.bundle;
        (bundle.state.right.cx - head.truth().right.cx) / bundle.covariance.sigma("right.cx").unwrap()
    };
    let (without, with) = (z(false), z(true));
    assert!(without.abs() > 4.0, "without the restart: {without}");
    assert!(with.abs() < 3.0, "with the restart: {with}");
}

/// One trial of `headalign experiment` at the paper's protocol (default scenario at
/// `noise_px`, head position 0, the experiments' estimation options).
fn experiment_trial(seed: u64, noise_px: f64) -> (SimulatedHead, VergeTiltOutcome) {
    let scenario = Scenario { seed, noise_px, ..Scenario::default() };
    let mut head = SimulatedHead::new(scenario.clone()).unwrap();
    let options = VergeTiltOptions {
        rotation_deg: scenario.rotation_deg,
        verge_rotation_deg: 3.0,
        estimation: EstimationOptions::scaled_for_noise(noise_px, seed),
        ..VergeTiltOptions::default()
    };
    let outcome = VergeTiltRun::default().run(&mut head, &options).unwrap();
    (head, outcome)
}

/// Seed 1211 of `experiment fig5-verge-tilt --seed 1001` (first head position, 3 px,
/// the experiment's options): the restarts from the x-reversed and the fully reversed
/// baseline end above the estimate, which has the baseline's forward component at +0.64
/// (unit baseline); the minimum the least squares reaches from the truth has it at -0.53
/// at 3.2 chi-square units lower cost, and the y-z reversed restart reaches it
/// (`docs/accuracy.md`). The sign of that component tells the two minima apart.
#[test]
fn yz_reversed_restart_reaches_the_lower_minimum() {
    let (_, outcome) = experiment_trial(1211, 3.0);
    let t = outcome.calibration.bundle.state.right_from_left.translation.vector.normalize();
    assert!(t.z < -0.3, "baseline direction {t:?}");
}

/// Regression (calibration experiment, 3 px, seed 368): the estimate's baseline was
/// (0.01, -0.36, -0.93), along the optical axis and 84 deg from the truth's, with left fx
/// 146 px off, 127 chi-square units above the minimum the least squares reaches from
/// the truth; the side-by-side restart reaches that minimum (left fx 45 px off, sigma
/// 22; baseline (-0.56, -0.25, -0.79): at 3 px the baseline's forward component is
/// weakly determined, the truth's minimum has -0.59). Limits: the baseline's x component
/// above 0.3 (it was 0.01) and left fx within 90 px (4 of its sigmas; it was 6.6 off).
#[test]
fn sideways_restart_leaves_a_baseline_along_the_optical_axis() {
    let (head, outcome) = experiment_trial(368, 3.0);
    let st = &outcome.calibration.bundle.state;
    let t = st.right_from_left.translation.vector.normalize();
    assert!(t.x.abs() > 0.3, "baseline direction {t:?}");
    assert!((st.left.fx - head.truth().left.fx).abs() < 90.0, "left fx {}", st.left.fx);
}

/// Default scenario (1 px, 10 % outliers): one seed within generous single-run limits
/// (the RMS bars over 20 seeds are 0.5 deg and 1.5 %; one run gets three times that),
/// and the reported sigmas are not absurd.
#[test]
fn default_scenario_aligns() {
    let (head, outcome) = run(Scenario { seed: 11, ..Scenario::default() });
    let e = head.alignment_errors(&head.encoders());
    for v in [e.verge_err_l_deg, e.verge_err_r_deg, e.elev_err_l_deg] {
        assert!(v.abs() < 1.5, "{e:?}");
    }
    let st = &outcome.calibration.bundle.state;
    let cal = calibration_errors(&head.truth().left, &head.truth().right, &st.left, &st.right);
    assert!(cal.f_err_pct < 4.5, "{cal:?}");
    let s = outcome.sigmas;
    for v in [s.elevation_deg, s.verge_left_deg, s.verge_right_deg] {
        assert!(v > 0.01 && v < 2.0, "sigma {v}");
    }
}

/// The vergence axes' own measurement adds uncertainty: with no axis source the
/// measured-axis sigmas equal [`alignment_sigmas`] (same finite differences, 1e-12 is
/// rounding); with the procedure's sources the vergence sigmas change a little, and the pose
/// variance scales with the pixel noise squared (resection covariance is sigma^2 (J^T J)^-1).
#[test]
fn measured_axes_add_their_own_uncertainty() {
    let (_, outcome) = run(Scenario { seed: 11, ..Scenario::default() });
    let calib = &outcome.calibration;
    let reference = calib.reference_encoders;
    let fixed = alignment_sigmas(calib, &outcome.verge_axes, &reference).unwrap();
    let none =
        alignment_sigmas_measured(calib, &outcome.verge_axes, &AxisSources::default(), &reference, None)
            .unwrap();
    assert!((fixed.verge_left_deg - none.verge_left_deg).abs() < 1e-12);
    assert!((fixed.elevation_deg - none.elevation_deg).abs() < 1e-12);
    let src = &outcome.axis_sources;
    assert!(src.left.is_some() && src.right.is_some());
    let measured = outcome.sigmas;
    // The axes' own measurement is a small part of the vergence sigmas (resection
    // against ~200 points; the points follow the calibration, which partly cancels):
    // they move, but by less than 5 % (measured: 0.05 %).
    for (m, f) in
        [(measured.verge_left_deg, fixed.verge_left_deg), (measured.verge_right_deg, fixed.verge_right_deg)]
    {
        assert!(m != f && (m / f - 1.0).abs() < 0.05, "{measured:?} vs {fixed:?}");
    }
    // Variance = calibration part + pose part * sigma^2: (v3 - v2) / (v2 - v1) = 5/3
    // (the finite differences are at 0.5 sigma of a nearly linear map: 2 % is generous).
    let var = |px: f64| {
        alignment_sigmas_measured(calib, &outcome.verge_axes, src, &reference, Some(px))
            .unwrap()
            .verge_left_deg
            .powi(2)
    };
    let ratio = (var(3.0) - var(2.0)) / (var(2.0) - var(1.0));
    assert!((ratio - 5.0 / 3.0).abs() < 0.035, "ratio {ratio}");
}

/// End to end with the auto mode (1 px, 10 % outliers): 10 deg each way and 10 deg
/// diagonals on the default room, every view estimated. Limits: the bars of the
/// issue's auto condition (0.15 deg, 0.5 %) with a factor 3 for one run.
#[test]
fn auto_rotation_with_diagonals_end_to_end() {
    let scenario = Scenario { seed: 4, ..Scenario::default() };
    let mut head = SimulatedHead::new(scenario.clone()).unwrap();
    let options = VergeTiltOptions {
        estimation: EstimationOptions { seed: scenario.seed, ..EstimationOptions::default() },
        auto_rotation: Some(AutoRotation::default()),
        ..VergeTiltOptions::default()
    };
    let mut run = VergeTiltRun::default();
    let outcome = run.run(&mut head, &options).unwrap();
    assert_eq!(
        (outcome.rotation_deg, outcome.diagonal_rotation_deg, outcome.verge_rotation_deg),
        (10.0, 10.0, 10.0)
    );
    assert_eq!(run.views.len(), 10 + outcome.checks.len(), "probes are not kept");
    assert_eq!(outcome.calibration.report.homographies.len(), 8, "every rotated view is estimated");
    let e = head.alignment_errors(&head.encoders());
    for v in [e.verge_err_l_deg, e.verge_err_r_deg, e.elev_err_l_deg] {
        assert!(v.abs() < 0.45, "{e:?}");
    }
    let st = &outcome.calibration.bundle.state;
    let cal = calibration_errors(&head.truth().left, &head.truth().right, &st.left, &st.right);
    assert!(cal.f_err_pct < 1.5, "{cal:?}");
}

/// A 50-point scene (1.5 px, the 50-point bar): the auto mode leaves the 3 deg
/// protocol (with the former `min_tracks` of 60 it never did, since such a scene never
/// shares 60 tracks) and every view is estimated. Limit 0.75 deg: three times the
/// RMS elevation error of 150 such runs (0.25 deg, `headalign experiment points --only
/// 50 --trials 300`), against 0.74 deg RMS with the fixed 3 deg protocol.
#[test]
fn auto_rotation_grows_in_a_fifty_point_scene() {
    let scenario = Scenario { seed: 2, points: 50, noise_px: 1.5, ..Scenario::default() };
    let mut head = SimulatedHead::new(scenario.clone()).unwrap();
    let options = VergeTiltOptions {
        estimation: EstimationOptions { seed: scenario.seed, ..EstimationOptions::default() },
        auto_rotation: Some(AutoRotation::default()),
        ..VergeTiltOptions::default()
    };
    let outcome = VergeTiltRun::default().run(&mut head, &options).unwrap();
    assert!(outcome.rotation_deg >= 6.0 && outcome.diagonal_rotation_deg >= 3.0, "{}", outcome.rotation_deg);
    let e = head.alignment_errors(&head.encoders());
    assert!(e.elev_err_l_deg.abs() < 0.75 && e.verge_err_l_deg.abs() < 0.75, "{e:?}");
}

/// Regression (calibration experiment, 3 px, seed 53): the re-selected adjustment
/// explained a wrong track by a point at depth 1e-11, whose rounding noise made the
/// reduced camera system indefinite, and the whole estimate failed ("a parameter is
/// unobservable"); such a point now leaves the covariance and the depth filter after
/// that adjustment removes it. Limit 2.2 deg: three times the RMS elevation and
/// vergence errors of 250 such runs (0.72 deg); this run ends at 0.14 and 0.47 deg.
#[test]
fn a_point_collapsed_onto_a_camera_does_not_fail_the_estimate() {
    let (head, _) = experiment_trial(53, 3.0);
    let e = head.alignment_errors(&head.encoders());
    assert!(e.elev_err_l_deg.abs() < 2.2 && e.verge_err_l_deg.abs() < 2.2, "{e:?}");
}

/// Regression (50 points, 1.5 px, 3 deg, seed 97, the experiment's thresholds scaled
/// by 1.5): a round of the maximum-likelihood re-classification left a parameter
/// unobservable and the whole estimate failed ("reduced camera system is singular");
/// the rounds now end at the last classification that fitted. Limit 2.2 deg: three
/// times the RMS elevation error of 150 such runs (0.74 deg); this run ends at 0.73.
#[test]
fn a_singular_reclassification_keeps_the_last_fit() {
    let scenario = Scenario { seed: 97, points: 50, noise_px: 1.5, ..Scenario::default() };
    let mut head = SimulatedHead::new(scenario.clone()).unwrap();
    let estimation = EstimationOptions::scaled_for_noise(1.5, 97);
    let options = VergeTiltOptions { estimation, verge_rotation_deg: 3.0, ..VergeTiltOptions::default() };
    VergeTiltRun::default().run(&mut head, &options).unwrap();
    let e = head.alignment_errors(&head.encoders());
    assert!(e.elev_err_l_deg.abs() < 2.2, "{e:?}");
}

/// Regression (3 px, seed 29, the former auto plan without diagonals): the first check
/// measured 0.41 deg, above the tolerance, and the correction re-measured the left
/// vergence axis from a 0.9 deg vergence turn after 8 deg of elevation: the axis came
/// out 80 deg off and the head ended 8 deg from aligned. Now an axis is re-measured only
/// from a vergence turn at least as large as the procedure's own (3 deg). Limit 1 deg:
/// this run ends at 0.04 deg elevation and 0.44 deg vergence (3 px).
#[test]
fn small_vergence_turns_do_not_remeasure_the_axis() {
    let scenario = Scenario { seed: 29, noise_px: 3.0, ..Scenario::default() };
    let mut head = SimulatedHead::new(scenario.clone()).unwrap();
    let estimation = EstimationOptions::scaled_for_noise(3.0, 29);
    let auto = AutoRotation {
        diagonals: false,
        choose_verge: false,
        min_overlap_fraction: 0.6,
        ..AutoRotation::default()
    };
    let options = VergeTiltOptions { estimation, auto_rotation: Some(auto), ..VergeTiltOptions::default() };
    let outcome = VergeTiltRun::default().run(&mut head, &options).unwrap();
    assert_eq!(outcome.rotation_deg, 10.0);
    let e = head.alignment_errors(&head.encoders());
    assert!(e.elev_err_l_deg.abs() < 1.0 && e.verge_err_l_deg.abs() < 1.0, "{e:?}");
}
