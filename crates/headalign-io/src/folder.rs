//! A folder of stereo views, read by one set of rules for `headalign calibrate DIR` and the
//! examples: either an image session ([`crate::session`]: `NN-name/` folders with
//! `left.png`, `right.png` and `view.json`) or a folder of stereo pairs.
//!
//! Stereo pairs: every file whose name contains `left` (any case) and ends in `.png`,
//! `.jpg` or `.jpeg` (any case) is a left image; its partner is the name with the first
//! `left` replaced by `right` (`Left` by `Right`, `LEFT` by `RIGHT`). A left image without
//! a partner is skipped. The pairs are taken in name order (byte order of the names),
//! every [`FolderOptions::every`]-th from the first; a view is named by its left file's
//! stem (`left03.png` is view `left03`). Every pair must have the size of the first, and
//! a folder with no pair is an error. Encoder readings are zero (the files hold none);
//! an image session's views keep the readings of their `view.json`.
//!
//! Degrees of freedom: none (a reader). Pitfall: the folder is told apart by its content,
//! not its name: a folder holding any subfolder with a `view.json` is an image session,
//! and its loose image files are then ignored.

use std::path::Path;

use headalign::AlignError;
use headalign_platform::{Encoders, GrayImage, StereoImages};

use crate::error::FileError;
use crate::session::read_image_session;

/// How a folder of stereo pairs is read.
#[derive(Debug, Clone, PartialEq)]
pub struct FolderOptions {
    /// Take every N-th pair in name order (default 1: every pair). Not used for an image
    /// session.
    pub every: usize,
}

impl Default for FolderOptions {
    fn default() -> Self {
        Self { every: 1 }
    }
}

impl FolderOptions {
    /// Check the options: `every` at least 1.
    pub fn validate(&self) -> Result<(), AlignError> {
        if self.every == 0 {
            return Err(AlignError::InvalidOption("every must be at least 1".into()));
        }
        Ok(())
    }
}

/// What a folder of stereo views holds (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FolderKind {
    /// An image session: subfolders with a `view.json`.
    ImageSession,
    /// Loose stereo pairs `left*` / `right*`.
    StereoPairs,
}

fn cannot_read(dir: &Path, e: std::io::Error) -> FileError {
    FileError::File(format!("cannot read '{}': {e}", dir.display()))
}

/// What `dir` holds; an error if it is not a readable folder.
pub fn folder_kind(dir: &Path) -> Result<FolderKind, FileError> {
    if !dir.is_dir() {
        return Err(FileError::File(format!("'{}' is not a folder", dir.display())));
    }
    let has_session = std::fs::read_dir(dir)
        .map_err(|e| cannot_read(dir, e))?
        .filter_map(Result::ok)
        .any(|e| e.path().join("view.json").exists());
    Ok(if has_session { FolderKind::ImageSession } else { FolderKind::StereoPairs })
}

/// The named stereo views of `dir` (module docs), in order. `progress(i, n)` is called
/// before the `i`-th of `n` stereo pairs is read (not for an image session).
pub fn read_folder(
    dir: &Path,
    options: &FolderOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<Vec<(String, StereoImages)>, FileError> {
    options.validate()?;
    match folder_kind(dir)? {
        FolderKind::ImageSession => {
            let views = read_image_session(dir)?;
            Ok(views.into_iter().map(|v| (v.name, v.images)).collect())
        }
        FolderKind::StereoPairs => read_stereo_pairs(dir, options, progress),
    }
}

/// The left images of a folder of stereo pairs (module docs), sorted, every N-th.
fn left_names(dir: &Path, every: usize) -> Result<Vec<String>, FileError> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .map_err(|e| cannot_read(dir, e))?
        .filter_map(Result::ok)
        .filter_map(|e| e.file_name().into_string().ok())
        .filter(|n| {
            let l = n.to_ascii_lowercase();
            l.contains("left") && (l.ends_with(".png") || l.ends_with(".jpg") || l.ends_with(".jpeg"))
        })
        .collect();
    names.sort();
    Ok(names.into_iter().step_by(every.max(1)).collect())
}

/// The stereo pairs of `dir` (module docs), in order; `progress` as in [`read_folder`].
pub fn read_stereo_pairs(
    dir: &Path,
    options: &FolderOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<Vec<(String, StereoImages)>, FileError> {
    options.validate()?;
    let names = left_names(dir, options.every)?;
    let mut out: Vec<(String, StereoImages)> = Vec::new();
    for (i, name) in names.iter().enumerate() {
        progress(i, names.len());
        let partner =
            name.replacen("left", "right", 1).replacen("Left", "Right", 1).replacen("LEFT", "RIGHT", 1);
        let (lp, rp) = (dir.join(name), dir.join(&partner));
        if !rp.exists() {
            continue;
        }
        let load = |p: &Path| GrayImage::load(p).map_err(|e| FileError::File(e.to_string()));
        let (left, right) = (load(&lp)?, load(&rp)?);
        let pair = StereoImages::new(Encoders::default(), left, right)
            .map_err(|e| FileError::File(format!("'{}' and '{}': {e}", lp.display(), rp.display())))?;
        if let Some((_, first)) = out.first()
            && first.image_size() != pair.image_size()
        {
            return Err(FileError::File(format!(
                "'{}' has a different size from the first pair",
                lp.display()
            )));
        }
        let stem = name.rsplit_once('.').map_or(name.as_str(), |(s, _)| s).to_string();
        out.push((stem, pair));
    }
    if out.is_empty() {
        return Err(FileError::File(format!(
            "'{}' holds neither an image session (NN-name/ with left.png, right.png, view.json) nor stereo pairs (files named left*/right*)",
            dir.display()
        )));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp(name: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("headalign-folder-{}-{name}", std::process::id()));
        std::fs::remove_dir_all(&d).ok();
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn image(w: u32, h: u32, k: u32) -> GrayImage {
        GrayImage::new(w, h, (0..w * h).map(|i| ((i * 7919 + k) % 251) as u8).collect()).unwrap()
    }

    /// The rules of the module docs: case-insensitive `left`, partner by name, a missing
    /// partner skipped, name order, every N-th, views named by the left stem.
    #[test]
    fn pairs_follow_the_rules() {
        let d = temp("rules");
        for (l, r) in [("left01.png", "right01.png"), ("Left00.JPG", "Right00.JPG"), ("left02.png", "")] {
            image(32, 24, 1).save(&d.join(l)).unwrap();
            if !r.is_empty() {
                image(32, 24, 2).save(&d.join(r)).unwrap();
            }
        }
        std::fs::write(d.join("notes.txt"), "x").unwrap();
        let mut calls = Vec::new();
        let views = read_folder(&d, &FolderOptions::default(), &mut |i, n| calls.push((i, n))).unwrap();
        let names: Vec<&str> = views.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(names, ["Left00", "left01"]);
        assert_eq!(calls, [(0, 3), (1, 3), (2, 3)]);
        let every2 = read_folder(&d, &FolderOptions { every: 2 }, &mut |_, _| ()).unwrap();
        assert_eq!(every2.iter().map(|(n, _)| n.as_str()).collect::<Vec<_>>(), ["Left00"]);
        assert!(FolderOptions { every: 0 }.validate().is_err());
        std::fs::remove_dir_all(&d).ok();
    }

    #[test]
    fn bad_folders_are_named() {
        let d = temp("bad");
        let err =
            |dir: &Path| read_folder(dir, &FolderOptions::default(), &mut |_, _| ()).unwrap_err().to_string();
        assert!(err(&d).contains("holds neither an image session"));
        assert!(err(&d.join("missing")).contains("is not a folder"));
        image(32, 24, 1).save(&d.join("left0.png")).unwrap();
        image(32, 24, 2).save(&d.join("right0.png")).unwrap();
        image(40, 24, 1).save(&d.join("left1.png")).unwrap();
        image(40, 24, 2).save(&d.join("right1.png")).unwrap();
        assert!(err(&d).contains("left1.png' has a different size from the first pair"));
        std::fs::create_dir_all(d.join("00-a")).unwrap();
        std::fs::write(d.join("00-a/view.json"), "{").unwrap();
        assert_eq!(folder_kind(&d).unwrap(), FolderKind::ImageSession);
        assert!(err(&d).contains("view.json"));
        std::fs::remove_dir_all(&d).ok();
    }
}
