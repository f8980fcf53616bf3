//! Tests of the verge/tilt procedure ([`super`]) that reach its private items: the
//! uncertainty propagations against their definitions and against Monte-Carlo runs, the
//! rotation choice and the capture plan. The end-to-end runs through the public API
//! (exactness, noisy readings, restarts, auto rotation) are in
//! `crates/headalign/tests/integration/verge_tilt_procedure.rs`. Most run whole simulated
//! procedures (slow); the experiments are ignored: run them by name. Units as in the
//! module: degrees, pixels.

use headalign_platform::{Encoders, StereoHead};
use headalign_sim::{Scenario, SimulatedHead};

use super::axes::{AxisFollow, project_into, resection_inliers, retriangulated};
use super::rotation::{choose_rotation, diagonal_offsets, single_joint_offsets};
use super::sigmas::{aligned_deltas, calibration_jacobian, fixation_jacobian, sigmas_of};
use super::*;
use crate::alignment::{VergeAxes, measure_cameras, solve_alignment, verge_axes_from_motion};
use crate::verge_tilt::{EstimationOptions, RigCalibration};

/// The procedure as `experiment fig5-verge-tilt` runs it (3 deg vergence move, RANSAC
/// thresholds scaled by the noise) from initial readings `initial`.
fn run_as_experiment(scenario: Scenario, initial: Encoders) -> (SimulatedHead, VergeTiltOutcome) {
    let mut head = SimulatedHead::new(scenario.clone()).unwrap();
    head.move_to(&initial).unwrap();
    let estimation = EstimationOptions::scaled_for_noise(scenario.noise_px, scenario.seed);
    let options = VergeTiltOptions { verge_rotation_deg: 3.0, estimation, ..VergeTiltOptions::default() };
    let outcome = VergeTiltRun::default().run(&mut head, &options).unwrap();
    (head, outcome)
}

/// The verge-tilt procedure as the experiments run it, at 2 px from (pan 4, elevation 4,
/// vergences 2 / -2) deg. Of seeds 1-30, seeds 4, 11, 13, 14, 15, 23 and 30 re-measure
/// the left axis in a check view 6-14 deg of elevation from the reference, where the
/// axis is most sensitive to the calibration (a past measurement).
fn check_view_case_at(seed: u64) -> (SimulatedHead, VergeTiltOutcome) {
    let initial = Encoders { pan: 4.0, elevation: 4.0, verge_left: 2.0, verge_right: -2.0 };
    run_as_experiment(Scenario { seed, noise_px: 2.0, ..Scenario::default() }, initial)
}

/// The linearised calibration part ([`AxisFollow::followed`]: one Gauss-Newton step for
/// the points and for each axis pose, least squares over the inliers held) against the
/// procedure's own computation under the same perturbations: points re-triangulated
/// to convergence (4 steps), the axis poses resected by [`measure_cameras`] itself
/// (robust, from its own inliers), the axes by [`verge_axes_from_motion`]. Both
/// Jacobians are propagated through the bundle covariance. Seeds 1-12, the first
/// twelve, unselected (seeds 4 and 11 re-measure the left axis in a check view). The
/// agreement is a property of each seed: the real resection's Huber weights (2 px, at
/// 2 px noise) and its own inlier choice make it a different estimator from least
/// squares over fixed inliers. Over seeds 1-30 (`scan_check_view_seeds`) the elevation
/// ratio is 0.79-1.08, median 1.001 (seed 9 lowest, seed 13 0.88; without
/// `EstimationOptions::image_border` 0.86-1.02, median 0.997), the vergences'
/// 0.99-1.01 (without it 0.96-1.01): each seed is held to 25 % on the elevation and 5 %
/// on the vergences, the elevation's median to 3 %. Letting the points seen only twice
/// into the linearised resection (as a first version did) gave 2.95x on the elevation
/// at seed 13.
#[test]
fn axis_sensitivity_matches_the_real_resection() {
    let mut elevation = Vec::new();
    for seed in 1..=12 {
        let (_, outcome) = check_view_case_at(seed);
        let [a, b] = linearised_and_resected_sigmas(&outcome);
        for (name, x, y, tol) in [
            ("elevation", a.elevation_deg, b.elevation_deg, 0.25),
            ("verge left", a.verge_left_deg, b.verge_left_deg, 0.05),
            ("verge right", a.verge_right_deg, b.verge_right_deg, 0.05),
        ] {
            assert!((x / y - 1.0).abs() < tol, "seed {seed} {name}: linearised {x} vs resection {y}");
        }
        elevation.push(a.elevation_deg / b.elevation_deg);
    }
    elevation.sort_by(f64::total_cmp);
    let median = 0.5 * (elevation[5] + elevation[6]);
    assert!((median - 1.0).abs() < 0.03, "median elevation ratio {median}: {elevation:?}");
}

/// The calibration part of the alignment sigmas, linearised ([`AxisFollow::followed`])
/// and through the procedure's own resection (see the test above).
fn linearised_and_resected_sigmas(outcome: &VergeTiltOutcome) -> [AlignmentSigmas; 2] {
    let calib = &outcome.calibration;
    let reference = calib.reference_encoders;
    let sources = &outcome.axis_sources;
    let follow = AxisFollow::new(calib, &outcome.verge_axes, sources, &reference);
    let cov = &calib.bundle.covariance;
    let linear = calibration_jacobian(cov, &[&|d| follow.followed(d)]);
    let full = calibration_jacobian(
        cov,
        &[&|d| {
            let mut st = calib.bundle.perturbed(d).ok()?;
            for _ in 0..4 {
                st = retriangulated(&st, &follow.by_point);
            }
            let moved = RigCalibration {
                bundle: headalign_geometry::bundle::BundleResult {
                    state: st.clone(),
                    ..calib.bundle.clone()
                },
                ..calib.clone()
            };
            let axis = |src: &Option<AxisMeasurement>| -> Option<VergeAxes> {
                let Some(src) = src else { return Some(outcome.verge_axes) };
                let m = measure_cameras(
                    &moved,
                    &src.capture,
                    &src.measured.ref_from_left,
                    &src.measured.ref_from_right,
                )
                .ok()?;
                verge_axes_from_motion(&st, &reference, &src.capture.encoders, &m).ok()
            };
            let axes = VergeAxes { left: axis(&sources.left)?.left, right: axis(&sources.right)?.right };
            solve_alignment(&st, &axes, &reference).ok().map(|s| aligned_deltas(&s))
        }],
    );
    [
        sigmas_of(&(&linear * &cov.matrix * linear.transpose())),
        sigmas_of(&(&full * &cov.matrix * full.transpose())),
    ]
}

/// Monte-Carlo of the pose part: the axis sources' captures re-drawn 300 times and run
/// through [`measure_cameras`], [`verge_axes_from_motion`] and [`solve_alignment`] with
/// the calibration held; the spread of the aligned deltas against the pose part of
/// [`alignment_sigmas_measured`] (its variance at 1 px minus at ~0 px). Each draw is the
/// model the prediction linearises: the tracks its resection holds, at the projections
/// of the calibration's points through the measured poses, plus 1 px Gaussian noise.
/// (Exact pixels of the true scene instead add the calibration's fixed misfit, which
/// through the resection's Huber weights moved the spread by -8 % to +68 % of the
/// prediction over seeds 1-30, seed 14 most; the model's draws 0.91-1.11.) 300 draws know a standard
/// deviation to 4 %; tolerance 15 % (3.5 standard errors) of the pose part plus 0.3 % of
/// the total sigma: the vergences' pose parts are a few thousandths of a degree (0.5-2 %
/// of the total), where the second-order term is as large as the linear one (seed 4's
/// left: 0.0023 deg against a linear 0.0017), and at that size a pose part changes the
/// total by less than 0.02 %.
/// Seeds 4 and 13 (check views 14 deg from the reference: the largest elevation pose
/// parts, 0.12 deg) and 14.
#[test]
fn pose_part_matches_monte_carlo() {
    for seed in [4, 13, 14] {
        let (head, outcome) = check_view_case_at(seed);
        let [predicted, sd, total] = pose_part_and_monte_carlo(&head, &outcome, 300, true);
        for (i, name) in ["elevation", "verge left", "verge right"].iter().enumerate() {
            assert!(
                (sd[i] - predicted[i]).abs() < 0.15 * predicted[i] + 0.003 * total[i],
                "seed {seed} {name}: Monte-Carlo {} vs {} (total {})",
                sd[i],
                predicted[i],
                total[i]
            );
        }
    }
}

/// The pose part of [`alignment_sigmas_measured`] at 1 px (elevation, verge left, verge
/// right; degrees), the standard deviations of `draws` Monte-Carlo re-draws (see the
/// test above; `consistent` false: exact pixels of the true scene), and the total
/// sigmas at 1 px.
fn pose_part_and_monte_carlo(
    head: &SimulatedHead,
    outcome: &VergeTiltOutcome,
    draws: usize,
    consistent: bool,
) -> [[f64; 3]; 3] {
    use rand::{RngExt, SeedableRng};
    let calib = &outcome.calibration;
    let reference = calib.reference_encoders;
    let sources = &outcome.axis_sources;
    let var = |px: f64| {
        let s = alignment_sigmas_measured(calib, &outcome.verge_axes, sources, &reference, Some(px)).unwrap();
        [s.elevation_deg.powi(2), s.verge_left_deg.powi(2), s.verge_right_deg.powi(2)]
    };
    let (v1, v0) = (var(1.0), var(1e-9));
    let predicted = [0, 1, 2].map(|i| (v1[i] - v0[i]).max(0.0).sqrt());
    let state = &calib.bundle.state;
    let points: std::collections::HashMap<u64, nalgebra::Point3<f64>> = calib.points().into_iter().collect();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut noisy = |c: &headalign_platform::StereoCapture| {
        let mut c = c.clone();
        for o in c.left.iter_mut().chain(c.right.iter_mut()) {
            o.pixel.x += rng.sample::<f64, _>(rand_distr::StandardNormal);
            o.pixel.y += rng.sample::<f64, _>(rand_distr::StandardNormal);
        }
        c
    };
    // The tracks the prediction's resections hold (left, right camera), from the real
    // capture of each axis source.
    let held = |src: &Option<AxisMeasurement>| -> [std::collections::HashSet<u64>; 2] {
        let Some(src) = src else { return Default::default() };
        let of =
            |k, obs, pose| resection_inliers(k, &points, obs, pose).into_iter().map(|(t, _)| t).collect();
        [
            of(&state.left, &src.capture.left, &src.measured.ref_from_left),
            of(&state.right, &src.capture.right, &src.measured.ref_from_right),
        ]
    };
    let held = [held(&sources.left), held(&sources.right)];
    let mut samples = Vec::with_capacity(draws);
    for _ in 0..draws {
        let mut axis = |src: &Option<AxisMeasurement>,
                        [left, right]: &[std::collections::HashSet<u64>; 2]| {
            let Some(src) = src else { return outcome.verge_axes };
            let mut capture = head.exact_capture(&src.capture.encoders);
            capture.left.retain(|o| left.contains(&o.track));
            capture.right.retain(|o| right.contains(&o.track));
            if consistent {
                for (obs, k, pose) in [
                    (&mut capture.left, &state.left, &src.measured.ref_from_left),
                    (&mut capture.right, &state.right, &src.measured.ref_from_right),
                ] {
                    for o in obs.iter_mut() {
                        if let Some(p) = points.get(&o.track).and_then(|x| project_into(k, pose, x)) {
                            o.pixel = nalgebra::Point2::from(p);
                        }
                    }
                }
            }
            let capture = noisy(&capture);
            let m =
                measure_cameras(calib, &capture, &src.measured.ref_from_left, &src.measured.ref_from_right)
                    .unwrap();
            verge_axes_from_motion(state, &reference, &capture.encoders, &m).unwrap()
        };
        let axes = VergeAxes {
            left: axis(&sources.left, &held[0]).left,
            right: axis(&sources.right, &held[1]).right,
        };
        samples.push(aligned_deltas(&solve_alignment(state, &axes, &reference).unwrap()));
    }
    let sd = [0, 1, 2].map(|i| {
        let mean = samples.iter().map(|s| s[i]).sum::<f64>() / draws as f64;
        (samples.iter().map(|s| (s[i] - mean).powi(2)).sum::<f64>() / (draws - 1) as f64).sqrt()
    });
    [predicted, sd, v1.map(f64::sqrt)]
}

/// The two checks above over seeds 1-30, printed (a diagnostic, not a test: `cargo test
/// --release -p headalign --lib scan_check_view_seeds -- --ignored --nocapture`); the
/// Monte-Carlo both ways (`consistent` true and false).
#[test]
#[ignore]
fn scan_check_view_seeds() {
    for seed in 1..=30 {
        let (head, outcome) = check_view_case_at(seed);
        let moved = outcome.axis_sources.left.as_ref().map_or(0.0, |src| {
            (src.capture.encoders.elevation - outcome.calibration.reference_encoders.elevation).abs()
        });
        let [a, b] = linearised_and_resected_sigmas(&outcome);
        let [p, model, _] = pose_part_and_monte_carlo(&head, &outcome, 200, true);
        let [_, scene, total] = pose_part_and_monte_carlo(&head, &outcome, 200, false);
        eprintln!(
            "seed {seed} check view {moved:.1} deg | calibration part linearised/resected: elevation \
             {:.3} verge {:.3} {:.3} | pose part (deg) predicted / Monte-Carlo model / scene: \
             elevation {:.4} {:.4} {:.4}, verge left {:.5} {:.5} {:.5}, right {:.5} {:.5} {:.5} \
             | total {:.3} {:.3} {:.3}",
            a.elevation_deg / b.elevation_deg,
            a.verge_left_deg / b.verge_left_deg,
            a.verge_right_deg / b.verge_right_deg,
            p[0],
            model[0],
            scene[0],
            p[1],
            model[1],
            scene[1],
            p[2],
            model[2],
            scene[2],
            total[0],
            total[1],
            total[2]
        );
    }
}

#[test]
fn capture_plan_has_both_directions_and_a_verge_view() {
    let e0 = Encoders::default();
    let plan = capture_plan(&e0, &VergeTiltOptions::default());
    let names: Vec<&str> = plan.iter().map(|p| p.0.as_str()).collect();
    assert_eq!(names, ["initial", "elevation+", "elevation-", "pan+", "pan-", "verge"]);
    assert_eq!(plan[2].1.elevation, -3.0);
    let short =
        capture_plan(&e0, &VergeTiltOptions { both_directions: false, ..VergeTiltOptions::default() });
    assert_eq!(short.len(), 4);
}

/// Auto rotation on the default scene grows past the fixed 3 deg (the simulated room
/// fills the view), and a demanding overlap keeps the first candidate.
#[test]
fn auto_rotation_grows_when_the_scene_allows() {
    let scenario = Scenario { seed: 3, noise_px: 0.5, outlier_fraction: 0.0, ..Scenario::default() };
    let mut head = SimulatedHead::new(scenario.clone()).unwrap();
    let e0 = head.read_encoders().unwrap();
    let loose = AutoRotation::default();
    let c = choose_rotation(&mut head, &e0, true, &loose).unwrap();
    assert!(c.rotation_deg > 3.0 && c.diagonal_rotation_deg > 3.0, "chose {c:?}");
    assert_eq!(head.read_encoders().unwrap(), e0, "returns to the initial readings");
    let strict = AutoRotation { min_overlap_fraction: 1.0, ..AutoRotation::default() };
    let c = choose_rotation(&mut head, &e0, true, &strict).unwrap();
    assert_eq!(c, RotationChoice { rotation_deg: 3.0, diagonal_rotation_deg: 0.0, verge_rotation_deg: None });
    let bad = AutoRotation { candidates_deg: vec![6.0, 3.0], ..AutoRotation::default() };
    assert!(bad.validate().is_err());
}

/// A field of view as the overlap test: a view keeps the overlap while each joint
/// turns at most `joint_max` and pan and elevation together at most `sum_max` (degrees).
fn field(joint_max: f64, sum_max: f64) -> impl Fn(f64, f64, f64) -> bool {
    move |p: f64, e: f64, v: f64| {
        p.abs() <= joint_max && e.abs() <= joint_max && v.abs() <= joint_max && p.abs() + e.abs() <= sum_max
    }
}

/// Run the pure choice on `keeps`, recording the probes.
fn choose(
    auto: &AutoRotation,
    both: bool,
    keeps: impl Fn(f64, f64, f64) -> bool,
) -> (RotationChoice, Vec<(f64, f64, f64)>) {
    let mut probes = Vec::new();
    let c = choose_rotations(auto, both, |p, e, v| {
        probes.push((p, e, v));
        Ok::<bool, ()>(keeps(p, e, v))
    })
    .unwrap();
    (c, probes)
}

#[test]
fn choice_takes_the_largest_rotations_the_field_allows() {
    let auto = AutoRotation::default();
    let rc = |r, d, v| RotationChoice { rotation_deg: r, diagonal_rotation_deg: d, verge_rotation_deg: v };
    // Everything in view: 10 deg each way, 10 deg diagonals and vergence; 9 probes
    // (largest first), none twice.
    let (c, probes) = choose(&auto, true, field(90.0, 180.0));
    assert_eq!(c, rc(10.0, 10.0, Some(10.0)));
    assert_eq!(probes.len(), 9);
    let mut unique = probes.clone();
    unique.sort_by(|a, b| a.partial_cmp(b).unwrap());
    unique.dedup();
    assert_eq!(unique.len(), probes.len(), "no view probed twice");
    // Diagonals lose the corners first: 10 deg single-joint views, 6 deg diagonals.
    assert_eq!(choose(&auto, true, field(12.0, 14.0)).0, rc(10.0, 6.0, Some(10.0)));
    // A narrow field: 3 deg (the fixed protocol) and 3 deg diagonals.
    assert_eq!(choose(&auto, true, field(4.0, 6.0)).0, rc(3.0, 3.0, Some(3.0)));
    // Nothing in view: the first candidate, no diagonals, the vergence move unchanged.
    assert_eq!(choose(&auto, true, field(1.0, 1.0)).0, rc(3.0, 0.0, None));
    // One direction only fails: the elevation-down view at 10 deg.
    let (c, _) = choose(&auto, true, |p: f64, e: f64, v: f64| e > -8.0 && field(90.0, 180.0)(p, e, v));
    assert_eq!(c, rc(6.0, 6.0, Some(6.0)));
    // The vergence move alone is limited.
    let (c, _) = choose(&auto, true, |p: f64, e: f64, v: f64| v < 7.0 && field(90.0, 180.0)(p, e, v));
    assert_eq!(c, rc(10.0, 10.0, Some(6.0)));
    // Diagonals and vergence off: neither probed.
    let off = AutoRotation { diagonals: false, choose_verge: false, ..AutoRotation::default() };
    let (c, probes) = choose(&off, true, field(90.0, 180.0));
    assert_eq!(c, rc(10.0, 0.0, None));
    assert!(probes.iter().all(|(p, e, v)| (*p == 0.0 || *e == 0.0) && *v == 0.0));
    // One direction: only positive offsets are probed.
    let (c, probes) = choose(&auto, false, field(90.0, 180.0));
    assert_eq!(c, rc(10.0, 10.0, Some(10.0)));
    assert!(probes.iter().all(|(p, e, v)| *p >= 0.0 && *e >= 0.0 && *v >= 0.0));
    // A failing probe (the head) stops the choice with its error.
    let mut n = 0;
    let err = choose_rotations(&auto, true, |_, _, _| {
        n += 1;
        if n == 3 { Err("head") } else { Ok(true) }
    });
    assert_eq!(err, Err("head"));
}

proptest::proptest! {
    /// For any field of view: the chosen single-joint views all keep the overlap (or
    /// it is the first candidate) and the next candidate's do not; the chosen
    /// diagonals keep it and every larger candidate up to the rotation does not.
    #[test]
    fn choice_is_the_largest_allowed(joint_max in 0.0f64..20.0, sum_max in 0.0f64..30.0, both: bool) {
        let auto = AutoRotation::default();
        let keeps = field(joint_max, sum_max);
        let (c, _) = choose(&auto, both, &keeps);
        let cross_ok = |r: f64| single_joint_offsets(r, both).iter().all(|&(_, p, e)| keeps(p, e, 0.0));
        let diag_ok = |d: f64| diagonal_offsets(d, both).iter().all(|&(_, p, e)| keeps(p, e, 0.0));
        let cands = &auto.candidates_deg;
        let i = cands.iter().position(|&x| x == c.rotation_deg).unwrap();
        proptest::prop_assert!(i == 0 || cross_ok(c.rotation_deg));
        for &larger in &cands[i + 1..] {
            proptest::prop_assert!(!cross_ok(larger));
        }
        proptest::prop_assert!(c.diagonal_rotation_deg == 0.0 || diag_ok(c.diagonal_rotation_deg));
        proptest::prop_assert!(c.diagonal_rotation_deg <= c.rotation_deg);
        for &d in cands.iter().filter(|&&d| d > c.diagonal_rotation_deg && d <= c.rotation_deg) {
            proptest::prop_assert!(!diag_ok(d));
        }
        let v = c.verge_rotation_deg.unwrap_or(0.0);
        proptest::prop_assert!(v == 0.0 || (keeps(0.0, 0.0, v) && v <= c.rotation_deg));
        for &w in cands.iter().filter(|&&w| w > v && w <= c.rotation_deg) {
            proptest::prop_assert!(!keeps(0.0, 0.0, w));
        }
    }
}

#[test]
fn capture_plan_adds_the_diagonals_before_the_verge_view() {
    let e0 = Encoders::default();
    let o =
        VergeTiltOptions { rotation_deg: 10.0, diagonal_rotation_deg: 6.0, ..VergeTiltOptions::default() };
    let plan = capture_plan(&e0, &o);
    let names: Vec<&str> = plan.iter().map(|p| p.0.as_str()).collect();
    assert_eq!(
        names,
        [
            "initial",
            "elevation+",
            "elevation-",
            "pan+",
            "pan-",
            "pan+elevation+",
            "pan+elevation-",
            "pan-elevation+",
            "pan-elevation-",
            "verge"
        ]
    );
    assert_eq!((plan[6].1.pan, plan[6].1.elevation), (6.0, -6.0));
    assert_eq!(plan[3].1.elevation, 0.0);
    let bad = VergeTiltOptions { diagonal_rotation_deg: 0.05, ..VergeTiltOptions::default() };
    assert!(bad.validate().is_err());
}

#[test]
fn invalid_options_are_errors() {
    let bad = VergeTiltOptions { rotation_deg: 0.0, ..VergeTiltOptions::default() };
    assert!(bad.validate().is_err());
    let bad = VergeTiltOptions { check_tolerance_deg: f64::NAN, ..VergeTiltOptions::default() };
    assert!(bad.validate().is_err());
}

/// Three views (initial, +3 deg elevation, +3 deg pan) and no vergence view: the
/// vergence axes are nominal ([`crate::alignment`] module docs: perpendicular to the
/// elevation axis, a positive vergence turning the camera right, the simulator's
/// convention). With the cameras mounted square on vergence axes perpendicular to the
/// elevation axis the nominal axes are the true ones, so at 0.01 px of noise (exactly
/// noise-free, the re-selected adjustment of these three views is singular) the aligned
/// readings are within 0.05 deg: their sigmas at this noise are about 0.004 deg (0.4 deg
/// at 1 px with these one-sided views; 0.011 deg measured at seed 2), a margin of over
/// ten; with the opposite sign the vergence readings were
/// off by twice the vergence needed (up to 20 deg).
#[test]
fn nominal_vergence_axes_follow_the_encoder_sign() {
    for seed in [1, 2, 3] {
        let scenario = Scenario {
            seed,
            noise_px: 0.01,
            outlier_fraction: 0.0,
            mount_rotation_max_deg: 0.0,
            verge_tilt_max_deg: 0.0,
            ..Scenario::default()
        };
        let mut head = SimulatedHead::new(scenario).unwrap();
        let e0 = head.encoders();
        let plan = [
            ("initial", e0),
            ("elevation", e0.moved(Joint::Elevation, 3.0)),
            ("pan", e0.moved(Joint::Pan, 3.0)),
        ];
        let mut views = Vec::new();
        for (name, e) in plan {
            head.move_to(&e).unwrap();
            views.push(crate::observations::View { name: name.into(), capture: head.capture().unwrap() });
        }
        // Through the offline alignment `align` runs: no vergence view, nominal axes.
        let session = super::align_session(&views, &EstimationOptions::default()).unwrap();
        assert!(session.verge_view.is_none() && session.verge_axes.left.is_none());
        let sol = session.solution;
        assert!(!sol.verge_axes_measured);
        // Sigmas hold the reading noise (0.01 deg) and stay far below the tolerance.
        let g = session.sigmas;
        assert!(g.elevation_deg >= 0.01 && g.verge_left_deg < 0.05, "{g:?}");
        let truth = head.aligned_encoders();
        let (a, t) = (sol.aligned_encoders, truth);
        for (name, err) in [
            ("verge_left", a.verge_left - t.verge_left),
            ("verge_right", a.verge_right - t.verge_right),
            ("elevation", a.elevation - t.elevation),
        ] {
            assert!(err.abs() < 0.05, "seed {seed}: {name} off by {err} deg");
        }
    }
}

/// A three-view session (initial, +3 deg elevation, +3 deg pan: no vergence view) of the
/// default simulated head at `seed` and `noise_px`, aligned offline as `align` does.
fn three_view_session(seed: u64, noise_px: f64) -> (SimulatedHead, SessionAlignment) {
    let scenario = Scenario { seed, noise_px, ..Scenario::default() };
    let mut head = SimulatedHead::new(scenario).unwrap();
    let e0 = head.encoders();
    let mut views = Vec::new();
    for (name, e) in
        [("initial", e0), ("elevation", e0.moved(Joint::Elevation, 3.0)), ("pan", e0.moved(Joint::Pan, 3.0))]
    {
        head.move_to(&e).unwrap();
        views.push(crate::observations::View { name: name.into(), capture: head.capture().unwrap() });
    }
    let options = EstimationOptions::scaled_for_noise(noise_px, seed);
    let session = super::align_session(&views, &options).unwrap();
    (head, session)
}

/// The true fixation points of `head` at the reference readings `reference`: where each
/// true camera sees the direction perpendicular to the pan and elevation axes (forward),
/// pixels, `[left, right]`.
fn true_fixation_px(head: &SimulatedHead, reference: &Encoders) -> [[f64; 2]; 2] {
    let truth = head.truth();
    let a_p = truth.axis_in_world(Joint::Pan, reference).direction.into_inner();
    let a_e = truth.axis_in_world(Joint::Elevation, reference).direction.into_inner();
    let d = a_e.cross(&a_p).normalize();
    let (wl, wr) = truth.world_from_cameras(reference);
    let see = |w: &nalgebra::Isometry3<f64>, k: &headalign_geometry::camera::Intrinsics| {
        let mut c = w.rotation.inverse() * d;
        if c.z < 0.0 {
            c = -c;
        }
        let p = k.project_unchecked(&nalgebra::Point3::from(c));
        [p.x, p.y]
    };
    [see(&wl, &truth.left), see(&wr, &truth.right)]
}

/// The z-scores of a three-view session's fixation points against the truth, per camera
/// and image axis (`[left x, left y, right x, right y]`): `(estimate - truth) / sigma`
/// with the fixation points' own sigmas ([`fixation_sigmas`]) and, as the independent
/// sessions' README scores them, with the aligned readings' sigmas (the pixel error over
/// the true focal length, in degrees, against the vergence sigma for x and the elevation
/// sigma for y), and third the angle of the fixation point from the principal point (what
/// a reading turns) against the aligned readings' sigmas.
fn three_view_fixation_z(head: &SimulatedHead, s: &SessionAlignment) -> [[f64; 4]; 3] {
    let t = true_fixation_px(head, &s.reference);
    let e = [s.solution.fixation_px_left, s.solution.fixation_px_right];
    let f = [s.fixation_sigmas.left_px, s.fixation_sigmas.right_px];
    let k = [head.truth().left, head.truth().right];
    let g = s.sigmas;
    let reading_sigma = [[g.verge_left_deg, g.elevation_deg], [g.verge_right_deg, g.elevation_deg]];
    let est = [s.calibration.bundle.state.left, s.calibration.bundle.state.right];
    let mut own = [0.0; 4];
    let mut by_readings = [0.0; 4];
    let mut from_principal = [0.0; 4];
    for c in 0..2 {
        let focal = [k[c].fx, k[c].fy];
        let (pp_true, pp_est) = ([k[c].cx, k[c].cy], [est[c].cx, est[c].cy]);
        let focal_est = [est[c].fx, est[c].fy];
        for a in 0..2 {
            let err = e[c][a] - t[c][a];
            own[2 * c + a] = err / f[c][a];
            by_readings[2 * c + a] = (err / focal[a]).to_degrees() / reading_sigma[c][a];
            let turn =
                ((e[c][a] - pp_est[a]) / focal_est[a]).atan() - ((t[c][a] - pp_true[a]) / focal[a]).atan();
            from_principal[2 * c + a] = turn.to_degrees() / reading_sigma[c][a];
        }
    }
    [own, by_readings, from_principal]
}

/// The vergence reading turns the optical axis (through the principal point) onto the
/// target, so its error is the fixation point's less the principal point's, over the
/// focal length: the left vergence sigma (nominal axes held, no reading noise) equals the
/// sigma of `(x_fix - cx) / fx` propagated from the fixation point's Jacobian, while the
/// fixation point's own sigma is larger (the two are uncertain together along x). 5 %:
/// the reading is an angle about the nominal vergence axis, not exactly the image x
/// offset (the axis is off the camera's y axis by the mounting, the fixation point a few
/// px from the principal point, where `fx`'s own error enters); measured 0.4-1.4 % at seeds
/// 1-3.
#[test]
fn vergence_sigma_is_the_fixation_point_less_the_principal_point() {
    for seed in [1, 2, 3] {
        let (_, s) = three_view_session(seed, 1.0);
        let cov = &s.calibration.bundle.covariance;
        let jac = fixation_jacobian(&s.calibration);
        let cx = cov.index("left.cx").unwrap();
        let mut relative = jac.row(0).clone_owned();
        relative[cx] -= 1.0;
        let var = |r: &nalgebra::RowDVector<f64>| (r * &cov.matrix * r.transpose())[(0, 0)];
        let fx = s.calibration.bundle.state.left.fx;
        let relative_deg = (var(&relative).sqrt() / fx).to_degrees();
        let held = alignment_sigmas(&s.calibration, &s.verge_axes, &s.reference).unwrap();
        let ratio = relative_deg / held.verge_left_deg;
        assert!(
            (ratio - 1.0).abs() < 0.05,
            "seed {seed}: (x_fix - cx) / fx sigma {relative_deg} deg, vergence sigma {} deg",
            held.verge_left_deg
        );
        let own_deg = (s.fixation_sigmas.left_px[0] / fx).to_degrees();
        println!(
            "seed {seed}: ratio {ratio:.4}, fixation x sigma {own_deg:.3} deg, vergence {:.3} deg",
            held.verge_left_deg
        );
        assert!(own_deg > held.verge_left_deg, "seed {seed}: fixation x sigma {own_deg} deg");
    }
}

/// Root mean square and the fraction within 1.96 of a set of z-scores.
fn rms_and_coverage(z: &[f64]) -> (f64, f64) {
    let n = z.len() as f64;
    let rms = (z.iter().map(|v| v * v).sum::<f64>() / n).sqrt();
    (rms, z.iter().filter(|v| v.abs() < 1.96).count() as f64 / n)
}

/// Experiment (ignored; run by name with `--nocapture`): the fixation points of
/// simulated three-view sessions at 1 px scored against the truth, with their own sigmas
/// and with the aligned readings' sigmas as the independent sessions' README does
/// (`docs/results.md`, "Three-view sessions of an independent head model").
#[test]
#[ignore = "experiment: about 0.3 s per seed; run by name"]
fn three_view_fixation_coverage() {
    let seeds: u64 = std::env::var("SEEDS").ok().and_then(|s| s.parse().ok()).unwrap_or(60);
    let (mut own, mut by_readings, mut from_principal) =
        (vec![Vec::new(); 2], vec![Vec::new(); 2], vec![Vec::new(); 2]);
    for seed in 1..=seeds {
        let (head, s) = three_view_session(seed, 1.0);
        let [o, r, p] = three_view_fixation_z(&head, &s);
        for a in 0..2 {
            own[a].extend([o[a], o[2 + a]]);
            by_readings[a].extend([r[a], r[2 + a]]);
            from_principal[a].extend([p[a], p[2 + a]]);
        }
    }
    for (a, name) in ["horizontal", "vertical"].iter().enumerate() {
        let (ro, co) = rms_and_coverage(&own[a]);
        let (rr, cr) = rms_and_coverage(&by_readings[a]);
        let (rp, cp) = rms_and_coverage(&from_principal[a]);
        let mean = |z: &[f64]| z.iter().sum::<f64>() / z.len() as f64;
        println!(
            "{name}: fixation sigmas z RMS {ro:.2}, mean {:+.2}, 95 % coverage {:.0} %; aligned readings' sigmas z RMS {rr:.2}, coverage {:.0} %; from the principal point z RMS {rp:.2}, coverage {:.0} %",
            mean(&own[a]),
            100.0 * co,
            100.0 * cr,
            100.0 * cp
        );
    }
}

/// The procedure switches: on the wall it runs the planar route and ends aligned within
/// 0.01 deg (noise-free); on the default room it runs the general route.
#[test]
fn the_procedure_switches_on_a_wall_only() {
    let scenario = Scenario { noise_px: 0.0, ..Scenario::wall().with_seed(3) };
    let mut head = SimulatedHead::new(scenario).unwrap();
    let out = VergeTiltRun::default().run_detecting(&mut head, &VergeTiltOptions::default()).unwrap();
    let RouteOutcome::Planar(p) = out else { panic!("the wall went the general way") };
    assert_eq!(p.calibration.scene.kind, crate::facing_plane::SceneKind::Planar);
    let err = head.alignment_errors(&head.encoders());
    let truth = head.alignment_errors(&head.aligned_encoders());
    for (e, t) in [(err.verge_err_l_deg, truth.verge_err_l_deg), (err.elev_err_l_deg, truth.elev_err_l_deg)] {
        assert!((e - t).abs() < 0.01, "{e} vs {t}");
    }
    let mut head = SimulatedHead::new(Scenario::default().with_seed(3)).unwrap();
    let out = VergeTiltRun::default().run_detecting(&mut head, &VergeTiltOptions::default()).unwrap();
    assert!(matches!(out, RouteOutcome::General(..)));
}

/// Noise-free `wall` and `far`: the check after the move, and a check 0.3 deg of
/// vergence and 0.2 deg of elevation away from it, measure the alignment errors the
/// simulator's truth has within 0.01 deg (the estimated axes are that close to the
/// true ones, `facing_plane` module docs), and no unmodelled rotation beyond it.
#[test]
fn the_check_measures_the_simulators_errors() {
    for (preset, seed) in [("wall", 3), ("far", 1)] {
        let scenario = Scenario { noise_px: 0.0, ..Scenario::preset(preset).unwrap().with_seed(seed) };
        let mut head = SimulatedHead::new(scenario).unwrap();
        let mut run = VergeTiltRun::default();
        let out = run.run_detecting(&mut head, &VergeTiltOptions::default()).unwrap();
        let RouteOutcome::Planar(p) = out else { panic!("{preset}: the general route ran") };
        let at_aligned = p.checks.first().cloned().unwrap_or_else(|| panic!("{:?}", p.check_failure));
        let truth_aligned = head.alignment_errors(&head.encoders());
        let moved = head.encoders().moved(Joint::VergeLeft, 0.3).moved(Joint::Elevation, 0.2);
        head.move_to(&moved).unwrap();
        let capture = head.capture().unwrap();
        let off =
            crate::facing_plane::check_alignment(&p.calibration, &run.views[0].capture, &capture).unwrap();
        let truth_off = head.alignment_errors(&head.encoders());
        for (c, truth) in [(&at_aligned, truth_aligned), (&off, truth_off)] {
            let m = c.measured;
            for (e, t) in [
                (m.verge_err_l_deg, truth.verge_err_l_deg),
                (m.verge_err_r_deg, truth.verge_err_r_deg),
                (m.elev_err_l_deg, truth.elev_err_l_deg),
                (m.elev_err_r_deg, truth.elev_err_r_deg),
            ] {
                assert!((e - t).abs() < 0.01, "{preset}: measured {m:?}, truth {truth:?}");
            }
            assert!(c.left.unmodelled_rotation_deg < 0.01 && c.right.unmodelled_rotation_deg < 0.01);
            assert!(
                c.left.tracks >= crate::facing_plane::MIN_CHECK_TRACKS
                    && c.unchecked.len() == crate::facing_plane::UNCHECKED.len()
            );
        }
        assert!(truth_off.verge_err_l_deg.abs() > 0.2, "the moved check is off: {truth_off:?}");
    }
}
