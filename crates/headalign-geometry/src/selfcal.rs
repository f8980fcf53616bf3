//! Linear self-calibration of a stereo rig from rigid motions (paper section 3.1,
//! `docs/how-it-works.md#linear-self-calibration`; Hartley & Zisserman 2nd ed. sections 10.4, 19.5).
//!
//! Input: 4x4 projective homographies `H_i` mapping the projective reconstruction of one
//! view to that of another (`Y ~ H_i X`), all in the projective frame with the left
//! camera `[I | 0]` (here in *conditioned* coordinates, see [`crate::frame`]). Each is
//! conjugate to a rigid motion: `H_i ~ H_PE^-1 D_i H_PE`,
//! `H_PE = [[K^-1, 0], [a^T, d]]`.
//!
//! Steps, each a pure function:
//! 1. [`plane_at_infinity`]: `(a, d)` is the common fixed plane, the null vector of the
//!    stacked `[H_1^T - I; H_2^T - I; ...]` (each `H_i` scaled to determinant +1). A single
//!    rotation fixes a whole pencil of planes: two rotations about different axes are
//!    needed; rotations about one axis are reported as degenerate (a second singular value
//!    near zero).
//! 2. [`infinite_homography`]: `M_i = A_i - b_i a^T / d`, scaled to determinant 1, equals
//!    `K R_i K^-1`.
//! 3. [`dual_image_of_absolute_conic`]: `w* = K K^T` solves `M_i w* M_i^T = w*`, six linear
//!    equations per motion in the six entries of the symmetric `w*`; least squares by SVD,
//!    then a check that it is positive definite.
//! 4. [`k_from_dual_conic`]: the upper-triangular factor `K` with `K K^T = w*`.
//! 5. [`euclidean_upgrade`], [`motion_from_homography`], [`decompose_camera`]: `H_PE`, the
//!    rigid motions `D_i = H_PE H_i H_PE^-1` (rotation block projected onto SO(3)), and
//!    `K_R [R | t]` from the right camera `P_R H_PE^-1` (RQ decomposition).
//!
//! 6. [`plane_at_infinity_general`] and [`calibrate_from_infinite_homographies`]: the same
//!    from ONE general screw motion (its only fixed plane is the plane at infinity) with
//!    prior constraints on `K` (zero skew, square pixels, known principal point), linear in
//!    the image of the absolute conic `w = K^-T K^-1` (H&Z section 19.6).
//!
//! Degrees of freedom: the plane at infinity 3, `K` 5; the metric scale of the Euclidean
//! frame is a gauge (fixed here by `d`, later by the baseline). Pitfall: everything is
//! linear and noise-sensitive (small rotations make `H_i` close to the identity); it is an
//! initialisation for the bundle adjustment, and it needs a well-conditioned frame.

use nalgebra::{
    Isometry3, Matrix3, Matrix3x4, Matrix4, SMatrix, Translation3, UnitQuaternion, Vector3, Vector4,
};

use crate::camera::Intrinsics;
use crate::homography3d::Homography3;
use crate::so3::nearest_rotation;
use crate::{GeometryError, Result};

/// Ratio of the second-smallest to the largest singular value below which the plane at
/// infinity is reported as not determined (rotations about a single axis, or no motion).
pub const PLANE_DEGENERACY_RATIO: f64 = 1e-9;

/// The plane at infinity `(a, d)` (unit 4-vector, sign with `d >= 0`) fixed by all the
/// given homographies, each of which is first scaled to determinant +1.
///
/// Errors: fewer than two homographies, a homography with non-positive determinant, or
/// motions that leave more than one plane fixed (rotations about one axis).
pub fn plane_at_infinity(homographies: &[Homography3]) -> Result<Vector4<f64>> {
    fixed_plane(homographies, 2).map(|(plane, _)| plane)
}

/// The plane at infinity from one or more motions, with its conditioning: the ratio of
/// the second-smallest to the largest singular value of the stacked `[H_i^T - I]` (near 0:
/// the plane is barely determined). One motion suffices when it is a *general* screw
/// motion (a translation along its rotation axis): its only fixed plane is the plane at
/// infinity. A pure rotation, or a planar motion (translation perpendicular to the axis),
/// fixes a pencil of planes and is reported as degenerate.
pub fn plane_at_infinity_general(homographies: &[Homography3]) -> Result<(Vector4<f64>, f64)> {
    fixed_plane(homographies, 1)
}

fn fixed_plane(homographies: &[Homography3], needed: usize) -> Result<(Vector4<f64>, f64)> {
    if homographies.len() < needed {
        return Err(GeometryError::NotEnoughData {
            what: "motions for the plane at infinity",
            needed,
            got: homographies.len(),
        });
    }
    let mut ata = Matrix4::<f64>::zeros();
    for h in homographies {
        let h = h.normalized_det()?;
        let m = h.0.transpose() - Matrix4::identity();
        ata += m.transpose() * m;
    }
    let eig = ata.symmetric_eigen();
    let mut order = [0usize, 1, 2, 3];
    order.sort_by(|&i, &j| eig.eigenvalues[i].total_cmp(&eig.eigenvalues[j]));
    let largest = eig.eigenvalues[order[3]].max(f64::MIN_POSITIVE);
    // Eigenvalues of A^T A are squared singular values.
    let second = eig.eigenvalues[order[1]].max(0.0);
    if (second / largest).sqrt() < PLANE_DEGENERACY_RATIO.sqrt() {
        return Err(GeometryError::Degenerate(
            "the motions fix more than one plane: rotations about the same axis (or no rotation), or one motion that is a pure rotation or planar".into(),
        ));
    }
    let mut plane: Vector4<f64> = eig.eigenvectors.column(order[0]).into_owned();
    if plane.w < 0.0 {
        plane = -plane;
    }
    Ok((plane.normalize(), (second / largest).sqrt()))
}

/// The infinite homography `M = A - b a^T / d` of a homography `H = [[A, b], [c^T, e]]`
/// given the plane at infinity `(a, d)`, scaled to determinant +1.
///
/// Errors if `d` vanishes (the plane at infinity passes through the left camera centre,
/// impossible for a real rig) or `M` is singular.
pub fn infinite_homography(h: &Homography3, plane: &Vector4<f64>) -> Result<Matrix3<f64>> {
    let d = plane.w;
    if d.abs() < 1e-12 * plane.norm() {
        return Err(GeometryError::Degenerate("plane at infinity through the camera centre".into()));
    }
    let a = plane.xyz();
    let hm = h.0;
    let big_a: Matrix3<f64> = hm.fixed_view::<3, 3>(0, 0).into_owned();
    let b: Vector3<f64> = hm.fixed_view::<3, 1>(0, 3).into_owned();
    let m = big_a - b * a.transpose() / d;
    let det = m.determinant();
    if !det.is_finite() || det.abs() < 1e-300 {
        return Err(GeometryError::InvalidEstimate("infinite homography is singular".into()));
    }
    Ok(m / det.cbrt())
}

/// Index of the symmetric entry (i, j) in the 6-vector `[w11, w12, w13, w22, w23, w33]`.
fn sym_index(i: usize, j: usize) -> usize {
    let (i, j) = if i <= j { (i, j) } else { (j, i) };
    match (i, j) {
        (0, 0) => 0,
        (0, 1) => 1,
        (0, 2) => 2,
        (1, 1) => 3,
        (1, 2) => 4,
        _ => 5,
    }
}

/// The dual image of the absolute conic `w* = K K^T` (scaled so `w*[2][2] = 1`) from
/// infinite homographies `M_i = K R_i K^-1` (each of determinant 1).
///
/// Errors: no homography, or a solution that is not positive definite (noise or a wrong
/// plane at infinity).
pub fn dual_image_of_absolute_conic(infinite_homographies: &[Matrix3<f64>]) -> Result<Matrix3<f64>> {
    if infinite_homographies.is_empty() {
        return Err(GeometryError::NotEnoughData { what: "infinite homographies", needed: 1, got: 0 });
    }
    // Normal equations of the stacked 6 x 6 blocks; the null vector is the eigenvector of
    // the smallest eigenvalue. Each equation row is scaled to unit norm.
    let mut ata = SMatrix::<f64, 6, 6>::zeros();
    for m in infinite_homographies {
        for i in 0..3 {
            for j in i..3 {
                let mut row = SMatrix::<f64, 1, 6>::zeros();
                for k in 0..3 {
                    for l in 0..3 {
                        row[sym_index(k, l)] += m[(i, k)] * m[(j, l)];
                    }
                }
                row[sym_index(i, j)] -= 1.0;
                let n = row.norm();
                if n > 0.0 {
                    let row = row / n;
                    ata += row.transpose() * row;
                }
            }
        }
    }
    let eig = ata.symmetric_eigen();
    let (imin, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))
        .ok_or_else(|| GeometryError::Numerical("empty eigen-decomposition".into()))?;
    let w = eig.eigenvectors.column(imin);
    let mut omega = Matrix3::new(w[0], w[1], w[2], w[1], w[3], w[4], w[2], w[4], w[5]);
    if omega[(2, 2)].abs() < 1e-300 {
        return Err(GeometryError::InvalidEstimate("dual conic has w33 = 0".into()));
    }
    omega /= omega[(2, 2)];
    let ev = omega.symmetric_eigenvalues();
    if ev.iter().any(|&v| v <= 0.0 || !v.is_finite()) {
        return Err(GeometryError::InvalidEstimate(format!(
            "dual image of the absolute conic is not positive definite (eigenvalues {:.3e}, {:.3e}, {:.3e})",
            ev[0], ev[1], ev[2]
        )));
    }
    Ok(omega)
}

/// Prior knowledge of `K` that the linear self-calibration can impose exactly. The
/// constraints are linear in the image of the absolute conic `w = K^-T K^-1` when the
/// coordinates are conditioned by a `K0` with zero skew, equal focal lengths and its
/// principal point at the principal point assumed known (as [`Intrinsics::rough_guess`]
/// is, with the image centre).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct IntrinsicConstraints {
    /// Skew zero: `w12 = 0`.
    pub zero_skew: bool,
    /// `fx = fy` (with zero skew): `w11 = w22`. Without `zero_skew` it is not linear in
    /// `w` and is left to the bundle adjustment.
    pub square_pixels: bool,
    /// Principal point at the origin of the conditioned coordinates: `w13 = w23 = 0`.
    pub principal_point_at_origin: bool,
}

impl IntrinsicConstraints {
    /// Number of independent linear constraints imposed on `w`.
    pub fn count(&self) -> usize {
        usize::from(self.zero_skew)
            + usize::from(self.square_pixels && self.zero_skew)
            + 2 * usize::from(self.principal_point_at_origin)
    }
}

/// Ratio of the second-smallest to the largest eigenvalue of the conic system below which
/// the solution is not unique (singular values below about 3e-6 of the largest: far under
/// any noise level, far above rounding).
pub const CONIC_DEGENERACY_RATIO: f64 = 1e-11;

/// `K` (conditioned coordinates) from infinite homographies `M_i = K R_i K^-1` (each of
/// determinant 1) and prior constraints, by the image of the absolute conic `w`:
/// `M_i^T w M_i = w` (six equations per motion, four independent) solved over the
/// subspace of symmetric matrices the constraints allow (Hartley & Zisserman 2nd ed.,
/// section 19.6 and table 19.3, "rotating cameras"). One rotation leaves a pencil of
/// solutions (the conic plus the pole of the rotation axis): it needs at least one
/// constraint (zero skew suffices in general); two rotations about different axes need
/// none. Returns `K` and the uniqueness ratio (second-smallest over largest eigenvalue of
/// the reduced normal equations).
///
/// Errors: no homography; a solution space of dimension > 1 (`Degenerate`, naming what
/// to add); a conic that is not positive definite (noise or a wrong plane at infinity).
pub fn calibrate_from_infinite_homographies(
    infinite_homographies: &[Matrix3<f64>],
    constraints: &IntrinsicConstraints,
) -> Result<(Intrinsics, f64)> {
    if infinite_homographies.is_empty() {
        return Err(GeometryError::NotEnoughData { what: "infinite homographies", needed: 1, got: 0 });
    }
    // Basis of the allowed symmetric matrices, as 6-vectors [w11, w12, w13, w22, w23, w33].
    let mut basis: Vec<SMatrix<f64, 6, 1>> = Vec::new();
    let e = |i: usize| {
        let mut v = SMatrix::<f64, 6, 1>::zeros();
        v[i] = 1.0;
        v
    };
    let tie = constraints.square_pixels && constraints.zero_skew;
    if tie {
        basis.push((e(0) + e(3)) / 2f64.sqrt());
    } else {
        basis.push(e(0));
        basis.push(e(3));
    }
    if !constraints.zero_skew {
        basis.push(e(1));
    }
    if !constraints.principal_point_at_origin {
        basis.push(e(2));
        basis.push(e(4));
    }
    basis.push(e(5));
    let p = basis.len();
    let b = nalgebra::DMatrix::from_fn(6, p, |r, c| basis[c][r]);
    let mut ata = nalgebra::DMatrix::<f64>::zeros(p, p);
    for m in infinite_homographies {
        for i in 0..3 {
            for j in i..3 {
                // (M^T w M)_ij - w_ij = sum_kl M_ki M_lj w_kl - w_ij.
                let mut row = SMatrix::<f64, 1, 6>::zeros();
                for k in 0..3 {
                    for l in 0..3 {
                        row[sym_index(k, l)] += m[(k, i)] * m[(l, j)];
                    }
                }
                row[sym_index(i, j)] -= 1.0;
                let reduced = nalgebra::DMatrix::from_row_slice(1, 6, row.as_slice()) * &b;
                let n = reduced.norm();
                if n > 0.0 && n.is_finite() {
                    let reduced = reduced / n;
                    ata += reduced.transpose() * &reduced;
                }
            }
        }
    }
    let eig = ata.symmetric_eigen();
    let mut order: Vec<usize> = (0..p).collect();
    order.sort_by(|&i, &j| eig.eigenvalues[i].total_cmp(&eig.eigenvalues[j]));
    let largest = eig.eigenvalues[order[p - 1]].max(f64::MIN_POSITIVE);
    let ratio = eig.eigenvalues[order[1]].max(0.0) / largest;
    if ratio.is_nan() || ratio < CONIC_DEGENERACY_RATIO {
        return Err(GeometryError::Degenerate(format!(
            "the motions leave the calibration undetermined (conic solution space of dimension > 1, ratio {ratio:.1e}): one rotation needs a constraint (zero skew, square pixels) or a second motion about another axis"
        )));
    }
    let c = eig.eigenvectors.column(order[0]).into_owned();
    let w6 = &b * c;
    let mut w = Matrix3::new(w6[0], w6[1], w6[2], w6[1], w6[3], w6[4], w6[2], w6[4], w6[5]);
    if w.trace() < 0.0 {
        w = -w;
    }
    let ev = w.symmetric_eigenvalues();
    if ev.iter().any(|&v| v <= 0.0 || !v.is_finite()) {
        return Err(GeometryError::InvalidEstimate(format!(
            "image of the absolute conic is not positive definite (eigenvalues {:.3e}, {:.3e}, {:.3e})",
            ev[0], ev[1], ev[2]
        )));
    }
    let w_star = w.try_inverse().ok_or_else(|| GeometryError::Numerical("singular conic".into()))?;
    let k = k_from_dual_conic(&(w_star / w_star[(2, 2)]))?;
    Ok((k, ratio.sqrt()))
}

/// The upper-triangular `K` with positive diagonal and `K K^T = w*` (`w*` positive
/// definite). Uses the Cholesky factor of the index-reversed matrix.
pub fn k_from_dual_conic(omega: &Matrix3<f64>) -> Result<Intrinsics> {
    // J w J = (J K J)(J K J)^T with J K J lower triangular.
    let j = Matrix3::new(0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0);
    let chol = (j * omega * j)
        .cholesky()
        .ok_or_else(|| GeometryError::InvalidEstimate("dual conic is not positive definite".into()))?;
    let k = j * chol.l() * j;
    Intrinsics::from_matrix(&k)
}

/// The upgrading homography `H_PE = [[K^-1, 0], [a^T, d]]` (Euclidean from projective),
/// with the plane scaled so that `d = 1`.
pub fn euclidean_upgrade(k: &Intrinsics, plane: &Vector4<f64>) -> Result<Matrix4<f64>> {
    if plane.w.abs() < 1e-12 * plane.norm() {
        return Err(GeometryError::Degenerate("plane at infinity through the camera centre".into()));
    }
    let p = plane / plane.w;
    let mut h = Matrix4::zeros();
    h.fixed_view_mut::<3, 3>(0, 0).copy_from(&k.inverse_matrix());
    h.fixed_view_mut::<1, 4>(3, 0).copy_from(&p.transpose());
    Ok(h)
}

/// The rigid motion `D = H_PE H H_PE^-1` (normalised so `D[3][3] = 1`, rotation block
/// projected onto SO(3)), mapping Euclidean points of the first view to the second.
pub fn motion_from_homography(h: &Homography3, h_pe: &Matrix4<f64>) -> Result<Isometry3<f64>> {
    let inv = h_pe.try_inverse().ok_or_else(|| GeometryError::Numerical("H_PE is singular".into()))?;
    let d = h_pe * h.0 * inv;
    let s = d[(3, 3)];
    if !s.is_finite() || s.abs() < 1e-300 {
        return Err(GeometryError::InvalidEstimate("motion has D[3][3] = 0".into()));
    }
    let d = d / s;
    let r = nearest_rotation(&d.fixed_view::<3, 3>(0, 0).into_owned())
        .ok_or_else(|| GeometryError::Numerical("SVD failed projecting onto SO(3)".into()))?;
    let t: Vector3<f64> = d.fixed_view::<3, 1>(0, 3).into_owned();
    Ok(Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_rotation_matrix(&r)))
}

/// RQ decomposition of a finite camera `P = K [R | t]` (up to scale): intrinsics with
/// positive focal lengths, `cam_from_world` with a proper rotation.
pub fn decompose_camera(p: &Matrix3x4<f64>) -> Result<(Intrinsics, Isometry3<f64>)> {
    let m: Matrix3<f64> = p.fixed_view::<3, 3>(0, 0).into_owned();
    let mut p = *p;
    if m.determinant() < 0.0 {
        p = -p;
    }
    let m: Matrix3<f64> = p.fixed_view::<3, 3>(0, 0).into_owned();
    if m.determinant().abs() < 1e-300 {
        return Err(GeometryError::Degenerate("camera at infinity (singular left 3x3 block)".into()));
    }
    // RQ via QR of the flipped transpose: M = K R.
    let j = Matrix3::new(0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0);
    let qr = (j * m).transpose().qr();
    let (q, r) = (qr.q(), qr.r());
    let mut k = j * r.transpose() * j;
    let mut rot = j * q.transpose();
    // Make the diagonal of K positive: K D, D R with D = diag(+-1).
    for i in 0..3 {
        if k[(i, i)] < 0.0 {
            for row in 0..3 {
                k[(row, i)] = -k[(row, i)];
            }
            for col in 0..3 {
                rot[(i, col)] = -rot[(i, col)];
            }
        }
    }
    if rot.determinant() < 0.0 {
        return Err(GeometryError::InvalidEstimate("camera decomposition gave an improper rotation".into()));
    }
    let scale = k[(2, 2)];
    let intrinsics = Intrinsics::from_matrix(&k)?;
    let t = (k / scale).try_inverse().ok_or_else(|| GeometryError::Numerical("singular K".into()))?
        * p.column(3)
        / scale;
    let r = nearest_rotation(&rot).ok_or_else(|| GeometryError::Numerical("SVD failed".into()))?;
    Ok((intrinsics, Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_rotation_matrix(&r))))
}

/// Everything the linear chain recovers from two or more motions.
#[derive(Debug, Clone)]
pub struct LinearCalibration {
    /// Left intrinsics in the coordinates of the input frame.
    pub left: Intrinsics,
    /// Plane at infinity in the projective frame (unit norm, `d >= 0`).
    pub plane_at_infinity: Vector4<f64>,
    /// `H_PE`, Euclidean from projective.
    pub euclidean_from_projective: Matrix4<f64>,
    /// Rigid motions `D_i` (Euclidean points of the first view to view `i`), one per input.
    pub motions: Vec<Isometry3<f64>>,
}

/// Steps 1-5 on a set of homographies (see the module documentation).
pub fn linear_self_calibration(homographies: &[Homography3]) -> Result<LinearCalibration> {
    let plane = plane_at_infinity(homographies)?;
    let ms = homographies
        .iter()
        .map(|h| infinite_homography(&h.normalized_det()?, &plane))
        .collect::<Result<Vec<_>>>()?;
    let omega = dual_image_of_absolute_conic(&ms)?;
    let left = k_from_dual_conic(&omega)?;
    let h_pe = euclidean_upgrade(&left, &plane)?;
    let motions =
        homographies.iter().map(|h| motion_from_homography(h, &h_pe)).collect::<Result<Vec<_>>>()?;
    Ok(LinearCalibration { left, plane_at_infinity: plane, euclidean_from_projective: h_pe, motions })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::so3::{Line, rotation_about_line};
    use nalgebra::{Point3, Unit};
    use proptest::prelude::*;

    /// A random but realistic projective frame and two rotations about different axes.
    fn setup(seed: [f64; 8]) -> (Intrinsics, Matrix4<f64>, Vec<Isometry3<f64>>, Vec<Homography3>) {
        let k = Intrinsics {
            fx: 1.0 + 0.2 * seed[0],
            fy: 1.0 + 0.2 * seed[1],
            skew: 0.01 * seed[2],
            cx: 0.05 * seed[3],
            cy: -0.05 * seed[4],
        };
        let plane = Vector4::new(0.1 * seed[5], -0.2 * seed[6], 0.05 * seed[7], 1.0);
        let h_pe = euclidean_upgrade(&k, &plane).unwrap();
        let pan = Line::new(
            Unit::new_normalize(Vector3::new(0.02 * seed[0], -1.0, 0.03)),
            Point3::new(0.1, 0.2, -0.1),
        );
        let elev = Line::new(
            Unit::new_normalize(Vector3::new(1.0, 0.01 * seed[1], 0.02)),
            Point3::new(0.0, 0.1, -0.05),
        );
        let d = vec![
            rotation_about_line(&elev, 0.05 + 0.02 * seed[2]),
            rotation_about_line(&pan, -0.05 - 0.02 * seed[3]),
        ];
        let inv = h_pe.try_inverse().unwrap();
        let hs = d.iter().map(|m| Homography3(inv * m.to_homogeneous() * h_pe * (0.5 + seed[4]))).collect();
        (k, h_pe, d, hs)
    }

    fn seeds() -> impl Strategy<Value = [f64; 8]> {
        prop::array::uniform8(-1.0..1.0f64)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(128))]
        /// Noise-free recovery. Tolerance 1e-7: the motions are 3-4 degrees, so the
        /// homographies differ from the identity by ~0.05 and the linear systems lose
        /// about two to three digits to that conditioning.
        #[test]
        fn recovers_k_plane_and_motions(seed in seeds()) {
            let (k, h_pe, d, hs) = setup(seed);
            let cal = linear_self_calibration(&hs).unwrap();
            prop_assert!((cal.left.matrix() - k.matrix()).norm() < 1e-7, "K {:?} vs {:?}", cal.left, k);
            let plane_true = h_pe.row(3).transpose().normalize();
            prop_assert!((cal.plane_at_infinity - plane_true).norm() < 1e-7);
            for (m, truth) in cal.motions.iter().zip(&d) {
                prop_assert!((m.to_homogeneous() - truth.to_homogeneous()).norm() < 1e-7);
            }
        }

        /// RQ decomposition recovers K and the pose of any finite camera to rounding.
        #[test]
        fn decompose_camera_round_trip(seed in seeds(), scale in -5.0..5.0f64) {
            prop_assume!(scale.abs() > 0.1);
            let k = Intrinsics { fx: 700.0 + 50.0 * seed[0], fy: 720.0 + 40.0 * seed[1], skew: seed[2], cx: 390.0 + 10.0 * seed[3], cy: 284.0 };
            let pose = Isometry3::from_parts(Translation3::new(seed[4], seed[5], seed[6]), UnitQuaternion::from_euler_angles(seed[7], seed[0] * 0.5, seed[1]));
            let p = crate::camera::ProjectiveCamera::from_pose(&k, &pose).0 * scale;
            let (k2, pose2) = decompose_camera(&p).unwrap();
            prop_assert!((k2.matrix() - k.matrix()).norm() < 1e-8 * 700.0);
            prop_assert!((pose2.to_homogeneous() - pose.to_homogeneous()).norm() < 1e-9);
        }
    }

    /// `H ~ H_PE^-1 D H_PE` of one general screw motion (rotation `angle` about a line
    /// with translation `pitch` along it).
    fn screw_setup(seed: [f64; 8], pitch: f64) -> (Intrinsics, Matrix4<f64>, Homography3, Isometry3<f64>) {
        let k = Intrinsics {
            fx: 1.0 + 0.2 * seed[0],
            fy: 1.0 + 0.2 * seed[0],
            skew: 0.0,
            cx: 0.05 * seed[3],
            cy: -0.05 * seed[4],
        };
        let plane = Vector4::new(0.1 * seed[5], -0.2 * seed[6], 0.05 * seed[7], 1.0);
        let h_pe = euclidean_upgrade(&k, &plane).unwrap();
        let axis = Line::new(
            Unit::new_normalize(Vector3::new(0.3 + 0.2 * seed[1], -1.0, 0.4 * seed[2])),
            Point3::new(0.1, 0.2 * seed[3], 1.0),
        );
        let rot = rotation_about_line(&axis, 0.15 + 0.05 * seed[2]);
        let d = Isometry3::from_parts(
            Translation3::from(rot.translation.vector + axis.direction.into_inner() * pitch),
            rot.rotation,
        );
        let inv = h_pe.try_inverse().unwrap();
        (k, h_pe, Homography3(inv * d.to_homogeneous() * h_pe * (0.5 + seed[4].abs())), d)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        /// One general screw motion (9-11 deg, 0.2 along the axis) fixes only the plane at
        /// infinity; with zero skew and square pixels it gives K. Noise-free; tolerance
        /// 1e-6: the translation along the axis is small against the frame, so the plane's
        /// null space is conditioned to about 1e-3 and four to five digits go.
        #[test]
        fn one_general_motion_with_constraints(seed in seeds()) {
            let (k, h_pe, h, _) = screw_setup(seed, 0.2);
            let (plane, ratio) = plane_at_infinity_general(&[h]).unwrap();
            let truth = h_pe.row(3).transpose().normalize();
            prop_assert!((plane - truth).norm() < 1e-6, "plane {plane:?} vs {truth:?} (ratio {ratio:e})");
            let m = infinite_homography(&h.normalized_det().unwrap(), &plane).unwrap();
            let c = IntrinsicConstraints { zero_skew: true, square_pixels: true, ..Default::default() };
            let (kk, _) = calibrate_from_infinite_homographies(&[m], &c).unwrap();
            prop_assert!((kk.matrix() - k.matrix()).norm() < 1e-6, "{kk:?} vs {k:?}");
            // Zero skew alone also suffices for one rotation.
            let c = IntrinsicConstraints { zero_skew: true, ..Default::default() };
            let (kk, _) = calibrate_from_infinite_homographies(&[m], &c).unwrap();
            prop_assert!((kk.matrix() - k.matrix()).norm() < 1e-6, "{kk:?} vs {k:?}");
        }

        /// Two rotations about different axes need no constraint: same K as the
        /// unconstrained dual-conic solver (1e-7 as in `recovers_k_plane_and_motions`).
        #[test]
        fn two_rotations_need_no_constraint(seed in seeds()) {
            let (k, h_pe, _, hs) = setup(seed);
            let plane = h_pe.row(3).transpose();
            let ms: Vec<_> = hs.iter().map(|h| infinite_homography(&h.normalized_det().unwrap(), &plane).unwrap()).collect();
            let (kk, _) = calibrate_from_infinite_homographies(&ms, &IntrinsicConstraints::default()).unwrap();
            prop_assert!((kk.matrix() - k.matrix()).norm() < 1e-7, "{kk:?} vs {k:?}");
        }
    }

    #[test]
    fn one_rotation_without_constraints_is_degenerate() {
        let (_, h_pe, _, hs) = setup([0.2; 8]);
        let plane = h_pe.row(3).transpose();
        let m = infinite_homography(&hs[0].normalized_det().unwrap(), &plane).unwrap();
        let e = calibrate_from_infinite_homographies(&[m], &IntrinsicConstraints::default()).unwrap_err();
        assert!(matches!(e, GeometryError::Degenerate(_)), "{e}");
        assert!(e.to_string().contains("constraint"), "{e}");
        // A pure rotation fixes a pencil of planes: the plane at infinity is undetermined.
        assert!(matches!(plane_at_infinity_general(&hs[..1]), Err(GeometryError::Degenerate(_))));
        // A screw with no translation along its axis is a pure rotation, too.
        let (_, _, h, _) = screw_setup([0.1; 8], 0.0);
        assert!(matches!(plane_at_infinity_general(&[h]), Err(GeometryError::Degenerate(_))));
        assert!(calibrate_from_infinite_homographies(&[], &IntrinsicConstraints::default()).is_err());
    }

    #[test]
    fn rotations_about_one_axis_are_degenerate() {
        let (_, h_pe, _, _) = setup([0.1; 8]);
        let axis = Line::new(Unit::new_normalize(Vector3::new(0.0, -1.0, 0.0)), Point3::new(0.0, 0.0, 0.1));
        let inv = h_pe.try_inverse().unwrap();
        let hs: Vec<_> = [0.05, -0.08]
            .iter()
            .map(|&a| Homography3(inv * rotation_about_line(&axis, a).to_homogeneous() * h_pe))
            .collect();
        assert!(matches!(plane_at_infinity(&hs), Err(GeometryError::Degenerate(_))));
        assert!(matches!(plane_at_infinity(&hs[..1]), Err(GeometryError::NotEnoughData { .. })));
    }

    #[test]
    fn negative_determinant_is_rejected() {
        let (_, _, _, mut hs) = setup([0.3; 8]);
        let col = -hs[0].0.column(0);
        hs[0].0.set_column(0, &col);
        assert!(plane_at_infinity(&hs).is_err());
    }

    #[test]
    fn non_positive_definite_conic_is_rejected() {
        // Identity "motions" satisfy every conic: the smallest-eigenvector is arbitrary, but
        // a reflection-like map forces an indefinite solution.
        let m = Matrix3::new(0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, -1.0);
        let r = dual_image_of_absolute_conic(&[m]);
        assert!(r.is_err() || r.unwrap().symmetric_eigenvalues().iter().all(|&v| v > 0.0));
        assert!(dual_image_of_absolute_conic(&[]).is_err());
    }
}
