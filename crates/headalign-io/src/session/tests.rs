//! Tests of the session format: bad input named, recording and replay, timestamps.

use std::path::Path;
use std::time::UNIX_EPOCH;

use headalign_platform::{
    Encoders, GrayImage, ImagingHead, PlatformError, StereoCapture, StereoHead, StereoImages,
};

use super::*;

fn write_view(dir: &Path, name: &str, left: &GrayImage, right: &GrayImage, json: &str) {
    let sub = dir.join(name);
    std::fs::create_dir_all(&sub).unwrap();
    left.save(&sub.join("left.png")).unwrap();
    right.save(&sub.join("right.png")).unwrap();
    std::fs::write(sub.join("view.json"), json).unwrap();
}

fn textured(w: u32, h: u32) -> GrayImage {
    let data = (0..w * h).map(|i| ((i * 7919) % 251) as u8).collect();
    GrayImage::new(w, h, data).unwrap()
}

#[test]
fn view_json_bad_input_is_named() {
    let enc = |pan: &str| {
        format!(
            r#"{{"name": "a", "encoders": {{"pan": {pan}, "elevation": 0, "verge_left": 0, "verge_right": 0}}}}"#
        )
    };
    let ok = parse_view_json(&enc("1.5"), "v.json").unwrap();
    assert_eq!((ok.name.as_str(), ok.encoders.pan), ("a", 1.5));
    let cases: Vec<(String, &str)> = vec![
        (String::new(), "EOF"),
        ("{\"name\": \"a\", \"enc".into(), "EOF"),
        ("[1, 2]".into(), "invalid type"),
        ("{\"name\": 3}".into(), "invalid type"),
        ("{\"name\": \"a\"}".into(), "missing field `encoders`"),
        (enc("1.5").replace("\"a\"", "\"  \""), "name is empty"),
        (enc("\"x\""), "invalid type"),
        (enc("1e999"), "number out of range"),
        (enc("1e308"), "beyond"),
        (enc("-3600.5"), "beyond"),
        (enc("99999999999999999999999"), "beyond"),
        (enc("NaN"), "expected value"),
    ];
    for (text, expect) in cases {
        let e = parse_view_json(&text, "v.json").unwrap_err().to_string();
        assert!(e.contains("v.json") && e.contains(expect), "'{text}': '{e}' lacks '{expect}'");
        assert!(!e.contains('\n'), "one line: {e}");
    }
}

#[test]
fn bad_sessions_name_the_file_and_the_problem() {
    let base = std::env::temp_dir().join(format!("headalign-session-{}", std::process::id()));
    let ok_json =
        r#"{"name": "initial", "encoders": {"pan": 0, "elevation": 0, "verge_left": 0, "verge_right": 0}}"#;
    let case = |name: &str, setup: &dyn Fn(&Path), expect: &[&str]| {
        let dir = base.join(name);
        std::fs::create_dir_all(&dir).unwrap();
        setup(&dir);
        let e = read_image_session(&dir).unwrap_err().to_string();
        for part in expect {
            assert!(e.contains(part), "{name}: '{e}' lacks '{part}'");
        }
    };
    case("empty", &|_| {}, &["holds no view folders"]);
    case(
        "blank",
        &|d| write_view(d, "00-initial", &GrayImage::filled(64, 48, 128), &textured(64, 48), ok_json),
        &["left.png", "blank"],
    );
    case(
        "mismatch",
        &|d| write_view(d, "00-initial", &textured(64, 48), &textured(60, 48), ok_json),
        &["left.png", "right.png", "same size"],
    );
    case(
        "bad-json",
        &|d| write_view(d, "00-initial", &textured(64, 48), &textured(64, 48), "{\"name\": 3}"),
        &["view.json"],
    );
    case(
        "unreadable",
        &|d| {
            write_view(d, "00-initial", &textured(64, 48), &textured(64, 48), ok_json);
            std::fs::write(d.join("00-initial").join("right.png"), b"not a png").unwrap();
        },
        &["right.png"],
    );
    case(
        "missing",
        &|d| {
            write_view(d, "00-initial", &textured(64, 48), &textured(64, 48), ok_json);
            std::fs::remove_file(d.join("00-initial").join("left.png")).unwrap();
        },
        &["left.png"],
    );
    case(
        "nan",
        &|d| {
            let j = r#"{"name": "a", "encoders": {"pan": 1e999, "elevation": 0, "verge_left": 0, "verge_right": 0}}"#;
            write_view(d, "00-initial", &textured(64, 48), &textured(64, 48), j)
        },
        &["view.json"],
    );
    case(
        "duplicate-name",
        &|d| {
            let named = ok_json.replace("\"initial\"", "\"01-again\"");
            write_view(d, "00-first", &textured(64, 48), &textured(64, 48), &named);
            write_view(d, "01-again", &textured(64, 48), &textured(64, 48), &named);
        },
        &["01-again", "view.json", "'01-again' is also the name of", "00-first", "its folder name"],
    );
    case(
        "directory-image",
        &|d| {
            write_view(d, "00-initial", &textured(64, 48), &textured(64, 48), ok_json);
            let p = d.join("00-initial").join("left.png");
            std::fs::remove_file(&p).unwrap();
            std::fs::create_dir_all(&p).unwrap();
        },
        &["left.png", "directory"],
    );
    // A good one reads back.
    let dir = base.join("good");
    write_view(&dir, "00-initial", &textured(64, 48), &textured(64, 48), ok_json);
    let v = read_image_session(&dir).unwrap();
    assert_eq!(v.len(), 1);
    assert_eq!(v[0].name, "initial");
    // An older view.json (no stage) counts as a verge/tilt view.
    assert!(v[0].stage.is_none() && v[0].is_verge_tilt());
    // A repeated name (sessions written before names were unique) reads back under the
    // view's folder name.
    write_view(&dir, "01-initial", &textured(64, 48), &textured(64, 48), ok_json);
    let v = read_image_session(&dir).unwrap();
    let names: Vec<_> = v.iter().map(|v| v.name.as_str()).collect();
    assert_eq!(names, ["initial", "01-initial"]);
    std::fs::remove_dir_all(&base).ok();
}

/// A head with a deterministic texture that shifts with the pan reading.
struct FakeHead {
    at: Encoders,
    reads: usize,
}

impl StereoHead for FakeHead {
    fn image_size(&self) -> [u32; 2] {
        [64, 48]
    }
    fn read_encoders(&mut self) -> Result<Encoders, PlatformError> {
        // Readings that are not the commanded ones (encoder noise), so a replay that
        // returned the commanded values would be caught.
        self.reads += 1;
        Ok(self.at.moved(headalign_platform::Joint::Pan, 1e-3 * self.reads as f64 + 1.0 / 3.0))
    }
    fn move_to(&mut self, target: &Encoders) -> Result<(), PlatformError> {
        self.at = *target;
        Ok(())
    }
    fn capture(&mut self) -> Result<StereoCapture, PlatformError> {
        Ok(StereoCapture { encoders: self.at, image_size: [64, 48], left: vec![], right: vec![] })
    }
}

impl ImagingHead for FakeHead {
    fn capture_images(&mut self) -> Result<StereoImages, PlatformError> {
        let shift = (self.at.pan * 10.0).round() as u32;
        let img = |k: u32| {
            let data = (0..64 * 48).map(|i| (((i + shift + k) * 7919) % 251) as u8).collect();
            GrayImage::new(64, 48, data).map_err(|e| PlatformError::Device(e.to_string()))
        };
        StereoImages::new(self.at, img(0)?, img(5)?)
    }
}

/// The calls a small procedure makes, and what it saw.
fn script<H: ImagingHead>(head: &mut H) -> Result<Vec<(Encoders, StereoImages)>, PlatformError> {
    let mut seen = Vec::new();
    for k in 0..3 {
        let e = head.read_encoders()?;
        head.move_to(&e.moved(headalign_platform::Joint::Pan, 0.7 * f64::from(k)))?;
        seen.push((head.read_encoders()?, head.capture_images()?));
    }
    Ok(seen)
}

#[test]
fn a_recorded_run_replays_exactly_and_a_diverging_one_is_named() {
    let dir = std::env::temp_dir().join(format!("headalign-rec-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    let info = SessionInfo::new("test", 3.0, 0, [64, 48]);
    let mut fake = FakeHead { at: Encoders { pan: 0.1, ..Encoders::default() }, reads: 0 };
    let writer = SessionWriter::create(&dir, &info).unwrap();
    let mut rec = RecordingHead::new(&mut fake, writer);
    rec.set_stage(
        STAGE_VERGING,
        vec![("first".into(), Encoders { pan: 0.1 + 1.0 / 3.0 + 1e-3, ..Encoders::default() })],
        "x",
    );
    let live = script(&mut rec).unwrap();
    assert_eq!(rec.writer().views(), 3);
    let writer = rec.into_writer();
    writer.write_report(&serde_json::json!({"ok": 1})).unwrap();
    // The folders, named by the plan or numbered, and their metadata.
    let views = read_image_session(&dir).unwrap();
    let names: Vec<_> = views.iter().map(|v| v.name.as_str()).collect();
    assert_eq!(names, ["first", "x-1", "x-2"]);
    assert!(views.iter().all(|v| !v.is_verge_tilt()));
    let meta = read_view_meta(&dir.join("01-x-1").join("view.json")).unwrap();
    assert_eq!(meta.index, Some(1));
    assert!(meta.commanded.is_some() && meta.time_s.is_some_and(|t| t >= 0.0));
    // Replay: the same readings and images, bit for bit, and nothing left over.
    let mut replay = ReplayHead::open(&dir).unwrap();
    let again = script(&mut replay).unwrap();
    assert_eq!(replay.remaining(), 0);
    for ((e1, i1), (e2, i2)) in live.iter().zip(&again) {
        assert_eq!(e1, e2);
        assert_eq!(i1, i2);
    }
    // One more call than recorded: the end of the recording is named.
    let e = replay.capture_images().unwrap_err().to_string();
    assert!(e.contains("ends after 12 events"), "{e}");
    // A different procedure: the event where it diverges is named.
    let mut replay = ReplayHead::open(&dir).unwrap();
    replay.read_encoders().unwrap();
    let e = replay.move_to(&Encoders::default()).unwrap_err().to_string();
    assert!(e.contains("diverged") && e.contains("event 2"), "{e}");
    let mut replay = ReplayHead::open(&dir).unwrap();
    let e = replay.capture_images().unwrap_err().to_string();
    assert!(e.contains("asks to capture") && e.contains("\"op\":\"read\""), "{e}");
    // A session is never overwritten.
    let e = SessionWriter::create(&dir, &info).unwrap_err().to_string();
    assert!(e.contains("already holds a session"), "{e}");
    // Damaged files name themselves.
    std::fs::write(dir.join("events.jsonl"), "{\"op\":\"capture\",\"folder\":\"../x\"}\n").unwrap();
    let e = ReplayHead::open(&dir).unwrap_err().to_string();
    assert!(e.contains("events.jsonl' line 1"), "{e}");
    std::fs::write(dir.join("events.jsonl"), "{\"op\":\"jump\"}\n").unwrap();
    assert!(ReplayHead::open(&dir).unwrap_err().to_string().contains("line 1"));
    std::fs::write(dir.join("session.json"), "{\"format\": 1}").unwrap();
    assert!(ReplayHead::open(&dir).unwrap_err().to_string().contains("session.json"));
    std::fs::remove_dir_all(&dir).ok();
}

/// View names are unique in a session: a stage that runs again continues its numbers,
/// and a planned name captured twice gets a suffix; every reader accepts the session.
#[test]
fn a_stage_that_runs_again_continues_its_numbers() {
    let dir = std::env::temp_dir().join(format!("headalign-names-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    let info = SessionInfo::new("test", 3.0, 0, [64, 48]);
    let mut fake = FakeHead { at: Encoders::default(), reads: 0 };
    let mut rec = RecordingHead::new(&mut fake, SessionWriter::create(&dir, &info).unwrap());
    for stage in ["pan", "steering", "pan"] {
        rec.set_stage(stage, Vec::new(), stage);
        rec.capture_images().unwrap();
        rec.capture_images().unwrap();
    }
    let target = Encoders { pan: 0.5, ..Encoders::default() };
    rec.move_to(&target).unwrap();
    rec.set_stage("check", vec![("again".into(), target)], "check");
    rec.capture_images().unwrap();
    rec.capture_images().unwrap();
    drop(rec);
    let names: Vec<String> = read_image_session(&dir).unwrap().into_iter().map(|v| v.name).collect();
    assert_eq!(names, ["pan-1", "pan-2", "steering-1", "steering-2", "pan-3", "pan-4", "again", "again-2"]);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn utc_timestamps_are_civil_dates() {
    let t = |s: u64| utc_timestamp(UNIX_EPOCH + std::time::Duration::from_secs(s), true);
    assert_eq!(t(0), "1970-01-01T00:00:00Z");
    assert_eq!(t(1_700_000_000), "2023-11-14T22:13:20Z");
    assert_eq!(t(951_782_400), "2000-02-29T00:00:00Z");
    assert_eq!(utc_timestamp(UNIX_EPOCH + std::time::Duration::from_secs(86_399), false), "19700101T235959Z");
}

proptest::proptest! {
    /// Replay is bit for bit only if recorded readings parse back exactly: any finite
    /// reading survives an event line unchanged (`float_roundtrip`).
    #[test]
    fn recorded_readings_round_trip_exactly(
        pan in proptest::num::f64::NORMAL | proptest::num::f64::SUBNORMAL | proptest::num::f64::ZERO,
        elevation in -90.0f64..90.0,
        verge_left in -1e-300f64..1e-300,
        verge_right in proptest::num::f64::ANY,
    ) {
        let verge_right = if verge_right.is_finite() { verge_right } else { 0.0 };
        let e = Encoders { pan, elevation, verge_left, verge_right };
        for event in [Event::Read { encoders: e }, Event::Move { target: e }] {
            let line = serde_json::to_string(&event).unwrap();
            let back: Event = serde_json::from_str(&line).unwrap();
            let (Event::Read { encoders: b } | Event::Move { target: b }) = back else {
                panic!("wrong event {line}")
            };
            for j in headalign_platform::Joint::ALL {
                proptest::prop_assert_eq!(b.get(j).to_bits(), e.get(j).to_bits(), "{}", line);
            }
        }
    }
}
