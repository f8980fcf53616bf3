//! Step 1 of the estimation ([`super`]): the role of each view, from its encoder
//! readings against those of the first ("reference") view.
//!
//! A view where only pan and elevation moved is a *rig* view: the stereo rig is the same
//! as in the reference view, so its stereo matches share one fundamental matrix and one
//! projective frame (paper section 3.2 step 1). A view where a vergence joint moved is a
//! *verge* view (the rig changed); it is left to the vergence-axis measurement of
//! [`crate::procedure`]. The paper's procedure needs one rotation about pan alone and one
//! about elevation alone (section 3.1: two rotations about different axes fix the plane
//! at infinity); anything else is an error that names the offending views.
//!
//! Units: encoder differences in degrees; a joint "moved" when its reading changed by
//! more than [`MOVED_DEG`]. Pitfall: the threshold must sit above the read jitter of a
//! joint at rest (0.014 deg RMS between two readings at the default encoder noise) and
//! far below any commanded rotation, or a pan view with a jittering elevation reading is
//! no single-joint rotation.

use headalign_platform::Joint;

use crate::error::AlignError;
use crate::observations::View;

/// Encoder differences below this (degrees) count as "did not move": above the read jitter
/// of a joint at rest (a reading with Gaussian noise of [`ENCODER_SIGMA_DEG`](super::ENCODER_SIGMA_DEG) differs from
/// another by 0.014 deg RMS; 0.05 deg still failed 1 trial in 200 with "no view rotates the
/// pan joint alone"), far below any commanded rotation (1 deg and up).
pub const MOVED_DEG: f64 = 0.1;

/// The role of a view, from its encoder differences to the reference view.
#[derive(Debug, Clone, PartialEq)]
pub enum ViewRole {
    /// The first view.
    Reference,
    /// Only pan and/or elevation moved: the rig is unchanged. Differences in degrees.
    Rig {
        /// Pan difference, degrees.
        pan_deg: f64,
        /// Elevation difference, degrees.
        elevation_deg: f64,
    },
    /// A vergence joint moved (the rig changed): used to measure the vergence axes.
    Verge,
}

/// Classify each view; errors for a view that did not move and for rotations that are all
/// about one joint.
pub fn classify_views(views: &[View]) -> Result<Vec<ViewRole>, AlignError> {
    let Some(first) = views.first() else {
        return Err(AlignError::Observations("no views".into()));
    };
    let e0 = first.capture.encoders;
    let mut roles = vec![ViewRole::Reference];
    for v in &views[1..] {
        let d = |j: Joint| v.capture.encoders.get(j) - e0.get(j);
        let moved: Vec<Joint> = Joint::ALL.iter().copied().filter(|&j| d(j).abs() > MOVED_DEG).collect();
        if moved.is_empty() {
            return Err(AlignError::NotARotation {
                view: v.name.clone(),
                why: format!("its encoder readings equal those of '{}': no rotation to measure", first.name),
            });
        }
        if moved.iter().any(|j| matches!(j, Joint::VergeLeft | Joint::VergeRight)) {
            roles.push(ViewRole::Verge);
        } else {
            roles.push(ViewRole::Rig { pan_deg: d(Joint::Pan), elevation_deg: d(Joint::Elevation) });
        }
    }
    // Single-joint rotations give the axes; at least one about each of pan and elevation.
    let single = |joint: Joint| -> Option<usize> {
        roles.iter().enumerate().find_map(|(i, r)| match (r, joint) {
            (ViewRole::Rig { pan_deg, elevation_deg }, Joint::Pan)
                if elevation_deg.abs() <= MOVED_DEG && pan_deg.abs() > MOVED_DEG =>
            {
                Some(i)
            }
            (ViewRole::Rig { pan_deg, elevation_deg }, Joint::Elevation)
                if pan_deg.abs() <= MOVED_DEG && elevation_deg.abs() > MOVED_DEG =>
            {
                Some(i)
            }
            _ => None,
        })
    };
    let rig_views: Vec<usize> =
        (0..roles.len()).filter(|&i| matches!(roles[i], ViewRole::Rig { .. })).collect();
    match (single(Joint::Pan), single(Joint::Elevation)) {
        (Some(_), Some(_)) => Ok(roles),
        (p, e) => {
            // Name the two views rotating about the same joint, if that is the problem.
            let joint = if p.is_some() { Joint::Pan } else { Joint::Elevation };
            let same: Vec<usize> = rig_views
                .iter()
                .copied()
                .filter(|&i| single(joint) == Some(i) || is_single(&roles[i], joint))
                .collect();
            if (p.is_some() || e.is_some()) && same.len() >= 2 {
                return Err(AlignError::SameAxis {
                    first: views[same[0]].name.clone(),
                    second: views[same[1]].name.clone(),
                    joint: joint.name().to_string(),
                });
            }
            let missing = if p.is_none() { "pan" } else { "elevation" };
            Err(AlignError::MissingMotion(format!(
                "no view rotates the {missing} joint alone; the procedure needs one rotation about pan and one about elevation"
            )))
        }
    }
}

/// Whether `role` is a rig view that rotates `joint` (pan or elevation) alone: it moved
/// by more than [`MOVED_DEG`] and the other of the two did not.
fn is_single(role: &ViewRole, joint: Joint) -> bool {
    match role {
        ViewRole::Rig { pan_deg, elevation_deg } => match joint {
            Joint::Pan => elevation_deg.abs() <= MOVED_DEG && pan_deg.abs() > MOVED_DEG,
            Joint::Elevation => pan_deg.abs() <= MOVED_DEG && elevation_deg.abs() > MOVED_DEG,
            _ => false,
        },
        _ => false,
    }
}
