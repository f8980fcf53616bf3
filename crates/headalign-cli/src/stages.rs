//! The robot stages' flags (`demo --stages ...`, `run --stages ...`): the stage list
//! parsed and checked against the stage flags given, and the one-line summary of what the
//! stages found. The stages themselves run in the library
//! ([`headalign::robot::stages::run_robot_stages`]).

use anyhow::{Result, bail};
use headalign::robot::stages::STAGES;

/// An error naming each stage flag given (`given`: flag name, whether given) whose
/// stages `stages` leaves out: the flag would be ignored.
pub fn refuse_unused_flags(stages: &[String], given: &[(&str, bool)]) -> Result<()> {
    for &(flag, on) in given {
        let users: &[&str] = match flag {
            "--drive" => &["pan", "pan-fixate", "one-motion"],
            "--steer-drive" | "--steer-settings" => &["steering"],
            "--horizon-from-drive" => &["one-motion"],
            _ => continue,
        };
        if on && !stages.iter().any(|s| users.contains(&s.as_str())) {
            let (names, noun) = match users {
                [one] => (one.to_string(), "stage"),
                many => (many.join(", "), "stages"),
            };
            bail!("{flag} applies to the {names} {noun}, which --stages leaves out");
        }
    }
    Ok(())
}

/// Parse a comma-separated stage list; unknown names are errors.
pub fn parse_stages(list: &str) -> Result<Vec<String>> {
    let stages: Vec<String> =
        list.split(',').map(str::trim).filter(|s| !s.is_empty()).map(str::to_string).collect();
    for st in &stages {
        if !STAGES.contains(&st.as_str()) {
            bail!("unknown stage '{st}' (expected {})", STAGES.join(", "));
        }
    }
    Ok(stages)
}

/// One line naming what the robot stages found, from a run's JSON (`pan`, `steering`
/// members): each pan stage's final pan reading, the steering zero, and the pan axis'
/// tilt from the floor normal (the steering stage's, else the last pan drive's;
/// [`headalign::robot::FloorNormal`]); `None` when only the verge/tilt stage was asked for.
pub fn summary_line(v: &serde_json::Value) -> Option<String> {
    let stages = v["stages"].as_array()?;
    if stages.iter().all(|s| s.as_str() == Some(headalign_io::session::STAGE_VERGE_TILT)) {
        return None;
    }
    let mut parts = Vec::new();
    let pans: Vec<String> = v["pan"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|p| p["final_encoders"]["pan"].as_f64())
        .map(|pan| format!("{pan:.3}"))
        .collect();
    if !pans.is_empty() {
        parts.push(format!("pan reading after each pan stage {} deg", pans.join(", ")));
    }
    if let (Some(zero), Some(sigma)) =
        (v["steering"]["steer_zero_deg"].as_f64(), v["steering"]["sigma_steer_zero_deg"].as_f64())
    {
        parts.push(format!("steering zero {zero:.3} +- {sigma:.3} deg"));
    }
    let pan_floor = v["pan"].as_array().and_then(|p| p.last()).map(|p| &p["floor"]);
    let floor = if v["steering"]["floor"].is_object() { Some(&v["steering"]["floor"]) } else { pan_floor };
    if let Some(f) = floor
        && let (Some(tilt), Some(sigma)) = (f["pan_tilt_deg"].as_f64(), f["sigma_pan_tilt_deg"].as_f64())
    {
        parts.push(format!("pan axis {tilt:.2} +- {sigma:.2} deg from the floor normal"));
    }
    let names: Vec<&str> = stages.iter().filter_map(serde_json::Value::as_str).collect();
    Some(format!("stages {}: {}", names.join(","), parts.join("; ")))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The summary names each pan stage's reading, the steering zero, and the pan axis'
    /// tilt from the floor normal: the steering stage's when it ran, else the last pan
    /// drive's (the members of `headalign::robot::FloorNormal`).
    #[test]
    fn summary_line_reports_the_floor_tilt() {
        let floor = |t: f64, s: f64| serde_json::json!({"pan_tilt_deg": t, "sigma_pan_tilt_deg": s});
        let pan = serde_json::json!([{"final_encoders": {"pan": 1.5}, "floor": floor(2.5, 3.1)}]);
        let v = serde_json::json!({
            "stages": ["verge-tilt", "pan", "steering"],
            "pan": pan,
            "steering": {"steer_zero_deg": 0.25, "sigma_steer_zero_deg": 0.04, "floor": floor(3.0, 0.07)},
        });
        let line = summary_line(&v).unwrap();
        assert!(line.contains("steering zero 0.250 +- 0.040 deg"), "{line}");
        assert!(line.contains("pan axis 3.00 +- 0.07 deg from the floor normal"), "{line}");
        let v = serde_json::json!({"stages": ["verge-tilt", "pan"], "pan": pan});
        let line = summary_line(&v).unwrap();
        assert!(line.contains("pan reading after each pan stage 1.500 deg"), "{line}");
        assert!(line.contains("pan axis 2.50 +- 3.10 deg from the floor normal"), "{line}");
    }
}
