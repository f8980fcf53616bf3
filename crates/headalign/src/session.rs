//! Recorded image sessions on disk (DESIGN.md section 3): one folder per captured view,
//! `NN-name/left.png`, `right.png` and `view.json` (`name`, `encoders` in degrees), in
//! capture order (the folders sort by their `NN` prefix). `headalign demo --images --save
//! DIR` writes them; [`read_image_session`] reads them back and [`track_session`] runs the
//! image front end over them, giving the views the estimation consumes, exactly as the
//! live run did (same images, same order, same tracker: the same observations).
//!
//! Every bad input is an error naming the file and the problem: a missing or unreadable
//! image, a malformed `view.json`, left and right images of different sizes, a view whose
//! size differs from the first, a blank (textureless) image.

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

#[derive(Deserialize)]
struct ViewFile {
    name: String,
    encoders: Encoders,
}

fn load(path: &Path) -> Result<GrayImage, AlignError> {
    let img = GrayImage::load(path).map_err(|e| AlignError::Images(e.to_string()))?;
    let n = img.pixels().len() as f64;
    let mean = img.pixels().iter().map(|&v| f64::from(v)).sum::<f64>() / n;
    let var = img.pixels().iter().map(|&v| (f64::from(v) - mean).powi(2)).sum::<f64>() / n;
    if var.sqrt() < MIN_IMAGE_STD {
        return Err(AlignError::Images(format!(
            "'{}' is blank: grey-level standard deviation {:.2} (< {MIN_IMAGE_STD}), nothing to match",
            path.display(),
            var.sqrt()
        )));
    }
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
        let meta: ViewFile = serde_json::from_str(&text)
            .map_err(|e| AlignError::Images(format!("'{}': {e}", meta_path.display())))?;
        if !meta.encoders.is_finite() {
            return Err(AlignError::Images(format!(
                "'{}': encoder readings must be finite",
                meta_path.display()
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
        // A good one reads back.
        let dir = base.join("good");
        write_view(&dir, "00-initial", &textured(64, 48), &textured(64, 48), ok_json);
        let v = read_image_session(&dir).unwrap();
        assert_eq!(v.len(), 1);
        assert_eq!(v[0].name, "initial");
        std::fs::remove_dir_all(&base).ok();
    }
}
