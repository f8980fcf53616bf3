//! `headalign calibrate` on the real images in `data/` (see each folder's README for
//! provenance and licence; docs/results-real.md for the numbers).
//!
//! Reference data in `tests/data`: `motorcycle_calibration.yml` (the Middlebury
//! calibration of the down-sampled pair, from the data's README), and from
//! `bench/real_data_reference.py` (OpenCV): `chessboard_reference.yml` (cv2.stereoCalibrate
//! from the board, RMS 0.44 px) and `chessboard_corners.json` (the board's corners found
//! by OpenCV in all 13 pairs, undistorted).

use std::path::{Path, PathBuf};

use serde_json::Value;

use super::common::{bin, data_dir, fixture, tmp_dir};

fn calibrate(args: &[&str]) -> (bool, Value, String) {
    let out = bin().arg("calibrate").args(args).output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).to_string();
    let json = serde_json::from_slice(&out.stdout).unwrap_or(Value::Null);
    (out.status.success(), json, stderr)
}

fn matrix3(v: &Value) -> [[f64; 3]; 3] {
    let mut m = [[0.0; 3]; 3];
    for (i, row) in m.iter_mut().enumerate() {
        for (j, x) in row.iter_mut().enumerate() {
            *x = v[i][j].as_f64().unwrap();
        }
    }
    m
}

fn apply(f: &[[f64; 3]; 3], p: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|i| f[i][0] * p[0] + f[i][1] * p[1] + f[i][2] * p[2])
}

fn transpose(f: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    [0, 1, 2].map(|i| [0, 1, 2].map(|j| f[j][i]))
}

/// Distance of `q` from the line `l`.
fn line_distance(l: [f64; 3], q: [f64; 2]) -> f64 {
    (l[0] * q[0] + l[1] * q[1] + l[2]).abs() / l[0].hypot(l[1])
}

fn vec3(v: &Value) -> [f64; 3] {
    [0, 1, 2].map(|i| v[i].as_f64().unwrap())
}

fn angle_deg(a: [f64; 3], b: [f64; 3]) -> f64 {
    let dot: f64 = (0..3).map(|i| a[i] * b[i]).sum();
    let na: f64 = a.iter().map(|x| x * x).sum::<f64>().sqrt();
    let nb: f64 = b.iter().map(|x| x * x).sum::<f64>().sqrt();
    (dot / (na * nb)).clamp(-1.0, 1.0).acos().to_degrees()
}

/// The Middlebury motorcycle pair is rectified: true epipolar lines are image rows. Our F
/// (the rig refined on its 5 dof over 666 of 767 feature matches, Sampson RMS 0.22 px,
/// with the default stereo patch refinement) puts its epipolar lines within 1 px of the
/// rows everywhere on a 20 x 15 grid of the image at disparities 20-80 px (measured: max
/// 0.31 px; 0.44 px with `--patch-refinement off`). 1 px: twice the feature localisation
/// RMS, since the grid reaches the image corners where F is extrapolated. With the known
/// intrinsics the rig is R = I (measured 0.03 deg; bound 0.3 deg) and t along -x
/// (measured 0.23 deg, 0.39 deg with refinement off; bound 1 deg; docs/results-real.md).
#[test]
fn motorcycle_f_agrees_with_the_known_calibration() {
    let data = data_dir();
    let dir = data.join("skimage_data/motorcycle_stereo");
    let cal = fixture("motorcycle_calibration.yml");
    let (ok, j, err) = calibrate(&[dir.to_str().unwrap(), "--intrinsics", cal.to_str().unwrap(), "--json"]);
    assert!(ok, "{err}");
    let f = matrix3(&j["fundamental_undistorted"]);
    let mut worst: f64 = 0.0;
    for iu in 0..20 {
        for iv in 0..15 {
            let (u, v) = (740.0 * f64::from(iu) / 19.0, 499.0 * f64::from(iv) / 14.0);
            let l = apply(&f, [u, v, 1.0]);
            for d in [20.0, 80.0] {
                let x = u - d;
                let y = -(l[0] * x + l[2]) / l[1];
                worst = worst.max((y - v).abs());
            }
        }
    }
    assert!(worst < 1.0, "epipolar lines up to {worst:.3} px off the rows");
    let rig = &j["right_from_left"];
    let rot = rig["rotation_deg"].as_f64().unwrap();
    assert!(rot < 0.3, "rotation {rot} deg");
    let t = angle_deg(vec3(&rig["translation_direction"]), [-1.0, 0.0, 0.0]);
    assert!(t < 1.0, "translation {t} deg off -x");
}

/// Self-calibration from the OpenCV chessboard pairs is impossible (a fixed rig and a
/// moving planar board: the matches between views are the static background, the board
/// has no projective reconstruction) and says so, with a non-zero exit.
#[test]
fn chessboard_self_calibration_names_the_degeneracy() {
    let data = data_dir();
    let dir = data.join("opencv_samples/stereo_chessboard");
    let (ok, _, err) = calibrate(&[dir.to_str().unwrap()]);
    assert!(!ok);
    // The line is cut at 300 characters; the whole message is in the file it names.
    assert!(err.contains("no view is rotated"), "{err}");
    let full = err.split("(full message: ").nth(1).and_then(|s| s.split(')').next()).unwrap_or_default();
    let text = std::fs::read_to_string(full).unwrap_or_default();
    assert!(text.contains("no view is rotated") && text.contains("planar target"), "{err}: {text}");
}

/// What the chessboard pairs do give: F from the feature matches of all 13 pairs (the rig
/// is fixed, so together they are not planar), and the rig from E with known intrinsics.
/// Checked against the board's own corners (found by OpenCV, exact correspondences):
/// their epipolar distances under our F have RMS below 1 px (measured 0.32 px with the
/// default stereo patch refinement, 0.64 px with `--patch-refinement off`; under OpenCV's
/// stereoCalibrate F 0.27 px, which was fitted to those very corners; our F comes from
/// FAST corners with 0.4 px (0.7 px unrefined) Sampson RMS in 640x480 JPEGs, so up to
/// about twice that is what the features allow). The rig agrees with stereoCalibrate's:
/// translation direction within 2 deg (measured 0.15 deg; 0.67 deg unrefined), relative
/// rotation within 0.5 deg (measured 0.19 deg; 0.15 deg unrefined).
#[test]
fn chessboard_with_known_intrinsics_agrees_with_the_board() {
    let data = data_dir();
    let dir = data.join("opencv_samples/stereo_chessboard");
    let cal = fixture("chessboard_reference.yml");
    let (ok, j, err) = calibrate(&[dir.to_str().unwrap(), "--intrinsics", cal.to_str().unwrap(), "--json"]);
    assert!(ok, "{err}");
    let f = matrix3(&j["fundamental_undistorted"]);
    let corners: Value =
        serde_json::from_str(&std::fs::read_to_string(fixture("chessboard_corners.json")).unwrap()).unwrap();
    let (mut sum, mut n) = (0.0, 0usize);
    let ft = transpose(&f);
    for (views_l, views_r) in
        corners["left"].as_array().unwrap().iter().zip(corners["right"].as_array().unwrap())
    {
        for (a, b) in views_l.as_array().unwrap().iter().zip(views_r.as_array().unwrap()) {
            let (a, b) = (
                [a[0].as_f64().unwrap(), a[1].as_f64().unwrap()],
                [b[0].as_f64().unwrap(), b[1].as_f64().unwrap()],
            );
            let dr = line_distance(apply(&f, [a[0], a[1], 1.0]), b);
            let dl = line_distance(apply(&ft, [b[0], b[1], 1.0]), a);
            sum += dr * dr + dl * dl;
            n += 2;
        }
    }
    let rms = (sum / n as f64).sqrt();
    assert!(n > 1000 && rms < 1.0, "board corners: RMS epipolar distance {rms:.3} px over {n}");
    let t_ref = [0, 1, 2].map(|i| corners["reference_T_m"][i].as_f64().unwrap());
    let t = angle_deg(vec3(&j["right_from_left"]["translation_direction"]), t_ref);
    assert!(t < 2.0, "translation direction {t:.2} deg from stereoCalibrate's");
    // Relative rotation: both are small rotations, compare as rotation vectors.
    let rv = |axis: [f64; 3], deg: f64| axis.map(|a| a * deg);
    let ours = rv(
        vec3(&j["right_from_left"]["rotation_axis"]),
        j["right_from_left"]["rotation_deg"].as_f64().unwrap(),
    );
    let r = matrix3(&corners["reference_R"]);
    // Rotation vector of the reference (small angle: the skew part of R).
    let reference = [(r[2][1] - r[1][2]) / 2.0, (r[0][2] - r[2][0]) / 2.0, (r[1][0] - r[0][1]) / 2.0]
        .map(f64::to_degrees);
    let diff: f64 = (0..3).map(|i| (ours[i] - reference[i]).powi(2)).sum::<f64>().sqrt();
    assert!(diff < 0.5, "rotation {ours:?} vs {reference:?} deg ({diff:.3} apart)");
}

/// The raw EuRoC V1_01 pairs 3 and 2 (one general motion of a real VI-Sensor rig with a
/// barrel lens, k1 about -0.28) in a temporary folder of `leftNN.png` / `rightNN.png`.
fn euroc_one_motion(data: &Path, name: &str) -> PathBuf {
    euroc_pairs(data, name, [3, 2])
}

/// The raw EuRoC V1_01 pairs `pairs` (the data folder's numbers) in a temporary folder
/// of `leftNN.png` / `rightNN.png`, in that order.
fn euroc_pairs(data: &Path, name: &str, pairs: [usize; 2]) -> PathBuf {
    let src = data.join("euroc_v101_pairs");
    let dir = tmp_dir(name);
    for (i, pair) in pairs.iter().enumerate() {
        for side in ["left", "right"] {
            std::fs::copy(src.join(format!("{side}_img_{pair}.png")), dir.join(format!("{side}{i:02}.png")))
                .unwrap();
        }
    }
    dir
}

/// The dataset's own calibration (Kalibr, a target): fx, fy of cam0 and cam1.
const EUROC_FOCAL: [[f64; 2]; 2] = [[458.654, 457.296], [457.587, 456.134]];

/// Relative focal errors of a calibrate JSON against [`EUROC_FOCAL`].
fn euroc_focal_errors(j: &Value) -> Vec<f64> {
    ["left", "right"]
        .iter()
        .zip(EUROC_FOCAL)
        .flat_map(|(side, f)| {
            [("fx", f[0]), ("fy", f[1])].map(|(k, truth)| j[side][k].as_f64().unwrap() / truth - 1.0)
        })
        .collect()
}

/// `calibrate DIR` with no flags on the raw pairs (the bar): `--lens auto` and
/// zero skew are the defaults. Auto compares the pinhole, radtan (k1 k2; with p1 p2; with
/// k3) and equidistant (k1 k2; k1..k4) by BIC on one set of observations and says so.
/// Measured (seed 0): BIC pinhole 142,343, radtan k1 k2 3,774, with p1 p2 3,745, with k3
/// 3,338, equidistant k1 k2 3,252, k1..k4 3,284 on 3,613 observations; equidistant k1 k2
/// is kept, with the focal lengths +0.11, +0.43, +0.07, +0.46 % off the dataset's. The
/// bar is 1 %, the issue's; the focal sigma is 0.4 %. Run without `--json`: the text
/// names the chosen model and terms, the criterion and each camera's coefficients with
/// their sigmas; the report file holds the same JSON.
#[test]
fn euroc_raw_pairs_default_flags_give_the_focal_lengths() {
    let data = data_dir();
    let dir = euroc_one_motion(data, "auto");
    let out_dir = dir.join("out");
    let out = bin().args(["calibrate", dir.to_str().unwrap(), "--out"]).arg(&out_dir).output().unwrap();
    let (text, err) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{err}");
    let report = std::fs::read_to_string(out_dir.join("calibrate_report.json")).unwrap();
    let j: Value = serde_json::from_str(&report).unwrap();
    assert_eq!(j["constraints"]["zero_skew"], true);
    assert_eq!(j["left"]["skew"].as_f64(), Some(0.0));
    let sel = &j["report"]["lens_selection"];
    let terms: Vec<&str> = sel["terms"].as_array().unwrap().iter().map(|t| t.as_str().unwrap()).collect();
    let chosen_line = format!(
        "lens model {} {} (--lens auto): smallest BIC",
        sel["chosen"].as_str().unwrap(),
        terms.join(" ")
    );
    assert!(text.contains(&chosen_line), "{text}");
    for side in ["left ", "right"] {
        let line = text.lines().find(|l| l.starts_with(&format!("{side} lens "))).unwrap_or_default();
        assert!(line.contains(" k1 ") && line.contains(" +- ") && line.ends_with("(estimated)"), "{text}");
    }
    let tried: Vec<String> = sel["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            let terms: Vec<&str> =
                c["terms"].as_array().unwrap().iter().map(|t| t.as_str().unwrap()).collect();
            format!("{} {}", c["model"].as_str().unwrap(), terms.join(" ")).trim().to_string()
        })
        .chain(sel["failed"].as_array().unwrap().iter().map(|f| f["candidate"].as_str().unwrap().to_string()))
        .collect();
    for c in [
        "pinhole",
        "radtan k1 k2",
        "radtan k1 k2 p1 p2",
        "radtan k1 k2 p1 p2 k3",
        "equidistant k1 k2",
        "equidistant k1 k2 k3 k4",
    ] {
        assert!(tried.iter().any(|t| t == c), "{c} neither compared nor reported failed: {sel}");
    }
    let chosen = sel["chosen"].as_str().unwrap();
    assert!(chosen != "pinhole", "a barrel lens of k1 -0.28 must not be called a pinhole: {sel}");
    assert!(sel["reason"].as_str().unwrap().contains("BIC"));
    assert_eq!(
        j["distortion"]["model"][0].as_str().unwrap(),
        if chosen == "radtan" { "plumb_bob" } else { "equidistant" }
    );
    for e in euroc_focal_errors(&j) {
        assert!(e.abs() < 0.01, "focal lengths {:?} against the dataset's", euroc_focal_errors(&j));
    }
}

/// Every candidate of `--lens auto` is either compared or reported failed with a one-line
/// reason and left out, and the choice goes on among the others. On the raw pairs in the
/// order 2 -> 3 with the skew free (`--free-skew`, 1500 corners) the reduced camera
/// system of the pinhole refit is near singular; the optimiser's damping carries it to a
/// fit (rms 0.62 px against 0.09 px for the lens models), so the pinhole is compared and
/// loses. A failed candidate, when there is one, is named in the text.
#[test]
fn euroc_lens_auto_compares_or_leaves_out_every_candidate() {
    let data = data_dir();
    let dir = euroc_pairs(data, "failed-candidate", [2, 3]);
    let out_dir = dir.join("out");
    let out = bin()
        .args(["calibrate", dir.to_str().unwrap(), "--free-skew", "--corners", "1500", "--out"])
        .arg(&out_dir)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report = std::fs::read_to_string(out_dir.join("calibrate_report.json")).unwrap();
    let j: Value = serde_json::from_str(&report).unwrap();
    let sel = &j["report"]["lens_selection"];
    let failed = sel["failed"].as_array().unwrap();
    for f in failed {
        let reason = f["reason"].as_str().unwrap();
        assert!(!reason.is_empty() && !reason.contains('\n') && reason.len() <= 203, "{f}");
        assert!(sel["candidates"].as_array().unwrap().iter().all(|c| c["model"] != f["candidate"]), "{sel}");
    }
    eprintln!("failed candidates: {failed:?}");
    let candidates = sel["candidates"].as_array().unwrap();
    assert_eq!(candidates.len() + failed.len(), 6, "six candidates, each compared or failed: {sel}");
    assert!(sel["chosen"] != "pinhole", "{sel}");
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    for f in failed {
        let name = f["candidate"].as_str().unwrap();
        assert!(text.contains(&format!("lens candidate {name} left out: ")), "{text}");
    }
}

/// The dataset's principal points (cx, cy) of cam0 and cam1.
const EUROC_CENTRE: [[f64; 2]; 2] = [[367.215, 248.375], [379.999, 255.238]];

/// Issue 31 item 3 on the real pairs: the residuals were checked against the noise
/// measured from the images, and each intrinsic (fx, fy, cx, cy of both cameras) is within
/// 3 reported sigmas of the dataset's, or a warning says why not (the residuals against
/// the images' noise, or their structure). With square pixels `fy` is `fx`, with its sigma.
fn euroc_intrinsics_within_3_sigmas_or_warned(j: &Value) {
    let noise = &j["report"]["image_noise"];
    assert_eq!(noise["status"], "checked", "{noise}");
    let mut beyond = Vec::new();
    for (side, (f, c)) in ["left", "right"].iter().zip(EUROC_FOCAL.iter().zip(EUROC_CENTRE)) {
        for (k, truth) in [("fx", f[0]), ("fy", f[1]), ("cx", c[0]), ("cy", c[1])] {
            // With square pixels fy is fx (no sigma of its own).
            let sigma = j[side]["sigma"][k].as_f64().or_else(|| j[side]["sigma"]["fx"].as_f64()).unwrap();
            let z = (j[side][k].as_f64().unwrap() - truth) / sigma;
            if z.abs() > 3.0 {
                beyond.push(format!("{side}.{k} {z:+.1} sigmas"));
            }
        }
    }
    let warned = j["report"]["warnings"].as_array().unwrap().iter().any(|w| {
        let w = w.as_str().unwrap_or("");
        w.contains("localisation noise measured from the images") || w.contains("lack of fit")
    });
    eprintln!("beyond 3 sigmas: {beyond:?}; image noise {noise}; warned {warned}");
    assert!(beyond.is_empty() || warned, "{beyond:?} without a warning: {}", j["report"]["warnings"]);
}

/// `--lens radtan` on the raw pairs: both focal lengths of both cameras within 1 % of the
/// dataset's (measured -0.58, -0.87, -0.52, -0.74 %: the density rule keeps 3000 corners),
/// `k1` within 0.01 of the dataset's -0.283 (measured -0.291 for both, sigma 0.0023; the
/// bar is the issue's). The equidistant model's files: OpenCV YAML names `fisheye` and
/// has 4 coefficients, ROS `equidistant`, Kalibr `equidistant`, and `--intrinsics` reads
/// that YAML back as an equidistant lens.
#[test]
fn euroc_raw_pairs_lens_models_and_their_files() {
    let data = data_dir();
    let dir = euroc_one_motion(data, "models");
    let d = dir.to_str().unwrap();
    let (ok, j, err) = calibrate(&[d, "--lens", "radtan", "--zero-skew", "--json"]);
    assert!(ok, "{err}");
    assert!(euroc_focal_errors(&j).iter().all(|e| e.abs() < 0.01), "{:?}", euroc_focal_errors(&j));
    for side in ["left", "right"] {
        let k1 = j["distortion"][side][0].as_f64().unwrap();
        assert!((k1 + 0.2834).abs() < 0.01, "{side} k1 {k1}");
        assert!(j["distortion"]["sigma"][format!("{side}.k1")].as_f64().unwrap() > 0.0);
    }
    euroc_intrinsics_within_3_sigmas_or_warned(&j);
    let out = dir.join("out");
    let (ok, j, err) =
        calibrate(&[d, "--lens", "equidistant", "--zero-skew", "--json", "--out", out.to_str().unwrap()]);
    assert!(ok, "{err}");
    assert_eq!(j["distortion"]["left"].as_array().unwrap().len(), 4);
    let read = |f: &str| std::fs::read_to_string(out.join(f)).unwrap();
    assert!(read("opencv_stereo.yaml").contains("distortion_model: fisheye"));
    assert!(read("left.yaml").contains("distortion_model: equidistant"));
    assert!(read("camchain.yaml").contains("distortion_model: equidistant"));
    // Read back as known intrinsics and lens: the stereo matches undistorted through the
    // equidistant model fit one rig (Sampson RMS measured 0.29 px; the same coefficients
    // read as a radial-tangential lens give 0.36 px). The exact reading of the model is
    // checked in `export`'s unit tests.
    let yaml = out.join("opencv_stereo.yaml");
    let (ok, back, err) = calibrate(&[d, "--intrinsics", yaml.to_str().unwrap(), "--json"]);
    assert!(ok, "{err}");
    assert!((back["left"]["fx"].as_f64().unwrap() - j["left"]["fx"].as_f64().unwrap()).abs() < 1e-9);
    let rms = back["stereo_rms_px"].as_f64().unwrap();
    assert!(rms < 0.5, "stereo Sampson RMS {rms} px through the equidistant lens read back");
}

/// Issue 31 items 2-3 on a real motion held out from the bar's pairs: EuRoC pairs 1 -> 0
/// (37.5 deg and 0.44 m, 98 s apart, the same place revisited; docs/results-real.md). One
/// weak motion: about 270 tracks seen in both views (480 for pairs 3 -> 2). Measured:
/// `--lens radtan --zero-skew` puts the focal lengths +34 / +19 % off (5-8 sigmas, cx and
/// cy too) and warns that the focal length is poorly determined and that the
/// residuals are 1.6 times the images' noise; `--lens auto --zero-skew --square-pixels`
/// (the docs' advice for one motion) among the `k1 k2` models (`--lens-terms radial`)
/// gives +1.2 to +1.6 %, every intrinsic within 3 sigmas; with the dataset's lens removed
/// (`--distortion`, square pixels) +10 to +11 % at 2.5 sigmas, flagged. Each run: every
/// intrinsic within 3 sigmas of the dataset's or a warning says why, and a focal error
/// beyond 3 % is flagged as poorly determined. Not held here: `auto` with every term
/// (the default) on this motion keeps `radtan k1 k2 p1 p2 k3` (p1 -0.006 for the
/// dataset's 0.0002) at +8.2 % with a sigma of 0.73 % and no warning (docs/results-real.md,
/// "A held-out motion"): an open defect.
#[test]
fn euroc_held_out_weak_motion_is_warned() {
    let data = data_dir();
    let dir = euroc_pairs(data, "held-out", [1, 0]);
    let d = dir.to_str().unwrap();
    let lens = fixture("euroc_v101_lenses.yml");
    let known = ["--distortion", lens.to_str().unwrap(), "--zero-skew", "--square-pixels"];
    for flags in [
        &["--lens", "radtan", "--zero-skew"][..],
        &["--lens", "auto", "--lens-terms", "radial", "--square-pixels"],
        &known,
    ] {
        let (ok, j, err) = calibrate(&[&[d, "--json"][..], flags].concat());
        assert!(ok, "{flags:?}: {err}");
        euroc_intrinsics_within_3_sigmas_or_warned(&j);
        let errors = euroc_focal_errors(&j);
        let flagged = j["report"]["warnings"]
            .as_array()
            .unwrap()
            .iter()
            .any(|w| w.as_str().unwrap_or("").contains("poorly determined"));
        eprintln!("{flags:?}: focal errors {errors:?}, poorly determined warned: {flagged}");
        assert!(errors.iter().all(|e| e.abs() < 0.03) || flagged, "{flags:?}: {errors:?} unflagged");
    }
}

/// The dataset's calibration against the tracks (docs/results-real.md, "A held-out motion"):
/// on the tracks of `calibrate --lens radtan --zero-skew` (3000 corners, as the density
/// rule keeps), the adjustment with the dataset's intrinsics and lenses held (rig, motion
/// and points free) against the estimate, and the adjustment freed from there. Prints the
/// chi-squares at the estimate's noise. `cargo test --release -p headalign-cli --test
/// integration euroc_dataset_calibration_held -- --ignored --nocapture`.
#[test]
#[ignore = "diagnostic: prints the likelihood of the dataset's calibration on the EuRoC tracks"]
fn euroc_dataset_calibration_held() {
    use headalign::calibrate::{
        CalibrateOptions, LensChoice, calibrate_tracked, read_opencv_lenses, track_views,
    };
    use headalign::tracking::FrontEndOptions;
    use headalign_geometry::bundle::{
        BundleObservation, BundleOptions, RigState, RobustLoss, bundle_adjust, bundle_adjust_holding,
        residual_pixels,
    };
    use headalign_geometry::camera::Intrinsics;
    use headalign_geometry::distortion::LensKind;
    use headalign_platform::{GrayImage, StereoImages};

    let data = data_dir();
    let rss = |state: &RigState, obs: &[BundleObservation]| -> f64 {
        obs.iter().filter_map(|o| residual_pixels(state, o)).map(|r| r.norm_squared()).sum()
    };
    let file = fixture("euroc_v101_lenses.yml");
    let lenses =
        read_opencv_lenses(&std::fs::read_to_string(&file).unwrap(), "euroc_v101_lenses.yml").unwrap();
    for pairs in [[3, 2], [1, 0]] {
        let dir = euroc_pairs(data, "held", pairs);
        let views: Vec<(String, StereoImages)> = (0..2)
            .map(|i| {
                let load = |side: &str| GrayImage::load(&dir.join(format!("{side}{i:02}.png"))).unwrap();
                (
                    format!("left{i:02}"),
                    StereoImages::new(Default::default(), load("left"), load("right")).unwrap(),
                )
            })
            .collect();
        let mut front = FrontEndOptions::default();
        front.features.max_features = 3000;
        let options = CalibrateOptions {
            zero_skew: true,
            lens: LensChoice::Model(LensKind::RadialTangential),
            ..CalibrateOptions::default()
        };
        let tracked = track_views(&views, &front, &options).unwrap();
        let cal = calibrate_tracked(tracked, None, &options).unwrap();
        let (est, obs, sigma) = (&cal.bundle.state, &cal.observations, cal.bundle.report.sigma_px);
        let mut dataset = est.clone();
        let k = |c: usize| {
            Intrinsics::new(EUROC_FOCAL[c][0], EUROC_FOCAL[c][1], EUROC_CENTRE[c][0], EUROC_CENTRE[c][1])
        };
        (dataset.left, dataset.right) = (k(0), k(1));
        (dataset.left_distortion, dataset.right_distortion) = (lenses[0].distortion, lenses[1].distortion);
        let ls = BundleOptions {
            robust: RobustLoss::None,
            noise_sigma_px: None,
            max_iterations: 200,
            zero_skew: true,
            estimate_distortion: true,
            ..options.estimation.bundle.clone()
        };
        let robust = BundleOptions { robust: options.estimation.bundle.robust, ..ls.clone() };
        let held: Vec<String> = ["left", "right"]
            .iter()
            .flat_map(|s| ["fx", "fy", "cx", "cy", "k1", "k2"].map(|k| format!("{s}.{k}")))
            .collect();
        let held: Vec<&str> = held.iter().map(String::as_str).collect();
        let near = bundle_adjust_holding(&dataset, obs, &robust, &held).unwrap();
        let at_dataset = bundle_adjust_holding(&near.state, obs, &ls, &held).unwrap();
        let freed = bundle_adjust(&at_dataset.state, obs, &ls).unwrap();
        let chi2 = |s: &RigState| rss(s, obs) / (sigma * sigma);
        let motion = |s: &RigState| {
            let m = s.motions.ref_from_cam(1);
            (m.rotation.angle().to_degrees(), m.translation.vector.norm())
        };
        eprintln!(
            "pairs {pairs:?}: {} observations, noise {sigma:.3} px; chi-square at the estimate {:.0} \
             (left fx {:.1}, motion {:.2?}), with the dataset's calibration held {:.0} (motion {:.2?}), \
             freed from there {:.0} (left fx {:.1})",
            obs.len(),
            chi2(est),
            est.left.fx,
            motion(est),
            chi2(&at_dataset.state),
            motion(&at_dataset.state),
            chi2(&freed.state),
            freed.state.left.fx,
        );
    }
}

/// The four EuRoC MAV V1_01_easy pairs as a raw folder (`left00.png` = `left_img_3.png`,
/// `left01` = `_2`, `left02` = `_1`, `left03` = `_0`): pairs 3 -> 2 are one general rig
/// motion (15.6 deg), 1 -> 0 another (37.5 deg), and 0/1 share no view with 2/3. View 02
/// overlaps the first by 4 tracks, so the folder is tracked as a sequence: two segments,
/// each adding its one motion (relative to its own gauge) to one calibration. With the
/// dataset's own lenses removed (`--distortion`, no constraint) the focal lengths come out
/// at fx 464.5 / 463.5 px (+1.3 % on the dataset's Kalibr calibration, both cameras),
/// fy 457.4 / 456.3 (+0.03 %); with the lenses estimated (`--estimate-distortion
/// --zero-skew`) fx 460.1 / 459.2 (+0.3 %); with `--lens auto` on this sequence the
/// equidistant model, fx 460.9 / 459.8 (+0.5 %). Bound: 2 %, the bar. Every run's
/// intrinsics are within 3 sigmas of the dataset's or a warning says why not.
#[test]
fn euroc_four_pairs_calibrate_with_both_motions() {
    let data = data_dir();
    let src = data.join("euroc_v101_pairs");
    let dir = tmp_dir("euroc4");
    for (view, pair) in [(0, 3), (1, 2), (2, 1), (3, 0)] {
        for side in ["left", "right"] {
            std::fs::copy(
                src.join(format!("{side}_img_{pair}.png")),
                dir.join(format!("{side}{view:02}.png")),
            )
            .unwrap();
        }
    }
    let lens = fixture("euroc_v101_lenses.yml");
    let runs = [
        vec![dir.to_str().unwrap(), "--distortion", lens.to_str().unwrap(), "--json"],
        vec![dir.to_str().unwrap(), "--estimate-distortion", "--zero-skew", "--json"],
        vec![dir.to_str().unwrap(), "--lens", "auto", "--zero-skew", "--json"],
    ];
    let truth = [458.654, 457.587];
    for args in runs {
        let (ok, j, err) = calibrate(&args);
        assert!(ok, "{args:?}: {err}");
        if args.contains(&"auto") {
            let sel = &j["report"]["lens_selection"];
            assert!(sel["chosen"] != "pinhole" && sel["reason"].as_str().unwrap().contains("BIC"), "{sel}");
        }
        euroc_intrinsics_within_3_sigmas_or_warned(&j);
        for (side, f) in ["left", "right"].iter().zip(truth) {
            let fx = j[side]["fx"].as_f64().unwrap();
            assert!((fx - f).abs() / f < 0.02, "{args:?}: {side} fx {fx} vs {f}");
        }
        let report = &j["report"];
        let segments = report["sequence"]["segments"].as_array().unwrap();
        let gauges: Vec<&str> = segments.iter().map(|s| s["gauge"].as_str().unwrap()).collect();
        assert_eq!(gauges, ["left00", "left02"], "{report}");
        let motions: Vec<(&str, &str, bool)> = report["motions"]
            .as_array()
            .unwrap()
            .iter()
            .map(|m| {
                (
                    m["view"].as_str().unwrap(),
                    m["relative_to"].as_str().unwrap(),
                    m["linear"].as_bool().unwrap(),
                )
            })
            .collect();
        assert_eq!(motions, [("left01", "left00", true), ("left03", "left02", true)], "{report}");
        for (m, deg) in report["motions"].as_array().unwrap().iter().zip([15.6, 37.5]) {
            let r = m["rotation_deg"].as_f64().unwrap();
            // The README's motions are known to about 2 deg.
            assert!((r - deg).abs() < 2.0, "{args:?}: rotation {r} for {deg}");
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}
