//! The demo's members against the simulator's truth (`headalign_io::report::schema`'s
//! [`Truth`], [`Errors`], [`Before`] and the `demo --images` [`DemoReport`]), filled from
//! `headalign_sim`: the report formats live in `headalign-io`, which does not see the
//! simulator. Errors are in degrees (alignment, pan, steering) and percent (calibration,
//! reconstruction), as `headalign_sim::metrics` computes them; nothing is estimated here.

use headalign::procedure::RouteOutcome;
use headalign::robot::stages::RobotOutcomes;
use headalign_io::report::schema::{
    Before, Camera, DEMO, DemoReport, Errors, Procedure, ReadingErrors, Truth,
};
use headalign_sim::{AlignmentErrors, CalibrationErrors, Scenario, SimulatedRobot, calibration_errors};

/// The errors after the run: the alignment errors at the final readings, the right
/// camera's unavoidable part (`unavoidable_r`, degrees), the calibration errors, and
/// the pan and steering errors where a stage moved them.
pub fn errors(
    after: &AlignmentErrors,
    unavoidable_r: f64,
    cal: &CalibrationErrors,
    recon_err_pct: Option<f64>,
    pan_err_deg: Option<f64>,
    steer_err_deg: Option<f64>,
) -> Errors {
    Errors {
        verge_err_l_deg: after.verge_err_l_deg,
        verge_err_r_deg: after.verge_err_r_deg,
        elev_err_l_deg: after.elev_err_l_deg,
        elev_err_r_deg: after.elev_err_r_deg,
        elev_err_r_unavoidable_deg: unavoidable_r,
        elev_err_r_excess_deg: after.elev_err_r_deg - unavoidable_r,
        pan_err_deg,
        steer_err_deg,
        f_err_pct: cal.f_err_pct,
        aspect_err_pct: cal.aspect_err_pct,
        pp_err_pct: cal.pp_err_pct,
        recon_err_pct,
    }
}

/// The alignment, pan and steering errors at the start.
pub fn before(e: &AlignmentErrors, pan_err_deg: f64, steer_err_deg: f64) -> Before {
    Before {
        verge_err_l_deg: e.verge_err_l_deg,
        verge_err_r_deg: e.verge_err_r_deg,
        elev_err_l_deg: e.elev_err_l_deg,
        elev_err_r_deg: e.elev_err_r_deg,
        pan_err_deg,
        steer_err_deg,
    }
}

/// The simulated robot's truth: its cameras, rendered lens and aligned readings.
pub fn truth(robot: &SimulatedRobot, scenario: &Scenario) -> Result<Truth, serde_json::Error> {
    let head = robot.head();
    let t = head.truth();
    Ok(Truth {
        left: Camera::new(&t.left, |_| None),
        right: Camera::new(&t.right, |_| None),
        distortion: serde_json::to_value(scenario.render.distortion)?,
        aligned_encoders: head.aligned_encoders(),
        steer_zero_deg: robot.truth().steer_zero_deg,
        wheelbase_m: robot.truth().wheelbase_m,
        pan_tilt_deg: robot.truth().pan_tilt_deg(),
    })
}

/// The JSON of `demo --images` ([`DemoReport`]): the run's `procedure` (on `route`, with
/// the robot stages' outcomes `stages`) against the simulated robot's truth after the
/// run, and its errors `before` any stage.
pub fn demo_images_report(
    robot: &SimulatedRobot,
    scenario: &Scenario,
    route: &RouteOutcome,
    procedure: Procedure,
    stages: Option<&RobotOutcomes>,
    before: Before,
) -> Result<DemoReport, serde_json::Error> {
    let head = robot.head();
    let after = head.alignment_errors(&head.encoders());
    let truth = truth(robot, scenario)?;
    let (k_left, k_right) = match route {
        RouteOutcome::General(o, _) => (o.calibration.bundle.state.left, o.calibration.bundle.state.right),
        RouteOutcome::Planar(p) => (p.calibration.left.intrinsics, p.calibration.right.intrinsics),
    };
    let t = head.truth();
    let cal = calibration_errors(&t.left, &t.right, &k_left, &k_right);
    let unavoidable_r = head.alignment_errors(&truth.aligned_encoders).elev_err_r_deg;
    let pan_after = stages.filter(|o| o.panned()).map(|_| robot.pan_err_deg(&head.encoders()));
    let steer_after =
        stages.and_then(|o| o.steering.as_ref()).map(|_| robot.steer_err_deg(robot.steering_encoder_deg()));
    let aligned = procedure.estimate.aligned_encoders;
    Ok(DemoReport {
        schema: DEMO,
        procedure,
        scenario: serde_json::to_value(scenario)?,
        errors: errors(&after, unavoidable_r, &cal, None, pan_after, steer_after),
        before,
        aligned_reading_errors_deg: ReadingErrors::new(&aligned, &truth.aligned_encoders),
        truth,
    })
}
