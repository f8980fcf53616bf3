//! The procedure's choice of its calibration rotations when the scene allows
//! ([`super`] module docs, "rotation size"): the single-joint and diagonal view offsets,
//! the pure choice logic ([`choose_rotations`]) and the probing of a head for it
//! ([`resolve_rotation`]).
//!
//! What is measured: per probed view, how many of the reference view's stereo tracks
//! (seen by both cameras) it still sees in both cameras, against `min_tracks` and
//! `min_overlap_fraction` of them. Candidates in degrees, largest first (10, 6, 3 by
//! default); each joint turns at most the chosen size. No estimation, no degrees of
//! freedom.
//!
//! Pitfalls: the overlap is counted by track id, which in image mode means the tracker's
//! matches: a tracker that loses tracks at larger rotations shrinks the choice, as it
//! should. Probe captures are discarded; a recording caller calls [`resolve_rotation`]
//! itself to record them as their own stage.

use headalign_platform::{Encoders, Joint, StereoHead};

use super::{AutoRotation, VergeTiltOptions};
use crate::error::AlignError;
pub(super) use crate::plan::{diagonal_offsets, single_joint_offsets};

/// Track ids seen by both cameras of a capture.
fn stereo_tracks(capture: &headalign_platform::StereoCapture) -> std::collections::HashSet<u64> {
    let left: std::collections::HashSet<u64> = capture.left.iter().map(|o| o.track).collect();
    capture.right.iter().map(|o| o.track).filter(|t| left.contains(t)).collect()
}

/// How many of `reference`'s stereo tracks `capture` also sees in both cameras.
pub fn shared_stereo_tracks(
    reference: &headalign_platform::StereoCapture,
    capture: &headalign_platform::StereoCapture,
) -> (usize, usize) {
    let r = stereo_tracks(reference);
    let c = stereo_tracks(capture);
    (r.intersection(&c).count(), r.len())
}

/// The calibration rotations the procedure uses, degrees.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RotationChoice {
    /// Single-joint (elevation, pan) rotation.
    pub rotation_deg: f64,
    /// Diagonal rotation (pan and elevation together); 0 for none.
    pub diagonal_rotation_deg: f64,
    /// Vergence move (both vergences together), if chosen.
    pub verge_rotation_deg: Option<f64>,
}

/// The choice logic of the auto mode, pure (module docs): `keeps_overlap(pan, elevation,
/// verge)` says whether the view at those offsets (degrees; `verge` turns both vergences)
/// from the initial readings keeps enough of the reference view's tracks. The single-joint
/// rotation is the largest candidate whose views all keep it, probing in decreasing order
/// (a view that fails moves on to the next smaller candidate; the first candidate is used
/// regardless, unprobed: the fixed protocol); largest first costs 4 probes when the scene
/// allows the largest (8 probing upwards, which matters on images, where each probe is a
/// capture and tracking); then, if `auto.diagonals`, the diagonal rotation is
/// the largest candidate not above it whose diagonal views all keep it, probing in
/// decreasing order (0 if none does); then, if `auto.choose_verge`, the vergence move
/// likewise (`None` if none does). Probes are requested in the order they are needed, and
/// none twice.
pub fn choose_rotations<E>(
    auto: &AutoRotation,
    both_directions: bool,
    mut keeps_overlap: impl FnMut(f64, f64, f64) -> Result<bool, E>,
) -> Result<RotationChoice, E> {
    let mut chosen = auto.candidates_deg.first().copied().unwrap_or(3.0);
    'candidates: for &r in auto.candidates_deg.iter().skip(1).rev() {
        for (_, pan, elevation) in single_joint_offsets(r, both_directions) {
            if !keeps_overlap(pan, elevation, 0.0)? {
                continue 'candidates;
            }
        }
        chosen = r;
        break;
    }
    let mut diagonal = 0.0;
    if auto.diagonals {
        'diagonals: for &d in auto.candidates_deg.iter().rev().filter(|&&d| d <= chosen) {
            for (_, pan, elevation) in diagonal_offsets(d, both_directions) {
                if !keeps_overlap(pan, elevation, 0.0)? {
                    continue 'diagonals;
                }
            }
            diagonal = d;
            break;
        }
    }
    let mut verge = None;
    if auto.choose_verge {
        for &v in auto.candidates_deg.iter().rev().filter(|&&v| v <= chosen) {
            if keeps_overlap(0.0, 0.0, v)? {
                verge = Some(v);
                break;
            }
        }
    }
    Ok(RotationChoice { rotation_deg: chosen, diagonal_rotation_deg: diagonal, verge_rotation_deg: verge })
}

/// The options with the auto mode resolved: if `options.auto_rotation` is set, probe the
/// head from its current readings ([`choose_rotations`]; the head returns there) and
/// return the options with the chosen `rotation_deg` and `diagonal_rotation_deg` and no
/// auto mode; otherwise a copy. [`VergeTiltRun::run`] calls it first; a caller that
/// records sessions calls it itself to record the probes as their own stage.
///
/// [`VergeTiltRun::run`]: super::VergeTiltRun::run
pub fn resolve_rotation<H: StereoHead>(
    head: &mut H,
    options: &VergeTiltOptions,
) -> Result<VergeTiltOptions, AlignError> {
    let Some(auto) = &options.auto_rotation else { return Ok(options.clone()) };
    auto.validate()?;
    let e0 = head.read_encoders()?;
    let c = choose_rotation(head, &e0, options.both_directions, auto)?;
    Ok(VergeTiltOptions {
        rotation_deg: c.rotation_deg,
        diagonal_rotation_deg: c.diagonal_rotation_deg,
        verge_rotation_deg: c.verge_rotation_deg.unwrap_or(options.verge_rotation_deg),
        auto_rotation: None,
        ..options.clone()
    })
}

/// Probe the head for [`choose_rotations`]: capture a reference view at `e0`, then each
/// requested view; count its shared stereo tracks. Returns to `e0`.
pub(super) fn choose_rotation<H: StereoHead>(
    head: &mut H,
    e0: &Encoders,
    both_directions: bool,
    auto: &AutoRotation,
) -> Result<RotationChoice, AlignError> {
    head.move_to(e0)?;
    let reference = head.capture()?;
    let choice = choose_rotations(auto, both_directions, |pan, elevation, verge| {
        let target = e0
            .moved(Joint::Pan, pan)
            .moved(Joint::Elevation, elevation)
            .moved(Joint::VergeLeft, verge)
            .moved(Joint::VergeRight, verge);
        head.move_to(&target)?;
        let probe = head.capture()?;
        let (shared, total) = shared_stereo_tracks(&reference, &probe);
        Ok::<bool, AlignError>(
            shared >= auto.min_tracks && (shared as f64) >= auto.min_overlap_fraction * total as f64,
        )
    })?;
    head.move_to(e0)?;
    Ok(choice)
}
