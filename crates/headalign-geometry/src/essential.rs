//! Calibrated relative pose of a stereo pair, estimated directly (not through `F`).
//!
//! What it computes: `right_from_left` (rotation and unit translation: 5 degrees of
//! freedom) of two cameras with known intrinsics, from point matches, by minimising the
//! sum of squared Sampson distances (pixels) of the fundamental matrix it induces,
//! `F = K_R^-T [t]x R K_L^-1` (Hartley & Zisserman 2nd ed., section 9.6 and 11.4.3),
//! over the matches within a threshold (re-selected each round, MSAC cost to compare
//! solutions). Several starts, the lowest MSAC cost wins; the sign of `t` is chosen by
//! cheirality (most matches in front of both cameras).
//!
//! Why: with a stereo head's nearly parallel cameras the epipoles lie far outside the
//! images and `F` (7 dof) is ill-determined by noisy matches: at 3 px of noise the
//! best-supported `F` of some scenes has its epipole inside the image, with a Sampson cost
//! equal to or lower than the true `F`'s (measured, docs/accuracy.md). Knowing the
//! intrinsics removes two degrees of freedom, and the ambiguity with them.
//!
//! Parametrisation: `R <- exp(w) R` (3), `t <- normalise(t + B d)` with `B` a basis of the
//! tangent plane of the unit sphere at `t` (2). Jacobian: each Sampson distance's
//! analytic gradient with respect to `F`'s nine entries, chained with `dF / d pose` by
//! central differences of the (normalised) `F` (5 columns, step 1e-6: smooth and O(1) in
//! these units). Before, every residual was differenced (10 Sampson evaluations per match
//! per iteration), a tenth of `experiment fig5-verge-tilt`'s time.
//!
//! Pitfalls: the twisted-pair solution (`R` rotated by pi about `t`) has the same `E`; a
//! start near the true `R` (a stereo head: near the identity) avoids it, and cheirality
//! would reject it. Starts with `t` along an image axis cover the usual rigs.

use nalgebra::{Isometry3, Matrix3, Point2, SMatrix, SVector, Translation3, Unit, UnitQuaternion, Vector3};

use crate::camera::Intrinsics;
use crate::fundamental::FundamentalMatrix;
use crate::lm::minimise;
use crate::{GeometryError, Result};

/// Re-selection rounds of [`refine_relative_pose`].
pub const REFINE_ROUNDS: usize = 5;

/// The fundamental matrix (Frobenius norm 1, `x_R^T F x_L = 0`) of two cameras with
/// intrinsics `k_left`, `k_right` and pose `right_from_left`.
pub fn fundamental_from_pose(
    k_left: &Intrinsics,
    k_right: &Intrinsics,
    right_from_left: &Isometry3<f64>,
) -> FundamentalMatrix {
    let t = right_from_left.translation.vector;
    let e = t.cross_matrix() * right_from_left.rotation.to_rotation_matrix().matrix();
    let f = k_right.inverse_matrix().transpose() * e * k_left.inverse_matrix();
    let n = f.norm();
    FundamentalMatrix(if n > 0.0 { f / n } else { f })
}

/// Signed Sampson distance (pixels) of one match under `f` (`x_R^T F x_L = 0`).
pub fn signed_sampson(f: &Matrix3<f64>, l: &Point2<f64>, r: &Point2<f64>) -> f64 {
    let xl = Vector3::new(l.x, l.y, 1.0);
    let xr = Vector3::new(r.x, r.y, 1.0);
    let fx = f * xl;
    let ftx = f.transpose() * xr;
    let den = fx.x * fx.x + fx.y * fx.y + ftx.x * ftx.x + ftx.y * ftx.y;
    if den > 0.0 { xr.dot(&fx) / den.sqrt() } else { f64::INFINITY }
}

/// [`signed_sampson`] and its gradient with respect to the entries of `f` (row-major:
/// entry `3 i + j` is `d s / d F_ij`). With `e = x_R^T F x_L`, `a = F x_L`, `b = F^T x_R`
/// and `d = a_0^2 + a_1^2 + b_0^2 + b_1^2`, `s = e / sqrt d` and
/// `d s / d F_ij = x_Ri x_Lj / sqrt d - e / (2 d^(3/2)) (2 a_i x_Lj [i < 2] + 2 b_j x_Ri [j < 2])`.
/// `None` where `d` vanishes (the distance is then infinite).
pub fn signed_sampson_gradient(
    f: &Matrix3<f64>,
    l: &Point2<f64>,
    r: &Point2<f64>,
) -> Option<(f64, [f64; 9])> {
    let xl = [l.x, l.y, 1.0];
    let xr = [r.x, r.y, 1.0];
    let fx = f * Vector3::from(xl);
    let ftx = f.tr_mul(&Vector3::from(xr));
    let den = fx.x * fx.x + fx.y * fx.y + ftx.x * ftx.x + ftx.y * ftx.y;
    if den.is_nan() || den <= 0.0 {
        return None;
    }
    let e = Vector3::from(xr).dot(&fx);
    let inv = 1.0 / den.sqrt();
    let s = e * inv;
    let k = s / den;
    let mut g = [0.0; 9];
    for i in 0..3 {
        for j in 0..3 {
            let dd = if i < 2 { fx[i] * xl[j] } else { 0.0 } + if j < 2 { ftx[j] * xr[i] } else { 0.0 };
            g[3 * i + j] = xr[i] * xl[j] * inv - k * dd;
        }
    }
    Some((s, g))
}

/// MSAC cost `sum min(d, tau)^2` of a pose over all matches.
pub fn pose_msac(
    k_left: &Intrinsics,
    k_right: &Intrinsics,
    right_from_left: &Isometry3<f64>,
    matches: &[(Point2<f64>, Point2<f64>)],
    tau: f64,
) -> f64 {
    let f = fundamental_from_pose(k_left, k_right, right_from_left).0;
    matches.iter().map(|(l, r)| signed_sampson(&f, l, r).abs().min(tau).powi(2)).sum()
}

#[derive(Clone, Copy)]
struct Pose {
    r: UnitQuaternion<f64>,
    t: Unit<Vector3<f64>>,
}

impl Pose {
    fn iso(&self) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::from(self.t.into_inner()), self.r)
    }

    fn retract(&self, d: &SVector<f64, 5>) -> Pose {
        let w = Vector3::new(d[0], d[1], d[2]);
        let t = self.t.into_inner();
        let a = if t.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
        let b1 = t.cross(&a).normalize();
        let b2 = t.cross(&b1);
        Pose {
            r: UnitQuaternion::from_scaled_axis(w) * self.r,
            t: Unit::new_normalize(t + b1 * d[3] + b2 * d[4]),
        }
    }
}

/// Refine `start` on the matches within `threshold_px` (Sampson distance) of it, re-selected
/// after each refinement (at most [`REFINE_ROUNDS`] rounds, stopping when the set is
/// stable or the MSAC cost stops falling). Returns the pose and its MSAC cost over all
/// matches; `None` when fewer than 6 matches are selected.
pub fn refine_relative_pose(
    k_left: &Intrinsics,
    k_right: &Intrinsics,
    start: &Isometry3<f64>,
    matches: &[(Point2<f64>, Point2<f64>)],
    threshold_px: f64,
) -> Option<(Isometry3<f64>, f64)> {
    let tn = start.translation.vector.norm();
    if !(tn.is_finite() && tn > 0.0) {
        return None;
    }
    let mut pose = Pose { r: start.rotation, t: Unit::new_normalize(start.translation.vector) };
    let f_of = |p: &Pose| fundamental_from_pose(k_left, k_right, &p.iso()).0;
    let msac = |p: &Pose| pose_msac(k_left, k_right, &p.iso(), matches, threshold_px);
    let mut cost = msac(&pose);
    let mut selected: Vec<usize> = Vec::new();
    for round in 0..REFINE_ROUNDS {
        let f = f_of(&pose);
        let d: Vec<f64> = matches.iter().map(|(l, r)| signed_sampson(&f, l, r).abs()).collect();
        // The first round also admits the better half of the matches: a generic start
        // (identity rotation) can be several pixels off for every match.
        let gate = if round == 0 {
            let mut sorted = d.clone();
            sorted.sort_by(f64::total_cmp);
            threshold_px.max(2.0 * sorted.get(sorted.len() / 2).copied().unwrap_or(0.0))
        } else {
            threshold_px
        };
        let next: Vec<usize> = (0..matches.len()).filter(|&i| d[i] <= gate).collect();
        if next.len() < 6 || next == selected {
            break;
        }
        selected = next;
        let residuals = |p: &Pose| -> Vec<f64> {
            let f = f_of(p);
            selected.iter().map(|&i| signed_sampson(&f, &matches[i].0, &matches[i].1)).collect()
        };
        let ls_cost = |p: &Pose| residuals(p).iter().map(|v| v * v).sum::<f64>();
        let normal = |p: &Pose| -> Option<(SMatrix<f64, 5, 5>, SVector<f64, 5>)> {
            let f = f_of(p);
            let df = pose_jacobian_of_f(p, &f_of);
            let mut jtj = SMatrix::<f64, 5, 5>::zeros();
            let mut jtr = SVector::<f64, 5>::zeros();
            for &i in &selected {
                let (l, r) = &matches[i];
                let Some((s, g)) = signed_sampson_gradient(&f, l, r) else { continue };
                let row = SMatrix::<f64, 1, 9>::from_row_slice(&g) * df;
                jtr += row.transpose() * s;
                jtj += row.transpose() * row;
            }
            (jtj.iter().all(|v| v.is_finite()) && jtr.iter().all(|v| v.is_finite())).then_some((jtj, jtr))
        };
        let start_cost = ls_cost(&pose);
        if !start_cost.is_finite() {
            return None;
        }
        let (refined, _) = minimise(pose, start_cost, 50, normal, |p, d| Some(p.retract(d)), ls_cost);
        let c = msac(&refined);
        if round > 0 && c > cost {
            break;
        }
        pose = refined;
        cost = c;
    }
    (selected.len() >= 6 && cost.is_finite()).then(|| (pose.iso(), cost))
}

/// `d F / d pose` (9 x 5: `F`'s entries row-major against the pose's tangent parameters)
/// by central differences (step 1e-6) of `f_of`, which includes `F`'s normalisation.
fn pose_jacobian_of_f(p: &Pose, f_of: &impl Fn(&Pose) -> Matrix3<f64>) -> SMatrix<f64, 9, 5> {
    let h = 1e-6;
    let mut df = SMatrix::<f64, 9, 5>::zeros();
    for k in 0..5 {
        let mut d = SVector::<f64, 5>::zeros();
        d[k] = h;
        let diff = (f_of(&p.retract(&d)) - f_of(&p.retract(&(-d)))) / (2.0 * h);
        for i in 0..3 {
            for j in 0..3 {
                df[(3 * i + j, k)] = diff[(i, j)];
            }
        }
    }
    df
}

/// Depths `(z_left, z_right)` of the ray pair `x1` (left, normalised) and `x2` (right) under
/// `X_R = R X_L + t`, by least squares on `z2 x2 = z1 R x1 + t`.
fn depths(rot: &Matrix3<f64>, t: &Vector3<f64>, x1: &Vector3<f64>, x2: &Vector3<f64>) -> (f64, f64) {
    let a = nalgebra::Matrix3x2::from_columns(&[rot * x1, -x2]);
    let ata = a.transpose() * a;
    let Some(inv) = ata.try_inverse() else { return (f64::NAN, f64::NAN) };
    let z = inv * (a.transpose() * (-t));
    (z[0], z[1])
}

/// Sign of `t` by cheirality: the pose with `t` or `-t` that puts more of the matches within
/// `threshold_px` in front of both cameras, with that count and the number of such matches.
fn oriented(
    k_left: &Intrinsics,
    k_right: &Intrinsics,
    pose: &Isometry3<f64>,
    matches: &[(Point2<f64>, Point2<f64>)],
    threshold_px: f64,
) -> (Isometry3<f64>, usize, usize) {
    let rot = *pose.rotation.to_rotation_matrix().matrix();
    let t = pose.translation.vector;
    let (kl, kr) = (k_left.inverse_matrix(), k_right.inverse_matrix());
    let f = fundamental_from_pose(k_left, k_right, pose).0;
    let (mut plus, mut minus, mut total) = (0usize, 0usize, 0usize);
    for (l, r) in matches {
        if signed_sampson(&f, l, r).abs() > threshold_px {
            continue;
        }
        total += 1;
        let x1 = kl * Vector3::new(l.x, l.y, 1.0);
        let x2 = kr * Vector3::new(r.x, r.y, 1.0);
        let (a, b) = depths(&rot, &t, &x1, &x2);
        plus += usize::from(a > 0.0 && b > 0.0);
        let (a, b) = depths(&rot, &(-t), &x1, &x2);
        minus += usize::from(a > 0.0 && b > 0.0);
    }
    let t = if plus >= minus { t } else { -t };
    (Isometry3::from_parts(Translation3::from(t), pose.rotation), plus.max(minus), total)
}

/// The calibrated relative pose (module docs): each of `starts` refined by
/// [`refine_relative_pose`] and given `t`'s sign by cheirality; among the solutions that
/// put most of their matches in front of both cameras (the twisted pair of the same `E`
/// puts none), the lowest MSAC cost wins. Returns the pose and its MSAC cost; errors with
/// a bad threshold or no acceptable solution.
pub fn calibrated_relative_pose(
    k_left: &Intrinsics,
    k_right: &Intrinsics,
    starts: &[Isometry3<f64>],
    matches: &[(Point2<f64>, Point2<f64>)],
    threshold_px: f64,
) -> Result<(Isometry3<f64>, f64)> {
    if !(threshold_px.is_finite() && threshold_px > 0.0) {
        return Err(GeometryError::InvalidOption(format!("threshold must be positive, got {threshold_px}")));
    }
    let mut best: Option<(Isometry3<f64>, f64)> = None;
    for s in starts {
        let Some((p, c)) = refine_relative_pose(k_left, k_right, s, matches, threshold_px) else { continue };
        let (p, in_front, total) = oriented(k_left, k_right, &p, matches, threshold_px);
        if 2 * in_front <= total {
            continue;
        }
        if best.as_ref().is_none_or(|(_, b)| c < *b) {
            best = Some((p, c));
        }
    }
    best.ok_or_else(|| {
        GeometryError::Degenerate("no relative pose puts the matches in front of both cameras".into())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;
    use proptest::prelude::*;

    fn rig(yaw: f64, tx: f64, ty: f64, tz: f64) -> (Intrinsics, Intrinsics, Isometry3<f64>) {
        let kl = Intrinsics { fx: 700.0, fy: 720.0, skew: 0.0, cx: 390.0, cy: 284.0 };
        let kr = Intrinsics { fx: 705.0, fy: 716.0, skew: 0.0, cx: 380.0, cy: 290.0 };
        let t = Vector3::new(tx, ty, tz).normalize();
        let r = UnitQuaternion::from_euler_angles(0.01, yaw, -0.005);
        (kl, kr, Isometry3::from_parts(Translation3::from(t), r))
    }

    fn matches(
        kl: &Intrinsics,
        kr: &Intrinsics,
        pose: &Isometry3<f64>,
        seed: u64,
    ) -> Vec<(Point2<f64>, Point2<f64>)> {
        let mut out = Vec::new();
        let mut s = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        let mut u = || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        while out.len() < 150 {
            // Scene 10-40 baselines ahead, spread over the view.
            let z = 10.0 + 30.0 * u();
            let p = Point3::new((u() - 0.5) * z, (u() - 0.5) * 0.75 * z, z);
            let q = pose * p;
            if q.z <= 0.0 {
                continue;
            }
            let pl = kl.project(&p);
            let pr = kr.project(&q);
            if let (Some(pl), Some(pr)) = (pl, pr) {
                out.push((pl, pr));
            }
        }
        out
    }

    /// The induced F is zero on exact matches.
    #[test]
    fn fundamental_from_pose_is_consistent() {
        let (kl, kr, pose) = rig(-0.12, -1.0, 0.02, -0.08);
        let f = fundamental_from_pose(&kl, &kr, &pose);
        for (l, r) in matches(&kl, &kr, &pose, 3) {
            assert!(f.sampson_distance(&l, &r) < 1e-9);
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        /// The Sampson distance's analytic gradient against central differences over
        /// random rigs and matches. In pixel coordinates a unit-norm F's entries weigh
        /// products of coordinates of hundreds of pixels (gradients up to ~1e6 px per unit),
        /// so the step is 1e-8: truncation was measured 1.2e-6 relative at 1e-6, so about
        /// 1e-10 here; rounding about 1e-16 * 1e5 / 1e-8 = 1e-3 px per unit, 1e-9 relative.
        #[test]
        fn sampson_gradient_matches_finite_differences(
            seed in 0u64..1000, yaw in -0.2f64..0.2, ty in -0.2f64..0.2, tz in -0.3f64..0.3,
            dx in -3.0f64..3.0, dy in -3.0f64..3.0,
        ) {
            let (kl, kr, pose) = rig(yaw, -1.0, ty, tz);
            let f = fundamental_from_pose(&kl, &kr, &pose).0;
            for (l, r) in matches(&kl, &kr, &pose, seed).into_iter().take(5) {
                let r = Point2::new(r.x + dx, r.y + dy);
                let (s0, g) = signed_sampson_gradient(&f, &l, &r).unwrap();
                prop_assert!((s0 - signed_sampson(&f, &l, &r)).abs() <= 1e-12 * s0.abs().max(1.0));
                let scale = g.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
                for k in 0..9 {
                    let h = 1e-8;
                    let mut fp = f;
                    fp[(k / 3, k % 3)] += h;
                    let mut fm = f;
                    fm[(k / 3, k % 3)] -= h;
                    let fd = (signed_sampson(&fp, &l, &r) - signed_sampson(&fm, &l, &r)) / (2.0 * h);
                    prop_assert!((fd - g[k]).abs() <= 1e-6 * scale, "entry {}: {} vs {}", k, g[k], fd);
                }
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]
        /// Noise-free: from generic starts (identity rotation, t along x or y) the pose is
        /// recovered to 1e-7 (rotation, radians; translation direction) with the right sign.
        #[test]
        fn noise_free_pose_is_recovered(
            seed in 0u64..1000, yaw in -0.2f64..0.2, ty in -0.1f64..0.1, tz in -0.2f64..0.2, side in 0usize..2,
        ) {
            let tx = if side == 0 { -1.0 } else { 1.0 };
            let (kl, kr, pose) = rig(yaw, tx, ty, tz);
            let m = matches(&kl, &kr, &pose, seed);
            let starts = [
                Isometry3::from_parts(Translation3::new(1.0, 0.0, 0.0), UnitQuaternion::identity()),
                Isometry3::from_parts(Translation3::new(0.0, 1.0, 0.0), UnitQuaternion::identity()),
            ];
            let (est, cost) = calibrated_relative_pose(&kl, &kr, &starts, &m, 3.0).unwrap();
            prop_assert!(cost < 1e-12, "{cost}");
            prop_assert!(est.rotation.angle_to(&pose.rotation) < 1e-7);
            prop_assert!((est.translation.vector - pose.translation.vector).norm() < 1e-7);
        }
    }

    #[test]
    fn rejects_a_bad_threshold() {
        let (kl, kr, pose) = rig(0.0, -1.0, 0.0, 0.0);
        assert!(calibrated_relative_pose(&kl, &kr, &[pose], &[], f64::NAN).is_err());
        assert!(calibrated_relative_pose(&kl, &kr, &[pose], &[], 1.0).is_err());
    }
}
