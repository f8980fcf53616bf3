//! What the integration modules share: the binaries under test, a scratch path per test
//! process, and the checks of a command's outcome (success with JSON, or a clean failure).

use std::path::PathBuf;
use std::process::{Command, Output};

use serde_json::Value;

/// The `headalign` binary.
pub fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_headalign"))
}

/// The simulated head's driver process (`headalign-sim-driver`).
pub fn driver() -> &'static str {
    env!("CARGO_BIN_EXE_headalign-sim-driver")
}

/// A path `name` in this test process's scratch folder of `subject`: the folder exists,
/// the path does not (anything left there by an earlier test of the process is removed).
pub fn scratch(subject: &str, name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("headalign-{subject}-tests-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join(name);
    std::fs::remove_dir_all(&p).ok();
    std::fs::remove_file(&p).ok();
    p
}

/// The JSON on stdout of a command that must have succeeded.
pub fn ok_json(out: &Output) -> Value {
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).unwrap()
}

/// A clean failure: a non-zero exit that is not a panic, exactly one line on stderr, and
/// every `expected` part in it (case-insensitive). Returns stderr.
pub fn assert_clean_failure(out: &Output, expected: &[&str]) -> String {
    let stderr = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(!out.status.success(), "expected failure, got success; stderr: {stderr}");
    assert!(!stderr.contains("panicked") && !stderr.contains("stack backtrace"), "panic: {stderr}");
    assert_eq!(stderr.trim_end().lines().count(), 1, "one line expected: {stderr}");
    let lower = stderr.to_lowercase();
    for part in expected {
        assert!(lower.contains(&part.to_lowercase()), "expected '{part}' in: {stderr}");
    }
    stderr
}
