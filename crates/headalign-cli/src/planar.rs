//! `headalign demo` on a planar or far scene (point mode): the planar route's report
//! ([`headalign::planar`]) against the simulator's truth, as a table or one JSON object.
//! The robot stages need the 3D reconstruction a plane does not give: they are skipped,
//! and the report says so.

use anyhow::Result;
use headalign::planar::{CameraPlanar, SceneCheck};
use headalign::procedure::PlanarOutcome;
use headalign_sim::{Scenario, SimulatedHead};
use serde_json::{Value, json};

use crate::encoders_json;

/// Print a line to stdout, ignoring write errors (as `demo`).
macro_rules! say {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stdout(), $($arg)*);
    }};
}

/// The text line of a scene check: `scene: kind (why)`.
pub fn scene_line(check: &SceneCheck) -> String {
    format!("scene: {} ({})", check.kind.name(), check.why)
}

/// One camera's line: intrinsics with sigmas, residual, plane normal.
fn camera_line(name: &str, c: &CameraPlanar, truth: &headalign_geometry::camera::Intrinsics) -> String {
    let s = |n: &str| c.sigma(n).unwrap_or(f64::NAN);
    let k = &c.intrinsics;
    let normal = c.plane_normal.map_or_else(
        || "undetermined".to_string(),
        |n| format!("[{:.3}, {:.3}, {:.3}] ± {:.2} deg", n[0], n[1], n[2], c.plane_normal_sigma_deg),
    );
    format!(
        "  {name:<5} fx {:.2} ± {:.2} (true {:.2})  fy {:.2} ± {:.2} ({:.2})  cx {:.2} ± {:.2} ({:.2})  cy {:.2} ± {:.2} ({:.2})  rms {:.3} px, {} points; plane normal {normal}",
        k.fx,
        s("fx"),
        truth.fx,
        k.fy,
        s("fy"),
        truth.fy,
        k.cx,
        s("cx"),
        truth.cx,
        k.cy,
        s("cy"),
        truth.cy,
        c.rms_px,
        c.points
    )
}

/// Print (or return as JSON) the planar outcome of a demo run on `head` (after the
/// procedure, the head at the aligned readings).
pub fn report(
    scenario: &Scenario,
    head: &SimulatedHead,
    out: &PlanarOutcome,
    json: bool,
) -> Result<Option<Value>> {
    let truth = head.aligned_encoders();
    let a = out.solution.aligned_encoders;
    let errors =
        [a.elevation - truth.elevation, a.verge_left - truth.verge_left, a.verge_right - truth.verge_right];
    let after = head.alignment_errors(&head.encoders());
    let cal = &out.calibration;
    if json {
        return Ok(Some(json!({
            "seed": scenario.seed,
            "route": "planar",
            "scene": cal.scene,
            "planar": cal,
            "aligned_encoders": encoders_json(&a),
            "sigmas_deg": {
                "elevation": out.sigmas.elevation_deg,
                "verge_left": out.sigmas.verge_left_deg,
                "verge_right": out.sigmas.verge_right_deg,
            },
            "truth": { "aligned_encoders": encoders_json(&truth) },
            "aligned_reading_errors_deg": { "elevation": errors[0], "verge_left": errors[1], "verge_right": errors[2] },
            "alignment_errors_after": after,
            "robot_stages": "skipped: they need the 3D reconstruction a plane does not give",
            "estimation_seconds": out.estimation_seconds,
        })));
    }
    say!("{}", scene_line(&cal.scene));
    say!("planar route (paper section 3.3): each camera from its own plane homographies");
    let t = head.truth();
    say!("{}", camera_line("left", &cal.left, &t.left));
    say!("{}", camera_line("right", &cal.right, &t.right));
    say!("undetermined: {}", cal.undetermined.join("; "));
    if !cal.dropped_views.is_empty() {
        say!("views left out: {}", cal.dropped_views.join("; "));
    }
    say!(
        "aligned readings (deg): elevation {:.4} ± {:.4} (true {:.4}), verge_left {:.4} ± {:.4} ({:.4}), verge_right {:.4} ± {:.4} ({:.4})",
        a.elevation,
        out.sigmas.elevation_deg,
        truth.elevation,
        a.verge_left,
        out.sigmas.verge_left_deg,
        truth.verge_left,
        a.verge_right,
        out.sigmas.verge_right_deg,
        truth.verge_right
    );
    say!(
        "alignment errors after the move (deg): verge_err_l {:+.4}, verge_err_r {:+.4}, elev_err_l {:+.4}, elev_err_r {:+.4}",
        after.verge_err_l_deg,
        after.verge_err_r_deg,
        after.elev_err_l_deg,
        after.elev_err_r_deg
    );
    say!("robot stages: skipped (they need the 3D reconstruction a plane does not give)");
    say!("time: estimation {:.1} ms", 1e3 * out.estimation_seconds);
    Ok(None)
}
