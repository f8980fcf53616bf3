//! Writing a session as it happens ([`SessionWriter`]): `session.json` at creation, a
//! view folder per capture (`view.json` after both images: a folder with a `view.json` is
//! complete), `events.jsonl` line by line, `report.json` at the end. Files are written
//! through a temporary file and a rename.
use std::collections::{HashMap, HashSet};
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use headalign::AlignError;
use headalign_platform::{Encoders, StereoCapture, StereoImages};
use serde::Serialize;

use super::format::*;
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
    pub(super) dir: PathBuf,
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
