//! The session format's types and pure parts: the format tags and stage names,
//! `session.json` ([`SessionInfo`]), the lines of `events.jsonl` ([`Event`]), `view.json`
//! ([`ViewMeta`], parsed and checked by [`parse_view_json`]), the views read back
//! ([`RecordedView`], [`RecordedPoints`]), the blank-image check ([`check_image`]) and
//! the choice of the views that estimate ([`estimation_views`]). The layout is the
//! module documentation of `session`.
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use headalign::AlignError;
use headalign::calibrate::LensChoice;
use headalign::robot::stages::RobotPlan;
use headalign_geometry::distortion::DistortionTerms;
use headalign_platform::{Encoders, GrayImage, Odometry, StereoCapture, StereoImages};
use serde::{Deserialize, Serialize};

use crate::FileError;
use crate::observations::View;
/// The format tag of `session.json`.
pub const SESSION_FORMAT: &str = "headalign-session/1";
/// The format tag of `view.json`.
pub const VIEW_FORMAT: &str = "headalign-view/1";
/// The stage of the captures made while verging (the rig is not rigid there).
pub const STAGE_VERGING: &str = "verging";
/// The stage of the verge/tilt procedure's captures.
pub const STAGE_VERGE_TILT: &str = "verge-tilt";
/// The stage of the views of a rig-calibration session (`simulate --images`).
pub const STAGE_CALIBRATE: &str = "calibrate";
/// Stage name of the auto mode's probe captures (`procedure::resolve_rotation`): not
/// estimated from, so `align --images` leaves them out.
pub const STAGE_ROTATION_PROBE: &str = "rotation-probe";
/// A replayed move may differ from the recorded target by this much per joint, degrees
/// (recorded numbers round-trip exactly, so this only absorbs hand-edited files).
pub const REPLAY_MOVE_TOLERANCE_DEG: f64 = 1e-9;

/// Images whose grey-level standard deviation is below this are blank (no texture to
/// match), grey levels.
pub const MIN_IMAGE_STD: f64 = 2.0;

/// What ran, written to `session.json` when the session starts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SessionInfo {
    /// [`SESSION_FORMAT`].
    pub format: String,
    /// Creation time, UTC, `YYYY-MM-DDTHH:MM:SSZ`.
    pub created_utc: String,
    /// The procedure: `verge-tilt-images` (verging, then verge/tilt on images through the
    /// front end) or `verge-tilt-points` (verge/tilt on the head's tracked points).
    pub procedure: String,
    /// Rotation of the procedure's moves, degrees (with `auto_rotation`, the vergence
    /// move's; the elevation/pan rotations were chosen by probing).
    pub rotation_deg: f64,
    /// The procedure chose its elevation/pan rotations itself (probe captures in stage
    /// `rotation-probe` before the verge/tilt stage); absent in older sessions: false.
    #[serde(default)]
    pub auto_rotation: bool,
    /// Seed of the estimation's random choices.
    pub estimation_seed: u64,
    /// Image size `[width, height]`, pixels.
    pub image_size: [u32; 2],
    /// Free-form description of the head (simulator scenario, driver command, ...).
    #[serde(default)]
    pub head: serde_json::Value,
    /// The stages run after the verge/tilt procedure and their settings (procedure
    /// `robot-images`); absent otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stages: Option<serde_json::Value>,
    /// The lens model the estimation used (`radtan`, `equidistant` or `auto`:
    /// [`headalign::verge_tilt::EstimationOptions::lens`]); absent for the pinhole, and in older
    /// sessions.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lens: Option<String>,
    /// The lens coefficients estimated with `lens` ([`headalign::verge_tilt::EstimationOptions::lens_terms`]);
    /// absent with `lens`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lens_terms: Option<headalign_geometry::distortion::DistortionTerms>,
}

impl SessionInfo {
    /// A description stamped with the current time.
    pub fn new(procedure: &str, rotation_deg: f64, estimation_seed: u64, image_size: [u32; 2]) -> Self {
        Self {
            format: SESSION_FORMAT.to_string(),
            created_utc: utc_timestamp(SystemTime::now(), true),
            procedure: procedure.to_string(),
            rotation_deg,
            auto_rotation: false,
            estimation_seed,
            image_size,
            head: serde_json::Value::Null,
            stages: None,
            lens: None,
            lens_terms: None,
        }
    }

    /// The robot stages the session recorded (`stages`: their names and settings), if
    /// any; an error names `dir`'s `session.json`.
    pub fn robot_plan(&self, dir: &Path) -> Result<Option<RobotPlan>, FileError> {
        self.stages
            .clone()
            .map(serde_json::from_value)
            .transpose()
            .map_err(|e| FileError::File(format!("'{}': stages: {e}", dir.join("session.json").display())))
    }

    /// The lens model the session recorded (`lens`; the pinhole when absent); an unknown
    /// name is an error naming it.
    pub fn lens_choice(&self) -> Result<LensChoice, FileError> {
        match &self.lens {
            None => Ok(LensChoice::Pinhole),
            Some(name) => LensChoice::parse(name)
                .ok_or_else(|| FileError::File(format!("session.json: unknown lens model '{name}'"))),
        }
    }

    /// Record the lens model `lens` and its `terms` (nothing for the pinhole).
    pub fn set_lens(&mut self, lens: LensChoice, terms: Option<DistortionTerms>) {
        if lens != LensChoice::Pinhole {
            self.lens = Some(lens.name().to_string());
            self.lens_terms = terms;
        }
    }
}

/// One head call, a line of `events.jsonl`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "op", rename_all = "snake_case", deny_unknown_fields)]
pub enum Event {
    /// `read_encoders` returned these readings.
    Read {
        /// The readings, degrees.
        encoders: Encoders,
    },
    /// `move_to` succeeded with this target.
    Move {
        /// The target, degrees.
        target: Encoders,
    },
    /// A capture, saved in this view folder.
    Capture {
        /// The folder name (`NN-name`), relative to the session.
        folder: String,
    },
    /// `Vehicle::drive` succeeded with this signed distance.
    Drive {
        /// Metres (negative: backwards).
        distance_m: f64,
        /// What the vehicle's odometry measured of the drive, if it reports any.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        odometry: Option<Odometry>,
    },
    /// `Vehicle::steer_to` succeeded with this steering encoder target.
    Steer {
        /// Degrees.
        encoder_deg: f64,
    },
    /// `Vehicle::read_steering` returned this reading.
    ReadSteering {
        /// Degrees.
        encoder_deg: f64,
    },
}

/// What the vehicle did since the previous capture (`view.json` member `vehicle`, only in
/// sessions whose head is a vehicle).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
pub struct VehicleActions {
    /// Every drive since the previous capture, signed metres, in order.
    pub drives_m: Vec<f64>,
    /// The steering encoder, degrees: the last reading or target (`None`: not known yet).
    pub steering_deg: Option<f64>,
    /// The odometry of those drives, for a vehicle that reports it (in order; empty
    /// otherwise).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub odometry: Vec<Odometry>,
}

/// The contents of a `view.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewMeta {
    /// [`VIEW_FORMAT`] (absent in older sessions).
    #[serde(default)]
    pub format: Option<String>,
    /// Capture index in the session.
    #[serde(default)]
    pub index: Option<usize>,
    /// The view's name.
    pub name: String,
    /// The procedure stage ([`STAGE_VERGING`], [`STAGE_ROTATION_PROBE`], [`STAGE_VERGE_TILT`]); absent: verge-tilt.
    #[serde(default)]
    pub stage: Option<String>,
    /// Encoder readings at capture time, degrees.
    pub encoders: Encoders,
    /// The last commanded move before the capture, degrees.
    #[serde(default)]
    pub commanded: Option<Encoders>,
    /// Seconds since the session started.
    #[serde(default)]
    pub time_s: Option<f64>,
    /// Seconds since 1970-01-01 UTC.
    #[serde(default)]
    pub unix_time_s: Option<f64>,
    /// Image size `[width, height]`.
    #[serde(default)]
    pub image_size: Option<[u32; 2]>,
    /// Point mode: the tracked points of the capture.
    #[serde(default)]
    pub capture: Option<StereoCapture>,
    /// A head on a vehicle: the drives since the previous capture and the steering.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vehicle: Option<VehicleActions>,
}

/// `YYYY-MM-DDTHH:MM:SSZ` (or `YYYYMMDDTHHMMSSZ` when `separators` is false), UTC.
pub fn utc_timestamp(t: SystemTime, separators: bool) -> String {
    let secs = t.duration_since(UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0);
    let (days, rem) = ((secs / 86_400) as i64, secs % 86_400);
    // Civil date from days since 1970-01-01 (H. Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    let (hh, mm, ss) = (rem / 3600, rem % 3600 / 60, rem % 60);
    if separators {
        format!("{y:04}-{m:02}-{d:02}T{hh:02}:{mm:02}:{ss:02}Z")
    } else {
        format!("{y:04}{m:02}{d:02}T{hh:02}{mm:02}{ss:02}Z")
    }
}

/// A fresh session folder under `base` named by the current UTC time
/// (`base/20261123T212636Z`, with `-2`, `-3`, ... if that exists).
pub fn default_session_dir(base: &Path) -> PathBuf {
    let stamp = utc_timestamp(SystemTime::now(), false);
    let mut dir = base.join(&stamp);
    let mut k = 2;
    while dir.exists() {
        dir = base.join(format!("{stamp}-{k}"));
        k += 1;
    }
    dir
}

/// One recorded view.
#[derive(Debug, Clone)]
pub struct RecordedView {
    /// The view's name (from `view.json`).
    pub name: String,
    /// Its stage ([`STAGE_VERGING`], [`STAGE_ROTATION_PROBE`], [`STAGE_VERGE_TILT`]; absent in older sessions).
    pub stage: Option<String>,
    /// Its folder.
    pub folder: PathBuf,
    /// The images and the encoder readings.
    pub images: StereoImages,
}

impl RecordedView {
    /// True for the views of the verge/tilt procedure (stage absent or `verge-tilt`):
    /// the ones the estimation uses.
    pub fn is_verge_tilt(&self) -> bool {
        self.stage.as_deref().is_none_or(|s| s == STAGE_VERGE_TILT)
    }
}

/// Largest encoder reading a `view.json` may hold, degrees (ten turns, as the
/// observation reader allows: larger values are corrupt data, and differences of huge
/// readings overflow).
pub const MAX_ENCODER_DEG: f64 = 3600.0;

/// Parse and validate the text of a `view.json`; `origin` names it in messages.
pub fn parse_view_json(text: &str, origin: &str) -> Result<ViewMeta, AlignError> {
    let mut meta: ViewMeta =
        serde_json::from_str(text).map_err(|e| AlignError::Images(format!("'{origin}': {e}")))?;
    meta.name = meta.name.trim().to_string();
    if meta.name.is_empty() {
        return Err(AlignError::Images(format!("'{origin}': the view name is empty")));
    }
    let finite = |e: &Option<Encoders>| e.as_ref().is_none_or(Encoders::is_finite);
    if !meta.encoders.is_finite() || !finite(&meta.commanded) {
        return Err(AlignError::Images(format!("'{origin}': encoder readings must be finite")));
    }
    let huge =
        |e: &Encoders| headalign_platform::Joint::ALL.iter().any(|&j| e.get(j).abs() > MAX_ENCODER_DEG);
    if huge(&meta.encoders) || meta.commanded.as_ref().is_some_and(huge) {
        return Err(AlignError::Images(format!(
            "'{origin}': encoder reading beyond +-{MAX_ENCODER_DEG} deg"
        )));
    }
    Ok(meta)
}

/// Check that a decoded image has texture to match (grey-level standard deviation at
/// least [`MIN_IMAGE_STD`]); `origin` names it in messages.
pub fn check_image(img: &GrayImage, origin: &str) -> Result<(), AlignError> {
    let n = img.pixels().len() as f64;
    let mean = img.pixels().iter().map(|&v| f64::from(v)).sum::<f64>() / n;
    let var = img.pixels().iter().map(|&v| (f64::from(v) - mean).powi(2)).sum::<f64>() / n;
    if var.sqrt() < MIN_IMAGE_STD {
        return Err(AlignError::Images(format!(
            "'{origin}' is blank: grey-level standard deviation {:.2} (< {MIN_IMAGE_STD}), nothing to match",
            var.sqrt()
        )));
    }
    Ok(())
}

/// One view of a point-mode session.
#[derive(Debug, Clone)]
pub struct RecordedPoints {
    /// Its stage (as [`RecordedView::stage`]).
    pub stage: Option<String>,
    /// Its folder.
    pub folder: PathBuf,
    /// The view: name and tracked points (track ids are the session's).
    pub view: View,
}

impl RecordedPoints {
    /// True for the verge/tilt views (as [`RecordedView::is_verge_tilt`]).
    pub fn is_verge_tilt(&self) -> bool {
        self.stage.as_deref().is_none_or(|s| s == STAGE_VERGE_TILT)
    }
}

/// The views of a session that estimate a head's rig from its rotations (`align
/// --images`), chosen by stage (`stage_of`): the verge/tilt views if the session has any
/// (stage `verge-tilt` or absent: verging captures, rotation probes and robot stages are
/// left out), otherwise the views of stage `calibrate` (a rig session as `simulate
/// --images` records), otherwise every view.
pub fn estimation_views<T>(views: Vec<T>, stage_of: impl Fn(&T) -> Option<&str>) -> Vec<T> {
    let verge_tilt = |s: Option<&str>| s.is_none_or(|s| s == STAGE_VERGE_TILT);
    let keep: fn(Option<&str>) -> bool = if views.iter().any(|v| verge_tilt(stage_of(v))) {
        |s| s.is_none_or(|s| s == STAGE_VERGE_TILT)
    } else if views.iter().any(|v| stage_of(v) == Some(STAGE_CALIBRATE)) {
        |s| s == Some(STAGE_CALIBRATE)
    } else {
        |_| true
    };
    views.into_iter().filter(|v| keep(stage_of(v))).collect()
}
