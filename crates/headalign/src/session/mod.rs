//! Sessions on disk: everything a procedure captured, written as it is captured, and
//! read back for offline replay (`docs/formats.md#sessions`). This module is the one place the
//! format is defined.
//!
//! ## Layout (format `headalign-session/1`)
//!
//! ```text
//! DIR/
//!   session.json        what ran: format, created_utc, procedure, rotation_deg,
//!                       estimation_seed, image_size, head (free-form description), and
//!                       with robot stages `stages` (their names and settings); with
//!                       a lens model `lens` and `lens_terms` (absent: the pinhole)
//!   events.jsonl        every call the procedure made on the head, one JSON object a line:
//!                       {"op":"read","encoders":{..}} | {"op":"move","target":{..}}
//!                       | {"op":"capture","folder":"03-pan+"}, and on a vehicle
//!                       {"op":"drive","distance_m":0.1[,"odometry":{"distance_m":..,
//!                       "heading_deg":..}]} | {"op":"steer","encoder_deg":20.0}
//!                       | {"op":"read_steering","encoder_deg":0.0}
//!   NN-name/            one folder per capture, NN = capture index (00, 01, ...)
//!     left.png right.png   8-bit grey images (image mode)
//!     view.json         format, index, name, stage, encoders (degrees, read at capture
//!                       time), commanded (the last move target before the capture, or
//!                       null), time_s (seconds since the session started), unix_time_s,
//!                       image_size, in point mode `capture` (the tracked points), and on
//!                       a vehicle `vehicle` (drives_m since the previous capture, the
//!                       steering_deg, the drives' odometry if the vehicle reports it)
//!   report.json         the results (the command's `--json` object), written at the end;
//!                       on failure {"status": "failed", "error": "..."}
//!   figure6.png aligned.png   annotated images (image mode, after success)
//!   report.html         the results and the annotated images for a browser (image mode)
//!   observations.json   point mode: the views as an observation session
//!                       (`headalign-observations/1`, [`crate::observations`])
//! ```
//!
//! Encoder readings are degrees; `time_s` seconds. `view.json` is written after both
//! images (a folder with a `view.json` is complete), and before the procedure sees the
//! capture: a failure later leaves every captured view on disk. `stage` names the part of
//! the procedure (`verging`: the right camera verges to a common view, the rig is not
//! rigid; `rotation-probe`: the auto mode's probes; `verge-tilt`: the captures of the
//! verge/tilt procedure, from its initial view on; `pan`, `steering`, ...: the robot
//! stages; `calibrate`: the views of a rig-calibration session). View names are unique in
//! a session: planned captures are named by the plan, others `stage-N`, numbered over the
//! session (a stage that runs twice continues its numbers). Sessions written before names
//! were unique repeat a stage's names; the readers know such a view by its folder name
//! (`21-pan-1`). Older sessions (no `session.json`, `view.json` with only `name` and
//! `encoders`) still read with [`read_image_session`]; they have no events, so only `align
//! --images` (estimation from the views) works on them, not replay.
//!
//! ## Recording and replay
//!
//! [`RecordingHead`] wraps any head and writes every capture through a [`SessionWriter`]
//! before returning it, and logs every read and move. [`ReplayHead`] plays a session's
//! events back as a head: reads return the recorded readings, moves must equal the
//! recorded targets (within [`REPLAY_MOVE_TOLERANCE_DEG`]), captures return the recorded
//! images. Running the same (deterministic) procedure on it reproduces the recorded run:
//! the same images in the same order through the same code give the same numbers, bit for
//! bit (JSON numbers round-trip exactly: `serde_json` is built with `float_roundtrip`).
//! A procedure that asks for something else than the recording holds stops with an error
//! naming the event.
//!
//! [`read_image_session`] reads the view folders alone; [`track_session`] runs the image
//! front end over them, giving the views the estimation consumes. [`read_point_session`]
//! reads a point-mode session's tracked points instead; [`estimation_views`] picks the
//! views that estimate the head's rig from its rotations.
//!
//! Every bad input is an error naming the file and the problem: a missing or unreadable
//! image, a malformed `view.json` (wrong types, missing fields, an empty view name, a
//! repeated name whose folder name is taken too, non-finite encoder readings or readings
//! beyond +-3600 deg), left and right images of different sizes, a view whose size
//! differs from the first, a blank (textureless) image, a malformed event line.
//! [`parse_view_json`] and [`check_image`] are the pure parts of the reader (fuzzed
//! without files: `fuzz/`, targets `view_json` and `png_decode`).

use std::collections::{HashMap, HashSet};
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use headalign_platform::{
    Encoders, GrayImage, ImagingHead, Odometry, PlatformError, StereoCapture, StereoHead, StereoImages,
    Vehicle,
};
use serde::{Deserialize, Serialize};

use crate::AlignError;
use crate::observations::View;
use crate::tracking::{FrontEndOptions, Tracker};

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
    /// [`crate::verge_tilt::EstimationOptions::lens`]); absent for the pinhole, and in older
    /// sessions.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lens: Option<String>,
    /// The lens coefficients estimated with `lens` ([`crate::verge_tilt::EstimationOptions::lens_terms`]);
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

fn io_err(what: &str, path: &Path, e: impl std::fmt::Display) -> AlignError {
    AlignError::Output(format!("cannot {what} '{}': {e}", path.display()))
}

/// Write `bytes` to `path` through a temporary file and a rename (a crash never leaves a
/// half-written file under the final name).
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), AlignError> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes).map_err(|e| io_err("write", &tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| io_err("write", path, e))
}

fn to_json<T: Serialize>(v: &T) -> Result<String, AlignError> {
    serde_json::to_string_pretty(v)
        .map(|s| s + "\n")
        .map_err(|e| AlignError::Output(format!("cannot encode JSON: {e}")))
}

/// What a view folder records besides the capture itself.
#[derive(Debug, Clone, Copy)]
pub struct ViewLabel<'a> {
    /// The view's name (the folder is `NN-name`).
    pub name: &'a str,
    /// The procedure stage.
    pub stage: &'a str,
    /// The last commanded move before the capture.
    pub commanded: Option<Encoders>,
    /// A vehicle's actions since the previous capture.
    pub vehicle: Option<&'a VehicleActions>,
}

/// Writes a session as it happens: `session.json` at creation, one view folder per
/// capture, `events.jsonl` line by line, `report.json` at the end.
#[derive(Debug)]
pub struct SessionWriter {
    dir: PathBuf,
    start: Instant,
    views: usize,
    events: std::fs::File,
    /// Every view name written (names are unique in a session).
    names: HashSet<String>,
    /// The last number given to each prefix by [`SessionWriter::numbered_name`].
    numbers: HashMap<String, usize>,
}

impl SessionWriter {
    /// Start a session in `dir` (created if needed). Refuses a folder that already holds a
    /// session or view folders: sessions are never mixed or overwritten.
    pub fn create(dir: &Path, info: &SessionInfo) -> Result<Self, AlignError> {
        if dir.exists() {
            let entries = std::fs::read_dir(dir).map_err(|e| io_err("read", dir, e))?;
            let used = entries.filter_map(Result::ok).any(|e| {
                let p = e.path();
                p.file_name().is_some_and(|n| n == "session.json") || p.join("view.json").exists()
            });
            if used {
                return Err(AlignError::Output(format!(
                    "'{}' already holds a session; give a new folder",
                    dir.display()
                )));
            }
        }
        std::fs::create_dir_all(dir).map_err(|e| io_err("create", dir, e))?;
        write_atomic(&dir.join("session.json"), to_json(info)?.as_bytes())?;
        let path = dir.join("events.jsonl");
        let events = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(|e| io_err("create", &path, e))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            start: Instant::now(),
            views: 0,
            events,
            names: HashSet::new(),
            numbers: HashMap::new(),
        })
    }

    /// The next unused name `prefix-N` (N counts from 1 per prefix over the whole
    /// session: a stage that runs twice continues its numbering).
    pub fn numbered_name(&mut self, prefix: &str) -> String {
        let n = self.numbers.entry(prefix.to_string()).or_insert(0);
        loop {
            *n += 1;
            let name = format!("{prefix}-{n}");
            if !self.names.contains(&name) {
                return name;
            }
        }
    }

    /// `name`, or if a view of the session already has it, `name-2`, `name-3`, ...
    fn unique_name(&self, name: &str) -> String {
        let mut unique = name.to_string();
        let mut k = 1;
        while self.names.contains(&unique) {
            k += 1;
            unique = format!("{name}-{k}");
        }
        unique
    }

    /// The session folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Number of views written so far.
    pub fn views(&self) -> usize {
        self.views
    }

    /// Append one event line (written through at once).
    pub fn log(&mut self, event: &Event) -> Result<(), AlignError> {
        let line = serde_json::to_string(event)
            .map_err(|e| AlignError::Output(format!("cannot encode event: {e}")))?;
        let path = self.dir.join("events.jsonl");
        self.events.write_all(format!("{line}\n").as_bytes()).map_err(|e| io_err("write", &path, e))
    }

    /// Write one captured view (images and/or tracked points) as folder `NN-name`;
    /// returns the folder name. A name that a view of the session already has gets a
    /// suffix (`-2`, `-3`, ...): view names are unique in a session.
    pub fn write_view(
        &mut self,
        label: &ViewLabel<'_>,
        encoders: Encoders,
        images: Option<&StereoImages>,
        capture: Option<&StereoCapture>,
    ) -> Result<String, AlignError> {
        let ViewLabel { name, stage, commanded, vehicle } = *label;
        let name = self.unique_name(name.trim());
        let safe: String = name
            .chars()
            .map(|c| if c.is_ascii_alphanumeric() || "+-_.".contains(c) { c } else { '_' })
            .collect();
        let folder = format!("{:02}-{safe}", self.views);
        let sub = self.dir.join(&folder);
        std::fs::create_dir_all(&sub).map_err(|e| io_err("create", &sub, e))?;
        let mut image_size = capture.map(|c| c.image_size);
        if let Some(pair) = images {
            for (file, img) in [("left.png", &pair.left), ("right.png", &pair.right)] {
                let path = sub.join(file);
                img.save(&path).map_err(|e| io_err("write", &path, e))?;
            }
            image_size = Some(pair.image_size());
        }
        let meta = ViewMeta {
            format: Some(VIEW_FORMAT.to_string()),
            index: Some(self.views),
            name: name.clone(),
            stage: Some(stage.to_string()),
            encoders,
            commanded,
            time_s: Some(self.start.elapsed().as_secs_f64()),
            unix_time_s: SystemTime::now().duration_since(UNIX_EPOCH).ok().map(|d| d.as_secs_f64()),
            image_size,
            capture: capture.cloned(),
            vehicle: vehicle.cloned(),
        };
        write_atomic(&sub.join("view.json"), to_json(&meta)?.as_bytes())?;
        self.views += 1;
        self.names.insert(name);
        Ok(folder)
    }

    /// Write `report.json` (the results, or the failure).
    pub fn write_report(&self, report: &serde_json::Value) -> Result<PathBuf, AlignError> {
        let path = self.dir.join("report.json");
        write_atomic(&path, to_json(report)?.as_bytes())?;
        Ok(path)
    }
}

/// A head that records: every capture is written to the session before it is returned,
/// and every read and move is logged, so the run can be replayed ([`ReplayHead`]) and
/// nothing captured is lost when a later step fails. A failure to write is an error of
/// the capture (a run that cannot be recorded stops).
pub struct RecordingHead<'a, H> {
    head: &'a mut H,
    writer: SessionWriter,
    stage: String,
    commanded: Option<Encoders>,
    names: Vec<(String, Encoders)>,
    other_name: String,
    vehicle: Option<VehicleActions>,
    odometry: Option<Odometry>,
}

impl<'a, H> RecordingHead<'a, H> {
    /// Record `head`'s captures into `writer`'s session, in stage [`STAGE_VERGE_TILT`].
    pub fn new(head: &'a mut H, writer: SessionWriter) -> Self {
        Self {
            head,
            writer,
            stage: STAGE_VERGE_TILT.to_string(),
            commanded: None,
            names: Vec::new(),
            other_name: STAGE_VERGE_TILT.to_string(),
            vehicle: None,
            odometry: None,
        }
    }

    /// Start a stage; `plan` names the captures whose commanded target equals a planned
    /// one (as [`crate::procedure::capture_plan`] gives); others are named
    /// `other_name-1`, `other_name-2`, ... (numbered over the session: a stage that runs
    /// again continues the numbers, [`SessionWriter::numbered_name`]).
    pub fn set_stage(&mut self, stage: &str, plan: Vec<(String, Encoders)>, other_name: &str) {
        self.stage = stage.to_string();
        self.names = plan;
        self.other_name = other_name.to_string();
    }

    /// The session writer (folder, view count, report).
    pub fn writer(&self) -> &SessionWriter {
        &self.writer
    }

    /// The wrapped head.
    pub fn inner(&mut self) -> &mut H {
        self.head
    }

    /// End the recording; the writer can still write the report.
    pub fn into_writer(self) -> SessionWriter {
        self.writer
    }

    fn name(&mut self) -> String {
        let planned = self.commanded.and_then(|c| {
            self.names.iter().find(|(_, e)| {
                headalign_platform::Joint::ALL.iter().all(|&j| (e.get(j) - c.get(j)).abs() <= 1e-9)
            })
        });
        match planned {
            Some((n, _)) => n.clone(),
            None => self.writer.numbered_name(&self.other_name),
        }
    }

    fn record(
        &mut self,
        encoders: Encoders,
        images: Option<&StereoImages>,
        capture: Option<&StereoCapture>,
    ) -> Result<(), PlatformError> {
        let name = self.name();
        let fail =
            |e: AlignError, dir: &Path| PlatformError::Device(format!("session '{}': {e}", dir.display()));
        let folder = self
            .writer
            .write_view(
                &ViewLabel {
                    name: &name,
                    stage: &self.stage,
                    commanded: self.commanded,
                    vehicle: self.vehicle.as_ref(),
                },
                encoders,
                images,
                capture,
            )
            .map_err(|e| fail(e, &self.writer.dir))?;
        if let Some(v) = &mut self.vehicle {
            v.drives_m.clear();
            v.odometry.clear();
        }
        self.writer.log(&Event::Capture { folder }).map_err(|e| fail(e, &self.writer.dir))
    }

    fn log(&mut self, event: Event) -> Result<(), PlatformError> {
        self.writer
            .log(&event)
            .map_err(|e| PlatformError::Device(format!("session '{}': {e}", self.writer.dir.display())))
    }
}

impl<H: StereoHead> StereoHead for RecordingHead<'_, H> {
    fn image_size(&self) -> [u32; 2] {
        self.head.image_size()
    }

    fn read_encoders(&mut self) -> Result<Encoders, PlatformError> {
        let encoders = self.head.read_encoders()?;
        self.log(Event::Read { encoders })?;
        Ok(encoders)
    }

    fn move_to(&mut self, target: &Encoders) -> Result<(), PlatformError> {
        self.head.move_to(target)?;
        self.commanded = Some(*target);
        self.log(Event::Move { target: *target })
    }

    fn capture(&mut self) -> Result<StereoCapture, PlatformError> {
        let capture = self.head.capture()?;
        self.record(capture.encoders, None, Some(&capture))?;
        Ok(capture)
    }
}

/// A vehicle's calls are logged (`drive`, `steer`, `read_steering` events) and the next
/// capture's `view.json` records the drives since the previous one and the steering.
impl<H: Vehicle> Vehicle for RecordingHead<'_, H> {
    fn drive(&mut self, distance_m: f64) -> Result<(), PlatformError> {
        self.head.drive(distance_m)?;
        let odometry = self.head.last_odometry();
        let actions = self.vehicle.get_or_insert_with(VehicleActions::default);
        actions.drives_m.push(distance_m);
        actions.odometry.extend(odometry);
        self.odometry = odometry;
        self.log(Event::Drive { distance_m, odometry })
    }

    fn steer_to(&mut self, encoder_deg: f64) -> Result<(), PlatformError> {
        self.head.steer_to(encoder_deg)?;
        self.vehicle.get_or_insert_with(VehicleActions::default).steering_deg = Some(encoder_deg);
        self.log(Event::Steer { encoder_deg })
    }

    fn read_steering(&mut self) -> Result<f64, PlatformError> {
        let encoder_deg = self.head.read_steering()?;
        self.vehicle.get_or_insert_with(VehicleActions::default).steering_deg = Some(encoder_deg);
        self.log(Event::ReadSteering { encoder_deg })?;
        Ok(encoder_deg)
    }

    fn last_odometry(&self) -> Option<Odometry> {
        self.odometry
    }
}

impl<H: ImagingHead> ImagingHead for RecordingHead<'_, H> {
    fn capture_images(&mut self) -> Result<StereoImages, PlatformError> {
        let images = self.head.capture_images()?;
        self.record(images.encoders, Some(&images), None)?;
        Ok(images)
    }
}

/// Read a session's `session.json`.
pub fn read_session_info(dir: &Path) -> Result<SessionInfo, AlignError> {
    let path = dir.join("session.json");
    let text = std::fs::read_to_string(&path).map_err(|e| {
        AlignError::Images(format!(
            "cannot read '{}': {e} (is '{}' a session folder?)",
            path.display(),
            dir.display()
        ))
    })?;
    let info: SessionInfo =
        serde_json::from_str(&text).map_err(|e| AlignError::Images(format!("'{}': {e}", path.display())))?;
    if info.format != SESSION_FORMAT {
        return Err(AlignError::Images(format!(
            "'{}': unsupported format '{}', expected '{SESSION_FORMAT}'",
            path.display(),
            info.format
        )));
    }
    if !(info.rotation_deg.is_finite() && info.rotation_deg > 0.0 && info.rotation_deg < 90.0) {
        return Err(AlignError::Images(format!(
            "'{}': rotation_deg must be in (0, 90), got {}",
            path.display(),
            info.rotation_deg
        )));
    }
    let [w, h] = info.image_size;
    if w == 0 || h == 0 || w > 100_000 || h > 100_000 {
        return Err(AlignError::Images(format!(
            "'{}': image_size {w} x {h} is not a valid image size",
            path.display()
        )));
    }
    Ok(info)
}

/// Read and check one `view.json`.
pub fn read_view_meta(path: &Path) -> Result<ViewMeta, AlignError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| AlignError::Images(format!("cannot read '{}': {e}", path.display())))?;
    parse_view_json(&text, &path.display().to_string())
}

/// A recorded session played back as a head (see the module documentation).
#[derive(Debug)]
pub struct ReplayHead {
    dir: PathBuf,
    image_size: [u32; 2],
    events: Vec<Event>,
    next: usize,
    position: Option<Encoders>,
    odometry: Option<Odometry>,
}

impl ReplayHead {
    /// Open the session in `dir`: `session.json` and `events.jsonl` (the views are read
    /// when the procedure captures them).
    pub fn open(dir: &Path) -> Result<Self, AlignError> {
        let info = read_session_info(dir)?;
        let path = dir.join("events.jsonl");
        let text = std::fs::read_to_string(&path)
            .map_err(|e| AlignError::Images(format!("cannot read '{}': {e}", path.display())))?;
        let mut events = Vec::new();
        for (i, line) in text.lines().enumerate() {
            if line.trim().is_empty() {
                continue;
            }
            let event: Event = serde_json::from_str(line)
                .map_err(|e| AlignError::Images(format!("'{}' line {}: {e}", path.display(), i + 1)))?;
            let finite = match &event {
                Event::Read { encoders } => encoders.is_finite(),
                Event::Move { target } => target.is_finite(),
                Event::Capture { folder } => {
                    !folder.is_empty() && !folder.contains(['/', '\\']) && folder != ".." && folder != "."
                }
                Event::Drive { distance_m, odometry } => {
                    distance_m.is_finite() && odometry.as_ref().is_none_or(Odometry::is_finite)
                }
                Event::Steer { encoder_deg: v } | Event::ReadSteering { encoder_deg: v } => v.is_finite(),
            };
            if !finite {
                return Err(AlignError::Images(format!(
                    "'{}' line {}: non-finite readings or a folder outside the session",
                    path.display(),
                    i + 1
                )));
            }
            events.push(event);
        }
        Ok(Self {
            dir: dir.to_path_buf(),
            image_size: info.image_size,
            events,
            next: 0,
            position: None,
            odometry: None,
        })
    }

    /// Events not played yet.
    pub fn remaining(&self) -> usize {
        self.events.len() - self.next
    }

    fn next_event(&mut self, asked: &str) -> Result<Event, PlatformError> {
        let Some(event) = self.events.get(self.next).cloned() else {
            return Err(PlatformError::Device(format!(
                "replay: the procedure asks to {asked} but the recording of '{}' ends after {} events (the recorded run stopped there)",
                self.dir.display(),
                self.events.len()
            )));
        };
        self.next += 1;
        Ok(event)
    }

    fn diverged(&self, asked: &str, event: &Event) -> PlatformError {
        PlatformError::Device(format!(
            "replay diverged: the procedure asks to {asked} but event {} of '{}' is {}",
            self.next,
            self.dir.join("events.jsonl").display(),
            serde_json::to_string(event).unwrap_or_default()
        ))
    }

    fn capture_folder(&mut self) -> Result<(PathBuf, ViewMeta), PlatformError> {
        let event = self.next_event("capture")?;
        let Event::Capture { folder } = &event else { return Err(self.diverged("capture", &event)) };
        let sub = self.dir.join(folder);
        let meta =
            read_view_meta(&sub.join("view.json")).map_err(|e| PlatformError::Device(e.to_string()))?;
        Ok((sub, meta))
    }
}

impl StereoHead for ReplayHead {
    fn image_size(&self) -> [u32; 2] {
        self.image_size
    }

    fn read_encoders(&mut self) -> Result<Encoders, PlatformError> {
        let event = self.next_event("read the encoders")?;
        match event {
            Event::Read { encoders } => Ok(encoders),
            other => Err(self.diverged("read the encoders", &other)),
        }
    }

    fn move_to(&mut self, target: &Encoders) -> Result<(), PlatformError> {
        let asked = format!("move to {}", serde_json::to_string(target).unwrap_or_default());
        let event = self.next_event(&asked)?;
        match event {
            Event::Move { target: recorded }
                if headalign_platform::Joint::ALL
                    .iter()
                    .all(|&j| (recorded.get(j) - target.get(j)).abs() <= REPLAY_MOVE_TOLERANCE_DEG) =>
            {
                self.position = Some(recorded);
                Ok(())
            }
            other => Err(self.diverged(&asked, &other)),
        }
    }

    fn capture(&mut self) -> Result<StereoCapture, PlatformError> {
        let (sub, meta) = self.capture_folder()?;
        meta.capture.ok_or_else(|| {
            PlatformError::Device(format!(
                "'{}' holds no tracked points (an image session: replay it in image mode)",
                sub.join("view.json").display()
            ))
        })
    }
}

/// Replaying a vehicle: drives and steering targets must equal the recorded ones (within
/// [`REPLAY_MOVE_TOLERANCE_DEG`], metres or degrees), steering reads return the recorded
/// readings.
impl Vehicle for ReplayHead {
    fn drive(&mut self, distance_m: f64) -> Result<(), PlatformError> {
        let asked = format!("drive {distance_m} m");
        match self.next_event(&asked)? {
            Event::Drive { distance_m: d, odometry }
                if (d - distance_m).abs() <= REPLAY_MOVE_TOLERANCE_DEG =>
            {
                self.odometry = odometry;
                Ok(())
            }
            other => Err(self.diverged(&asked, &other)),
        }
    }

    fn steer_to(&mut self, encoder_deg: f64) -> Result<(), PlatformError> {
        let asked = format!("steer to {encoder_deg} deg");
        match self.next_event(&asked)? {
            Event::Steer { encoder_deg: e } if (e - encoder_deg).abs() <= REPLAY_MOVE_TOLERANCE_DEG => Ok(()),
            other => Err(self.diverged(&asked, &other)),
        }
    }

    fn read_steering(&mut self) -> Result<f64, PlatformError> {
        match self.next_event("read the steering")? {
            Event::ReadSteering { encoder_deg } => Ok(encoder_deg),
            other => Err(self.diverged("read the steering", &other)),
        }
    }

    fn last_odometry(&self) -> Option<Odometry> {
        self.odometry
    }
}

impl ImagingHead for ReplayHead {
    fn capture_images(&mut self) -> Result<StereoImages, PlatformError> {
        let (sub, meta) = self.capture_folder()?;
        let view = load_view(&sub, meta, None).map_err(|e| PlatformError::Device(e.to_string()))?;
        Ok(view.images)
    }
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

fn load(path: &Path) -> Result<GrayImage, AlignError> {
    let img = GrayImage::load(path).map_err(|e| AlignError::Images(e.to_string()))?;
    check_image(&img, &path.display().to_string())?;
    Ok(img)
}

/// Load the images of one view folder, checking them (and against `first_size`).
fn load_view(
    folder: &Path,
    meta: ViewMeta,
    first_size: Option<[u32; 2]>,
) -> Result<RecordedView, AlignError> {
    let (lp, rp) = (folder.join("left.png"), folder.join("right.png"));
    let (left, right) = (load(&lp)?, load(&rp)?);
    if left.size() != right.size() {
        return Err(AlignError::Images(format!(
            "'{}' is {}x{} but '{}' is {}x{}: left and right images must have the same size",
            lp.display(),
            left.width(),
            left.height(),
            rp.display(),
            right.width(),
            right.height()
        )));
    }
    if let Some([w, h]) = first_size
        && [w, h] != left.size()
    {
        return Err(AlignError::Images(format!(
            "'{}' is {}x{} but the first view's images are {w}x{h}",
            lp.display(),
            left.width(),
            left.height(),
        )));
    }
    let images = StereoImages::new(meta.encoders, left, right)?;
    Ok(RecordedView { name: meta.name, stage: meta.stage, folder: folder.to_path_buf(), images })
}

/// The view folders of `dir` (those with a `view.json`), sorted, each with its
/// `view.json`; view names made unique (a name an earlier view already has is replaced by
/// the folder's name: sessions written before names were unique repeat the names of a
/// stage that ran twice).
fn read_view_folders(dir: &Path) -> Result<Vec<(PathBuf, ViewMeta)>, AlignError> {
    let entries = std::fs::read_dir(dir)
        .map_err(|e| AlignError::Images(format!("cannot read session folder '{}': {e}", dir.display())))?;
    let mut folders: Vec<PathBuf> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.is_dir() && p.join("view.json").exists())
        .collect();
    folders.sort();
    if folders.is_empty() {
        return Err(AlignError::Images(format!(
            "'{}' holds no view folders (NN-name/ with left.png, right.png, view.json)",
            dir.display()
        )));
    }
    let mut out: Vec<(PathBuf, ViewMeta)> = Vec::new();
    for folder in folders {
        let meta_path = folder.join("view.json");
        let mut meta = read_view_meta(&meta_path)?;
        if out.iter().any(|(_, m)| m.name == meta.name) {
            let folder_name = folder.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
            if let Some((other, _)) = out.iter().find(|(_, m)| m.name == folder_name) {
                return Err(AlignError::Images(format!(
                    "'{}': view name '{}' is also the name of '{}', and so is its folder name",
                    meta_path.display(),
                    meta.name,
                    other.display()
                )));
            }
            meta.name = folder_name;
        }
        out.push((folder, meta));
    }
    Ok(out)
}

/// Read every view folder of `dir` in order (all stages; see
/// [`RecordedView::is_verge_tilt`]). A view whose name an earlier view already has is
/// known by its folder name (`21-pan-1`).
pub fn read_image_session(dir: &Path) -> Result<Vec<RecordedView>, AlignError> {
    let mut views: Vec<RecordedView> = Vec::new();
    for (folder, meta) in read_view_folders(dir)? {
        let first = views.first().map(|v| v.images.image_size());
        views.push(load_view(&folder, meta, first)?);
    }
    Ok(views)
}

/// True if `dir` is a point-mode session: its first view folder's `view.json` holds the
/// tracked points (`capture`) and the folder no `left.png`.
pub fn is_point_session(dir: &Path) -> bool {
    read_view_folders(dir)
        .ok()
        .and_then(|f| f.into_iter().next())
        .is_some_and(|(folder, meta)| meta.capture.is_some() && !folder.join("left.png").exists())
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

/// Read every view of a point-mode session (`view.json` with `capture`), in order; an
/// error names a view without tracked points.
pub fn read_point_session(dir: &Path) -> Result<Vec<RecordedPoints>, AlignError> {
    read_view_folders(dir)?
        .into_iter()
        .map(|(folder, meta)| {
            let Some(capture) = meta.capture else {
                return Err(AlignError::Images(format!(
                    "'{}' holds no tracked points (`capture`): not a point-mode session",
                    folder.join("view.json").display()
                )));
            };
            let view = View { name: meta.name, capture };
            Ok(RecordedPoints { stage: meta.stage, folder, view })
        })
        .collect()
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

/// Run the image front end over recorded views (the first is the tracking reference).
pub fn track_session(views: &[RecordedView], options: &FrontEndOptions) -> Result<Vec<View>, AlignError> {
    track_session_reporting(views, options).map(|(v, _)| v)
}

/// [`track_session`] with the front end's report of each view (its localisation noise is
/// keyed by the views' names: [`crate::verge_tilt::model_fit`]).
pub fn track_session_reporting(
    views: &[RecordedView],
    options: &FrontEndOptions,
) -> Result<(Vec<View>, Vec<crate::tracking::ViewTracking>), AlignError> {
    let mut tracker = Tracker::new(options.clone())?;
    views
        .iter()
        .map(|v| {
            let (capture, report) = tracker.track(&v.images, &v.name).map_err(|e| {
                AlignError::Images(format!("view '{}' ({}): {e}", v.name, v.folder.display()))
            })?;
            Ok((View { name: v.name.clone(), capture }, report))
        })
        .collect::<Result<Vec<_>, AlignError>>()
        .map(|pairs| pairs.into_iter().unzip())
}

#[cfg(test)]
mod tests;
