//! The experiments' definitions: for each name of [`super::NAMES`] (but `all`) its
//! conditions (the swept parameter's values, each a scenario and a rotation mode, grouped),
//! the series it plots and tabulates, the initial head positions, the quantities reported
//! with a sigma, and its default trial count. [`super::experiment`] picks one by name; the
//! series and condition builders they share are in the parent module.
//!
//! Units: noise in pixels, rotations and angle errors in degrees, intrinsics' errors in
//! percent (of the focal length for the principal point), drives in metres.

use headalign_platform::Encoders;
use headalign_sim::Scenario;

use super::{
    COVERAGE_FIXED_PX, COVERAGE_ROBOT_PX, COVERAGE_THREE_VIEW_PX, COVERAGE_TRIALS, Condition, Experiment,
    NOISE_GRID, PAN_INDEX, ROBOT_QUANTITIES, RotationMode, SIGMA_QUANTITIES, Series, alignment_series, base,
    elevation_left, fixed, focal_pooled, q_crb_pct, q_rel_pct, recon_median, recon_rms, verge_left,
    worst_focal,
};

/// `fig5-verge-tilt` (paper Figure 5 left): the aligned readings' errors against image
/// noise, from three initial head positions.
pub(super) fn fig5_verge_tilt(scene: &Scenario) -> Experiment {
    let base = |noise: f64| base(scene, noise);
    Experiment {
        name: "fig5-verge-tilt",
        title: "Verge/tilt alignment error vs noise (3 deg, 200 points)",
        x_label: "image noise (px)",
        y_label: "RMS error (deg)",
        default_trials: 1250,
        robot: false,
        quantities: &SIGMA_QUANTITIES,
        note: "",
        positions: vec![
            Encoders::default(),
            Encoders { pan: 4.0, elevation: 4.0, verge_left: 2.0, verge_right: -2.0 },
            Encoders { pan: -4.0, elevation: -4.0, verge_left: -2.0, verge_right: 2.0 },
        ],
        conditions: NOISE_GRID.iter().map(|&n| fixed(n, base(n))).collect(),
        series: alignment_series(),
    }
}

/// `calibration`: the intrinsics' and the reconstruction's errors against image noise.
pub(super) fn calibration(scene: &Scenario) -> Experiment {
    let base = |noise: f64| base(scene, noise);
    Experiment {
        name: "calibration",
        title: "Calibration error vs noise (3 deg, 200 points)",
        x_label: "image noise (px)",
        y_label: "RMS error (%)",
        default_trials: 1250,
        robot: false,
        quantities: &SIGMA_QUANTITIES,
        note: "",
        positions: vec![Encoders::default()],
        conditions: [0.5, 1.0, 1.5, 2.0, 3.0].iter().map(|&n| fixed(n, base(n))).collect(),
        series: vec![
            Series { label: "left fx (%)", value: |r| q_rel_pct(r, 0), crb: Some(|r| q_crb_pct(r, 0)) },
            Series { label: "right fx (%)", value: |r| q_rel_pct(r, 4), crb: Some(|r| q_crb_pct(r, 4)) },
            focal_pooled(),
            worst_focal(),
            Series { label: "aspect ratio, worst (%)", value: |r| r.aspect_err_pct, crb: None },
            Series { label: "principal point, worst (% of f)", value: |r| r.pp_err_pct, crb: None },
            recon_rms(),
            recon_median(),
        ],
    }
}

/// `points`: errors against the number of scene points, and the 50-point bar with the
/// rotations the procedure chooses (group `auto`).
pub(super) fn points(scene: &Scenario) -> Experiment {
    let base = |noise: f64| base(scene, noise);
    Experiment {
        name: "points",
        title: "Error vs number of points (1.5 px, 3 deg)",
        x_label: "points",
        y_label: "RMS error (deg, %)",
        default_trials: 150,
        robot: false,
        quantities: &SIGMA_QUANTITIES,
        note: "Group `auto`: 50 points with the rotations the procedure chooses itself (`--auto-rotation`, default `AutoRotation`). Its overlap rule keeps a rotation while every probed view shares at least half of the reference view's stereo tracks and at least 30 of them (`AutoRotation::min_tracks`), so a 50-point scene mostly gets 10 deg single-joint views, 6-10 deg diagonal views and a 10 deg vergence move (the `rotation` column is the mean single-joint rotation). The reconstruction error's tail is the likelihood's own, not the estimator's: started from the truth on the same inliers, the bundle adjustment ends at the estimate's cost; the worst trials have their points on one wall 3-6 m away, where the baseline direction is known to 15-20 deg and far points are reconstructed near infinity.",
        positions: vec![Encoders::default()],
        conditions: {
            let mut c: Vec<Condition> = [50usize, 100, 200, 400]
                .iter()
                .map(|&p| fixed(p as f64, Scenario { points: p, ..base(1.5) }))
                .collect();
            // The 50-point bar with the rotations the procedure chooses itself.
            c.push(Condition {
                group: "auto",
                x: 50.0,
                scenario: Scenario { points: 50, ..base(1.5) },
                rotation: RotationMode::Auto,
                robot: false,
            });
            c
        },
        series: vec![
            elevation_left(),
            verge_left(),
            focal_pooled(),
            worst_focal(),
            recon_rms(),
            recon_median(),
        ],
    }
}

/// `rotation`: errors against the size of the rotations, and the rotations the procedure
/// chooses at 1 and 3 px (group `auto`).
pub(super) fn rotation(scene: &Scenario) -> Experiment {
    let base = |noise: f64| base(scene, noise);
    let mut conditions: Vec<Condition> = [1.0, 3.0, 6.0, 10.0, 15.0]
        .iter()
        .map(|&d| fixed(d, Scenario { rotation_deg: d, ..base(1.0) }))
        .collect();
    for n in [1.0, 3.0] {
        conditions.push(Condition {
            group: "auto",
            x: n,
            scenario: base(n),
            rotation: RotationMode::Auto,
            robot: false,
        });
    }
    Experiment {
        name: "rotation",
        title: "Error vs rotation size (1 px, 200 points)",
        x_label: "rotation (deg)",
        y_label: "RMS error (deg, %)",
        default_trials: 140,
        robot: false,
        quantities: &SIGMA_QUANTITIES,
        note: "",
        positions: vec![Encoders::default()],
        conditions,
        series: vec![
            verge_left(),
            elevation_left(),
            Series { label: "left fx (%)", value: |r| q_rel_pct(r, 0), crb: Some(|r| q_crb_pct(r, 0)) },
            focal_pooled(),
            worst_focal(),
        ],
    }
}

/// `outliers`: errors against the fraction of outlying observations.
pub(super) fn outliers(scene: &Scenario) -> Experiment {
    let base = |noise: f64| base(scene, noise);
    Experiment {
        name: "outliers",
        title: "Error vs outlier fraction (1 px, 3 deg, 200 points)",
        x_label: "outlier fraction (per observation)",
        y_label: "RMS error (deg, %)",
        default_trials: 70,
        robot: false,
        quantities: &SIGMA_QUANTITIES,
        note: "",
        positions: vec![Encoders::default()],
        conditions: [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
            .iter()
            .map(|&o| fixed(o, Scenario { outlier_fraction: o, ..base(1.0) }))
            .collect(),
        series: vec![elevation_left(), verge_left(), worst_focal()],
    }
}

/// `coverage`: the reported sigmas against the actual errors, verge/tilt (`fixed`) and
/// with the robot stages (`robot`).
pub(super) fn coverage(scene: &Scenario) -> Experiment {
    let base = |noise: f64| base(scene, noise);
    Experiment {
        name: "coverage",
        title: "Reported sigma vs actual error (3 deg, 200 points)",
        x_label: "image noise (px)",
        y_label: "RMS error (deg)",
        default_trials: COVERAGE_TRIALS
            * (COVERAGE_FIXED_PX.len() + COVERAGE_ROBOT_PX.len() + COVERAGE_THREE_VIEW_PX.len()),
        robot: false,
        quantities: &ROBOT_QUANTITIES,
        note: "Groups: `fixed` runs the verge/tilt procedure in the plain room at each noise level; `robot` runs the robot stages as `fig5-pan-tilt` does (verge/tilt, pan, steering, pan; 6 near panels, pan zeros up to 20 deg, 0.10 m drive) at 1 and 3 px, which adds the final pan reading (`pan.aligned`: its sigma is the last drive's: the verge/tilt calibration's uncertainty, the drive motion's (all 6 dof, through the derotated flow and the half turn) and the flow's, propagated) and the steering zero (`steer.zero`), and repeats the verge/tilt quantities in the robot's scene; `three-view` aligns recorded three-view sessions offline as `headalign align` does (the initial view, 3 deg of elevation, 3 deg of pan, one direction each, no vergence view: nominal vergence axes, sigmas that hold them fixed) at 1 px, then moves the head to the aligned readings. These are every sigma headalign reports in point mode (the intrinsics, the aligned readings, the pan and elevation axes' directions, the pan reading and the steering zero).",
        positions: vec![Encoders::default()],
        conditions: {
            let mut c: Vec<Condition> = COVERAGE_FIXED_PX.iter().map(|&n| fixed(n, base(n))).collect();
            c.extend(COVERAGE_ROBOT_PX.iter().map(|&n| Condition {
                group: "robot",
                x: n,
                scenario: base(n),
                rotation: RotationMode::Fixed,
                robot: true,
            }));
            c.extend(COVERAGE_THREE_VIEW_PX.iter().map(|&n| Condition {
                group: "three-view",
                x: n,
                scenario: base(n),
                rotation: RotationMode::ThreeView,
                robot: false,
            }));
            c
        },
        series: alignment_series(),
    }
}

/// `fig5-pan-tilt` (paper Figure 5 right): the pan alignment by the forward drive after
/// the robot stages, against noise, largest initial pan and drive distance.
pub(super) fn fig5_pan_tilt(scene: &Scenario) -> Experiment {
    let base = |noise: f64| base(scene, noise);
    let robot = |group: &'static str, x: f64, noise: f64, pan_max: f64, drive: f64| Condition {
        group,
        x,
        scenario: Scenario { pan_zero_max_deg: pan_max, drive_m: drive, ..base(noise) },
        rotation: RotationMode::Fixed,
        robot: true,
    };
    let mut conditions: Vec<Condition> =
        NOISE_GRID.iter().map(|&n| robot("noise", n, n, 20.0, 0.10)).collect();
    conditions.extend([10.0, 20.0, 40.0, 60.0].iter().map(|&p| robot("pan zero", p, 1.0, p, 0.10)));
    conditions.extend([0.05, 0.10, 0.20, 0.40].iter().map(|&d| robot("drive", d, 1.0, 20.0, d)));
    Experiment {
        name: "fig5-pan-tilt",
        title: "Pan alignment by the forward drive (verge/tilt, pan, steering, pan)",
        x_label: "noise (px) / max initial pan (deg) / drive (m)",
        y_label: "RMS error (deg)",
        default_trials: 260,
        robot: true,
        quantities: &ROBOT_QUANTITIES,
        note: "Groups: `noise` sweeps the image noise (pan zeros up to 20 deg, 0.10 m drive); `pan zero` sweeps the largest initial pan error (1 px, 0.10 m); `drive` sweeps the forward drive in metres (1 px, up to 20 deg). Each trial runs the demo's default stages (verge-tilt, pan, steering, pan) in point mode with 6 near panels about 1 m ahead, the robot's floor tilted 2 deg against the pan axis (the scenario's `pan_tilt_deg`; its direction drawn per seed); errors are measured after the last stage. The plot shows the `noise` group. No Cramer-Rao bound for the pan: the pan stage has no joint likelihood whose covariance could be evaluated at the truth, so the bound columns are '-'. The reported pan sigma is the last drive's correction sigma: the verge/tilt calibration's covariance and the drive motion's propagated through the pan computation, plus the flow's noise (bounded for its unmodelled correlation with the motion's); the trials also report the steering zero with its sigma (`steer.zero`) and the verge/tilt quantities in the robot's scene. The paper's real robot: 1.7 deg RMS pan for initial pans up to 20 deg, 3.5 deg up to 60 deg.",
        positions: vec![Encoders::default()],
        conditions,
        series: vec![
            Series { label: "pan (deg)", value: |r| r.pan_err_deg, crb: None },
            Series {
                label: "reported pan sigma (deg)",
                value: |r| r.quantities.get(PAN_INDEX).map_or(f64::NAN, |q| q.sigma),
                crb: None,
            },
            Series { label: "elevation left (deg)", value: |r| r.elev_err_l_deg, crb: None },
            Series { label: "elevation right (deg)", value: |r| r.elev_err_r_deg, crb: None },
            Series { label: "elevation right, excess (deg)", value: |r| r.elev_err_r_excess_deg, crb: None },
        ],
    }
}
