//! Fixtures shared by the tests of the rig bundle adjustment's files (test builds only):
//! a distance between two states (largest relative difference over intrinsics, distortion,
//! rig, motions, axes and points; dimensionless, radians for angles) and the synthetic
//! problem re-observed through a barrel lens.

use nalgebra::{Point2, Vector3};

use super::{BundleObservation, Motions, RigState, residual_pixels};
use crate::distortion::Distortion;
use crate::so3::Line;
use crate::synthetic::{Synth, synth};

pub(super) fn angle_between(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.normalize().dot(&b.normalize()).clamp(-1.0, 1.0).acos()
}

pub(super) fn axes(s: &RigState) -> Vec<Line> {
    match &s.motions {
        Motions::Joints { axes, .. } => axes.clone(),
        Motions::Free { .. } => Vec::new(),
    }
}

/// Largest relative difference over intrinsics, rig, motions and points.
pub(super) fn state_distance(a: &RigState, b: &RigState) -> f64 {
    let mut d: f64 = 0.0;
    for (ka, kb) in [(&a.left, &b.left), (&a.right, &b.right)] {
        for (x, y) in [(ka.fx, kb.fx), (ka.fy, kb.fy), (ka.cx, kb.cx), (ka.cy, kb.cy)] {
            d = d.max((x - y).abs() / y.abs());
        }
        d = d.max((ka.skew - kb.skew).abs() / kb.fx);
    }
    for (da, db) in [(&a.left_distortion, &b.left_distortion), (&a.right_distortion, &b.right_distortion)] {
        for (x, y) in da.params().iter().zip(db.params()) {
            d = d.max((x - y).abs());
        }
    }
    d = d.max(a.right_from_left.rotation.angle_to(&b.right_from_left.rotation));
    d = d.max(
        (a.right_from_left.translation.vector - b.right_from_left.translation.vector).norm()
            / b.right_from_left.translation.vector.norm(),
    );
    for k in 0..b.motions.view_count() {
        let (pa, pb) = (a.motions.ref_from_cam(k), b.motions.ref_from_cam(k));
        d = d.max(pa.rotation.angle_to(&pb.rotation));
        d = d.max((pa.translation.vector - pb.translation.vector).norm());
    }
    for (la, lb) in axes(a).iter().zip(axes(b).iter()) {
        d = d.max(angle_between(&la.direction, &lb.direction));
        d = d.max((la.point - lb.point).norm());
    }
    for (pa, pb) in a.points.iter().zip(&b.points) {
        d = d.max((pa - pb).norm() / pb.coords.norm());
    }
    d
}

/// The synthetic problem re-observed through a barrel lens (`k1 = -0.2, k2 = 0.05` on
/// the left, `-0.15, 0.03` on the right: up to ~6 % radial at the image corners),
/// noise-free.
pub(super) fn distorted(seed: u64, n_points: usize, free: bool) -> Synth {
    distorted_with(seed, n_points, free, [Distortion::radial(-0.2, 0.05), Distortion::radial(-0.15, 0.03)])
}

/// [`distorted`] with the given lenses (left, right).
pub(super) fn distorted_with(seed: u64, n_points: usize, free: bool, lenses: [Distortion; 2]) -> Synth {
    let mut s = synth(seed, n_points, 0.0, 0.0, free);
    s.truth.left_distortion = lenses[0];
    s.truth.right_distortion = lenses[1];
    let truth = s.truth.clone();
    s.obs.retain_mut(|o| {
        let at = BundleObservation { pixel: Point2::origin(), ..*o };
        match residual_pixels(&truth, &at) {
            Some(r) => {
                o.pixel = Point2::from(r);
                true
            }
            None => false,
        }
    });
    s
}
