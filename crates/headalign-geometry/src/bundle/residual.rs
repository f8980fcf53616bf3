//! Reprojection residuals of the rig bundle adjustment and their linearisation (module
//! docs of [`crate::bundle`], sections What it computes and Algorithm, Jacobians).
//!
//! # What it computes
//!
//! The residual of an observation is the projected minus the observed pixel (2
//! components, pixels): `K_L m_L(X_c)` in the left camera and `K_R m_R(R X_c + t)` in the
//! right one, with `X_c = cam_k_from_ref X`, `(R, t)` the rig's `right_from_left` and `m`
//! the camera's lens model's projection to its image plane (`crate::lens`: the pinhole
//! `(X/Z, Y/Z)`, radial-tangential or equidistant distortion of it, or the double sphere
//! of the ray itself). The pinhole (a radial-tangential lens with zero coefficients) is
//! the pinhole row's arithmetic, bit-identical to the code before lens models existed.
//! [`residual_pixels`] and [`residual_pixels_at`] are the public form.
//!
//! `linearise_obs` returns the same residual with its Jacobians, analytic for the
//! intrinsics, the lens parameters (the model's `param_jacobian`), the rig rotation and baseline direction, the free view poses (via
//! the pose tangent, `so3::skew`) and the point, in its homogeneous 3-dof tangent of
//! `layout.rs` (2x3). For `Joints` the derivative of each view's pose tangent with respect
//! to the axis and angle parameters is a central difference of the small pose function
//! (`view_geoms`, step `JOINT_FD_STEP` = 1e-6, one 6-vector per parameter per view per
//! linearisation), chained analytically with the pose Jacobian: its relative error of
//! about 1e-10 affects only the convergence rate, not the minimum. The structure is the
//! standard one of bundle adjustment (Hartley & Zisserman, 2nd ed., appendix A6; Triggs et
//! al. 2000, section 6): each observation involves one point and the parameters of one
//! (view, side) pair.
//!
//! # Pitfalls
//!
//! - A point outside the lens model's validity region (for the pinhole-plane models on
//!   or behind the camera, `z <= 0` or NaN; for the double sphere beyond its field) has
//!   no residual (`None`): the problem's set-up leaves such observations out, and the
//!   solver rejects a step that would bring a used point there.
//! - These are the plain residuals: the measurement window's shift (`robust.rs`,
//!   `Problem::observe`) and the robust weights are applied by the callers.
//! - `linearise_obs` without `cols` computes the residual only; the point Jacobian it
//!   returns is then zero.

use nalgebra::{Isometry3, Matrix2x3, Matrix3, Matrix3x2, Point3, Vector2, Vector3, Vector6};

use super::layout::{Layout, homogeneous_basis, point_homogeneous, retract_line, side_index, tangent_basis};
use super::state::{BundleObservation, Motions, RigState, Side, joint_pose};
use crate::so3;

/// Residual (projected - observed, pixels) of one observation; `None` if the point is
/// behind the camera or an index is out of range.
pub fn residual_pixels(state: &RigState, obs: &BundleObservation) -> Option<Vector2<f64>> {
    if obs.view >= state.motions.view_count() {
        return None;
    }
    let x = state.points.get(obs.point)?;
    residual_pixels_at(state, &state.motions.ref_from_cam(obs.view), x, obs)
}

/// [`residual_pixels`] of the point `point_in_ref` (in place of the state's point
/// `obs.point`) seen from the view pose `ref_from_cam` (the left camera of `obs.view`,
/// `state.motions.ref_from_cam(obs.view)`, computed once by a caller that evaluates many
/// observations or point positions in one view). Same arithmetic: the result is
/// bit-identical to [`residual_pixels`] for the state's own pose and point.
pub fn residual_pixels_at(
    state: &RigState,
    ref_from_cam: &Isometry3<f64>,
    point_in_ref: &Point3<f64>,
    obs: &BundleObservation,
) -> Option<Vector2<f64>> {
    let xc = ref_from_cam.inverse_transform_point(point_in_ref);
    let (k, d, xs) = match obs.side {
        Side::Left => (&state.left, &state.left_distortion, xc),
        Side::Right => (&state.right, &state.right_distortion, state.right_from_left * xc),
    };
    let m = d.kind.model().project(&d.params(), &xs.coords)?;
    Some(Vector2::new(k.fx * m.x + k.skew * m.y + k.cx - obs.pixel.x, k.fy * m.y + k.cy - obs.pixel.y))
}

const JOINT_FD_STEP: f64 = 1e-6;

/// Per-view geometry and the pose-tangent Jacobian columns `(param index, d xi / d param)`.
pub(super) struct ViewGeom {
    /// `cam_from_ref` rotation.
    rt: Matrix3<f64>,
    /// `ref_from_cam` translation.
    t: Vector3<f64>,
    cols: Vec<(usize, Vector6<f64>)>,
}

/// Left-multiplicative tangent `(w, v)` with `b = (exp(w), v) * a`.
fn pose_tangent(b: &Isometry3<f64>, a: &Isometry3<f64>) -> Vector6<f64> {
    let dr = b.rotation * a.rotation.inverse();
    let w = dr.scaled_axis();
    let v = b.translation.vector - dr * a.translation.vector;
    Vector6::new(w.x, w.y, w.z, v.x, v.y, v.z)
}

pub(super) fn view_geoms(state: &RigState, layout: &Layout, with_jac: bool) -> Vec<ViewGeom> {
    let n_views = state.motions.view_count();
    let mut out = Vec::with_capacity(n_views);
    for k in 0..n_views {
        let pose = state.motions.ref_from_cam(k);
        let mut cols = Vec::new();
        if with_jac && k >= 1 {
            match &state.motions {
                Motions::Free { .. } => {
                    let ri = layout.view_rot.get(k).copied().unwrap_or([None; 3]);
                    let ti = layout.view_trans.get(k).copied().unwrap_or([None; 3]);
                    for (i, idx) in ri.iter().chain(ti.iter()).enumerate() {
                        if let Some(idx) = idx {
                            let mut g = Vector6::zeros();
                            g[i] = 1.0;
                            cols.push((*idx, g));
                        }
                    }
                }
                Motions::Joints { axes, angles, .. } => {
                    let row = angles.get(k).cloned().unwrap_or_default();
                    let h = JOINT_FD_STEP;
                    let fd = |f: &dyn Fn(f64) -> Isometry3<f64>| {
                        (pose_tangent(&f(h), &pose) - pose_tangent(&f(-h), &pose)) / (2.0 * h)
                    };
                    for j in 0..axes.len() {
                        let di = layout.axis_dir.get(j).copied().unwrap_or([None; 2]);
                        let pi = layout.axis_pt.get(j).copied().unwrap_or([None; 2]);
                        for c in 0..4 {
                            let idx = if c < 2 { di[c] } else { pi[c - 2] };
                            let Some(idx) = idx else { continue };
                            let g = fd(&|e| {
                                let mut a = [0.0; 2];
                                let mut b = [0.0; 2];
                                if c < 2 {
                                    a[c] = e;
                                } else {
                                    b[c - 2] = e;
                                }
                                let mut ax = axes.clone();
                                if let Some(l) = ax.get_mut(j) {
                                    *l = retract_line(l, a, b);
                                }
                                joint_pose(&ax, &row)
                            });
                            cols.push((idx, g));
                        }
                        if let Some(Some(idx)) = layout.angle.get(k).and_then(|r| r.get(j)) {
                            let g = fd(&|e| {
                                let mut r = row.clone();
                                if let Some(a) = r.get_mut(j) {
                                    *a += e;
                                }
                                joint_pose(axes, &r)
                            });
                            cols.push((*idx, g));
                        }
                    }
                }
            }
        }
        out.push(ViewGeom {
            rt: pose.rotation.to_rotation_matrix().into_inner().transpose(),
            t: pose.translation.vector,
            cols,
        });
    }
    out
}

/// Rig quantities shared by all observations.
pub(super) struct RigGeom {
    r: Matrix3<f64>,
    t: Vector3<f64>,
    /// `|t| * tangent_basis(t/|t|)`.
    tdir: Matrix3x2<f64>,
}

pub(super) fn rig_geom(state: &RigState) -> RigGeom {
    let t = state.right_from_left.translation.vector;
    let n = t.norm();
    RigGeom {
        r: state.right_from_left.rotation.to_rotation_matrix().into_inner(),
        t,
        tdir: tangent_basis(&(t / n)) * n,
    }
}

/// Residual and, if `cols` is given, the Jacobians of one observation: returns
/// `(residual, d residual / d point)` and fills `cols` with `(param index, column)`;
/// without `cols` the point Jacobian returned is zero (not computed).
#[allow(clippy::too_many_arguments)]
pub(super) fn linearise_obs(
    state: &RigState,
    layout: &Layout,
    views: &[ViewGeom],
    rig: &RigGeom,
    obs: &BundleObservation,
    x: &Point3<f64>,
    cols: Option<&mut Vec<(usize, Vector2<f64>)>>,
) -> Option<(Vector2<f64>, Matrix2x3<f64>)> {
    let view = views.get(obs.view)?;
    let xc = view.rt * (x.coords - view.t);
    let (k, dist, xs, dxs) = match obs.side {
        Side::Left => (&state.left, &state.left_distortion, xc, Matrix3::identity()),
        Side::Right => (&state.right, &state.right_distortion, rig.r * xc + rig.t, rig.r),
    };
    // The lens model's projection (`crate::lens`): `None` outside its validity region.
    let model = dist.kind.model();
    let params = dist.params();
    let lin = model.linearise(k, &params, &xs)?;
    let (a, b, jproj) = (lin.m.x, lin.m.y, lin.d_ray);
    let r = Vector2::new(k.fx * a + k.skew * b + k.cx - obs.pixel.x, k.fy * b + k.cy - obs.pixel.y);
    let Some(cols) = cols else {
        // The residual alone (cost evaluations): no Jacobian.
        return Some((r, Matrix2x3::zeros()));
    };
    let jpoint = jproj * dxs * view.rt;
    // Point Jacobian in the homogeneous tangent parametrisation (see `retract_point`):
    // h = (X, 1) / |(X, 1)|, d residual / d h = [jpoint, d/dw] / w, then times the basis.
    let h = point_homogeneous(x);
    let side_t = if obs.side == Side::Right { rig.t } else { Vector3::zeros() };
    let jw = jproj * (dxs * (-(view.rt * view.t)) + side_t);
    let mut j4 = nalgebra::Matrix2x4::zeros();
    j4.fixed_view_mut::<2, 3>(0, 0).copy_from(&jpoint);
    j4.set_column(3, &jw);
    let jhom = j4 * homogeneous_basis(&h) / h.w;
    cols.clear();
    let s = side_index(obs.side);
    let intr = &layout.intr[s];
    let dk = [
        if layout.square[s] { Vector2::new(a, b) } else { Vector2::new(a, 0.0) },
        Vector2::new(0.0, b),
        Vector2::new(b, 0.0),
        Vector2::new(1.0, 0.0),
        Vector2::new(0.0, 1.0),
    ];
    for (idx, d) in intr.iter().zip(dk) {
        if let Some(idx) = idx {
            cols.push((*idx, d));
        }
    }
    let didx = &layout.dist[s];
    if didx.iter().any(Option::is_some) {
        // The layout's lens entries are the model's parameters, in its order.
        let mut estimated = [false; crate::lens::MAX_PARAMS];
        for (e, i) in estimated.iter_mut().zip(didx) {
            *e = i.is_some();
        }
        let jc = model.param_jacobian(k, &params, &xs, &estimated);
        for (i, idx) in didx.iter().enumerate() {
            if let Some(idx) = idx {
                cols.push((*idx, jc.column(i).into_owned()));
            }
        }
    }
    if obs.side == Side::Right {
        let jrot = jproj * (-so3::skew(&(rig.r * xc)));
        for (i, idx) in layout.rig_rot.iter().enumerate() {
            if let Some(idx) = idx {
                cols.push((*idx, jrot.column(i).into_owned()));
            }
        }
        let jt = jproj * rig.tdir;
        for (i, idx) in layout.rig_tdir.iter().enumerate() {
            if let Some(idx) = idx {
                cols.push((*idx, jt.column(i).into_owned()));
            }
        }
    }
    if !view.cols.is_empty() {
        // d xc / d(w, v) = [R^T [X]x, -R^T]
        let jw = jpoint * so3::skew(&x.coords);
        for (idx, g) in &view.cols {
            let gw = Vector3::new(g[0], g[1], g[2]);
            let gv = Vector3::new(g[3], g[4], g[5]);
            cols.push((*idx, jw * gw - jpoint * gv));
        }
    }
    Some((r, jhom))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bundle::BundleOptions;
    use crate::bundle::layout::{retract, retract_point};
    use crate::bundle::test_support::distorted;
    use crate::distortion::{Distortion, DistortionTerms, LensKind};
    use crate::synthetic::{Synth, perturb, synth};
    use nalgebra::DVector;

    #[test]
    fn synthetic_problem_has_the_expected_size() {
        let s = synth(1, 200, 0.0, 0.0, false);
        assert!(s.obs.len() > 1100, "{} observations", s.obs.len());
        assert!(s.obs.iter().all(|o| residual_pixels(&s.truth, o).unwrap().norm() < 1e-9));
    }

    /// Central differences of `residual_pixels` along camera parameter `i` / point coordinate.
    fn fd_check(state: &RigState, options: &BundleOptions, obs: &[BundleObservation]) {
        let layout = Layout::build(state, options).unwrap();
        let views = view_geoms(state, &layout, true);
        let rig = rig_geom(state);
        let mut cols = Vec::new();
        let h = 1e-6;
        let mut checked = 0;
        for o in obs {
            let x = state.points[o.point];
            let (r, jp) = linearise_obs(state, &layout, &views, &rig, o, &x, Some(&mut cols)).unwrap();
            assert!((r - residual_pixels(state, o).unwrap()).norm() < 1e-9);
            let mut dense = vec![Vector2::zeros(); layout.len()];
            for (i, c) in &cols {
                dense[*i] += c;
            }
            for (i, analytic) in dense.iter().enumerate() {
                let mut e = DVector::zeros(layout.len());
                e[i] = h;
                let plus = residual_pixels(&retract(state, &layout, &e).unwrap(), o).unwrap();
                let minus = residual_pixels(&retract(state, &layout, &(-e)).unwrap(), o).unwrap();
                let numeric = (plus - minus) / (2.0 * h);
                let err = (numeric - analytic).norm();
                assert!(
                    err < 1e-5 * (1.0 + numeric.norm()),
                    "{}: analytic {analytic:?} numeric {numeric:?}",
                    layout.params[i].name()
                );
                checked += 1;
            }
            for c in 0..3 {
                let mut sp = state.clone();
                let mut e = Vector3::zeros();
                e[c] = h;
                sp.points[o.point] = retract_point(&x, &e).unwrap();
                let plus = residual_pixels(&sp, o).unwrap();
                sp.points[o.point] = retract_point(&x, &(-e)).unwrap();
                let minus = residual_pixels(&sp, o).unwrap();
                let numeric = (plus - minus) / (2.0 * h);
                assert!((numeric - jp.column(c)).norm() < 1e-6 * (1.0 + numeric.norm()), "point {c}");
            }
        }
        assert!(checked > 0);
    }

    #[test]
    fn jacobians_match_finite_differences() {
        let pick = |s: &Synth| -> Vec<BundleObservation> {
            let mut out = Vec::new();
            for view in 0..3 {
                for side in [Side::Left, Side::Right] {
                    out.extend(s.obs.iter().filter(|o| o.view == view && o.side == side).take(2));
                }
            }
            out
        };
        let s = synth(6, 30, 0.0, 0.0, false);
        let st = perturb(&s.truth, 60);
        // Joints with free angles, skew and non-square pixels.
        let all = BundleOptions { zero_skew: false, ..BundleOptions::default() };
        let mut st_skew = st.clone();
        st_skew.left.skew = 1.5;
        st_skew.right.skew = -0.7;
        fd_check(&st_skew, &all, &pick(&s));
        // Square pixels and a fixed principal point.
        let mut sq = st.clone();
        for k in [&mut sq.left, &mut sq.right] {
            k.fy = k.fx;
        }
        let opts =
            BundleOptions { square_pixels: true, fix_principal_point: true, ..BundleOptions::default() };
        fd_check(&sq, &opts, &pick(&s));
        // Free model.
        let f = synth(7, 30, 0.0, 0.0, true);
        fd_check(&perturb(&f.truth, 70), &BundleOptions::default(), &pick(&f));
    }

    #[test]
    fn distortion_jacobians_match_finite_differences() {
        let s = distorted(13, 30, false);
        let pick: Vec<_> = s.obs.iter().step_by(7).take(12).copied().collect();
        let opts = BundleOptions { estimate_distortion: true, zero_skew: false, ..BundleOptions::default() };
        let mut st = perturb(&s.truth, 130);
        st.left.skew = 1.5;
        fd_check(&st, &opts, &pick);
        // From the pinhole start (zero distortion takes the pinhole branch of the projection).
        st.left_distortion = Distortion::default();
        st.right_distortion = Distortion::default();
        fd_check(&st, &opts, &pick);
        // Tangential and k3 held but used; square pixels.
        let mut sq = perturb(&s.truth, 131);
        *sq.left_distortion.param_named_mut("p1").unwrap() = 1e-3;
        *sq.right_distortion.param_named_mut("k3").unwrap() = 0.01;
        for k in [&mut sq.left, &mut sq.right] {
            k.fy = k.fx;
        }
        let opts =
            BundleOptions { estimate_distortion: true, square_pixels: true, ..BundleOptions::default() };
        fd_check(&sq, &opts, &pick);
        let f = distorted(14, 30, true);
        let pick: Vec<_> = f.obs.iter().step_by(5).take(12).copied().collect();
        fd_check(
            &perturb(&f.truth, 140),
            &BundleOptions { estimate_distortion: true, ..BundleOptions::default() },
            &pick,
        ); // Every radial-tangential coefficient free (k1 k2 p1 p2 k3), and the equidistant
        // model with k1..k4 free, with a skew.
        let mut full = perturb(&s.truth, 132);
        *full.left_distortion.param_named_mut("p1").unwrap() = 1e-3;
        *full.right_distortion.param_named_mut("p2").unwrap() = -2e-3;
        full.left.skew = 0.8;
        let five = BundleOptions {
            estimate_distortion: true,
            zero_skew: false,
            distortion_terms: DistortionTerms::Full5,
            ..BundleOptions::default()
        };
        fd_check(&full, &five, &pick);
        let mut equi = perturb(&s.truth, 133);
        equi.left_distortion = Distortion::equidistant([0.05, -0.01, 0.002, -0.0005]);
        equi.right_distortion = Distortion::zero(LensKind::Equidistant);
        equi.left.skew = -0.6;
        fd_check(&equi, &BundleOptions { distortion_terms: DistortionTerms::Full4, ..five.clone() }, &pick);
        // The double sphere with xi and alpha free (the projection of the ray itself).
        let mut ds = perturb(&s.truth, 134);
        ds.left_distortion = Distortion::double_sphere(-0.1, 0.55);
        ds.right_distortion = Distortion::double_sphere(0.2, 0.6);
        ds.left.skew = 0.4;
        fd_check(&ds, &five, &pick);
        let layout = Layout::build(&ds, &five).unwrap();
        assert!(
            layout.names().iter().any(|n| n == "left.xi")
                && layout.names().iter().any(|n| n == "right.alpha")
        );
    }
}
