//! Uncertainty of the aligned readings ([`super`] module docs;
//! `docs/how-it-works.md#3-alignment-move-check`): the bundle adjustment's covariance
//! propagated to the aligned joint changes
//! (elevation, left and right vergence; degrees) by central differences of
//! [`solve_alignment`] along each calibration parameter, at [`PROPAGATION_STEP_SIGMAS`]
//! of its standard deviation: with the vergence axes held as given
//! ([`alignment_sigmas`]), or re-derived under each perturbation with the resected poses'
//! own noise added ([`alignment_sigmas_measured`]; the linearisation is
//! [`super::axes`]'s).
//!
//! [`fixation_sigmas`] propagates the same covariance to the fixation points (pixels):
//! where each camera sees the target direction. An aligned reading's error is the
//! fixation point's error less the principal point's (the reading turns the optical axis,
//! through the principal point, onto the target), so the two sigmas differ: with three
//! 3 deg views the fixation point's x sigma is 1.1-1.6 times the vergence reading's
//! (median 1.4), because the fixation point and the principal point are uncertain along
//! x together and the reading depends on their difference (`docs/accuracy.md`,
//! "Three-view sessions").
//!
//! Degrees of freedom: 3 outputs (4 for the fixation points); as many inputs as the bundle has parameters (a
//! parameter without positive variance contributes nothing). Pitfalls: the propagation
//! is linear; a derivative whose evaluation fails on either side falls back to the next
//! evaluation (held axes) for the whole central difference, never mixing the two; the
//! reading noise of the reference view is added by the caller
//! ([`AlignmentSigmas::with_reading_noise`]).

use headalign_platform::Encoders;
use nalgebra::DVector;

use super::axes::{AxisFollow, AxisSources, resection_pose_covariance, tangent_step};
use super::{AlignmentSigmas, AxisPerturbations, FixationSigmas, PROPAGATION_STEP_SIGMAS};
use crate::alignment::{AlignmentSolution, VergeAxes, solve_alignment};
use crate::error::AlignError;
use crate::verge_tilt::RigCalibration;

/// Propagate the bundle adjustment's covariance to the aligned readings by central
/// differences of [`solve_alignment`] along each parameter's standard deviation, the
/// vergence axes held as given ([`alignment_sigmas_measured`] adds their measurement).
pub fn alignment_sigmas(
    calib: &RigCalibration,
    verge: &VergeAxes,
    reference: &Encoders,
) -> Result<AlignmentSigmas, AlignError> {
    let jac = calibration_jacobian(
        &calib.bundle.covariance,
        &[&|delta| held_axes_deltas(calib, verge, reference, delta)],
    );
    Ok(sigmas_of(&(&jac * &calib.bundle.covariance.matrix * jac.transpose())))
}

/// Propagate the bundle adjustment's covariance to the fixation points (module docs) by
/// central differences of [`solve_alignment`] along each parameter's standard deviation.
/// The fixation points depend on the calibration alone (the intersections of the
/// invariant lines, through the lens if one is estimated), not on the vergence axes or
/// the readings, so neither is an input.
pub fn fixation_sigmas(calib: &RigCalibration) -> FixationSigmas {
    let jac = fixation_jacobian(calib);
    let cov = &jac * &calib.bundle.covariance.matrix * jac.transpose();
    let sd = |i: usize| cov[(i, i)].max(0.0).sqrt();
    FixationSigmas { left_px: [sd(0), sd(1)], right_px: [sd(2), sd(3)] }
}

/// Jacobian (4 x n: left x, left y, right x, right y, pixels per unit of each bundle
/// parameter) of the fixation points ([`fixation_sigmas`]).
pub(super) fn fixation_jacobian(calib: &RigCalibration) -> nalgebra::DMatrix<f64> {
    let at = |delta: &DVector<f64>| -> Option<[f64; 4]> {
        let st = calib.bundle.perturbed(delta).ok()?;
        let s = solve_alignment(&st, &VergeAxes::default(), &Encoders::default()).ok()?;
        let ([lu, lv], [ru, rv]) = (s.fixation_px_left, s.fixation_px_right);
        Some([lu, lv, ru, rv])
    };
    calibration_jacobian(&calib.bundle.covariance, &[&at])
}

/// The aligned deltas with the bundle's parameters moved by `delta` (its tangent) and
/// the vergence axes held as given.
fn held_axes_deltas(
    calib: &RigCalibration,
    verge: &VergeAxes,
    reference: &Encoders,
    delta: &DVector<f64>,
) -> Option<[f64; 3]> {
    let st = calib.bundle.perturbed(delta).ok()?;
    solve_alignment(&st, verge, reference).ok().map(|s| aligned_deltas(&s))
}

/// The aligned joint changes (elevation, left and right vergence), degrees.
pub(super) fn aligned_deltas(s: &AlignmentSolution) -> [f64; 3] {
    [s.delta_elevation_deg, s.delta_verge_left_deg, s.delta_verge_right_deg]
}

/// `N` quantities (the aligned deltas, the fixation points) under a perturbation of the
/// bundle's parameters (its tangent, in its covariance's order); `None` where they cannot
/// be computed.
type AlignedDeltasAt<'a, const N: usize> = dyn Fn(&DVector<f64>) -> Option<[f64; N]> + 'a;

/// Jacobian (N x n, per unit of each parameter) of `N` quantities (the aligned deltas) under a
/// perturbation of the bundle's parameters (in its covariance's order) by central
/// differences at [`PROPAGATION_STEP_SIGMAS`] of each parameter's standard deviation
/// ([`AxisPerturbations::calibration_step`]). Each column comes from the first of `fs`
/// that succeeds on both sides (so a fallback is never mixed into one difference); a
/// column whose parameter has no positive variance, or where every one fails, is zero.
pub(super) fn calibration_jacobian<const N: usize>(
    cov: &headalign_geometry::bundle::Covariance,
    fs: &[&AlignedDeltasAt<N>],
) -> nalgebra::DMatrix<f64> {
    let n = cov.matrix.nrows();
    let mut jac = nalgebra::DMatrix::<f64>::zeros(N, n);
    for i in 0..n {
        let h = AxisPerturbations::calibration_step(cov, i);
        if h.is_nan() || h <= 0.0 {
            continue;
        }
        let mut plus = DVector::zeros(n);
        plus[i] = h;
        let minus = -&plus;
        if let Some((p, m)) = fs.iter().find_map(|f| Some((f(&plus)?, f(&minus)?))) {
            for r in 0..N {
                jac[(r, i)] = (p[r] - m[r]) / (2.0 * h);
            }
        }
    }
    jac
}

/// Square roots of the diagonal of a 3x3 covariance of the aligned deltas.
pub(super) fn sigmas_of(cov: &nalgebra::DMatrix<f64>) -> AlignmentSigmas {
    AlignmentSigmas {
        elevation_deg: cov[(0, 0)].max(0.0).sqrt(),
        verge_left_deg: cov[(1, 1)].max(0.0).sqrt(),
        verge_right_deg: cov[(2, 2)].max(0.0).sqrt(),
    }
}

/// [`alignment_sigmas`] with the vergence axes' own measurement uncertainty: the aligned
/// readings are a function of the calibration (bundle covariance) and of the poses
/// resected after the vergence move (covariance [`resection_pose_covariance`], pixel noise
/// `noise_px` or the resection residuals' estimate), independent because the vergence
/// view is not in the bundle. Each axis is re-derived by [`verge_axes_from_motion`] from
/// the perturbed calibration (its pan/elevation chain and stereo pose) and the perturbed
/// resected pose, then [`solve_alignment`] is differentiated centrally. An axis without a
/// source is held as given. Under each calibration perturbation the scene points follow
/// the cameras (one Gauss-Newton re-triangulation each, their conditional mean: the
/// covariance has them eliminated) and the axis poses are re-resected (one Gauss-Newton
/// step), so the axes' dependence on the calibration is propagated with its correlations.
///
/// The re-resection must be the resection [`crate::alignment::measure_cameras`] ran: the
/// same points (seen three or more times) and the same inliers, chosen once at the
/// estimate. Points seen twice (one stereo pair) follow the calibration far more than the
/// rest; letting them into the linearised resection, or re-applying an outlier threshold
/// per perturbation, inflated the elevation sigma of runs whose axis was re-measured in a
/// check view after a large elevation move up to 2.7x, while their actual errors moved by
/// a few hundredths of a degree (a past measurement, no command reproduces it; 150 seeds at
/// 2 px): the term raises the elevation sigma by 2 % where the axes come from the
/// procedure's vergence view, by 6 % where a check view re-measured them (a third of the
/// runs), and the vergence sigmas by under 0.1 %.
///
/// Pitfalls: the points' own conditional noise (given the cameras) is not propagated into
/// the resections; with `noise_px` `None` the pixel noise is estimated from residuals
/// truncated at the resection's 5 px outlier threshold (7 % low at 2 px), which only the
/// small pose part feels.
///
/// [`verge_axes_from_motion`]: crate::alignment::verge_axes_from_motion
pub fn alignment_sigmas_measured(
    calib: &RigCalibration,
    verge: &VergeAxes,
    sources: &AxisSources,
    reference: &Encoders,
    noise_px: Option<f64>,
) -> Result<AlignmentSigmas, AlignError> {
    let follow = AxisFollow::new(calib, verge, sources, reference);
    let cov = &calib.bundle.covariance;
    // A parameter under which the axes cannot be re-derived (a re-resection that fails)
    // keeps at least its held-axes part rather than none.
    let jac = calibration_jacobian(
        cov,
        &[&|delta| follow.followed(delta), &|delta| held_axes_deltas(calib, verge, reference, delta)],
    );
    let mut out = &jac * &cov.matrix * jac.transpose();
    // The resected poses' own noise.
    let state = &calib.bundle.state;
    let points: std::collections::HashMap<u64, nalgebra::Point3<f64>> = calib.points().into_iter().collect();
    for side in 0..2 {
        let Some((obs, k, pose0)) = follow.resected(side) else { continue };
        let Some(pcov) = resection_pose_covariance(k, &points, obs, &pose0, noise_px) else { continue };
        let mut jp = nalgebra::Matrix3x6::<f64>::zeros();
        for c in 0..6 {
            let h = PROPAGATION_STEP_SIGMAS * pcov[(c, c)].max(0.0).sqrt();
            if h.is_nan() || h <= 0.0 {
                continue;
            }
            let mut d = nalgebra::Vector6::<f64>::zeros();
            d[c] = h;
            let eval = |d: &nalgebra::Vector6<f64>| {
                let moved = pose0 * tangent_step(d);
                let mut poses = [follow.poses[0].as_ref(), follow.poses[1].as_ref()];
                poses[side] = Some(&moved);
                follow.deltas(state, poses)
            };
            if let (Some(p), Some(m)) = (eval(&d), eval(&-d)) {
                for r in 0..3 {
                    jp[(r, c)] = (p[r] - m[r]) / (2.0 * h);
                }
            }
        }
        let add = jp * pcov * jp.transpose();
        for r in 0..3 {
            for c in 0..3 {
                out[(r, c)] += add[(r, c)];
            }
        }
    }
    Ok(sigmas_of(&out))
}
