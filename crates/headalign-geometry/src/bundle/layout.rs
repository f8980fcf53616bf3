//! The parametrisation of the rig bundle adjustment: which camera (non-point) parameters
//! are free, where each sits in the camera-parameter vector, and how a tangent step moves
//! a state (module docs of [`crate::bundle`], section Parameters and degrees of freedom).
//!
//! # What it computes
//!
//! - `Layout::build` lists the free camera parameters in their fixed order, with the
//!   names of [`Covariance::names`] (`Param::name`,
//!   `Param::parse`): per camera `fx fy skew cx cy` (pixels; `fy` absent with square
//!   pixels, skew absent with zero skew, `cx cy` absent with a fixed principal point) and
//!   the estimated distortion coefficients (dimensionless; `k1 k2` by default, see
//!   `BundleOptions::distortion_terms`); `rig.rot0..2` (radians) and `rig.tdir0..1`
//!   (the baseline direction's tangent, radians to first order); then `view{k}.rot0..2`,
//!   `view{k}.trans0..2` for a free view `k >= 1` (radians, baseline units), or
//!   `axis{j}.dir0..1`, `axis{j}.pt0..1` per joint axis (radians, baseline units) and
//!   `view{k}.angle{j}` with an angle prior (radians).
//! - `retract` applies a step over those parameters: additive for intrinsics, distortion
//!   and angles; `R <- exp(w) R` for the rig rotation (left-multiplicative, `so3::exp`,
//!   safe at zero); `t <- |t| normalize(t/|t| + B d)` for the baseline (its length is held:
//!   the scale gauge); an axis's direction on the sphere and its foot point in the plane
//!   perpendicular to it, both by the tangent basis `B`; `ref_from_cam <- (exp(w), v)
//!   ref_from_cam` for a free view. `local` is its inverse, the step between two states
//!   ([`BundleResult::tangent_offset`]).
//! - `retract_point`: a point (3 dof) moves on the unit sphere of homogeneous 4-vectors,
//!   `h <- normalize(h + B d)` with `B` a Householder basis of the tangent space (Triggs,
//!   McLauchlan, Hartley, Fitzgibbon, "Bundle adjustment - a modern synthesis", 2000,
//!   section 2.2): depth along a ray then enters the disparity nearly linearly, which
//!   keeps Gauss-Newton steps good for far points.
//!
//! # Pitfalls
//!
//! - The order of the parameters is an interface: covariance matrices, the deltas of
//!   `perturbed` and the names held by `bundle_adjust_holding` all follow it.
//! - With square pixels `fy` has no slot and follows `fx` (`Layout::square`); a held `fy`
//!   is not such a tie (the solver keeps the options' tie flags when it removes held
//!   parameters).
//! - `local` inverts `retract` only for rotations that differ by less than pi and
//!   directions in the same half-space (the ends of the tangent charts); a baseline or
//!   axis direction turned by 90 deg or more is an error.
//! - The tangent updates never flip an axis: `(-a, -theta)` is the same motion but lies in
//!   another chart.
//!
//! [`Covariance::names`]: super::Covariance::names
//! [`BundleResult::tangent_offset`]: super::BundleResult::tangent_offset

use nalgebra::{DVector, Isometry3, Matrix3x2, Point3, Translation3, Unit, UnitQuaternion, Vector2, Vector3};

use super::gt;
use super::state::{BundleOptions, Motions, RigState, Side};
use crate::camera::Intrinsics;
use crate::distortion::LensKind;
use crate::lens::MAX_PARAMS;
use crate::so3::{self, Line};
use crate::{GeometryError, Result};

const INTR_NAMES: [&str; 5] = ["fx", "fy", "skew", "cx", "cy"];

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Param {
    Intr(Side, usize),
    /// Lens parameter `i` of the camera's model, in the model's order (its row of the lens
    /// table, `crate::lens`, names it).
    Dist(Side, LensKind, usize),
    RigRot(usize),
    RigTdir(usize),
    AxisDir(usize, usize),
    AxisPt(usize, usize),
    /// (view, axis)
    Angle(usize, usize),
    ViewRot(usize, usize),
    ViewTrans(usize, usize),
}

impl Param {
    pub(super) fn name(&self) -> String {
        match *self {
            Param::Intr(side, i) => {
                let s = if side == Side::Left { "left" } else { "right" };
                format!("{s}.{}", INTR_NAMES.get(i).copied().unwrap_or("?"))
            }
            Param::Dist(side, kind, i) => {
                let s = if side == Side::Left { "left" } else { "right" };
                format!("{s}.{}", kind.coefficient_names().get(i).copied().unwrap_or("?"))
            }
            Param::RigRot(i) => format!("rig.rot{i}"),
            Param::RigTdir(i) => format!("rig.tdir{i}"),
            Param::AxisDir(j, i) => format!("axis{j}.dir{i}"),
            Param::AxisPt(j, i) => format!("axis{j}.pt{i}"),
            Param::Angle(k, j) => format!("view{k}.angle{j}"),
            Param::ViewRot(k, i) => format!("view{k}.rot{i}"),
            Param::ViewTrans(k, i) => format!("view{k}.trans{i}"),
        }
    }

    /// The parameter named `name` in `state` (a lens parameter by the name its camera's
    /// model gives it).
    pub(super) fn parse(name: &str, state: &RigState) -> Option<Param> {
        let (head, tail) = name.split_once('.')?;
        let num = |prefix: &str| tail.strip_prefix(prefix).and_then(|s| s.parse::<usize>().ok());
        match head {
            "left" | "right" => {
                let side = if head == "left" { Side::Left } else { Side::Right };
                INTR_NAMES.iter().position(|n| *n == tail).map(|i| Param::Intr(side, i)).or_else(|| {
                    let kind = state.distortion(side).kind;
                    kind.coefficient_names()
                        .iter()
                        .position(|n| *n == tail)
                        .map(|i| Param::Dist(side, kind, i))
                })
            }
            "rig" => num("rot").map(Param::RigRot).or_else(|| num("tdir").map(Param::RigTdir)),
            _ => {
                if let Some(j) = head.strip_prefix("axis").and_then(|s| s.parse::<usize>().ok()) {
                    num("dir")
                        .map(|i| Param::AxisDir(j, i))
                        .or_else(|| num("pt").map(|i| Param::AxisPt(j, i)))
                } else if let Some(k) = head.strip_prefix("view").and_then(|s| s.parse::<usize>().ok()) {
                    num("angle")
                        .map(|j| Param::Angle(k, j))
                        .or_else(|| num("rot").map(|i| Param::ViewRot(k, i)))
                        .or_else(|| num("trans").map(|i| Param::ViewTrans(k, i)))
                } else {
                    None
                }
            }
        }
    }
}

/// Where each parameter sits in the camera-parameter vector.
#[derive(Clone, Debug)]
pub(super) struct Layout {
    pub(super) params: Vec<Param>,
    pub(super) intr: [[Option<usize>; 5]; 2],
    pub(super) dist: [[Option<usize>; MAX_PARAMS]; 2],
    pub(super) square: [bool; 2],
    pub(super) rig_rot: [Option<usize>; 3],
    pub(super) rig_tdir: [Option<usize>; 2],
    pub(super) axis_dir: Vec<[Option<usize>; 2]>,
    pub(super) axis_pt: Vec<[Option<usize>; 2]>,
    pub(super) angle: Vec<Vec<Option<usize>>>,
    pub(super) view_rot: Vec<[Option<usize>; 3]>,
    pub(super) view_trans: Vec<[Option<usize>; 3]>,
}

pub(super) fn side_index(s: Side) -> usize {
    match s {
        Side::Left => 0,
        Side::Right => 1,
    }
}

impl Layout {
    pub(super) fn build(state: &RigState, options: &BundleOptions) -> Result<Self> {
        let mut p = Vec::new();
        for side in [Side::Left, Side::Right] {
            p.push(Param::Intr(side, 0));
            if !options.square_pixels {
                p.push(Param::Intr(side, 1));
            }
            if !options.zero_skew {
                p.push(Param::Intr(side, 2));
            }
            if !options.fix_principal_point {
                p.push(Param::Intr(side, 3));
                p.push(Param::Intr(side, 4));
            }
            if options.estimate_distortion {
                let kind = state.distortion(side).kind;
                p.extend(options.distortion_terms.params(kind).iter().map(|&i| Param::Dist(side, kind, i)));
            }
        }
        p.extend((0..3).map(Param::RigRot));
        p.extend((0..2).map(Param::RigTdir));
        let v = state.motions.view_count();
        match &state.motions {
            Motions::Free { .. } => {
                for k in (1..v).filter(|k| !options.gauge_views.contains(k)) {
                    p.extend((0..3).map(|i| Param::ViewRot(k, i)));
                    p.extend((0..3).map(|i| Param::ViewTrans(k, i)));
                }
            }
            Motions::Joints { axes, .. } => {
                for j in 0..axes.len() {
                    p.extend((0..2).map(|i| Param::AxisDir(j, i)));
                    p.extend((0..2).map(|i| Param::AxisPt(j, i)));
                }
                if options.angle_prior_sigma.is_some() {
                    for k in 1..v {
                        p.extend((0..axes.len()).map(|j| Param::Angle(k, j)));
                    }
                }
            }
        }
        Self::from_params(p, &state.motions)
    }

    pub(super) fn from_params(params: Vec<Param>, motions: &Motions) -> Result<Self> {
        let n_views = motions.view_count();
        let n_axes = match motions {
            Motions::Joints { axes, .. } => axes.len(),
            Motions::Free { .. } => 0,
        };
        let free = matches!(motions, Motions::Free { .. });
        let mut l = Layout {
            params: Vec::new(),
            intr: [[None; 5]; 2],
            dist: [[None; MAX_PARAMS]; 2],
            square: [false; 2],
            rig_rot: [None; 3],
            rig_tdir: [None; 2],
            axis_dir: vec![[None; 2]; n_axes],
            axis_pt: vec![[None; 2]; n_axes],
            angle: vec![vec![None; n_axes]; n_views],
            view_rot: vec![[None; 3]; n_views],
            view_trans: vec![[None; 3]; n_views],
        };
        let bad = |p: &Param| {
            GeometryError::InvalidOption(format!("parameter {} does not fit the state", p.name()))
        };
        for (idx, p) in params.iter().enumerate() {
            let slot: Option<&mut Option<usize>> = match *p {
                Param::Intr(s, i) => l.intr[side_index(s)].get_mut(i),
                Param::Dist(s, _, i) => l.dist[side_index(s)].get_mut(i),
                Param::RigRot(i) => l.rig_rot.get_mut(i),
                Param::RigTdir(i) => l.rig_tdir.get_mut(i),
                Param::AxisDir(j, i) => l.axis_dir.get_mut(j).and_then(|a| a.get_mut(i)),
                Param::AxisPt(j, i) => l.axis_pt.get_mut(j).and_then(|a| a.get_mut(i)),
                Param::Angle(k, j) if k >= 1 => l.angle.get_mut(k).and_then(|a| a.get_mut(j)),
                Param::ViewRot(k, i) if k >= 1 && free => l.view_rot.get_mut(k).and_then(|a| a.get_mut(i)),
                Param::ViewTrans(k, i) if k >= 1 && free => {
                    l.view_trans.get_mut(k).and_then(|a| a.get_mut(i))
                }
                _ => None,
            };
            match slot {
                Some(s) if s.is_none() => *s = Some(idx),
                _ => return Err(bad(p)),
            }
        }
        for s in 0..2 {
            l.square[s] = l.intr[s][0].is_some() && l.intr[s][1].is_none();
        }
        l.params = params;
        Ok(l)
    }

    pub(super) fn len(&self) -> usize {
        self.params.len()
    }

    pub(super) fn names(&self) -> Vec<String> {
        self.params.iter().map(Param::name).collect()
    }
}

/// Orthonormal basis (3x2) of the plane perpendicular to the unit vector `d`: the basis of
/// the baseline direction's tangent parameters `rig.tdir0..1` (and of an axis direction's).
pub fn tangent_basis(d: &Vector3<f64>) -> Matrix3x2<f64> {
    let a = if d.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
    let b1 = (a - d * d.dot(&a)).normalize();
    let b2 = d.cross(&b1);
    Matrix3x2::from_columns(&[b1, b2])
}

fn quat_exp(w: &Vector3<f64>) -> UnitQuaternion<f64> {
    UnitQuaternion::from_rotation_matrix(&so3::exp(w))
}

fn comp<const N: usize>(idx: &[Option<usize>; N], delta: &DVector<f64>) -> [f64; N] {
    let mut out = [0.0; N];
    for (o, i) in out.iter_mut().zip(idx) {
        if let Some(i) = i {
            *o = delta.get(*i).copied().unwrap_or(0.0);
        }
    }
    out
}

pub(super) fn retract_line(line: &Line, a: [f64; 2], b: [f64; 2]) -> Line {
    let d = line.direction.into_inner();
    let basis = tangent_basis(&d);
    let dir = Unit::new_normalize(d + basis * Vector2::new(a[0], a[1]));
    let pt = line.point + basis * Vector2::new(b[0], b[1]);
    Line::new(dir, pt)
}

/// The state moved by a step over the camera parameters (points unchanged).
pub(super) fn retract(state: &RigState, layout: &Layout, delta: &DVector<f64>) -> Result<RigState> {
    let mut out = state.clone();
    for (s, k) in [(0, &mut out.left), (1, &mut out.right)] {
        let d = comp(&layout.intr[s], delta);
        k.fx += d[0];
        k.fy += d[1];
        k.skew += d[2];
        k.cx += d[3];
        k.cy += d[4];
        if layout.square[s] {
            k.fy = k.fx;
        }
    }
    for (s, d) in [(0, &mut out.left_distortion), (1, &mut out.right_distortion)] {
        let c = comp(&layout.dist[s], delta);
        for (i, step) in c.iter().enumerate() {
            if let Some(v) = d.param_mut(i) {
                *v += step;
            }
        }
    }
    let w = comp(&layout.rig_rot, delta);
    let td = comp(&layout.rig_tdir, delta);
    let t = state.right_from_left.translation.vector;
    let n = t.norm();
    let t_hat = t / n;
    let t_new = (t_hat + tangent_basis(&t_hat) * Vector2::new(td[0], td[1])).normalize() * n;
    out.right_from_left = Isometry3::from_parts(
        Translation3::from(t_new),
        quat_exp(&Vector3::new(w[0], w[1], w[2])) * state.right_from_left.rotation,
    );
    match &mut out.motions {
        Motions::Free { ref_from_cam } => {
            for (k, pose) in ref_from_cam.iter_mut().enumerate() {
                let (Some(ri), Some(ti)) = (layout.view_rot.get(k), layout.view_trans.get(k)) else {
                    continue;
                };
                let w = comp(ri, delta);
                let v = comp(ti, delta);
                let step = Isometry3::from_parts(
                    Translation3::new(v[0], v[1], v[2]),
                    quat_exp(&Vector3::new(w[0], w[1], w[2])),
                );
                *pose = step * *pose;
            }
        }
        Motions::Joints { axes, angles, .. } => {
            for (j, axis) in axes.iter_mut().enumerate() {
                let (Some(di), Some(pi)) = (layout.axis_dir.get(j), layout.axis_pt.get(j)) else {
                    continue;
                };
                *axis = retract_line(axis, comp(di, delta), comp(pi, delta));
            }
            for (k, row) in angles.iter_mut().enumerate() {
                for (j, a) in row.iter_mut().enumerate() {
                    if let Some(Some(i)) = layout.angle.get(k).and_then(|r| r.get(j)) {
                        *a += delta.get(*i).copied().unwrap_or(0.0);
                    }
                }
            }
        }
    }
    Ok(out)
}

/// The inverse of [`retract`]: the step over `params` that moves `from` to `to`.
pub(super) fn local(from: &RigState, to: &RigState, params: &[Param]) -> Result<DVector<f64>> {
    let shape = || GeometryError::InvalidOption("the two states differ in shape".into());
    let line_offset = |a: &Line, b: &Line| -> Option<([f64; 2], [f64; 2])> {
        let d = a.direction.into_inner();
        let e = b.direction.into_inner();
        let basis = tangent_basis(&d);
        let along = d.dot(&e);
        if along <= 0.0 {
            return None;
        }
        let dir = basis.transpose() * e / along;
        // The point of `b` in the plane through `a.point` perpendicular to `d`.
        let s = (a.point - b.point).dot(&d) / along;
        let x = b.point + e * s;
        let pt = basis.transpose() * (x - a.point);
        Some(([dir[0], dir[1]], [pt[0], pt[1]]))
    };
    let t = from.right_from_left.translation.vector;
    let t_hat = t / t.norm();
    let u_hat = to.right_from_left.translation.vector.normalize();
    let along = t_hat.dot(&u_hat);
    let tdir = tangent_basis(&t_hat).transpose() * u_hat / along;
    let rig_rot = so3::log(
        &(to.right_from_left.rotation * from.right_from_left.rotation.inverse()).to_rotation_matrix(),
    );
    let mut out = DVector::zeros(params.len());
    for (o, p) in out.iter_mut().zip(params) {
        *o = match *p {
            Param::Intr(side, i) => {
                let (a, b) =
                    if side == Side::Left { (&from.left, &to.left) } else { (&from.right, &to.right) };
                let f = |k: &Intrinsics| [k.fx, k.fy, k.skew, k.cx, k.cy];
                f(b).get(i).copied().ok_or_else(shape)? - f(a).get(i).copied().ok_or_else(shape)?
            }
            Param::Dist(side, kind, i) => {
                let (a, b) = (from.distortion(side), to.distortion(side));
                if a.kind != kind || b.kind != kind {
                    return Err(shape());
                }
                b.params().get(i).copied().ok_or_else(shape)?
                    - a.params().get(i).copied().ok_or_else(shape)?
            }
            Param::RigRot(i) => rig_rot.get(i).copied().ok_or_else(shape)?,
            Param::RigTdir(i) if along > 0.0 => tdir.get(i).copied().ok_or_else(shape)?,
            Param::RigTdir(_) => return Err(shape()),
            Param::AxisDir(j, i) | Param::AxisPt(j, i) => {
                let (Motions::Joints { axes: a, .. }, Motions::Joints { axes: b, .. }) =
                    (&from.motions, &to.motions)
                else {
                    return Err(shape());
                };
                let (dir, pt) = line_offset(a.get(j).ok_or_else(shape)?, b.get(j).ok_or_else(shape)?)
                    .ok_or_else(shape)?;
                let v = if matches!(p, Param::AxisDir(..)) { dir } else { pt };
                v.get(i).copied().ok_or_else(shape)?
            }
            Param::Angle(k, j) => {
                let (Motions::Joints { angles: a, .. }, Motions::Joints { angles: b, .. }) =
                    (&from.motions, &to.motions)
                else {
                    return Err(shape());
                };
                let get = |m: &Vec<Vec<f64>>| m.get(k).and_then(|r| r.get(j)).copied().ok_or_else(shape);
                get(b)? - get(a)?
            }
            Param::ViewRot(k, i) | Param::ViewTrans(k, i) => {
                let (Motions::Free { ref_from_cam: a }, Motions::Free { ref_from_cam: b }) =
                    (&from.motions, &to.motions)
                else {
                    return Err(shape());
                };
                let step = b.get(k).ok_or_else(shape)? * a.get(k).ok_or_else(shape)?.inverse();
                let v = if matches!(p, Param::ViewRot(..)) {
                    so3::log(&step.rotation.to_rotation_matrix())
                } else {
                    step.translation.vector
                };
                v.get(i).copied().ok_or_else(shape)?
            }
        };
    }
    Ok(out)
}

/// The unit homogeneous 4-vector `(X, 1) / |(X, 1)|` of a point (its `w` is positive).
pub(super) fn point_homogeneous(x: &Point3<f64>) -> nalgebra::Vector4<f64> {
    nalgebra::Vector4::new(x.x, x.y, x.z, 1.0).normalize()
}

/// Orthonormal 4x3 basis of the tangent space of the unit sphere at `h` (`h.w > 0`): the
/// first three columns of the Householder reflection that maps `h` to `-e4`.
pub(super) fn homogeneous_basis(h: &nalgebra::Vector4<f64>) -> nalgebra::Matrix4x3<f64> {
    let v = h + nalgebra::Vector4::w();
    let house = nalgebra::Matrix4::identity() - v * v.transpose() * (2.0 / v.norm_squared());
    house.fixed_view::<4, 3>(0, 0).into_owned()
}

/// A point moved by a homogeneous tangent step: `h <- normalize(h + B d)`, back to
/// Euclidean. Points are updated on the sphere of homogeneous 4-vectors (Triggs et al.
/// section 2.2) because depth along a ray is then nearly linear in the parameters (it
/// enters the disparity through `w`), which keeps Gauss-Newton steps good for far
/// points. `None` if the step would take the point to or through infinity.
pub(super) fn retract_point(x: &Point3<f64>, d: &Vector3<f64>) -> Option<Point3<f64>> {
    let h = point_homogeneous(x);
    let h2 = (h + homogeneous_basis(&h) * d).normalize();
    if !gt(h2.w, 1e-12) {
        return None;
    }
    let p = Point3::new(h2.x / h2.w, h2.y / h2.w, h2.z / h2.w);
    p.coords.iter().all(|v| v.is_finite()).then_some(p)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bundle::test_support::state_distance;
    use crate::bundle::{BundleOptions, bundle_adjust};
    use crate::synthetic::synth;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn covariance_names_and_perturbed() {
        let s = synth(9, 60, 0.5, 0.0, false);
        let res = bundle_adjust(&s.truth, &s.obs, &BundleOptions::default()).unwrap();
        let names = &res.covariance.names;
        for n in ["left.fx", "left.fy", "left.cx", "left.cy", "right.fx", "rig.rot0", "rig.tdir1"] {
            assert!(res.covariance.index(n).is_some(), "{n} missing from {names:?}");
        }
        for n in ["axis0.dir0", "axis1.pt1", "view1.angle0", "view2.angle1"] {
            assert!(res.covariance.index(n).is_some(), "{n} missing from {names:?}");
        }
        assert!(res.covariance.index("left.skew").is_none());
        assert_eq!(res.covariance.matrix.nrows(), names.len());
        assert!(res.covariance.sigma("left.fx").unwrap() > 0.0);
        let same = res.perturbed(&DVector::zeros(names.len())).unwrap();
        assert!(state_distance(&same, &res.state) < 1e-14);
        let mut d = DVector::zeros(names.len());
        d[res.covariance.index("left.fx").unwrap()] = 1.0;
        d[res.covariance.index("view2.angle0").unwrap()] = 0.01;
        let moved = res.perturbed(&d).unwrap();
        assert!((moved.left.fx - res.state.left.fx - 1.0).abs() < 1e-12);
        let (Motions::Joints { angles: a, .. }, Motions::Joints { angles: b, .. }) =
            (&moved.motions, &res.state.motions)
        else {
            panic!("joints expected")
        };
        assert!((a[2][0] - b[2][0] - 0.01).abs() < 1e-15);
        assert!(res.perturbed(&DVector::zeros(3)).is_err());
        // Free model names.
        let f = synth(10, 40, 0.5, 0.0, true);
        let opts = BundleOptions { square_pixels: true, ..BundleOptions::default() };
        let res = bundle_adjust(&f.truth, &f.obs, &opts).unwrap();
        assert!(res.covariance.index("view2.trans2").is_some() && res.covariance.index("left.fy").is_none());
        let same = res.perturbed(&DVector::zeros(res.covariance.names.len())).unwrap();
        assert!(state_distance(&same, &res.state) < 1e-14);
        assert!((res.state.left.fx - res.state.left.fy).abs() < 1e-12);
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(32))]
        /// `tangent_offset` inverts `perturbed` over every kind of parameter (intrinsics,
        /// rig rotation and baseline direction, joint axes, angles; free view poses), for
        /// random steps of realistic size: to near machine precision.
        #[test]
        fn tangent_offset_inverts_perturbed(seed in 0u64..1000, scale in 1e-4f64..0.05, free in proptest::bool::ANY) {
            use rand_distr::{Distribution, StandardNormal};
            let s = synth(seed, 30, 0.5, 0.0, free);
            let res = bundle_adjust(&s.truth, &s.obs, &BundleOptions { max_iterations: 0, ..BundleOptions::default() }).unwrap();
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let n = res.covariance.names.len();
            let delta = DVector::from_fn(n, |i, _| {
                let z: f64 = StandardNormal.sample(&mut rng);
                // Pixels for the intrinsics, radians / baselines for the rest.
                if res.covariance.names[i].starts_with("left.") || res.covariance.names[i].starts_with("right.") { z * 1000.0 * scale } else { z * scale }
            });
            let moved = res.perturbed(&delta).unwrap();
            let back = res.tangent_offset(&moved).unwrap();
            let err = (&back - &delta).amax();
            proptest::prop_assert!(err < 1e-9 * (1.0 + delta.amax()), "offset error {err:e}");
            let same = res.tangent_offset(&res.state).unwrap();
            proptest::prop_assert!(same.amax() < 1e-15);
        }
    }
}
