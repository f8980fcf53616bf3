//! A small dense Levenberg-Marquardt for problems with a fixed, small number `N` of
//! parameters (Hartley & Zisserman appendix A6.2; Marquardt's damping): the refinements
//! of F (7 dof), of a 3D homography (16) and of a camera pose (6) share it. The bundle
//! adjustment has its own solver (Schur complement over points).
//!
//! The caller supplies the normal equations `(J^T W J, J^T W r)` at a state, a retraction
//! `state (+) delta`, and the cost that the normal equations linearise. A step is taken
//! only if it lowers the cost; the damping `lambda * diag` (Marquardt's scaling, invariant
//! to parameter units) starts at `lambda = 1e-3`, shrinks tenfold after a success and
//! grows tenfold after a failure. It stops when no step of up to 20 tries lowers the cost, when the relative
//! decrease falls to 1e-14, or after `max_iterations`. Pitfall: the cost must be exactly
//! what the normal equations linearise (the same weights), or steps are refused.

use nalgebra::{SMatrix, SVector};

/// Minimise `cost` from `start` (whose cost is `start_cost`). Returns the final state and
/// its cost; never a state worse than the start.
pub fn minimise<const N: usize, S>(
    start: S,
    start_cost: f64,
    max_iterations: usize,
    normal_equations: impl Fn(&S) -> Option<(SMatrix<f64, N, N>, SVector<f64, N>)>,
    retract: impl Fn(&S, &SVector<f64, N>) -> Option<S>,
    cost: impl Fn(&S) -> f64,
) -> (S, f64) {
    let (mut state, mut current) = (start, start_cost);
    let mut lambda = 1e-3;
    for _ in 0..max_iterations {
        let Some((jtj, jtr)) = normal_equations(&state) else { break };
        // Marquardt's scaling: damping proportional to each diagonal entry (with a floor so
        // a parameter the data do not see is still damped), invariant to parameter units.
        let floor = 1e-12 * (0..N).map(|i| jtj[(i, i)]).fold(0.0, f64::max).max(1e-300);
        let mut improved = false;
        for _ in 0..20 {
            let mut a = jtj;
            for i in 0..N {
                a[(i, i)] += lambda * jtj[(i, i)].max(floor);
            }
            let Some(delta) = a.cholesky().map(|c| c.solve(&(-jtr))) else {
                lambda *= 10.0;
                continue;
            };
            let Some(candidate) = retract(&state, &delta) else {
                lambda *= 10.0;
                continue;
            };
            let c = cost(&candidate);
            if c.is_finite() && c < current {
                let rel = (current - c) / current.max(1e-300);
                state = candidate;
                current = c;
                lambda = (lambda * 0.1).max(1e-15);
                improved = rel > 1e-14;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    (state, current)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix2, Vector2};

    /// Rosenbrock's valley as least squares, r = (10 (y - x^2), 1 - x): the minimum (1, 1)
    /// to 1e-8 from (-1.2, 1) (Gauss-Newton is exact at a zero-residual minimum).
    #[test]
    fn minimises_rosenbrock() {
        let res = |p: &Vector2<f64>| Vector2::new(10.0 * (p.y - p.x * p.x), 1.0 - p.x);
        let cost = |p: &Vector2<f64>| res(p).norm_squared();
        let normal = |p: &Vector2<f64>| {
            let j = Matrix2::new(-20.0 * p.x, 10.0, -1.0, 0.0);
            Some((j.transpose() * j, j.transpose() * res(p)))
        };
        let start = Vector2::new(-1.2, 1.0);
        let (p, c) = minimise(start, cost(&start), 200, normal, |p, d| Some(p + d), cost);
        assert!((p - Vector2::new(1.0, 1.0)).norm() < 1e-8 && c < 1e-16, "{p} {c}");
    }
}
