//! Helpers shared by the integration tests: fresh temporary folders and the crate's test
//! data.

use std::path::{Path, PathBuf};

/// A fresh, empty temporary folder for one test (`prefix` names the module, `name` the
/// test), unique to this process.
pub fn temp_dir(prefix: &str, name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("headalign-{prefix}-{}-{name}", std::process::id()));
    std::fs::remove_dir_all(&d).ok();
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A path under this crate's `tests/` folder (`tests/data/...`, `tests/fuzz_regressions/...`).
pub fn test_path(relative: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests").join(relative)
}
