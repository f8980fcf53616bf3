//! What the integration modules share: the binaries under test, the repository's data
//! folder, scratch paths (one folder per test process and module), and the checks of a
//! command's outcome (success with JSON, or a clean failure).

use std::path::{Path, PathBuf};
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

/// The repository's `data/` folder (data/README.md): the real images and sessions.
pub fn data_dir() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../../data"))
}

/// A fixture of this crate's `tests/data`.
pub fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data").join(name)
}

/// A path `name` in the scratch folder of this test process and of the calling module
/// (`headalign-cli-tests-<pid>/<module>/`, the module read from the caller's file name,
/// so that two modules' names never meet): the folder exists, the path does not
/// (anything left there by an earlier test of the process is removed).
#[track_caller]
pub fn tmp(name: &str) -> PathBuf {
    let caller = Path::new(std::panic::Location::caller().file());
    let module = caller.file_stem().map_or_else(|| "tests".into(), |s| s.to_string_lossy().into_owned());
    let dir = std::env::temp_dir().join(format!("headalign-cli-tests-{}", std::process::id())).join(module);
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join(name);
    std::fs::remove_dir_all(&p).ok();
    std::fs::remove_file(&p).ok();
    p
}

/// [`tmp`], created as an empty folder.
#[track_caller]
pub fn tmp_dir(name: &str) -> PathBuf {
    let p = tmp(name);
    std::fs::create_dir_all(&p).unwrap();
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
