//! A calibrated stereo pair as the procedures give it and the calibration files hold it
//! ([`StereoCalibration`]): both cameras' intrinsics (pixels) with their sigmas, the rig
//! pose `right_from_left`, each camera's lens distortion, and the pair's rectification.
//!
//! What it computes: nothing is estimated here; a rig estimate ([`RigCalibration`], any
//! [`BundleResult`]) is put in this form, its translation scaled to metres when the user
//! gives the baseline length and to unit length (baselines) otherwise: the
//! self-calibration is only up to scale. The rectification comes from
//! [`headalign_geometry::rectify::rectify_stereo`]. The files (JSON, OpenCV YAML, ROS
//! `camera_info`, Kalibr `camchain.yaml`) are written by the `headalign-io` crate
//! (`headalign_io::export`).

use headalign_geometry::bundle::BundleResult;
use headalign_geometry::camera::Intrinsics;
use headalign_geometry::distortion::Distortion;
use headalign_geometry::rectify::{Rectification, rectify_stereo};
use nalgebra::{Isometry3, Matrix3};

use crate::AlignError;
use crate::verge_tilt::RigCalibration;

/// The unit of the rig translation in the written files.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TranslationUnit {
    /// Metres (the user gave the baseline length).
    Metres,
    /// Baselines: the translation has unit length (self-calibration fixes no scale).
    Baselines,
}

impl TranslationUnit {
    /// The unit's name in the files: `m` or `baselines`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Metres => "m",
            Self::Baselines => "baselines",
        }
    }
}

/// Standard deviations of one camera's intrinsics, pixels (`None` where not estimated).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct IntrinsicSigmas {
    /// Of `fx`.
    pub fx: Option<f64>,
    /// Of `fy`.
    pub fy: Option<f64>,
    /// Of `cx`.
    pub cx: Option<f64>,
    /// Of `cy`.
    pub cy: Option<f64>,
    /// Of the skew.
    pub skew: Option<f64>,
}

/// A calibrated stereo pair, ready to be written.
#[derive(Debug, Clone, PartialEq)]
pub struct StereoCalibration {
    /// Image size `[width, height]`, pixels.
    pub image_size: [u32; 2],
    /// Left camera intrinsics.
    pub left: Intrinsics,
    /// Right camera intrinsics.
    pub right: Intrinsics,
    /// Their standard deviations.
    pub sigmas: [IntrinsicSigmas; 2],
    /// Rig pose: maps points in the left camera frame to the right one.
    pub right_from_left: Isometry3<f64>,
    /// Unit of `right_from_left`'s translation.
    pub unit: TranslationUnit,
    /// Lens distortion of each camera (OpenCV `plumb_bob` `k1 k2 p1 p2 k3`; zero when no
    /// lens model was given).
    pub distortion: [Distortion; 2],
}

impl StereoCalibration {
    /// From an estimated rig, with its estimated lenses (zero for a pinhole estimate:
    /// [`crate::verge_tilt::EstimationOptions::lens`]). With `baseline_m` the translation is
    /// scaled to metres; without, it stays in baselines.
    pub fn from_rig(
        calib: &RigCalibration,
        image_size: [u32; 2],
        baseline_m: Option<f64>,
    ) -> Result<Self, AlignError> {
        let mut c = Self::from_bundle(&calib.bundle, image_size, baseline_m)?;
        c.distortion = [calib.bundle.state.left_distortion, calib.bundle.state.right_distortion];
        Ok(c)
    }

    /// From any rig bundle adjustment (its state's cameras and rig, its covariance's
    /// sigmas); distortion zero. With `baseline_m` the translation is scaled to metres.
    pub fn from_bundle(
        bundle: &BundleResult,
        image_size: [u32; 2],
        baseline_m: Option<f64>,
    ) -> Result<Self, AlignError> {
        let state = &bundle.state;
        let mut right_from_left = state.right_from_left;
        let norm = right_from_left.translation.vector.norm();
        if !norm.is_finite() || norm <= 0.0 {
            return Err(AlignError::Output("the rig has no baseline".into()));
        }
        let unit = scale_translation(&mut right_from_left, baseline_m)?;
        let c = &bundle.covariance;
        let sig = |side: &str| IntrinsicSigmas {
            fx: c.sigma(&format!("{side}.fx")),
            fy: c.sigma(&format!("{side}.fy")),
            cx: c.sigma(&format!("{side}.cx")),
            cy: c.sigma(&format!("{side}.cy")),
            skew: c.sigma(&format!("{side}.skew")),
        };
        Ok(Self {
            image_size,
            left: state.left,
            right: state.right,
            sigmas: [sig("left"), sig("right")],
            right_from_left,
            unit,
            distortion: [Distortion::default(); 2],
        })
    }

    /// From known cameras (`left`, `right`, no sigmas), their lenses and the rig
    /// `right_from_left` of a calibrated relative pose (any translation length: scaled to
    /// `baseline_m` metres, else to one baseline).
    pub fn from_known(
        image_size: [u32; 2],
        left: Intrinsics,
        right: Intrinsics,
        right_from_left: Isometry3<f64>,
        distortion: [Distortion; 2],
        baseline_m: Option<f64>,
    ) -> Result<Self, AlignError> {
        let mut right_from_left = right_from_left;
        let unit = scale_translation(&mut right_from_left, baseline_m)?;
        Ok(Self { image_size, left, right, sigmas: Default::default(), right_from_left, unit, distortion })
    }

    /// The rectification of the pair.
    pub fn rectification(&self) -> Result<Rectification, AlignError> {
        rectify_stereo(&self.left, &self.right, &self.right_from_left, self.image_size)
            .map_err(|e| AlignError::Output(format!("stereo rectification: {e}")))
    }

    /// The rotation of `right_from_left` as a matrix.
    pub fn rotation(&self) -> Matrix3<f64> {
        self.right_from_left.rotation.to_rotation_matrix().into_inner()
    }
}

/// Scale the rig's translation to `baseline_m` metres, or to one baseline without it; the
/// unit it is then in. A baseline that is not a positive number is an error.
fn scale_translation(
    right_from_left: &mut Isometry3<f64>,
    baseline_m: Option<f64>,
) -> Result<TranslationUnit, AlignError> {
    let norm = right_from_left.translation.vector.norm();
    match baseline_m {
        Some(b) if b.is_finite() && b > 0.0 => {
            right_from_left.translation.vector *= b / norm;
            Ok(TranslationUnit::Metres)
        }
        Some(b) => Err(AlignError::InvalidOption(format!("baseline must be positive, got {b}"))),
        None => {
            right_from_left.translation.vector /= norm;
            Ok(TranslationUnit::Baselines)
        }
    }
}
