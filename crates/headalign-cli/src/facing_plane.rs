//! The planar route's report ([`headalign::facing_plane`]): `demo` on a planar or far scene
//! (point mode, against the simulator's truth, as a table), and the summary lines every
//! command shares (`demo --images`, `replay`, `run`, `align`): [`summary_lines`]. The
//! JSON of every route is [`headalign_io::report::schema`]'s. The robot stages need the 3D
//! reconstruction a plane does not give: they are skipped, and the report says so.

use anyhow::Result;
use headalign::facing_plane::CameraPlanar;
use headalign::procedure::PlanarOutcome;
use headalign_sim::SimulatedHead;
use serde_json::{Value, json};

/// The lines every command prints about the route from a report's JSON: the scene
/// (`scene: kind (why)`, when the report has one) and, on the planar route, what is
/// undetermined, the check after the move and what it cannot check.
pub fn summary_lines(v: &Value) -> Vec<String> {
    let mut lines = Vec::new();
    if let Some(kind) = v["scene"]["kind"].as_str() {
        lines.push(format!("scene: {kind} ({})", v["scene"]["why"].as_str().unwrap_or("")));
    }
    if v["route"].as_str() != Some("planar") {
        return lines;
    }
    lines.push("planar route (paper section 3.3): each camera from its own plane homographies".into());
    let join = |x: &Value| {
        x.as_array()
            .map_or(String::new(), |a| a.iter().filter_map(Value::as_str).collect::<Vec<_>>().join("; "))
    };
    lines.push(format!("undetermined: {}", join(&v["planar"]["undetermined"])));
    let f = |x: &Value| x.as_f64().unwrap_or(f64::NAN);
    if let Some(c) = v["checks"].as_array().and_then(|c| c.last()) {
        let m = &c["measured"];
        lines.push(format!(
            "check after the move (deg, each camera against its own axes): verge_err_l {:+.4}, verge_err_r {:+.4}, elev_err_l {:+.4}, elev_err_r {:+.4}; unmodelled rotation left {:.4}, right {:.4} ({} / {} tracks)",
            f(&m["verge_err_l_deg"]),
            f(&m["verge_err_r_deg"]),
            f(&m["elev_err_l_deg"]),
            f(&m["elev_err_r_deg"]),
            f(&c["left"]["unmodelled_rotation_deg"]),
            f(&c["right"]["unmodelled_rotation_deg"]),
            c["left"]["tracks"],
            c["right"]["tracks"]
        ));
        lines.push(format!("not checked: {}", join(&c["unchecked"])));
    }
    if let Some(why) = v["check_failure"].as_str() {
        lines.push(format!("check after the move: not made ({why})"));
    }
    lines.push(format!("robot stages: {}", headalign_io::report::schema::ROBOT_STAGES_SKIPPED));
    lines
}

/// What an image session holds besides its views, by the report's route (the planar route
/// draws no `figure6.png`).
pub fn session_files(v: &Value) -> &'static str {
    if v["route"].as_str() == Some("planar") {
        "views, report.json, report.html, aligned.png"
    } else {
        "views, report.json, figure6.png, aligned.png"
    }
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

/// Print the planar outcome of a point-mode demo run on `head` (after the procedure, the
/// head at the aligned readings) against its truth; its JSON is the demo's
/// ([`headalign_io::report::schema::DemoReport`]).
pub fn report(head: &SimulatedHead, out: &PlanarOutcome) -> Result<()> {
    let truth = head.aligned_encoders();
    let a = out.solution.aligned_encoders;
    let after = head.alignment_errors(&head.encoders());
    let cal = &out.calibration;
    say!("{}", headalign_io::report::html::scene_line(&cal.scene));
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
    let v = json!({"route": "planar", "planar": {"undetermined": cal.undetermined}, "checks": serde_json::to_value(&out.checks)?, "check_failure": out.check_failure});
    for line in summary_lines(&v).into_iter().skip(2) {
        say!("{line}");
    }
    say!("time: estimation {:.1} ms", 1e3 * out.estimation_seconds);
    Ok(())
}
