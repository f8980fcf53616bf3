//! # headalign-platform
//!
//! The seam between the alignment procedures and whatever moves the cameras: the
//! [`StereoHead`] trait and the data it exchanges. The procedures in the `headalign`
//! crate see a head only through this trait; the simulator (`headalign-sim`), a recorded
//! session on disk, or a user's driver implement it.
//!
//! Units: encoder readings in degrees (the joint angle is `encoder - zero_offset`, the
//! offsets being what alignment finds); pixels with (0, 0) at the centre of the top-left
//! pixel (`docs/conventions.md#joints-and-encoders`, `docs/conventions.md#pixels-and-intrinsics`).

pub use headalign_vision::GrayImage;
use nalgebra::Point2;
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// One of the four revolute joints of the head.
///
/// Directions (the simulator's, and what the image-mode procedures assume at first; they
/// detect and correct a reversed joint): a positive pan move turns the head left, a
/// positive elevation move turns it up, a positive vergence move turns that camera right.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Joint {
    /// Pan: axis nominally vertical, fixed to the robot.
    Pan,
    /// Elevation (tilt): axis nominally horizontal, carried by pan.
    Elevation,
    /// Left vergence: carried by elevation.
    VergeLeft,
    /// Right vergence: carried by elevation.
    VergeRight,
}

impl Joint {
    /// All joints, from the root of the kinematic chain outwards (pan, elevation, verges).
    pub const ALL: [Joint; 4] = [Joint::Pan, Joint::Elevation, Joint::VergeLeft, Joint::VergeRight];

    /// The name used in files and reports.
    pub fn name(self) -> &'static str {
        match self {
            Joint::Pan => "pan",
            Joint::Elevation => "elevation",
            Joint::VergeLeft => "verge_left",
            Joint::VergeRight => "verge_right",
        }
    }
}

/// Encoder readings of the four joints, degrees.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Encoders {
    /// Pan encoder, degrees.
    pub pan: f64,
    /// Elevation encoder, degrees.
    pub elevation: f64,
    /// Left vergence encoder, degrees.
    pub verge_left: f64,
    /// Right vergence encoder, degrees.
    pub verge_right: f64,
}

impl Encoders {
    /// Reading of one joint.
    pub fn get(&self, joint: Joint) -> f64 {
        match joint {
            Joint::Pan => self.pan,
            Joint::Elevation => self.elevation,
            Joint::VergeLeft => self.verge_left,
            Joint::VergeRight => self.verge_right,
        }
    }

    /// Mutable reading of one joint.
    pub fn get_mut(&mut self, joint: Joint) -> &mut f64 {
        match joint {
            Joint::Pan => &mut self.pan,
            Joint::Elevation => &mut self.elevation,
            Joint::VergeLeft => &mut self.verge_left,
            Joint::VergeRight => &mut self.verge_right,
        }
    }

    /// These readings with one joint moved by `delta_deg`.
    pub fn moved(mut self, joint: Joint, delta_deg: f64) -> Self {
        *self.get_mut(joint) += delta_deg;
        self
    }

    /// True if every reading is finite.
    pub fn is_finite(&self) -> bool {
        Joint::ALL.iter().all(|&j| self.get(j).is_finite())
    }
}

/// One observation of a scene point in one image: its track id (the same id names the
/// same scene point in every image of every view) and its pixel position.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TrackObservation {
    /// Track identity.
    pub track: u64,
    /// Pixel position.
    pub pixel: Point2<f64>,
}

/// What one capture returns in point mode: the encoder readings at capture time and the
/// tracked points seen by each camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StereoCapture {
    /// Encoder readings when the images were taken.
    pub encoders: Encoders,
    /// Image size `[width, height]`, pixels.
    pub image_size: [u32; 2],
    /// Observations in the left image.
    pub left: Vec<TrackObservation>,
    /// Observations in the right image.
    pub right: Vec<TrackObservation>,
}

/// Failures reported by a platform.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum PlatformError {
    /// A commanded position is outside the joint's range.
    #[error("joint {joint:?} cannot reach {target_deg} deg (range {min_deg}..{max_deg})")]
    OutOfRange {
        /// The joint.
        joint: Joint,
        /// Commanded reading.
        target_deg: f64,
        /// Lowest reachable reading.
        min_deg: f64,
        /// Highest reachable reading.
        max_deg: f64,
    },
    /// A command or reading that is not a finite number.
    #[error("invalid command: {0}")]
    InvalidCommand(String),
    /// The device failed (communication, timeout, driver exit).
    #[error("device error: {0}")]
    Device(String),
    /// The image front end of an imaging head failed (no usable matches, bad images).
    #[error("image front end: {0}")]
    FrontEnd(String),
}

/// A stereo pan-tilt-verge head as the procedures see it.
///
/// Implementations: the simulator, a recorded session (replay), a real head's driver.
pub trait StereoHead {
    /// Image size `[width, height]` in pixels, the same for both cameras.
    fn image_size(&self) -> [u32; 2];
    /// Current encoder readings.
    fn read_encoders(&mut self) -> Result<Encoders, PlatformError>;
    /// Move every joint to the given encoder readings (absolute), blocking until done.
    fn move_to(&mut self, target: &Encoders) -> Result<(), PlatformError>;
    /// Capture a stereo view at the current position.
    fn capture(&mut self) -> Result<StereoCapture, PlatformError>;
}

/// A stereo pair of images and the encoder readings when they were taken (image mode).
#[derive(Debug, Clone, PartialEq)]
pub struct StereoImages {
    /// Encoder readings when the images were taken.
    pub encoders: Encoders,
    /// Left image.
    pub left: GrayImage,
    /// Right image.
    pub right: GrayImage,
}

impl StereoImages {
    /// A pair; errors if the two images differ in size.
    pub fn new(encoders: Encoders, left: GrayImage, right: GrayImage) -> Result<Self, PlatformError> {
        if left.size() != right.size() {
            return Err(PlatformError::Device(format!(
                "left image is {}x{} but right image is {}x{}",
                left.width(),
                left.height(),
                right.width(),
                right.height()
            )));
        }
        Ok(Self { encoders, left, right })
    }

    /// Image size `[width, height]`.
    pub fn image_size(&self) -> [u32; 2] {
        self.left.size()
    }
}

/// A head whose cameras deliver images (image mode). The image-mode procedures move it
/// with [`StereoHead::move_to`], read it with [`StereoHead::read_encoders`] and take
/// pictures with [`ImagingHead::capture_images`]; they find correspondences themselves and
/// never call [`StereoHead::capture`] (a head without its own tracker may return an error
/// there).
pub trait ImagingHead: StereoHead {
    /// Capture both images at the current position.
    fn capture_images(&mut self) -> Result<StereoImages, PlatformError>;
}

/// What a vehicle's own sensors measured of its last drive (wheel odometry). The
/// procedures never use it (they measure every motion by vision); sessions record it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Odometry {
    /// Distance travelled, signed metres (negative: backwards).
    pub distance_m: f64,
    /// Change of heading, degrees, positive turning left (`None`: not measured).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub heading_deg: Option<f64>,
}

impl Odometry {
    /// True if every number is finite.
    pub fn is_finite(&self) -> bool {
        self.distance_m.is_finite() && self.heading_deg.is_none_or(f64::is_finite)
    }
}

/// A wheeled robot carrying the head, as the procedures see it: a tricycle AGV (one
/// steered front wheel, a fixed rear axle) that drives on the ground plane
/// (`docs/conventions.md#the-robot-and-steering`).
///
/// Units: metres for distances (positive forward, negative reverses along the same
/// arc), degrees for the steering encoder (the true steering angle is
/// `encoder - zero_offset`; the zero offset is what steering alignment finds).
pub trait Vehicle {
    /// Drive `distance_m` along the current steering arc, blocking until done.
    fn drive(&mut self, distance_m: f64) -> Result<(), PlatformError>;
    /// Turn the steering wheel to the absolute encoder reading `encoder_deg`.
    fn steer_to(&mut self, encoder_deg: f64) -> Result<(), PlatformError>;
    /// Current steering encoder reading, degrees.
    fn read_steering(&mut self) -> Result<f64, PlatformError>;
    /// Turn the steering wheel by `delta_deg` from its current reading.
    fn steer_by(&mut self, delta_deg: f64) -> Result<(), PlatformError> {
        let now = self.read_steering()?;
        self.steer_to(now + delta_deg)
    }
    /// The odometry of the last drive, if the vehicle reports any (default: none).
    fn last_odometry(&self) -> Option<Odometry> {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn encoders_get_and_move() {
        let e = Encoders { pan: 1.0, elevation: 2.0, verge_left: 3.0, verge_right: 4.0 };
        let m = e.moved(Joint::Elevation, 3.0);
        assert_eq!(m.get(Joint::Elevation), 5.0);
        assert_eq!(m.get(Joint::Pan), 1.0);
        assert!(m.is_finite());
        assert!(!e.moved(Joint::Pan, f64::NAN).is_finite());
        let names: Vec<_> = Joint::ALL.iter().map(|j| j.name()).collect();
        assert_eq!(names, ["pan", "elevation", "verge_left", "verge_right"]);
    }
}
