//! Reading sessions back: `session.json` ([`read_session_info`]), the view folders of an
//! image session ([`read_image_session`], each image checked) or of a point session
//! ([`read_point_session`]), and the image front end over recorded views
//! ([`track_session`]). Every bad input is an error naming the file and the problem.
use std::path::{Path, PathBuf};

use headalign::AlignError;
use headalign::tracking::{FrontEndOptions, Tracker};
use headalign_platform::{GrayImage, StereoImages};

use super::format::*;
use crate::observations::View;
/// Read a session's `session.json`.
pub fn read_session_info(dir: &Path) -> Result<SessionInfo, AlignError> {
    let path = dir.join("session.json");
    let text = std::fs::read_to_string(&path).map_err(|e| {
        AlignError::Images(format!(
            "cannot read '{}': {e} (is '{}' a session folder?)",
            path.display(),
            dir.display()
        ))
    })?;
    let info: SessionInfo =
        serde_json::from_str(&text).map_err(|e| AlignError::Images(format!("'{}': {e}", path.display())))?;
    if info.format != SESSION_FORMAT {
        return Err(AlignError::Images(format!(
            "'{}': unsupported format '{}', expected '{SESSION_FORMAT}'",
            path.display(),
            info.format
        )));
    }
    if !(info.rotation_deg.is_finite() && info.rotation_deg > 0.0 && info.rotation_deg < 90.0) {
        return Err(AlignError::Images(format!(
            "'{}': rotation_deg must be in (0, 90), got {}",
            path.display(),
            info.rotation_deg
        )));
    }
    let [w, h] = info.image_size;
    if w == 0 || h == 0 || w > 100_000 || h > 100_000 {
        return Err(AlignError::Images(format!(
            "'{}': image_size {w} x {h} is not a valid image size",
            path.display()
        )));
    }
    Ok(info)
}

/// Read and check one `view.json`.
pub fn read_view_meta(path: &Path) -> Result<ViewMeta, AlignError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| AlignError::Images(format!("cannot read '{}': {e}", path.display())))?;
    parse_view_json(&text, &path.display().to_string())
}

fn load(path: &Path) -> Result<GrayImage, AlignError> {
    let img = GrayImage::load(path).map_err(|e| AlignError::Images(e.to_string()))?;
    check_image(&img, &path.display().to_string())?;
    Ok(img)
}

/// Load the images of one view folder, checking them (and against `first_size`).
pub(super) fn load_view(
    folder: &Path,
    meta: ViewMeta,
    first_size: Option<[u32; 2]>,
) -> Result<RecordedView, AlignError> {
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
    if let Some([w, h]) = first_size
        && [w, h] != left.size()
    {
        return Err(AlignError::Images(format!(
            "'{}' is {}x{} but the first view's images are {w}x{h}",
            lp.display(),
            left.width(),
            left.height(),
        )));
    }
    let images = StereoImages::new(meta.encoders, left, right)?;
    Ok(RecordedView { name: meta.name, stage: meta.stage, folder: folder.to_path_buf(), images })
}

/// The view folders of `dir` (those with a `view.json`), sorted, each with its
/// `view.json`; view names made unique (a name an earlier view already has is replaced by
/// the folder's name: sessions written before names were unique repeat the names of a
/// stage that ran twice).
fn read_view_folders(dir: &Path) -> Result<Vec<(PathBuf, ViewMeta)>, AlignError> {
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
    let mut out: Vec<(PathBuf, ViewMeta)> = Vec::new();
    for folder in folders {
        let meta_path = folder.join("view.json");
        let mut meta = read_view_meta(&meta_path)?;
        if out.iter().any(|(_, m)| m.name == meta.name) {
            let folder_name = folder.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
            if let Some((other, _)) = out.iter().find(|(_, m)| m.name == folder_name) {
                return Err(AlignError::Images(format!(
                    "'{}': view name '{}' is also the name of '{}', and so is its folder name",
                    meta_path.display(),
                    meta.name,
                    other.display()
                )));
            }
            meta.name = folder_name;
        }
        out.push((folder, meta));
    }
    Ok(out)
}

/// Read every view folder of `dir` in order (all stages; see
/// [`RecordedView::is_verge_tilt`]). A view whose name an earlier view already has is
/// known by its folder name (`21-pan-1`).
pub fn read_image_session(dir: &Path) -> Result<Vec<RecordedView>, AlignError> {
    let mut views: Vec<RecordedView> = Vec::new();
    for (folder, meta) in read_view_folders(dir)? {
        let first = views.first().map(|v| v.images.image_size());
        views.push(load_view(&folder, meta, first)?);
    }
    Ok(views)
}

/// True if `dir` is a point-mode session: its first view folder's `view.json` holds the
/// tracked points (`capture`) and the folder no `left.png`.
pub fn is_point_session(dir: &Path) -> bool {
    read_view_folders(dir)
        .ok()
        .and_then(|f| f.into_iter().next())
        .is_some_and(|(folder, meta)| meta.capture.is_some() && !folder.join("left.png").exists())
}

/// Read every view of a point-mode session (`view.json` with `capture`), in order; an
/// error names a view without tracked points.
pub fn read_point_session(dir: &Path) -> Result<Vec<RecordedPoints>, AlignError> {
    read_view_folders(dir)?
        .into_iter()
        .map(|(folder, meta)| {
            let Some(capture) = meta.capture else {
                return Err(AlignError::Images(format!(
                    "'{}' holds no tracked points (`capture`): not a point-mode session",
                    folder.join("view.json").display()
                )));
            };
            let view = View { name: meta.name, capture };
            Ok(RecordedPoints { stage: meta.stage, folder, view })
        })
        .collect()
}

/// Run the image front end over recorded views (the first is the tracking reference).
pub fn track_session(views: &[RecordedView], options: &FrontEndOptions) -> Result<Vec<View>, AlignError> {
    track_session_reporting(views, options).map(|(v, _)| v)
}

/// [`track_session`] with the front end's report of each view (its localisation noise is
/// keyed by the views' names: [`headalign::verge_tilt::model_fit`]).
pub fn track_session_reporting(
    views: &[RecordedView],
    options: &FrontEndOptions,
) -> Result<(Vec<View>, Vec<headalign::tracking::ViewTracking>), AlignError> {
    let mut tracker = Tracker::new(options.clone())?;
    views
        .iter()
        .map(|v| {
            let (capture, report) = tracker.track(&v.images, &v.name).map_err(|e| {
                AlignError::Images(format!("view '{}' ({}): {e}", v.name, v.folder.display()))
            })?;
            Ok((View { name: v.name.clone(), capture }, report))
        })
        .collect::<Result<Vec<_>, AlignError>>()
        .map(|pairs| pairs.into_iter().unzip())
}
