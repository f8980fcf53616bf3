//! [`RecordingHead`]: any head, recorded: every capture is written through a
//! [`SessionWriter`] before it is returned, every read, move, drive and steer is logged in
//! `events.jsonl` (session module documentation).
use std::path::Path;

use headalign::AlignError;
use headalign_platform::{
    Encoders, ImagingHead, Odometry, PlatformError, StereoCapture, StereoHead, StereoImages, Vehicle,
};

use super::format::*;
use super::writer::{SessionWriter, ViewLabel};
/// A head that records: every capture is written to the session before it is returned,
/// and every read and move is logged, so the run can be replayed ([`ReplayHead`](super::ReplayHead)) and
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
    /// one (as [`headalign::procedure::capture_plan`] gives); others are named
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
