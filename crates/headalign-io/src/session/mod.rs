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
//!
//! Files: `format` (the types, `view.json` parsing, the blank-image check, the choice of
//! views), `reader` (reading sessions back), `writer` ([`SessionWriter`]),
//! `recording_head` ([`RecordingHead`]), `replay_head` ([`ReplayHead`]); everything is
//! re-exported here.

mod format;
mod reader;
mod recording_head;
mod replay_head;
mod writer;

pub use format::*;
pub use reader::*;
pub use recording_head::RecordingHead;
pub use replay_head::ReplayHead;
pub use writer::{SessionWriter, ViewLabel};

#[cfg(test)]
mod tests;
