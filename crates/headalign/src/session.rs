//! Recorded image sessions on disk (DESIGN.md section 3): one folder per captured view,
//! `NN-name/left.png`, `right.png` and `view.json` (`name`, `encoders` in degrees), in
//! capture order (the folders sort by their `NN` prefix). `headalign demo --images --save
//! DIR` writes them; [`read_image_session`] reads them back and [`track_session`] runs the
//! image front end over them, giving the views the estimation consumes, exactly as the
//! live run did (same images, same order, same tracker: the same observations).
//!
//! Every bad input is an error naming the file and the problem: a missing or unreadable
//! image, a malformed `view.json` (wrong types, missing fields, an empty or repeated view
//! name, non-finite encoder readings or readings beyond +-3600 deg), left and right
//! images of different sizes, a view whose size differs from the first, a blank
//! (textureless) image. [`parse_view_json`] and [`check_image`] are the pure parts of the
//! reader (fuzzed without files: `fuzz/`, targets `view_json` and `png_decode`).

use std::path::{Path, PathBuf};

use headalign_platform::{Encoders, GrayImage, StereoImages};
use serde::Deserialize;

use crate::AlignError;
use crate::frontend::{FrontEndOptions, Tracker};
use crate::observations::View;

/// Images whose grey-level standard deviation is below this are blank (no texture to
/// match), grey levels.
pub const MIN_IMAGE_STD: f64 = 2.0;

/// One recorded view.
#[derive(Debug, Clone)]
pub struct RecordedView {
    /// The view's name (from `view.json`).
    pub name: String,
    /// Its folder.
    pub folder: PathBuf,
    /// The images and the encoder readings.
    pub images: StereoImages,
}

/// Largest encoder reading a `view.json` may hold, degrees (ten turns, as the
/// observation reader allows: larger values are corrupt data, and differences of huge
/// readings overflow).
pub const MAX_ENCODER_DEG: f64 = 3600.0;

/// The contents of a `view.json` that the reader uses (other keys, e.g. `image_size`
/// and `tracked` written by `--save`, are ignored).
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct ViewMeta {
    /// The view's name (non-empty, trimmed).
    pub name: String,
    /// Encoder readings, degrees.
    pub encoders: Encoders,
}

/// Parse and validate the text of a `view.json`; `origin` names it in messages.
pub fn parse_view_json(text: &str, origin: &str) -> Result<ViewMeta, AlignError> {
    let mut meta: ViewMeta =
        serde_json::from_str(text).map_err(|e| AlignError::Images(format!("'{origin}': {e}")))?;
    meta.name = meta.name.trim().to_string();
    if meta.name.is_empty() {
        return Err(AlignError::Images(format!("'{origin}': the view name is empty")));
    }
    if !meta.encoders.is_finite() {
        return Err(AlignError::Images(format!("'{origin}': encoder readings must be finite")));
    }
    if headalign_platform::Joint::ALL.iter().any(|&j| meta.encoders.get(j).abs() > MAX_ENCODER_DEG) {
        return Err(AlignError::Images(format!(
            "'{origin}': encoder reading beyond +-{MAX_ENCODER_DEG} deg"
        )));
    }
    Ok(meta)
}

/// Check that a decoded image has texture to match (grey-level standard deviation at
/// least [`MIN_IMAGE_STD`]); `origin` names it in messages.
pub fn check_image(img: &GrayImage, origin: &str) -> Result<(), AlignError> {
    let n = img.pixels().len() as f64;
    let mean = img.pixels().iter().map(|&v| f64::from(v)).sum::<f64>() / n;
    let var = img.pixels().iter().map(|&v| (f64::from(v) - mean).powi(2)).sum::<f64>() / n;
    if var.sqrt() < MIN_IMAGE_STD {
        return Err(AlignError::Images(format!(
            "'{origin}' is blank: grey-level standard deviation {:.2} (< {MIN_IMAGE_STD}), nothing to match",
            var.sqrt()
        )));
    }
    Ok(())
}

fn load(path: &Path) -> Result<GrayImage, AlignError> {
    let img = GrayImage::load(path).map_err(|e| AlignError::Images(e.to_string()))?;
    check_image(&img, &path.display().to_string())?;
    Ok(img)
}

/// Read every view folder of `dir` in order.
pub fn read_image_session(dir: &Path) -> Result<Vec<RecordedView>, AlignError> {
    let entries = std::fs::read_dir(dir)
        .map_err(|e| AlignError::Images(format!("cannot read session folder '{}': {e}", dir.display())))?;
    let mut folders: Vec<PathBuf> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.is_dir() && p.join("view.json").exists())
        .collect();
    folders.sort();
    if folders.is_empty() {
        return Err(AlignError::Images(format!(
            "'{}' holds no view folders (NN-name/ with left.png, right.png, view.json)",
            dir.display()
        )));
    }
    let mut views: Vec<RecordedView> = Vec::new();
    for folder in folders {
        let meta_path = folder.join("view.json");
        let text = std::fs::read_to_string(&meta_path)
            .map_err(|e| AlignError::Images(format!("cannot read '{}': {e}", meta_path.display())))?;
        let meta = parse_view_json(&text, &meta_path.display().to_string())?;
        if let Some(other) = views.iter().find(|v| v.name == meta.name) {
            return Err(AlignError::Images(format!(
                "'{}': view name '{}' is also the name of '{}'",
                meta_path.display(),
                meta.name,
                other.folder.display()
            )));
        }
        let (lp, rp) = (folder.join("left.png"), folder.join("right.png"));
        let (left, right) = (load(&lp)?, load(&rp)?);
        if left.size() != right.size() {
            return Err(AlignError::Images(format!(
                "'{}' is {}x{} but '{}' is {}x{}: left and right images must have the same size",
                lp.display(),
                left.width(),
                left.height(),
                rp.display(),
                right.width(),
                right.height()
            )));
        }
        if let Some(first) = views.first()
            && first.images.image_size() != left.size()
        {
            return Err(AlignError::Images(format!(
                "'{}' is {}x{} but the first view's images are {}x{}",
                lp.display(),
                left.width(),
                left.height(),
                first.images.image_size()[0],
                first.images.image_size()[1]
            )));
        }
        let images = StereoImages::new(meta.encoders, left, right)?;
        views.push(RecordedView { name: meta.name, folder, images });
    }
    Ok(views)
}

/// Run the image front end over recorded views (the first is the tracking reference).
pub fn track_session(views: &[RecordedView], options: &FrontEndOptions) -> Result<Vec<View>, AlignError> {
    let mut tracker = Tracker::new(options.clone())?;
    views
        .iter()
        .map(|v| {
            let (capture, _) = tracker.track(&v.images, &v.name).map_err(|e| {
                AlignError::Images(format!("view '{}' ({}): {e}", v.name, v.folder.display()))
            })?;
            Ok(View { name: v.name.clone(), capture })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write_view(dir: &Path, name: &str, left: &GrayImage, right: &GrayImage, json: &str) {
        let sub = dir.join(name);
        std::fs::create_dir_all(&sub).unwrap();
        left.save(&sub.join("left.png")).unwrap();
        right.save(&sub.join("right.png")).unwrap();
        std::fs::write(sub.join("view.json"), json).unwrap();
    }

    fn textured(w: u32, h: u32) -> GrayImage {
        let data = (0..w * h).map(|i| ((i * 7919) % 251) as u8).collect();
        GrayImage::new(w, h, data).unwrap()
    }

    #[test]
    fn view_json_bad_input_is_named() {
        let enc = |pan: &str| {
            format!(
                r#"{{"name": "a", "encoders": {{"pan": {pan}, "elevation": 0, "verge_left": 0, "verge_right": 0}}}}"#
            )
        };
        let ok = parse_view_json(&enc("1.5"), "v.json").unwrap();
        assert_eq!((ok.name.as_str(), ok.encoders.pan), ("a", 1.5));
        let cases: Vec<(String, &str)> = vec![
            (String::new(), "EOF"),
            ("{\"name\": \"a\", \"enc".into(), "EOF"),
            ("[1, 2]".into(), "invalid type"),
            ("{\"name\": 3}".into(), "invalid type"),
            ("{\"name\": \"a\"}".into(), "missing field `encoders`"),
            (enc("1.5").replace("\"a\"", "\"  \""), "name is empty"),
            (enc("\"x\""), "invalid type"),
            (enc("1e999"), "number out of range"),
            (enc("1e308"), "beyond"),
            (enc("-3600.5"), "beyond"),
            (enc("99999999999999999999999"), "beyond"),
            (enc("NaN"), "expected value"),
        ];
        for (text, expect) in cases {
            let e = parse_view_json(&text, "v.json").unwrap_err().to_string();
            assert!(e.contains("v.json") && e.contains(expect), "'{text}': '{e}' lacks '{expect}'");
            assert!(!e.contains('\n'), "one line: {e}");
        }
    }

    #[test]
    fn bad_sessions_name_the_file_and_the_problem() {
        let base = std::env::temp_dir().join(format!("headalign-session-{}", std::process::id()));
        let ok_json = r#"{"name": "initial", "encoders": {"pan": 0, "elevation": 0, "verge_left": 0, "verge_right": 0}}"#;
        let case = |name: &str, setup: &dyn Fn(&Path), expect: &[&str]| {
            let dir = base.join(name);
            std::fs::create_dir_all(&dir).unwrap();
            setup(&dir);
            let e = read_image_session(&dir).unwrap_err().to_string();
            for part in expect {
                assert!(e.contains(part), "{name}: '{e}' lacks '{part}'");
            }
        };
        case("empty", &|_| {}, &["holds no view folders"]);
        case(
            "blank",
            &|d| write_view(d, "00-initial", &GrayImage::filled(64, 48, 128), &textured(64, 48), ok_json),
            &["left.png", "blank"],
        );
        case(
            "mismatch",
            &|d| write_view(d, "00-initial", &textured(64, 48), &textured(60, 48), ok_json),
            &["left.png", "right.png", "same size"],
        );
        case(
            "bad-json",
            &|d| write_view(d, "00-initial", &textured(64, 48), &textured(64, 48), "{\"name\": 3}"),
            &["view.json"],
        );
        case(
            "unreadable",
            &|d| {
                write_view(d, "00-initial", &textured(64, 48), &textured(64, 48), ok_json);
                std::fs::write(d.join("00-initial").join("right.png"), b"not a png").unwrap();
            },
            &["right.png"],
        );
        case(
            "missing",
            &|d| {
                write_view(d, "00-initial", &textured(64, 48), &textured(64, 48), ok_json);
                std::fs::remove_file(d.join("00-initial").join("left.png")).unwrap();
            },
            &["left.png"],
        );
        case(
            "nan",
            &|d| {
                let j = r#"{"name": "a", "encoders": {"pan": 1e999, "elevation": 0, "verge_left": 0, "verge_right": 0}}"#;
                write_view(d, "00-initial", &textured(64, 48), &textured(64, 48), j)
            },
            &["view.json"],
        );
        case(
            "duplicate-name",
            &|d| {
                write_view(d, "00-initial", &textured(64, 48), &textured(64, 48), ok_json);
                write_view(d, "01-again", &textured(64, 48), &textured(64, 48), ok_json);
            },
            &["01-again", "view.json", "'initial' is also the name of", "00-initial"],
        );
        case(
            "directory-image",
            &|d| {
                write_view(d, "00-initial", &textured(64, 48), &textured(64, 48), ok_json);
                let p = d.join("00-initial").join("left.png");
                std::fs::remove_file(&p).unwrap();
                std::fs::create_dir_all(&p).unwrap();
            },
            &["left.png", "directory"],
        );
        // A good one reads back.
        let dir = base.join("good");
        write_view(&dir, "00-initial", &textured(64, 48), &textured(64, 48), ok_json);
        let v = read_image_session(&dir).unwrap();
        assert_eq!(v.len(), 1);
        assert_eq!(v[0].name, "initial");
        std::fs::remove_dir_all(&base).ok();
    }
}
