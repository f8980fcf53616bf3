//! The crate's integration tests, one module per subject, linked into one test binary
//! (a binary per file costs a link of the whole crate graph each: build time of the suite).
//! Run one subject with `cargo test --release -p headalign --test integration <module>::`.

mod common;
mod doc_links;
mod fixation;
mod patch_refinement;
mod robot_images;
mod robot_stages;
mod rotating_camera;
mod tracking_progress;
mod verge_tilt_procedure;
