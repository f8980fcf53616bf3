//! The alignment of a recorded session without moving the head (what `headalign align`
//! computes from an observation or image session): the rig calibration from the views in
//! which no vergence joint moved, the vergence axes from the first view in which one did
//! (nominal axes if none), the aligned readings and their sigmas, and the fixation
//! points' sigmas ([`fixation_sigmas`]: not the readings', whose error is the fixation
//! point's less the principal point's).
//!
//! Degrees of freedom: those of [`estimate_rig`] (the rig bundle adjustment), then per
//! camera one vergence axis (a pose resected from the vergence view, screw axis against
//! the modelled pan/elevation chain; 2 dof of direction each) and the three aligned
//! readings ([`solve_alignment`]). Units: degrees for readings and sigmas, pixels for the
//! adjustment's residuals.
//!
//! Paper section 3.2 steps 1-7 without the head's moves: the procedure
//! ([`super::VergeTiltRun`]) additionally moves to the aligned readings and checks them by
//! vision; a session has no such check.
//!
//! Pitfalls: with no vergence view the vergence axes are nominal (the camera's down
//! direction made perpendicular to the elevation axis: a positive vergence turns the
//! camera right, [`crate::alignment::solve_alignment`]); their sign and the cameras'
//! mounting on them are assumptions the data cannot check, and the sigmas
//! ([`alignment_sigmas`]) hold those axes fixed. The sigmas include the reference view's
//! reading noise (the estimation's angle prior sigma per joint, as the procedure adds it:
//! the aligned readings are that view's readings plus the solved turns).
//!
//! [`align_session_detecting`] first asks whether the scene is planar or far
//! ([`crate::facing_plane::detect_scene`] on the reference and rig views, as
//! [`super::VergeTiltRun::run_detecting`] does) and then runs the planar route
//! ([`crate::facing_plane::estimate_planar`] on the reference, rig and first vergence views: the
//! views the procedure estimates from) instead; what a plane leaves undetermined is named
//! in its [`crate::facing_plane::PlanarCalibration::undetermined`].

use headalign_platform::{Encoders, Joint};

use super::{AlignmentSigmas, FixationSigmas, alignment_sigmas, fixation_sigmas, pinhole_capture};
use crate::alignment::{
    AlignmentSolution, VergeAxes, head_motion, measure_cameras, solve_alignment, verge_axes_from_motion,
};
use crate::error::AlignError;
use crate::facing_plane::{PlanarCalibration, SceneCheck, SceneKind, detect_scene};
use crate::observations::View;
use crate::rig::image_noise::MeasuredVariances;
use crate::verge_tilt::{
    EstimationOptions, ModelFit, RigCalibration, ViewRole, classify_views, estimate_rig, model_fit,
    observation_view_names,
};

/// What [`align_session`] estimated.
#[derive(Debug, Clone)]
pub struct SessionAlignment {
    /// The rig calibration from the views in which no vergence joint moved.
    pub calibration: RigCalibration,
    /// Readings of the first view: the reference of the alignment.
    pub reference: Encoders,
    /// Vergence axes measured from the first vergence view (`None` each: nominal).
    pub verge_axes: VergeAxes,
    /// Index into the session's views of the view the vergence axes came from, if any.
    pub verge_view: Option<usize>,
    /// The aligned readings.
    pub solution: AlignmentSolution,
    /// Their 1-sigma uncertainties (module docs: what they include and hold fixed).
    pub sigmas: AlignmentSigmas,
    /// The fixation points' 1-sigma uncertainties ([`fixation_sigmas`]; not the readings').
    pub fixation_sigmas: FixationSigmas,
}

/// Align a recorded session (module docs): `views[0]` is the reference.
///
/// Errors: those of [`classify_views`] (too few or inconsistent views), [`estimate_rig`],
/// the vergence view's resection and [`solve_alignment`].
pub fn align_session(views: &[View], estimation: &EstimationOptions) -> Result<SessionAlignment, AlignError> {
    let roles = classify_views(views)?;
    let rig = rig_views(views, &roles);
    let calibration = estimate_rig(&rig, estimation)?;
    let state = &calibration.bundle.state;
    let reference = views.first().map(|v| v.capture.encoders).unwrap_or_default();
    let verge_view = roles.iter().position(|r| matches!(r, ViewRole::Verge));
    let mut verge_axes = VergeAxes::default();
    if let Some(v) = verge_view.and_then(|i| views.get(i)) {
        let d = |j: Joint| (v.capture.encoders.get(j) - reference.get(j)).to_radians();
        let chain = head_motion(state, d(Joint::Pan), d(Joint::Elevation))
            .ok_or_else(|| AlignError::MissingMotion("pan and elevation axes of the head model".into()))?;
        let capture = pinhole_capture(&calibration, &v.capture);
        let measured =
            measure_cameras(&calibration, &capture, &chain, &(chain * state.right_from_left.inverse()))?;
        verge_axes = verge_axes_from_motion(state, &reference, &v.capture.encoders, &measured)?;
    }
    let solution = solve_alignment(state, &verge_axes, &reference)?;
    let reading_sigma_deg = estimation.bundle.angle_prior_sigma.map_or(0.0, f64::to_degrees);
    let sigmas =
        alignment_sigmas(&calibration, &verge_axes, &reference)?.with_reading_noise(reading_sigma_deg);
    let fixation_sigmas = fixation_sigmas(&calibration);
    Ok(SessionAlignment { calibration, reference, verge_axes, verge_view, solution, sigmas, fixation_sigmas })
}

/// What [`align_session_detecting`] estimated: the general route with the detection's
/// numbers, or the planar route.
#[derive(Debug, Clone)]
pub enum SessionRoute {
    /// The scene had depth: [`align_session`]'s result and the detection.
    General(Box<SessionAlignment>, SceneCheck),
    /// The scene was planar or far.
    Planar(Box<PlanarSessionAlignment>),
}

/// The planar route on a recorded session.
#[derive(Debug, Clone)]
pub struct PlanarSessionAlignment {
    /// Each camera's planar calibration, the scene verdict and what is undetermined.
    pub calibration: PlanarCalibration,
    /// Readings of the first view: the reference of the alignment.
    pub reference: Encoders,
    /// The aligned readings (each camera from its own axes).
    pub solution: AlignmentSolution,
    /// Their 1-sigma uncertainties (both cameras' covariances and the reading noise).
    pub sigmas: AlignmentSigmas,
}

/// The model-fit checks of a session's estimate `calib` ([`crate::verge_tilt::model_fit`])
/// on its rig views (the reference and the views where no vergence joint moved), each
/// keyed by its name in the front end's noise `measured` (image sessions: `align --images`).
pub fn session_model_fit(calib: &RigCalibration, views: &[View], measured: &MeasuredVariances) -> ModelFit {
    let roles = classify_views(views).unwrap_or_default();
    let rig: Vec<(String, String)> = views
        .iter()
        .zip(&roles)
        .filter(|(_, r)| !matches!(r, ViewRole::Verge))
        .map(|(v, _)| (v.name.clone(), v.name.clone()))
        .collect();
    let keys = observation_view_names(calib, &rig);
    let size = views.first().map_or([0, 0], |v| v.capture.image_size);
    model_fit(calib, &keys, measured, size)
}

/// The views that move the whole rig (every view but the vergence one), in order.
fn rig_views(views: &[View], roles: &[ViewRole]) -> Vec<View> {
    views.iter().zip(roles).filter(|(_, r)| !matches!(r, ViewRole::Verge)).map(|(v, _)| v.clone()).collect()
}

/// Align a recorded session, detecting a planar or far scene first (module docs).
///
/// Errors: those of [`classify_views`], then of [`align_session`] or of the planar route
/// ([`crate::facing_plane::estimate_planar`], [`crate::alignment::solve_alignment_axes`]).
pub fn align_session_detecting(
    views: &[View],
    estimation: &EstimationOptions,
) -> Result<SessionRoute, AlignError> {
    let roles = classify_views(views)?;
    let rig = rig_views(views, &roles);
    let scene = detect_scene(&rig, &estimation.fundamental);
    if scene.kind == SceneKind::General {
        return align_session(views, estimation).map(|a| SessionRoute::General(Box::new(a), scene));
    }
    let mut used = rig;
    if let Some(v) = roles.iter().position(|r| matches!(r, ViewRole::Verge)).and_then(|i| views.get(i)) {
        used.push(v.clone());
    }
    let (calibration, solution, sigmas) = super::planar_alignment(&used, scene, estimation)?;
    let reference = calibration.reference_encoders;
    Ok(SessionRoute::Planar(Box::new(PlanarSessionAlignment { calibration, reference, solution, sigmas })))
}
