//! Calibration files in the formats robotics software reads: JSON, OpenCV FileStorage YAML
//! (`cv2.FileStorage`, the layout of OpenCV's `stereo_calib` sample: `M1 D1 M2 D2 R T R1
//! R2 P1 P2 Q`), ROS `camera_info` YAML for each camera (`camera_calibration_parsers`
//! layout), and a Kalibr `camchain.yaml`.
//!
//! What it computes: nothing is estimated here. The pair is the library's
//! [`StereoCalibration`] (`headalign::calibration`); its files are the
//! [`CalibrationFiles`] methods. The stereo rectification that OpenCV's `R1 R2 P1 P2 Q` and
//! ROS's `rectification_matrix` / `projection_matrix` need comes from
//! [`headalign_geometry::rectify::rectify_stereo`] ([`StereoCalibration::rectification`]).
//!
//! Units: pixels for intrinsics; the rig translation is in metres when the user gives the
//! baseline length, otherwise in baselines (the self-calibration is only up to scale;
//! every file then says so in a comment and the JSON in `translation_unit`).
//!
//! Pitfalls: OpenCV's YAML needs the `%YAML:1.0` header and `!!opencv-matrix` tags, so it
//! is written by hand, as are the other YAML files (small, fixed layouts). Numbers are
//! written with Rust's shortest round-trip formatting, so reading them back gives the same
//! `f64`; a non-finite number is an error, never written. Kalibr's pinhole model has no
//! skew: a non-zero skew is reported in a comment and dropped there only. Distortion is the
//! lens model each camera has, under each format's own name: radial-tangential is
//! `plumb_bob` in OpenCV and ROS (`D` = `k1 k2 p1 p2 k3`) and `radtan` in Kalibr (`k1 k2 p1
//! p2`, a `k3` is noted in a comment); equidistant is OpenCV's `fisheye` (the YAML's
//! `distortion_model` key; `D` = `k1 k2 k3 k4` for `cv::fisheye`), ROS's `equidistant` and
//! Kalibr's `equidistant`; the double sphere is Kalibr's `camera_model: ds` (`intrinsics:
//! [xi, alpha, fu, fv, pu, pv]`, `distortion_model: none`), and OpenCV and ROS have no such
//! model: their writers refuse it with an error naming the model, and [`StereoCalibration::write_all`]
//! leaves those files out. The names, and Kalibr's form of each model (camera model,
//! parameters before `fu fv pu pv`, distortion model and coefficients; a non-zero
//! parameter it has no place for noted in a comment), come from the lens table
//! (`headalign_geometry::lens`), so a new model is written without a change here.
//! Zero radial-tangential when no lens was given.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use headalign::AlignError;
pub use headalign::calibration::{IntrinsicSigmas, StereoCalibration, TranslationUnit};
use headalign_geometry::camera::Intrinsics;
use headalign_geometry::distortion::Distortion;
use nalgebra::{DMatrix, Matrix3};
use serde_json::{Value, json};

/// The calibration files of a [`StereoCalibration`] (the type is the library's,
/// `headalign::calibration`; its files are written here).
pub trait CalibrationFiles {
    /// JSON: both cameras (K, sigmas, distortion), the rig, the rectification.
    fn json(&self) -> Result<Value, AlignError>;
    /// OpenCV FileStorage YAML (readable by `cv::FileStorage` / `cv2.FileStorage`).
    fn opencv_yaml(&self) -> Result<String, AlignError>;
    /// ROS `camera_info` YAML of one camera (`0` left, `1` right), with the rectification
    /// of the pair (`rectification_matrix`, `projection_matrix`).
    fn ros_camera_info(&self, index: usize, camera_name: &str) -> Result<String, AlignError>;
    /// Kalibr `camchain.yaml`: `cam0` (left), `cam1` (right) with `T_cn_cnm1` =
    /// `right_from_left` as a 4x4 matrix.
    fn kalibr_camchain(&self) -> Result<String, AlignError>;
    /// Write every format into `dir` (created if missing): `calibration.json`,
    /// `opencv_stereo.yaml`, `left.yaml`, `right.yaml` (ROS), `camchain.yaml` (Kalibr).
    /// Returns the paths written.
    fn write_all(&self, dir: &Path) -> Result<Vec<PathBuf>, AlignError>;
}

impl CalibrationFiles for StereoCalibration {
    /// JSON: both cameras (K, sigmas, distortion), the rig, the rectification.
    fn json(&self) -> Result<Value, AlignError> {
        let r = self.rectification()?;
        let cam = |k: &Intrinsics, s: &IntrinsicSigmas, d: &Distortion| {
            json!({
                "K": rows(&k.matrix()),
                "fx": k.fx, "fy": k.fy, "skew": k.skew, "cx": k.cx, "cy": k.cy,
                "sigma": {"fx": s.fx, "fy": s.fy, "cx": s.cx, "cy": s.cy, "skew": s.skew},
                "distortion_model": d.kind.ros_name(),
                "distortion_coefficients": d.coefficients(),
            })
        };
        let v = json!({
            "format": "headalign-calibration/1",
            "image_size": self.image_size,
            "left": cam(&self.left, &self.sigmas[0], &self.distortion[0]),
            "right": cam(&self.right, &self.sigmas[1], &self.distortion[1]),
            "right_from_left": {
                "R": rows(&self.rotation()),
                "t": self.right_from_left.translation.vector.as_slice(),
            },
            "translation_unit": self.unit.name(),
            "rectification": {
                "R1": rows(&r.rect_from_left), "R2": rows(&r.rect_from_right),
                "P1": dyn_rows(&DMatrix::from_column_slice(3, 4, r.p_left.as_slice())),
                "P2": dyn_rows(&DMatrix::from_column_slice(3, 4, r.p_right.as_slice())),
                "Q": dyn_rows(&DMatrix::from_column_slice(4, 4, r.q.as_slice())),
            },
        });
        check_finite(&v)?;
        Ok(v)
    }

    /// OpenCV FileStorage YAML (readable by `cv::FileStorage` / `cv2.FileStorage`).
    fn opencv_yaml(&self) -> Result<String, AlignError> {
        let r = self.rectification()?;
        let models = self.distortion.map(|d| d.kind.model().names().opencv);
        let [Some(m0), Some(m1)] = models else {
            return Err(inexpressible("OpenCV", &self.distortion));
        };
        let mut s = String::from("%YAML:1.0\n---\n");
        let _ = writeln!(s, "# headalign stereo calibration; translation unit: {}", self.unit.name());
        let _ = writeln!(s, "image_width: {}", self.image_size[0]);
        let _ = writeln!(s, "image_height: {}", self.image_size[1]);
        let d = |i: usize| {
            let c = self.distortion[i].coefficients();
            DMatrix::from_row_slice(1, c.len(), &c)
        };
        // OpenCV's own name of the model the D vectors belong to (`cv::fisheye` for the
        // equidistant one); FileStorage readers that do not know the key ignore it.
        if m0 == m1 {
            let _ = writeln!(s, "distortion_model: {m0}");
        } else {
            let _ = writeln!(s, "distortion_model_1: {m0}\ndistortion_model_2: {m1}");
        }
        let t = self.right_from_left.translation.vector;
        let entries: [(&str, DMatrix<f64>); 11] = [
            ("M1", dyn3(&self.left.matrix())),
            ("D1", d(0)),
            ("M2", dyn3(&self.right.matrix())),
            ("D2", d(1)),
            ("R", dyn3(&self.rotation())),
            ("T", DMatrix::from_column_slice(3, 1, t.as_slice())),
            ("R1", dyn3(&r.rect_from_left)),
            ("R2", dyn3(&r.rect_from_right)),
            ("P1", DMatrix::from_column_slice(3, 4, r.p_left.as_slice())),
            ("P2", DMatrix::from_column_slice(3, 4, r.p_right.as_slice())),
            ("Q", DMatrix::from_column_slice(4, 4, r.q.as_slice())),
        ];
        for (name, m) in entries {
            let _ = writeln!(
                s,
                "{name}: !!opencv-matrix\n   rows: {}\n   cols: {}\n   dt: d\n   data: [ {} ]",
                m.nrows(),
                m.ncols(),
                row_major(&m)?.join(", ")
            );
        }
        Ok(s)
    }

    /// ROS `camera_info` YAML of one camera (`0` left, `1` right), with the rectification
    /// of the pair (`rectification_matrix`, `projection_matrix`).
    fn ros_camera_info(&self, index: usize, camera_name: &str) -> Result<String, AlignError> {
        let r = self.rectification()?;
        let (k, rect, p, dist) = match index {
            0 => (&self.left, r.rect_from_left, r.p_left, self.distortion[0]),
            1 => (&self.right, r.rect_from_right, r.p_right, self.distortion[1]),
            _ => return Err(AlignError::Output(format!("camera index {index} (0 = left, 1 = right)"))),
        };
        let Some(ros_model) = dist.kind.ros() else {
            return Err(inexpressible("ROS camera_info", &[dist]));
        };
        let block = |name: &str, m: &DMatrix<f64>| -> Result<String, AlignError> {
            Ok(format!(
                "{name}:\n  rows: {}\n  cols: {}\n  data: [{}]\n",
                m.nrows(),
                m.ncols(),
                row_major(m)?.join(", ")
            ))
        };
        let mut s = format!(
            "# headalign; projection_matrix translation unit: {}\nimage_width: {}\nimage_height: {}\ncamera_name: {}\n",
            self.unit.name(),
            self.image_size[0],
            self.image_size[1],
            yaml_string(camera_name)
        );
        s += &block("camera_matrix", &dyn3(&k.matrix()))?;
        let _ = writeln!(s, "distortion_model: {ros_model}");
        let coefficients = dist.coefficients();
        s += &block(
            "distortion_coefficients",
            &DMatrix::from_row_slice(1, coefficients.len(), &coefficients),
        )?;
        s += &block("rectification_matrix", &dyn3(&rect))?;
        s += &block("projection_matrix", &DMatrix::from_column_slice(3, 4, p.as_slice()))?;
        Ok(s)
    }

    /// Kalibr `camchain.yaml`: `cam0` (left), `cam1` (right) with `T_cn_cnm1` =
    /// `right_from_left` as a 4x4 matrix.
    fn kalibr_camchain(&self) -> Result<String, AlignError> {
        let cam = |k: &Intrinsics, d: &Distortion, topic: &str| kalibr_camera(k, d, topic, self.image_size);
        let mut s = format!("# headalign; translation unit: {}\ncam0:\n", self.unit.name());
        s += &cam(&self.left, &self.distortion[0], "/left/image_raw")?;
        s += "cam1:\n  T_cn_cnm1:\n";
        let m = self.right_from_left.to_homogeneous();
        for i in 0..4 {
            let row: Result<Vec<String>, _> = (0..4).map(|j| num(m[(i, j)])).collect();
            let _ = writeln!(s, "  - [{}]", row?.join(", "));
        }
        s += &cam(&self.right, &self.distortion[1], "/right/image_raw")?;
        Ok(s)
    }

    /// Write every format into `dir` (created if missing): `calibration.json`,
    /// `opencv_stereo.yaml`, `left.yaml`, `right.yaml` (ROS), `camchain.yaml` (Kalibr);
    /// each file only when its format has the cameras' lens model (OpenCV and ROS lack
    /// the double sphere). Returns the paths written.
    fn write_all(&self, dir: &Path) -> Result<Vec<PathBuf>, AlignError> {
        std::fs::create_dir_all(dir)
            .map_err(|e| AlignError::Output(format!("cannot create {}: {e}", dir.display())))?;
        let json = serde_json::to_string_pretty(&self.json()?)
            .map_err(|e| AlignError::Output(format!("JSON: {e}")))?;
        let opencv = self.distortion.iter().all(|d| d.kind.model().names().opencv.is_some());
        let ros = self.distortion.iter().all(|d| d.kind.ros().is_some());
        let mut files = vec![("calibration.json", json + "\n")];
        if opencv {
            files.push(("opencv_stereo.yaml", self.opencv_yaml()?));
        }
        if ros {
            files.push(("left.yaml", self.ros_camera_info(0, "left")?));
            files.push(("right.yaml", self.ros_camera_info(1, "right")?));
        }
        if self.distortion.iter().all(|d| d.kind.model().names().kalibr.is_some()) {
            files.push(("camchain.yaml", self.kalibr_camchain()?));
        }
        let mut written = Vec::new();
        for (name, text) in files {
            let path = dir.join(name);
            std::fs::write(&path, text)
                .map_err(|e| AlignError::Output(format!("cannot write {}: {e}", path.display())))?;
            written.push(path);
        }
        Ok(written)
    }
}

/// A YAML-safe number: shortest round-trip form, always with a decimal point or exponent
/// (so YAML reads a float); non-finite numbers are errors.
fn num(v: f64) -> Result<String, AlignError> {
    if !v.is_finite() {
        return Err(AlignError::Output(format!("non-finite number {v} in a calibration file")));
    }
    let s = format!("{v:?}");
    Ok(if s.contains(['.', 'e', 'E']) { s } else { format!("{s}.0") })
}

fn row_major(m: &DMatrix<f64>) -> Result<Vec<String>, AlignError> {
    let mut out = Vec::with_capacity(m.len());
    for i in 0..m.nrows() {
        for j in 0..m.ncols() {
            out.push(num(m[(i, j)])?);
        }
    }
    Ok(out)
}

fn dyn3(m: &Matrix3<f64>) -> DMatrix<f64> {
    DMatrix::from_column_slice(3, 3, m.as_slice())
}

fn rows(m: &Matrix3<f64>) -> Vec<[f64; 3]> {
    (0..3).map(|i| [m[(i, 0)], m[(i, 1)], m[(i, 2)]]).collect()
}

fn dyn_rows(m: &DMatrix<f64>) -> Vec<Vec<f64>> {
    (0..m.nrows()).map(|i| (0..m.ncols()).map(|j| m[(i, j)]).collect()).collect()
}

/// A YAML scalar for a name: plain if it is a simple identifier, quoted otherwise.
fn yaml_string(s: &str) -> String {
    if !s.is_empty() && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-' || c == '/') {
        s.to_string()
    } else {
        format!("{:?}", s)
    }
}

fn check_finite(v: &Value) -> Result<(), AlignError> {
    match v {
        // serde_json turns non-finite f64 into null; a null where a matrix entry belongs
        // means a non-finite number (sigmas may legitimately be null).
        Value::Array(a) => a.iter().try_for_each(|x| {
            if x.is_null() {
                Err(AlignError::Output("non-finite number in a matrix".into()))
            } else {
                check_finite(x)
            }
        }),
        Value::Object(o) => o.values().try_for_each(check_finite),
        _ => Ok(()),
    }
}

/// The error of a writer whose format has no model of one of `lenses`.
fn inexpressible(format: &str, lenses: &[Distortion]) -> AlignError {
    let names: Vec<&str> = lenses.iter().map(|d| d.kind.model().names().id).collect();
    AlignError::Output(format!(
        "the {format} format has no {} lens model: write a format that has it (the JSON has every model; Kalibr's camchain the double sphere, camera_model ds)",
        names.join("/")
    ))
}

/// One camera of a Kalibr camchain in its model's Kalibr form (the lens table's
/// `KalibrForm`): `camera_model`, `intrinsics` (the form's parameters, then `fu fv pu
/// pv`), `distortion_model` and `distortion_coeffs`; a non-zero parameter the form has no
/// place for, and a skew, noted in a comment. A model Kalibr lacks is an error.
fn kalibr_camera(k: &Intrinsics, d: &Distortion, topic: &str, size: [u32; 2]) -> Result<String, AlignError> {
    let Some(form) = d.kind.model().names().kalibr else {
        return Err(inexpressible("Kalibr", &[*d]));
    };
    let value = |n: &str| d.param(n).unwrap_or(0.0);
    let list =
        |names: &[&str]| -> Result<Vec<String>, AlignError> { names.iter().map(|n| num(value(n))).collect() };
    let mut notes = String::new();
    if k.skew.abs() > 1e-9 {
        let _ = writeln!(
            notes,
            "  # skew {} px is not representable in Kalibr's {} model",
            num(k.skew)?,
            form.camera_model
        );
    }
    for (&n, &v) in d.kind.coefficient_names().iter().zip(&d.params()) {
        if v != 0.0 && !form.intrinsics.contains(&n) && !form.distortion_coeffs.contains(&n) {
            let _ = writeln!(
                notes,
                "  # {n} = {} is not representable in Kalibr's {} model",
                num(v)?,
                form.distortion_model
            );
        }
    }
    let mut intrinsics = list(form.intrinsics)?;
    intrinsics.extend([num(k.fx)?, num(k.fy)?, num(k.cx)?, num(k.cy)?]);
    Ok(format!(
        "{notes}  camera_model: {}\n  intrinsics: [{}]\n  distortion_model: {}\n  distortion_coeffs: [{}]\n  resolution: [{}, {}]\n  rostopic: {topic}\n",
        form.camera_model,
        intrinsics.join(", "),
        form.distortion_model,
        list(form.distortion_coeffs)?.join(", "),
        size[0],
        size[1]
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};

    fn sample() -> StereoCalibration {
        StereoCalibration {
            image_size: [768, 576],
            left: Intrinsics { fx: 700.25, fy: 720.5, skew: 0.0, cx: 390.125, cy: 284.0 },
            right: Intrinsics { fx: 705.0, fy: 716.0, skew: 0.3, cx: 380.0, cy: 290.0 },
            sigmas: [IntrinsicSigmas { fx: Some(2.0), ..Default::default() }, IntrinsicSigmas::default()],
            right_from_left: Isometry3::from_parts(
                Translation3::new(-0.25, 0.001, 0.002),
                UnitQuaternion::from_euler_angles(0.01, -0.05, 0.002),
            ),
            unit: TranslationUnit::Metres,
            distortion: [
                Distortion::from_opencv(&[-0.25, 0.125, 0.001, -0.002]).unwrap(),
                Distortion::default(),
            ],
        }
    }

    /// Numbers in a `data: [...]` list after `key`.
    fn data_after(text: &str, key: &str) -> Vec<f64> {
        let start = text.find(key).unwrap();
        let rest = &text[start..];
        let open = rest.find('[').unwrap();
        let close = rest.find(']').unwrap();
        rest[open + 1..close].split(',').map(|x| x.trim().parse::<f64>().unwrap()).collect()
    }

    #[test]
    fn opencv_yaml_has_every_matrix_with_exact_numbers() {
        let c = sample();
        let y = c.opencv_yaml().unwrap();
        assert!(y.starts_with("%YAML:1.0\n---\n"));
        for key in ["M1:", "D1:", "M2:", "D2:", "R:", "T:", "R1:", "R2:", "P1:", "P2:", "Q:"] {
            assert!(y.contains(&format!("{key} !!opencv-matrix")), "{key}");
        }
        // Round trip is exact: shortest round-trip formatting.
        let m1 = data_after(&y, "M1:");
        assert_eq!(m1, vec![700.25, 0.0, 390.125, 0.0, 720.5, 284.0, 0.0, 0.0, 1.0]);
        let t = data_after(&y, "\nT:");
        assert_eq!(t, vec![-0.25, 0.001, 0.002]);
        let m2 = data_after(&y, "M2:");
        assert_eq!(m2[1], 0.3, "skew kept in OpenCV's camera matrix");
    }

    /// Each camera's model under each format's name, and read back exactly: an
    /// equidistant left lens and a radial-tangential right one in one OpenCV YAML, an
    /// equidistant ROS `camera_info`.
    #[test]
    fn lens_models_are_written_and_read_back() {
        use headalign::calibrate::read_opencv_lenses;
        let mut c = sample();
        c.distortion[0] = Distortion::equidistant([0.01, -0.002, 0.0003, -0.00004]);
        let y = c.opencv_yaml().unwrap();
        assert!(y.contains("distortion_model_1: fisheye\ndistortion_model_2: plumb_bob"));
        assert_eq!(data_after(&y, "D1:").len(), 4);
        let lenses = read_opencv_lenses(&y, "t").unwrap();
        assert_eq!(lenses[0].distortion, c.distortion[0]);
        assert_eq!(lenses[1].distortion, c.distortion[1]);
        let ros = c.ros_camera_info(0, "left").unwrap();
        assert!(ros.contains("distortion_model: equidistant"));
        assert_eq!(read_opencv_lenses(&ros, "t").unwrap()[0].distortion, c.distortion[0]);
        let kalibr = c.kalibr_camchain().unwrap();
        assert!(
            kalibr.contains(
                "distortion_model: equidistant\n  distortion_coeffs: [0.01, -0.002, 0.0003, -4e-5]"
            )
        );
        assert!(kalibr.contains("distortion_model: radtan"));
        assert_eq!(c.json().unwrap()["left"]["distortion_model"], "equidistant");
    }

    /// The double sphere: Kalibr's `ds` camera model with `[xi, alpha, fu, fv, pu, pv]`;
    /// OpenCV and ROS refuse it by name, and `write_all` leaves their files out.
    #[test]
    fn double_sphere_is_written_as_kalibr_ds_only() {
        let mut c = sample();
        c.distortion[1] = Distortion::double_sphere(-0.2, 0.57);
        let kalibr = c.kalibr_camchain().unwrap();
        assert!(kalibr.contains(
            "camera_model: ds\n  intrinsics: [-0.2, 0.57, 705.0, 716.0, 380.0, 290.0]\n  distortion_model: none\n  distortion_coeffs: []"
        ), "{kalibr}");
        for e in [c.opencv_yaml().unwrap_err(), c.ros_camera_info(1, "right").unwrap_err()] {
            assert!(e.to_string().contains("double-sphere"), "{e}");
        }
        assert_eq!(c.json().unwrap()["right"]["distortion_coefficients"], json!([-0.2, 0.57]));
        let dir = std::env::temp_dir().join(format!("headalign-export-ds-{}", std::process::id()));
        let written = c.write_all(&dir).unwrap();
        let names: Vec<_> = written.iter().filter_map(|p| p.file_name()?.to_str()).collect();
        assert_eq!(names, ["calibration.json", "camchain.yaml"]);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn ros_and_kalibr_layouts() {
        let c = sample();
        let l = c.ros_camera_info(0, "left").unwrap();
        for key in [
            "image_width: 768",
            "camera_name: left",
            "camera_matrix:",
            "distortion_model: plumb_bob",
            "distortion_coefficients:",
            "rectification_matrix:",
            "projection_matrix:",
        ] {
            assert!(l.contains(key), "{key}");
        }
        assert_eq!(data_after(&l, "projection_matrix:\n").len(), 12);
        let r = c.ros_camera_info(1, "right").unwrap();
        let p = data_after(&r, "projection_matrix:\n");
        // P2[0][3] = -f B with B = |t| (metres here).
        let b = c.right_from_left.translation.vector.norm();
        assert!((p[3] + p[0] * b).abs() < 1e-9 * p[0]);
        assert!(c.ros_camera_info(2, "x").is_err());
        let k = c.kalibr_camchain().unwrap();
        assert!(k.contains("cam0:\n") && k.contains("cam1:\n  T_cn_cnm1:\n"));
        assert!(k.contains("intrinsics: [700.25, 720.5, 390.125, 284.0]"));
        assert!(k.contains("# skew 0.3 px"));
    }

    #[test]
    fn non_finite_numbers_are_errors_not_files() {
        let mut c = sample();
        c.left.fx = f64::NAN;
        assert!(c.opencv_yaml().is_err());
        assert!(c.kalibr_camchain().is_err());
        assert!(c.json().is_err());
        let dir = std::env::temp_dir().join(format!("headalign-export-nan-{}", std::process::id()));
        assert!(c.write_all(&dir).is_err());
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn write_all_writes_five_files() {
        let dir = std::env::temp_dir().join(format!("headalign-export-{}", std::process::id()));
        let paths = sample().write_all(&dir).unwrap();
        assert_eq!(paths.len(), 5);
        for p in &paths {
            assert!(std::fs::metadata(p).unwrap().len() > 50, "{}", p.display());
        }
        let v: Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join("calibration.json")).unwrap()).unwrap();
        assert_eq!(v["translation_unit"], "m");
        assert_eq!(v["left"]["sigma"]["fx"], 2.0);
        std::fs::remove_dir_all(&dir).ok();
    }

    /// The OpenCV YAML our export writes is a lens file `--distortion` reads back exactly
    /// (shortest round-trip number formatting).
    #[test]
    fn reads_back_our_own_export() {
        let d = [
            Distortion::from_opencv(&[-0.25, 0.125, 0.001, -0.002, 0.01]).unwrap(),
            Distortion::radial(0.1, 0.0),
        ];
        let stereo = StereoCalibration {
            image_size: [768, 576],
            left: Intrinsics { fx: 700.25, fy: 720.5, skew: 0.0, cx: 390.125, cy: 284.0 },
            right: Intrinsics::new(705.0, 716.0, 380.0, 290.0),
            sigmas: Default::default(),
            right_from_left: Isometry3::translation(-0.25, 0.0, 0.0),
            unit: TranslationUnit::Metres,
            distortion: d,
        };
        let [l, r] =
            headalign::calibrate::read_opencv_lenses(&stereo.opencv_yaml().unwrap(), "ours").unwrap();
        assert_eq!((l.k, l.distortion, r.k, r.distortion), (stereo.left, d[0], stereo.right, d[1]));
    }
}
