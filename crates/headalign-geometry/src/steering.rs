//! Steering-wheel zero, wheelbase and forward direction of a tricycle robot from the
//! turning centres of drives at known steering-encoder differences (paper section 7,
//! `docs/how-it-works.md#pan-steering-and-the-drives-motion`).
//!
//! Model: the robot turns about the vertical line through the intersection of the
//! rear-axle line and the front wheel's axle line. On the ground plane (seen along the
//! vertical `up`), with `j` the forward direction, `i = up x j` (pointing left) the
//! rear-axle direction and `a` the foot of the front wheel on the rear-axle line, a true
//! steering angle `sigma` (positive left) puts the centre at `a + (L cot sigma) i`. The
//! encoder reads `E = sigma + z` (zero offset `z`). So each drive `k` gives a position
//! `u_k = p + L cot(E_k - z)` along the fitted axle line (unknowns `p`, `L`, `z`: three
//! turns; two when the wheelbase `L` is known).
//!
//! Algorithm: project the centres on the plane perpendicular to `up`; the axle line is
//! their principal direction; the forward direction is perpendicular to it, its sign
//! given by a hint (the direction the robot drove). Then `(p, L)` are linear for fixed `z`:
//! a scan of `z` over `(-45, 45)` degrees between the singularities of `cot`, then
//! least squares on `(p, L, z)` (analytic Jacobian) by the project's Levenberg-Marquardt
//! ([`crate::lm`]) until no step lowers the cost (machine precision).
//!
//! Units: the centres' length unit (e.g. stereo baselines) for `L` and `p`; degrees for
//! encoders and `z`. Residual: distance along the axle line, centre units.
//!
//! Pitfalls: a turn with a tiny steering angle puts its centre far away and badly
//! located (the caller must reject small rotations before calling); three settings on
//! the same side of straight are fine, but settings very close together make `z` weakly
//! determined; centres off the axle line (residual across it) mean the motion was not a
//! tricycle turn (slip, or a non-planar motion).

use nalgebra::{Matrix3, Point3, Unit, Vector3};

use crate::{GeometryError, Result};

/// One drive: its steering encoder reading and a point of its turning axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Turn {
    /// Steering encoder reading during the drive, degrees.
    pub steer_encoder_deg: f64,
    /// A point on the turning axis (any height), in a frame fixed to the robot.
    pub centre: Point3<f64>,
}

/// Result of [`steering_from_turns`].
#[derive(Debug, Clone, PartialEq)]
pub struct SteeringSolution {
    /// Steering encoder reading at which the wheel is straight, degrees.
    pub steer_zero_deg: f64,
    /// Wheelbase, centre units (the given one when known).
    pub wheelbase: f64,
    /// Forward direction of the robot (perpendicular to the axle line and to `up`).
    pub forward: Unit<Vector3<f64>>,
    /// A point of the rear-axle line: the foot of the front wheel on it (height of the
    /// centres' mean).
    pub axle_point: Point3<f64>,
    /// RMS distance of the centres from the fitted axle line, centre units.
    pub across_rms: f64,
    /// RMS residual along the line after the fit, centre units.
    pub along_rms: f64,
}

fn cot(x: f64) -> f64 {
    x.cos() / x.sin()
}

/// The inputs' checks of [`steering_from_turns`] (its errors).
fn check_turns(turns: &[Turn], wheelbase: Option<f64>) -> Result<()> {
    let needed = if wheelbase.is_some() { 2 } else { 3 };
    if turns.len() < needed {
        return Err(GeometryError::NotEnoughData { what: "turns", needed, got: turns.len() });
    }
    if let Some(l) = wheelbase
        && !(l.is_finite() && l > 0.0)
    {
        return Err(GeometryError::InvalidOption(format!("wheelbase must be positive, got {l}")));
    }
    for (a, ta) in turns.iter().enumerate() {
        for tb in &turns[a + 1..] {
            if (ta.steer_encoder_deg - tb.steer_encoder_deg).abs() < 1e-9 {
                return Err(GeometryError::Degenerate("two turns at the same steering reading".into()));
            }
        }
    }
    Ok(())
}

/// The rear-axle line's frame on the floor: the mean of the turning centres projected
/// onto the floor (perpendicular to `up`) and the forward direction, perpendicular to
/// the centres' principal direction (the axle line) and to `up`, its sign that of
/// `forward_hint` (module docs).
fn axle_frame(
    up: &Unit<Vector3<f64>>,
    turns: &[Turn],
    forward_hint: &Vector3<f64>,
) -> Result<(Vector3<f64>, Vector3<f64>)> {
    let up_v = up.into_inner();
    let flat = |p: &Point3<f64>| p.coords - up_v * up_v.dot(&p.coords);
    let n = turns.len() as f64;
    let mean = turns.iter().map(|t| flat(&t.centre)).sum::<Vector3<f64>>() / n;
    let mut scatter = Matrix3::zeros();
    for t in turns {
        let d = flat(&t.centre) - mean;
        scatter += d * d.transpose();
    }
    let eig = scatter.symmetric_eigen();
    let (imax, lmax) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .ok_or_else(|| GeometryError::Numerical("eigen decomposition".into()))?;
    if *lmax <= 1e-24 || lmax.is_nan() {
        return Err(GeometryError::Degenerate("the turning centres coincide".into()));
    }
    let axle = eig.eigenvectors.column(imax).into_owned();
    let axle = (axle - up_v * up_v.dot(&axle)).normalize();
    let mut forward = up_v.cross(&axle).normalize();
    let hint = forward.dot(forward_hint);
    if hint.abs() < 1e-12 * forward_hint.norm().max(1e-300) {
        return Err(GeometryError::Degenerate("forward hint along the rear-axle line".into()));
    }
    if hint < 0.0 {
        forward = -forward;
    }
    Ok((mean, forward))
}

/// Solve for the steering zero, wheelbase and forward direction (module docs).
///
/// `forward_hint`: any vector with a positive component along the true forward
/// direction (e.g. the displacement of a drive). `wheelbase`: `Some(L)` when known.
///
/// Errors: [`GeometryError::NotEnoughData`] with fewer than 3 turns (2 with a known
/// wheelbase); [`GeometryError::Degenerate`] when the centres coincide, the hint is
/// along the axle line, or two turns share an encoder reading.
pub fn steering_from_turns(
    up: &Unit<Vector3<f64>>,
    turns: &[Turn],
    forward_hint: &Vector3<f64>,
    wheelbase: Option<f64>,
) -> Result<SteeringSolution> {
    check_turns(turns, wheelbase)?;
    let up_v = up.into_inner();
    let flat = |p: &Point3<f64>| p.coords - up_v * up_v.dot(&p.coords);
    let n = turns.len() as f64;
    let (mean, forward) = axle_frame(up, turns, forward_hint)?;
    let left = up_v.cross(&forward);
    let u: Vec<f64> = turns.iter().map(|t| (flat(&t.centre) - mean).dot(&left)).collect();
    let across_rms =
        (turns.iter().map(|t| (flat(&t.centre) - mean).dot(&forward).powi(2)).sum::<f64>() / n).sqrt();
    let e: Vec<f64> = turns.iter().map(|t| t.steer_encoder_deg.to_radians()).collect();

    let (z, p, l) = scan_zero(&u, &e, wheelbase)
        .ok_or_else(|| GeometryError::Degenerate("no positive wheelbase fits the turns".into()))?;
    let (z, p, l) = refine(&u, &e, (z, p, l), wheelbase.is_some());
    let along_rms =
        (u.iter().zip(&e).map(|(uk, ek)| (uk - p - l * cot(ek - z)).powi(2)).sum::<f64>() / n).sqrt();
    if !(z.is_finite() && l.is_finite() && p.is_finite()) {
        return Err(GeometryError::Numerical("steering fit diverged".into()));
    }
    let mean_height = turns.iter().map(|t| up_v * up_v.dot(&t.centre.coords)).sum::<Vector3<f64>>() / n;
    Ok(SteeringSolution {
        steer_zero_deg: z.to_degrees(),
        wheelbase: l,
        forward: Unit::new_normalize(forward),
        axle_point: Point3::from(mean + left * p + mean_height),
        across_rms,
        along_rms,
    })
}

/// The start of [`refine`]: for each zero offset `z` of a scan over `(-45, 45)` degrees
/// (0.05 deg apart), `(p, L)` by linear least squares (`p` alone when the `wheelbase` is
/// known) of the positions `u` at readings `e` (radians); the `(z, p, L)` of least squares
/// with a positive `L`, `None` if there is none.
fn scan_zero(u: &[f64], e: &[f64], wheelbase: Option<f64>) -> Option<(f64, f64, f64)> {
    let n = u.len() as f64;
    // For fixed z: (p, L) by linear least squares (or p alone with L known).
    let solve_linear = |z: f64| -> Option<(f64, f64, f64)> {
        let c: Vec<f64> = e.iter().map(|ek| cot(ek - z)).collect();
        if c.iter().any(|v| !v.is_finite() || v.abs() > 1e8) {
            return None;
        }
        let (p, l) = match wheelbase {
            Some(l) => ((0..u.len()).map(|k| u[k] - l * c[k]).sum::<f64>() / n, l),
            None => {
                let (sc, su) = (c.iter().sum::<f64>(), u.iter().sum::<f64>());
                let scc = c.iter().map(|v| v * v).sum::<f64>();
                let scu = c.iter().zip(u).map(|(a, b)| a * b).sum::<f64>();
                let det = n * scc - sc * sc;
                if det.abs() < 1e-300 {
                    return None;
                }
                let l = (n * scu - sc * su) / det;
                ((su - l * sc) / n, l)
            }
        };
        let ss = (0..u.len()).map(|k| (u[k] - p - l * c[k]).powi(2)).sum::<f64>();
        Some((p, l, ss))
    };
    let mut best: Option<(f64, f64, f64, f64)> = None;
    let steps = 1800;
    for s in 0..=steps {
        let z = (-45.0 + 90.0 * s as f64 / steps as f64).to_radians();
        if let Some((p, l, ss)) = solve_linear(z)
            && l > 0.0
            && best.is_none_or(|b| ss < b.3)
        {
            best = Some((z, p, l, ss));
        }
    }
    best.map(|(z, p, l, _)| (z, p, l))
}

/// Most iterations of [`refine`] (it stops at the cost's rounding level long before).
const REFINE_ITERATIONS: usize = 50;

/// The least-squares `(z, p, L)` of the positions `u` along the axle line at encoder
/// readings `e` (radians) from `start` (the scan's best), by [`crate::lm::minimise_with`]
/// run to rounding
/// (analytic Jacobian; `L` held when `hold_l`, the wheelbase known). Residuals in centre
/// units.
fn refine(u: &[f64], e: &[f64], start: (f64, f64, f64), hold_l: bool) -> (f64, f64, f64) {
    // State (p, L, z).
    let cost = |x: &Vector3<f64>| {
        u.iter().zip(e).map(|(uk, ek)| (uk - x.x - x.y * cot(ek - x.z)).powi(2)).sum::<f64>()
    };
    let normal = |x: &Vector3<f64>| {
        let (p, l, z) = (x.x, x.y, x.z);
        let mut jtj = Matrix3::zeros();
        let mut jtr = Vector3::zeros();
        for (uk, ek) in u.iter().zip(e) {
            let a = ek - z;
            let r = uk - p - l * cot(a);
            let s2 = a.sin().powi(2);
            let j = Vector3::new(-1.0, if hold_l { 0.0 } else { -cot(a) }, -l / s2);
            jtj += j * j.transpose();
            jtr += j * r;
        }
        if hold_l {
            jtj[(1, 1)] = 1.0;
        }
        Some((jtj, jtr))
    };
    let x0 = Vector3::new(start.1, start.2, start.0);
    // To rounding (no function tolerance): the robot's steering stage differentiates this
    // fit by central differences at 1e-6.
    let options = crate::lm::LmOptions {
        max_iterations: REFINE_ITERATIONS,
        function_tolerance: 0.0,
        parameter_tolerance: 0.0,
    };
    let (x, _) = crate::lm::minimise_with(x0, cost(&x0), &options, normal, |x, d| Some(x + d), cost);
    (x.z, x.x, x.y)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(128))]
        /// Noise-free: zero, wheelbase and forward to 1e-9 in an arbitrary robot-fixed frame.
        #[test]
        fn noise_free_recovery(z in -10.0..10.0f64, l in 0.3..2.0f64, yaw in -3.0..3.0f64, tilt in -0.5..0.5f64,
                               ox in -1.0..1.0f64, oz in -1.0..1.0f64, known in proptest::bool::ANY) {
            let frame = Rotation3::from_euler_angles(tilt, yaw, 0.3 * tilt);
            let up = Unit::new_normalize(frame * -Vector3::y());
            let fwd = frame * Vector3::z();
            let left = up.cross(&fwd);
            let foot = frame * Vector3::new(ox, 0.7, oz);
            let encoders = [z - 20.0, z + 18.0, z + 31.0];
            let turns: Vec<Turn> = encoders.iter().enumerate().map(|(k, e)| {
                let s = (e - z).to_radians();
                Turn { steer_encoder_deg: *e, centre: Point3::from(foot + left * (l / s.tan()) + up.into_inner() * (k as f64 * 0.1)) }
            }).collect();
            let sol = steering_from_turns(&up, &turns, &(fwd + left * 0.3), known.then_some(l)).unwrap();
            prop_assert!((sol.steer_zero_deg - z).abs() < 1e-9, "{} vs {}", sol.steer_zero_deg, z);
            prop_assert!((sol.wheelbase - l).abs() < 1e-9);
            prop_assert!((sol.forward.into_inner() - fwd).norm() < 1e-9);
            prop_assert!(sol.along_rms < 1e-9 && sol.across_rms < 1e-9);
        }
    }

    #[test]
    fn degenerate_inputs() {
        let up = -Vector3::y_axis();
        let t = |e: f64, x: f64| Turn { steer_encoder_deg: e, centre: Point3::new(x, 0.0, 0.0) };
        let fwd = Vector3::z();
        assert!(matches!(
            steering_from_turns(&up, &[t(10.0, 1.0), t(-10.0, -1.0)], &fwd, None),
            Err(GeometryError::NotEnoughData { .. })
        ));
        assert!(matches!(
            steering_from_turns(&up, &[t(10.0, 1.0), t(10.0, -1.0), t(20.0, 2.0)], &fwd, None),
            Err(GeometryError::Degenerate(_))
        ));
        assert!(matches!(
            steering_from_turns(&up, &[t(10.0, 1.0), t(-10.0, 1.0), t(20.0, 1.0)], &fwd, None),
            Err(GeometryError::Degenerate(_))
        ));
        assert!(matches!(
            steering_from_turns(&up, &[t(10.0, 1.0), t(-10.0, -1.0), t(20.0, 2.0)], &Vector3::x(), None),
            Err(GeometryError::Degenerate(_))
        ));
    }
}
