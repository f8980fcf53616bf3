//! Cross-validation of a self-calibration (`headalign check --split`): the views of one rig
//! split in two halves, each half self-calibrated on its own
//! ([`crate::calibrate::views::calibrate_views`]), and the two calibrations compared
//! against the uncertainty they predict, as mrcal's cross-validation does (two
//! calibrations from independent data should differ by no more than their sigmas allow).
//!
//! # What it computes
//!
//! For each quantity both halves estimate, the difference `second - first` and its sigma
//! `sqrt(s1^2 + s2^2)` (the halves' data are independent, so their errors are), and `z =
//! |difference| / sigma`:
//! - the intrinsics `fx fy cx cy` (and `skew` when estimated) of each camera, pixels;
//! - the rig rotation `R_2 R_1^-1 = exp([pitch, yaw, roll])` about the right camera's x, y
//!   and z axes (the convention of [`super::check_views`]'s rotation change and of the
//!   bundle's `rig.rot` tangent), degrees;
//! - the baseline direction: the second half's in the tangent basis of the first's
//!   ([`headalign_geometry::bundle::tangent_basis`], the basis of `rig.tdir0..1`: for a
//!   baseline along the cameras' x axis the first component is about y, the vertical, the
//!   second about z, along the optical axis), degrees (the length is the scale gauge of a
//!   self-calibration: not compared);
//! - each lens coefficient either half estimates (dimensionless), when both halves have
//!   the same lens model (with `lens auto` they may choose different ones: then a warning
//!   says so and no coefficient is compared).
//!
//! The sigmas are each half's reported ones (the bundle covariance after `calibrate`'s
//! widenings: the bootstrap of the focal lengths and the lens, the residual structure), so
//! the test checks those sigmas as much as the calibration.
//!
//! # Warning rule
//!
//! A difference beyond [`SplitOptions::warn_sigmas`] (default 3) of its sigma is a
//! warning. Under Gaussian errors a single quantity passes 3 sigmas in 0.27 % of
//! splits; with the 15-25 quantities compared, about 4-7 % of consistent calibrations show
//! one warning by chance, which is why a warning names its quantity and its `z` rather
//! than failing the check.
//!
//! # The split
//!
//! Views of one rig ([`crate::calibrate::views::one_rig`], the others named in `skipped`)
//! are split in order: the first `ceil(n / 2)` views and the rest (each half a stretch of
//! the recording, whose views overlap the way the recording's do). With
//! [`SplitOptions::interleave`] even-indexed views form the first half and odd-indexed the
//! second, so that both halves span the session's motions (the procedure's session,
//! initial, elevation+-, pan+-, split in order leaves one half with a single rotation
//! axis). Each half needs at least two views (a reference and one moved view), so at least
//! four views are needed. Four pairs (e.g. `data/euroc_v101_pairs`, two places visited
//! twice: pairs 0-1 and 2-3 overlap, 0/1 and 2/3 do not) give halves of one motion each:
//! their calibrations lean on the constraints (zero skew) and their sigmas are large; the
//! comparison is valid, but weak.
//!
//! # Pitfalls
//!
//! - Consecutive frames of a video are nearly the same view: interleaved halves then share
//!   their scene and motions, and differ only by image noise; the test checks the sigmas'
//!   noise part, not their sensitivity to the choice of views.
//! - The halves' sigmas at their own estimates: for differences many sigmas large the
//!   linearisation is only indicative (the warning stands).

use headalign_geometry::bundle::{BundleResult, tangent_basis};
use headalign_geometry::so3;
use headalign_platform::StereoImages;
use nalgebra::{Matrix2, Rotation3};
use serde::Serialize;

use super::CheckError;
use crate::AlignError;
use crate::calibrate::views::{
    CalibrateViewsOptions, StereoViews, ViewsCalibration, ViewsProgress, calibrate_views, one_rig,
};
use crate::observations::View;

/// The options of [`cross_validate`].
#[derive(Debug, Clone)]
pub struct SplitOptions {
    /// The self-calibration of each half. Default [`CalibrateViewsOptions::default`].
    pub calibrate: CalibrateViewsOptions,
    /// A difference beyond this many of its sigmas is a warning. Default 3.
    pub warn_sigmas: f64,
    /// Split into even- and odd-indexed views instead of the first and the second half of
    /// the views in order. Default false.
    pub interleave: bool,
}

impl Default for SplitOptions {
    fn default() -> Self {
        Self { calibrate: CalibrateViewsOptions::default(), warn_sigmas: 3.0, interleave: false }
    }
}

impl SplitOptions {
    /// An error naming the first bad option.
    pub fn validate(&self) -> Result<(), CheckError> {
        self.calibrate.validate()?;
        if !(self.warn_sigmas.is_finite() && self.warn_sigmas > 0.0) {
            return Err(CheckError::InvalidOption(format!(
                "the warning threshold must be a positive number of sigmas, got {}",
                self.warn_sigmas
            )));
        }
        Ok(())
    }
}

/// One compared quantity.
#[derive(Debug, Clone, Serialize)]
pub struct Difference {
    /// `left.fx`, `rotation.yaw`, `baseline.tdir0`, `right.k1`, ...
    pub name: String,
    /// `px`, `deg` or empty (lens coefficients).
    pub unit: &'static str,
    /// The first half's value (0 for the rotation and the baseline direction: the
    /// difference is measured from the first half).
    pub first: f64,
    /// The second half's value (the difference for the rotation and baseline direction).
    pub second: f64,
    /// `second - first`.
    pub difference: f64,
    /// `sqrt(s1^2 + s2^2)`.
    pub sigma: f64,
    /// `|difference| / sigma`.
    pub z: f64,
}

/// The result of [`cross_validate`].
#[derive(Debug, Clone, Serialize)]
pub struct SplitReport {
    /// The names of each half's views.
    pub halves: [Vec<String>; 2],
    /// Each compared quantity.
    pub differences: Vec<Difference>,
    /// The largest `z`.
    pub max_z: f64,
    /// The threshold of the warnings, sigmas.
    pub warn_sigmas: f64,
    /// One line per difference beyond `warn_sigmas`, and a lens model mismatch.
    pub warnings: Vec<String>,
    /// Views left out as of another rig state, each with the reason.
    pub skipped: Vec<String>,
    /// Each half's RMS reprojection error, pixels.
    pub rms_px: [f64; 2],
}

/// The two halves of `items`: the first `ceil(n / 2)` and the rest, or with `interleave`
/// the even- and odd-indexed items.
fn halves_of<T: Clone>(items: &[T], interleave: bool) -> [Vec<T>; 2] {
    if interleave {
        let half = |r: usize| items.iter().skip(r).step_by(2).cloned().collect();
        return [half(0), half(1)];
    }
    let (a, b) = items.split_at(items.len().div_ceil(2));
    [a.to_vec(), b.to_vec()]
}

/// Self-calibrate each half of `views` and compare the two (module docs); `progress`
/// hears each half's steps with the half's index (0, 1).
pub fn cross_validate(
    views: StereoViews<'_>,
    options: &SplitOptions,
    progress: &mut dyn FnMut(usize, ViewsProgress),
) -> Result<SplitReport, CheckError> {
    options.validate()?;
    let mut halves: [Vec<String>; 2] = Default::default();
    let mut results = Vec::new();
    let skipped = match views {
        StereoViews::Images(images) => {
            let (rig, skipped) = one_rig(images, |(n, v)| (n.as_str(), v.encoders));
            let split: [Vec<(String, StereoImages)>; 2] = halves_of(&rig, options.interleave);
            need_views(rig.len())?;
            for (k, half) in split.iter().enumerate() {
                halves[k] = half.iter().map(|(n, _)| n.clone()).collect();
                results.push(calibrate_half(StereoViews::Images(half), k, &halves[k], options, progress)?);
            }
            skipped
        }
        StereoViews::Tracked(tracked) => {
            let (rig, skipped) = one_rig(tracked, |v| (v.name.as_str(), v.capture.encoders));
            let split: [Vec<View>; 2] = halves_of(&rig, options.interleave);
            need_views(rig.len())?;
            for (k, half) in split.iter().enumerate() {
                halves[k] = half.iter().map(|v| v.name.clone()).collect();
                results.push(calibrate_half(StereoViews::Tracked(half), k, &halves[k], options, progress)?);
            }
            skipped
        }
    };
    let [a, b] = [&results[0].calibration.bundle, &results[1].calibration.bundle];
    let (differences, mut warnings) = differences(a, b);
    let max_z = differences.iter().map(|d| d.z).filter(|z| z.is_finite()).fold(0.0, f64::max);
    for d in differences.iter().filter(|d| d.z > options.warn_sigmas) {
        warnings.push(format!(
            "{}: the halves differ by {:.4} {} ({:.1} sigmas of {:.4})",
            d.name, d.difference, d.unit, d.z, d.sigma
        ));
    }
    Ok(SplitReport {
        halves,
        differences,
        max_z,
        warn_sigmas: options.warn_sigmas,
        warnings,
        skipped,
        rms_px: [a.report.final_rms_px, b.report.final_rms_px],
    })
}

/// An error unless `n` views of one rig make two halves of at least two views.
fn need_views(n: usize) -> Result<(), CheckError> {
    if n < 4 {
        return Err(CheckError::Align(AlignError::Observations(format!(
            "cross-validation needs at least 4 views of one rig (two per half), got {n}"
        ))));
    }
    Ok(())
}

/// The self-calibration of half `k` (its views named `names`).
fn calibrate_half(
    views: StereoViews<'_>,
    k: usize,
    names: &[String],
    options: &SplitOptions,
    progress: &mut dyn FnMut(usize, ViewsProgress),
) -> Result<ViewsCalibration, CheckError> {
    calibrate_views(views, &options.calibrate, &mut |p| progress(k, p)).map_err(|e| {
        let which = if k == 0 { "first" } else { "second" };
        CheckError::Align(e.in_step(&format!("calibrating the {which} half ({})", names.join(", "))))
    })
}

/// A difference of `first` and `second` with the halves' sigmas.
fn difference(name: String, unit: &'static str, first: f64, second: f64, s: [f64; 2]) -> Difference {
    let sigma = s[0].hypot(s[1]);
    let d = second - first;
    Difference { name, unit, first, second, difference: d, sigma, z: d.abs() / sigma }
}

/// The compared quantities of two calibrations (module docs) and a lens-model warning.
fn differences(a: &BundleResult, b: &BundleResult) -> (Vec<Difference>, Vec<String>) {
    let (ca, cb) = (&a.covariance, &b.covariance);
    let sig = |name: &str| [ca.sigma(name), cb.sigma(name)];
    let mut out = Vec::new();
    let mut warnings = Vec::new();
    for (side, ka, kb) in [("left", &a.state.left, &b.state.left), ("right", &a.state.right, &b.state.right)]
    {
        let values = |k: &headalign_geometry::camera::Intrinsics| [k.fx, k.fy, k.skew, k.cx, k.cy];
        for (i, what) in ["fx", "fy", "skew", "cx", "cy"].iter().enumerate() {
            let name = format!("{side}.{what}");
            if let [Some(s1), Some(s2)] = sig(&name) {
                out.push(difference(name, "px", values(ka)[i], values(kb)[i], [s1, s2]));
            }
        }
    }
    out.extend(rotation_and_baseline(a, b));
    for (side, da, db) in [
        ("left", &a.state.left_distortion, &b.state.left_distortion),
        ("right", &a.state.right_distortion, &b.state.right_distortion),
    ] {
        if da.kind != db.kind {
            warnings.push(format!(
                "the halves chose different {side} lens models ({} and {}): their coefficients are not compared",
                da.kind.model().names().short,
                db.kind.model().names().short
            ));
            continue;
        }
        let (pa, pb) = (da.params(), db.params());
        for (i, param) in da.kind.coefficient_names().iter().enumerate() {
            let name = format!("{side}.{param}");
            if let [Some(s1), Some(s2)] = sig(&name) {
                out.push(difference(name, "", pa[i], pb[i], [s1, s2]));
            }
        }
    }
    (out, warnings)
}

/// The rotation `R_b R_a^-1` (pitch, yaw, roll) and the baseline direction of `b` in the
/// tangent basis of `a`'s, degrees, with the halves' sigmas (module docs).
fn rotation_and_baseline(a: &BundleResult, b: &BundleResult) -> Vec<Difference> {
    let mut out = Vec::new();
    let (ra, rb) = (a.state.right_from_left, b.state.right_from_left);
    let w = so3::log(&Rotation3::from(rb.rotation * ra.rotation.inverse()));
    let (ca, cb) = (&a.covariance, &b.covariance);
    for (i, axis) in ["pitch", "yaw", "roll"].iter().enumerate() {
        let name = format!("rig.rot{i}");
        if let (Some(s1), Some(s2)) = (ca.sigma(&name), cb.sigma(&name)) {
            let d = w[i].to_degrees();
            out.push(difference(
                format!("rotation.{axis}"),
                "deg",
                0.0,
                d,
                [s1.to_degrees(), s2.to_degrees()],
            ));
        }
    }
    let (ta, tb) = (ra.translation.vector.normalize(), rb.translation.vector.normalize());
    let (ba, bb) = (tangent_basis(&ta), tangent_basis(&tb));
    let along = ta.dot(&tb);
    let block = |c: &headalign_geometry::bundle::Covariance| -> Option<Matrix2<f64>> {
        let i = [c.index("rig.tdir0")?, c.index("rig.tdir1")?];
        Some(Matrix2::from_fn(|r, s| c.matrix[(i[r], i[s])]))
    };
    if let (Some(c1), Some(c2)) = (block(ca), block(cb))
        && along > 0.0
    {
        let d = ba.transpose() * tb / along;
        // The second half's tangent covariance carried into the first half's basis.
        let j = ba.transpose() * bb;
        let c = c1 + j * c2 * j.transpose();
        for i in 0..2 {
            let s = c[(i, i)].max(0.0).sqrt().to_degrees();
            out.push(difference(format!("baseline.tdir{i}"), "deg", 0.0, d[i].to_degrees(), [s, 0.0]));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use headalign_platform::{Joint, StereoHead};
    use headalign_sim::{Scenario, SimulatedHead};
    use nalgebra::{Point2, Vector3};

    use super::*;

    /// Six point-mode views of the simulated head at one vergence (one rig), ordered so
    /// that each half has the initial position and one elevation and one pan rotation of 5
    /// deg (two axes: a self-calibration without constraints).
    fn session(noise_px: f64) -> Vec<View> {
        let scenario =
            Scenario { seed: 3, noise_px, points: 600, outlier_fraction: 0.0, ..Scenario::default() };
        let mut head = SimulatedHead::new(scenario).unwrap();
        let e0 = head.encoders();
        let at = [
            ("initial-a", e0),
            ("elevation+", e0.moved(Joint::Elevation, 5.0)),
            ("pan+", e0.moved(Joint::Pan, 5.0)),
            ("initial-b", e0),
            ("elevation-", e0.moved(Joint::Elevation, -5.0)),
            ("pan-", e0.moved(Joint::Pan, -5.0)),
        ];
        at.iter()
            .map(|(name, enc)| {
                head.move_to(enc).unwrap();
                View { name: (*name).into(), capture: head.capture().unwrap() }
            })
            .collect()
    }

    /// The right camera of `view` turned by `w` (radians) about its centre: its pixels move
    /// by the homography `K dR K^-1` (exact for the simulator's pinhole cameras).
    fn turn_right(view: &mut View, k: &headalign_geometry::camera::Intrinsics, w: &Vector3<f64>) {
        let h = k.matrix() * so3::exp(w).matrix() * k.inverse_matrix();
        for o in &mut view.capture.right {
            let x = h * Vector3::new(o.pixel.x, o.pixel.y, 1.0);
            o.pixel = Point2::new(x.x / x.z, x.y / x.z);
        }
    }

    /// Halves of one rig agree within their sigmas on every quantity (4 sigmas: one seed,
    /// about 20 quantities); the right camera turned by 0.3 deg of pitch in the second
    /// half's views (a knock between the halves) is found (within 4 sigmas of 0.3) and
    /// warned of.
    #[test]
    fn halves_agree_and_a_knock_between_them_is_warned_of() {
        let views = session(0.5);
        let options = SplitOptions::default();
        let r = cross_validate(StereoViews::Tracked(&views), &options, &mut |_, _| {}).unwrap();
        assert_eq!(r.halves[0], ["initial-a", "elevation+", "pan+"]);
        // Pinhole halves: 8 intrinsics (zero skew held), 3 rotation angles, 2 baseline components.
        assert_eq!(r.differences.len(), 13, "{:?}", r.differences);
        assert!(r.max_z < 4.0 && r.warnings.is_empty(), "{r:#?}");
        let mut knocked = views.clone();
        let k = SimulatedHead::new(Scenario { seed: 3, ..Scenario::default() }).unwrap().truth().right;
        let w = Vector3::new(0.3_f64.to_radians(), 0.0, 0.0);
        for v in knocked.iter_mut().skip(3) {
            turn_right(v, &k, &w);
        }
        let r = cross_validate(StereoViews::Tracked(&knocked), &options, &mut |_, _| {}).unwrap();
        let pitch = r.differences.iter().find(|d| d.name == "rotation.pitch").unwrap();
        assert!((pitch.difference - 0.3).abs() < 4.0 * pitch.sigma && pitch.z > 3.0, "{pitch:?}");
        assert!(r.warnings.iter().any(|w| w.starts_with("rotation.pitch")), "{:?}", r.warnings);
    }

    #[test]
    fn halves_in_order_or_interleaved() {
        assert_eq!(halves_of(&[0, 1, 2, 3, 4], true), [vec![0, 2, 4], vec![1, 3]]);
        assert_eq!(halves_of(&[0, 1, 2, 3, 4], false), [vec![0, 1, 2], vec![3, 4]]);
    }

    #[test]
    fn bad_options_are_errors() {
        let o = SplitOptions { warn_sigmas: 0.0, ..SplitOptions::default() };
        assert!(matches!(o.validate(), Err(CheckError::InvalidOption(_))));
        assert!(SplitOptions::default().validate().is_ok());
    }

    #[test]
    fn too_few_views_are_an_error() {
        let e = cross_validate(StereoViews::Tracked(&[]), &SplitOptions::default(), &mut |_, _| {});
        assert!(matches!(e, Err(CheckError::Align(AlignError::Observations(_)))), "{e:?}");
    }
}
