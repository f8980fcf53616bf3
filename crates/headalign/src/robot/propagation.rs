//! Uncertainty propagation and the planarity test of the robot stages ([`super`] module
//! docs, "uncertainty of the pan", "the readings' noise", "planarity").
//!
//! - [`calibration_covariance_dyn`]: `J C J^T` of any quantity computed from the
//!   verge/tilt calibration, `J` by central differences along each calibration parameter
//!   at [`PROPAGATION_STEP_SIGMAS`] of its sigma, plus (given [`AxisPerturbations`]) the
//!   vergence axes' own modes and (given reading noise) each joint's reading moved by
//!   `sqrt(2) sigma` (two independent reads).
//! - `motion_covariance`: a drive motion's 6x6 covariance (left perturbation, rotation
//!   first, radians and baselines) through the two pan estimates, by central differences
//!   along the columns of its Cholesky factor.
//! - The planarity test: the out-of-plane part of a drive (its rotation about the two
//!   axes perpendicular to the pan axis, radians, and the centre's displacement along it,
//!   baselines; 3 dof) against its covariance (the motion's and the calibration's, plus a
//!   floor of 1e-12 for the rounding of noise-free data), as a chi-square with 3 dof.
//!
//! Pitfalls: the propagation is linear, so the step must be small against the curvature
//! of what is differentiated yet large against the solvers' tolerances
//! ([`PROPAGATION_STEP_SIGMAS`]); a quantity that cannot be computed at a perturbed
//! calibration makes the whole covariance `None` (callers then report NaN sigmas rather
//! than a partial one).

use headalign_geometry::rigmotion::{RigMotionEstimate, RigMotionOptions, perturb};
use headalign_platform::{Encoders, Joint};
use nalgebra::{DMatrix, DVector, Isometry3, Matrix2, Matrix3, SMatrix, SVector, Vector2, Vector3, Vector6};

use super::drive::LEAST_SQUARES_HUBER_PX;
use crate::alignment::VergeAxes;
use crate::procedure::{AxisPerturbations, PROPAGATION_STEP_SIGMAS};
use crate::verge_tilt::RigCalibration;

/// An orthonormal pair perpendicular to `up`.
pub(super) fn perpendicular_basis(up: &Vector3<f64>) -> [Vector3<f64>; 2] {
    let helper = if up.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
    let e1 = up.cross(&helper).normalize();
    [e1, up.cross(&e1).normalize()]
}

/// The out-of-plane part of a drive `cam2_from_cam1` (zero for a motion on the plane
/// perpendicular to `up`): its rotation vector's components along `basis` (radians) and
/// the centre's displacement along `up` (baselines).
pub(super) fn out_of_plane(
    motion: &Isometry3<f64>,
    up: &Vector3<f64>,
    basis: &[Vector3<f64>; 2],
) -> Vector3<f64> {
    let w = motion.rotation.inverse().scaled_axis();
    let c = -(motion.rotation.inverse() * motion.translation.vector);
    Vector3::new(w.dot(&basis[0]), w.dot(&basis[1]), c.dot(up))
}

/// Covariance of [`out_of_plane`] from the motion's own covariance (left perturbation,
/// rotation first; Jacobian by central differences, step 1e-6: the map is smooth and
/// O(1) in these units).
pub(super) fn out_of_plane_covariance(
    ml: &RigMotionEstimate,
    up: &Vector3<f64>,
    basis: &[Vector3<f64>; 2],
) -> Matrix3<f64> {
    let h = 1e-6;
    let mut j = SMatrix::<f64, 3, 6>::zeros();
    for k in 0..6 {
        let mut d = Vector6::zeros();
        d[k] = h;
        let p = out_of_plane(&perturb(&ml.cam2_from_cam1, &d), up, basis);
        d[k] = -h;
        let m = out_of_plane(&perturb(&ml.cam2_from_cam1, &d), up, basis);
        j.set_column(k, &((p - m) / (2.0 * h)));
    }
    j * ml.covariance * j.transpose()
}

/// Variance floor added to the out-of-plane covariance's diagonal (radians squared /
/// baselines squared): rounding of noise-free data, far below any real tilt (1e-6 rad is
/// 0.00006 deg).
const PLANARITY_FLOOR: f64 = 1e-12;

/// Chi-square of the out-of-plane part `v` with covariance `cov` (plus the floor).
pub(super) fn planarity_chi2(v: &Vector3<f64>, cov: &Matrix3<f64>) -> f64 {
    let c = cov + Matrix3::identity() * PLANARITY_FLOOR;
    c.try_inverse().map_or(f64::INFINITY, |inv| (v.transpose() * inv * v)[(0, 0)])
}

/// Covariance (2x2) of the two pan estimates `q(motion)` from a drive motion's own
/// covariance ([`RigMotionEstimate::covariance`], left perturbation, rotation first):
/// `q` is evaluated at the motion moved by `+-` [`PROPAGATION_STEP_SIGMAS`] times each
/// column of the covariance's Cholesky factor `L` (`C = L L^T`), and the central
/// differences `D` (per unit of each column) give `D D^T` (exact for a linear `q`; the
/// factor keeps the strong rotation-translation correlations of a short drive). `None`
/// if `q` fails or the covariance is not positive definite.
pub(super) fn motion_covariance(
    ml: &RigMotionEstimate,
    q: impl Fn(&Isometry3<f64>) -> Option<Vector2<f64>>,
) -> Option<Matrix2<f64>> {
    let l = ml.covariance.cholesky()?.l();
    let mut out = Matrix2::zeros();
    for k in 0..6 {
        let step: Vector6<f64> = l.column(k) * PROPAGATION_STEP_SIGMAS;
        let plus = q(&perturb(&ml.cam2_from_cam1, &step))?;
        let minus = q(&perturb(&ml.cam2_from_cam1, &(-step)))?;
        let d = (plus - minus) / (2.0 * PROPAGATION_STEP_SIGMAS);
        out += d * d.transpose();
    }
    Some(out)
}

/// Calibration parameters that move the rig or the head axes (the bundle's per-view
/// angles and poses do not enter the robot stages), with a usable standard deviation.
fn calibration_parameters(calib: &RigCalibration) -> Vec<usize> {
    let cov = &calib.bundle.covariance;
    (0..cov.names.len())
        .filter(|&i| {
            let v = cov.matrix[(i, i)];
            !cov.names[i].starts_with("view") && v.is_finite() && v > 0.0
        })
        .collect()
}

/// Encoder readings a quantity is computed at, with the standard deviation of each
/// joint's reading noise (degrees; 0: the readings taken as exact).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Readings {
    pub(crate) enc: Encoders,
    pub(crate) sigma_deg: f64,
}

impl Readings {
    /// The readings taken as exact.
    pub(crate) fn exact(enc: Encoders) -> Self {
        Self { enc, sigma_deg: 0.0 }
    }
}

/// Covariance of a quantity `q(calibration, vergence axes, readings)` (`n_out` values)
/// from the verge/tilt calibration's covariance, given `axes` ([`AxisPerturbations`]) the
/// vergence axes' own, and the noise of the encoder `readings` the quantity is computed
/// at: `J C J^T`, `J` by central differences of `q` along each parameter, step
/// [`PROPAGATION_STEP_SIGMAS`] of its standard deviation (as
/// [`crate::procedure::alignment_sigmas`]).
///
/// Without `axes`: the parameters of [`calibration_parameters`], the axes held as given
/// (the stereo rig predicted at other vergence readings then counts no error of the
/// axes). With `axes`: every parameter with a step in `axes.calibration` (the per-view
/// ones too: they move the scene points the axis views were resected against), the
/// axes moved with the calibration, plus the resected poses' noise modes (unit
/// variance, independent of the calibration) with the calibration held. The readings'
/// noise: the rig is predicted from each joint's reading minus the calibration's
/// reference reading, two independent reads, so each joint's reading is moved by `+-`
/// [`PROPAGATION_STEP_SIGMAS`] `sqrt(2) sigma`, independent of the other joints and of
/// the calibration (whose angle priors hold the differences of the calibration views'
/// readings, not the reference reading's own error).
/// `None` if `q` fails at a perturbed calibration.
pub(crate) fn calibration_covariance_dyn(
    calib: &RigCalibration,
    verge: &VergeAxes,
    axes: Option<&AxisPerturbations>,
    readings: &Readings,
    n_out: usize,
    mut q: impl FnMut(&RigCalibration, &VergeAxes, &Encoders) -> Option<DVector<f64>>,
) -> Option<DMatrix<f64>> {
    let cov = &calib.bundle.covariance;
    let n = cov.names.len();
    let enc = &readings.enc;
    let axes = axes.filter(|a| a.calibration.len() == n);
    let idx: Vec<usize> = match axes {
        Some(a) => (0..n).filter(|&i| a.calibration[i].is_some()).collect(),
        None => calibration_parameters(calib),
    };
    let mut scratch = calib.clone();
    let mut jac = DMatrix::<f64>::zeros(n_out, idx.len());
    for (col, &i) in idx.iter().enumerate() {
        let h = AxisPerturbations::calibration_step(cov, i);
        let (plus_axes, minus_axes) = match axes.and_then(|a| a.calibration[i].as_ref()) {
            Some(st) => (st.plus, st.minus),
            None => (*verge, *verge),
        };
        let mut delta = DVector::zeros(n);
        delta[i] = h;
        scratch.bundle.state = calib.bundle.perturbed(&delta).ok()?;
        let plus = q(&scratch, &plus_axes, enc)?;
        delta[i] = -h;
        scratch.bundle.state = calib.bundle.perturbed(&delta).ok()?;
        let minus = q(&scratch, &minus_axes, enc)?;
        if plus.len() != n_out || minus.len() != n_out {
            return None;
        }
        jac.set_column(col, &((plus - minus) / (2.0 * h)));
    }
    let sub = cov.matrix.select_rows(idx.iter()).select_columns(idx.iter());
    let mut out = &jac * sub * jac.transpose();
    // Unit-variance modes at +-PROPAGATION_STEP_SIGMAS: the difference over twice the
    // step is the change per unit of the mode.
    let mut add_mode = |d: DVector<f64>| {
        if d.len() != n_out {
            return None;
        }
        let d = d / (2.0 * PROPAGATION_STEP_SIGMAS);
        out += &d * d.transpose();
        Some(())
    };
    if let Some(a) = axes {
        // The resected poses' noise.
        for st in &a.pose {
            add_mode(q(calib, &st.plus, enc)? - q(calib, &st.minus, enc)?)?;
        }
    }
    if readings.sigma_deg > 0.0 {
        let half = PROPAGATION_STEP_SIGMAS * std::f64::consts::SQRT_2 * readings.sigma_deg;
        for joint in Joint::ALL {
            let (mut plus, mut minus) = (*enc, *enc);
            *plus.get_mut(joint) += half;
            *minus.get_mut(joint) -= half;
            add_mode(q(calib, verge, &plus)? - q(calib, verge, &minus)?)?;
        }
    }
    Some(out)
}

/// [`calibration_covariance_dyn`] for a fixed-size quantity.
pub(crate) fn calibration_covariance<const N: usize>(
    calib: &RigCalibration,
    verge: &VergeAxes,
    axes: Option<&AxisPerturbations>,
    readings: &Readings,
    mut q: impl FnMut(&RigCalibration, &VergeAxes, &Encoders) -> Option<SVector<f64, N>>,
) -> Option<SMatrix<f64, N, N>> {
    let c = calibration_covariance_dyn(calib, verge, axes, readings, N, |cp, va, e| {
        q(cp, va, e).map(|v| DVector::from_column_slice(v.as_slice()))
    })?;
    Some(SMatrix::<f64, N, N>::from_fn(|r, k| c[(r, k)]))
}

/// Options of the least-squares refits under a perturbed calibration (warm start).
pub(super) fn refit_options() -> RigMotionOptions {
    RigMotionOptions { huber_px: LEAST_SQUARES_HUBER_PX, max_iterations: 10 }
}
