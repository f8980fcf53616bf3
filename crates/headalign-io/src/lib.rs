//! # headalign-io
//!
//! The formats and devices of headalign: everything that reads or writes a file, or talks
//! to a device, around the procedures of the `headalign` crate (which reads and writes no
//! file format and depends on no container or compression crate). Errors are one line
//! naming the file and the problem: the library's [`headalign::AlignError`] for the formats
//! its procedures reach, [`FileError`] for the folder reader and `alignment.json`.
//!
//! - [`session`]: sessions on disk (`headalign-session/1`): the format, the writer, the
//!   recording head and the replay head.
//! - [`recordings`]: ROS 2 bags (MCAP) and EuRoC folders read as sessions.
//! - [`observations`]: observation files (`headalign-observations/1`, bring your own
//!   correspondences).
//! - [`export`]: calibration files (JSON, OpenCV YAML, ROS `camera_info`, Kalibr
//!   `camchain.yaml`) of the library's [`headalign::calibration::StereoCalibration`].
//! - [`import`]: calibration files read back (headalign's JSON, OpenCV stereo YAML,
//!   Kalibr `camchain.yaml`), for `check`.
//! - [`process_head`]: a head behind a driver process (JSON lines, `docs/head-protocol.md`).
//! - [`alignment_file`]: the file `alignment.json` (`headalign-alignment/2`).
//! - [`folder`]: a folder of stereo views (an image session or `left*`/`right*` pairs),
//!   read by one set of rules for the command line and the examples.
//!
//! The formats are specified in `docs/formats.md`. The example `calibrate_folder`
//! self-calibrates a rig from a folder of stereo images
//! (`cargo run --release -p headalign-io --example calibrate_folder [-- DIR]`).

pub mod alignment_file;
pub mod error;
pub mod export;
pub mod folder;
pub mod import;
pub mod observations;
pub mod process_head;
pub mod recordings;
pub mod session;

pub use error::FileError;
