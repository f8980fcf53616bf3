//! The crate's integration tests, one module per subject, linked into one test binary
//! (a binary per file costs a link of the whole crate graph each: build time of the suite).
//! Run one subject with `cargo test --release -p headalign-cli --test integration <module>::`.

mod bad_input;
mod check;
mod cli;
mod common;
mod experiment;
mod json_schemas;
mod lens;
mod live_check;
mod real_data;
mod recordings;
mod sessions;
mod threeview;
