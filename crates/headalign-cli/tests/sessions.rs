//! End-to-end tests of sessions, replay and the head protocol: `demo --images` records a
//! session (default location or `--session`), `replay` reproduces it bit for bit, and a
//! driver that dies, garbles or hangs stops the run with one line naming the request and
//! the session, which keeps every view captured so far. That `run --head-cmd` drives the
//! example simulator driver through the protocol to the demo's result is in `cli.rs`,
//! beside the image demo it compares with.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use serde_json::Value;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_headalign"))
}

fn driver() -> &'static str {
    env!("CARGO_BIN_EXE_headalign-sim-driver")
}

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("headalign-session-tests-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join(name);
    std::fs::remove_dir_all(&p).ok();
    p
}

fn ok_json(out: &Output) -> Value {
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).unwrap()
}

/// A non-zero exit with exactly one line on stderr containing every `expected` part.
fn assert_clean_failure(out: &Output, expected: &[&str]) -> String {
    let stderr = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(!out.status.success(), "expected failure; stderr: {stderr}");
    assert!(!stderr.contains("panicked"), "panic: {stderr}");
    assert_eq!(stderr.trim_end().lines().count(), 1, "one line expected: {stderr}");
    for part in expected {
        assert!(stderr.contains(part), "expected '{part}' in: {stderr}");
    }
    stderr
}

fn view_folders(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .filter_map(Result::ok)
        .filter(|e| e.path().join("view.json").exists())
        .map(|e| e.file_name().to_string_lossy().to_string())
        .collect();
    v.sort();
    v
}

fn replay(dir: &Path) -> Value {
    ok_json(&bin().args(["replay", dir.to_str().unwrap(), "--json"]).output().unwrap())
}

#[test]
fn demo_records_to_the_default_place_and_replays_bit_for_bit() {
    // No --session: ./headalign-sessions/<UTC time> in the working directory.
    let cwd = tmp("cwd");
    std::fs::create_dir_all(&cwd).unwrap();
    // A short robot run: verge/tilt, then the pan stage (drives recorded as events).
    let out = bin()
        .current_dir(&cwd)
        .args(["demo", "--images", "--seed", "1", "--stages", "verge-tilt,pan", "--json"])
        .output()
        .unwrap();
    let live = ok_json(&out);
    let base = cwd.join("headalign-sessions");
    let sessions: Vec<_> = std::fs::read_dir(&base).unwrap().filter_map(Result::ok).collect();
    assert_eq!(sessions.len(), 1);
    let dir = sessions[0].path();
    assert_eq!(live["session"].as_str().map(Path::new), Some(dir.strip_prefix(&cwd).unwrap()));
    // Verging captures, then the procedure's, each with its metadata; the report is the
    // --json output.
    let folders = view_folders(&dir);
    assert!(folders[0].ends_with("-verging-1"), "{folders:?}");
    assert!(
        folders.iter().any(|f| f.ends_with("-initial")) && folders.iter().any(|f| f.ends_with("-check-1"))
    );
    let meta: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join(&folders[2]).join("view.json")).unwrap())
            .unwrap();
    for key in ["format", "index", "name", "stage", "encoders", "commanded", "time_s", "unix_time_s"] {
        assert!(!meta[key].is_null(), "view.json lacks {key}: {meta}");
    }
    let report: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap();
    assert_eq!(report, live);
    assert!(dir.join("figure6.png").exists());
    // Replay: the same estimate and checks, bit for bit (JSON numbers round-trip exactly).
    let r = replay(&dir);
    assert_eq!(r["estimate"], live["estimate"]);
    assert_eq!(r["checks"], live["checks"]);
    assert_eq!(r["images"]["views"], live["images"]["views"]);
    assert_eq!(r["unplayed_events"], 0);
    // The robot stage too: the same drives, the same pan corrections, bit for bit; its
    // views record the drives since the capture before.
    assert_eq!(r["pan"], live["pan"]);
    assert!(live["pan"][0]["steps"].as_array().is_some_and(|s| s.len() == 2), "{}", live["pan"]);
    assert!(live["errors"]["pan_err_deg"].is_number());
    let pan2 = folders.iter().find(|f| f.ends_with("-pan-2")).expect("a pan-2 view");
    let meta: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join(pan2).join("view.json")).unwrap()).unwrap();
    assert_eq!(meta["stage"], "pan");
    assert_eq!(meta["vehicle"]["drives_m"], serde_json::json!([0.1]));
    let events = std::fs::read_to_string(dir.join("events.jsonl")).unwrap();
    assert!(events.contains("{\"op\":\"drive\",\"distance_m\":0.1}"), "no drive event");
    // A session is never overwritten.
    let out = bin().args(["demo", "--images", "--session", dir.to_str().unwrap()]).output().unwrap();
    assert_clean_failure(&out, &["already holds a session"]);
    // Replay of a folder that is not a session.
    let out = bin().args(["replay", cwd.to_str().unwrap()]).output().unwrap();
    assert_clean_failure(&out, &["session.json"]);
    std::fs::remove_dir_all(&cwd).ok();
}

#[test]
fn driver_failures_stop_the_run_and_keep_the_session() {
    // Requests: 1 hello, 2 capture, 3 read, 4 move, 5 capture, 6 read, ...
    for (flags, timeout, expect) in [
        (
            "--die-at 5",
            "30",
            vec!["exited (exit status: 3) before answering 'capture' (request 5)", "simulated crash"],
        ),
        ("--garble-at 6", "30", vec!["malformed answer to 'read' (request 6)", "this is not JSON"]),
        ("--sleep-at 5 --sleep-s 60", "3", vec!["no answer to 'capture' (request 5) within 3.0 s"]),
    ] {
        let dir = tmp(&format!("fail-{}", flags.len()));
        let t0 = std::time::Instant::now();
        let out = bin()
            .args(["run", "--head-timeout", timeout, "--session"])
            .arg(&dir)
            .args(["--head-cmd", &format!("'{}' --seed 1 {flags}", driver())])
            .output()
            .unwrap();
        let mut parts = expect.clone();
        let where_ = format!("kept in {}", dir.display());
        parts.push(&where_);
        let err = assert_clean_failure(&out, &parts);
        assert!(t0.elapsed().as_secs() < 40, "{flags}: took {:?}", t0.elapsed());
        // The views captured before the failure are on disk, complete.
        let folders = view_folders(&dir);
        let want = if flags.starts_with("--garble") { 2 } else { 1 };
        assert_eq!(folders.len(), want, "{flags}: {folders:?} ({err})");
        for f in &folders {
            assert!(dir.join(f).join("left.png").exists() && dir.join(f).join("right.png").exists());
        }
        let report: Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap();
        assert_eq!(report["status"], "failed");
        // Replaying the stopped session stops where the recording does.
        let out = bin().args(["replay", dir.to_str().unwrap()]).output().unwrap();
        assert_clean_failure(&out, &["the recorded run stopped there"]);
        std::fs::remove_dir_all(&dir).ok();
    }
    // A driver that cannot be started, and bad options.
    let out = bin().args(["run", "--head-cmd", "/nonexistent/driver --port x"]).output().unwrap();
    assert_clean_failure(&out, &["cannot start head driver '/nonexistent/driver'"]);
    let out = bin().args(["run", "--head-cmd", "x", "--head-timeout=0"]).output().unwrap();
    assert_clean_failure(&out, &["--head-timeout"]);
}

#[test]
fn point_mode_sessions_record_every_stage_and_replay() {
    let dir = tmp("points-3");
    let live =
        ok_json(&bin().args(["demo", "--seed", "3", "--json", "--session"]).arg(&dir).output().unwrap());
    let report: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap();
    assert_eq!(report, live);
    let folders = view_folders(&dir);
    assert_eq!(folders.first().map(String::as_str), Some("00-initial"));
    let meta: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join(&folders[1]).join("view.json")).unwrap())
            .unwrap();
    assert!(meta["capture"]["left"].as_array().is_some_and(|l| !l.is_empty()), "{meta}");
    // Replay: the same calibration and aligned readings, bit for bit.
    let r = replay(&dir);
    for side in ["left", "right"] {
        for k in ["fx", "fy", "cx", "cy"] {
            assert_eq!(r["estimate"][side][k], live["estimate"][side][k], "{side} {k}");
        }
    }
    assert_eq!(r["estimate"]["aligned_encoders"], live["estimate"]["aligned_encoders"]);
    // The robot stages (default: pan, steering, pan) are recorded and replayed too: their
    // captures are folders named by stage, every recorded event is played back, and the
    // corrections are the live run's, bit for bit.
    assert!(folders.iter().any(|f| f.ends_with("steering-1")), "{folders:?}");
    assert_eq!(r["unplayed_events"], 0, "{r}");
    assert_eq!(r["robot"]["pan"], live["pan"]);
    assert_eq!(r["robot"]["steering"], live["steering"]);
    // The views are also an observation session.
    let out = bin().args(["align", "--observations"]).arg(dir.join("observations.json")).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    // A run that fails after capturing (too few points to estimate) keeps its views.
    let dir2 = tmp("points-fail");
    let out = bin().args(["demo", "--seed", "3", "--points", "6", "--session"]).arg(&dir2).output().unwrap();
    assert_clean_failure(&out, &["too few tracks", &format!("kept in {}", dir2.display())]);
    assert_eq!(view_folders(&dir2).len(), 6);
    assert!(dir2.join("observations.json").exists());
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_dir_all(&dir2).ok();
}

/// `--auto-rotation` in point mode: the probes are recorded in their own stage (not
/// estimated from, not in observations.json), the verge/tilt stage has the chosen
/// rotations, and replay (which probes again on the recorded captures) is bit for bit.
#[test]
fn auto_rotation_sessions_record_the_probes_and_replay() {
    let dir = tmp("points-auto");
    let live = ok_json(
        &bin()
            .args(["demo", "--seed", "3", "--stages", "verge-tilt", "--auto-rotation", "--json", "--session"])
            .arg(&dir)
            .output()
            .unwrap(),
    );
    assert_eq!(live["rotations"]["rotation_deg"], 10.0, "{}", live["rotations"]);
    assert_eq!(live["rotations"]["verge_rotation_deg"], 10.0, "{}", live["rotations"]);
    let info: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("session.json")).unwrap()).unwrap();
    assert_eq!(info["auto_rotation"], true);
    let folders = view_folders(&dir);
    let stage = |f: &String| -> String {
        let meta: Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join(f).join("view.json")).unwrap()).unwrap();
        meta["stage"].as_str().unwrap_or("").to_string()
    };
    let probes = folders.iter().filter(|f| stage(f) == "rotation-probe").count();
    let first_vt = folders.iter().position(|f| stage(f) == "verge-tilt").unwrap();
    assert!(probes >= 9 && first_vt == probes, "probes first: {folders:?}");
    assert!(folders[first_vt].ends_with("-initial"), "{folders:?}");
    let observations: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("observations.json")).unwrap()).unwrap();
    let n_views = observations["views"].as_array().map_or(0, Vec::len);
    assert_eq!(n_views, folders.len() - probes, "observations.json holds the verge/tilt views only");
    let r = replay(&dir);
    for side in ["left", "right"] {
        for k in ["fx", "fy", "cx", "cy"] {
            assert_eq!(r["estimate"][side][k], live["estimate"][side][k], "{side} {k}");
        }
    }
    assert_eq!(r["estimate"]["aligned_encoders"], live["estimate"]["aligned_encoders"]);
    std::fs::remove_dir_all(&dir).ok();
}
