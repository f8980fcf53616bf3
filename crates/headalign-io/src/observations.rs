//! Observation sessions on disk (`docs/formats.md#observation-files`): point observations with track
//! identities, one JSON file, format `headalign-observations/1`. The views are the
//! library's [`View`] (`headalign::observations`, re-exported here).
//!
//! Reading validates everything a user can get wrong and names it: the format tag, the
//! image size, view names (unique), encoder readings (finite), pixels (finite, inside the
//! image: `-0.5 <= x < width - 0.5`, or at most [`OUTSIDE_MARGIN_PX`] beyond it),
//! duplicate track ids within one image, and that there are at least three views. Angles
//! are degrees, pixels have (0, 0) at the centre of the top-left pixel.
//!
//! Pitfall: a corner seen at the image's edge, with pixel noise added by another model of
//! the head or by a sub-pixel detector, lands a fraction of a pixel outside the image
//! (`y = -0.5`, `x = 768.02`). Such observations are real measurements and are kept: a
//! whole session must not be lost for one point. Farther out is a wrong coordinate
//! convention or a corrupt file, and an error.

use std::collections::HashSet;
use std::path::Path;

use headalign_platform::{Encoders, StereoCapture, TrackObservation};
use nalgebra::Point2;
use serde::{Deserialize, Serialize};

use headalign::AlignError;
pub use headalign::observations::View;

/// Observations at most this far outside the image (pixels, beyond the edge pixels'
/// outer borders) are kept as measured; farther out is an error.
pub const OUTSIDE_MARGIN_PX: f64 = 2.0;

/// The format tag this version reads and writes.
pub const FORMAT: &str = "headalign-observations/1";

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSession {
    format: String,
    image_size: [u32; 2],
    views: Vec<RawView>,
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawView {
    name: String,
    encoders: Encoders,
    left: Vec<(u64, f64, f64)>,
    right: Vec<(u64, f64, f64)>,
}

/// Parse and validate a session from JSON text. `origin` names the source in messages.
pub fn parse_session(text: &str, origin: &str) -> Result<Vec<View>, AlignError> {
    let raw: RawSession = serde_json::from_str(text)
        .map_err(|e| AlignError::Observations(format!("{origin}: malformed JSON: {e}")))?;
    if raw.format != FORMAT {
        return Err(AlignError::Observations(format!(
            "{origin}: unsupported format '{}', expected '{FORMAT}'",
            raw.format
        )));
    }
    let [w, h] = raw.image_size;
    if w == 0 || h == 0 || w > 100_000 || h > 100_000 {
        return Err(AlignError::Observations(format!(
            "{origin}: image_size {w} x {h} is not a valid image size"
        )));
    }
    if raw.views.len() < 3 {
        return Err(AlignError::Observations(format!(
            "{origin}: {} view(s); the verge/tilt procedure needs at least 3 (initial, elevation, pan)",
            raw.views.len()
        )));
    }
    let mut names = HashSet::new();
    let mut views = Vec::with_capacity(raw.views.len());
    for (i, v) in raw.views.into_iter().enumerate() {
        let name = v.name.trim().to_string();
        if name.is_empty() {
            return Err(AlignError::Observations(format!("{origin}: view {i} has an empty name")));
        }
        if !names.insert(name.clone()) {
            return Err(AlignError::Observations(format!("{origin}: view name '{name}' appears twice")));
        }
        if !v.encoders.is_finite() {
            return Err(AlignError::Observations(format!(
                "{origin}: view '{name}': encoder readings must be finite"
            )));
        }
        if headalign_platform::Joint::ALL.iter().any(|&j| v.encoders.get(j).abs() > 3600.0) {
            return Err(AlignError::Observations(format!(
                "{origin}: view '{name}': encoder reading beyond +-3600 deg"
            )));
        }
        let left = convert_side(&v.left, w, h, origin, &name, "left")?;
        let right = convert_side(&v.right, w, h, origin, &name, "right")?;
        views.push(View {
            name,
            capture: StereoCapture { encoders: v.encoders, image_size: [w, h], left, right },
        });
    }
    Ok(views)
}

fn convert_side(
    obs: &[(u64, f64, f64)],
    w: u32,
    h: u32,
    origin: &str,
    view: &str,
    side: &str,
) -> Result<Vec<TrackObservation>, AlignError> {
    let mut seen = HashSet::with_capacity(obs.len());
    let mut out = Vec::with_capacity(obs.len());
    let (wf, hf) = (f64::from(w), f64::from(h));
    for &(track, x, y) in obs {
        if !x.is_finite() || !y.is_finite() {
            return Err(AlignError::Observations(format!(
                "{origin}: view '{view}' {side} track {track}: pixel is not finite"
            )));
        }
        let m = OUTSIDE_MARGIN_PX;
        if x < -0.5 - m || y < -0.5 - m || x > wf - 0.5 + m || y > hf - 0.5 + m {
            // Short even for absurd values (one line of at most about 300 characters).
            let px = |v: f64| if v.abs() < 1e6 { format!("{v}") } else { format!("{v:.3e}") };
            return Err(AlignError::Observations(format!(
                "{origin}: view '{view}' {side} track {track}: pixel ({}, {}) more than {m} px outside the {w} x {h} image",
                px(x),
                px(y)
            )));
        }
        if !seen.insert(track) {
            return Err(AlignError::Observations(format!(
                "{origin}: view '{view}' {side}: track {track} appears twice"
            )));
        }
        out.push(TrackObservation { track, pixel: Point2::new(x, y) });
    }
    Ok(out)
}

/// Read and validate a session file.
pub fn read_session(path: &Path) -> Result<Vec<View>, AlignError> {
    let origin = path.display().to_string();
    let text = std::fs::read_to_string(path)
        .map_err(|e| AlignError::Observations(format!("{origin}: cannot read: {e}")))?;
    parse_session(&text, &origin)
}

/// Serialise views to the session JSON format.
pub fn session_to_json(views: &[View]) -> Result<String, AlignError> {
    let image_size = views.first().map(|v| v.capture.image_size).unwrap_or([0, 0]);
    let raw = RawSession {
        format: FORMAT.to_string(),
        image_size,
        views: views
            .iter()
            .map(|v| RawView {
                name: v.name.clone(),
                encoders: v.capture.encoders,
                left: v.capture.left.iter().map(|o| (o.track, o.pixel.x, o.pixel.y)).collect(),
                right: v.capture.right.iter().map(|o| (o.track, o.pixel.x, o.pixel.y)).collect(),
            })
            .collect(),
    };
    serde_json::to_string_pretty(&raw)
        .map_err(|e| AlignError::Observations(format!("cannot serialise session: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn session(views: &str) -> String {
        format!(r#"{{"format": "{FORMAT}", "image_size": [768, 576], "views": [{views}]}}"#)
    }

    fn view(name: &str, elev: f64) -> String {
        format!(
            r#"{{"name": "{name}", "encoders": {{"pan": 0.0, "elevation": {elev}, "verge_left": 0.0, "verge_right": 0.0}},
               "left": [[17, 412.3, 251.9], [18, 80.0, 301.2]], "right": [[17, 371.0, 250.2]]}}"#
        )
    }

    #[test]
    fn parses_valid_session_and_round_trips() {
        let text = session(&[view("initial", 0.0), view("elevation", 3.0), view("pan", 0.0)].join(","));
        let views = parse_session(&text, "t").unwrap();
        assert_eq!(views.len(), 3);
        assert_eq!(views[1].capture.encoders.elevation, 3.0);
        assert_eq!(views[0].capture.left[1].track, 18);
        let again = parse_session(&session_to_json(&views).unwrap(), "t").unwrap();
        assert_eq!(again, views);
    }

    #[test]
    fn every_bad_input_is_named() {
        let ok3 = [view("initial", 0.0), view("elevation", 3.0), view("pan", 0.0)].join(",");
        let cases: Vec<(String, &str)> = vec![
            ("{".to_string(), "malformed JSON"),
            (session(&ok3).replace(FORMAT, "other/2"), "unsupported format"),
            (session(&ok3).replace("[768, 576]", "[0, 576]"), "not a valid image size"),
            (session(&[view("a", 0.0), view("b", 1.0)].join(",")), "needs at least 3"),
            (session(&[view("a", 0.0), view("a", 1.0), view("c", 2.0)].join(",")), "appears twice"),
            (session(&ok3).replacen("412.3", "1e9", 1), "outside"),
            (session(&ok3).replacen("[18, 80.0", "[17, 80.0", 1), "track 17 appears twice"),
            (session(&ok3).replacen("\"elevation\": 3", "\"elevation\": \"x\"", 1), "malformed JSON"),
            (session(&ok3).replacen("\"pan\": 0.0,", "", 1), "missing field"),
            (session(&ok3).replacen("412.3", "-5", 1), "outside"),
            (session(&ok3).replacen("[17, 412.3", "[-17, 412.3", 1), "malformed JSON"),
        ];
        for (text, expected) in cases {
            let err = parse_session(&text, "file.json").unwrap_err().to_string();
            assert!(err.contains(expected), "expected '{expected}' in '{err}'");
            assert!(err.starts_with("file.json"), "message must name the file: {err}");
            assert!(!err.contains('\n'), "one line: {err}");
        }
    }

    /// Noisy observations at the edge (the reported `y = -0.5`, `x = 768.02`, and up to
    /// 2 px out) are kept as measured; 2.01 px out is an error.
    #[test]
    fn points_just_outside_the_image_are_kept() {
        for (x, y) in [(412.3, -0.5), (768.02, 100.0), (-2.5, -2.5), (769.5, 577.5)] {
            let text = session(&[view("initial", 0.0), view("elevation", 3.0), view("pan", 0.0)].join(","))
                .replacen("412.3, 251.9", &format!("{x}, {y}"), 1);
            let views = parse_session(&text, "t").unwrap();
            assert_eq!(views[0].capture.left[0].pixel, Point2::new(x, y));
        }
        for (x, y) in [(-2.51, 10.0), (10.0, 577.51), (769.51, 10.0)] {
            let text = session(&[view("initial", 0.0), view("elevation", 3.0), view("pan", 0.0)].join(","))
                .replacen("412.3, 251.9", &format!("{x}, {y}"), 1);
            let err = parse_session(&text, "t").unwrap_err().to_string();
            assert!(err.contains("more than 2 px outside the 768 x 576 image"), "{err}");
        }
    }

    #[test]
    fn unreadable_file_is_an_error() {
        let err = read_session(Path::new("/nonexistent/obs.json")).unwrap_err().to_string();
        assert!(err.contains("/nonexistent/obs.json") && err.contains("cannot read"));
    }
}
