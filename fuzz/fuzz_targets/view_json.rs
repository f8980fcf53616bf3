//! Fuzz the image-session `view.json` reader (`headalign_io::session::parse_view_json`):
//! any bytes give a validated view (non-empty name, finite readings within +-3600 deg) or
//! a typed error naming the file.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    match headalign_io::session::parse_view_json(text, "view.json") {
        Ok(meta) => {
            assert!(!meta.name.trim().is_empty());
            assert!(meta.encoders.is_finite());
        }
        Err(e) => assert!(e.to_string().contains("view.json")),
    }
});
