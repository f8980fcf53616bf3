//! EuRoC / ASL folders ([`super`] module docs) and their `sensor.yaml` lens files.
//!
//! ## The folder
//!
//! ```text
//! SEQ/mav0/cam0/data.csv      #timestamp [ns],filename   then one row per image
//! SEQ/mav0/cam0/data/<filename>   8-bit grey PNG
//! SEQ/mav0/cam0/sensor.yaml   the camera's calibration (below)
//! SEQ/mav0/cam1/...           the same for the right camera
//! ```
//!
//! `SEQ` or `SEQ/mav0` may be given. The cameras are `cam0` (left) and `cam1` (right)
//! unless other folder names are given ([`super::RecordingOptions::topics`]). The images
//! are paired by timestamp (the rig is hardware-synchronised: the stamps are equal).
//! EuRoC folders hold no head joints: every encoder reading is zero.
//!
//! ## `sensor.yaml`
//!
//! Kalibr's camera description as EuRoC ships it, `%YAML:1.0` first:
//! `camera_model: pinhole`, `intrinsics: [fu, fv, cu, cv]`, `distortion_model:
//! radial-tangential` (also written `radtan` or `plumb_bob`) with `distortion_coefficients:
//! [k1, k2, p1, p2]`, or `equidistant` with `[k1, k2, k3, k4]`; or `camera_model: ds`
//! with `intrinsics: [xi, alpha, fu, fv, cu, cv]` (every form is the lens table's
//! `KalibrForm`); and `resolution: [width, height]`; the rest (`T_BS`, `rate_hz`) is not read. The reader is a small parser of these top-level keys (flow lists may span lines,
//! `#` starts a comment), not a general YAML parser.
//!
//! Degrees of freedom: none. Units: stamps in nanoseconds, intrinsics in pixels.
//! Pitfalls: the coefficients belong to the intrinsics in the same file (see
//! [`headalign::calibrate::LensModel`]); other models (Kalibr's `fov`) are refused, not
//! approximated.

use std::path::{Path, PathBuf};

use headalign_geometry::camera::Intrinsics;
use headalign_geometry::distortion::{Distortion, LensKind};
use headalign_geometry::lens::{KalibrForm, MODELS};
use headalign_platform::{Encoders, GrayImage};

use super::{Recording, RecordingFormat, RecordingOptions, Stamped, build_views, pair_streams, select_pairs};
use headalign::AlignError;
use headalign::calibrate::LensModel;

use crate::FileError;

/// The folder holding the camera folders: `path/mav0` if it exists, else `path`.
pub fn camera_root(path: &Path) -> PathBuf {
    let mav0 = path.join("mav0");
    if mav0.is_dir() { mav0 } else { path.to_path_buf() }
}

/// The camera folder names (left, right) the options select.
fn cameras(options: &RecordingOptions) -> [String; 2] {
    options.topics.clone().unwrap_or_else(|| ["cam0".to_string(), "cam1".to_string()])
}

/// The `sensor.yaml` of both cameras of the EuRoC folder at `path`.
pub fn sensor_yaml_paths(path: &Path, options: &RecordingOptions) -> [PathBuf; 2] {
    let root = camera_root(path);
    cameras(options).map(|c| root.join(c).join("sensor.yaml"))
}

/// Parse a camera's `data.csv`: (stamp ns, file name) per row; `origin` names the file.
pub fn parse_data_csv(text: &str, origin: &str) -> Result<Vec<(i64, String)>, AlignError> {
    let mut rows = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = |why: &str| AlignError::Recording(format!("'{origin}' line {}: {why}", i + 1));
        let Some((stamp, name)) = line.split_once(',') else {
            return Err(bad("expected 'timestamp,filename'"));
        };
        let stamp: i64 =
            stamp.trim().parse().map_err(|_| bad("the timestamp is not an integer of nanoseconds"))?;
        let name = name.trim();
        if name.is_empty() || Path::new(name).is_absolute() || name.split(['/', '\\']).any(|c| c == "..") {
            return Err(bad("the file name is empty or leaves the data folder"));
        }
        rows.push((stamp, name.to_string()));
    }
    Ok(rows)
}

/// Read an EuRoC folder ([`super::read_recording`] checked the options).
pub(crate) fn read(path: &Path, options: &RecordingOptions) -> Result<Recording, AlignError> {
    if !options.joints.is_empty() {
        return Err(AlignError::Recording(format!(
            "'{}' is an EuRoC folder: it holds no joint states to map onto the head's joints",
            path.display()
        )));
    }
    let root = camera_root(path);
    let names = cameras(options);
    let mut rows = Vec::new();
    for cam in &names {
        let csv = root.join(cam).join("data.csv");
        let text = std::fs::read_to_string(&csv).map_err(|e| {
            AlignError::Recording(format!(
                "EuRoC folder '{}' has no camera '{cam}' ('{}': {e})",
                root.display(),
                csv.display()
            ))
        })?;
        rows.push(parse_data_csv(&text, &csv.display().to_string())?);
    }
    let stream = |r: &[(i64, String)]| -> Vec<Stamped> {
        r.iter().enumerate().map(|(index, (stamp_ns, _))| Stamped { stamp_ns: *stamp_ns, index }).collect()
    };
    let mut notes = Vec::new();
    let tolerance_ns = (options.pair_tolerance_s * 1e9).round() as i64;
    let pairs = pair_streams(stream(&rows[0]), stream(&rows[1]), tolerance_ns, &names, &mut notes)?;
    let selected = select_pairs(&pairs, options)?;
    let load = |side: usize, index: usize| -> Result<GrayImage, AlignError> {
        let p = root.join(&names[side]).join("data").join(&rows[side][index].1);
        GrayImage::load(&p).map_err(|e| AlignError::Recording(e.to_string()))
    };
    let items = selected.iter().map(|p| {
        Ok((
            p.left.stamp_ns.to_string(),
            Encoders::default(),
            load(0, p.left.index)?,
            load(1, p.right.index)?,
        ))
    });
    let views = build_views(path, items, &mut notes)?;
    Ok(Recording {
        format: RecordingFormat::Euroc,
        source: path.to_path_buf(),
        topics: names,
        pairs_found: pairs.len(),
        views,
        notes,
    })
}

/// The text after a top-level `key:` (to the end of the line, or of its flow list across
/// lines), comments removed.
fn yaml_value(text: &str, key: &str) -> Option<String> {
    let mut lines = text.lines();
    let first = lines.by_ref().find_map(|l| l.strip_prefix(key)?.trim_start().strip_prefix(':'))?;
    let uncomment = |l: &str| l.split('#').next().unwrap_or("").to_string();
    let mut value = uncomment(first);
    if value.contains('[') {
        for l in lines {
            if value.contains(']') {
                break;
            }
            value.push(' ');
            value.push_str(&uncomment(l));
        }
    }
    Some(value.trim().to_string())
}

/// The numbers of a flow list `[a, b, ...]`.
fn yaml_numbers(value: &str) -> Option<Vec<f64>> {
    let inner = value.strip_prefix('[')?.split(']').next()?;
    inner.split(',').filter(|s| !s.trim().is_empty()).map(|s| s.trim().parse::<f64>().ok()).collect()
}

/// A camera's lens model and resolution from the text of a Kalibr/EuRoC `sensor.yaml`
/// (module docs); `origin` names the file in messages.
pub fn parse_sensor_yaml(text: &str, origin: &str) -> Result<(LensModel, Option<[u32; 2]>), AlignError> {
    let bad = |m: String| AlignError::InvalidOption(format!("'{origin}': {m}"));
    let numbers = |key: &str, n: usize| -> Result<Vec<f64>, AlignError> {
        let v = yaml_value(text, key).ok_or_else(|| bad(format!("no '{key}'")))?;
        let nums = yaml_numbers(&v).ok_or_else(|| bad(format!("'{key}' is not a list of numbers: {v}")))?;
        if nums.len() != n || nums.iter().any(|x| !x.is_finite()) {
            return Err(bad(format!("'{key}' needs {n} finite numbers, got {v}")));
        }
        Ok(nums)
    };
    let scalar = |key: &str| yaml_value(text, key).map(|v| v.trim_matches(['"', '\'']).to_string());
    // Kalibr's camera models, from the lens table's Kalibr forms: `pinhole` (intrinsics fu
    // fv pu pv, then a distortion model) or a model of its own (the double sphere's `ds`:
    // intrinsics xi alpha fu fv pu pv).
    let camera_model = scalar("camera_model").unwrap_or_else(|| "pinhole".into());
    let forms: Vec<(LensKind, KalibrForm)> =
        MODELS.iter().filter_map(|m| m.names().kalibr.map(|f| (m.kind(), f))).collect();
    let mine: Vec<(LensKind, KalibrForm)> =
        forms.iter().copied().filter(|(_, f)| f.camera_model == camera_model).collect();
    let Some(&(_, first)) = mine.first() else {
        let mut known: Vec<&str> = forms.iter().map(|(_, f)| f.camera_model).collect();
        known.dedup();
        return Err(bad(format!("camera_model '{camera_model}' is not supported ({})", known.join(", "))));
    };
    let all = numbers("intrinsics", first.intrinsics.len() + 4)?;
    let k = &all[all.len() - 4..];
    let k = Intrinsics::new(k[0], k[1], k[2], k[3]);
    if !(k.fx > 0.0 && k.fy > 0.0) {
        return Err(bad(format!("intrinsics: focal lengths must be positive, got {} and {}", k.fx, k.fy)));
    }
    let read = |kind: LensKind, names: &[&str], values: &[f64]| {
        Distortion::from_named_values(kind, names.iter().copied().zip(values.iter().copied()))
            .and_then(|d| d.validate().map(|()| d))
            .map_err(|e| bad(e.to_string()))
    };
    let distortion = match (mine.as_slice(), scalar("distortion_model").as_deref()) {
        // A camera model of one lens model (`ds`): its parameters lead the intrinsics.
        ([(kind, form)], _) => read(*kind, form.intrinsics, &all[..form.intrinsics.len()])?,
        (_, Some("none") | None) => Distortion::default(),
        (_, Some(name)) => {
            let supported = || {
                let list: Vec<String> = mine
                    .iter()
                    .filter(|(_, f)| !f.distortion_coeffs.is_empty())
                    .map(|(_, f)| format!("{}: {}", f.distortion_model, f.distortion_coeffs.join(", ")))
                    .collect();
                bad(format!("distortion_model '{name}' is not supported ({})", list.join("; ")))
            };
            let kind = LensKind::parse(name).ok_or_else(supported)?;
            let (_, form) = mine.iter().find(|(k, _)| *k == kind).ok_or_else(supported)?;
            let d = numbers("distortion_coefficients", form.distortion_coeffs.len())?;
            read(kind, form.distortion_coeffs, &d)?
        }
    };
    let resolution = match yaml_value(text, "resolution") {
        Some(_) => {
            let r = numbers("resolution", 2)?;
            if r.iter().any(|&v| !(1.0..=100_000.0).contains(&v) || v.fract() != 0.0) {
                return Err(bad(format!("resolution {r:?} is not an image size")));
            }
            Some([r[0] as u32, r[1] as u32])
        }
        None => None,
    };
    Ok((LensModel { k, distortion }, resolution))
}

/// The lenses of two `sensor.yaml` files (left, right), each file's `resolution` (where
/// it gives one) checked against the images' size `image_size`, pixels.
pub fn read_sensor_yaml_pair(
    paths: &[PathBuf; 2],
    image_size: [u32; 2],
) -> Result<[LensModel; 2], FileError> {
    let read = |p: &PathBuf| -> Result<LensModel, FileError> {
        let (lens, resolution) = read_sensor_yaml(p)?;
        match resolution {
            Some(r) if r != image_size => Err(FileError::File(format!(
                "'{}' describes a {}x{} camera but the images are {}x{}",
                p.display(),
                r[0],
                r[1],
                image_size[0],
                image_size[1]
            ))),
            _ => Ok(lens),
        }
    };
    Ok([read(&paths[0])?, read(&paths[1])?])
}

/// Read a `sensor.yaml` file.
pub fn read_sensor_yaml(path: &Path) -> Result<(LensModel, Option<[u32; 2]>), AlignError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| AlignError::InvalidOption(format!("cannot read '{}': {e}", path.display())))?;
    parse_sensor_yaml(&text, &path.display().to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The dataset's own file (Kimera-VIO's copy of V1_01_easy's cam0), as text.
    const CAM0: &str = "%YAML:1.0
# General sensor definitions.
camera_id: left_cam

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
";

    #[test]
    fn the_datasets_sensor_yaml_reads() {
        let (lens, res) = parse_sensor_yaml(CAM0, "cam0.yaml").unwrap();
        assert_eq!(res, Some([752, 480]));
        assert_eq!((lens.k.fx, lens.k.fy, lens.k.cx, lens.k.cy), (458.654, 457.296, 367.215, 248.375));
        assert_eq!(lens.distortion.to_opencv(), [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0]);
        let (fisheye, _) =
            parse_sensor_yaml(&CAM0.replace("radial-tangential", "equidistant"), "c.yaml").unwrap();
        assert_eq!(fisheye.distortion.kind, LensKind::Equidistant);
        assert_eq!(fisheye.distortion.coefficients(), [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]);
        let e = parse_sensor_yaml(&CAM0.replace("radial-tangential", "fov"), "c.yaml").unwrap_err();
        assert!(e.to_string().contains("'c.yaml': distortion_model 'fov' is not supported"), "{e}");
        let e = parse_sensor_yaml(&CAM0.replace("[458.654, 457.296, ", "[458.654, "), "c.yaml").unwrap_err();
        assert!(e.to_string().contains("'intrinsics' needs 4"), "{e}");
        let e = parse_sensor_yaml("%YAML:1.0\n", "c.yaml").unwrap_err();
        assert!(e.to_string().contains("no 'intrinsics'"), "{e}");
    }

    #[test]
    fn data_csv_rows_and_bad_lines() {
        let rows = parse_data_csv(
            "#timestamp [ns],filename\n1403715273262142976,1403715273262142976.png\n\n",
            "d.csv",
        )
        .unwrap();
        assert_eq!(rows, [(1_403_715_273_262_142_976, "1403715273262142976.png".to_string())]);
        for (text, why) in [("12\n", "expected"), ("x,a.png\n", "integer"), ("1,../a.png\n", "leaves")] {
            let e = parse_data_csv(text, "d.csv").unwrap_err().to_string();
            assert!(e.contains("'d.csv' line 1") && e.contains(why), "{e}");
        }
    }
}
