//! Step 5a of the estimation ([`super`]): the start from the linear self-calibration
//! chain (paper section 3.1 and section 3.2 step 4(c); `docs/how-it-works.md#linear-self-calibration`).
//!
//! From the 3D homographies `H_i ~ H_PE^-1 D_i H_PE` of two or more rotations about
//! different axes ([`headalign_geometry::selfcal::linear_self_calibration`]): the plane at
//! infinity `(a, d)` (3 dof) as their common fixed plane, the infinite homographies
//! `K R_i K^-1`, the dual image of the absolute conic `w* = K K^T` (5 dof) and `K_L` from
//! it, the Euclidean upgrade `H_PE`, the motions `D_i`, and the right camera `K_R [R | t]`
//! from `P_R H_PE^-1`. Everything is in the frame's conditioned coordinates, so `K_L` is
//! relative to the rough calibration `K0`. The metric scale is a gauge: the baseline is
//! scaled to 1 here, and the points and motions with it.
//!
//! Units: the scene in baselines. Pitfalls: with 3 deg rotations each `H_i` is close to
//! the identity and the chain is noisy (focal lengths tens of percent off are common),
//! so it is only one of the starts screened by [`super::adjust`]; a 3D homography without
//! a complex eigenvalue pair blocks it ([`super::homographies`]); a zero or non-finite
//! baseline, or a singular `H_PE`, is an error of this start only.

use headalign_geometry::bundle::RigState;
use headalign_geometry::camera::{Intrinsics, dehomogenise3};
use headalign_geometry::selfcal::{decompose_camera, linear_self_calibration};
use nalgebra::{Isometry3, Point3};

use super::starts::InitContext;
use crate::error::{AlignError, StepContext};

/// Initial state from the linear self-calibration chain (module docs).
pub(super) fn linear_initial_state(
    ctx: &InitContext<'_>,
    homographies: &[headalign_geometry::homography3d::Homography3],
    k0: &Intrinsics,
    p_r: &headalign_geometry::camera::ProjectiveCamera,
) -> Result<RigState, AlignError> {
    let lin = linear_self_calibration(homographies).step("linear self-calibration")?;
    let k_left = Intrinsics::from_matrix(&(k0.matrix() * lin.left.matrix())).step("left intrinsics")?;
    let h_pe = lin.euclidean_from_projective;
    let h_pe_inv = h_pe.try_inverse().ok_or_else(|| AlignError::Geometry {
        step: "Euclidean upgrade".into(),
        cause: headalign_geometry::GeometryError::Numerical("H_PE is singular".into()),
    })?;
    let (k_right, right_from_left) =
        decompose_camera(&(p_r.0 * h_pe_inv)).step("right camera decomposition")?;
    let baseline = right_from_left.translation.vector.norm();
    if !baseline.is_finite() || baseline <= 0.0 {
        return Err(AlignError::Geometry {
            step: "right camera decomposition".into(),
            cause: headalign_geometry::GeometryError::Degenerate("zero baseline".into()),
        });
    }
    let scale = 1.0 / baseline;
    let right_from_left =
        Isometry3::from_parts((right_from_left.translation.vector * scale).into(), right_from_left.rotation);
    // ref_from_cam_k = D_k^-1 (D maps reference points to view k), scaled.
    let mut ref_from_cam = vec![Isometry3::identity(); ctx.rig.len()];
    for (m, d) in lin.motions.iter().enumerate() {
        let inv = d.inverse();
        ref_from_cam[m + 1] = Isometry3::from_parts((inv.translation.vector * scale).into(), inv.rotation);
    }
    ctx.state(k_left, k_right, right_from_left, &ref_from_cam, |slot, track| {
        let (x, _, _) = ctx.recon[slot].get(&track)?;
        dehomogenise3(&(h_pe * x)).map(|p| Point3::from(p.coords * scale))
    })
}
