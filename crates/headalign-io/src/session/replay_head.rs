//! [`ReplayHead`]: a recorded session played back as a head. Reads return the recorded
//! readings, moves, drives and steering targets must equal the recorded ones (within
//! [`REPLAY_MOVE_TOLERANCE_DEG`]), captures return the recorded images; a procedure that
//! asks for something else than the recording holds stops with an error naming the event.
use std::path::{Path, PathBuf};

use headalign::AlignError;
use headalign_platform::{
    Encoders, ImagingHead, Odometry, PlatformError, StereoCapture, StereoHead, StereoImages, Vehicle,
};

use super::format::*;
use super::reader::{load_view, read_session_info, read_view_meta};
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
