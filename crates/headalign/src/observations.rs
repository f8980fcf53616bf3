//! The stereo view every procedure consumes: a name, the encoder readings at capture time
//! and the points tracked in each image (track identities shared across views and
//! cameras). Angles are degrees; pixels have (0, 0) at the centre of the top-left pixel.
//!
//! Views come from a head (`procedure`, `calibrate`), from the tracker ([`crate::tracking`])
//! or from files: the observation-session format `headalign-observations/1`
//! (`docs/formats.md#observation-files`) is read and written by the `headalign-io` crate
//! (`headalign_io::observations`), which validates what a user can get wrong.

use headalign_platform::StereoCapture;

/// One view of a session: a name, the encoder readings, the tracked points.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    /// Unique name (e.g. "initial", "elevation", "pan").
    pub name: String,
    /// The capture (encoders and observations).
    pub capture: StereoCapture,
}
