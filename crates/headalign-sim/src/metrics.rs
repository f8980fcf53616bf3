//! Ground-truth error metrics (`docs/conventions.md#error-metrics`), the same names in every report.
//!
//! - [`AlignmentErrors`]: `verge_err_{l,r}` = `asin(optical . elevation_dir)`, the signed
//!   angle of a camera's optical axis out of the plane perpendicular to the current
//!   elevation axis (moved by pan); positive when the camera looks towards the elevation
//!   axis direction (right). `elev_err_{l,r}` = `asin(optical . pan_dir)`, out of the
//!   plane perpendicular to the pan axis; positive when looking up (the pan direction is
//!   stored pointing up). Degrees. See [`crate::kinematics`] for the joint signs.
//! - [`CalibrationErrors`]: focal, aspect and principal point errors in percent.
//! - `recon_err_pct`: Euclidean reconstruction error after the best similarity
//!   (Umeyama), RMS over points of `|error| / distance from the camera`, percent;
//!   [`ReconErrors`] has the RMS and the median over points.
//! - [`AxisErrors`]: direction (degrees) and position (metres) error of a recovered axis.
//!
//! Pitfall: estimated points and axes are compared in the **left camera frame at the
//! given encoder readings**; a reconstruction is defined up to a similarity, an axis
//! direction up to sign (the angle reported is between lines, at most 90 deg), and an
//! axis position only once the metric scale is fixed (e.g. from a known baseline).

use headalign_geometry::registration::similarity_fit;
use std::collections::HashMap;

use headalign_geometry::camera::Intrinsics;
use headalign_geometry::so3::Line;
use headalign_platform::{Encoders, Joint};
use nalgebra::{Point3, Vector3};
use serde::Serialize;

use crate::SimError;
use crate::head::SimulatedHead;

/// Signed alignment errors of both cameras, degrees.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct AlignmentErrors {
    /// Left optical axis out of the plane perpendicular to the elevation axis.
    pub verge_err_l_deg: f64,
    /// Right optical axis out of the plane perpendicular to the elevation axis.
    pub verge_err_r_deg: f64,
    /// Left optical axis out of the plane perpendicular to the pan axis (up positive).
    pub elev_err_l_deg: f64,
    /// Right optical axis out of the plane perpendicular to the pan axis (up positive).
    pub elev_err_r_deg: f64,
}

/// Reconstruction errors over the points of one reconstruction, percent of each true
/// point's distance from the camera ([`SimulatedHead::recon_errors`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ReconErrors {
    /// RMS over points.
    pub rms_pct: f64,
    /// Median over points.
    pub median_pct: f64,
}

/// Calibration errors of a stereo pair, percent.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct CalibrationErrors {
    /// Largest relative error of the four focal lengths.
    pub f_err_pct: f64,
    /// Largest relative error of the two aspect ratios `fy / fx`.
    pub aspect_err_pct: f64,
    /// Largest principal point error, as a fraction of the camera's mean true focal length.
    pub pp_err_pct: f64,
}

/// Errors of a recovered head axis.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct AxisErrors {
    /// Angle between the recovered and the true axis lines, degrees, in `[0, 90]`.
    pub direction_deg: f64,
    /// Distance from the recovered line to the point of the true axis nearest the left
    /// camera centre, metres (meaningful only with the metric scale fixed).
    pub position_m: f64,
}

fn asin_deg(x: f64) -> f64 {
    x.clamp(-1.0, 1.0).asin().to_degrees()
}

/// Calibration errors of estimated intrinsics against the truth.
pub fn calibration_errors(
    truth_l: &Intrinsics,
    truth_r: &Intrinsics,
    est_l: &Intrinsics,
    est_r: &Intrinsics,
) -> CalibrationErrors {
    let rel = |est: f64, truth: f64| ((est - truth) / truth).abs() * 100.0;
    let mut f = 0.0f64;
    let mut aspect = 0.0f64;
    let mut pp = 0.0f64;
    for (t, e) in [(truth_l, est_l), (truth_r, est_r)] {
        f = f.max(rel(e.fx, t.fx)).max(rel(e.fy, t.fy));
        aspect = aspect.max(rel(e.fy / e.fx, t.fy / t.fx));
        pp = pp.max((e.cx - t.cx).hypot(e.cy - t.cy) / t.mean_focal() * 100.0);
    }
    CalibrationErrors { f_err_pct: f, aspect_err_pct: aspect, pp_err_pct: pp }
}

impl SimulatedHead {
    /// Signed alignment errors of both cameras at the given encoder readings, degrees.
    pub fn alignment_errors(&self, enc: &Encoders) -> AlignmentErrors {
        let truth = self.truth();
        let (world_from_left, world_from_right) = truth.world_from_cameras(enc);
        let optical_l = world_from_left.rotation * Vector3::z();
        let optical_r = world_from_right.rotation * Vector3::z();
        let elev_dir = truth.axis_in_world(Joint::Elevation, enc).direction.into_inner();
        let pan_dir = truth.pan_axis.direction.into_inner();
        AlignmentErrors {
            verge_err_l_deg: asin_deg(optical_l.dot(&elev_dir)),
            verge_err_r_deg: asin_deg(optical_r.dot(&elev_dir)),
            elev_err_l_deg: asin_deg(optical_l.dot(&pan_dir)),
            elev_err_r_deg: asin_deg(optical_r.dot(&pan_dir)),
        }
    }

    /// Pan error, degrees: the angle about the pan axis from the robot's forward
    /// direction (+z, the direction of travel with the wheel straight) to the head's
    /// forward direction, taken as the mean of the two optical axes projected onto the
    /// plane perpendicular to the pan axis. Positive when the head looks left (the pan
    /// joint's sign). Zero-length projection (cameras looking straight up) gives NaN.
    pub fn pan_err_deg(&self, enc: &Encoders) -> f64 {
        self.pan_err_from_deg(enc, &Vector3::z())
    }

    /// Pan error from a direction of travel `travel` (robot frame; the robot's on a floor
    /// tilted against the pan axis, [`crate::robot`]): as [`Self::pan_err_deg`], the angle
    /// about the pan axis from `travel` to the head's forward direction, both projected
    /// onto the plane perpendicular to the pan axis. NaN when either projection vanishes.
    pub fn pan_err_from_deg(&self, enc: &Encoders, travel: &Vector3<f64>) -> f64 {
        let (world_from_left, world_from_right) = self.world_from_cameras(enc);
        let forward = world_from_left.rotation * Vector3::z() + world_from_right.rotation * Vector3::z();
        let up = self.truth().pan_axis.direction.into_inner();
        let horizontal = forward - up * up.dot(&forward);
        let t = travel - up * up.dot(travel);
        if horizontal.norm() < 1e-12 || t.norm() < 1e-12 {
            return f64::NAN;
        }
        // Right-handed angle about `up` from `t`: sin along up x t.
        up.cross(&t).dot(&horizontal).atan2(t.dot(&horizontal)).to_degrees()
    }

    /// The true aligned readings: zero `verge_err_l`, `verge_err_r` and `elev_err_l`; pan
    /// at its zero offset. See [`crate::HeadTruth::aligned_encoders`].
    pub fn aligned_encoders(&self) -> Encoders {
        self.truth().aligned_encoders()
    }

    /// Reconstruction error, percent: `estimated` points (track id, position in the LEFT
    /// camera frame at readings `enc`, any scale, rotation and origin) are mapped by the
    /// best similarity onto the true points in that frame; then the RMS over points of
    /// `|error| / distance of the true point from the camera` x 100
    /// ([`ReconErrors::rms_pct`] of [`SimulatedHead::recon_errors`]).
    ///
    /// Errors: fewer than 3 points, an unknown track id, a non-finite point, or points
    /// that do not fix a similarity.
    pub fn recon_err_pct(&self, enc: &Encoders, estimated: &[(u64, Point3<f64>)]) -> Result<f64, SimError> {
        self.recon_errors(enc, estimated).map(|e| e.rms_pct)
    }

    /// Reconstruction errors of [`SimulatedHead::recon_err_pct`]: the RMS and the median
    /// over points of the relative error (the paper's "reconstruction error, expressed as
    /// a percentage of distance of a point from the camera" does not say which; with
    /// stereo depth noise growing with distance the RMS is dominated by the far points).
    pub fn recon_errors(
        &self,
        enc: &Encoders,
        estimated: &[(u64, Point3<f64>)],
    ) -> Result<ReconErrors, SimError> {
        if estimated.len() < 3 {
            return Err(SimError::Metric(format!("need at least 3 points, got {}", estimated.len())));
        }
        let by_id: HashMap<u64, Point3<f64>> = self.scene_points().iter().copied().collect();
        let (world_from_left, _) = self.scene_from_cameras(enc);
        let left_from_world = world_from_left.inverse();
        let mut src = Vec::with_capacity(estimated.len());
        let mut dst = Vec::with_capacity(estimated.len());
        for (track, p) in estimated {
            if !p.coords.iter().all(|v| v.is_finite()) {
                return Err(SimError::Metric(format!("estimated point of track {track} is not finite")));
            }
            let Some(point_in_world) = by_id.get(track) else {
                return Err(SimError::Metric(format!("track {track} is not a scene point")));
            };
            src.push(p.coords);
            dst.push((left_from_world * point_in_world).coords);
        }
        let src: Vec<Point3<f64>> = src.into_iter().map(Point3::from).collect();
        let dst: Vec<Point3<f64>> = dst.into_iter().map(Point3::from).collect();
        let sim = similarity_fit(&src, &dst, true)
            .map_err(|e| SimError::Metric(format!("best similarity: {e}")))?;
        let mut rel = Vec::with_capacity(src.len());
        for (a, b) in src.iter().zip(&dst) {
            let err = (sim.transform(a) - b).norm();
            let b = b.coords;
            let dist = b.norm();
            if dist <= 0.0 || !dist.is_finite() {
                return Err(SimError::Metric("a true point is at the camera centre".into()));
            }
            rel.push(err / dist);
        }
        let rms_pct = (rel.iter().map(|v| v * v).sum::<f64>() / rel.len() as f64).sqrt() * 100.0;
        rel.sort_by(f64::total_cmp);
        let n = rel.len();
        let median = if n % 2 == 1 { rel[n / 2] } else { 0.5 * (rel[n / 2 - 1] + rel[n / 2]) };
        Ok(ReconErrors { rms_pct, median_pct: median * 100.0 })
    }

    /// The true axis of a joint as a line in the LEFT camera frame at readings `enc`.
    pub fn axis_in_left_camera(&self, joint: Joint, enc: &Encoders) -> Line {
        let (world_from_left, _) = self.world_from_cameras(enc);
        self.truth().axis_in_world(joint, enc).transformed(&world_from_left.inverse())
    }

    /// Errors of a recovered axis (a line in the LEFT camera frame at readings `enc`,
    /// metres) against the true axis of `joint`. The direction error ignores the sign of
    /// the direction.
    pub fn axis_errors(&self, joint: Joint, enc: &Encoders, estimated: &Line) -> AxisErrors {
        let truth = self.axis_in_left_camera(joint, enc);
        let cos = estimated.direction.dot(&truth.direction).abs().min(1.0);
        let direction_deg = cos.acos().to_degrees();
        // Point of the true axis nearest the camera centre (the origin of this frame).
        let position_m = estimated.distance_to(&truth.point);
        AxisErrors { direction_deg, position_m }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenario::Scenario;
    use nalgebra::{Isometry3, Translation3, Unit, UnitQuaternion};

    fn ideal() -> SimulatedHead {
        SimulatedHead::new(Scenario {
            mount_rotation_max_deg: 0.0,
            elevation_tilt_max_deg: 0.0,
            verge_tilt_max_deg: 0.0,
            ..Scenario::default()
        })
        .unwrap()
    }

    fn all_abs(e: &AlignmentErrors) -> [f64; 4] {
        [e.verge_err_l_deg.abs(), e.verge_err_r_deg.abs(), e.elev_err_l_deg.abs(), e.elev_err_r_deg.abs()]
    }

    #[test]
    fn ideal_head_aligned_has_zero_errors() {
        let head = ideal();
        let aligned = head.aligned_encoders();
        assert_eq!(aligned, head.truth().zero_offsets);
        for e in all_abs(&head.alignment_errors(&aligned)) {
            assert!(e < 1e-12, "{e}");
        }
        // ... and at any pan.
        for e in all_abs(&head.alignment_errors(&aligned.moved(Joint::Pan, 33.0))) {
            assert!(e < 1e-12, "{e}");
        }
    }

    #[test]
    fn aligned_encoders_zero_the_claimed_errors() {
        for seed in 1..=10 {
            let head = SimulatedHead::new(Scenario::default().with_seed(seed)).unwrap();
            let aligned = head.aligned_encoders();
            assert_eq!(aligned.pan, head.truth().zero_offsets.pan);
            let e = head.alignment_errors(&aligned);
            assert!(e.verge_err_l_deg.abs() < 1e-9, "seed {seed}: {e:?}");
            assert!(e.verge_err_r_deg.abs() < 1e-9, "seed {seed}: {e:?}");
            assert!(e.elev_err_l_deg.abs() < 1e-9, "seed {seed}: {e:?}");
            // What no joint corrects: bounded by the mounting and tilt errors.
            assert!(e.elev_err_r_deg.abs() < 4.0, "seed {seed}: {e:?}");
            // Aligned readings are near the zero offsets (small tilts and mounting).
            let z = head.truth().zero_offsets;
            assert!((aligned.elevation - z.elevation).abs() < 3.0);
            assert!((aligned.verge_left - z.verge_left).abs() < 3.0);
        }
    }

    #[test]
    fn pan_leaves_verge_and_elevation_errors_unchanged() {
        let head = SimulatedHead::new(Scenario::default().with_seed(4)).unwrap();
        let base = Encoders { pan: 3.0, elevation: 5.0, verge_left: -2.0, verge_right: 4.0 };
        let e0 = head.alignment_errors(&base);
        for pan in [-40.0, -3.0, 0.0, 17.0, 90.0] {
            let e = head.alignment_errors(&Encoders { pan, ..base });
            for (a, b) in all_abs(&e).iter().zip(all_abs(&e0)) {
                assert!((a - b).abs() < 1e-9);
            }
            assert!((e.verge_err_l_deg - e0.verge_err_l_deg).abs() < 1e-9);
            assert!((e.elev_err_r_deg - e0.elev_err_r_deg).abs() < 1e-9);
        }
    }

    #[test]
    fn error_signs_follow_their_joints() {
        let head = SimulatedHead::new(Scenario::default().with_seed(2)).unwrap();
        let a = head.aligned_encoders();
        let e = |enc: &Encoders| head.alignment_errors(enc);
        // +1 deg of a joint adds about +1 deg to its error (first order).
        assert!((e(&a.moved(Joint::VergeLeft, 1.0)).verge_err_l_deg - 1.0).abs() < 0.05);
        assert!((e(&a.moved(Joint::VergeRight, 1.0)).verge_err_r_deg - 1.0).abs() < 0.05);
        assert!((e(&a.moved(Joint::Elevation, 1.0)).elev_err_l_deg - 1.0).abs() < 0.05);
        // Looking right is positive vergence error, looking up positive elevation error.
        let ideal = ideal();
        let z = ideal.truth().zero_offsets;
        let (l, _) = ideal.world_from_cameras(&z.moved(Joint::VergeLeft, 2.0));
        assert!((l.rotation * Vector3::z()).x > 0.0);
        assert!((ideal.alignment_errors(&z.moved(Joint::VergeLeft, 2.0)).verge_err_l_deg - 2.0).abs() < 1e-9);
        let (l, _) = ideal.world_from_cameras(&z.moved(Joint::Elevation, 2.0));
        assert!((l.rotation * Vector3::z()).y < 0.0);
        assert!((ideal.alignment_errors(&z.moved(Joint::Elevation, 2.0)).elev_err_r_deg - 2.0).abs() < 1e-9);
    }

    #[test]
    fn pan_error_sign_and_value() {
        let head = ideal();
        let z = head.truth().zero_offsets;
        assert!(head.pan_err_deg(&z).abs() < 1e-12);
        assert!((head.pan_err_deg(&z.moved(Joint::Pan, 5.0)) - 5.0).abs() < 1e-9);
        assert!(
            (head.pan_err_deg(&z.moved(Joint::Pan, -12.0).moved(Joint::Elevation, 8.0)) + 12.0).abs() < 1e-9
        );
        // Symmetric vergence does not change the head's forward direction.
        let sym = z.moved(Joint::VergeLeft, 3.0).moved(Joint::VergeRight, -3.0);
        assert!(head.pan_err_deg(&sym).abs() < 1e-9);
    }

    #[test]
    fn recon_err_of_exact_points_is_zero() {
        let head = SimulatedHead::new(Scenario::default()).unwrap();
        let enc = Encoders { pan: 2.0, elevation: 1.0, verge_left: 0.5, verge_right: -0.5 };
        let (world_from_left, _) = head.world_from_cameras(&enc);
        let left_from_world = world_from_left.inverse();
        // An arbitrary similarity applied to the true points in the left frame.
        let gauge = Isometry3::from_parts(
            Translation3::new(3.0, -1.0, 0.5),
            UnitQuaternion::from_axis_angle(&Unit::new_normalize(Vector3::new(1.0, 2.0, 3.0)), 0.7),
        );
        let scale = 0.37;
        let estimated: Vec<(u64, Point3<f64>)> = head
            .scene_points()
            .iter()
            .take(300)
            .map(|(id, p)| (*id, Point3::from((gauge * (left_from_world * p)).coords * scale)))
            .collect();
        let err = head.recon_err_pct(&enc, &estimated).unwrap();
        assert!(err < 1e-9, "{err}");

        // A 1 % radial perturbation of every other point gives a positive error.
        let noisy: Vec<_> = head
            .scene_points()
            .iter()
            .take(300)
            .enumerate()
            .map(|(i, (id, p))| {
                let q = left_from_world * p;
                (*id, if i % 2 == 0 { Point3::from(q.coords * 1.01) } else { q })
            })
            .collect();
        let err = head.recon_err_pct(&enc, &noisy).unwrap();
        assert!(err > 0.2 && err < 1.0, "{err}");
        // Half the points off: the median sits between the exact and the perturbed ones
        // (the similarity spreads the error, so it is small but not zero), below the RMS.
        let both = head.recon_errors(&enc, &noisy).unwrap();
        assert!(both.median_pct < both.rms_pct && both.median_pct >= 0.0, "{both:?}");

        assert!(head.recon_err_pct(&enc, &estimated[..2]).is_err());
        assert!(head.recon_err_pct(&enc, &[(u64::MAX, Point3::origin()); 3]).is_err());
        let mut bad = estimated.clone();
        bad[0].1.x = f64::NAN;
        assert!(head.recon_err_pct(&enc, &bad).is_err());
    }

    #[test]
    fn calibration_error_values() {
        let tl = Intrinsics::new(700.0, 720.0, 390.0, 284.0);
        let tr = Intrinsics::new(705.0, 716.0, 380.0, 290.0);
        let zero = calibration_errors(&tl, &tr, &tl, &tr);
        assert_eq!(zero, CalibrationErrors { f_err_pct: 0.0, aspect_err_pct: 0.0, pp_err_pct: 0.0 });
        let el = Intrinsics { fx: 707.0, ..tl }; // +1 % fx
        let er = Intrinsics { cx: tr.cx + 3.0, cy: tr.cy + 4.0, ..tr }; // 5 px
        let c = calibration_errors(&tl, &tr, &el, &er);
        assert!((c.f_err_pct - 1.0).abs() < 1e-12);
        assert!((c.aspect_err_pct - (1.0 - 1.0 / 1.01) * 100.0).abs() < 1e-9);
        assert!((c.pp_err_pct - 5.0 / 710.5 * 100.0).abs() < 1e-12);
    }

    #[test]
    fn axis_errors_of_truth_are_zero() {
        let head = SimulatedHead::new(Scenario::default().with_seed(5)).unwrap();
        let enc = Encoders { pan: 1.0, elevation: 2.0, verge_left: 3.0, verge_right: 4.0 };
        for joint in Joint::ALL {
            let t = head.axis_in_left_camera(joint, &enc);
            for line in [t, t.reversed()] {
                let e = head.axis_errors(joint, &enc, &line);
                assert!(e.direction_deg < 1e-6 && e.position_m < 1e-12, "{joint:?}: {e:?}");
            }
        }
        // The elevation axis seen from the left camera: about along x, about 6 cm below
        // and 3 cm behind the camera centre (camera y down: below is +y).
        let elev = head.axis_in_left_camera(Joint::Elevation, &head.aligned_encoders());
        assert!(elev.direction.x.abs() > 0.99);
        assert!((elev.point.y - 0.06).abs() < 0.01 && (elev.point.z + 0.03).abs() < 0.01, "{elev:?}");
        // A 1 deg wrong direction reads as 1 deg.
        let t = head.axis_in_left_camera(Joint::Pan, &enc);
        let perp = Unit::new_normalize(t.direction.cross(&Vector3::x()));
        let tilted = UnitQuaternion::from_axis_angle(&perp, 1f64.to_radians()) * t.direction;
        let e = head.axis_errors(Joint::Pan, &enc, &Line::new(tilted, t.point));
        assert!((e.direction_deg - 1.0).abs() < 1e-9);
    }
}
