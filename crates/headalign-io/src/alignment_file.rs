//! The file `alignment.json` (`align --out`), format `headalign-alignment/2`
//! (`docs/formats.md#calibration-files`): where the head is aligned, on either route.
//!
//! Members: `format`, `route` (`general` or `planar`), `reference_encoders` (the readings
//! the alignment is relative to), `aligned_encoders` and `aligned_sigma_deg` (the
//! estimated aligned readings and their sigmas), `verge_axes_measured`,
//! `predicted_elev_err_r_deg` (the right camera's elevation error no joint can remove),
//! `roll_left_deg`, `roll_right_deg`, and `undetermined` (what a plane leaves
//! undetermined; empty on the general route). Every angle is degrees.
//!
//! Nothing is computed here: the members are the procedure's [`AlignmentSolution`] and
//! [`AlignmentSigmas`] as they are. Numbers round-trip exactly (`serde_json` with
//! `float_roundtrip`).

use std::path::Path;

use headalign::alignment::AlignmentSolution;
use headalign::procedure::AlignmentSigmas;
use headalign_platform::Encoders;
use serde::Serialize;

use crate::error::FileError;

/// The format tag of `alignment.json`.
pub const FORMAT: &str = "headalign-alignment/2";

/// The file `alignment.json` (module docs), on either route.
#[derive(Debug, Clone, Serialize)]
pub struct AlignmentFile {
    /// [`FORMAT`].
    pub format: &'static str,
    /// `general` or `planar`.
    pub route: &'static str,
    /// The readings the alignment is relative to, degrees.
    pub reference_encoders: Encoders,
    /// The aligned readings, degrees.
    pub aligned_encoders: Encoders,
    /// Their sigmas, degrees.
    pub aligned_sigma_deg: AlignmentSigmas,
    /// The vergence axes were measured (not nominal).
    pub verge_axes_measured: bool,
    /// The right camera's elevation error no joint can remove, degrees.
    pub predicted_elev_err_r_deg: f64,
    /// The left camera's roll, degrees.
    pub roll_left_deg: f64,
    /// The right camera's roll, degrees.
    pub roll_right_deg: f64,
    /// What the scene leaves undetermined (empty on the general route).
    pub undetermined: Vec<String>,
}

impl AlignmentFile {
    /// The file of `route`: the reference and aligned readings with their sigmas, the
    /// rolls and what the scene leaves `undetermined`.
    pub fn new(
        route: &'static str,
        reference: Encoders,
        solution: &AlignmentSolution,
        sigmas: AlignmentSigmas,
        undetermined: &[String],
    ) -> Self {
        Self {
            format: FORMAT,
            route,
            reference_encoders: reference,
            aligned_encoders: solution.aligned_encoders,
            aligned_sigma_deg: sigmas,
            verge_axes_measured: solution.verge_axes_measured,
            predicted_elev_err_r_deg: solution.predicted_elev_err_r_deg,
            roll_left_deg: solution.roll_left_deg,
            roll_right_deg: solution.roll_right_deg,
            undetermined: undetermined.to_vec(),
        }
    }

    /// Write the file to `path` (pretty JSON and a final newline).
    pub fn write(&self, path: &Path) -> Result<(), FileError> {
        let text = serde_json::to_string_pretty(self)
            .map_err(|e| FileError::File(format!("cannot encode JSON: {e}")))?;
        std::fs::write(path, text + "\n")
            .map_err(|e| FileError::File(format!("cannot write {}: {e}", path.display())))
    }
}
