//! Calibration files read back into the library's [`StereoCalibration`]: the formats
//! [`crate::export`] writes, and the same formats written by other tools
//! ([`read_calibration`] tells them apart by content).
//!
//! - headalign's JSON (`format: headalign-calibration/1`, [`from_json`]);
//! - an OpenCV stereo FileStorage YAML (`M1 D1 M2 D2 R T`, with `distortion_model`, or
//!   `distortion_model_1`/`_2` per camera; [`from_opencv_yaml`]), as OpenCV's
//!   `stereo_calib` sample and headalign's `opencv_stereo.yaml` write it;
//! - a Kalibr `camchain.yaml` (`cam0` left, `cam1` right with `T_cn_cnm1` =
//!   `right_from_left`; `camera_model` `pinhole` with `distortion_model` `radtan` or
//!   `equidistant`, or `ds`; [`from_kalibr_camchain`]).
//!
//! What it computes: nothing is estimated. Units: pixels for the intrinsics; the rig
//! translation is in metres unless the file says `baselines` (the JSON's
//! `translation_unit`, the comment headalign writes into its YAML files). Sigmas are read
//! from the JSON only. The image size is the file's (`image_size`, `image_width` and
//! `image_height`, Kalibr's `resolution`), or `[0, 0]` where a file has none (OpenCV's
//! sample): the caller then takes it from the images ([`StereoCalibration::image_size`]).
//!
//! Pitfalls: the YAML readers are small parsers of the fixed layouts these tools write
//! (OpenCV's `!!opencv-matrix` blocks or inline lists, Kalibr's `key: [..]` lists and
//! `T_cn_cnm1` rows), not general YAML parsers; a rotation that is not orthonormal to 1e-6
//! is an error, never silently projected.

use std::path::Path;

use headalign::AlignError;
use headalign::calibration::{IntrinsicSigmas, StereoCalibration, TranslationUnit};
use headalign::rig::{opencv_matrix, read_opencv_lenses, scalar};
use headalign_geometry::camera::Intrinsics;
use headalign_geometry::distortion::{Distortion, LensKind};
use nalgebra::{Isometry3, Matrix3, Matrix4, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde_json::Value;

/// Read a calibration file of any format of the module docs.
pub fn read_calibration(path: &Path) -> Result<StereoCalibration, AlignError> {
    let origin = path.display().to_string();
    let text = std::fs::read_to_string(path)
        .map_err(|e| AlignError::InvalidOption(format!("cannot read {origin}: {e}")))?;
    if text.trim_start().starts_with('{') {
        let v: Value = serde_json::from_str(&text)
            .map_err(|e| AlignError::InvalidOption(format!("{origin}: JSON: {e}")))?;
        return from_json(&v, &origin);
    }
    if text.lines().any(|l| l.starts_with("cam0:")) {
        return from_kalibr_camchain(&text, &origin);
    }
    if opencv_matrix(&text, "M1").is_some() {
        return from_opencv_yaml(&text, &origin);
    }
    Err(AlignError::InvalidOption(format!(
        "{origin}: not a calibration file headalign reads (headalign JSON, OpenCV stereo YAML with M1 D1 M2 D2 R T, or a Kalibr camchain with cam0 and cam1)"
    )))
}

/// The rig pose from a rotation (row-major) and translation, the rotation checked.
fn pose(r: &[f64], t: &[f64], origin: &str) -> Result<Isometry3<f64>, AlignError> {
    let bad = |m: String| AlignError::InvalidOption(format!("{origin}: {m}"));
    if r.len() != 9 || t.len() != 3 {
        return Err(bad(format!(
            "the rig needs a 3x3 R and a 3-vector T, got {} and {} numbers",
            r.len(),
            t.len()
        )));
    }
    let m = Matrix3::from_row_slice(r);
    let orth = (m.transpose() * m - Matrix3::identity()).abs().max();
    if !(orth < 1e-6 && m.determinant() > 0.0) {
        return Err(bad(format!(
            "R is not a rotation (|R^T R - I| = {orth:.2e}, det {:.6})",
            m.determinant()
        )));
    }
    if !t.iter().all(|v| v.is_finite()) {
        return Err(bad("T is not finite".into()));
    }
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(m));
    Ok(Isometry3::from_parts(Translation3::new(t[0], t[1], t[2]), q))
}

/// `baselines` when the text says so (headalign's YAML comment), metres otherwise.
fn unit_of(text: &str) -> TranslationUnit {
    if text.lines().take(3).any(|l| l.starts_with('#') && l.contains("translation unit: baselines")) {
        TranslationUnit::Baselines
    } else {
        TranslationUnit::Metres
    }
}

/// An OpenCV stereo FileStorage YAML (module docs).
pub fn from_opencv_yaml(text: &str, origin: &str) -> Result<StereoCalibration, AlignError> {
    let [l, r] = read_opencv_lenses(text, origin)?;
    let need = |name: &str| {
        opencv_matrix(text, name)
            .ok_or_else(|| AlignError::InvalidOption(format!("{origin}: no {name} matrix")))
    };
    let right_from_left = pose(&need("R")?, &need("T")?, origin)?;
    let size = |k: &str| scalar(text, k).and_then(|v| v.parse::<u32>().ok()).unwrap_or(0);
    Ok(StereoCalibration {
        image_size: [size("image_width"), size("image_height")],
        left: l.k,
        right: r.k,
        sigmas: [IntrinsicSigmas::default(); 2],
        right_from_left,
        unit: unit_of(text),
        distortion: [l.distortion, r.distortion],
    })
}

/// The numbers of an inline list `[a, b, ...]` in `line` after its key.
fn list(line: &str) -> Option<Vec<f64>> {
    let open = line.find('[')?;
    let close = line[open..].find(']')? + open;
    let inner = line[open + 1..close].trim();
    if inner.is_empty() {
        return Some(Vec::new());
    }
    inner.split(',').map(|v| v.trim().parse::<f64>().ok()).collect()
}

/// The lines of the top-level block `name:` of a camchain.
fn block<'a>(text: &'a str, name: &str) -> Option<Vec<&'a str>> {
    let mut lines = text.lines().skip_while(|l| !l.starts_with(&format!("{name}:"))).skip(1);
    let mut out = Vec::new();
    for l in lines.by_ref() {
        if !l.starts_with(' ') && !l.starts_with('-') && !l.trim().is_empty() && !l.starts_with('#') {
            break;
        }
        out.push(l);
    }
    (!out.is_empty()).then_some(out)
}

/// The value of `key:` in a camchain block (the rest of its line).
fn value<'a>(lines: &[&'a str], key: &str) -> Option<&'a str> {
    let k = format!("{key}:");
    lines
        .iter()
        .find_map(|l| l.trim_start().strip_prefix(k.as_str()))
        .map(|v| v.split('#').next().unwrap_or("").trim())
}

/// One camera of a Kalibr camchain block: intrinsics, lens and resolution.
fn kalibr_camera(
    lines: &[&str],
    origin: &str,
    cam: &str,
) -> Result<(Intrinsics, Distortion, [u32; 2]), AlignError> {
    let bad = |m: String| AlignError::InvalidOption(format!("{origin}: {cam}: {m}"));
    let get = |k: &str| value(lines, k).ok_or_else(|| bad(format!("no {k}")));
    let intr = list(get("intrinsics")?).ok_or_else(|| bad("intrinsics are not a list of numbers".into()))?;
    let coeffs = value(lines, "distortion_coeffs").and_then(list).unwrap_or_default();
    let camera_model = get("camera_model")?;
    let (k, distortion) = match (camera_model, intr.as_slice()) {
        ("pinhole", &[fx, fy, cx, cy]) => {
            let model = value(lines, "distortion_model").unwrap_or("none");
            let kind = match model {
                "none" => LensKind::Pinhole,
                m => LensKind::parse(m)
                    .ok_or_else(|| bad(format!("distortion model '{m}' is not supported")))?,
            };
            let d = if kind == LensKind::Pinhole {
                Distortion::zero(LensKind::RadialTangential)
            } else {
                Distortion::from_coefficients(kind, &coeffs).map_err(|e| bad(e.to_string()))?
            };
            (Intrinsics::new(fx, fy, cx, cy), d)
        }
        ("ds", &[xi, alpha, fx, fy, cx, cy]) => {
            (Intrinsics::new(fx, fy, cx, cy), Distortion::double_sphere(xi, alpha))
        }
        (m, v) => {
            return Err(bad(format!(
                "camera model '{m}' with {} intrinsics is not supported (pinhole with 4, ds with 6)",
                v.len()
            )));
        }
    };
    let res = value(lines, "resolution").and_then(list).unwrap_or_default();
    let size = match res.as_slice() {
        &[w, h] if w >= 0.0 && h >= 0.0 => [w as u32, h as u32],
        _ => [0, 0],
    };
    Ok((k, distortion, size))
}

/// A Kalibr `camchain.yaml` (module docs).
pub fn from_kalibr_camchain(text: &str, origin: &str) -> Result<StereoCalibration, AlignError> {
    let bad = |m: String| AlignError::InvalidOption(format!("{origin}: {m}"));
    let cam0 = block(text, "cam0").ok_or_else(|| bad("no cam0".into()))?;
    let cam1 =
        block(text, "cam1").ok_or_else(|| bad("no cam1 (a stereo camchain has two cameras)".into()))?;
    let (kl, dl, size) = kalibr_camera(&cam0, origin, "cam0")?;
    let (kr, dr, _) = kalibr_camera(&cam1, origin, "cam1")?;
    let start = cam1
        .iter()
        .position(|l| l.trim_start().starts_with("T_cn_cnm1:"))
        .ok_or_else(|| bad("cam1 has no T_cn_cnm1".into()))?;
    let rows: Vec<Vec<f64>> = cam1[start + 1..].iter().take(4).filter_map(|l| list(l)).collect();
    if rows.len() != 4 || rows.iter().any(|r| r.len() != 4) {
        return Err(bad("T_cn_cnm1 is not a 4x4 matrix of 4 rows [a, b, c, d]".into()));
    }
    let m = Matrix4::from_fn(|i, j| rows[i][j]);
    let r: Vec<f64> = (0..3).flat_map(|i| (0..3).map(move |j| m[(i, j)])).collect();
    let t = Vector3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]);
    Ok(StereoCalibration {
        image_size: size,
        left: kl,
        right: kr,
        sigmas: [IntrinsicSigmas::default(); 2],
        right_from_left: pose(&r, t.as_slice(), origin)?,
        unit: unit_of(text),
        distortion: [dl, dr],
    })
}

/// headalign's calibration JSON (`headalign-calibration/1`, [`crate::export`]).
pub fn from_json(v: &Value, origin: &str) -> Result<StereoCalibration, AlignError> {
    let bad = |m: &str| AlignError::InvalidOption(format!("{origin}: {m}"));
    if v["format"] != "headalign-calibration/1" {
        return Err(bad("not a headalign-calibration/1 file"));
    }
    let num = |x: &Value, what: &str| x.as_f64().ok_or_else(|| bad(&format!("{what} is not a number")));
    let nums = |x: &Value, what: &str| -> Result<Vec<f64>, AlignError> {
        x.as_array()
            .ok_or_else(|| bad(&format!("{what} is not a list")))?
            .iter()
            .map(|e| num(e, what))
            .collect()
    };
    let camera = |c: &Value, side: &str| -> Result<(Intrinsics, IntrinsicSigmas, Distortion), AlignError> {
        let k = Intrinsics {
            fx: num(&c["fx"], &format!("{side}.fx"))?,
            fy: num(&c["fy"], &format!("{side}.fy"))?,
            skew: num(&c["skew"], &format!("{side}.skew"))?,
            cx: num(&c["cx"], &format!("{side}.cx"))?,
            cy: num(&c["cy"], &format!("{side}.cy"))?,
        };
        let s = &c["sigma"];
        let sigmas = IntrinsicSigmas {
            fx: s["fx"].as_f64(),
            fy: s["fy"].as_f64(),
            cx: s["cx"].as_f64(),
            cy: s["cy"].as_f64(),
            skew: s["skew"].as_f64(),
        };
        let model =
            c["distortion_model"].as_str().ok_or_else(|| bad(&format!("{side}.distortion_model missing")))?;
        let kind = LensKind::parse(model)
            .ok_or_else(|| bad(&format!("{side}: lens model '{model}' is not supported")))?;
        let coeffs = nums(&c["distortion_coefficients"], &format!("{side}.distortion_coefficients"))?;
        let d = Distortion::from_coefficients(kind, &coeffs).map_err(|e| bad(&format!("{side}: {e}")))?;
        Ok((k, sigmas, d))
    };
    let (kl, sl, dl) = camera(&v["left"], "left")?;
    let (kr, sr, dr) = camera(&v["right"], "right")?;
    let r: Vec<f64> = v["right_from_left"]["R"]
        .as_array()
        .ok_or_else(|| bad("right_from_left.R is not a list of rows"))?
        .iter()
        .map(|row| nums(row, "right_from_left.R"))
        .collect::<Result<Vec<_>, _>>()?
        .concat();
    let t = nums(&v["right_from_left"]["t"], "right_from_left.t")?;
    let size = nums(&v["image_size"], "image_size")?;
    let unit = match v["translation_unit"].as_str() {
        Some("baselines") => TranslationUnit::Baselines,
        Some("m") | None => TranslationUnit::Metres,
        Some(u) => return Err(bad(&format!("translation unit '{u}' (m or baselines)"))),
    };
    Ok(StereoCalibration {
        image_size: match size.as_slice() {
            &[w, h] if w >= 0.0 && h >= 0.0 => [w as u32, h as u32],
            _ => return Err(bad("image_size is not [width, height]")),
        },
        left: kl,
        right: kr,
        sigmas: [sl, sr],
        right_from_left: pose(&r, &t, origin)?,
        unit,
        distortion: [dl, dr],
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::export::CalibrationFiles as _;

    /// A rig with the lens `d` on both cameras, metres or baselines.
    fn sample(d: [Distortion; 2], unit: TranslationUnit) -> StereoCalibration {
        StereoCalibration {
            image_size: [752, 480],
            left: Intrinsics::new(458.654, 457.296, 367.215, 248.375),
            right: Intrinsics::new(457.587, 456.134, 379.999, 255.238),
            sigmas: [IntrinsicSigmas { fx: Some(0.5), cy: Some(0.25), ..Default::default() }; 2],
            right_from_left: Isometry3::from_parts(
                Translation3::new(-0.110074, 0.000399, -0.000853),
                UnitQuaternion::from_euler_angles(-0.01409, 0.00034, -0.00232),
            ),
            unit,
            distortion: d,
        }
    }

    fn lenses() -> Vec<[Distortion; 2]> {
        let radtan = Distortion::from_params(
            LensKind::RadialTangential,
            [-0.2834, 0.07396, 0.000194, 1.76e-5, 0.0, 0.0],
        );
        let with_k3 = Distortion::from_params(
            LensKind::RadialTangential,
            [-0.2834, 0.07396, 0.000194, 1.76e-5, 0.01, 0.0],
        );
        let equi = Distortion::equidistant([0.01, -0.002, 0.0003, -4e-5]);
        vec![[radtan, with_k3], [equi, radtan], [Distortion::zero(LensKind::RadialTangential); 2]]
    }

    /// Poses agree to 1e-15 (the quaternion's round trip through a matrix).
    fn same(a: &StereoCalibration, b: &StereoCalibration, sigmas: bool) {
        assert_eq!(
            (a.image_size, a.left, a.right, a.unit, a.distortion),
            (b.image_size, b.left, b.right, b.unit, b.distortion)
        );
        assert!(
            (a.right_from_left.to_homogeneous() - b.right_from_left.to_homogeneous()).abs().max() < 1e-15
        );
        if sigmas {
            assert_eq!(a.sigmas, b.sigmas);
        }
    }

    #[test]
    fn json_round_trip() {
        for d in lenses().into_iter().chain([[Distortion::double_sphere(-0.2, 0.57); 2]]) {
            for unit in [TranslationUnit::Metres, TranslationUnit::Baselines] {
                let c = sample(d, unit);
                let back = from_json(&c.json().unwrap(), "t").unwrap();
                same(&c, &back, true);
            }
        }
    }

    #[test]
    fn opencv_yaml_round_trip() {
        for d in lenses() {
            let c = sample(d, TranslationUnit::Metres);
            same(&c, &from_opencv_yaml(&c.opencv_yaml().unwrap(), "t").unwrap(), false);
        }
        let c = sample(lenses()[0], TranslationUnit::Baselines);
        assert_eq!(
            from_opencv_yaml(&c.opencv_yaml().unwrap(), "t").unwrap().unit,
            TranslationUnit::Baselines
        );
    }

    /// Kalibr's radtan has no k3 (the writer notes it in a comment): the rest round-trips.
    #[test]
    fn kalibr_round_trip() {
        for d in lenses().into_iter().chain([[Distortion::double_sphere(-0.2, 0.57); 2]]) {
            let mut c = sample(d, TranslationUnit::Metres);
            if let Some(k3) = c.distortion[1].param_named_mut("k3") {
                *k3 = 0.0;
            }
            same(&c, &from_kalibr_camchain(&c.kalibr_camchain().unwrap(), "t").unwrap(), false);
        }
    }

    /// A file of each format is told apart by `read_calibration`; a bad file is an error
    /// naming it.
    #[test]
    fn reads_each_format_from_disk() {
        let dir = std::env::temp_dir().join(format!("headalign-import-{}", std::process::id()));
        let c = sample(lenses()[0], TranslationUnit::Metres);
        let written = c.write_all(&dir).unwrap();
        for p in written.iter().filter(|p| !p.ends_with("left.yaml") && !p.ends_with("right.yaml")) {
            let back = read_calibration(p).unwrap();
            assert_eq!(back.left, c.left, "{}", p.display());
        }
        let bad = dir.join("bad.yaml");
        std::fs::write(&bad, "foo: 1\n").unwrap();
        let e = read_calibration(&bad).unwrap_err().to_string();
        assert!(e.contains("bad.yaml") && e.contains("not a calibration file"), "{e}");
        std::fs::write(&bad, "%YAML:1.0\nM1: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1, 0, 0, 0, 1, 0, 0, 0, 1 ]\nD1: [0, 0, 0, 0]\nM2: [1, 0, 0, 0, 1, 0, 0, 0, 1]\nD2: [0, 0, 0, 0]\nR: [1, 0, 0, 0, 2, 0, 0, 0, 1]\nT: [1, 0, 0]\n").unwrap();
        let e = read_calibration(&bad).unwrap_err().to_string();
        assert!(e.contains("not a rotation"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
