//! Fuzz the observation-session reader (`headalign_io::observations::parse_session`): any
//! bytes must give a session or a typed error, never a panic, a hang or a huge
//! allocation. A session that parses must write back to JSON and parse to the same views,
//! and classifying its views (the first step of `align`) must not panic either.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let Ok(views) = headalign_io::observations::parse_session(text, "fuzz") else { return };
    let json = headalign_io::observations::session_to_json(&views).expect("a parsed session serialises");
    let again = headalign_io::observations::parse_session(&json, "fuzz").expect("round trip parses");
    assert_eq!(again, views, "round trip changed the session");
    let _ = headalign::verge_tilt::classify_views(&views);
});
