//! Tests of the planar route on the simulated head (point mode).

use headalign_platform::{Encoders, Joint, StereoHead};
use headalign_sim::{Scenario, SimulatedHead};

use super::*;
use crate::alignment::solve_alignment_axes;
use crate::estimate::EstimationOptions;

/// The procedure's default plan: reference, elevation and pan both ways, both vergences.
pub(crate) fn capture_plan(head: &mut SimulatedHead, r: f64) -> Vec<View> {
    let e0 = head.encoders();
    let plan = [
        ("initial", e0),
        ("elevation+", e0.moved(Joint::Elevation, r)),
        ("elevation-", e0.moved(Joint::Elevation, -r)),
        ("pan+", e0.moved(Joint::Pan, r)),
        ("pan-", e0.moved(Joint::Pan, -r)),
        ("verge", e0.moved(Joint::VergeLeft, r).moved(Joint::VergeRight, r)),
    ];
    let mut views = Vec::new();
    for (name, e) in plan {
        head.move_to(&e).unwrap();
        views.push(View { name: name.into(), capture: head.capture().unwrap() });
    }
    head.move_to(&e0).unwrap();
    views
}

/// Largest aligned-reading error against the simulator's truth, degrees.
fn worst_error(views: &[View], head: &SimulatedHead) -> (f64, PlanarCalibration) {
    let check = detect_scene(views, &EstimationOptions::default().fundamental);
    assert_ne!(check.kind, SceneKind::General, "{check:?}");
    let calib = estimate_planar(views, check, &PlanarOptions::default()).unwrap();
    let e0: Encoders = views[0].capture.encoders;
    let sol = solve_alignment_axes(&calib.left.axes(), &calib.right.axes(), &e0).unwrap();
    let t = head.aligned_encoders();
    let a = sol.aligned_encoders;
    let worst = [a.elevation - t.elevation, a.verge_left - t.verge_left, a.verge_right - t.verge_right]
        .iter()
        .fold(0f64, |m, e| m.max(e.abs()));
    (worst, calib)
}

/// Noise-free (10 % outliers), `wall` and `far`: the aligned readings within 0.01 deg of
/// the truth (issue 34's bar), the wall's plane normal determined and the far scene's
/// not; the intrinsics within 0.1 % (the angle prior fixes the scale of `K`).
#[test]
fn noise_free_wall_and_far_align_within_a_hundredth_of_a_degree() {
    for (preset, seed) in [("wall", 1), ("wall", 2), ("far", 1), ("far", 2)] {
        let scenario = Scenario { noise_px: 0.0, ..Scenario::preset(preset).unwrap().with_seed(seed) };
        let mut head = SimulatedHead::new(scenario).unwrap();
        let views = capture_plan(&mut head, 3.0);
        let (worst, calib) = worst_error(&views, &head);
        assert!(worst < 0.01, "{preset} seed {seed}: {worst} deg");
        let fx = head.truth().left.fx;
        assert!((calib.left.intrinsics.fx - fx).abs() < 1e-3 * fx, "{preset} {:?}", calib.left.intrinsics);
        let far = preset == "far";
        assert_eq!(
            calib.scene.kind,
            if far { SceneKind::Far } else { SceneKind::Planar },
            "{:?}",
            calib.scene
        );
        assert_eq!(calib.left.plane_normal.is_none(), far);
    }
}

/// The room of the default scene is no plane: the detection keeps the general route.
#[test]
fn the_default_room_is_general() {
    for seed in [1, 2, 3] {
        let mut head = SimulatedHead::new(Scenario::default().with_seed(seed)).unwrap();
        let views = capture_plan(&mut head, 3.0);
        let check = detect_scene(&views, &EstimationOptions::default().fundamental);
        assert_eq!(check.kind, SceneKind::General, "seed {seed}: {check:?}");
    }
}

/// The procedure switches: on the wall it runs the planar route and ends aligned within
/// 0.01 deg (noise-free); on the default room it runs the general route.
#[test]
fn the_procedure_switches_on_a_wall_only() {
    use crate::procedure::{RouteOutcome, VergeTiltOptions, VergeTiltRun};
    let scenario = Scenario { noise_px: 0.0, ..Scenario::wall().with_seed(3) };
    let mut head = SimulatedHead::new(scenario).unwrap();
    let out = VergeTiltRun::default().run_detecting(&mut head, &VergeTiltOptions::default()).unwrap();
    let RouteOutcome::Planar(p) = out else { panic!("the wall went the general way") };
    assert_eq!(p.calibration.scene.kind, SceneKind::Planar);
    let err = head.alignment_errors(&head.encoders());
    let truth = head.alignment_errors(&head.aligned_encoders());
    for (e, t) in [(err.verge_err_l_deg, truth.verge_err_l_deg), (err.elev_err_l_deg, truth.elev_err_l_deg)] {
        assert!((e - t).abs() < 0.01, "{e} vs {t}");
    }
    let mut head = SimulatedHead::new(Scenario::default().with_seed(3)).unwrap();
    let out = VergeTiltRun::default().run_detecting(&mut head, &VergeTiltOptions::default()).unwrap();
    assert!(matches!(out, RouteOutcome::General(..)));
}

/// At 1 px the wall's large errors are the least squares' own minimum, not a local one:
/// restarted from the fit of the exact pixels (the truth, within 0.07 deg), seeds 9 and 7
/// (verge errors 2.2-2.4 deg, 5-6 times the Cramér-Rao bound, `experiment planar --scene
/// wall --only 1`) end at the same cost (relative 1e-4: the regular fit stops when the
/// cost falls by under 1e-12 relative, a few hundredths of a unit short) and readings
/// within 0.05 deg of the regular fit's.
#[test]
fn the_noisy_wall_fit_is_its_least_squares_minimum() {
    use headalign_geometry::bundle::Side;
    use headalign_platform::{StereoCapture, TrackObservation};

    use crate::procedure::{VergeTiltOptions, capture_plan as plan};
    for seed in [9, 7] {
        let s = Scenario { noise_px: 1.0, encoder_noise_deg: 0.01, ..Scenario::wall().with_seed(seed) };
        let mut head = SimulatedHead::new(s).unwrap();
        let e0 = head.read_encoders().unwrap();
        let (mut views, mut exact) = (Vec::new(), Vec::new());
        for (name, e) in plan(&e0, &VergeTiltOptions::default()) {
            head.move_to(&e).unwrap();
            let c = head.capture().unwrap();
            let x = head.exact_capture(&e);
            // The exact pixels of the tracks whose noisy observation is no outlier.
            let keep = |ex: Vec<TrackObservation>, n: &[TrackObservation]| -> Vec<TrackObservation> {
                ex.into_iter()
                    .filter(|o| n.iter().any(|q| q.track == o.track && (q.pixel - o.pixel).norm() < 5.0))
                    .collect()
            };
            let (left, right) = (keep(x.left, &c.left), keep(x.right, &c.right));
            let capture = StereoCapture { encoders: c.encoders, image_size: x.image_size, left, right };
            exact.push(View { name: name.clone(), capture });
            views.push(View { name, capture: c });
        }
        let check = detect_scene(&views[..views.len() - 1], &EstimationOptions::default().fundamental);
        let mut options = PlanarOptions::default();
        options.homography.threshold =
            options.homography.threshold.max(HOMOGRAPHY_SIGMAS * 2f64.sqrt() * check.sigma_px);
        let fit = |v: &[View], side: Side| {
            let data = start::camera_data(v, side, &options, &mut Vec::new()).unwrap();
            refine::maximum_likelihood(start::initial_problem(&data, side).unwrap(), &options).unwrap()
        };
        let mut cams = Vec::new();
        for side in [Side::Left, Side::Right] {
            let (truth, regular) = (fit(&exact, side), fit(&views, side));
            let (c_regular, c_restart, restart) = refine::restart_from(&regular, &truth, &options);
            assert!(
                (c_restart - c_regular).abs() < 1e-4 * c_regular,
                "seed {seed} {side:?}: {c_regular} {c_restart}"
            );
            cams.push((regular.into_camera(side), restart.unwrap().into_camera(side)));
        }
        let e = views[0].capture.encoders;
        let a = solve_alignment_axes(&cams[0].0.axes(), &cams[1].0.axes(), &e).unwrap().aligned_encoders;
        let b = solve_alignment_axes(&cams[0].1.axes(), &cams[1].1.axes(), &e).unwrap().aligned_encoders;
        for (x, y) in
            [(a.elevation, b.elevation), (a.verge_left, b.verge_left), (a.verge_right, b.verge_right)]
        {
            assert!((x - y).abs() < 0.05, "seed {seed}: {a:?} vs {b:?}");
        }
    }
}
