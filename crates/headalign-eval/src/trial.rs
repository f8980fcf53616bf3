//! One trial of the verge/tilt procedure on the simulated head, scored against the truth,
//! and the Cramer-Rao bound of the same scenario.
//!
//! A trial runs [`VergeTiltRun`] on a [`SimulatedHead`] built from a [`Scenario`] (seed,
//! noise, points, outliers), optionally from another initial head position, and records:
//! the alignment errors after the procedure moved the head (degrees, signed, from the
//! simulator's truth), the calibration errors (percent), the reconstruction error
//! (percent), and for every quantity headalign reports with a sigma (the eight
//! intrinsics in pixels, the three aligned readings in degrees, the pan and elevation
//! axes' directions as two tangent components each in degrees) the estimate, the truth,
//! the reported 1-sigma and the Cramer-Rao bound.
//!
//! Cramer-Rao bound ("the standard deviation predicted by the bundle adjustment's
//! covariance at the true parameters"): the same scenario is run noise-free (same seed,
//! same head, scene and outlier fraction, so RANSAC rejects the outliers exactly and the
//! inlier set has the same expected size). Its bundle state equals the truth in the
//! estimator's gauge (reference left camera frame, |t_rig| = 1) to the solver's tolerance
//! (about 1e-6, see `procedure::tests::noise_free_alignment_is_exact`). The covariance is
//! then evaluated at that state without iterating (`bundle_adjust` with zero iterations,
//! no robust loss, `noise_sigma_px` = the scenario's noise, so the angle prior is weighted
//! as in the real estimate) and propagated to the aligned readings by
//! [`alignment_sigmas`], exactly as the procedure does for its own sigmas. One
//! noise-free run per seed serves every noise level (the bound scales with the noise but
//! the prior does not, so it is recomputed per level, which is cheap).
//!
//! The noise-free run draws the same random numbers as the noisy trials of its seed: its
//! pixel noise is [`CLEAN_NOISE_PX`] (1e-300 px, which rounds away in every pixel) rather
//! than 0, because the simulator skips the noise draws at 0 and its outliers would then
//! fall on other observations than in the noisy trials. With the tiny noise every noise
//! level of a seed has the same outliers, so the bound is evaluated on the very inlier set
//! of the trial it is compared with (before, on another random inlier set of the same
//! expected size: right on average, but not the bound of that trial's data).
//!
//! Pitfalls: the bound ignores the outlier-rejection's randomness and the vergence-axis
//! measurement (taken as exact, like `alignment_sigmas`); at noise 0 it is 0. The
//! procedure's reported sigmas do include the axes' measurement
//! (`procedure::alignment_sigmas_measured`), but not this bound: the noise-free run never
//! re-measures an axis in a check view (its first solution passes the check), so its axes
//! come from the 3 deg vergence move, whose tilt error times the vergence correction (up to
//! 10 deg) would enter the elevation bound, while a noisy run re-measures after a large
//! correction. Evaluated that way the elevation bound rose 5 % (up to 1.65x for the largest
//! corrections; `fig5-verge-tilt --only 2 --trials 250`), a bound of another estimator.
//!
//! The bound's observations are the true inliers: the noise-free run keeps every point
//! (its [`EstimationOptions::lone_depth_gate`] off, since without noise that test can only
//! drop good points, and did: up to 28 % on a focal length's bound at one seed), and the
//! points with an observation that is not the simulator's exact pixel (an outlier that
//! the noise-free adjustment fitted exactly, as it can the only observation of a point in
//! one camera) are left out with all their observations ([`true_inlier_observations`]; 5
//! points in the 250 noise-free runs of `calibration --only 0.5 --trials 250`).

use std::time::Instant;

use anyhow::{Context, Result, anyhow};
use headalign::observations::View;
use headalign::procedure::{
    AutoRotation, AxisSources, VergeTiltOptions, VergeTiltOutcome, VergeTiltRun, align_session,
    alignment_sigmas,
};
use headalign::verge_tilt::{DepthProfile, EstimationOptions, LoneDepthGate, RigCalibration, axes_of};
use headalign_geometry::bootstrap::BootstrapOptions;
use headalign_geometry::bundle::{AnglePrior, BundleOptions, Covariance, RobustLoss, bundle_adjust};
use headalign_platform::{Encoders, Joint, StereoHead};
use headalign_sim::{Scenario, SimulatedHead, calibration_errors};
use nalgebra::{DVector, Matrix3x2};
use serde::Serialize;

/// Names of the quantities reported with a sigma, in record order: intrinsics (pixels),
/// then aligned readings (degrees), then the pan and elevation axes' directions (degrees:
/// the estimate's offset from the truth in the bundle adjustment's own tangent coordinates
/// of each axis, `axis0.dir0` ... `axis1.dir1`, whose sigmas `headalign align` reports as
/// `direction_sigma_deg` = their root sum of squares; [`axis_direction_offsets`]).
pub const SIGMA_QUANTITIES: [&str; 15] = [
    "left.fx",
    "left.fy",
    "left.cx",
    "left.cy",
    "right.fx",
    "right.fy",
    "right.cx",
    "right.cy",
    "aligned.elevation",
    "aligned.verge_left",
    "aligned.verge_right",
    "pan_axis.dir0",
    "pan_axis.dir1",
    "elevation_axis.dir0",
    "elevation_axis.dir1",
];

/// The bundle adjustment's covariance names of [`SIGMA_QUANTITIES`]' axis directions
/// (radians), same order.
const AXIS_DIRECTION_PARAMS: [&str; 4] = ["axis0.dir0", "axis0.dir1", "axis1.dir0", "axis1.dir1"];

/// The sigmas of [`AXIS_DIRECTION_PARAMS`] in `cov`, degrees (NaN where absent).
fn axis_direction_sigmas_deg(cov: &Covariance) -> impl Iterator<Item = f64> + '_ {
    AXIS_DIRECTION_PARAMS.iter().map(|n| cov.sigma(n).map_or(f64::NAN, f64::to_degrees))
}

/// Pixel noise of the noise-free run ([`CleanRun`], module docs): far below the rounding of
/// any pixel coordinate, but positive so that the simulator draws the same random numbers
/// as at any other noise level (same outliers).
pub const CLEAN_NOISE_PX: f64 = 1e-300;

/// How the trial chooses the calibration rotation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub enum RotationMode {
    /// The scenario's `rotation_deg`.
    Fixed,
    /// The procedure chooses (default [`AutoRotation`]: up to 10 deg each way, diagonal
    /// views and the vergence move, as far as the scene stays in view).
    Auto,
    /// Not the procedure: a recorded three-view session (the initial view, the
    /// scenario's `rotation_deg` of elevation, as much pan; one direction each, no
    /// vergence view) aligned offline as `headalign align` does ([`align_session`]:
    /// nominal vergence axes), after which the head moves to the aligned readings.
    ThreeView,
}

/// What one trial runs.
#[derive(Clone, Debug)]
pub struct TrialSpec {
    /// The simulation (seed, noise, points, outliers, rotation).
    pub scenario: Scenario,
    /// Encoder readings the head starts from (the procedure's reference view).
    pub initial: Encoders,
    /// Rotation choice.
    pub rotation: RotationMode,
    /// The depth-scale profile of the reported covariance
    /// ([`EstimationOptions::depth_profile`]; `experiment --depth-profile`, default the
    /// library's).
    pub depth_profile: Option<DepthProfile>,
    /// Model the image border in the least squares ([`EstimationOptions::image_border`];
    /// `experiment --image-border`, default the library's).
    pub image_border: bool,
    /// The depth test of points seen once by one camera
    /// ([`EstimationOptions::lone_depth_gate`]; `experiment --lone-depth-gate`, default
    /// the library's).
    pub lone_depth_gate: Option<LoneDepthGate>,
    /// The commanded angles' error model ([`BundleOptions::angle_prior`];
    /// `experiment --angle-prior`, default the library's).
    pub angle_prior: AnglePrior,
    /// The bootstrap of the covariance ([`EstimationOptions::bootstrap`];
    /// `experiment --bootstrap`, default the library's: off). The noise-free run of the
    /// bound never bootstraps: its covariance is not used.
    pub bootstrap: Option<BootstrapOptions>,
}

/// One reported quantity of one trial.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct Quantity {
    /// Estimate.
    pub est: f64,
    /// Truth.
    pub truth: f64,
    /// Reported 1-sigma.
    pub sigma: f64,
    /// Cramer-Rao bound (1-sigma at the truth); NaN if not computed.
    pub crb: f64,
}

/// Result of one successful trial.
#[derive(Clone, Debug, Serialize)]
pub struct TrialRecord {
    /// Alignment errors after the procedure, degrees (signed).
    pub verge_err_l_deg: f64,
    /// Right vergence error, degrees.
    pub verge_err_r_deg: f64,
    /// Left elevation error, degrees.
    pub elev_err_l_deg: f64,
    /// Right elevation error, degrees (includes the unavoidable mounting part).
    pub elev_err_r_deg: f64,
    /// Right elevation error beyond the unavoidable part, degrees.
    pub elev_err_r_excess_deg: f64,
    /// Largest focal length error, percent.
    pub f_err_pct: f64,
    /// Largest aspect ratio error, percent.
    pub aspect_err_pct: f64,
    /// Largest principal point error, percent of f.
    pub pp_err_pct: f64,
    /// Reconstruction error, RMS over points, percent (NaN if not computable).
    pub recon_err_pct: f64,
    /// Reconstruction error, median over points, percent (NaN if not computable).
    pub recon_median_pct: f64,
    /// Rotation used, degrees.
    pub rotation_deg: f64,
    /// Pan error after the robot stages, degrees (signed; NaN when they did not run).
    pub pan_err_deg: f64,
    /// The quantities of [`SIGMA_QUANTITIES`], same order.
    pub quantities: Vec<Quantity>,
    /// Wall time of the trial, seconds.
    pub seconds: f64,
}

/// Estimation options of a trial: [`EstimationOptions::scaled_for_noise`] at its noise
/// and seed, with its depth profile and image-border setting.
pub fn estimation_options(spec: &TrialSpec) -> EstimationOptions {
    let o = EstimationOptions::scaled_for_noise(spec.scenario.noise_px, spec.scenario.seed);
    EstimationOptions {
        depth_profile: spec.depth_profile,
        image_border: spec.image_border,
        lone_depth_gate: spec.lone_depth_gate,
        bootstrap: spec.bootstrap,
        bundle: BundleOptions { angle_prior: spec.angle_prior, ..o.bundle.clone() },
        ..o
    }
}

fn procedure_options(spec: &TrialSpec) -> VergeTiltOptions {
    VergeTiltOptions {
        rotation_deg: spec.scenario.rotation_deg,
        verge_rotation_deg: 3.0,
        estimation: estimation_options(spec),
        auto_rotation: match spec.rotation {
            RotationMode::Fixed | RotationMode::ThreeView => None,
            RotationMode::Auto => Some(AutoRotation::default()),
        },
        ..VergeTiltOptions::default()
    }
}

/// A simulated head for `spec` with the verge/tilt procedure run on it, and the run's
/// views.
fn run_procedure(spec: &TrialSpec) -> Result<(SimulatedHead, VergeTiltRun, VergeTiltOutcome)> {
    let mut head = SimulatedHead::new(spec.scenario.clone()).map_err(|e| anyhow!("simulator: {e}"))?;
    let mut run = VergeTiltRun::default();
    let outcome = run_on(&mut head, &mut run, spec)?;
    Ok((head, run, outcome))
}

/// The verge/tilt procedure on `head`, which first moves to `spec.initial`.
pub(super) fn verge_tilt_on(head: &mut SimulatedHead, spec: &TrialSpec) -> Result<VergeTiltOutcome> {
    run_on(head, &mut VergeTiltRun::default(), spec)
}

fn run_on(head: &mut SimulatedHead, run: &mut VergeTiltRun, spec: &TrialSpec) -> Result<VergeTiltOutcome> {
    head.move_to(&spec.initial).map_err(|e| anyhow!("simulator: {e}"))?;
    if spec.rotation == RotationMode::ThreeView {
        return three_view_on(head, run, spec);
    }
    run.run(head, &procedure_options(spec)).context("verge/tilt procedure")
}

/// [`RotationMode::ThreeView`]: capture the three views into `run.views`, align them
/// offline, move to the aligned readings; the outcome has no vergence view, no axis
/// sources and no checks.
fn three_view_on(
    head: &mut SimulatedHead,
    run: &mut VergeTiltRun,
    spec: &TrialSpec,
) -> Result<VergeTiltOutcome> {
    let e0 = spec.initial;
    let r = spec.scenario.rotation_deg;
    let plan =
        [("initial", e0), ("elevation", e0.moved(Joint::Elevation, r)), ("pan", e0.moved(Joint::Pan, r))];
    for (name, encoders) in plan {
        head.move_to(&encoders).map_err(|e| anyhow!("simulator: {e}"))?;
        let capture = head.capture().map_err(|e| anyhow!("simulator: {e}"))?;
        run.views.push(View { name: name.into(), capture });
    }
    let t0 = Instant::now();
    let a = align_session(&run.views, &estimation_options(spec)).context("three-view session")?;
    let estimation_seconds = t0.elapsed().as_secs_f64();
    head.move_to(&a.solution.aligned_encoders).map_err(|e| anyhow!("simulator: {e}"))?;
    Ok(VergeTiltOutcome {
        calibration: a.calibration,
        verge_axes: a.verge_axes,
        axis_sources: AxisSources { left: None, right: None },
        solution: a.solution,
        sigmas: a.sigmas,
        checks: Vec::new(),
        verdict: headalign::procedure::CheckVerdict::unchecked("none"),
        final_encoders: head.encoders(),
        rotation_deg: r,
        diagonal_rotation_deg: 0.0,
        verge_rotation_deg: 0.0,
        estimation_seconds,
    })
}

/// The values of [`SIGMA_QUANTITIES`] of an outcome: estimates and reported sigmas.
fn estimates(outcome: &VergeTiltOutcome) -> Vec<(f64, f64)> {
    let st = &outcome.calibration.bundle.state;
    let cov = &outcome.calibration.bundle.covariance;
    let s = |n: &str| cov.sigma(n).unwrap_or(f64::NAN);
    let a = outcome.solution.aligned_encoders;
    let g = outcome.sigmas;
    vec![
        (st.left.fx, s("left.fx")),
        (st.left.fy, s("left.fy")),
        (st.left.cx, s("left.cx")),
        (st.left.cy, s("left.cy")),
        (st.right.fx, s("right.fx")),
        (st.right.fy, s("right.fy")),
        (st.right.cx, s("right.cx")),
        (st.right.cy, s("right.cy")),
        (a.elevation, g.elevation_deg),
        (a.verge_left, g.verge_left_deg),
        (a.verge_right, g.verge_right_deg),
    ]
}

/// The pan and elevation axes' directions of an outcome against the truth
/// ([`SIGMA_QUANTITIES`]' last four, degrees): the estimate's offset from the true
/// direction in the bundle adjustment's tangent coordinates at the estimate (a direction
/// `d` moves to `normalise(d + B a)`; `B` is read by central differences through
/// [`headalign_geometry::bundle::BundleResult::perturbed`], so the basis stays the
/// adjustment's own). The truth is the simulator's axis at the reference view's true
/// readings `reference`, in that view's left camera frame (the estimate's gauge). NaN
/// where the state has no such axes or the perturbation fails.
fn axis_direction_offsets(
    head: &SimulatedHead,
    outcome: &VergeTiltOutcome,
    reference: &Encoders,
) -> [f64; 4] {
    let mut out = [f64::NAN; 4];
    let bundle = &outcome.calibration.bundle;
    let truth = head.truth();
    let left_from_world = truth.world_from_cameras(reference).0.inverse();
    let Some((pan, elevation)) = axes_of(&bundle.state) else { return out };
    let direction_of = |state: &headalign_geometry::bundle::RigState, j: usize| {
        axes_of(state).map(|(p, e)| if j == 0 { p.direction.into_inner() } else { e.direction.into_inner() })
    };
    for (j, (joint, line)) in [(Joint::Pan, pan), (Joint::Elevation, elevation)].into_iter().enumerate() {
        let d = line.direction.into_inner();
        let d_true = left_from_world.rotation * truth.axis_in_world(joint, reference).direction.into_inner();
        let mut basis = Matrix3x2::zeros();
        for i in 0..2 {
            let Some(k) = bundle.covariance.index(AXIS_DIRECTION_PARAMS[2 * j + i]) else { return out };
            let h = 1e-6;
            let at = |sign: f64| {
                let mut delta = DVector::zeros(bundle.covariance.names.len());
                delta[k] = sign * h;
                bundle.perturbed(&delta).ok().and_then(|st| direction_of(&st, j))
            };
            let (Some(plus), Some(minus)) = (at(1.0), at(-1.0)) else { return out };
            basis.set_column(i, &((plus - minus) / (2.0 * h)));
        }
        // The truth's tangent coordinates: the gnomonic point `d_true / (d . d_true)`
        // less `d`, in the basis (least squares: the central differences are not exactly
        // orthonormal).
        let v = d_true / d.dot(&d_true) - d;
        let Some(a) = (basis.transpose() * basis).try_inverse().map(|m| m * basis.transpose() * v) else {
            return out;
        };
        out[2 * j] = -a[0].to_degrees();
        out[2 * j + 1] = -a[1].to_degrees();
    }
    out
}

/// The observations of a noise-free run's calibration whose points are seen only at the
/// simulator's exact pixels (module docs): a point with any other observation (an outlier
/// kept) loses all of them. The rig views are the run's views before its vergence move,
/// as the procedure passes them to the estimate. The observations are returned unchanged
/// with a view dropped by the estimate (its view indices no longer match) and with encoder
/// noise (the readings are then not the angles the exact pixels need).
fn true_inlier_observations(
    head: &SimulatedHead,
    run: &VergeTiltRun,
    calib: &RigCalibration,
) -> Vec<headalign_geometry::bundle::BundleObservation> {
    use headalign_geometry::bundle::Side;
    use std::collections::{HashMap, HashSet};
    if !calib.report.dropped_views.is_empty() || head.scenario().encoder_noise_deg > 0.0 {
        return calib.observations.clone();
    }
    let exact: Vec<[HashMap<u64, nalgebra::Point2<f64>>; 2]> = run
        .views
        .iter()
        .take_while(|v| v.name != "verge")
        .map(|v| {
            let c = head.exact_capture(&v.capture.encoders);
            let map =
                |l: &[headalign_platform::TrackObservation]| l.iter().map(|o| (o.track, o.pixel)).collect();
            [map(&c.left), map(&c.right)]
        })
        .collect();
    // An exact pixel is reproduced to rounding (the noise is 1e-300 px).
    const SAME_PX: f64 = 1e-6;
    let outlier_points: HashSet<usize> = calib
        .observations
        .iter()
        .filter(|o| {
            let track = calib.point_tracks.get(o.point);
            let pixel = exact
                .get(o.view)
                .zip(track)
                .and_then(|(views, t)| views[usize::from(o.side == Side::Right)].get(t));
            pixel.is_none_or(|p| (o.pixel - p).norm() > SAME_PX)
        })
        .map(|o| o.point)
        .collect();
    calib.observations.iter().copied().filter(|o| !outlier_points.contains(&o.point)).collect()
}

/// The noise-free run of a scenario, from which the Cramer-Rao bound at any noise level
/// is evaluated ([`CleanRun::crb_sigmas`]).
#[derive(Clone, Debug)]
pub struct CleanRun {
    head: SimulatedHead,
    outcome: VergeTiltOutcome,
    /// The trial's bundle options (its angle prior is the bound's).
    bundle: BundleOptions,
    /// The head's readings where the procedure started (its reference view).
    initial: Encoders,
    seconds: f64,
}

impl CleanRun {
    /// Run `spec` with the noise set to zero (same seed, head, scene, outliers: the noise
    /// is [`CLEAN_NOISE_PX`]).
    pub fn new(spec: &TrialSpec) -> Result<Self> {
        let t0 = Instant::now();
        let mut clean = spec.clone();
        clean.scenario.noise_px = CLEAN_NOISE_PX;
        clean.scenario.encoder_noise_deg = 0.0;
        clean.lone_depth_gate = None;
        clean.bootstrap = None;
        let (head, run, mut outcome) =
            run_procedure(&clean).context("noise-free run for the Cramer-Rao bound")?;
        let inliers = true_inlier_observations(&head, &run, &outcome.calibration);
        outcome.calibration.observations = inliers;
        let bundle = estimation_options(spec).bundle;
        Ok(Self { head, outcome, bundle, initial: spec.initial, seconds: t0.elapsed().as_secs_f64() })
    }

    /// The noise-free run as a trial record (its bound is 0).
    pub fn record(&self) -> Result<TrialRecord> {
        let zeros = vec![0.0; SIGMA_QUANTITIES.len()];
        Ok(record_from(&self.head, &self.outcome, &self.initial, Some(&zeros), self.seconds))
    }

    /// Cramer-Rao bounds of [`SIGMA_QUANTITIES`] at pixel noise `noise_px` (module docs).
    pub fn crb_sigmas(&self, noise_px: f64) -> Result<Vec<f64>> {
        if noise_px <= 0.0 {
            return Ok(vec![0.0; SIGMA_QUANTITIES.len()]);
        }
        let calib = &self.outcome.calibration;
        let mut options = self.bundle.clone();
        options.max_iterations = 0;
        options.robust = RobustLoss::None;
        options.noise_sigma_px = Some(noise_px);
        let bundle = bundle_adjust(&calib.bundle.state, &calib.observations, &options)
            .map_err(|e| anyhow!("covariance at the truth: {e}"))?;
        let at_truth = RigCalibration { bundle, ..calib.clone() };
        let sig = alignment_sigmas(&at_truth, &self.outcome.verge_axes, &calib.reference_encoders)
            .map_err(|e| anyhow!("alignment sigmas at the truth: {e}"))?;
        let cov = &at_truth.bundle.covariance;
        let mut out: Vec<f64> =
            SIGMA_QUANTITIES[..8].iter().map(|n| cov.sigma(n).unwrap_or(f64::NAN)).collect();
        out.extend([sig.elevation_deg, sig.verge_left_deg, sig.verge_right_deg]);
        out.extend(axis_direction_sigmas_deg(cov));
        Ok(out)
    }
}

/// Run one trial; `crb` (from [`CleanRun::crb_sigmas`]) fills the bounds (NaN if `None`).
pub fn run_trial(spec: &TrialSpec, crb: Option<&[f64]>) -> Result<TrialRecord> {
    let t0 = Instant::now();
    let (head, _, outcome) = run_procedure(spec)?;
    Ok(record_from(&head, &outcome, &spec.initial, crb, t0.elapsed().as_secs_f64()))
}

/// Score an outcome against the head's truth.
/// `reference`: the true (commanded) readings of the reference view, where the procedure
/// started (the estimate's frame, [`axis_direction_offsets`]).
pub(super) fn record_from(
    head: &SimulatedHead,
    outcome: &VergeTiltOutcome,
    reference: &Encoders,
    crb: Option<&[f64]>,
    seconds: f64,
) -> TrialRecord {
    let after = head.alignment_errors(&head.encoders());
    let truth = head.truth().clone();
    let st = &outcome.calibration.bundle.state;
    let cal = calibration_errors(&truth.left, &truth.right, &st.left, &st.right);
    let recon =
        head.recon_errors(&outcome.calibration.reference_encoders, &outcome.calibration.points()).ok();
    let aligned = head.aligned_encoders();
    let unavoidable_r = head.alignment_errors(&aligned).elev_err_r_deg;
    let truths = [
        truth.left.fx,
        truth.left.fy,
        truth.left.cx,
        truth.left.cy,
        truth.right.fx,
        truth.right.fy,
        truth.right.cx,
        truth.right.cy,
        aligned.elevation,
        aligned.verge_left,
        aligned.verge_right,
    ];
    let axes = axis_direction_offsets(head, outcome, reference)
        .into_iter()
        .zip(axis_direction_sigmas_deg(&outcome.calibration.bundle.covariance))
        .map(|estimate| (estimate, 0.0));
    let quantities = estimates(outcome)
        .into_iter()
        .zip(truths)
        .chain(axes)
        .enumerate()
        .map(|(i, ((est, sigma), truth))| Quantity {
            est,
            truth,
            sigma,
            crb: crb.and_then(|c| c.get(i).copied()).unwrap_or(f64::NAN),
        })
        .collect();
    TrialRecord {
        verge_err_l_deg: after.verge_err_l_deg,
        verge_err_r_deg: after.verge_err_r_deg,
        elev_err_l_deg: after.elev_err_l_deg,
        elev_err_r_deg: after.elev_err_r_deg,
        elev_err_r_excess_deg: after.elev_err_r_deg - unavoidable_r,
        f_err_pct: cal.f_err_pct,
        aspect_err_pct: cal.aspect_err_pct,
        pp_err_pct: cal.pp_err_pct,
        recon_err_pct: recon.map_or(f64::NAN, |r| r.rms_pct),
        recon_median_pct: recon.map_or(f64::NAN, |r| r.median_pct),
        rotation_deg: outcome.rotation_deg,
        pan_err_deg: f64::NAN,
        quantities,
        seconds,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(noise: f64) -> TrialSpec {
        TrialSpec {
            scenario: Scenario { seed: 5, noise_px: noise, ..Scenario::default() },
            initial: Encoders::default(),
            rotation: RotationMode::Fixed,
            depth_profile: EstimationOptions::default().depth_profile,
            image_border: EstimationOptions::default().image_border,
            lone_depth_gate: EstimationOptions::default().lone_depth_gate,
            angle_prior: AnglePrior::default(),
            bootstrap: None,
        }
    }

    /// The bound's observations: in a noise-free run (seed 5, its outliers rejected) every
    /// observation is the simulator's exact pixel and all are kept; one moved by 10 px takes
    /// every observation of its point out, and nothing else.
    #[test]
    fn true_inliers_drop_the_points_of_a_moved_observation() {
        let mut clean = spec(CLEAN_NOISE_PX);
        clean.lone_depth_gate = None;
        let mut head = SimulatedHead::new(clean.scenario.clone()).unwrap();
        let mut run = VergeTiltRun::default();
        let outcome = run.run(&mut head, &procedure_options(&clean)).unwrap();
        let mut calib = outcome.calibration.clone();
        let key = |v: &[headalign_geometry::bundle::BundleObservation]| -> Vec<(usize, usize, f64, f64)> {
            v.iter().map(|o| (o.point, o.view, o.pixel.x, o.pixel.y)).collect()
        };
        assert_eq!(key(&true_inlier_observations(&head, &run, &calib)), key(&calib.observations));
        calib.observations[0].pixel.x += 10.0;
        let moved = calib.observations[0].point;
        let kept = true_inlier_observations(&head, &run, &calib);
        let of_moved = calib.observations.iter().filter(|o| o.point == moved).count();
        assert!(of_moved >= 3, "{of_moved}");
        assert_eq!(kept.len(), calib.observations.len() - of_moved);
        assert!(kept.iter().all(|o| o.point != moved));
    }

    /// A 3D homography without a rotation's complex eigenvalue pair only skips the linear
    /// start: seed 22 of the paper-like scene with 50 points at 1.5 px failed with "view
    /// 'pan-' is not a rotation of the head" before; it now runs, and its (poorly
    /// conditioned) errors stay within 3 of its bounds.
    #[test]
    fn noisy_homography_without_rotation_eigenvalues_does_not_fail_the_trial() {
        let s = TrialSpec {
            scenario: Scenario { seed: 22, noise_px: 1.5, points: 50, ..Scenario::paper_lab() },
            initial: Encoders::default(),
            rotation: RotationMode::Fixed,
            depth_profile: EstimationOptions::default().depth_profile,
            image_border: EstimationOptions::default().image_border,
            lone_depth_gate: EstimationOptions::default().lone_depth_gate,
            angle_prior: AnglePrior::default(),
            bootstrap: None,
        };
        let clean = CleanRun::new(&s).unwrap();
        let crb = clean.crb_sigmas(1.5).unwrap();
        let rec = run_trial(&s, Some(&crb)).unwrap();
        for (i, q) in rec.quantities.iter().enumerate() {
            assert!((q.est - q.truth).abs() < 3.0 * q.crb, "{}: {q:?}", SIGMA_QUANTITIES[i]);
        }
    }

    /// The noise-free run sees the outliers on the same observations as a noisy trial of
    /// its seed (identical outlier pixels; inliers differ by the noise only, < 20 px at
    /// 1 px), so the bound is that of the trial's own inlier set; at noise exactly 0 the
    /// simulator's stream diverges and most outliers fall elsewhere.
    #[test]
    fn clean_run_has_the_trials_outliers() {
        let far = |clean_noise: f64| {
            let capture = |noise: f64| {
                let mut head =
                    SimulatedHead::new(Scenario { seed: 5, noise_px: noise, ..Scenario::default() }).unwrap();
                head.capture().unwrap()
            };
            let (a, b) = (capture(clean_noise), capture(1.0));
            let mut far = 0;
            for (x, y) in [(&a.left, &b.left), (&a.right, &b.right)] {
                for o in x.iter() {
                    if let Some(p) = y.iter().find(|p| p.track == o.track) {
                        far += usize::from((o.pixel - p.pixel).norm() > 20.0);
                    }
                }
            }
            far
        };
        assert_eq!(far(CLEAN_NOISE_PX), 0);
        assert!(far(0.0) > 10, "{}", far(0.0));
    }

    /// The axis offsets' sign, scale and components: a noise-free estimate (the truth to
    /// about 1e-6) moved by 0.5 deg along its elevation axis's second tangent coordinate
    /// reads (0, 0, 0, +0.5) deg; 1e-2 deg allows the tangent basis at the moved direction,
    /// which differs from the one at the estimate to second order (0.5 deg x 0.009 rad).
    #[test]
    fn axis_offsets_follow_a_known_tangent_step() {
        let (head, _, mut outcome) = run_procedure(&spec(0.0)).unwrap();
        let zero = axis_direction_offsets(&head, &outcome, &Encoders::default());
        assert!(zero.iter().all(|v| v.abs() < 1e-4), "{zero:?}");
        let b = &outcome.calibration.bundle;
        let mut delta = DVector::zeros(b.covariance.names.len());
        delta[b.covariance.index("axis1.dir1").unwrap()] = 0.5_f64.to_radians();
        outcome.calibration.bundle.state = b.perturbed(&delta).unwrap();
        let o = axis_direction_offsets(&head, &outcome, &Encoders::default());
        assert!(o[0].abs() < 1e-4 && o[1].abs() < 1e-4, "pan moved: {o:?}");
        assert!(o[2].abs() < 1e-2 && (o[3] - 0.5).abs() < 1e-2, "{o:?}");
    }

    /// The aligned readings' reported sigmas against their bound in the two trials of
    /// `docs/results` (at c46cdb3) where the propagation broke, both `calibration` at 3 px
    /// with the experiments' 0.01 deg encoder noise. Seed 72: a point near infinity,
    /// re-triangulated under each perturbation, stepped through infinity to behind its
    /// cameras, every re-resection failed and the sigmas fell to the encoder prior's
    /// (0.018-0.088 of the bound). Seed 273: the 0.5-sigma difference step straddled a
    /// bend of the re-derived left vergence axis (elevation sigma 2.96 times the bound;
    /// `procedure::PROPAGATION_STEP_SIGMAS`). Now 0.96-1.05 (seed 72) and 1.03-1.17 (seed
    /// 273) of the bound; 0.75-1.35 keeps both failures out with a wide margin (over
    /// seeds 1-150 at 3 px the aligned sigmas lie within 0.83-1.58 of their bound, the
    /// upper end where the bound leaves out re-measured vergence axes).
    #[test]
    fn aligned_sigmas_stay_near_the_bound_where_the_propagation_broke() {
        for seed in [72, 273] {
            let mut s = spec(3.0);
            s.scenario.seed = seed;
            s.scenario.encoder_noise_deg = 0.01;
            let crb = CleanRun::new(&s).unwrap().crb_sigmas(3.0).unwrap();
            let rec = run_trial(&s, Some(&crb)).unwrap();
            for (i, q) in
                rec.quantities.iter().enumerate().filter(|(i, _)| SIGMA_QUANTITIES[*i].starts_with("aligned"))
            {
                let r = q.sigma / q.crb;
                assert!(
                    (0.75..=1.35).contains(&r),
                    "seed {seed} {}: sigma {} bound {}",
                    SIGMA_QUANTITIES[i],
                    q.sigma,
                    q.crb
                );
            }
        }
    }

    /// The bound grows with the noise, at most linearly (the angle prior is fixed in
    /// degrees, so it weighs more against noisier pixels: measured 1.85x, not 2x, for
    /// left.fx from 1 to 2 px), and the noise-free trial's estimates equal the truth
    /// (the bound is evaluated at the truth).
    #[test]
    fn crb_scales_with_noise_and_clean_run_is_truth() {
        let clean = CleanRun::new(&spec(1.0)).unwrap();
        let one = clean.crb_sigmas(1.0).unwrap();
        let two = clean.crb_sigmas(2.0).unwrap();
        for (i, (a, b)) in one.iter().zip(&two).enumerate() {
            assert!(*a > 0.0 && a.is_finite(), "{}: {a}", SIGMA_QUANTITIES[i]);
            assert!(*b > 1.2 * a && *b <= 2.0 * a * (1.0 + 1e-9), "{}: {a} {b}", SIGMA_QUANTITIES[i]);
        }
        assert!(clean.crb_sigmas(0.0).unwrap().iter().all(|v| *v == 0.0));
        let rec = run_trial(&spec(0.0), Some(&one)).unwrap();
        for (i, q) in rec.quantities.iter().enumerate() {
            // 1e-3 px / deg: the solver stops at ~1e-6 relative; the aligned readings go
            // through the vergence-axis resection and a correction loop.
            assert!((q.est - q.truth).abs() < 1e-3, "{}: {q:?}", SIGMA_QUANTITIES[i]);
        }
    }
}
