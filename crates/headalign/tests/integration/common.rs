//! What the integration modules share: the repository's data folder.

use std::path::{Path, PathBuf};

/// A file or folder `rel` of the repository's `data/` folder (data/README.md): the real
/// images and sessions. A missing one fails the test that reads it.
pub fn data_path(rel: &str) -> PathBuf {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../../data")).join(rel)
}
