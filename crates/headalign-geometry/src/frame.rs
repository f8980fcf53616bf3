//! A well-conditioned (quasi-Euclidean) projective frame for a stereo rig
//! ("Conditioning" in `docs/how-it-works.md#projective-structure-from-one-rig`).
//!
//! Any pair `P_L = [I | 0]`, `P_R = [[e']x F + e' v^T | lambda e']` is consistent with a
//! fundamental matrix `F` (Hartley & Zisserman result 9.15). The canonical choice
//! `v = 0` puts the plane at infinity far from `(0, 0, 0, 1)` and makes the later linear
//! self-calibration numerically useless. Here instead:
//! 1. pixels are conditioned by a rough calibration `K0` (focal = image width, centre of
//!    the image), `F_n = K0^T F K0`;
//! 2. `F_n` is decomposed as if it were an essential matrix, giving four `(R, t)`; the one
//!    that puts the given matches in front of both cameras is kept (cheirality);
//! 3. the scale of `[e']x F_n` and the frame vector `v` are chosen by linear least squares
//!    so that the left 3x3 block of `P_R` is as close as possible to `R`, and the last
//!    column is `t` (unit norm).
//!
//! The frame is then nearly Euclidean (up to the error of `K0`), the plane at infinity is
//! close to `(0, 0, 0, 1)`, and the stacked `[H_i^T - I]` of small rotations is well
//! conditioned. Both returned cameras map to pixels: `P_L = K0 [I | 0]`,
//! `P_R = K0 [A | t]`; the projective frame itself is expressed in conditioned
//! coordinates, so a calibration found in it is relative to `K0`.
//!
//! Degrees of freedom: the frame has 4 (v and lambda), all fixed here. Pitfall: the
//! cheirality vote needs matches that are not all at infinity; ties are an error.

use nalgebra::{Matrix3, Matrix3x4, Point2, SMatrix, SVector, Vector3};

use crate::camera::{Intrinsics, ProjectiveCamera};
use crate::so3::skew;
use crate::{GeometryError, Result};

/// The quasi-Euclidean frame of a stereo rig.
#[derive(Debug, Clone, Copy)]
pub struct StereoFrame {
    /// The conditioning calibration `K0`.
    pub k0: Intrinsics,
    /// Right camera in conditioned coordinates, `[A | t]` (the left is `[I | 0]`).
    pub right_conditioned: Matrix3x4<f64>,
    /// The rotation `R` of the essential-matrix decomposition that `A` approximates.
    pub rotation_guess: Matrix3<f64>,
}

impl StereoFrame {
    /// Left camera in pixels, `K0 [I | 0]`.
    pub fn left_camera(&self) -> ProjectiveCamera {
        ProjectiveCamera(self.k0.matrix() * Matrix3x4::identity())
    }

    /// Right camera in pixels, `K0 [A | t]`.
    pub fn right_camera(&self) -> ProjectiveCamera {
        ProjectiveCamera(self.k0.matrix() * self.right_conditioned)
    }
}

/// The four essential-matrix decompositions of a 3x3 matrix treated as essential.
fn essential_decompositions(e: &Matrix3<f64>) -> Result<[(Matrix3<f64>, Vector3<f64>); 4]> {
    let svd = e
        .try_svd(true, true, 1e-15, 500)
        .ok_or_else(|| GeometryError::Numerical("SVD of F failed".into()))?;
    let (mut u, mut v_t) = match (svd.u, svd.v_t) {
        (Some(u), Some(v_t)) => (u, v_t),
        _ => return Err(GeometryError::Numerical("SVD of F returned no vectors".into())),
    };
    // nalgebra does not sort singular values: put the smallest last.
    let s = svd.singular_values;
    let imin = if s[0] <= s[1] && s[0] <= s[2] {
        0
    } else if s[1] <= s[2] {
        1
    } else {
        2
    };
    if imin != 2 {
        u.swap_columns(imin, 2);
        v_t.swap_rows(imin, 2);
    }
    if u.determinant() < 0.0 {
        u = -u;
    }
    if v_t.determinant() < 0.0 {
        v_t = -v_t;
    }
    let w = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
    let r1 = u * w * v_t;
    let r2 = u * w.transpose() * v_t;
    let t: Vector3<f64> = u.column(2).into_owned();
    Ok([(r1, t), (r1, -t), (r2, t), (r2, -t)])
}

/// Depths of a conditioned match in `[I|0]` and `[R|t]` by the midpoint-free linear
/// method: solves `z2 x2 = z1 R x1 + t` in least squares.
fn depths(r: &Matrix3<f64>, t: &Vector3<f64>, x1: &Vector3<f64>, x2: &Vector3<f64>) -> (f64, f64) {
    let a = r * x1;
    // [a, -x2] [z1; z2] = -t
    let m = nalgebra::Matrix3x2::from_columns(&[a, -x2]);
    let mtm = m.transpose() * m;
    match mtm.try_inverse() {
        Some(inv) => {
            let z = inv * (m.transpose() * (-t));
            (z[0], z[1])
        }
        None => (0.0, 0.0),
    }
}

/// The quasi-Euclidean frame of a rig with fundamental matrix `f` (pixels,
/// `x_R^T F x_L = 0`), conditioned by `k0`, with `matches` (left, right pixels, ideally
/// inliers) for the cheirality vote.
pub fn quasi_euclidean_frame(
    f: &Matrix3<f64>,
    k0: &Intrinsics,
    matches: &[(Point2<f64>, Point2<f64>)],
) -> Result<StereoFrame> {
    if matches.is_empty() {
        return Err(GeometryError::NotEnoughData {
            what: "matches for the cheirality vote",
            needed: 1,
            got: 0,
        });
    }
    let k = k0.matrix();
    let k_inv = k0.inverse_matrix();
    let mut f_n = k.transpose() * f * k;
    let norm = f_n.norm();
    if !norm.is_finite() || norm <= 0.0 {
        return Err(GeometryError::InvalidEstimate("fundamental matrix is zero or not finite".into()));
    }
    f_n /= norm;
    let (rot, t) = pose_by_cheirality(&f_n, &k_inv, &k_inv, matches)?;
    // A = alpha [t]x F_n + t v^T closest to R: 4 unknowns (alpha, v), 9 equations.
    let b = skew(&t) * f_n;
    let mut design = SMatrix::<f64, 9, 4>::zeros();
    let mut rhs = SVector::<f64, 9>::zeros();
    for i in 0..3 {
        for j in 0..3 {
            let row = 3 * i + j;
            design[(row, 0)] = b[(i, j)];
            design[(row, 1 + j)] = t[i];
            rhs[row] = rot[(i, j)];
        }
    }
    let sol = (design.transpose() * design)
        .try_inverse()
        .ok_or_else(|| GeometryError::Numerical("frame least squares is singular".into()))?
        * (design.transpose() * rhs);
    let v = Vector3::new(sol[1], sol[2], sol[3]);
    let a = b * sol[0] + t * v.transpose();
    let mut right = Matrix3x4::zeros();
    right.fixed_view_mut::<3, 3>(0, 0).copy_from(&a);
    right.set_column(3, &t);
    Ok(StereoFrame { k0: *k0, right_conditioned: right, rotation_guess: rot })
}

/// The `(R, t)` (`|t| = 1`) of the four decompositions of the essential matrix `e` (in
/// coordinates normalised by `k_left_inv`, `k_right_inv`) that puts most of `matches`
/// (pixels) in front of both cameras. Errors on a tied vote.
fn pose_by_cheirality(
    e: &Matrix3<f64>,
    k_left_inv: &Matrix3<f64>,
    k_right_inv: &Matrix3<f64>,
    matches: &[(Point2<f64>, Point2<f64>)],
) -> Result<(Matrix3<f64>, Vector3<f64>)> {
    let candidates = essential_decompositions(e)?;
    let rays: Vec<(Vector3<f64>, Vector3<f64>)> = matches
        .iter()
        .map(|(l, r)| (k_left_inv * Vector3::new(l.x, l.y, 1.0), k_right_inv * Vector3::new(r.x, r.y, 1.0)))
        .collect();
    let mut votes = [0usize; 4];
    for (c, (r, t)) in candidates.iter().enumerate() {
        votes[c] = rays
            .iter()
            .filter(|(x1, x2)| {
                let (z1, z2) = depths(r, t, x1, x2);
                z1 > 0.0 && z2 > 0.0
            })
            .count();
    }
    let best = (0..4).max_by_key(|&c| votes[c]).unwrap_or(0);
    let runner_up = (0..4).filter(|&c| c != best).map(|c| votes[c]).max().unwrap_or(0);
    if votes[best] == 0 || votes[best] == runner_up {
        return Err(GeometryError::Degenerate(
            "cannot tell which side of the cameras the scene is on (cheirality vote tied)".into(),
        ));
    }
    let (rot, t) = candidates[best];
    Ok((rot, t))
}

/// Relative pose `right_from_left` (unit translation) of two calibrated cameras from their
/// fundamental matrix (pixels, `x_R^T F x_L = 0`), by decomposing `E = K_R^T F K_L` and
/// keeping the solution that puts `matches` in front of both cameras (H&Z section 9.6).
pub fn relative_pose(
    f: &Matrix3<f64>,
    k_left: &Intrinsics,
    k_right: &Intrinsics,
    matches: &[(Point2<f64>, Point2<f64>)],
) -> Result<nalgebra::Isometry3<f64>> {
    if matches.is_empty() {
        return Err(GeometryError::NotEnoughData {
            what: "matches for the cheirality vote",
            needed: 1,
            got: 0,
        });
    }
    let e = k_right.matrix().transpose() * f * k_left.matrix();
    let n = e.norm();
    if !n.is_finite() || n <= 0.0 {
        return Err(GeometryError::InvalidEstimate("essential matrix is zero or not finite".into()));
    }
    let (rot, t) =
        pose_by_cheirality(&(e / n), &k_left.inverse_matrix(), &k_right.inverse_matrix(), matches)?;
    let r =
        crate::so3::nearest_rotation(&rot).ok_or_else(|| GeometryError::Numerical("SVD failed".into()))?;
    Ok(nalgebra::Isometry3::from_parts(t.into(), nalgebra::UnitQuaternion::from_rotation_matrix(&r)))
}

/// The fundamental matrix (pixels, `x_R^T F x_L = 0`) of two calibrated cameras related by
/// `right_from_left`: `K_R^-T [t]x R K_L^-1`.
pub fn fundamental_of_pose(
    right_from_left: &nalgebra::Isometry3<f64>,
    k_left: &Intrinsics,
    k_right: &Intrinsics,
) -> Matrix3<f64> {
    let e = skew(&right_from_left.translation.vector)
        * right_from_left.rotation.to_rotation_matrix().into_inner();
    k_right.inverse_matrix().transpose() * e * k_left.inverse_matrix()
}

/// Signed Sampson distance (pixels) of one match under `f`; `None` where it is undefined.
fn signed_sampson(f: &Matrix3<f64>, l: &Point2<f64>, r: &Point2<f64>) -> Option<f64> {
    let (xl, xr) = (Vector3::new(l.x, l.y, 1.0), Vector3::new(r.x, r.y, 1.0));
    let (fx, ftx) = (f * xl, f.transpose() * xr);
    let den = fx.x * fx.x + fx.y * fx.y + ftx.x * ftx.x + ftx.y * ftx.y;
    (den > 0.0).then(|| xr.dot(&fx) / den.sqrt())
}

/// Refine a calibrated relative pose (unit translation) on its 5 degrees of freedom
/// (rotation, translation direction) by Levenberg-Marquardt on the sum of squared Sampson
/// distances (pixels) of `matches` (left, right) under [`fundamental_of_pose`] (the
/// first-order ML estimate for isotropic pixel noise, H&Z section 11.4.3, with the
/// intrinsics held fixed). Unlike decomposing a fitted 7-dof `F` ([`relative_pose`]), the
/// two surplus degrees of freedom cannot absorb noise that then leaks into the pose when
/// `F` is projected onto the essential manifold. Returns the refined pose and its RMS
/// Sampson distance (px); never a pose worse than `start`. The Jacobian is by central
/// differences (5 parameters: cheap, and tested against the noise-free optimum).
pub fn refine_relative_pose(
    start: &nalgebra::Isometry3<f64>,
    k_left: &Intrinsics,
    k_right: &Intrinsics,
    matches: &[(Point2<f64>, Point2<f64>)],
    max_iterations: usize,
) -> Result<(nalgebra::Isometry3<f64>, f64)> {
    if matches.len() < 5 {
        return Err(GeometryError::NotEnoughData {
            what: "matches to refine a pose",
            needed: 5,
            got: matches.len(),
        });
    }
    let t0 = start.translation.vector;
    let n0 = t0.norm();
    if n0.is_nan() || n0 <= 0.0 {
        return Err(GeometryError::InvalidEstimate("pose translation is zero".into()));
    }
    type State = (nalgebra::UnitQuaternion<f64>, Vector3<f64>);
    let pose = |s: &State| nalgebra::Isometry3::from_parts(s.1.into(), s.0);
    let residuals = |s: &State| -> Option<Vec<f64>> {
        let f = fundamental_of_pose(&pose(s), k_left, k_right);
        matches.iter().map(|(l, r)| signed_sampson(&f, l, r)).collect()
    };
    let cost = |s: &State| residuals(s).map_or(f64::INFINITY, |r| r.iter().map(|x| x * x).sum());
    // Retraction: rotation increment on the left, translation along two directions
    // orthogonal to it, renormalised.
    let retract = |s: &State, d: &SVector<f64, 5>| -> Option<State> {
        let t = s.1.normalize();
        let a = if t.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
        let b1 = t.cross(&a).normalize();
        let b2 = t.cross(&b1);
        let rot = nalgebra::UnitQuaternion::from_scaled_axis(Vector3::new(d[0], d[1], d[2])) * s.0;
        let tn = (t + b1 * d[3] + b2 * d[4]).try_normalize(1e-300)?;
        Some((rot, tn))
    };
    let normal = |s: &State| -> Option<(SMatrix<f64, 5, 5>, SVector<f64, 5>)> {
        let r = residuals(s)?;
        const H: f64 = 1e-6;
        let mut jac = vec![[0.0; 5]; r.len()];
        for k in 0..5 {
            let mut d = SVector::<f64, 5>::zeros();
            d[k] = H;
            let plus = residuals(&retract(s, &d)?)?;
            d[k] = -H;
            let minus = residuals(&retract(s, &d)?)?;
            for (row, (p, m)) in jac.iter_mut().zip(plus.iter().zip(&minus)) {
                row[k] = (p - m) / (2.0 * H);
            }
        }
        let (mut jtj, mut jtr) = (SMatrix::<f64, 5, 5>::zeros(), SVector::<f64, 5>::zeros());
        for (row, ri) in jac.iter().zip(&r) {
            let j = SVector::<f64, 5>::from_column_slice(row);
            jtj += j * j.transpose();
            jtr += j * *ri;
        }
        Some((jtj, jtr))
    };
    let s0: State = (start.rotation, t0.normalize());
    let c0 = cost(&s0);
    if !c0.is_finite() {
        return Err(GeometryError::InvalidEstimate("Sampson distance undefined at the start pose".into()));
    }
    let (s, c) = crate::lm::minimise(s0, c0, max_iterations, normal, retract, cost);
    Ok((pose(&s), (c / matches.len() as f64).sqrt()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion};
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        /// With true K equal to K0 and noise-free data, F is an exact essential matrix in
        /// conditioned coordinates, so the frame must be exactly Euclidean:
        /// `A = R`, `t = t_true / |t_true|` (1e-9: SVD of a well-conditioned 3x3).
        #[test]
        fn exact_calibration_gives_euclidean_frame(rx in -0.1..0.1f64, ry in -0.3..0.3f64, rz in -0.1..0.1f64, ty in -0.1..0.1f64, tz in -0.1..0.1f64) {
            let k0 = Intrinsics::rough_guess(768, 576);
            let rot = UnitQuaternion::from_euler_angles(rx, ry, rz);
            let t = Vector3::new(-1.0, ty, tz);
            let right_from_left = Isometry3::from_parts(Translation3::from(t), rot);
            let e = skew(&t) * rot.to_rotation_matrix().into_inner();
            let f = k0.inverse_matrix().transpose() * e * k0.inverse_matrix();
            let pts: Vec<_> = (0..20).map(|i| {
                let p = Point3::new(-1.0 + 0.1 * i as f64, 0.3 - 0.03 * i as f64, 4.0 + 0.2 * i as f64);
                (k0.project(&p).unwrap(), k0.project(&(right_from_left * p)).unwrap())
            }).collect();
            let frame = quasi_euclidean_frame(&f, &k0, &pts).unwrap();
            let a = frame.right_conditioned.fixed_view::<3, 3>(0, 0).into_owned();
            prop_assert!((a - rot.to_rotation_matrix().into_inner()).norm() < 1e-9);
            prop_assert!((frame.right_conditioned.column(3) - t.normalize()).norm() < 1e-9);
            // The pixel cameras reproduce the matches.
            let pr = frame.right_camera();
            for (i, (_, xr)) in pts.iter().enumerate() {
                let p = Point3::new(-1.0 + 0.1 * i as f64, 0.3 - 0.03 * i as f64, 4.0 + 0.2 * i as f64);
                let x = nalgebra::Vector4::new(p.x, p.y, p.z, t.norm());
                let proj = pr.project(&x).unwrap();
                prop_assert!((proj - xr).norm() < 1e-6);
            }
        }
    }

    #[test]
    fn errors_on_bad_input() {
        let k0 = Intrinsics::rough_guess(768, 576);
        assert!(
            quasi_euclidean_frame(&Matrix3::zeros(), &k0, &[(Point2::origin(), Point2::origin())]).is_err()
        );
        assert!(quasi_euclidean_frame(&Matrix3::identity(), &k0, &[]).is_err());
    }
    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]
        /// Noise-free matches of random rigs: from a start pose perturbed by up to ~1.7 deg
        /// in rotation and ~3 deg in translation direction, the refinement recovers the true
        /// pose (1e-7 rad: the optimum is exact, LM stops on relative cost decrease near
        /// 1e-14).
        #[test]
        fn refine_relative_pose_recovers_noise_free_rigs(
            rx in -0.1..0.1f64, ry in -0.3..0.3f64, rz in -0.1..0.1f64, ty in -0.1..0.1f64, tz in -0.1..0.1f64,
            px in -0.03..0.03f64, pt in -0.05..0.05f64,
        ) {
            let kl = Intrinsics::rough_guess(768, 576);
            let kr = Intrinsics { fx: kl.fx * 1.02, cx: kl.cx + 20.0, ..kl };
            let rot = UnitQuaternion::from_euler_angles(rx, ry, rz);
            let t = Vector3::new(-1.0, ty, tz).normalize();
            let truth = Isometry3::from_parts(Translation3::from(t), rot);
            let pts: Vec<_> = (0..40).map(|i| {
                let p = Point3::new(-1.5 + 0.075 * i as f64, 0.8 - 0.04 * ((i * 7) % 40) as f64, 3.0 + 0.25 * ((i * 13) % 40) as f64);
                (kl.project(&p).unwrap(), kr.project(&(truth * p)).unwrap())
            }).collect();
            let start = Isometry3::from_parts(
                Translation3::from((t + Vector3::new(0.0, pt, -pt)).normalize()),
                UnitQuaternion::from_euler_angles(px, -px, px) * rot,
            );
            let (got, rms) = refine_relative_pose(&start, &kl, &kr, &pts, 100).unwrap();
            prop_assert!(rms < 1e-6, "rms {rms}");
            prop_assert!(got.rotation.angle_to(&rot) < 1e-7);
            prop_assert!((got.translation.vector - t).norm() < 1e-7);
        }
    }

    #[test]
    fn refine_relative_pose_errors_on_bad_input() {
        let k = Intrinsics::rough_guess(768, 576);
        let one = (Point2::new(1.0, 2.0), Point2::new(3.0, 4.0));
        assert!(refine_relative_pose(&Isometry3::identity(), &k, &k, &[one; 10], 10).is_err());
        let pose = Isometry3::from_parts(Translation3::new(-1.0, 0.0, 0.0), UnitQuaternion::identity());
        assert!(refine_relative_pose(&pose, &k, &k, &[one; 4], 10).is_err());
    }
}
