//! `headalign experiment`: every experiment runs with one seed per condition and writes
//! its CSV, PNG, SVG and Markdown; `fig5-pan-tilt` and unknown names fail cleanly.

use std::path::PathBuf;
use std::process::Command;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_headalign"))
}

fn out_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("headalign-exp-tests-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[test]
fn every_experiment_writes_its_files() {
    for name in ["fig5-verge-tilt", "calibration", "points", "rotation", "outliers", "coverage"] {
        let dir = out_dir(name);
        // --trials 1: one seed, run at every condition.
        let out = bin()
            .args(["experiment", name, "--trials", "1", "--out", dir.to_str().unwrap()])
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{name}: {stderr}");
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
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(stdout.contains("Cramer-Rao"), "{name}: {stdout}");
    }
}

#[test]
fn json_summary_and_clean_errors() {
    let dir = out_dir("json");
    let out = bin()
        .args(["experiment", "points", "--trials", "1", "--json", "--out", dir.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v[0]["experiment"], "points");
    assert_eq!(v[0]["conditions"].as_array().map(|a| a.len()), Some(4));
    for (args, expected) in [
        (vec!["experiment", "fig5-pan-tilt"], "robot stage"),
        (vec!["experiment", "nope"], "unknown experiment"),
        (vec!["experiment", "points", "--trials", "0"], "at least 1"),
    ] {
        let out = bin().args(&args).arg("--out").arg(dir.to_str().unwrap()).output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && !stderr.contains("panicked"), "{stderr}");
        assert!(stderr.contains(expected), "expected '{expected}' in {stderr}");
    }
}
