//! The normal equations of the rig bundle adjustment and their damped solution by the
//! Schur complement over the points, the reduced camera system (module docs of
//! [`crate::bundle`], section Algorithm).
//!
//! # What it computes
//!
//! - `Problem::normal_equations`: at a state, the Gauss-Newton normal equations
//!   `J^T W J`, `J^T W r` of the robustly weighted residuals (IRLS weights `rho'(s)/s` at
//!   the linearisation point), split into the dense camera block `U` (`c x c`, `c` camera
//!   parameters), one 3x3 block `V_p` per point, the off-diagonal blocks `W` (`c x 3n`)
//!   and the gradients `g_c, g_p` (`Normal`, in pixels and the parameters' units). `U` is
//!   one dense product per (view, side) pair (`CameraBlock`: all its observations share
//!   the same camera columns); the angle-prior rows add to `U` and `g_c` with the given
//!   prior weight; the depth-scale pseudo-residual is kept as a row over the points.
//! - `reduced_camera_system`: `S = U - sum_p W_p V_p^-1 W_p^T`, formed as `U - M M^T` with
//!   `M_p = W_p L_p^-T` (`V_p = L_p L_p^T`), with `U` and every `V_p` damped on their
//!   diagonals (Triggs, McLauchlan, Hartley, Fitzgibbon, "Bundle adjustment - a modern
//!   synthesis", 2000, section 6; Hartley & Zisserman, 2nd ed., appendix A6, sparse
//!   Levenberg-Marquardt).
//! - `solve_rhs` / `solve`: Cholesky of `S` for the camera step, back-substitution for the
//!   points; the depth-scale pseudo-residual's dense rank-one term by Sherman-Morrison.
//!   Marquardt's scaling: the damping adds `lambda` times the diagonal clamped to
//!   `[1e-6, 1e32]` (`damping_diagonal`).
//! - `predicted_decrease`: the decrease of the local quadratic model for a damped step, the
//!   denominator of Nielsen's gain ratio (`solver.rs`).
//!
//! # Pitfalls
//!
//! - A damped point block or `S` that is not positive definite fails the solve (`None`):
//!   the solver then raises the damping. The covariance, undamped, instead leaves such
//!   points out (`skip_singular`).
//! - All observations of one (view, side) pair must yield the same camera columns in the
//!   same order; otherwise `normal_equations` gives `None`.
//! - `S` is symmetrised (`(S + S^T) / 2`) before Cholesky; the order of the sums is part of
//!   the results (they are compared bit for bit across refactors).

use nalgebra::{DMatrix, DVector, Matrix3, Vector3};

use super::covariance::{log_depth_scale_jacobian, log_depth_scale_of};
use super::layout::side_index;
use super::problem::Problem;
use super::residual::{rig_geom, view_geoms};
use super::robust::robust;
use super::state::RigState;

pub(super) struct Normal {
    pub(super) u: DMatrix<f64>,
    pub(super) gc: DVector<f64>,
    pub(super) v: Vec<Matrix3<f64>>,
    pub(super) gp: Vec<Vector3<f64>>,
    /// `W`, camera parameters x points: point `p`'s block is columns `3p..3p+3`.
    pub(super) w: DMatrix<f64>,
    pub(super) sum_wsq: f64,
    /// The depth-scale pseudo-residual: its Jacobian row over the points (compact order)
    /// and its value; its rank-one normal term is applied in [`solve`] (Sherman-Morrison).
    pub(super) depth: Option<(Vec<Vector3<f64>>, f64)>,
}

impl Problem<'_> {
    pub(super) fn normal_equations(&self, state: &RigState, prior_weight: f64) -> Option<Normal> {
        let nc = self.layout.len();
        let np = self.points.len();
        let views = view_geoms(state, &self.layout, true);
        let rig = rig_geom(state);
        let mut n = Normal {
            u: DMatrix::zeros(nc, nc),
            gc: DVector::zeros(nc),
            v: vec![Matrix3::zeros(); np],
            gp: vec![Vector3::zeros(); np],
            w: DMatrix::zeros(nc, 3 * np),
            sum_wsq: 0.0,
            depth: None,
        };
        if let Some((target, tol)) = self.depth {
            let r = (log_depth_scale_of(state, &self.points)? - target) / tol;
            let row = log_depth_scale_jacobian(state, &self.points)?;
            n.depth = Some((row.into_iter().map(|a| a / tol).collect(), r));
        }
        // Every observation of one (view, side) pair has the same camera-parameter
        // columns in the same order (they follow from the layout, the side and the view
        // alone), so the pair's weighted Jacobian rows are stacked densely over that list
        // and its share of `U` is one matrix product, scattered once at the end.
        let mut blocks: Vec<Option<CameraBlock>> = (0..2 * views.len()).map(|_| None).collect();
        let mut cols = Vec::with_capacity(32);
        for (o, &p) in self.obs.iter().zip(&self.obs_point) {
            let x = state.points.get(*self.points.get(p)?)?;
            let (r, jp) = self.observe(state, &views, &rig, o, x, Some(&mut cols))?;
            let s2 = r.norm_squared();
            let wt = robust(self.options.robust, s2).1;
            n.sum_wsq += wt * s2;
            let jpw = jp * wt;
            *n.v.get_mut(p)? += jp.transpose() * jpw;
            *n.gp.get_mut(p)? += jpw.transpose() * r;
            let block = blocks.get_mut(2 * o.view + side_index(o.side))?.get_or_insert_with(|| CameraBlock {
                idx: cols.iter().map(|c| c.0).collect(),
                rows: Vec::new(),
            });
            if !block.idx.iter().eq(cols.iter().map(|c| &c.0)) {
                return None;
            }
            let sw = wt.sqrt();
            block.rows.extend(cols.iter().map(|c| c.1.x * sw));
            block.rows.extend(cols.iter().map(|c| c.1.y * sw));
            for &(a, ja) in &cols {
                n.gc[a] += wt * ja.dot(&r);
                let wrow = ja.transpose() * jpw;
                for c in 0..3 {
                    n.w[(a, 3 * p + c)] += wrow[c];
                }
            }
        }
        for block in blocks.into_iter().flatten() {
            let k = block.idx.len();
            // The row-major rows of `sqrt(w) J` are the columns of its transpose.
            let jt = DMatrix::from_vec(k, block.rows.len() / k.max(1), block.rows);
            let h = &jt * jt.transpose();
            for (i, &a) in block.idx.iter().enumerate() {
                for (j, &b) in block.idx.iter().enumerate() {
                    n.u[(a, b)] += h[(i, j)];
                }
            }
        }
        for row in self.prior_terms(state) {
            for &(a, da) in &row.entries {
                n.gc[a] += prior_weight * row.residual * da;
                for &(b, db) in &row.entries {
                    n.u[(a, b)] += prior_weight * da * db;
                }
            }
        }
        Some(n)
    }
}

/// The camera-parameter Jacobian of the observations of one (view, side) pair: their
/// parameter indices in column order and the rows of `sqrt(w) J`, row-major (two per
/// observation).
struct CameraBlock {
    idx: Vec<usize>,
    rows: Vec<f64>,
}

/// `S` and the points' `L_p^-1` (see [`reduced_camera_system`]).
type ReducedSystem = (DMatrix<f64>, Vec<Option<Matrix3<f64>>>);

/// The reduced camera system `S = U - W V^-1 W^T` of `n` with every point block `V_p`
/// (and `U`'s diagonal) damped by `damp` of its diagonal, as one product `S = U - M M^T`
/// with `M_p = W_p L_p^-T` (`V_p = L_p L_p^T`). Per point its `L_p^-1`, or `None` for a
/// block that is not positive definite: such a point is left out when `skip_singular`,
/// otherwise the whole system is `None`.
pub(super) fn reduced_camera_system(
    n: &Normal,
    damp: impl Fn(f64) -> f64,
    skip_singular: bool,
) -> Option<ReducedSystem> {
    let nc = n.u.nrows();
    let mut m = DMatrix::zeros(nc, n.w.ncols());
    let mut l_inv = Vec::with_capacity(n.v.len());
    for (p, v) in n.v.iter().enumerate() {
        let mut vd = *v;
        for i in 0..3 {
            vd[(i, i)] += damp(v[(i, i)]);
        }
        let li = vd.cholesky().and_then(|ch| ch.l().try_inverse());
        let Some(li) = li else {
            if skip_singular {
                l_inv.push(None);
                continue;
            }
            return None;
        };
        m.columns_mut(3 * p, 3).gemm(1.0, &n.w.columns(3 * p, 3), &li.transpose(), 0.0);
        l_inv.push(Some(li));
    }
    let mut s = n.u.clone();
    for i in 0..nc {
        s[(i, i)] += damp(n.u[(i, i)]);
    }
    s.gemm(-1.0, &m, &m.transpose(), 1.0);
    Some((0.5 * (&s + s.transpose()), l_inv))
}

/// Solve the damped normal equations by the Schur complement over the points; with a
/// depth-scale pseudo-residual `r_s` (Jacobian `a`, points only) the normal matrix gains
/// the dense rank-one term `a a^T` and the gradient `a r_s`, solved by Sherman-Morrison:
/// `x = y - z (a.y) / (1 + a.z)` with `N y = -g - a r_s`, `N z = a`.
pub(super) fn solve(n: &Normal, lambda: f64) -> Option<(DVector<f64>, Vec<Vector3<f64>>)> {
    let rc = -&n.gc;
    let Some((a, r)) = &n.depth else {
        let rp: Vec<Vector3<f64>> = n.gp.iter().map(|g| -g).collect();
        return solve_rhs(n, lambda, &rc, &rp);
    };
    let rp: Vec<Vector3<f64>> = n.gp.iter().zip(a).map(|(g, ai)| -g - ai * *r).collect();
    let (yc, yp) = solve_rhs(n, lambda, &rc, &rp)?;
    let (zc, zp) = solve_rhs(n, lambda, &DVector::zeros(rc.len()), a)?;
    let ay: f64 = a.iter().zip(&yp).map(|(ai, y)| ai.dot(y)).sum();
    let az: f64 = a.iter().zip(&zp).map(|(ai, z)| ai.dot(z)).sum();
    let f = ay / (1.0 + az);
    let dc = yc - zc * f;
    let dp = yp.iter().zip(&zp).map(|(y, z)| y - z * f).collect();
    Some((dc, dp))
}

/// The decrease of the cost that the damped step `(dc, dp)` of [`solve`] predicts (the
/// local quadratic model, cost units): with `(N + lambda D) h = -g`,
/// `-g.h - h^T N h / 2 = (-g.h + lambda h^T D h) / 2`, where `g` includes the depth-scale
/// pseudo-residual's gradient and `D` is the clamped diagonal the damping uses.
pub(super) fn predicted_decrease(n: &Normal, lambda: f64, dc: &DVector<f64>, dp: &[Vector3<f64>]) -> f64 {
    let mut g_h = n.gc.dot(dc);
    let mut h_d_h: f64 = (0..dc.len()).map(|i| damping_diagonal(n.u[(i, i)]) * dc[i] * dc[i]).sum();
    for (p, d) in dp.iter().enumerate() {
        let (Some(g), Some(v)) = (n.gp.get(p), n.v.get(p)) else { continue };
        let mut g = *g;
        if let Some(a) = n.depth.as_ref().and_then(|(a, r)| a.get(p).map(|a| a * *r)) {
            g += a;
        }
        g_h += g.dot(d);
        h_d_h += (0..3).map(|i| damping_diagonal(v[(i, i)]) * d[i] * d[i]).sum::<f64>();
    }
    0.5 * (lambda * h_d_h - g_h)
}

/// A diagonal entry of the normal matrix as the damping scales it: clamped to
/// `[1e-6, 1e32]` (Marquardt scaling, module docs).
fn damping_diagonal(d: f64) -> f64 {
    d.clamp(1e-6, 1e32)
}

/// Solve the damped normal equations `N_lambda (dc, dp) = (rc, rp)` (data and priors
/// only) by the Schur complement over the points.
pub(super) fn solve_rhs(
    n: &Normal,
    lambda: f64,
    rc: &DVector<f64>,
    rp: &[Vector3<f64>],
) -> Option<(DVector<f64>, Vec<Vector3<f64>>)> {
    let (s, l_inv) = reduced_camera_system(n, |d| lambda * damping_diagonal(d), false)?;
    // V_p^-1 = L_p^-T L_p^-1.
    let v_inv: Vec<Matrix3<f64>> =
        l_inv.into_iter().map(|li| li.map(|li| li.transpose() * li)).collect::<Option<_>>()?;
    let mut b = rc.clone();
    for (p, (vi, g)) in v_inv.iter().zip(rp).enumerate() {
        b.gemv(-1.0, &n.w.columns(3 * p, 3), &(vi * g), 1.0);
    }
    let dc = s.cholesky()?.solve(&b);
    if !dc.iter().all(|v| v.is_finite()) {
        return None;
    }
    let dp = v_inv
        .iter()
        .zip(rp)
        .enumerate()
        .map(|(p, (vi, g))| vi * (g - n.w.columns(3 * p, 3).tr_mul(&dc)))
        .collect();
    Some((dc, dp))
}
