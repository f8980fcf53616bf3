//! `headalign experiment`: every experiment runs with one seed per condition and writes
//! its CSV, PNG, SVG and Markdown; `fig5-pan-tilt`'s numbers are finite and its
//! noise-free rows exact; unknown names fail cleanly.
//!
//! One test per experiment (and `fig5-pan-tilt` in two halves) so that the test threads
//! share them out: with one seed an experiment runs its conditions one after another in
//! one process. The Monte-Carlo statistics themselves are `headalign experiment`'s
//! (`docs/results`), not these tests'.

use super::common::{bin, tmp_dir};
use std::path::{Path, PathBuf};
use std::process::Output;

/// `experiment NAME --trials 1` (one seed, run at every condition) with `extra` flags,
/// into its own folder; asserts success.
fn run_one_seed(name: &str, extra: &[&str]) -> (PathBuf, Output) {
    let dir = tmp_dir(name);
    let out = bin()
        .args(["experiment", name, "--trials", "1", "--out", dir.to_str().unwrap()])
        .args(extra)
        .output()
        .unwrap();
    assert!(out.status.success(), "{name}: {}", String::from_utf8_lossy(&out.stderr));
    (dir, out)
}

/// The four files of experiment `name` (output stem `stem`) exist and are not empty, the
/// CSV's rows have the header's columns, and the Markdown summary `markdown` (printed on
/// stdout, or the `.md` file) names the Cramer-Rao bound.
fn check_files(dir: &Path, name: &str, markdown: &str) {
    for ext in ["csv", "png", "svg", "md"] {
        let f = dir.join(format!("{name}.{ext}"));
        let len = std::fs::metadata(&f).map(|m| m.len()).unwrap_or(0);
        assert!(len > 100, "{name}: {} missing or empty", f.display());
    }
    let csv = std::fs::read_to_string(dir.join(format!("{name}.csv"))).unwrap();
    let header_cols = csv.lines().next().unwrap().split(',').count();
    for line in csv.lines().skip(1) {
        assert_eq!(line.split(',').count(), header_cols, "{name}: ragged CSV row {line}");
    }
    assert!(markdown.contains("Cramer-Rao"), "{name}: {markdown}");
}

/// Experiment `name` with one seed at every condition writes its files and prints its
/// Markdown summary.
fn writes_its_files(name: &str) {
    let (dir, out) = run_one_seed(name, &[]);
    check_files(&dir, name, &String::from_utf8_lossy(&out.stdout));
}

#[test]
fn fig5_verge_tilt_writes_its_files() {
    writes_its_files("fig5-verge-tilt");
}

#[test]
fn calibration_writes_its_files() {
    writes_its_files("calibration");
}

#[test]
fn rotation_writes_its_files() {
    writes_its_files("rotation");
}

#[test]
fn outliers_writes_its_files() {
    writes_its_files("outliers");
}

/// `lens` with one seed per lens at 1 px: its four files, one CSV row per trial with the
/// header's columns, both lenses in the summary with a coverage table, and the
/// procedure's tuning flags refused.
#[test]
fn lens_writes_its_files() {
    let dir = tmp_dir("lens");
    let out = bin()
        .args(["experiment", "lens", "--trials", "2", "--only", "1", "--out", dir.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    for ext in ["csv", "png", "svg", "md"] {
        let len = std::fs::metadata(dir.join(format!("lens.{ext}"))).map(|m| m.len()).unwrap_or(0);
        assert!(len > 100, "lens.{ext} missing or empty");
    }
    let csv = std::fs::read_to_string(dir.join("lens.csv")).unwrap();
    let header_cols = csv.lines().next().unwrap().split(',').count();
    assert_eq!(csv.lines().count(), 3, "{csv}");
    for line in csv.lines().skip(1) {
        assert_eq!(line.split(',').count(), header_cols, "ragged CSV row {line}");
        assert!(line.contains(",true,"), "failed trial: {line}");
    }
    let md = String::from_utf8_lossy(&out.stdout);
    for words in ["| radtan | 1 | 1/1 |", "| fisheye | 1 | 1/1 |", "95 % coverage", "right.k4"] {
        assert!(md.contains(words), "'{words}' missing in {md}");
    }
    let out = bin()
        .args(["experiment", "lens", "--bootstrap", "off", "--out", dir.to_str().unwrap()])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && stderr.contains("does not apply"), "{stderr}");
}

#[test]
fn coverage_writes_its_files() {
    writes_its_files("coverage");
}

/// `points` with `--json`: the files as for every experiment (the Markdown summary is then
/// the `.md` file, stdout being the JSON), and the JSON summary.
#[test]
fn points_writes_its_files_and_a_json_summary() {
    let (dir, out) = run_one_seed("points", &["--json"]);
    let md = std::fs::read_to_string(dir.join("points.md")).unwrap();
    check_files(&dir, "points", &md);
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v[0]["experiment"], "points");
    // 4 point counts with 3 deg rotations, and 50 points with the procedure's own.
    assert_eq!(v[0]["conditions"].as_array().map(|a| a.len()), Some(5));
    assert_eq!(v[0]["scene"], "default");
}

#[test]
fn clean_errors() {
    let dir = tmp_dir("errors");
    for (args, expected) in [
        (vec!["experiment", "nope"], "unknown experiment"),
        (vec!["experiment", "points", "--trials", "0"], "at least 1"),
        (vec!["experiment", "points", "--scene", "moon"], "unknown scene 'moon'"),
        (vec!["experiment", "all", "--scene", "paper"], "--scene is for single experiments"),
    ] {
        let out = bin().args(&args).arg("--out").arg(dir.to_str().unwrap()).output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && !stderr.contains("panicked"), "{stderr}");
        assert!(stderr.contains(expected), "expected '{expected}' in {stderr}");
    }
}

/// `fig5-pan-tilt` with one seed at the conditions `only` (values of the swept
/// parameter), exact encoder readings (`--encoder-noise 0`: the experiments' default reads
/// them with 0.01 deg of noise, which leaves 0.02 deg RMS at 0 px): the files exist, the
/// summary says why there is no bound, every trial succeeded with finite errors and a
/// positive reported sigma where there is noise, and the noise-free row is exact to 0.01
/// deg (the verge/tilt solver's tolerance; seed 1 measures 0.006 deg of pan, seeds 2-20
/// below 1e-5).
fn pan_tilt_rows(stem: &str, only: &str, rows_expected: usize) {
    let dir = tmp_dir(stem);
    let out = bin()
        .args(["experiment", "fig5-pan-tilt", "--trials", "1", "--encoder-noise", "0", "--only", only])
        .args(["--out", dir.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    for ext in ["csv", "png", "svg", "md"] {
        let f = dir.join(format!("fig5-pan-tilt.{ext}"));
        assert!(std::fs::metadata(&f).map(|m| m.len()).unwrap_or(0) > 100, "{} missing", f.display());
    }
    let md = std::fs::read_to_string(dir.join("fig5-pan-tilt.md")).unwrap();
    assert!(md.contains("No Cramer-Rao bound for the pan"), "{md}");
    let csv = std::fs::read_to_string(dir.join("fig5-pan-tilt.csv")).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), rows_expected);
    for r in &rows {
        assert_eq!(r.len(), header.len(), "ragged row {r:?}");
        assert_eq!(r[col("ok")], "true", "failed trial {r:?}");
        let num = |name: &str| r[col(name)].parse::<f64>().unwrap();
        let noise = num("noise_px");
        for name in
            ["pan_err_deg", "elev_err_l_deg", "elev_err_r_deg", "pan.aligned.est", "pan.aligned.truth"]
        {
            assert!(num(name).is_finite(), "{name} in {r:?}");
        }
        if noise > 0.0 {
            assert!(num("pan.aligned.sigma") > 0.0, "{r:?}");
        } else {
            assert!(num("pan_err_deg").abs() < 0.01, "{r:?}");
            assert!(num("elev_err_l_deg").abs() < 0.01, "{r:?}");
            assert!(num("elev_err_r_excess_deg").abs() < 0.01, "{r:?}");
        }
    }
}

/// `fig5-pan-tilt`'s `noise` group (0-3 px, pan zeros up to 20 deg, 0.10 m drive), with
/// its noise-free row.
#[test]
fn pan_tilt_noise_group_is_finite_and_exact_without_noise() {
    pan_tilt_rows("pan-noise", "0,0.5,1,2,3", 5);
}

/// `fig5-pan-tilt`'s `pan zero` and `drive` groups but their middle rows: `pan zero` 20
/// deg and `drive` 0.10 m are the `noise` group's 1 px condition again (1 px, 20 deg,
/// 0.10 m: the same scenario, and one seed for every condition), so the same trial.
#[test]
fn pan_tilt_pan_zero_and_drive_groups_are_finite() {
    pan_tilt_rows("pan-zero-drive", "10,40,60,0.05,0.2,0.4", 6);
}

/// `--scene paper`: the files are named `<experiment>-paper`, the summary names the scene,
/// and the trials ran in the near room (reconstruction and bounds finite).
#[test]
fn paper_scene_writes_its_own_files() {
    let dir = tmp_dir("paper");
    let out = bin()
        .args(["experiment", "points", "--scene", "paper", "--only", "50", "--trials", "2"])
        .arg("--out")
        .arg(dir.to_str().unwrap())
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    for ext in ["csv", "png", "svg", "md"] {
        let f = dir.join(format!("points-paper.{ext}"));
        assert!(std::fs::metadata(&f).map(|m| m.len()).unwrap_or(0) > 100, "{} missing", f.display());
    }
    assert!(!dir.join("points.csv").exists());
    let md = std::fs::read_to_string(dir.join("points-paper.md")).unwrap();
    assert!(md.contains("## points-paper — scene `paper`") && md.contains("](points-paper.png)"), "{md}");
    // One seed per condition: the fixed and the auto group at 50 points, both succeeded.
    assert!(md.contains("| fixed | 50 | 1/1 |") && md.contains("| auto | 50 | 1/1 |"), "{md}");
}
