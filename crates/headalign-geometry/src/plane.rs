//! Plane geometry of a rotating camera (paper section 3.3, the degenerate case): the
//! plane-induced homography, the invariant line of a homography, and the projection of a
//! point of a plane into a camera moved by a chain of rotations about lines, with its
//! analytic Jacobians.
//!
//! - [`plane_homography`]: a camera moved by `X2 = R X1 + t` sees the plane
//!   `n^T X1 = d` (first camera's frame) through `H = K2 (R + t n^T / d) K1^-1`
//!   (Hartley & Zisserman 2nd ed., result 13.1). With `t = 0` (or `d` infinite) it is the
//!   infinite homography `K2 R K1^-1`.
//! - [`invariant_line`]: the line `l` a homography maps to itself (`H^-T l ~ l`): for a
//!   rotation about an axis `a` seen by `H = K R K^-1` it is `K^-T a`, the image of the
//!   line at infinity perpendicular to the axis (paper sections 3.1 and 3.3). It is the
//!   eigenvector of `H^T` of the real eigenvalue. Pitfall: with small angles the three
//!   eigenvalues lie close together (`1` and `exp(+-i theta)`), and noise can make them
//!   all real; the real one is then the one closest to the determinant's cube root.
//! - [`project_plane_point`]: the model of the planar route's maximum-likelihood
//!   refinement. A point on the plane `m^T X = 1` (`m = n / d`, reference camera frame,
//!   inverse metres; `m = 0` is the plane at infinity) is parameterised by its normalised
//!   reference-image coordinates `(x, y)`: `X ~ (x, y, 1, m^T (x, y, 1))` homogeneous, so
//!   a far plane needs no division. The camera's pose is `ref_from_cam = G_1 G_2 ... G_n`,
//!   `G_k` the rotation by `angle_k` about the line through `point_k` along `axis_k`
//!   (the pan, elevation, vergence chain). Pixel `= pi(K w)`, `w` the first three rows of
//!   `G_n^-1 ... G_1^-1 X`. Degrees of freedom: 4 intrinsics (`fx, fy, cx, cy`; zero
//!   skew), per factor the angle, 2 of the axis direction and 2 of the point (the
//!   tangent basis [`tangent_basis`] of the axis; the point's component along the axis is
//!   no parameter of a line), 3 of the plane, 2 of the point. Jacobians are exact and
//!   checked against central differences in the tests. The overall scale of the points on
//!   the axes against `1 / |m|` is a gauge (a plane cannot tell distance; the caller fixes
//!   it), and when `m` is zero the points on the axes do not enter at all.

use nalgebra::{Matrix2x3, Matrix2x4, Matrix3, Matrix4, Point2, Point3, Unit, Vector2, Vector3, Vector4};

use crate::so3::skew;
use crate::{GeometryError, Result};

/// `K2 (R + t n^T / d) K1^-1`, the homography induced by the plane `n^T X = d` (first
/// camera's frame) between a camera `K1` and a camera `K2` moved by `X2 = R X1 + t`.
/// `normal_over_d = n / d` (zero for the plane at infinity).
pub fn plane_homography(
    k_to: &Matrix3<f64>,
    rotation: &Matrix3<f64>,
    translation: &Vector3<f64>,
    normal_over_d: &Vector3<f64>,
    k_from_inverse: &Matrix3<f64>,
) -> Matrix3<f64> {
    k_to * (rotation + translation * normal_over_d.transpose()) * k_from_inverse
}

/// The invariant line of a homography that is conjugate to a rotation (module docs),
/// unit norm, sign with a non-negative largest-magnitude entry.
///
/// Errors: a non-finite or singular matrix.
pub fn invariant_line(h: &Matrix3<f64>) -> Result<Vector3<f64>> {
    let det = h.determinant();
    if !det.is_finite() || det.abs() < 1e-300 {
        return Err(GeometryError::Degenerate("singular homography has no invariant line".into()));
    }
    // Balance the pixel scale first: `B = D H D^-1`, `D = diag(1, 1, s)`, with `s` making
    // the translation column and the perspective row alike (in pixels they differ by the
    // square of the focal length, and the eigenvector of the cluster of eigenvalues near 1
    // then loses half the digits). The line of `H` is `D l_B`.
    let top = h[(0, 2)].hypot(h[(1, 2)]);
    let bottom = h[(2, 0)].hypot(h[(2, 1)]);
    let s = if top > 0.0 && bottom > 0.0 { (top / bottom).sqrt() } else { 1.0 };
    let d = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, s));
    let d_inv = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, 1.0 / s));
    let g = (d * h * d_inv).transpose() / det.cbrt();
    let eig = g.complex_eigenvalues();
    // The real eigenvalue: smallest imaginary part, ties (all real) to the one closest to 1.
    let pick = (0..3)
        .min_by(|&i, &j| {
            let key = |k: usize| (eig[k].im.abs(), (eig[k].re - 1.0).abs());
            let (a, b) = (key(i), key(j));
            (a.0 + 1e-9 * a.1).total_cmp(&(b.0 + 1e-9 * b.1))
        })
        .unwrap_or(0);
    // Polish the real root of det(G - l I) by Newton (the Schur form's eigenvalues of a
    // near-triple cluster are good to ~1e-9 only): d/dl det(G - l I) = -tr adj(G - l I).
    let mut lambda = eig[pick].re;
    for _ in 0..4 {
        let m = g - Matrix3::identity() * lambda;
        let minors = m[(1, 1)] * m[(2, 2)] - m[(1, 2)] * m[(2, 1)] + m[(0, 0)] * m[(2, 2)]
            - m[(0, 2)] * m[(2, 0)]
            + m[(0, 0)] * m[(1, 1)]
            - m[(0, 1)] * m[(1, 0)];
        if minors.abs() < 1e-300 {
            break;
        }
        let step = m.determinant() / minors;
        if !step.is_finite() {
            break;
        }
        lambda += step;
    }
    let m = g - Matrix3::identity() * lambda;
    let svd = m.svd(false, true);
    let v_t = svd.v_t.ok_or_else(|| GeometryError::Numerical("SVD failed".into()))?;
    let (mut smallest, mut at) = (f64::INFINITY, 0);
    for (i, s) in svd.singular_values.iter().enumerate() {
        if *s < smallest {
            smallest = *s;
            at = i;
        }
    }
    let mut l: Vector3<f64> = d * v_t.row(at).transpose();
    let big = l.iamax();
    if l[big] < 0.0 {
        l = -l;
    }
    let n = l.norm();
    if !(n.is_finite() && n > 0.0) {
        return Err(GeometryError::Numerical("invariant line is not finite".into()));
    }
    Ok(l / n)
}

/// Two unit vectors perpendicular to unit `a` and to each other, `(b1, b2)` with
/// `b1 x b2 = a`; a fixed function of `a` (the tangent coordinates of an axis).
pub fn tangent_basis(a: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let helper = if a.x.abs() < 0.6 { Vector3::x() } else { Vector3::y() };
    let b1 = (helper - a * a.dot(&helper)).normalize();
    let b2 = a.cross(&b1);
    (b1, b2)
}

/// One rotation of the camera's chain: by `angle` (radians, right-handed about `axis`)
/// about the line through `point` along `axis` (reference camera frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointFactor {
    /// Direction of the line.
    pub axis: Unit<Vector3<f64>>,
    /// A point of the line, metres (any: its component along the axis does not matter).
    pub point: Point3<f64>,
    /// Rotation angle, radians.
    pub angle: f64,
}

/// A projection with its Jacobians ([`project_plane_point`]).
#[derive(Debug, Clone, PartialEq)]
pub struct PlanarProjection {
    /// The pixel.
    pub pixel: Point2<f64>,
    /// d pixel / d (fx, fy, cx, cy).
    pub d_intrinsics: Matrix2x4<f64>,
    /// d pixel / d (x, y), the point's normalised reference coordinates.
    pub d_point: nalgebra::Matrix2<f64>,
    /// d pixel / d m, the plane.
    pub d_plane: Matrix2x3<f64>,
    /// Per factor: d pixel / d (angle, axis along b1, axis along b2, point along b1,
    /// point along b2), [`tangent_basis`] of its axis.
    pub d_factors: Vec<[Vector2<f64>; 5]>,
}

/// `L(a, p, phi) = [[R, p - R p], [0, 1]]`, `R = exp(phi [a]x)`, and its derivatives
/// along (phi, a + b1, a + b2, p + b1, p + b2).
fn line_rotation(a: &Vector3<f64>, p: &Vector3<f64>, phi: f64) -> (Matrix4<f64>, [Matrix4<f64>; 5]) {
    let ax = skew(a);
    let (s, c) = phi.sin_cos();
    let r = Matrix3::identity() + ax * s + ax * ax * (1.0 - c);
    let assemble = |rot: &Matrix3<f64>, top: &Vector3<f64>, one: f64| {
        let mut m = Matrix4::zeros();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(rot);
        m.fixed_view_mut::<3, 1>(0, 3).copy_from(top);
        m[(3, 3)] = one;
        m
    };
    let l = assemble(&r, &(p - r * p), 1.0);
    let dr_phi = ax * r;
    let d_phi = assemble(&dr_phi, &(-dr_phi * p), 0.0);
    let (b1, b2) = tangent_basis(a);
    let d_axis = |b: &Vector3<f64>| {
        let bx = skew(b);
        let dr = bx * s + (bx * ax + ax * bx) * (1.0 - c);
        assemble(&dr, &(-dr * p), 0.0)
    };
    let d_point = |b: &Vector3<f64>| assemble(&Matrix3::zeros(), &(b - r * b), 0.0);
    (l, [d_phi, d_axis(&b1), d_axis(&b2), d_point(&b1), d_point(&b2)])
}

/// The pixel of the plane point `(x, y)` (normalised reference coordinates) in a camera
/// `k` moved by the chain `factors` (`ref_from_cam = G_1 ... G_n`), plane `m`, with its
/// Jacobians (module docs). `None` if the point projects to infinity.
pub fn project_plane_point(
    k: &crate::camera::Intrinsics,
    factors: &[JointFactor],
    plane: &Vector3<f64>,
    xy: &Point2<f64>,
) -> Option<PlanarProjection> {
    let r = Vector3::new(xy.x, xy.y, 1.0);
    let x_h = Vector4::new(r.x, r.y, r.z, plane.dot(&r));
    // cam_from_ref = F_n ... F_1 with F_k = L(a_k, p_k, -angle_k).
    let parts: Vec<(Matrix4<f64>, [Matrix4<f64>; 5])> =
        factors.iter().map(|f| line_rotation(&f.axis, &f.point.coords, -f.angle)).collect();
    // prefix[k] = F_k-1 ... F_1 (applied first), suffix[k] = F_n ... F_k+1.
    let n = parts.len();
    let mut prefix = vec![Matrix4::identity(); n + 1];
    for k in 0..n {
        prefix[k + 1] = parts[k].0 * prefix[k];
    }
    let mut suffix = vec![Matrix4::identity(); n + 1];
    for k in (0..n).rev() {
        suffix[k] = suffix[k + 1] * parts[k].0;
    }
    let c = prefix[n];
    let y = c * x_h;
    let w = y.xyz();
    let q = k.matrix() * w;
    if q.z.abs() < 1e-300 || !q.iter().all(|v| v.is_finite()) {
        return None;
    }
    let (iz, pixel) = (1.0 / q.z, Point2::new(q.x / q.z, q.y / q.z));
    let d_pi = Matrix2x3::new(iz, 0.0, -pixel.x * iz, 0.0, iz, -pixel.y * iz);
    let d_w = d_pi * k.matrix();
    let d_intrinsics = Matrix2x4::from_columns(&[
        d_pi * Vector3::new(w.x, 0.0, 0.0),
        d_pi * Vector3::new(0.0, w.y, 0.0),
        d_pi * Vector3::new(w.z, 0.0, 0.0),
        d_pi * Vector3::new(0.0, w.z, 0.0),
    ]);
    let c3 = c.fixed_view::<3, 4>(0, 0).into_owned();
    let d_point = nalgebra::Matrix2::from_columns(&[
        d_w * (c3 * Vector4::new(1.0, 0.0, 0.0, plane.x)),
        d_w * (c3 * Vector4::new(0.0, 1.0, 0.0, plane.y)),
    ]);
    let col3: Vector3<f64> = c3.column(3).into_owned();
    let d_plane = d_w * (col3 * r.transpose());
    let d_factors = (0..n)
        .map(|k| {
            let mut out = [Vector2::zeros(); 5];
            for (j, dm) in parts[k].1.iter().enumerate() {
                let dy = suffix[k + 1] * dm * prefix[k] * x_h;
                // d/d angle = -d/d phi.
                let sign = if j == 0 { -1.0 } else { 1.0 };
                out[j] = d_w * dy.xyz() * sign;
            }
            out
        })
        .collect();
    Some(PlanarProjection { pixel, d_intrinsics, d_point, d_plane, d_factors })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;
    use crate::so3::{Line, rotation_about_line};
    use proptest::prelude::*;

    fn chain() -> Vec<JointFactor> {
        vec![
            JointFactor {
                axis: Unit::new_normalize(Vector3::new(0.02, -1.0, 0.01)),
                point: Point3::new(-0.12, 0.06, -0.03),
                angle: 0.09,
            },
            JointFactor {
                axis: Unit::new_normalize(Vector3::new(1.0, 0.01, -0.02)),
                point: Point3::new(0.0, 0.06, -0.03),
                angle: -0.05,
            },
        ]
    }

    /// The projection equals the explicit pose chain applied to the plane point (same
    /// pixel to 1e-9 px: two routes through the same f64 arithmetic).
    #[test]
    fn projection_matches_the_pose_chain() {
        let k = Intrinsics::new(700.0, 720.0, 390.0, 284.0);
        let m = Vector3::new(0.05, -0.1, 0.4);
        let f = chain();
        let xy = Point2::new(0.1, -0.2);
        let r = Vector3::new(xy.x, xy.y, 1.0);
        let x = Point3::from(r / m.dot(&r));
        let pose = f.iter().fold(nalgebra::Isometry3::identity(), |acc, g| {
            acc * rotation_about_line(&Line::new(g.axis, g.point), g.angle)
        });
        let expect = k.project(&(pose.inverse() * x)).unwrap();
        let got = project_plane_point(&k, &f, &m, &xy).unwrap().pixel;
        assert!((got - expect).norm() < 1e-9, "{got} {expect}");
    }

    /// Every analytic Jacobian against central differences (step 1e-6 in units of
    /// about 1: truncation ~1e-12 relative, rounding ~1e-10 px; tolerance 1e-5 px per unit).
    #[test]
    fn jacobians_match_central_differences() {
        let k = Intrinsics::new(700.0, 720.0, 390.0, 284.0);
        let m = Vector3::new(0.05, -0.1, 0.4);
        let f = chain();
        let xy = Point2::new(0.1, -0.2);
        let p = project_plane_point(&k, &f, &m, &xy).unwrap();
        let h = 1e-6;
        let check = |name: &str, analytic: Vector2<f64>, plus: Point2<f64>, minus: Point2<f64>| {
            let fd = (plus - minus) / (2.0 * h);
            assert!((fd - analytic).norm() < 1e-5 * (1.0 + fd.norm()), "{name}: {analytic} vs {fd}");
        };
        let kk = |i: usize, s: f64| {
            let mut v = [k.fx, k.fy, k.cx, k.cy];
            v[i] += s;
            Intrinsics::new(v[0], v[1], v[2], v[3])
        };
        for i in 0..4 {
            let pp = project_plane_point(&kk(i, h), &f, &m, &xy).unwrap().pixel;
            let pm = project_plane_point(&kk(i, -h), &f, &m, &xy).unwrap().pixel;
            check("intrinsics", p.d_intrinsics.column(i).into_owned(), pp, pm);
        }
        for i in 0..2 {
            let mut a = xy;
            a[i] += h;
            let mut b = xy;
            b[i] -= h;
            let (pp, pm) = (
                project_plane_point(&k, &f, &m, &a).unwrap().pixel,
                project_plane_point(&k, &f, &m, &b).unwrap().pixel,
            );
            check("point", p.d_point.column(i).into_owned(), pp, pm);
        }
        for i in 0..3 {
            let mut a = m;
            a[i] += h;
            let mut b = m;
            b[i] -= h;
            let (pp, pm) = (
                project_plane_point(&k, &f, &a, &xy).unwrap().pixel,
                project_plane_point(&k, &f, &b, &xy).unwrap().pixel,
            );
            check("plane", p.d_plane.column(i).into_owned(), pp, pm);
        }
        for (fi, factor) in f.iter().enumerate() {
            let (b1, b2) = tangent_basis(&factor.axis);
            for j in 0..5 {
                let moved = |s: f64| {
                    let mut g = f.clone();
                    let x = &mut g[fi];
                    match j {
                        0 => x.angle += s,
                        1 => x.axis = Unit::new_normalize(x.axis.into_inner() + b1 * s),
                        2 => x.axis = Unit::new_normalize(x.axis.into_inner() + b2 * s),
                        3 => x.point += b1 * s,
                        _ => x.point += b2 * s,
                    }
                    project_plane_point(&k, &g, &m, &xy).unwrap().pixel
                };
                check("factor", p.d_factors[fi][j], moved(h), moved(-h));
            }
        }
    }

    proptest! {
        /// `K R K^-1` leaves `K^-T a` fixed: the invariant line is it to 1e-7 (rotations of
        /// 2-20 deg: the eigenvalue gap is at least 0.035).
        #[test]
        fn invariant_line_of_a_rotation(ax in -1.0..1.0f64, ay in -1.0..1.0f64, deg in 2.0..20.0f64) {
            let a = Vector3::new(ax, ay, 0.3).normalize();
            let k = Intrinsics::new(700.0, 720.0, 390.0, 284.0);
            let r = nalgebra::Rotation3::from_axis_angle(&Unit::new_normalize(a), deg.to_radians());
            let h = plane_homography(&k.matrix(), r.matrix(), &Vector3::zeros(), &Vector3::zeros(), &k.inverse_matrix());
            let l = invariant_line(&(h * 3.0)).unwrap();
            let mut want = k.inverse_matrix().transpose() * a;
            want /= want.norm();
            if want[want.iamax()] < 0.0 { want = -want; }
            prop_assert!((l - want).norm() < 1e-7, "{} {}", l, want);
        }

        /// A plane homography maps the image of every point of its plane onto its image in
        /// the second camera (1e-9 px: exact arithmetic up to rounding).
        #[test]
        fn plane_homography_maps_plane_points(tx in -0.2..0.2f64, ty in -0.2..0.2f64, u in -1.0..1.0f64, v in -1.0..1.0f64) {
            let (k1, k2) = (Intrinsics::new(700.0, 720.0, 390.0, 284.0), Intrinsics::new(705.0, 716.0, 380.0, 290.0));
            let r = nalgebra::Rotation3::from_euler_angles(0.02, -0.05, 0.01);
            let t = Vector3::new(tx, ty, 0.01);
            let (n, d) = (Vector3::new(0.1, -0.2, 1.0).normalize(), 2.5);
            // A point of the plane n.X = d.
            let (e1, e2) = tangent_basis(&n);
            let x = n * d + e1 * u + e2 * v;
            let a = k1.project(&Point3::from(x)).unwrap();
            let b = k2.project(&Point3::from(r * x + t)).unwrap();
            let h = plane_homography(&k2.matrix(), r.matrix(), &t, &(n / d), &k1.inverse_matrix());
            let p = h * Vector3::new(a.x, a.y, 1.0);
            prop_assert!((Point2::new(p.x / p.z, p.y / p.z) - b).norm() < 1e-9);
        }
    }
}
