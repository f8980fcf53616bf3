//! The table's rows against their own contracts: every model's projection Jacobians
//! against central differences, unprojection against projection (random instances), and
//! the table's order and names.

use nalgebra::{Vector2, Vector3};
use proptest::prelude::*;

use super::*;

/// A model and parameters drawn for it (realistic ranges: radial-tangential and
/// equidistant as in `distortion.rs`'s tests, the double sphere over the paper's range of
/// real lenses, xi -0.4..0.9, alpha 0.2..0.8).
fn instance(which: usize, c: [f64; 6]) -> (&'static dyn LensModel, Params) {
    let model = MODELS[which % MODELS.len()];
    let p = match model.kind() {
        LensKind::RadialTangential => [c[0] * 0.3, c[1] * 0.1, c[2] * 0.002, c[3] * 0.002, c[4] * 0.02, 0.0],
        LensKind::Equidistant => [c[0] * 0.1, c[1] * 0.05, c[2] * 0.01, c[3] * 0.005, 0.0, 0.0],
        LensKind::DoubleSphere => [0.25 + 0.65 * c[0], 0.5 + 0.3 * c[1], 0.0, 0.0, 0.0, 0.0],
        LensKind::Pinhole => [0.0; MAX_PARAMS],
    };
    (model, p)
}

/// The largest angle from the axis, radians, at which the model projects (the double
/// sphere's `acos(-w2)`; 90 deg for the pinhole-plane models), times `margin`.
fn field(model: &dyn LensModel, p: &Params, margin: f64) -> f64 {
    let limit = match model.kind() {
        LensKind::DoubleSphere => {
            let (xi, alpha) = (p[0], p[1]);
            let w1 = if alpha <= 0.5 { alpha / (1.0 - alpha) } else { (1.0 - alpha) / alpha };
            (-(w1 + xi) / (2.0 * w1 * xi + xi * xi + 1.0).sqrt()).acos()
        }
        // The radial-tangential polynomial of the strongest barrel drawn (k1 -0.3,
        // k2 -0.1) folds at r ~ 0.8 (39 deg): 35 deg stays before it.
        LensKind::RadialTangential => 35f64.to_radians(),
        // The equidistant angle polynomial is monotonic over 70 deg for these terms.
        _ => 70f64.to_radians(),
    };
    limit * margin
}

fn ray_at(theta: f64, phi: f64, length: f64) -> Vector3<f64> {
    Vector3::new(theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()) * length
}

#[test]
fn the_table_is_in_the_order_of_the_kinds_and_names_are_unique() {
    for (i, m) in MODELS.iter().enumerate() {
        assert_eq!(m.kind() as usize, i, "{}", m.names().id);
        assert_eq!(model(m.kind()).names().id, m.names().id);
        assert!(m.param_names().len() <= MAX_PARAMS);
        assert!(m.max_half_fov_deg() >= 90.0);
        for alias in m.names().aliases {
            assert_eq!(LensKind::parse(alias), Some(m.kind()), "{alias}");
        }
        // The serde name of the kind is the table's id.
        assert_eq!(serde_json::to_string(&m.kind()).unwrap(), format!("\"{}\"", m.names().id));
    }
    assert_eq!(LensKind::DoubleSphere.kalibr_name(), "ds");
    // The levels of terms nest: each estimates at least the one before.
    for m in MODELS {
        let counts = DistortionTerms::LEVELS.map(|t| m.estimated(t));
        assert!(counts.windows(2).all(|w| w[0] <= w[1]) && counts[2] <= m.param_names().len(), "{counts:?}");
    }
    assert_eq!(LensKind::DoubleSphere.model().names().opencv, None);
}

/// The double sphere's projection against the paper's formula written out for one ray
/// (xi = -0.2, alpha = 0.6, ray (0.3, -0.4, 1.2)), and the pinhole it reduces to.
#[test]
fn double_sphere_matches_the_written_out_formula() {
    let (xi, alpha) = (-0.2f64, 0.6f64);
    let (x, y, z) = (0.3f64, -0.4f64, 1.2f64);
    let d1 = (x * x + y * y + z * z).sqrt();
    let d2 = (x * x + y * y + (xi * d1 + z).powi(2)).sqrt();
    let den = alpha * d2 + (1.0 - alpha) * (xi * d1 + z);
    let p = [xi, alpha, 0.0, 0.0, 0.0, 0.0];
    let m = DoubleSphere.project(&p, &Vector3::new(x, y, z)).unwrap();
    assert!((m - Vector2::new(x / den, y / den)).norm() < 1e-15, "{m:?}");
    // xi = alpha = 0 is the pinhole.
    let m0 = DoubleSphere.project(&[0.0; MAX_PARAMS], &Vector3::new(x, y, z)).unwrap();
    assert!((m0 - Vector2::new(x / z, y / z)).norm() < 1e-15);
    // A ray 100 deg off the axis projects with a lens of w2 > sin(10 deg) ...
    let wide = [0.5, 0.6, 0.0, 0.0, 0.0, 0.0];
    let back = ray_at(100f64.to_radians(), 0.3, 2.0);
    let m = DoubleSphere.project(&wide, &back).unwrap();
    assert!((DoubleSphere.unproject(&wide, &m).unwrap() - back.normalize()).norm() < 1e-12);
    // ... and the ray straight back never does.
    assert!(DoubleSphere.project(&wide, &Vector3::new(0.0, 0.0, -1.0)).is_none());
    // Outside the image circle of alpha > 1/2 there is no bearing.
    assert!(DoubleSphere.unproject(&wide, &Vector2::new(3.0, 0.0)).is_err());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    /// `project(unproject(m)) = m` and `unproject(project(ray)) = ray / |ray|` for every
    /// model on random instances and rays up to 95 % of the model's field: to 1e-12
    /// relative. Why that bound: both maps are a few dozen flops from well-conditioned
    /// quantities (the double sphere's closed form; Newton's fixed point stops at 1e-14),
    /// and the bearing's error in m is amplified by at most |dm/d bearing| ~ |m|^2 + 1 < 10
    /// in these fields: 1e-12 leaves a factor 10 over 1e-14 ... 1e-13.
    #[test]
    fn unproject_inverts_project(
        which in 0usize..4, c in proptest::array::uniform6(-1.0..1.0f64),
        t in 0.0..1.0f64, phi in -3.2..3.2f64, length in 0.2..5.0f64,
    ) {
        let (model, p) = instance(which, c);
        let ray = ray_at(field(model, &p, 0.95) * t, phi, length);
        let m = model.project(&p, &ray).unwrap();
        let bearing = model.unproject(&p, &m).unwrap();
        prop_assert!((bearing - ray.normalize()).norm() < 1e-12, "{:?}: {bearing:?} vs {:?}", model.kind(), ray.normalize());
        let again = model.project(&p, &bearing).unwrap();
        prop_assert!((again - m).norm() < 1e-12 * (1.0 + m.norm()), "{:?}: {again:?} vs {m:?}", model.kind());
    }

    /// The pixel Jacobians with respect to the ray and to every parameter against central
    /// differences (step 1e-6 on a ray of length 0.2-5, 1e-6 on a parameter), under a `K`
    /// of 400 px: tolerance 1e-5 px per unit derivative, relative. Truncation h^2 f''' is
    /// about 400 px * 1e-12 / length^3 < 1e-7 px, rounding 400 px * 1e-16 / 1e-6 = 4e-8 px.
    #[test]
    fn jacobians_match_finite_differences(
        which in 0usize..4, c in proptest::array::uniform6(-1.0..1.0f64),
        t in 0.0..1.0f64, phi in -3.2..3.2f64, length in 0.2..5.0f64,
    ) {
        let (model, p) = instance(which, c);
        let k = Intrinsics { fx: 400.0, fy: 410.0, skew: 0.5, cx: 320.0, cy: 240.0 };
        let ray = ray_at(field(model, &p, 0.9) * t, phi, length);
        let lin = model.linearise(&k, &p, &ray).unwrap();
        prop_assert!((lin.m - model.project(&p, &ray).unwrap()).norm() < 1e-15 * (1.0 + lin.m.norm()));
        let pixel = |p: &Params, r: &Vector3<f64>| pixel_of(&k, &model.project(p, r).unwrap());
        let h = 1e-6;
        for i in 0..3 {
            let mut e = Vector3::zeros();
            e[i] = h;
            let fd = (pixel(&p, &(ray + e)) - pixel(&p, &(ray - e))) / (2.0 * h);
            let an = lin.d_ray.column(i);
            prop_assert!((fd - an).norm() < 1e-5 * (1.0 + an.norm()), "{:?} ray {i}: {fd:?} vs {an:?}", model.kind());
        }
        let n = model.param_names().len();
        let mut estimated = [false; MAX_PARAMS];
        estimated[..n].iter_mut().for_each(|e| *e = true);
        let jp = model.param_jacobian(&k, &p, &ray, &estimated);
        for i in 0..n {
            let (mut a, mut b) = (p, p);
            a[i] += h;
            b[i] -= h;
            let fd = (pixel(&a, &ray) - pixel(&b, &ray)) / (2.0 * h);
            let an = jp.column(i);
            prop_assert!((fd - an).norm() < 1e-5 * (1.0 + an.norm()), "{:?} parameter {i}: {fd:?} vs {an:?}", model.kind());
        }
        // Only the radial terms estimated: the same first two columns.
        let mut radial = [false; MAX_PARAMS];
        radial[..n.min(2)].iter_mut().for_each(|e| *e = true);
        let jr = model.param_jacobian(&k, &p, &ray, &radial);
        for i in 0..n.min(2) {
            prop_assert!((jr.column(i) - jp.column(i)).norm() < 1e-9 * (1.0 + jp.column(i).norm()));
        }
    }
}
