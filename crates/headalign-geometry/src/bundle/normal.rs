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
//! - `PointBlocks`: `W` dense (`c x 3n`) for at most `DENSE_SCHUR_MAX_VIEWS` views, per
//!   point over its own rows above (`sparse.rs`: the reduced system formed point by point
//!   and factored by a profile Cholesky).
//! - `reduced_camera_system`: `S = U - sum_p W_p V_p^-1 W_p^T`, formed as `U - M M^T` with
//!   `M_p = W_p L_p^-T` (`V_p = L_p L_p^T`), with `U` and every `V_p` damped on their
//!   diagonals (Triggs, McLauchlan, Hartley, Fitzgibbon, "Bundle adjustment - a modern
//!   synthesis", 2000, section 6; Hartley & Zisserman, 2nd ed., appendix A6, sparse
//!   Levenberg-Marquardt).
//! - `solve_rhs` / `solve`: Cholesky of `S` for the camera step, back-substitution for the
//!   points; the depth-scale pseudo-residual's dense rank-one term by Sherman-Morrison
//!   (its two right-hand sides share one factorisation). Marquardt's scaling: the damping
//!   adds `lambda` times the diagonal clamped to `[1e-6, 1e32]` (`lm::damping_diagonal`).
//! - `predicted_decrease`: the decrease of the local quadratic model for a damped step, the
//!   denominator of Nielsen's gain ratio (`crate::lm`). `Normal` is the point-Schur back
//!   end of `crate::lm` (`lm::Linearisation`).
//!
//! # Block layout and storage
//!
//! The per-point quantities are fixed-size (`V_p`, `L_p^-1` and `V_p^-1` 3x3 matrices,
//! `g_p` 3-vectors, on the stack). The dense `W` is one column-major `c x 3n` matrix:
//! point `p`'s block `W_p` is the contiguous columns `3p..3p+3`, and so is its block of
//! `M = W L^-T` (same layout); `M_p`, `W_p x` and `W_p^T x` are formed column by column
//! over those 3 columns, `S -= M M^T` is one matrix product over all points (`M^T` a
//! strided view of `M`, not a copy). The large storage lives in the `Normal` and is
//! reused: its `Workspace` (`M`, `S` and its factor, the per-point `L_p^-1` and
//! `V_p^-1`) serves every solve of one linearisation (the Levenberg-Marquardt loop solves
//! again after each rejected step), and the bundle adjustment hands the whole `Normal`
//! back to the next linearisation (`Problem::normal_equations_reusing`, through
//! `lm::LeastSquares::recycle`), which zeroes and refills `U`, `W`, the point blocks and
//! the camera blocks' rows in place instead of allocating them again.
//!
//! # Pitfalls
//!
//! - A damped point block or `S` that is not positive definite fails the solve (`None`):
//!   the solver then raises the damping. The covariance, undamped, instead leaves such
//!   points out (`skip_singular`).
//! - All observations of one (view, side) pair must yield the same camera columns in the
//!   same order; otherwise `normal_equations` gives `None`.
//! - `S` is symmetrised (`(S + S^T) / 2`) before Cholesky; the order of the sums is part of
//!   the results (they are compared bit for bit across refactors: the per-point products
//!   written out here keep the order of nalgebra's own, and reused storage is zeroed, so
//!   the results do not depend on whether storage was reused).

use std::cell::RefCell;
use std::rc::Rc;

use nalgebra::{Cholesky, DMatrix, DMatrixView, DVector, Dyn, Matrix3, OMatrix, RowVector3, U3, Vector3};

use super::covariance::{log_depth_scale_jacobian, log_depth_scale_of};
use super::layout::side_index;
use super::problem::Problem;
use super::residual::{RigGeom, ViewGeom, rig_geom, view_geoms};
use super::robust::robust;
use super::sparse::{ProfileCholesky, SparseStructure, schur, view_first_order};
use super::state::RigState;
use crate::lm::damping_diagonal;

/// The normal equations of a point-Schur problem at one state (module docs).
pub(crate) struct Normal {
    pub(super) u: DMatrix<f64>,
    pub(super) gc: DVector<f64>,
    pub(super) v: Vec<Matrix3<f64>>,
    pub(super) gp: Vec<Vector3<f64>>,
    /// `W`, camera parameters x points ([`PointBlocks`]).
    pub(super) w: PointBlocks,
    pub(super) sum_wsq: f64,
    /// The depth-scale pseudo-residual: its Jacobian row over the points (compact order)
    /// and its value; its rank-one normal term is applied in [`solve`] (Sherman-Morrison).
    pub(super) depth: Option<(Vec<Vector3<f64>>, f64)>,
    /// The order of the profile Cholesky of the sparse form (`sparse.rs`): the per-view
    /// parameters, then the shared ones; `None` for the dense form.
    pub(super) order: Option<Vec<usize>>,
    /// The camera blocks, one per (view, side) pair (kept for their storage).
    blocks: Vec<CameraBlock>,
    /// The solves' storage (module docs, Block layout and storage).
    work: RefCell<Workspace>,
}

/// Storage of the solves of a [`Normal`], reused by each (module docs).
struct Workspace {
    /// `M = W L^-T` of the dense form, `c x 3n` column-major (only `c * 3n` entries used).
    m: Vec<f64>,
    /// `S`; moved into the dense Cholesky factor during a solve and back after it.
    s: DMatrix<f64>,
    /// The profile Cholesky's factor (sparse form).
    profile: Vec<f64>,
    /// Per point `L_p^-1` (`None`: a point left out).
    l_inv: Vec<Option<Matrix3<f64>>>,
    /// Per point `V_p^-1` of the damped blocks.
    v_inv: Vec<Matrix3<f64>>,
    /// A camera block's share of `U`.
    h: DMatrix<f64>,
}

impl Default for Workspace {
    fn default() -> Self {
        Self {
            m: Vec::new(),
            s: DMatrix::zeros(0, 0),
            profile: Vec::new(),
            l_inv: Vec::new(),
            v_inv: Vec::new(),
            h: DMatrix::zeros(0, 0),
        }
    }
}

/// `m` as a zero `rows x cols` matrix, in place when it has that shape already.
fn zero_matrix(m: &mut DMatrix<f64>, rows: usize, cols: usize) {
    if m.shape() == (rows, cols) {
        m.as_mut_slice().fill(0.0);
    } else {
        *m = DMatrix::zeros(rows, cols);
    }
}

/// `v` as `len` copies of `value`, in its own storage.
fn refill<T: Clone>(v: &mut Vec<T>, len: usize, value: T) {
    v.clear();
    v.resize(len, value);
}

impl Normal {
    /// Zero normal equations of `nc` camera parameters, `np` points and `blocks` camera
    /// blocks, `W` sparse over `structure` if given, dense otherwise; in the storage of
    /// `spare` when given (module docs, Block layout and storage).
    fn cleared(
        spare: Option<Normal>,
        nc: usize,
        np: usize,
        blocks: usize,
        structure: Option<Rc<SparseStructure>>,
    ) -> Normal {
        let mut n = spare.unwrap_or_else(|| Normal {
            u: DMatrix::zeros(0, 0),
            gc: DVector::zeros(0),
            v: Vec::new(),
            gp: Vec::new(),
            w: PointBlocks::Dense(DMatrix::zeros(0, 0)),
            sum_wsq: 0.0,
            depth: None,
            order: None,
            blocks: Vec::new(),
            work: RefCell::default(),
        });
        zero_matrix(&mut n.u, nc, nc);
        if n.gc.len() == nc {
            n.gc.fill(0.0);
        } else {
            n.gc = DVector::zeros(nc);
        }
        refill(&mut n.v, np, Matrix3::zeros());
        refill(&mut n.gp, np, Vector3::zeros());
        let old = std::mem::replace(&mut n.w, PointBlocks::Dense(DMatrix::zeros(0, 0)));
        n.w = match (structure, old) {
            (Some(s), PointBlocks::Sparse(_, mut values)) => {
                refill(&mut values, s.slot_count(), RowVector3::zeros());
                PointBlocks::Sparse(s, values)
            }
            (Some(s), PointBlocks::Dense(_)) => {
                let values = s.zeros();
                PointBlocks::Sparse(s, values)
            }
            (None, PointBlocks::Dense(mut w)) => {
                zero_matrix(&mut w, nc, 3 * np);
                PointBlocks::Dense(w)
            }
            (None, PointBlocks::Sparse(..)) => PointBlocks::Dense(DMatrix::zeros(nc, 3 * np)),
        };
        n.sum_wsq = 0.0;
        n.depth = None;
        n.order = None;
        for b in &mut n.blocks {
            b.used = false;
            b.idx.clear();
            b.rows.clear();
        }
        n.blocks.resize_with(blocks, CameraBlock::default);
        n
    }

    /// `U += sqrt(w) J^T sqrt(w) J` of every camera block used, one matrix product per
    /// block (`J^T` a strided view of its rows), scattered to the block's columns.
    fn add_camera_blocks(&mut self) {
        let h = &mut self.work.get_mut().h;
        for block in self.blocks.iter().filter(|b| b.used) {
            let k = block.idx.len();
            let m = block.rows.len() / k.max(1);
            if k == 0 || m == 0 {
                continue;
            }
            // The row-major rows of `sqrt(w) J` are the columns of its transpose.
            let jt = DMatrixView::from_slice(&block.rows, k, m);
            let j = DMatrixView::from_slice_with_strides(&block.rows, m, k, k, 1);
            if h.shape() != (k, k) {
                *h = DMatrix::zeros(k, k);
            }
            h.gemm(1.0, &jt, &j, 0.0);
            for (i, &a) in block.idx.iter().enumerate() {
                for (j, &b) in block.idx.iter().enumerate() {
                    self.u[(a, b)] += h[(i, j)];
                }
            }
        }
    }
}

impl Problem<'_> {
    /// The sparse structure of `W` for a problem of many views (`None`: dense), built at
    /// the first linearisation from its column lists and kept (it depends on the layout
    /// and the observations only); `None` in the outer option if an observation does not
    /// linearise at `state`.
    fn sparse_structure(
        &self,
        state: &RigState,
        views: &[ViewGeom],
        rig: &RigGeom,
    ) -> Option<Option<Rc<SparseStructure>>> {
        if !self.sparse {
            return Some(None);
        }
        if let Some(s) = self.structure.get() {
            return Some(Some(s.clone()));
        }
        let mut cols = Vec::with_capacity(32);
        let mut lists = Vec::with_capacity(self.obs.len());
        for (o, &p) in self.obs.iter().zip(&self.obs_point) {
            let x = state.points.get(*self.points.get(p)?)?;
            self.observe(state, views, rig, o, x, Some(&mut cols))?;
            lists.push((p, cols.iter().map(|c| c.0).collect::<Vec<usize>>()));
        }
        let s = Rc::new(SparseStructure::new(self.points.len(), &lists)?);
        let _ = self.structure.set(s.clone());
        Some(Some(s))
    }

    /// The normal equations at `state` (module docs), the angle priors weighted by
    /// `prior_weight`; `None` if an observation does not linearise.
    pub(super) fn normal_equations(&self, state: &RigState, prior_weight: f64) -> Option<Normal> {
        self.normal_equations_reusing(state, prior_weight, None)
    }

    /// [`Self::normal_equations`] in the storage of `spare`, normal equations of this
    /// problem at an earlier state (module docs, Block layout and storage): the same
    /// values, without allocating the large matrices again.
    pub(super) fn normal_equations_reusing(
        &self,
        state: &RigState,
        prior_weight: f64,
        spare: Option<Normal>,
    ) -> Option<Normal> {
        let views = view_geoms(state, &self.layout, true);
        let rig = rig_geom(state);
        let structure = self.sparse_structure(state, &views, &rig)?;
        let sparse = structure.is_some();
        let mut n = Normal::cleared(spare, self.layout.len(), self.points.len(), 2 * views.len(), structure);
        if sparse {
            n.order = Some(view_first_order(&self.layout));
        }
        if let Some((target, tol)) = self.depth {
            let r = (log_depth_scale_of(state, &self.points)? - target) / tol;
            let row = log_depth_scale_jacobian(state, &self.points)?;
            n.depth = Some((row.into_iter().map(|a| a / tol).collect(), r));
        }
        self.add_observations(state, &views, &rig, &mut n)?;
        n.add_camera_blocks();
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

    /// The observations' terms of `n` (zero on entry) but for `U`'s: `V_p`, `g_p`, `g_c`,
    /// `W` and the weighted squares, and each (view, side) pair's rows of `sqrt(w) J` in its
    /// camera block. Every observation of one pair has the same camera-parameter columns
    /// in the same order (they follow from the layout, the side and the view alone), so
    /// the pair's rows are stacked densely over that list and its share of `U` is one
    /// matrix product ([`Normal::add_camera_blocks`]). `None` if an observation does not
    /// linearise or breaks that rule.
    fn add_observations(
        &self,
        state: &RigState,
        views: &[ViewGeom],
        rig: &RigGeom,
        n: &mut Normal,
    ) -> Option<()> {
        let structure = match &n.w {
            PointBlocks::Sparse(s, _) => Some(s.clone()),
            PointBlocks::Dense(_) => None,
        };
        let mut cols = Vec::with_capacity(32);
        for (oi, (o, &p)) in self.obs.iter().zip(&self.obs_point).enumerate() {
            let x = state.points.get(*self.points.get(p)?)?;
            let (r, jp) = self.observe(state, views, rig, o, x, Some(&mut cols))?;
            let s2 = r.norm_squared();
            let wt = robust(self.options.robust, s2).1;
            n.sum_wsq += wt * s2;
            let jpw = jp * wt;
            *n.v.get_mut(p)? += jp.transpose() * jpw;
            *n.gp.get_mut(p)? += jpw.transpose() * r;
            let block = n.blocks.get_mut(2 * o.view + side_index(o.side))?;
            if !block.used {
                block.used = true;
                block.idx.extend(cols.iter().map(|c| c.0));
            }
            if !block.idx.iter().eq(cols.iter().map(|c| &c.0)) {
                return None;
            }
            let sw = wt.sqrt();
            block.rows.extend(cols.iter().map(|c| c.1.x * sw));
            block.rows.extend(cols.iter().map(|c| c.1.y * sw));
            let slots = structure.as_ref().map_or(&[][..], |s| s.slots(oi));
            for (j, &(a, ja)) in cols.iter().enumerate() {
                n.gc[a] += wt * ja.dot(&r);
                let wrow = ja.transpose() * jpw;
                n.w.add(slots.get(j), a, p, &wrow);
            }
        }
        Some(())
    }
}

/// The off-diagonal blocks `W_p = sum J_c^T w J_p` of the normal equations (camera
/// parameters x a point's 3 coordinates), stored densely for few views or per point for
/// many ([`DENSE_SCHUR_MAX_VIEWS`], `sparse.rs`).
pub(super) enum PointBlocks {
    /// One `c x 3n` matrix: point `p`'s block is columns `3p..3p+3`.
    Dense(DMatrix<f64>),
    /// Per point, its non-zero rows only (the camera parameters of its observations).
    Sparse(Rc<SparseStructure>, Vec<RowVector3<f64>>),
}

/// The largest number of views whose problems keep `W` dense (module docs, Algorithm):
/// the dense form is one product over all points, the sparse one a product per point over
/// its own rows only (`sparse.rs`). Dense costs `c^2 n` per iteration (`c` camera
/// parameters grow with the views, and so do the points `n` along a sequence: quadratic
/// in the views) and its Cholesky `c^3`; sparse `n k^2` (`k` a point's rows: the shared
/// parameters plus 6 per view that sees it) and a profile Cholesky linear in the views
/// along a sequence. Measured on a rendered 25-view sequence (15 keyframes, 7200 points):
/// the dense form spent 12 s of system time alone allocating its `c x 3n` matrices. The
/// dense form stays up to this many views so that the results of the small problems
/// (every head procedure, a few views of a rig) are those they always were (the order of
/// the sums is part of them).
pub(super) const DENSE_SCHUR_MAX_VIEWS: usize = 8;

/// Point `p`'s 3 columns of a column-major matrix of `rows` rows stored in `data`.
fn point_columns(data: &[f64], rows: usize, p: usize) -> Option<[&[f64]; 3]> {
    let at = |c: usize| data.get((3 * p + c) * rows..(3 * p + c + 1) * rows);
    Some([at(0)?, at(1)?, at(2)?])
}

impl PointBlocks {
    /// `W[a, point p] += row` for a column (parameter `a`) of an observation's Jacobian
    /// whose slot in the sparse form is `slot` (the column's entry of
    /// [`SparseStructure::slots`]).
    fn add(&mut self, slot: Option<&usize>, a: usize, p: usize, row: &RowVector3<f64>) {
        match self {
            PointBlocks::Dense(w) => {
                for c in 0..3 {
                    w[(a, 3 * p + c)] += row[c];
                }
            }
            PointBlocks::Sparse(_, values) => {
                if let Some(v) = slot.and_then(|&s| values.get_mut(s)) {
                    *v += row;
                }
            }
        }
    }

    /// `b -= W_p x` (the dense form in the order of nalgebra's `gemv`: column by column).
    fn sub_times(&self, p: usize, x: &Vector3<f64>, b: &mut DVector<f64>) {
        match self {
            PointBlocks::Dense(w) => {
                let Some([w0, w1, w2]) = point_columns(w.as_slice(), w.nrows(), p) else { return };
                for (((bi, a0), a1), a2) in b.iter_mut().zip(w0).zip(w1).zip(w2) {
                    *bi -= a0 * x[0];
                    *bi -= a1 * x[1];
                    *bi -= a2 * x[2];
                }
            }
            PointBlocks::Sparse(structure, values) => {
                for (a, row) in structure.block(values, p) {
                    b[a] -= row.dot(&x.transpose());
                }
            }
        }
    }

    /// `W_p^T x`.
    fn tr_mul(&self, p: usize, x: &DVector<f64>) -> Vector3<f64> {
        match self {
            PointBlocks::Dense(w) => w.fixed_columns::<3>(3 * p).tr_mul(x),
            PointBlocks::Sparse(structure, values) => {
                structure.block(values, p).map(|(a, row)| row.transpose() * x[a]).sum()
            }
        }
    }

    /// `W_p m` as a dense `c x 3` matrix (`c` camera parameters).
    pub(super) fn times(&self, p: usize, m: &Matrix3<f64>, nc: usize) -> OMatrix<f64, Dyn, U3> {
        match self {
            PointBlocks::Dense(w) => w.fixed_columns::<3>(3 * p) * m,
            PointBlocks::Sparse(structure, values) => {
                let mut out = OMatrix::<f64, Dyn, U3>::zeros(nc);
                for (a, row) in structure.block(values, p) {
                    out.set_row(a, &(row * m));
                }
                out
            }
        }
    }
}

/// The camera-parameter Jacobian of the observations of one (view, side) pair: their
/// parameter indices in column order and the rows of `sqrt(w) J`, row-major (two per
/// observation); `used` once an observation of the current linearisation filled it.
#[derive(Default)]
struct CameraBlock {
    idx: Vec<usize>,
    rows: Vec<f64>,
    used: bool,
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
    let mut work = n.work.borrow_mut();
    reduce(n, damp, skip_singular, &mut work)?;
    Some((std::mem::replace(&mut work.s, DMatrix::zeros(0, 0)), std::mem::take(&mut work.l_inv)))
}

/// [`reduced_camera_system`] into `work.s` and `work.l_inv`.
fn reduce(n: &Normal, damp: impl Fn(f64) -> f64, skip_singular: bool, work: &mut Workspace) -> Option<()> {
    let Workspace { m, s, l_inv, .. } = work;
    let nc = n.u.nrows();
    if s.shape() == n.u.shape() {
        s.copy_from(&n.u);
    } else {
        *s = n.u.clone();
    }
    for i in 0..nc {
        s[(i, i)] += damp(n.u[(i, i)]);
    }
    l_inv.clear();
    let w = match &n.w {
        PointBlocks::Dense(w) => w,
        PointBlocks::Sparse(structure, values) => {
            return schur(&n.v, structure, values, s, &damp, skip_singular, l_inv);
        }
    };
    let len = nc * w.ncols();
    if m.len() < len {
        m.resize(len, 0.0);
    }
    for (p, v) in n.v.iter().enumerate() {
        let mp = m.get_mut(3 * p * nc..3 * (p + 1) * nc)?;
        let mut vd = *v;
        for i in 0..3 {
            vd[(i, i)] += damp(v[(i, i)]);
        }
        let Some(li) = vd.cholesky().and_then(|ch| ch.l().try_inverse()) else {
            if skip_singular {
                mp.fill(0.0);
                l_inv.push(None);
                continue;
            }
            return None;
        };
        point_times(point_columns(w.as_slice(), nc, p)?, &li.transpose(), mp);
        l_inv.push(Some(li));
    }
    if len > 0 {
        // S -= M M^T, M^T a strided view of M.
        let mm = DMatrixView::from_slice(&m[..len], nc, w.ncols());
        let mt = DMatrixView::from_slice_with_strides(&m[..len], w.ncols(), nc, nc, 1);
        s.gemm(-1.0, &mm, &mt, 1.0);
    }
    // (S + S^T) / 2 in place: each pair's mean, the same sum both ways.
    for j in 0..nc {
        for i in j..nc {
            let mean = 0.5 * (s[(i, j)] + s[(j, i)]);
            s[(i, j)] = mean;
            s[(j, i)] = mean;
        }
    }
    Some(())
}

/// `out = W_p t` for a point's 3 columns `w` of `c` rows each (`out` column-major `c x
/// 3`), column by column in the order of nalgebra's `gemm` of a `c x 3` by a 3x3 matrix
/// (per entry `w_0 t_0j + w_1 t_1j + w_2 t_2j`, left to right).
fn point_times(w: [&[f64]; 3], t: &Matrix3<f64>, out: &mut [f64]) {
    let c = w[0].len();
    for (j, col) in out.chunks_exact_mut(c.max(1)).take(3).enumerate() {
        let (t0, t1, t2) = (t[(0, j)], t[(1, j)], t[(2, j)]);
        for (((o, a0), a1), a2) in col.iter_mut().zip(w[0]).zip(w[1]).zip(w[2]) {
            *o = a0 * t0 + a1 * t1 + a2 * t2;
        }
    }
}

/// The factored damped system of one solve: the Cholesky factor of `S` (dense or
/// profile); the points' `V_p^-1` are in the workspace.
enum Factor {
    Dense(Cholesky<f64, Dyn>),
    Profile(ProfileCholesky),
}

impl Factor {
    /// `S^-1 b`.
    fn solve(&self, b: &DVector<f64>) -> DVector<f64> {
        match self {
            Factor::Dense(ch) => ch.solve(b),
            Factor::Profile(f) => f.solve(b),
        }
    }

    /// Give the factor's storage back to `work`.
    fn release(self, work: &mut Workspace) {
        match self {
            Factor::Dense(ch) => work.s = ch.unpack_dirty(),
            Factor::Profile(f) => work.profile = f.into_storage(),
        }
    }
}

/// Form and factor the system of `n` damped by `lambda` ([`reduce`]); the points'
/// `V_p^-1` into `work.v_inv`. `None` if a damped block or `S` is not positive definite.
fn factor(n: &Normal, lambda: f64, work: &mut Workspace) -> Option<Factor> {
    reduce(n, |d| lambda * damping_diagonal(d), false, work)?;
    // V_p^-1 = L_p^-T L_p^-1.
    work.v_inv.clear();
    for li in &work.l_inv {
        let li = (*li)?;
        work.v_inv.push(li.transpose() * li);
    }
    match &n.w {
        PointBlocks::Dense(_) => {
            std::mem::replace(&mut work.s, DMatrix::zeros(0, 0)).cholesky().map(Factor::Dense)
        }
        PointBlocks::Sparse(..) => {
            let storage = std::mem::take(&mut work.profile);
            ProfileCholesky::new_in(&work.s, n.order.clone()?, storage).map(Factor::Profile)
        }
    }
}

/// The step of the factored system `f` (points' `V_p^-1` in `v_inv`) for the right-hand
/// side `(rc, rp)`: the camera step from `S`, then each point's by back-substitution.
fn back_substitute(
    n: &Normal,
    f: &Factor,
    v_inv: &[Matrix3<f64>],
    rc: &DVector<f64>,
    rp: &[Vector3<f64>],
) -> Option<(DVector<f64>, Vec<Vector3<f64>>)> {
    let mut b = rc.clone();
    for (p, (vi, g)) in v_inv.iter().zip(rp).enumerate() {
        n.w.sub_times(p, &(vi * g), &mut b);
    }
    let dc = f.solve(&b);
    if !dc.iter().all(|v| v.is_finite()) {
        return None;
    }
    let dp = v_inv.iter().zip(rp).enumerate().map(|(p, (vi, g))| vi * (g - n.w.tr_mul(p, &dc))).collect();
    Some((dc, dp))
}

/// Solve the damped normal equations by the Schur complement over the points; with a
/// depth-scale pseudo-residual `r_s` (Jacobian `a`, points only) the normal matrix gains
/// the dense rank-one term `a a^T` and the gradient `a r_s`, solved by Sherman-Morrison:
/// `x = y - z (a.y) / (1 + a.z)` with `N y = -g - a r_s`, `N z = a` (one factorisation
/// of `N` for both).
pub(super) fn solve(n: &Normal, lambda: f64) -> Option<(DVector<f64>, Vec<Vector3<f64>>)> {
    let mut work = n.work.borrow_mut();
    let f = factor(n, lambda, &mut work)?;
    let out = solve_factored(n, &f, &work.v_inv);
    f.release(&mut work);
    out
}

/// [`solve`] with the system factored.
fn solve_factored(
    n: &Normal,
    f: &Factor,
    v_inv: &[Matrix3<f64>],
) -> Option<(DVector<f64>, Vec<Vector3<f64>>)> {
    let rc = -&n.gc;
    let Some((a, r)) = &n.depth else {
        let rp: Vec<Vector3<f64>> = n.gp.iter().map(|g| -g).collect();
        return back_substitute(n, f, v_inv, &rc, &rp);
    };
    let rp: Vec<Vector3<f64>> = n.gp.iter().zip(a).map(|(g, ai)| -g - ai * *r).collect();
    let (yc, yp) = back_substitute(n, f, v_inv, &rc, &rp)?;
    let (zc, zp) = back_substitute(n, f, v_inv, &DVector::zeros(rc.len()), a)?;
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

impl Normal {
    /// The point-Schur normal equations of a problem outside the bundle adjustment (the
    /// rig motion, `rigmotion.rs`): the dense camera block `u` and its gradient `gc`, per
    /// point its block `v` and gradient `gp`, and `W` dense (`c x 3n`, point `p` in columns
    /// `3p..3p+3`); no depth-scale row.
    pub(crate) fn from_blocks(
        u: DMatrix<f64>,
        gc: DVector<f64>,
        v: Vec<Matrix3<f64>>,
        gp: Vec<Vector3<f64>>,
        w: DMatrix<f64>,
    ) -> Normal {
        Normal {
            u,
            gc,
            v,
            gp,
            w: PointBlocks::Dense(w),
            sum_wsq: 0.0,
            depth: None,
            order: None,
            blocks: Vec::new(),
            work: RefCell::default(),
        }
    }

    /// The undamped reduced camera system `S = U - W V^-1 W^T`; `None` if a point block
    /// is not positive definite.
    pub(crate) fn reduced_undamped(&self) -> Option<DMatrix<f64>> {
        reduced_camera_system(self, |_| 0.0, false).map(|(s, _)| s)
    }
}

/// The point-Schur back end of [`crate::lm`]: [`solve`] and [`predicted_decrease`].
impl crate::lm::Linearisation for Normal {
    type Step = (DVector<f64>, Vec<Vector3<f64>>);

    fn solve(&self, lambda: f64) -> Option<Self::Step> {
        solve(self, lambda)
    }

    fn predicted_decrease(&self, lambda: f64, step: &Self::Step) -> f64 {
        predicted_decrease(self, lambda, &step.0, &step.1)
    }
}

/// Solve the damped normal equations `N_lambda (dc, dp) = (rc, rp)` (data and priors
/// only) by the Schur complement over the points.
pub(super) fn solve_rhs(
    n: &Normal,
    lambda: f64,
    rc: &DVector<f64>,
    rp: &[Vector3<f64>],
) -> Option<(DVector<f64>, Vec<Vector3<f64>>)> {
    let mut work = n.work.borrow_mut();
    let f = factor(n, lambda, &mut work)?;
    let out = back_substitute(n, &f, &work.v_inv, rc, rp);
    f.release(&mut work);
    out
}

#[cfg(test)]
mod tests {
    use super::super::covariance::{CovarianceModel, covariance};
    use super::super::problem::problem;
    use super::*;
    use crate::bundle::{BundleOptions, Motions, RobustLoss};
    use crate::synthetic::{perturb, sequence};

    /// The two back ends of [`crate::lm`] give the same step: on a small bundle (2 views,
    /// 25 points, 0.5 px noise, from a perturbed start) the point-Schur back end's damped
    /// step and predicted decrease equal the dense back end's ([`crate::lm::DenseDyn`] on
    /// the whole normal matrix `[[U, W], [W^T, V]]`, 6 + 75 + camera unknowns) to 1e-9
    /// relative (rounding, amplified by the conditioning of the reduced system), at a small
    /// and a large damping.
    #[test]
    fn schur_and_dense_back_ends_give_the_same_step() {
        use crate::lm::{DenseDyn, Linearisation};
        let s = crate::synthetic::synth(3, 25, 0.5, 0.0, false);
        let start = perturb(&s.truth, 7);
        let options = BundleOptions { robust: RobustLoss::None, ..BundleOptions::default() };
        let (state, problem) = problem(&start, &s.obs, &options).unwrap();
        let n = problem.normal_equations(&state, problem.prior_weight).unwrap();
        let PointBlocks::Dense(w) = &n.w else { panic!("a 2-view problem keeps W dense") };
        let (nc, np) = (n.u.nrows(), n.v.len());
        let mut jtj = DMatrix::zeros(nc + 3 * np, nc + 3 * np);
        let mut jtr = DVector::zeros(nc + 3 * np);
        jtj.view_mut((0, 0), (nc, nc)).copy_from(&n.u);
        jtj.view_mut((0, nc), (nc, 3 * np)).copy_from(w);
        jtj.view_mut((nc, 0), (3 * np, nc)).copy_from(&w.transpose());
        jtr.rows_mut(0, nc).copy_from(&n.gc);
        for p in 0..np {
            jtj.view_mut((nc + 3 * p, nc + 3 * p), (3, 3)).copy_from(&n.v[p]);
            jtr.rows_mut(nc + 3 * p, 3).copy_from(&n.gp[p]);
        }
        let dense = DenseDyn { jtj, jtr };
        for lambda in [1e-6, 1e-1] {
            let (dc, dp) = Linearisation::solve(&n, lambda).unwrap();
            let mut schur = dc.clone().resize_vertically(nc + 3 * np, 0.0);
            for (p, d) in dp.iter().enumerate() {
                schur.rows_mut(nc + 3 * p, 3).copy_from(d);
            }
            let step = dense.solve(lambda).unwrap();
            assert!(
                (&step - &schur).norm() < 1e-9 * step.norm(),
                "lambda {lambda}: {:e}",
                (&step - &schur).norm()
            );
            let (a, b) = (n.predicted_decrease(lambda, &(dc, dp)), dense.predicted_decrease(lambda, &step));
            assert!((a - b).abs() < 1e-9 * b.abs(), "lambda {lambda}: {a} {b}");
        }
    }

    /// The sparse Schur complement is the dense one with other summation orders: on a
    /// 24-view sequence in two segments (noisy, from a perturbed start) the damped steps
    /// and the covariance agree to 1e-9 relative (rounding, amplified by the conditioning
    /// of the reduced system).
    #[test]
    fn sparse_and_dense_schur_agree() {
        let seq = sequence(3, 24, 2, 300, 0.5);
        let mut start = perturb(&seq.synth.truth, 4);
        if let Motions::Free { ref_from_cam } = &mut start.motions {
            for &g in &seq.gauge_views {
                ref_from_cam[g] = nalgebra::Isometry3::identity();
            }
        }
        let options = BundleOptions {
            gauge_views: seq.gauge_views.clone(),
            robust: RobustLoss::None,
            ..Default::default()
        };
        let (state, mut p) = problem(&start, &seq.synth.obs, &options).unwrap();
        assert!(p.sparse, "24 views take the sparse path");
        let sparse = p.normal_equations(&state, 1.0).unwrap();
        let (cov_sparse, _) = covariance(&p, &state, 0.5, CovarianceModel::PointClustered, None).unwrap();
        p.sparse = false;
        let dense = p.normal_equations(&state, 1.0).unwrap();
        let (cov_dense, _) = covariance(&p, &state, 0.5, CovarianceModel::PointClustered, None).unwrap();
        assert!(matches!(dense.w, PointBlocks::Dense(_)) && matches!(sparse.w, PointBlocks::Sparse(..)));
        let rel = |a: &DVector<f64>, b: &DVector<f64>| (a - b).norm() / b.norm();
        for lambda in [1e-3, 1.0] {
            let (dc_s, dp_s) = solve(&sparse, lambda).unwrap();
            let (dc_d, dp_d) = solve(&dense, lambda).unwrap();
            assert!(rel(&dc_s, &dc_d) < 1e-9, "camera step {:e}", rel(&dc_s, &dc_d));
            let worst =
                dp_s.iter().zip(&dp_d).map(|(a, b)| (a - b).norm() / b.norm().max(1e-12)).fold(0.0, f64::max);
            assert!(worst < 1e-9, "point step {worst:e}");
        }
        let cov_rel = (&cov_sparse.matrix - &cov_dense.matrix).norm() / cov_dense.matrix.norm();
        assert!(cov_rel < 1e-9, "covariance {cov_rel:e}");
    }
}
