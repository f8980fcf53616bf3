//! End-to-end test of the lens models in the image procedures: `demo --images --lens
//! radtan` on a simulated head whose cameras have a barrel lens aligns the head and
//! recovers the focal lengths and `k1`, writes the lens to the session (`session.json`,
//! the calibration files) and `replay` reproduces the run with it; `--lens pinhole` on the
//! same images is far off, and its verdict fails (exit code 1).

use std::path::Path;

use super::common::{assert_clean_failure, bin, ok_json, tmp};
use serde_json::Value;

/// A scenario file whose cameras have a barrel lens `k1` (the simulator's
/// `render.distortion`, applied to renders and points alike). The one place the test
/// builds the simulated lens.
fn sim_lens_scenario(path: &Path, k1: f64) {
    std::fs::write(path, format!("[render.distortion]\nk1 = {k1}\n")).unwrap();
}

/// `demo --images --stages verge-tilt` on the lensed scenario with `lens`, recording into
/// `session` (or not).
fn demo(scenario: &Path, lens: &str, session: Option<&Path>) -> Value {
    let mut cmd = bin();
    cmd.args(["demo", "--images", "--stages", "verge-tilt", "--json", "--lens", lens, "--scenario"])
        .arg(scenario);
    match session {
        Some(dir) => cmd.arg("--session").arg(dir),
        None => cmd.arg("--no-session"),
    };
    ok_json(&cmd.output().unwrap())
}

/// Seed 1, `k1 = -0.25` (about 55 px at the image corners), rendered images.
/// - `--lens radtan`: both focal lengths within 1 % and `k1` within 0.01 (the issue's
///   bars; measured 0.02 % and 0.0004), the aligned vergences and left elevation within
///   0.1 deg (measured 0.024 deg at most) with the right elevation's excess over the
///   unavoidable error too; `k1` has a sigma; `session.json` records the lens, the
///   session's `calibration/opencv_stereo.yaml` carries it, and `replay` gives the same
///   estimate bit for bit.
/// - `--lens pinhole` on the same images: the focal length error exceeds 20 % (measured
///   168 %: the lens is absorbed by a wrong projective solution), and the run fails its
///   verdict with one line that says to try `--lens auto`.
#[test]
fn a_lensed_head_aligns_with_its_lens_estimated() {
    let scenario = tmp("lens.toml");
    sim_lens_scenario(&scenario, -0.25);
    let session = tmp("radtan-session");
    let live = demo(&scenario, "radtan", Some(&session));
    let (est, truth) = (&live["estimate"], &live["truth"]);
    for side in ["left", "right"] {
        for f in ["fx", "fy"] {
            let (e, t) = (est[side][f].as_f64().unwrap(), truth[side][f].as_f64().unwrap());
            assert!((e / t - 1.0).abs() < 0.01, "{side} {f}: {e} vs {t}");
        }
        let k1 = est["lens"][side][0].as_f64().unwrap();
        assert!((k1 + 0.25).abs() < 0.01, "{side} k1 {k1}");
        assert!(est["lens"]["sigma"][format!("{side}.k1")].as_f64().unwrap() > 0.0, "{}", est["lens"]);
    }
    let errors = &live["errors"];
    for key in ["verge_err_l_deg", "verge_err_r_deg", "elev_err_l_deg", "elev_err_r_excess_deg"] {
        let e = errors[key].as_f64().unwrap();
        assert!(e.abs() < 0.1, "{key} {e}");
    }
    let info: Value =
        serde_json::from_str(&std::fs::read_to_string(session.join("session.json")).unwrap()).unwrap();
    assert_eq!(info["lens"], "radtan");
    let yaml = std::fs::read_to_string(session.join("calibration").join("opencv_stereo.yaml")).unwrap();
    let lenses = headalign::calibrate::read_opencv_lenses(&yaml, "opencv_stereo.yaml").unwrap();
    assert!((lenses[0].distortion.param("k1").unwrap() + 0.25).abs() < 0.01, "{yaml}");
    let replayed = ok_json(&bin().args(["replay", "--json"]).arg(&session).output().unwrap());
    assert_eq!(replayed["estimate"]["left"], est["left"]);
    assert_eq!(replayed["estimate"]["lens"], est["lens"]);

    assert_eq!(live["verdict"]["status"], "passed", "{}", live["verdict"]);

    // The pinhole on the same images: far off, and the run says so (issue 44: never a
    // confident wrong answer): the results are printed, then one error line naming the
    // failed verdict, exit code 1.
    let out = bin()
        .args(["demo", "--images", "--stages", "verge-tilt", "--json", "--lens", "pinhole", "--no-session"])
        .arg("--scenario")
        .arg(&scenario)
        .output()
        .unwrap();
    let stderr = assert_clean_failure(&out, &["try --lens auto"]);
    assert!(stderr.trim_end().chars().count() <= 300, "{stderr}");
    let pinhole: Value = serde_json::from_slice(&out.stdout).unwrap();
    let f_err = pinhole["errors"]["f_err_pct"].as_f64().unwrap();
    assert!(f_err.abs() > 20.0, "pinhole f error {f_err} %");
    assert!(pinhole["estimate"]["lens"].is_null(), "{}", pinhole["estimate"]["lens"]);
    assert_eq!(pinhole["verdict"]["status"], "failed", "{}", pinhole["verdict"]);
    assert!(!pinhole["warnings"].as_array().unwrap().is_empty(), "{}", pinhole["warnings"]);
}
