//! The bundle-adjustment problem as the solver sees it: the checked and normalised start
//! state, the observations it uses, the cost (module docs of [`crate::bundle`], sections
//! Gauge, Algorithm and Measurement window).
//!
//! # What it computes
//!
//! - `prepare_state` checks the start (finite intrinsics with positive focal lengths, valid
//!   distortion, a finite rig with a non-zero baseline, view 0 at the identity, angle rows
//!   of the right shape with row 0 zero, finite axes each moved in some view) and
//!   normalises it for the options: skew 0 with `zero_skew`, `fx = fy` at their mean with
//!   `square_pixels`, the angles at the commanded ones without an angle prior, unit axis
//!   directions.
//! - `problem` validates the options and the observations, builds the layout and keeps the
//!   observations in front of both cameras at the start whose points are then seen at
//!   least twice; the other points are returned unchanged, without error.
//! - `Problem::observe` is an observation's residual and Jacobians with the measurement
//!   window applied (the expected reported measurement, `robust.rs`); `evaluate` the cost
//!   `sum_obs rho(|r|) + prior_weight / 2 sum prior^2 (+ (s - target)^2 / (2 tol^2)` for
//!   the depth-scale constraint), in half squared pixels, with the plain sum of squared
//!   residuals for the RMS; `residual_norms` and `point_scores` serve the covariance.
//!
//! Degrees of freedom: the layout's camera parameters (`layout.rs`) plus 3 per used point;
//! residuals: 2 per used observation plus one per angle-prior row.
//!
//! # Pitfalls
//!
//! - Bad input is an error, never a panic: an out-of-range index, a non-finite pixel or
//!   point, a view without (usable) observations, a broken gauge
//!   ([`GeometryError::Degenerate`], [`GeometryError::NotEnoughData`]).
//! - The used points are in a compact order (`Problem::points` maps back to the state's):
//!   point blocks of the normal equations and the scores follow it.
//! - An axis whose angle is zero in every view moves nothing and cannot be estimated: it is
//!   rejected, not held.

use nalgebra::{DVector, Isometry3, Matrix2x3, Point3, Unit, Vector2, Vector3};

use super::covariance::log_depth_scale_of;
use super::gt;
use super::layout::Layout;
use super::normal::DENSE_SCHUR_MAX_VIEWS;
use super::residual::{RigGeom, ViewGeom, linearise_obs, rig_geom, view_geoms};
use super::robust::{robust, truncated_mean_shift};
use super::sparse::SparseStructure;
use super::state::{BundleObservation, BundleOptions, Motions, RigState};
use crate::camera::Intrinsics;
use crate::so3::Line;
use crate::{GeometryError, Result};

/// The problem after filtering: used observations and points.
pub(super) struct Problem<'a> {
    pub(super) layout: Layout,
    pub(super) obs: Vec<BundleObservation>,
    /// Compact point index of each used observation.
    pub(super) obs_point: Vec<usize>,
    /// Original index of each used point.
    pub(super) points: Vec<usize>,
    pub(super) options: &'a BundleOptions,
    /// Weight of the angle prior relative to pixels (`sigma_px^2`).
    pub(super) prior_weight: f64,
    /// The depth-scale constraint `(target, tolerance)` of [`bundle_adjust_at_depth_scale`].
    ///
    /// [`bundle_adjust_at_depth_scale`]: super::bundle_adjust_at_depth_scale
    pub(super) depth: Option<(f64, f64)>,
    /// The normal equations keep `W` per point (`normal.rs`): more than
    /// `DENSE_SCHUR_MAX_VIEWS` views.
    pub(super) sparse: bool,
    /// The sparse form's structure, built at the first linearisation (`sparse.rs`).
    pub(super) structure: std::cell::OnceCell<std::rc::Rc<SparseStructure>>,
}

pub(super) struct Eval {
    pub(super) cost: f64,
    pub(super) sum_sq: f64,
}

impl Problem<'_> {
    /// [`linearise_obs`] with the measurement window applied (module docs, Measurement
    /// window): the residual against the expected measurement, each image axis's Jacobian
    /// row scaled by the derivative of that expectation.
    pub(super) fn observe(
        &self,
        state: &RigState,
        views: &[ViewGeom],
        rig: &RigGeom,
        obs: &BundleObservation,
        x: &Point3<f64>,
        mut cols: Option<&mut Vec<(usize, Vector2<f64>)>>,
    ) -> Option<(Vector2<f64>, Matrix2x3<f64>)> {
        let (mut r, mut jp) = linearise_obs(state, &self.layout, views, rig, obs, x, cols.as_deref_mut())?;
        let (Some([x0, y0, x1, y1]), Some(sigma)) =
            (self.options.measurement_window, self.options.noise_sigma_px)
        else {
            return Some((r, jp));
        };
        for (axis, (lo, hi)) in [(x0, x1), (y0, y1)].into_iter().enumerate() {
            let predicted = r[axis] + obs.pixel[axis];
            let (shift, slope) = truncated_mean_shift(predicted, lo, hi, sigma);
            if shift == 0.0 && slope == 0.0 {
                continue;
            }
            r[axis] += shift;
            let scale = 1.0 + slope;
            for c in 0..3 {
                jp[(axis, c)] *= scale;
            }
            if let Some(cols) = cols.as_deref_mut() {
                for (_, j) in cols.iter_mut() {
                    j[axis] *= scale;
                }
            }
        }
        Some((r, jp))
    }

    pub(super) fn evaluate(&self, state: &RigState) -> Option<Eval> {
        let views = view_geoms(state, &self.layout, false);
        let rig = rig_geom(state);
        let mut cost = 0.0;
        let mut sum_sq = 0.0;
        for (o, &p) in self.obs.iter().zip(&self.obs_point) {
            let x = state.points.get(*self.points.get(p)?)?;
            let (r, _) = self.observe(state, &views, &rig, o, x, None)?;
            let s2 = r.norm_squared();
            cost += robust(self.options.robust, s2).0;
            sum_sq += s2;
        }
        for row in self.prior_terms(state) {
            cost += 0.5 * self.prior_weight * row.residual * row.residual;
        }
        if let Some((target, tol)) = self.depth {
            let r = (log_depth_scale_of(state, &self.points)? - target) / tol;
            cost += 0.5 * r * r;
        }
        (cost.is_finite()).then_some(Eval { cost, sum_sq })
    }

    pub(super) fn residual_norms(&self, state: &RigState) -> Option<Vec<f64>> {
        let views = view_geoms(state, &self.layout, false);
        let rig = rig_geom(state);
        let mut out = Vec::with_capacity(self.obs.len());
        for (o, &p) in self.obs.iter().zip(&self.obs_point) {
            let x = state.points.get(*self.points.get(p)?)?;
            out.push(self.observe(state, &views, &rig, o, x, None)?.0.norm());
        }
        Some(out)
    }

    /// Per point: the gradient of its observations' squared residuals with respect to the
    /// camera parameters (`sum w J_c^T r`) and to the point (`sum w J_p^T r`), pixels.
    pub(super) fn point_scores(&self, state: &RigState) -> Option<Vec<(DVector<f64>, Vector3<f64>)>> {
        let nc = self.layout.len();
        let views = view_geoms(state, &self.layout, true);
        let rig = rig_geom(state);
        let mut out = vec![(DVector::zeros(nc), Vector3::zeros()); self.points.len()];
        let mut cols = Vec::with_capacity(32);
        for (o, &p) in self.obs.iter().zip(&self.obs_point) {
            let x = state.points.get(*self.points.get(p)?)?;
            let (r, jp) = self.observe(state, &views, &rig, o, x, Some(&mut cols))?;
            let wt = robust(self.options.robust, r.norm_squared()).1;
            let (gc, gp) = out.get_mut(p)?;
            *gp += jp.transpose() * r * wt;
            for &(a, ja) in &cols {
                gc[a] += wt * ja.dot(&r);
            }
        }
        Some(out)
    }
}

fn check_intrinsics(k: &Intrinsics, name: &str) -> Result<()> {
    if !k.is_finite() || !gt(k.fx, 0.0) || !gt(k.fy, 0.0) {
        return Err(GeometryError::InvalidEstimate(format!(
            "{name} intrinsics must be finite with positive focal lengths, got {k:?}"
        )));
    }
    Ok(())
}

fn iso_finite(p: &Isometry3<f64>) -> bool {
    p.translation.vector.iter().chain(p.rotation.coords.iter()).all(|v| v.is_finite())
}

/// Check the state and normalise it for the options (skew, square pixels, fixed angles,
/// unit axis directions).
fn prepare_state(initial: &RigState, options: &BundleOptions) -> Result<RigState> {
    let mut s = initial.clone();
    check_intrinsics(&s.left, "left")?;
    check_intrinsics(&s.right, "right")?;
    for d in [&s.left_distortion, &s.right_distortion] {
        d.validate()?;
    }
    for k in [&mut s.left, &mut s.right] {
        if options.zero_skew {
            k.skew = 0.0;
        }
        if options.square_pixels {
            let f = 0.5 * (k.fx + k.fy);
            k.fx = f;
            k.fy = f;
        }
    }
    let t = s.right_from_left.translation.vector;
    if !iso_finite(&s.right_from_left) || !gt(t.norm(), 1e-12) {
        return Err(GeometryError::Degenerate(
            "right_from_left must be finite with a non-zero baseline (it fixes the scale)".into(),
        ));
    }
    let v = s.motions.view_count();
    if v == 0 {
        return Err(GeometryError::NotEnoughData { what: "views", needed: 1, got: 0 });
    }
    match &mut s.motions {
        Motions::Free { ref_from_cam } => {
            if ref_from_cam.iter().any(|p| !iso_finite(p)) {
                return Err(GeometryError::Degenerate("a view pose is not finite".into()));
            }
            let p0 = ref_from_cam.first().copied().unwrap_or_else(Isometry3::identity);
            if p0.translation.vector.norm() > 1e-9 || p0.rotation.angle() > 1e-9 {
                return Err(GeometryError::Degenerate("view 0 pose must be the identity (gauge)".into()));
            }
            if let Some(p) = ref_from_cam.first_mut() {
                *p = Isometry3::identity();
            }
        }
        Motions::Joints { axes, angles, commanded } => {
            if axes.is_empty() {
                return Err(GeometryError::NotEnoughData { what: "joint axes", needed: 1, got: 0 });
            }
            if commanded.len() != angles.len() {
                return Err(GeometryError::Degenerate(format!(
                    "{} rows of angles but {} rows of commanded angles",
                    angles.len(),
                    commanded.len()
                )));
            }
            for (k, (a, c)) in angles.iter().zip(commanded.iter()).enumerate() {
                if a.len() != axes.len() || c.len() != axes.len() {
                    return Err(GeometryError::Degenerate(format!(
                        "view {k}: angle rows must have one entry per axis ({})",
                        axes.len()
                    )));
                }
                if a.iter().chain(c).any(|x| !x.is_finite()) {
                    return Err(GeometryError::Degenerate(format!("view {k}: angles must be finite")));
                }
                if k == 0 && a.iter().chain(c).any(|x| x.abs() > 1e-12) {
                    return Err(GeometryError::Degenerate("row 0 of the angles must be zero (gauge)".into()));
                }
            }
            if options.angle_prior_sigma.is_none() {
                angles.clone_from(commanded);
            }
            for (j, l) in axes.iter_mut().enumerate() {
                let d = l.direction.into_inner();
                if !d.iter().chain(l.point.coords.iter()).all(|x| x.is_finite()) || !gt(d.norm(), 1e-12) {
                    return Err(GeometryError::Degenerate(format!("axis {j} is not a finite line")));
                }
                *l = Line::new(Unit::new_normalize(d), l.point);
                let moved = angles.iter().zip(commanded.iter()).any(|(a, c)| {
                    a.get(j).is_some_and(|x| x.abs() > 1e-12) || c.get(j).is_some_and(|x| x.abs() > 1e-12)
                });
                if !moved {
                    return Err(GeometryError::Degenerate(format!(
                        "axis {j} has zero angle in every view: it is not observable"
                    )));
                }
            }
        }
    }
    Ok(s)
}

/// The state normalised for the options ([`prepare_state`]) and the problem on it: the
/// observations in front of the cameras, of points seen at least twice.
pub(super) fn problem<'a>(
    initial: &RigState,
    observations: &[BundleObservation],
    options: &'a BundleOptions,
) -> Result<(RigState, Problem<'a>)> {
    options.validate()?;
    if observations.is_empty() {
        return Err(GeometryError::NotEnoughData { what: "observations", needed: 1, got: 0 });
    }
    let state = prepare_state(initial, options)?;
    let n_views = state.motions.view_count();
    if let Some(&k) = options.gauge_views.iter().find(|&&k| k == 0 || k >= n_views) {
        return Err(GeometryError::InvalidOption(format!(
            "gauge view {k} must be a view other than view 0 (of {n_views})"
        )));
    }
    if !options.gauge_views.is_empty() && !matches!(state.motions, Motions::Free { .. }) {
        return Err(GeometryError::InvalidOption("gauge views need free view poses".into()));
    }
    let mut per_view = vec![0usize; n_views];
    for (i, o) in observations.iter().enumerate() {
        if o.view >= n_views || o.point >= state.points.len() {
            return Err(GeometryError::Degenerate(format!(
                "observation {i} refers to view {} / point {} out of range",
                o.view, o.point
            )));
        }
        if !(o.pixel.x.is_finite() && o.pixel.y.is_finite()) {
            return Err(GeometryError::Degenerate(format!("observation {i} has a non-finite pixel")));
        }
        if let Some(c) = per_view.get_mut(o.view) {
            *c += 1;
        }
    }
    if let Some(k) = per_view.iter().position(|&c| c == 0) {
        return Err(GeometryError::Degenerate(format!("view {k} has no observations")));
    }
    let layout = Layout::build(&state, options)?;

    // Filter: in front of the cameras, points with >= 2 observations.
    let views0 = view_geoms(&state, &layout, false);
    let rig0 = rig_geom(&state);
    let mut kept: Vec<BundleObservation> = Vec::with_capacity(observations.len());
    let mut count = vec![0usize; state.points.len()];
    for o in observations {
        let Some(x) = state.points.get(o.point) else { continue };
        if !x.coords.iter().all(|v| v.is_finite()) {
            return Err(GeometryError::Degenerate(format!("point {} is not finite", o.point)));
        }
        if linearise_obs(&state, &layout, &views0, &rig0, o, x, None).is_some() {
            kept.push(*o);
            if let Some(c) = count.get_mut(o.point) {
                *c += 1;
            }
        }
    }
    let mut compact = vec![usize::MAX; state.points.len()];
    let mut points = Vec::new();
    for (i, &c) in count.iter().enumerate() {
        if c >= 2 {
            if let Some(slot) = compact.get_mut(i) {
                *slot = points.len();
            }
            points.push(i);
        }
    }
    kept.retain(|o| count.get(o.point).is_some_and(|&c| c >= 2));
    let obs_point: Vec<usize> = kept.iter().map(|o| compact.get(o.point).copied().unwrap_or(0)).collect();
    let mut per_view = vec![0usize; n_views];
    for o in &kept {
        if let Some(c) = per_view.get_mut(o.view) {
            *c += 1;
        }
    }
    if kept.is_empty() {
        return Err(GeometryError::NotEnoughData { what: "usable observations", needed: 2, got: 0 });
    }
    if let Some(k) = per_view.iter().position(|&c| c == 0) {
        return Err(GeometryError::Degenerate(format!(
            "view {k} has no usable observations (in front of the camera, point seen at least twice)"
        )));
    }

    let sigma_opt = options.noise_sigma_px.unwrap_or(1.0);
    let problem = Problem {
        layout,
        obs: kept,
        obs_point,
        points,
        options,
        prior_weight: sigma_opt * sigma_opt,
        depth: None,
        sparse: n_views > DENSE_SCHUR_MAX_VIEWS,
        structure: std::cell::OnceCell::new(),
    };
    Ok((state, problem))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bundle::{RobustLoss, Side, bundle_adjust, residual_pixels};
    use crate::synthetic::synth;
    use nalgebra::Point2;

    #[test]
    fn error_paths() {
        let s = synth(11, 30, 0.0, 0.0, false);
        let opts = BundleOptions::default();
        let ba = |st: &RigState, obs: &[BundleObservation], o: &BundleOptions| bundle_adjust(st, obs, o);
        assert!(matches!(ba(&s.truth, &[], &opts), Err(GeometryError::NotEnoughData { .. })));
        // A view with no observations.
        let no_view2: Vec<_> = s.obs.iter().copied().filter(|o| o.view != 2).collect();
        assert!(ba(&s.truth, &no_view2, &opts).is_err());
        // NaN pixel.
        let mut nan = s.obs.clone();
        nan[3].pixel.x = f64::NAN;
        assert!(ba(&s.truth, &nan, &opts).is_err());
        // Out-of-range indices.
        let mut oob = s.obs.clone();
        oob[0].point = 10_000;
        assert!(ba(&s.truth, &oob, &opts).is_err());
        // Non-positive focal length.
        let mut bad = s.truth.clone();
        bad.right.fx = 0.0;
        assert!(ba(&bad, &s.obs, &opts).is_err());
        bad.right.fx = -700.0;
        assert!(ba(&bad, &s.obs, &opts).is_err());
        // Zero baseline.
        let mut bad = s.truth.clone();
        bad.right_from_left.translation.vector = Vector3::zeros();
        assert!(ba(&bad, &s.obs, &opts).is_err());
        // Unobservable axis: elevation never moves.
        let mut bad = s.truth.clone();
        if let Motions::Joints { angles, commanded, .. } = &mut bad.motions {
            for row in angles.iter_mut().chain(commanded.iter_mut()) {
                row[1] = 0.0;
            }
        }
        let only_pan = |o: &&BundleObservation| o.view != 1;
        let obs02: Vec<_> = s.obs.iter().filter(only_pan).copied().collect();
        assert!(matches!(ba(&bad, &obs02, &opts), Err(GeometryError::Degenerate(_))));
        // Bad angle shapes, non-zero row 0.
        let mut bad = s.truth.clone();
        if let Motions::Joints { angles, .. } = &mut bad.motions {
            angles[0][0] = 0.1;
        }
        assert!(ba(&bad, &s.obs, &opts).is_err());
        let mut bad = s.truth.clone();
        if let Motions::Joints { commanded, .. } = &mut bad.motions {
            commanded.pop();
        }
        assert!(ba(&bad, &s.obs, &opts).is_err());
        // Free model with a non-identity view 0.
        let f = synth(12, 30, 0.0, 0.0, true);
        let mut bad = f.truth.clone();
        if let Motions::Free { ref_from_cam } = &mut bad.motions {
            ref_from_cam[0].translation.vector.x = 0.1;
        }
        assert!(ba(&bad, &f.obs, &opts).is_err());
        // Bad options.
        for o in [
            BundleOptions { robust: RobustLoss::Huber { scale_px: 0.0 }, ..opts.clone() },
            BundleOptions { robust: RobustLoss::Cauchy { scale_px: f64::NAN }, ..opts.clone() },
            BundleOptions { angle_prior_sigma: Some(-1.0), ..opts.clone() },
            BundleOptions { noise_sigma_px: Some(0.0), ..opts.clone() },
            BundleOptions { function_tolerance: f64::INFINITY, ..opts.clone() },
        ] {
            assert!(o.validate().is_err());
            assert!(matches!(ba(&s.truth, &s.obs, &o), Err(GeometryError::InvalidOption(_))));
        }
        assert!(opts.validate().is_ok());
        // Points seen once are left out without error; behind-camera points too.
        let mut partial = s.obs.clone();
        let lone = s.truth.points.len();
        let mut st = s.truth.clone();
        st.points.push(Point3::new(0.0, 0.0, 3.0));
        st.points.push(Point3::new(0.0, 0.0, -3.0));
        partial.push(BundleObservation {
            point: lone,
            view: 0,
            side: Side::Left,
            pixel: Point2::new(390.0, 284.0),
        });
        for view in 0..3 {
            partial.push(BundleObservation {
                point: lone + 1,
                view,
                side: Side::Left,
                pixel: Point2::new(100.0, 100.0),
            });
        }
        let res = ba(&st, &partial, &opts).unwrap();
        assert_eq!(res.report.observations, s.obs.len());
        assert_eq!(res.state.points[lone], st.points[lone]);
        assert_eq!(res.state.points[lone + 1], st.points[lone + 1]);
        // Angles held fixed without a prior.
        let fixed = BundleOptions { angle_prior_sigma: None, ..opts.clone() };
        let res = ba(&s.truth, &s.obs, &fixed).unwrap();
        assert!(res.covariance.index("view1.angle1").is_none());
        // Residual helper: behind the camera and out of range.
        assert!(residual_pixels(&st, &partial[partial.len() - 1]).is_none());
        let mut o = s.obs[0];
        o.view = 7;
        assert!(residual_pixels(&s.truth, &o).is_none());
    }
}
