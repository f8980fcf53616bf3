//! What the crate's unit tests share: a scratch folder per test process.

use std::path::PathBuf;

/// An empty folder `name` in this test process's scratch folder
/// (`headalign-vision-tests-<pid>/<name>`; anything left there earlier is removed).
pub(crate) fn scratch_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("headalign-vision-tests-{}", std::process::id())).join(name);
    std::fs::remove_dir_all(&dir).ok();
    std::fs::create_dir_all(&dir).unwrap();
    dir
}
