//! Errors of the alignment procedures: every bad input or failed estimate is one of
//! these, with a one-line message that names the problem (the CLI prints it as is).

use headalign_geometry::GeometryError;
use headalign_platform::PlatformError;
use thiserror::Error;

/// What can go wrong when estimating or aligning.
#[derive(Debug, Error)]
pub enum AlignError {
    /// A malformed or inconsistent observation session.
    #[error("{0}")]
    Observations(String),
    /// Not enough tracked points for a step.
    #[error("too few tracks {what}: need at least {needed}, have {got}")]
    TooFewTracks {
        /// Which step.
        what: String,
        /// Minimum.
        needed: usize,
        /// Available.
        got: usize,
    },
    /// A view whose motion is not a rotation of the head.
    #[error("view '{view}' is not a rotation of the head: {why}")]
    NotARotation {
        /// The view's name.
        view: String,
        /// Why.
        why: String,
    },
    /// Two rotations about the same joint cannot determine the plane at infinity.
    #[error(
        "views '{first}' and '{second}' both rotate only the {joint} joint: two rotations about the same axis cannot calibrate the head; rotate about a second joint"
    )]
    SameAxis {
        /// First view.
        first: String,
        /// Second view.
        second: String,
        /// The joint.
        joint: String,
    },
    /// The views do not contain the motions the procedure needs.
    #[error("missing motion: {0}")]
    MissingMotion(String),
    /// A geometric estimation step failed.
    #[error("{step}: {cause}")]
    Geometry {
        /// The step that failed.
        step: String,
        /// The cause (its message is part of this error's, so it is not chained again).
        cause: GeometryError,
    },
    /// The platform (head) failed.
    #[error("head: {0}")]
    Platform(#[from] PlatformError),
    /// The drive was too short for the scene depth: the image flow is too small to
    /// locate the epipole.
    #[error(
        "drive too short for the scene depth: median flow {median_flow_px:.2} px, need at least {min_flow_px} px; drive farther or face a nearer scene"
    )]
    DriveTooShort {
        /// Measured median flow, pixels.
        median_flow_px: f64,
        /// Required median flow, pixels.
        min_flow_px: f64,
    },
    /// A steering drive turned too little to locate its axis.
    #[error(
        "turn too small to locate its axis: {angle_deg:.3} deg, need at least {min_deg} deg; steer more or drive farther"
    )]
    TurnTooSmall {
        /// Measured turn, degrees.
        angle_deg: f64,
        /// Required turn, degrees.
        min_deg: f64,
    },
    /// The one-motion stage's drive moved the rig too little to give a direction.
    #[error(
        "one motion: no drive: pan-axis displacement {displacement:.4} baselines, need at least {min}; drive farther"
    )]
    NoDrive {
        /// Length of the displacement left after removing the tilt, stereo baselines.
        displacement: f64,
        /// Required length, stereo baselines.
        min: f64,
    },
    /// The one-motion stage's motion rotated too little to locate the elevation axis.
    #[error("one motion: no tilt: rotation {angle_deg:.3} deg, need at least {min_deg} deg; tilt more")]
    NoTilt {
        /// Measured rotation, degrees.
        angle_deg: f64,
        /// Required rotation, degrees.
        min_deg: f64,
    },
    /// The robot's motion was not planar (screw axis not parallel to the pan axis, or
    /// translation along it).
    #[error("motion not planar: {0}")]
    NotPlanar(String),
    /// The stereo rig predicted at a robot stage's readings (calibration and vergence
    /// axes) does not fit that stage's stereo captures, even with its relative pose
    /// re-fitted to them.
    #[error(
        "the calibration or the vergence axes do not hold at pan {:.2}, elevation {:.2}, verge {:.2} / {:.2} deg: the predicted rig misfits the stereo pairs by {misfit_px:.2} px (median; at most {bound_px:.2} expected, {refit_px:.2} re-fitted); run the verge/tilt stage again",
        readings.pan, readings.elevation, readings.verge_left, readings.verge_right
    )]
    RigMisfit {
        /// The readings the rig was predicted at.
        readings: headalign_platform::Encoders,
        /// Median misfit of the predicted rig, pixels ([`crate::robot::RigCheck`]).
        misfit_px: f64,
        /// The largest accepted, pixels.
        bound_px: f64,
        /// Median misfit after re-fitting the relative pose, pixels (infinite: the
        /// re-fit failed).
        refit_px: f64,
    },
    /// The steering drives leave the steering zero undetermined: its standard deviation
    /// exceeds [`crate::robot::SteeringOptions::max_sigma_zero_deg`]. The wheel is not
    /// commanded to it.
    #[error(
        "steering zero undetermined: {zero_deg:+.2} +- {sigma_deg:.2} deg from {drives} drives{}, above the {max_sigma_deg} deg accepted; drive farther, steer wider or add steering settings",
        if dropped_turns.is_empty() { String::new() } else { format!(" (drives {dropped_turns:?} left out as not planar)") }
    )]
    SteeringUndetermined {
        /// The steering zero found, degrees (encoder reading).
        zero_deg: f64,
        /// Its standard deviation, degrees.
        sigma_deg: f64,
        /// The largest accepted, degrees.
        max_sigma_deg: f64,
        /// Drives the solution used.
        drives: usize,
        /// Indices of drives left out (`SteeringOutcome::dropped_turns`).
        dropped_turns: Vec<usize>,
    },
    /// A move to the aligned readings far outside the range the procedure plans
    /// ([`crate::procedure::check_move`]), refused before it is sent.
    #[error(
        "refused to move the {joint} to {target_deg:.1} deg (a turn of {turn_deg:+.1}, beyond the {max_deg} deg planned): the estimate does not hold (lens model? try --lens auto) or the head starts far from aligned"
    )]
    ImplausibleMove {
        /// The joint.
        joint: String,
        /// The aligned reading, degrees.
        target_deg: f64,
        /// Its turn from the reference view's reading, degrees.
        turn_deg: f64,
        /// The largest turn accepted, degrees.
        max_deg: f64,
    },
    /// Invalid options.
    #[error("invalid option: {0}")]
    InvalidOption(String),
    /// Bad or unusable images.
    #[error("images: {0}")]
    Images(String),
    /// An output file could not be produced.
    #[error("output: {0}")]
    Output(String),
    /// A recording (ROS 2 bag, EuRoC folder) that cannot be read as asked: a missing
    /// topic, an unsupported encoding, images with no partner, a malformed file.
    #[error("recording: {0}")]
    Recording(String),
    /// A named step of a procedure failed: the step's name (its message), the failure as
    /// the source (printed after it by a caller that prints the chain, `step: cause`).
    #[error("{step}")]
    InStep {
        /// The step, e.g. `verging`.
        step: String,
        /// What failed in it.
        #[source]
        source: Box<AlignError>,
    },
}

impl AlignError {
    /// This error as the failure of the step `step` ([`AlignError::InStep`]).
    pub fn in_step(self, step: &str) -> Self {
        AlignError::InStep { step: step.to_string(), source: Box::new(self) }
    }
}

/// Attach the name of a step to geometry errors.
pub(crate) trait StepContext<T> {
    fn step(self, step: &str) -> Result<T, AlignError>;
}

impl<T> StepContext<T> for Result<T, GeometryError> {
    fn step(self, step: &str) -> Result<T, AlignError> {
        self.map_err(|cause| AlignError::Geometry { step: step.to_string(), cause })
    }
}
