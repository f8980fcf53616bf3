//! The integration tests of `headalign-io`, one module per subject, linked into one test
//! binary. Run one subject with `cargo test --release -p headalign-io --test integration
//! <module>::`.

mod common;
mod fuzz_regressions;
mod recordings;
