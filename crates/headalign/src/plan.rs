//! The capture plan of the verge/tilt procedure ([`crate::procedure`]): the views it
//! captures and their encoder readings, from the initial readings. The initial view;
//! elevation and pan rotations (each both ways if `both_directions`); the diagonal views
//! (pan and elevation turned together) if `diagonal_rotation_deg` is not 0; and last,
//! both vergences rotated (to measure the vergence axes). The view names (`initial`,
//! `elevation+`, `pan-`, `pan+elevation-`, `verge`, ...) are those the sessions record.
//!
//! Degrees, as encoders are. Pitfall: the plan is commanded readings; what the head
//! reaches is what its captures report.

use headalign_platform::{Encoders, Joint};

/// The rotations of the procedure's plan, degrees. The defaults are those of
/// [`crate::procedure::VergeTiltOptions`], the paper's protocol: 3 deg elevation, pan and
/// vergence turns, both ways, no diagonal views.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CapturePlan {
    /// Elevation and pan rotation, degrees (default 3).
    pub rotation_deg: f64,
    /// Vergence rotation, degrees (default 3).
    pub verge_rotation_deg: f64,
    /// Rotate each of elevation and pan both ways (default true).
    pub both_directions: bool,
    /// Diagonal rotation (pan and elevation together), degrees; 0 for none (default).
    pub diagonal_rotation_deg: f64,
}

impl Default for CapturePlan {
    fn default() -> Self {
        Self { rotation_deg: 3.0, verge_rotation_deg: 3.0, both_directions: true, diagonal_rotation_deg: 0.0 }
    }
}

impl CapturePlan {
    /// The views, in order, from the initial readings `e0` (module docs).
    pub fn views(&self, e0: &Encoders) -> Vec<(String, Encoders)> {
        let mut plan = vec![("initial".to_string(), *e0)];
        let moves = single_joint_offsets(self.rotation_deg, self.both_directions)
            .into_iter()
            .chain(diagonal_offsets(self.diagonal_rotation_deg, self.both_directions));
        for (name, pan, elevation) in moves {
            plan.push((name.to_string(), e0.moved(Joint::Pan, pan).moved(Joint::Elevation, elevation)));
        }
        let v = self.verge_rotation_deg;
        plan.push(("verge".to_string(), e0.moved(Joint::VergeLeft, v).moved(Joint::VergeRight, v)));
        plan
    }
}

/// The (pan, elevation) offsets of the single-joint views at rotation `r` (elevation
/// first), each both ways if `both_directions`.
pub(crate) fn single_joint_offsets(r: f64, both_directions: bool) -> Vec<(&'static str, f64, f64)> {
    if both_directions {
        vec![("elevation+", 0.0, r), ("elevation-", 0.0, -r), ("pan+", r, 0.0), ("pan-", -r, 0.0)]
    } else {
        vec![("elevation", 0.0, r), ("pan", r, 0.0)]
    }
}

/// The (pan, elevation) offsets of the diagonal views at rotation `d` (none if `d` is 0).
pub(crate) fn diagonal_offsets(d: f64, both_directions: bool) -> Vec<(&'static str, f64, f64)> {
    if d == 0.0 {
        Vec::new()
    } else if both_directions {
        vec![
            ("pan+elevation+", d, d),
            ("pan+elevation-", d, -d),
            ("pan-elevation+", -d, d),
            ("pan-elevation-", -d, -d),
        ]
    } else {
        vec![("pan+elevation+", d, d)]
    }
}
