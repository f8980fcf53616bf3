//! The sparse form of the reduced camera system, for problems of many views (a sequence's
//! keyframes; module docs of [`crate::bundle`], section Algorithm): the off-diagonal
//! blocks `W_p` kept per point over its own rows, the Schur complement formed point by
//! point, and the reduced system `S` factored by a profile (envelope) Cholesky in an order
//! that puts the per-view parameters first and the shared ones last.
//!
//! # What it computes
//!
//! - [`SparseStructure`]: per point, the camera parameters its observations depend on
//!   (the shared ones of its cameras and 6 per view that sees it), and per observation
//!   where each of its Jacobian's columns lands among them; found once per problem from
//!   the column lists of the linearisation (which depend on the layout, the view and the
//!   camera only).
//! - [`schur`]: `S -= M_p M_p^T` with `M_p = W_p L_p^-T` over the point's rows only:
//!   `k^2` per point for `k` rows, against `c^2` for the dense product (`c` all camera
//!   parameters, growing with the views).
//! - [`ProfileCholesky`]: `S = L L^T` in the permuted order (per-view parameters by view,
//!   then the shared ones): row `i` of `L` is non-zero only from the first non-zero column
//!   of row `i` of `S` on (fill-in stays inside the envelope; George and Liu, "Computer
//!   solution of large sparse positive definite systems", 1981, chapter 4). Views that
//!   share points lie within a few views of each other along a sequence, so the envelope
//!   is a band of some `6 b` columns plus the full rows of the `g` shared parameters:
//!   `O(c (6b)^2 + g^2 c)` to factor, linear in the views, where the dense factor is cubic.
//!   Its solves and the inverse (for the covariance, by columns) use the same envelope.
//!
//! Units: those of the normal equations (pixels and the parameters' units).
//!
//! # Pitfalls
//!
//! - The envelope is found from the exact zeros of `S`: entries of camera parameters that
//!   no point couples are never written, so they stay exactly zero.
//! - Views far apart in the layout that share points (a loop closure, a view and the
//!   segment gauge it was chained from) widen the envelope of every row between them; the
//!   factor stays correct, only slower.
//! - The sums run in another order than the dense path's, so the results agree with it to
//!   rounding only (`normal.rs` keeps the dense path for few views).
//! - `S` itself (and `U`, and the factor) is stored dense: `c^2` doubles, 11.5 MB at 1200
//!   camera parameters (200 keyframes), and the covariance's inverse costs `c^2` solves'
//!   worth; both start to show beyond a few hundred keyframes.

use nalgebra::{DMatrix, DVector, Matrix3, RowVector3};

use super::layout::{Layout, Param};

/// Where each point's rows and each observation's Jacobian columns sit in the flat
/// storage of the sparse `W` (module docs).
#[derive(Debug)]
pub(super) struct SparseStructure {
    /// Per point, its rows' range in `rows` (`point_start[p]..point_start[p + 1]`).
    point_start: Vec<usize>,
    /// Camera-parameter index of each row, ascending within a point.
    rows: Vec<usize>,
    /// Per observation, the range of its columns in `slots`.
    obs_start: Vec<usize>,
    /// For each column of each observation's Jacobian (in its order), the row it adds to.
    slots: Vec<usize>,
}

impl SparseStructure {
    /// The structure of observations given as `(point, column indices)` in order, over
    /// `points` points.
    pub(super) fn new(points: usize, observations: &[(usize, Vec<usize>)]) -> Option<Self> {
        let mut per_point: Vec<Vec<usize>> = vec![Vec::new(); points];
        for (p, cols) in observations {
            per_point.get_mut(*p)?.extend_from_slice(cols);
        }
        let mut point_start = Vec::with_capacity(points + 1);
        let mut rows = Vec::new();
        for list in &mut per_point {
            list.sort_unstable();
            list.dedup();
            point_start.push(rows.len());
            rows.extend_from_slice(list);
        }
        point_start.push(rows.len());
        let mut obs_start = Vec::with_capacity(observations.len() + 1);
        let mut slots = Vec::new();
        for (p, cols) in observations {
            obs_start.push(slots.len());
            let (a, b) = (*point_start.get(*p)?, *point_start.get(p + 1)?);
            for c in cols {
                slots.push(a + rows[a..b].binary_search(c).ok()?);
            }
        }
        obs_start.push(slots.len());
        Some(Self { point_start, rows, obs_start, slots })
    }

    /// The number of slots (rows of `W` over all points).
    pub(super) fn slot_count(&self) -> usize {
        self.rows.len()
    }

    /// Storage for the values of `W` (one 3-vector row per slot), zero.
    pub(super) fn zeros(&self) -> Vec<RowVector3<f64>> {
        vec![RowVector3::zeros(); self.rows.len()]
    }

    /// The slots of the columns of observation `obs`'s Jacobian, in their order.
    pub(super) fn slots(&self, obs: usize) -> &[usize] {
        match (self.obs_start.get(obs), self.obs_start.get(obs + 1)) {
            (Some(&a), Some(&b)) => &self.slots[a..b],
            _ => &[],
        }
    }

    /// Point `p`'s rows and their values in `w`.
    pub(super) fn block<'a>(
        &'a self,
        w: &'a [RowVector3<f64>],
        p: usize,
    ) -> impl Iterator<Item = (usize, &'a RowVector3<f64>)> + 'a {
        let (a, b) = match (self.point_start.get(p), self.point_start.get(p + 1)) {
            (Some(&a), Some(&b)) => (a, b),
            _ => (0, 0),
        };
        self.rows[a..b].iter().copied().zip(&w[a..b])
    }
}

/// `s -= M_p M_p^T` (`M_p = W_p L_p^-T`) over every point (module docs), each point's
/// `V_p` damped by `damp` of its diagonal; the points' `L_p^-1` into `l_inv` (cleared
/// first), `None` for a block that is not positive definite (skipped when
/// `skip_singular`, otherwise the whole result is `None`). The products go to the lower
/// triangle, which then replaces the upper one: `s` comes out exactly symmetric (its upper
/// triangle was `U`'s, symmetric too).
pub(super) fn schur(
    v: &[Matrix3<f64>],
    structure: &SparseStructure,
    w: &[RowVector3<f64>],
    s: &mut DMatrix<f64>,
    damp: &impl Fn(f64) -> f64,
    skip_singular: bool,
    l_inv: &mut Vec<Option<Matrix3<f64>>>,
) -> Option<()> {
    l_inv.clear();
    let mut m: Vec<(usize, RowVector3<f64>)> = Vec::new();
    for (p, vp) in v.iter().enumerate() {
        let mut vd = *vp;
        for i in 0..3 {
            vd[(i, i)] += damp(vp[(i, i)]);
        }
        let Some(li) = vd.cholesky().and_then(|ch| ch.l().try_inverse()) else {
            if skip_singular {
                l_inv.push(None);
                continue;
            }
            return None;
        };
        let lt = li.transpose();
        m.clear();
        m.extend(structure.block(w, p).map(|(a, row)| (a, row * lt)));
        // Rows ascend, so (a, b) with b <= a is in the lower triangle.
        for (i, (a, ma)) in m.iter().enumerate() {
            for (b, mb) in &m[..=i] {
                s[(*a, *b)] -= ma.dot(mb);
            }
        }
        l_inv.push(Some(li));
    }
    let n = s.nrows();
    for j in 0..n {
        for i in j + 1..n {
            s[(j, i)] = s[(i, j)];
        }
    }
    Some(())
}

/// The order of the profile factor (module docs): the per-view parameters of `layout`
/// in their order, then the shared ones.
pub(super) fn view_first_order(layout: &Layout) -> Vec<usize> {
    let per_view = |p: &Param| matches!(p, Param::ViewRot(..) | Param::ViewTrans(..) | Param::Angle(..));
    let views = layout.params.iter().enumerate().filter(|(_, p)| per_view(p)).map(|(i, _)| i);
    let shared = layout.params.iter().enumerate().filter(|(_, p)| !per_view(p)).map(|(i, _)| i);
    views.chain(shared).collect()
}

/// The Cholesky factor `P S P^T = L L^T` within the envelope of `P S P^T` (module docs).
pub(super) struct ProfileCholesky {
    /// `perm[i]`: the original index of position `i`.
    perm: Vec<usize>,
    /// First non-zero column of each row of `L`.
    first: Vec<usize>,
    /// `L`, row-major `n x n` (only the envelope is written and read; the rest may hold
    /// an earlier factor's values).
    l: Vec<f64>,
    n: usize,
}

impl ProfileCholesky {
    /// Factor the symmetric `s` in the order `perm`; `None` if it is not positive definite
    /// (or `perm` is not a permutation of its rows).
    pub(super) fn new(s: &DMatrix<f64>, perm: Vec<usize>) -> Option<Self> {
        Self::new_in(s, perm, Vec::new())
    }

    /// [`Self::new`] in `storage` (of an earlier factor, [`Self::into_storage`]): only the
    /// envelope of the factor is written, and only the envelope is ever read, so the
    /// storage needs no zeroing.
    pub(super) fn new_in(s: &DMatrix<f64>, perm: Vec<usize>, storage: Vec<f64>) -> Option<Self> {
        let n = s.nrows();
        let mut seen = vec![false; n];
        for &i in &perm {
            if std::mem::replace(seen.get_mut(i)?, true) {
                return None;
            }
        }
        if perm.len() != n || s.ncols() != n {
            return None;
        }
        let mut l = storage;
        l.resize(n * n, 0.0);
        let mut first = vec![0; n];
        for i in 0..n {
            let pi = perm[i];
            first[i] = (0..=i).find(|&j| s[(pi, perm[j])] != 0.0).unwrap_or(i);
            for j in first[i]..=i {
                let k0 = first[i].max(first[j]);
                let (ri, rj) = (&l[i * n..i * n + j], &l[j * n..j * n + j]);
                let dot: f64 = ri[k0..].iter().zip(&rj[k0..]).map(|(a, b)| a * b).sum();
                let value = s[(pi, perm[j])] - dot;
                if j == i {
                    if !(value > 0.0 && value.is_finite()) {
                        return None;
                    }
                    l[i * n + i] = value.sqrt();
                } else {
                    l[i * n + j] = value / l[j * n + j];
                }
            }
        }
        Some(Self { perm, first, l, n })
    }

    /// `S^-1 b`.
    pub(super) fn solve(&self, b: &DVector<f64>) -> DVector<f64> {
        let n = self.n;
        let mut y: Vec<f64> = self.perm.iter().map(|&i| b[i]).collect();
        for i in 0..n {
            let row = &self.l[i * n..i * n + i];
            let dot: f64 = row[self.first[i]..].iter().zip(&y[self.first[i]..i]).map(|(a, b)| a * b).sum();
            y[i] = (y[i] - dot) / self.l[i * n + i];
        }
        for i in (0..n).rev() {
            y[i] /= self.l[i * n + i];
            let xi = y[i];
            let row = &self.l[i * n + self.first[i]..i * n + i];
            for (yk, lik) in y[self.first[i]..i].iter_mut().zip(row) {
                *yk -= lik * xi;
            }
        }
        let mut out = DVector::zeros(n);
        for (i, &p) in self.perm.iter().enumerate() {
            out[p] = y[i];
        }
        out
    }

    /// The factor's storage, for [`Self::new_in`].
    pub(super) fn into_storage(self) -> Vec<f64> {
        self.l
    }

    /// `S^-1`, column by column.
    pub(super) fn inverse(&self) -> DMatrix<f64> {
        let mut inv = DMatrix::zeros(self.n, self.n);
        let mut e = DVector::zeros(self.n);
        for j in 0..self.n {
            e[j] = 1.0;
            inv.set_column(j, &self.solve(&e));
            e[j] = 0.0;
        }
        inv
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The profile factor solves and inverts like the dense Cholesky: a band matrix with a
    /// dense border (the shape of a sequence's reduced system), in a scrambled order;
    /// 1e-12 relative (rounding of a well-conditioned 40 x 40 system).
    #[test]
    fn profile_cholesky_matches_dense() {
        let n = 40;
        let mut a = DMatrix::<f64>::zeros(n, n);
        for i in 0..n {
            for j in 0..n {
                let band = i.abs_diff(j) <= 3;
                let border = i < 4 || j < 4;
                if band || border {
                    a[(i, j)] = 1.0 / (1.0 + (i + 2 * j) as f64 % 7.0) + if i == j { 20.0 } else { 0.0 };
                }
            }
        }
        let a = 0.5 * (&a + a.transpose());
        let perm: Vec<usize> = (4..n).chain(0..4).collect();
        let f = ProfileCholesky::new(&a, perm).unwrap();
        let b = DVector::from_fn(n, |i, _| (i as f64).sin());
        let dense = a.clone().cholesky().unwrap();
        let rel = |x: &DVector<f64>, y: &DVector<f64>| (x - y).norm() / y.norm();
        assert!(rel(&f.solve(&b), &dense.solve(&b)) < 1e-12);
        let inv = f.inverse();
        assert!((&inv - dense.inverse()).norm() / inv.norm() < 1e-12);
        // Not positive definite: no factor.
        let mut bad = a.clone();
        bad[(10, 10)] = -1.0;
        assert!(ProfileCholesky::new(&bad, (0..n).collect()).is_none());
        assert!(ProfileCholesky::new(&a, vec![0; n]).is_none());
    }
}
