//! The general rigid motion of the whole stereo rig that `headalign simulate --images
//! --motion general` records: one screw motion (a rotation about an axis and a translation
//! along it), the minimum from which a rig with zero skew and square pixels
//! self-calibrates (`headalign::calibrate`).
//!
//! The motion: [`GENERAL_ANGLE_DEG`] (25 deg) about the vertical line through the head
//! (robot frame: direction `-y`, through `(0, -1.2, 0)`, the nominal head height), with
//! [`GENERAL_ALONG_M`] (0.3 m) along it: the rig turned about the vertical while raised. Units: degrees, metres, robot frame (x right, y down, z forward).
//!
//! Why this one (the rule a user moving a hand-held rig should follow): the Cramer-Rao
//! bound of the focal length at 0.5 px noise (`calibrate::tests::general_motion_grid` in
//! the `headalign` crate, 400 points, seeds 1-60) is 0.18 % median and at most 0.40 % for
//! this motion. The motion used before, 20 deg about the oblique axis `(0.8, -1, 0.3)`,
//! has a median of 0.20 % but 14 of 60 seeds above 0.5 % and up to 30 %: its axis has a
//! large component along the baseline (x), and a rotation about the baseline is close to
//! critical for a stereo rig (about the x axis alone: median 0.3-0.8 %, worst 21-139 %).
//! An axis along the optical axis (a roll) is critical for one rotation with square
//! pixels. So: turn the rig about an axis perpendicular to both the baseline and the
//! optical axis (for a side-by-side rig, the vertical), by 20-30 deg, and move it along
//! that axis by 0.2-0.3 m (a tenth of the scene depth), keeping most of the scene in view.
//! More translation or turn loses overlap (0.4 m: worst bound 1.5 %).
//!
//! Pitfalls: the bound depends on the scene too; `calibrate` reports the sigma of f and
//! warns when it is large: trust it, and add a second motion when it warns.

use headalign_geometry::so3::{Line, rotation_about_line};
use nalgebra::{Isometry3, Point3, Unit, Vector3};

/// Rotation of the simulated general motion, degrees.
pub const GENERAL_ANGLE_DEG: f64 = 25.0;

/// Translation along the rotation axis of the simulated general motion, metres.
pub const GENERAL_ALONG_M: f64 = 0.3;

/// A screw motion of the whole rig (robot frame, the new `world_from_robot`): `angle_deg`
/// about the line through `(0, -1.2, 0)` with direction `axis` (any length, not zero),
/// then `along_m` metres along it. A zero `axis` gives the identity rotation.
pub fn screw_motion(axis: Vector3<f64>, angle_deg: f64, along_m: f64) -> Isometry3<f64> {
    let Some(direction) = Unit::try_new(axis, 1e-12) else {
        return Isometry3::translation(0.0, 0.0, 0.0);
    };
    let line = Line::new(direction, Point3::new(0.0, -1.2, 0.0));
    let r = rotation_about_line(&line, angle_deg.to_radians());
    Isometry3::from_parts((r.translation.vector + direction.into_inner() * along_m).into(), r.rotation)
}

/// The general motion of `simulate --motion general` (module docs).
pub fn general_rig_motion() -> Isometry3<f64> {
    screw_motion(-Vector3::y(), GENERAL_ANGLE_DEG, GENERAL_ALONG_M)
}

#[cfg(test)]
mod tests {
    use super::*;
    use headalign_geometry::so3::screw_from_isometry;

    /// The motion is the screw it says: 25 deg about the vertical, 0.3 m along it
    /// (1e-12: exact arithmetic up to rounding).
    #[test]
    fn general_motion_is_the_documented_screw() {
        let m = general_rig_motion();
        let s = screw_from_isometry(&m, 1e-12).unwrap();
        assert!((s.angle.to_degrees() - GENERAL_ANGLE_DEG).abs() < 1e-12);
        assert!(s.axis.direction.x.abs() < 1e-12 && s.axis.direction.z.abs() < 1e-12);
        let along = m.translation.vector.dot(&s.axis.direction);
        assert!((along.abs() - GENERAL_ALONG_M).abs() < 1e-12, "{along}");
        assert_eq!(screw_motion(Vector3::zeros(), 10.0, 1.0), Isometry3::identity());
    }
}
