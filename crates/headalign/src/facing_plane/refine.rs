//! Step 4 of the planar route ([`super`] module docs): the maximum-likelihood adjustment of
//! one camera's planar model, and its covariance.
//!
//! Cost (whitened): `sum |pi(obs) - obs|^2 / sigma^2` over the observations (pixels) +
//! `sum ((angle - commanded) / sigma_angle)^2` + `sum |p_j|^2 + |m|^2` (the gauge prior,
//! unit variance in metres and inverse metres: the model depends on the offsets `p_j` and
//! the plane `m` only through `p_j m^T`, so scaling one up and the other down changes no
//! residual; the prior picks one point of that orbit and, against thousands of pixel
//! residuals, moves no observable quantity measurably). Model and Jacobians:
//! [`project_plane_point`]. Parameter layout (the dense "camera" block): `fx, fy, cx, cy`;
//! per joint its axis' two tangent components and its offset's two (the basis of
//! [`tangent_basis`] at the current axis); the angles; `m`. Each point's 2 dof are
//! eliminated by the Schur complement (2x2 blocks).
//!
//! Passes: one at `sigma = 1 px` from each start of [`PLANE_STARTS`] (the plane enters
//! bilinearly with the offsets; the fit of least cost is kept); observations beyond
//! [`super::PlanarOptions::reselect_sigmas`] robust sigmas (1.4826 MAD of the residual
//! coordinates, at least [`MIN_SIGMA_PX`]) dropped and points left with one observation
//! removed; one more at the robust sigma. The pixel noise is then the residuals' RMS over
//! the degrees of freedom, and the covariance the inverse of the reduced normal
//! equations weighted by it (the angle prior keeps its own sigma, as the general route's
//! maximum-likelihood pass does; [`super::PlanarOptions::covariance_sigma_px`] replaces
//! the estimated pixel noise, and `profile.rs` then widens it). Levenberg-Marquardt:
//! Marquardt's diagonal scaling, `lambda` from 1e-3, tenfold up on a failed step and down
//! on a good one; stops when the cost falls by less than 1e-12 relative or after
//! `max_iterations`.
//!
//! Pitfalls: the plane enters bilinearly with the offsets, so the cost has long curved
//! valleys and, near [`PLANE_STARTS`], several minima. This loop often stops short of
//! its minimum (at the iteration limit, or at a step that gains under 1e-12 after the
//! damping rose): of 86 adjustments in `experiment planar --scene wall --trials 10`,
//! instrumented, 47 ended at the limit of 100, others up to 1.2 in the whitened cost
//! above the minimum. The project's Levenberg-Marquardt (`headalign_geometry::lm`, with
//! this module's Schur complement as its back end) reaches the minimum, but from the
//! same starts it ends in a higher one in some trials (the `far` scene at 1 px, seed 2,
//! second camera: 1939.70 from all three starts against this loop's 1934.35 from two;
//! the `wall` at 2 px, seeds 4 and 5: 7.4 and 4.3 higher), which moved readings by up to
//! 3.8 sigmas in `experiment planar --scene wall` and `--scene far` with `--trials 20`.
//! So the route keeps this loop until its starts find the lowest minimum under either.

use headalign_geometry::bundle::Side;
use headalign_geometry::camera::Intrinsics;
use headalign_geometry::plane::{JointFactor, project_plane_point, tangent_basis};
use headalign_geometry::so3::{Line, rotation_about_line};
use nalgebra::{DMatrix, DVector, Matrix2, Point2, Point3, Unit, Vector2, Vector3};

use super::profile::{NormalProfile, PlaneTest, profile_normal, test_plane_at_infinity};
use super::{CameraPlanar, FAR_PARALLAX_PX, NORMAL_UNDETERMINED_DEG, PlanarOptions, camera_joints};
use crate::error::AlignError;

/// Floor of the robust pixel sigma of the reselection, pixels: noise-free data keep every
/// observation within a few hundredths of a pixel of the model (a far scene's parallax).
pub const MIN_SIGMA_PX: f64 = 0.05;

/// Starts of the plane's inverse distance (per metre, fronto-parallel), module docs.
pub const PLANE_STARTS: [f64; 3] = [0.25, 1.0 / 3.0, 1.0];

/// A joint's state: its slot in [`camera_joints`], axis direction and a point of the axis
/// (camera frame of the reference view, metres up to the gauge).
#[derive(Debug, Clone, Copy)]
pub(super) struct JointState {
    pub slot: usize,
    pub axis: Unit<Vector3<f64>>,
    pub point: Vector3<f64>,
}

/// One observation: view index, point index, pixel.
#[derive(Debug, Clone, Copy)]
pub(super) struct Observation {
    pub view: usize,
    pub point: usize,
    pub pixel: Point2<f64>,
}

/// A penalty `weight sum_k (m . c_k)^2` over the directions `c_k` of `across`: with the
/// two directions perpendicular to a normal it holds the plane's normal there (the
/// profile's ends), with all three it holds `m` at zero (the plane at infinity; both in
/// `profile.rs`).
#[derive(Debug, Clone)]
pub(super) struct PlaneHold {
    pub across: Vec<Vector3<f64>>,
    pub weight: f64,
}

/// One camera's planar problem (module docs).
#[derive(Debug, Clone)]
pub(super) struct Problem {
    pub k: Intrinsics,
    pub joints: Vec<JointState>,
    pub angles: Vec<f64>,
    pub angle_cmd: Vec<f64>,
    /// Per view: (joint index, angle index) in chain order.
    pub view_factors: Vec<Vec<(usize, usize)>>,
    pub plane: Vector3<f64>,
    pub points: Vec<Point2<f64>>,
    pub tracks: Vec<u64>,
    pub obs: Vec<Observation>,
    /// The profile's hold on the normal (`None` in the adjustment proper).
    pub plane_hold: Option<PlaneHold>,
}

/// The adjusted problem with its covariance.
pub(super) struct Fit {
    problem: Problem,
    /// Covariance of the camera block (layout of the module docs).
    covariance: DMatrix<f64>,
    sigma_px: f64,
    rms_px: f64,
    profile: NormalProfile,
    plane_test: PlaneTest,
}

impl Problem {
    fn n_camera(&self) -> usize {
        4 + 4 * self.joints.len() + self.angles.len() + 3
    }

    pub(super) fn plane_index(&self) -> usize {
        4 + 4 * self.joints.len() + self.angles.len()
    }

    fn factors(&self, view: usize) -> Vec<JointFactor> {
        self.view_factors[view]
            .iter()
            .map(|&(j, a)| JointFactor {
                axis: self.joints[j].axis,
                point: Point3::from(self.joints[j].point),
                angle: self.angles[a],
            })
            .collect()
    }

    /// The plane's own effect: the largest displacement `f |t_i| |m|` it adds to the
    /// infinite homography over the views, pixels (gauge-free: `t_i` scales as `1 / |m|`).
    pub(super) fn plane_parallax_px(&self) -> f64 {
        let mn = self.plane.norm();
        (0..self.view_factors.len())
            .map(|v| {
                let pose = self.factors(v).iter().fold(nalgebra::Isometry3::identity(), |acc, f| {
                    acc * rotation_about_line(&Line::new(f.axis, f.point), f.angle)
                });
                self.k.mean_focal() * pose.translation.vector.norm() * mn
            })
            .fold(0.0, f64::max)
    }

    /// Pixel residuals of every observation (`None` where a point projects to infinity).
    fn residuals(&self) -> Vec<Option<Vector2<f64>>> {
        let factors: Vec<Vec<JointFactor>> = (0..self.view_factors.len()).map(|v| self.factors(v)).collect();
        self.obs
            .iter()
            .map(|o| {
                let p = project_plane_point(&self.k, &factors[o.view], &self.plane, &self.points[o.point])?;
                Some(p.pixel - o.pixel)
            })
            .collect()
    }

    /// Whitened cost at pixel sigma `sigma`, infinite if a point projects to infinity.
    pub(super) fn cost(&self, sigma: f64, angle_sigma: f64) -> f64 {
        let mut c = 0.0;
        for r in self.residuals() {
            match r {
                Some(r) => c += r.norm_squared() / (sigma * sigma),
                None => return f64::INFINITY,
            }
        }
        for (a, b) in self.angles.iter().zip(&self.angle_cmd) {
            c += ((a - b) / angle_sigma).powi(2);
        }
        if let Some(h) = &self.plane_hold {
            c += h.weight * h.across.iter().map(|a| a.dot(&self.plane).powi(2)).sum::<f64>();
        }
        c + self.joints.iter().map(|j| j.point.norm_squared()).sum::<f64>() + self.plane.norm_squared()
    }

    /// The problem moved by a step of the camera block and of the points.
    fn retract(&self, dc: &DVector<f64>, dp: &[Vector2<f64>]) -> Problem {
        let mut p = self.clone();
        p.k = Intrinsics::new(self.k.fx + dc[0], self.k.fy + dc[1], self.k.cx + dc[2], self.k.cy + dc[3]);
        for (j, js) in p.joints.iter_mut().enumerate() {
            let o = 4 + 4 * j;
            let (b1, b2) = tangent_basis(&js.axis);
            let axis = Unit::new_normalize(js.axis.into_inner() + b1 * dc[o] + b2 * dc[o + 1]);
            let point = js.point + b1 * dc[o + 2] + b2 * dc[o + 3];
            js.point = point - axis.into_inner() * axis.dot(&point);
            js.axis = axis;
        }
        let a0 = 4 + 4 * self.joints.len();
        for (i, a) in p.angles.iter_mut().enumerate() {
            *a += dc[a0 + i];
        }
        let m0 = self.plane_index();
        p.plane += Vector3::new(dc[m0], dc[m0 + 1], dc[m0 + 2]);
        for (x, d) in p.points.iter_mut().zip(dp) {
            *x += d;
        }
        p
    }
}

/// Normal equations: the camera block `u`, its gradient `gc`, per point `v`, `gp` and the
/// coupling `w` (n_camera x 2).
struct Normal {
    u: DMatrix<f64>,
    gc: DVector<f64>,
    v: Vec<Matrix2<f64>>,
    gp: Vec<Vector2<f64>>,
    w: Vec<DMatrix<f64>>,
}

/// Build the normal equations at `p` (module docs).
fn normal_equations(p: &Problem, sigma: f64, angle_sigma: f64) -> Option<Normal> {
    let nc = p.n_camera();
    let np = p.points.len();
    let mut n = Normal {
        u: DMatrix::zeros(nc, nc),
        gc: DVector::zeros(nc),
        v: vec![Matrix2::zeros(); np],
        gp: vec![Vector2::zeros(); np],
        w: vec![DMatrix::zeros(nc, 2); np],
    };
    let factors: Vec<Vec<JointFactor>> = (0..p.view_factors.len()).map(|v| p.factors(v)).collect();
    let a0 = 4 + 4 * p.joints.len();
    let m0 = p.plane_index();
    let mut jc = DMatrix::<f64>::zeros(2, nc);
    for o in &p.obs {
        let proj = project_plane_point(&p.k, &factors[o.view], &p.plane, &p.points[o.point])?;
        let e = (proj.pixel - o.pixel) / sigma;
        jc.fill(0.0);
        jc.view_mut((0, 0), (2, 4)).copy_from(&(proj.d_intrinsics / sigma));
        for (f, &(j, a)) in p.view_factors[o.view].iter().enumerate() {
            let d = &proj.d_factors[f];
            for c in 0..2 {
                jc[(c, 4 + 4 * j)] += d[1][c] / sigma;
                jc[(c, 4 + 4 * j + 1)] += d[2][c] / sigma;
                jc[(c, 4 + 4 * j + 2)] += d[3][c] / sigma;
                jc[(c, 4 + 4 * j + 3)] += d[4][c] / sigma;
                jc[(c, a0 + a)] += d[0][c] / sigma;
            }
        }
        jc.view_mut((0, m0), (2, 3)).copy_from(&(proj.d_plane / sigma));
        let jp = proj.d_point / sigma;
        n.u += jc.transpose() * &jc;
        n.gc += jc.transpose() * e;
        n.v[o.point] += jp.transpose() * jp;
        n.gp[o.point] += jp.transpose() * e;
        n.w[o.point] += jc.transpose() * jp;
    }
    for (i, (a, b)) in p.angles.iter().zip(&p.angle_cmd).enumerate() {
        n.u[(a0 + i, a0 + i)] += 1.0 / (angle_sigma * angle_sigma);
        n.gc[a0 + i] += (a - b) / (angle_sigma * angle_sigma);
    }
    for (j, js) in p.joints.iter().enumerate() {
        let (b1, b2) = tangent_basis(&js.axis);
        let o = 4 + 4 * j + 2;
        let basis = [b1, b2];
        for r in 0..2 {
            n.gc[o + r] += basis[r].dot(&js.point);
            for c in 0..2 {
                n.u[(o + r, o + c)] += basis[r].dot(&basis[c]);
            }
        }
    }
    for i in 0..3 {
        n.u[(m0 + i, m0 + i)] += 1.0;
        n.gc[m0 + i] += p.plane[i];
    }
    if let Some(h) = &p.plane_hold {
        for a in &h.across {
            let g = a * (h.weight * a.dot(&p.plane));
            let hess = a * a.transpose() * h.weight;
            for r in 0..3 {
                n.gc[m0 + r] += g[r];
                for c in 0..3 {
                    n.u[(m0 + r, m0 + c)] += hess[(r, c)];
                }
            }
        }
    }
    Some(n)
}

/// The reduced camera matrix, its right-hand side and the inverted point blocks.
type Reduced = (DMatrix<f64>, DVector<f64>, Vec<Matrix2<f64>>);

/// The reduced camera system `S = U - sum W V^-1 W^T`, `b = -gc + sum W V^-1 gp`, with
/// Marquardt damping `lambda` on the diagonals (zero for the covariance).
fn reduced(n: &Normal, lambda: f64) -> Option<Reduced> {
    let mut s = n.u.clone();
    for i in 0..s.nrows() {
        s[(i, i)] += lambda * n.u[(i, i)].max(1e-12);
    }
    let mut b = -&n.gc;
    let mut v_inv = Vec::with_capacity(n.v.len());
    for ((v, gp), w) in n.v.iter().zip(&n.gp).zip(&n.w) {
        let mut vd = *v;
        for i in 0..2 {
            vd[(i, i)] += lambda * v[(i, i)].max(1e-12);
        }
        let vi = vd.try_inverse()?;
        let wv = w * vi;
        s -= &wv * w.transpose();
        b += &wv * gp;
        v_inv.push(vi);
    }
    Some((s, b, v_inv))
}

/// Levenberg-Marquardt on `p` at pixel sigma `sigma` (module docs).
pub(super) fn adjust(
    mut p: Problem,
    sigma: f64,
    angle_sigma: f64,
    max_iterations: usize,
) -> Result<Problem, AlignError> {
    let mut cost = p.cost(sigma, angle_sigma);
    if !cost.is_finite() {
        return Err(AlignError::Geometry {
            step: "planar adjustment".into(),
            cause: headalign_geometry::GeometryError::InvalidEstimate(
                "the start projects a point to infinity".into(),
            ),
        });
    }
    let mut lambda = 1e-3;
    for _ in 0..max_iterations {
        let Some(n) = normal_equations(&p, sigma, angle_sigma) else { break };
        let mut improved = false;
        for _ in 0..12 {
            let Some((s, b, v_inv)) = reduced(&n, lambda) else {
                lambda *= 10.0;
                continue;
            };
            let Some(dc) = s.clone().cholesky().map(|c| c.solve(&b)) else {
                lambda *= 10.0;
                continue;
            };
            let dp: Vec<Vector2<f64>> =
                (0..p.points.len()).map(|i| v_inv[i] * (-n.gp[i] - n.w[i].transpose() * &dc)).collect();
            let candidate = p.retract(&dc, &dp);
            let c = candidate.cost(sigma, angle_sigma);
            if c.is_finite() && c < cost {
                let rel = (cost - c) / cost.max(1e-300);
                p = candidate;
                cost = c;
                lambda = (lambda * 0.1).max(1e-12);
                improved = rel > 1e-12;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    Ok(p)
}

/// Drop observations beyond `k` robust sigmas and points left with fewer than two; the
/// robust sigma (pixels, per coordinate).
fn reselect(p: &mut Problem, k: f64) -> f64 {
    let res = p.residuals();
    let mut coords: Vec<f64> = res.iter().flatten().flat_map(|r| [r.x.abs(), r.y.abs()]).collect();
    coords.sort_by(f64::total_cmp);
    let mad = coords.get(coords.len() / 2).copied().unwrap_or(1.0);
    let sigma = (1.4826 * mad).max(MIN_SIGMA_PX);
    let keep: Vec<Observation> = p
        .obs
        .iter()
        .zip(&res)
        .filter(|(_, r)| r.is_some_and(|r| r.norm() <= k * sigma))
        .map(|(o, _)| *o)
        .collect();
    let mut count = vec![0usize; p.points.len()];
    for o in &keep {
        count[o.point] += 1;
    }
    // Renumber the points that keep at least two observations.
    let mut new_index = vec![usize::MAX; p.points.len()];
    let (mut points, mut tracks) = (Vec::new(), Vec::new());
    for (i, c) in count.iter().enumerate() {
        if *c >= 2 {
            new_index[i] = points.len();
            points.push(p.points[i]);
            tracks.push(p.tracks[i]);
        }
    }
    p.obs = keep
        .into_iter()
        .filter(|o| new_index[o.point] != usize::MAX)
        .map(|o| Observation { point: new_index[o.point], ..o })
        .collect();
    p.points = points;
    p.tracks = tracks;
    sigma
}

/// The covariance of the camera block at `p` (the inverse of the reduced normal equations
/// at pixel weight `sigma`), `None` where a point projects to infinity or the system is
/// singular.
pub(super) fn covariance_at(p: &Problem, sigma: f64, angle_sigma: f64) -> Option<DMatrix<f64>> {
    let n = normal_equations(p, sigma, angle_sigma)?;
    let (s, _, _) = reduced(&n, 0.0)?;
    s.try_inverse()
}

/// The passes of the module docs; the covariance at the result.
pub(super) fn maximum_likelihood(start: Problem, options: &PlanarOptions) -> Result<Fit, AlignError> {
    let angle_sigma = options.angle_prior_sigma_deg.to_radians();
    // The plane enters bilinearly with the axes' offsets: start it at several distances
    // and keep the fit of least cost.
    let mut best: Option<(f64, Problem)> = None;
    for inverse_distance in PLANE_STARTS {
        let mut s = start.clone();
        s.plane = Vector3::new(0.0, 0.0, inverse_distance);
        let Ok(fit) = adjust(s, 1.0, angle_sigma, options.max_iterations) else { continue };
        let c = fit.cost(1.0, angle_sigma);
        if best.as_ref().is_none_or(|b| c < b.0) {
            best = Some((c, fit));
        }
    }
    let Some((_, mut p)) = best else {
        return Err(AlignError::Geometry {
            step: "planar adjustment".into(),
            cause: headalign_geometry::GeometryError::InvalidEstimate("no start converged".into()),
        });
    };
    let robust = reselect(&mut p, options.reselect_sigmas);
    if p.points.len() < options.min_tracks {
        return Err(AlignError::TooFewTracks {
            what: "on the plane after outlier rejection".into(),
            needed: options.min_tracks,
            got: p.points.len(),
        });
    }
    let p = adjust(p, robust, angle_sigma, options.max_iterations)?;
    let res: Vec<Vector2<f64>> = p.residuals().into_iter().flatten().collect();
    let sum: f64 = res.iter().map(|r| r.norm_squared()).sum();
    let dof = (2 * res.len()).saturating_sub(2 * p.points.len() + p.n_camera() - 1).max(1);
    let sigma_px = (sum / dof as f64).sqrt().max(1e-12);
    let rms_px = (sum / (res.len().max(1) as f64)).sqrt();
    let weight_px = options.covariance_sigma_px.unwrap_or(sigma_px);
    let mut covariance = covariance_at(&p, weight_px, angle_sigma).ok_or_else(|| AlignError::Geometry {
        step: "planar covariance".into(),
        cause: headalign_geometry::GeometryError::Numerical(
            "a point projects to infinity or the normal equations are singular".into(),
        ),
    })?;
    // Only a plane the data determine is profiled (profile.rs): one that moves some view
    // by FAR_PARALLAX_PX and that the plane at infinity does not explain as well.
    let plane_test = test_plane_at_infinity(&p, weight_px, angle_sigma, options.max_iterations);
    let profile = match options.normal_profile_z {
        Some(z) if p.plane_parallax_px() >= FAR_PARALLAX_PX && plane_test.determines_plane() => {
            profile_normal(&p, &mut covariance, weight_px, angle_sigma, z)
        }
        _ => NormalProfile { max_widening: 1.0, ..NormalProfile::default() },
    };
    Ok(Fit { problem: p, covariance, sigma_px, rms_px, profile, plane_test })
}

impl Fit {
    /// The camera's result: intrinsics, axes, plane, and the covariance of the intrinsics
    /// and axis directions.
    pub(super) fn into_camera(self, side: Side) -> CameraPlanar {
        let p = &self.problem;
        let names = ["pan", "elevation", "verge"];
        let mut rows: Vec<usize> = vec![0, 1, 2, 3];
        let mut parameter_names: Vec<String> =
            ["fx", "fy", "cx", "cy"].iter().map(|s| s.to_string()).collect();
        let (mut pan, mut elevation, mut verge) = ([0.0; 3], [0.0; 3], None);
        for (j, js) in p.joints.iter().enumerate() {
            let a = [js.axis.x, js.axis.y, js.axis.z];
            match js.slot {
                0 => pan = a,
                1 => elevation = a,
                _ => verge = Some(a),
            }
            for c in 0..2 {
                rows.push(4 + 4 * j + c);
                parameter_names.push(format!("{}.dir{c}", names[js.slot.min(2)]));
            }
        }
        let covariance = DMatrix::from_fn(rows.len(), rows.len(), |r, c| self.covariance[(rows[r], rows[c])]);
        // The plane normal's direction and its sigma (perpendicular to m).
        let m0 = p.plane_index();
        let cm = self.covariance.view((m0, m0), (3, 3)).into_owned();
        let m = p.plane;
        let mn = m.norm();
        let (normal, sigma_deg) = if mn > 0.0 {
            let u = m / mn;
            let perp = nalgebra::Matrix3::identity() - u * u.transpose();
            let var = (perp * cm * perp).trace().max(0.0);
            (-u, (var.sqrt() / mn).atan().to_degrees())
        } else {
            (Vector3::zeros(), 90.0)
        };
        let parallax_px = p.plane_parallax_px();
        let determined = sigma_deg < NORMAL_UNDETERMINED_DEG
            && parallax_px >= FAR_PARALLAX_PX
            && self.plane_test.determines_plane();
        CameraPlanar {
            side,
            intrinsics: p.k,
            pan,
            elevation,
            verge,
            plane_normal: determined.then_some([normal.x, normal.y, normal.z]),
            plane_normal_sigma_deg: sigma_deg,
            plane_parallax_px: parallax_px,
            covariance,
            parameter_names,
            sigma_px: self.sigma_px,
            rms_px: self.rms_px,
            profile_widening: self.profile.max_widening,
            plane_test: self.plane_test,
            observations: p.obs.len(),
            points: p.points.len(),
            joint_lines: p
                .joints
                .iter()
                .map(|j| (camera_joints(side)[j.slot], Line::new(j.axis, Point3::from(j.point))))
                .collect(),
            plane_m: [m.x, m.y, m.z],
        }
    }
}

/// Test support: `reg`'s observations re-fitted at its pixel sigma from `truth`'s
/// parameters (the same tracks' points where `truth` has them); the costs of `reg` and of
/// the re-fit, and the re-fit (with `reg`'s covariance).
#[cfg(test)]
pub(super) fn restart_from(reg: &Fit, truth: &Fit, options: &PlanarOptions) -> (f64, f64, Option<Fit>) {
    let angle_sigma = options.angle_prior_sigma_deg.to_radians();
    let t = &truth.problem;
    let mut s = reg.problem.clone();
    s.k = t.k;
    s.joints = t.joints.clone();
    s.angles = t.angles.clone();
    s.plane = t.plane;
    for (i, tr) in s.tracks.iter().enumerate() {
        if let Some(j) = t.tracks.iter().position(|x| x == tr) {
            s.points[i] = t.points[j];
        }
    }
    let sig = reg.sigma_px;
    let c_reg = reg.problem.cost(sig, angle_sigma);
    let Ok(problem) = adjust(s, sig, angle_sigma, options.max_iterations) else {
        return (c_reg, f64::INFINITY, None);
    };
    let c = problem.cost(sig, angle_sigma);
    let fit = Fit { problem, covariance: reg.covariance.clone(), ..*reg };
    (c_reg, c, Some(fit))
}
