//! Replays every input the fuzzers (`fuzz/`, nightly) ever failed on, with the same checks
//! as the fuzz targets, so stable CI keeps them fixed. Inputs live in
//! `tests/fuzz_regressions/TARGET/` (one file each, named after the bug).

use std::path::PathBuf;

fn inputs(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let dir = crate::common::test_path("fuzz_regressions").join(target);
    let Ok(entries) = std::fs::read_dir(&dir) else { return Vec::new() };
    let mut files: Vec<PathBuf> = entries.filter_map(Result::ok).map(|e| e.path()).collect();
    files.sort();
    files.into_iter().map(|p| (p.clone(), std::fs::read(&p).unwrap())).collect()
}

/// Target `observations`: parse, write back, parse again: the same views bit for bit.
/// Found: serde_json's default float parser is not correctly rounded for long decimals
/// (`100.0888...8` with 100 digits read 1 ulp off), so a session written and read back
/// changed; fixed by serde_json's `float_roundtrip` feature.
#[test]
fn observations_regressions() {
    let cases = inputs("observations");
    assert!(!cases.is_empty());
    for (path, bytes) in cases {
        let Ok(text) = std::str::from_utf8(&bytes) else { continue };
        let Ok(views) = headalign_io::observations::parse_session(text, "fuzz") else { continue };
        let json = headalign_io::observations::session_to_json(&views).unwrap();
        let again = headalign_io::observations::parse_session(&json, "fuzz").unwrap();
        assert_eq!(again, views, "{}: round trip changed the session", path.display());
        let _ = headalign::verge_tilt::classify_views(&views);
    }
}

/// Target `view_json`: a view or an error naming the file.
#[test]
fn view_json_regressions() {
    for (path, bytes) in inputs("view_json") {
        let Ok(text) = std::str::from_utf8(&bytes) else { continue };
        match headalign_io::session::parse_view_json(text, "view.json") {
            Ok(meta) => assert!(!meta.name.is_empty() && meta.encoders.is_finite(), "{}", path.display()),
            Err(e) => assert!(e.to_string().contains("view.json"), "{}", path.display()),
        }
    }
}

/// Target `png_decode`: an image within the limits or an error. Found: a 673-byte
/// progressive JPEG declaring 4099 x 12336 pixels took 10 s to decode (a decompression
/// bomb); `MAX_PIXELS` now refuses it from the header, at once.
#[test]
fn png_decode_regressions() {
    let t0 = std::time::Instant::now();
    for (path, bytes) in inputs("png_decode") {
        if let Ok(img) = headalign_vision::GrayImage::decode(&bytes) {
            let max = headalign_vision::image::MAX_SIDE;
            assert!(img.width() <= max && img.height() <= max, "{}", path.display());
            let _ = headalign_io::session::check_image(&img, "left.png");
        }
    }
    // Generous: each input is refused from its header in microseconds.
    assert!(t0.elapsed().as_secs_f64() < 2.0, "decoding took {:?}", t0.elapsed());
}

/// The round trip that failed, stated directly: a long decimal pixel coordinate.
#[test]
fn long_decimals_round_trip_exactly() {
    let digits = "8".repeat(100);
    let text = format!("{{\"x\": 100.0{digits}}}");
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    let x = v["x"].as_f64().unwrap();
    assert_eq!(x, 100.08888888888889, "correctly rounded");
    let back: serde_json::Value = serde_json::from_str(&v.to_string()).unwrap();
    assert_eq!(back["x"].as_f64().unwrap().to_bits(), x.to_bits());
}
