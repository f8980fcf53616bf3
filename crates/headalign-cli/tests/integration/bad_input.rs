//! Bad input of every kind, for every command that reads a file: `align --observations
//! FILE`, `align --images DIR`, `demo --scenario FILE`, and the recording flags on folders
//! that are no recording. Each case must fail with a
//! non-zero exit and exactly one line on stderr that names the file (or folder) and the
//! problem; never a panic or a backtrace. The inputs that fuzzing (`fuzz/`) found are
//! replayed here too, so CI checks them without a nightly toolchain.

use std::path::{Path, PathBuf};
use std::process::Output;

use headalign_vision::GrayImage;

use super::common::{bin, tmp_dir};
use serde_json::{Value, json};

fn run(args: &[&str]) -> Output {
    bin().args(args).env("RUST_BACKTRACE", "1").output().unwrap()
}

/// Non-zero exit, one line on stderr, no panic or backtrace, and every `expected` part
/// (case-insensitive) in the message.
fn assert_clean_failure(case: &str, out: &Output, expected: &[&str]) {
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{case}: expected failure, got success; stderr: {stderr}");
    assert_eq!(out.status.code(), Some(1), "{case}: exit code (a signal or abort is not clean): {stderr}");
    assert!(!stderr.contains("panicked") && !stderr.contains("stack backtrace"), "{case}: panic: {stderr}");
    assert_eq!(stderr.trim_end().lines().count(), 1, "{case}: one line expected: {stderr}");
    // Issue 44: at most about 300 characters (the full text of a longer one goes to a file).
    let chars = stderr.trim_end().chars().count();
    assert!(chars <= 300, "{case}: {chars} characters, at most 300 expected: {stderr}");
    for part in expected {
        assert!(
            stderr.to_lowercase().contains(&part.to_lowercase()),
            "{case}: expected '{part}' in: {stderr}"
        );
    }
}

/// A small valid observation session (three views, eight tracks each side): valid JSON
/// that the reader accepts; each case below breaks one thing.
fn observations() -> Value {
    let view = |name: &str, pan: f64, elev: f64| {
        let pts: Vec<Value> = (0..8).map(|i| json!([i, 100.0 + 20.0 * f64::from(i), 200.0])).collect();
        json!({"name": name, "encoders": {"pan": pan, "elevation": elev, "verge_left": 0.0, "verge_right": 0.0},
               "left": pts, "right": pts})
    };
    json!({"format": "headalign-observations/1", "image_size": [768, 576],
           "views": [view("initial", 0.0, 0.0), view("elevation", 0.0, 3.0), view("pan", 3.0, 0.0)]})
}

/// The observation session `observations()` changed by `f`, as file contents.
fn edited(f: impl FnOnce(&mut Value)) -> Vec<u8> {
    let mut v = observations();
    f(&mut v);
    serde_json::to_string(&v).unwrap().into()
}

/// The valid observation session as text, for cases that cut or rewrite its bytes.
fn good_observations() -> String {
    serde_json::to_string(&observations()).unwrap()
}

/// Each case's bytes written to a file of its own in a fresh folder named by `test`, and
/// `align --observations FILE` must fail cleanly naming the file and the case's expected
/// parts.
fn check_observation_cases(test: &str, cases: &[(&str, Vec<u8>, Vec<&str>)]) {
    let dir = tmp_dir(test);
    for (i, (case, bytes, expected)) in cases.iter().enumerate() {
        let path = dir.join(format!("case{i}.json"));
        std::fs::write(&path, bytes).unwrap();
        let p = path.to_str().unwrap();
        let mut parts = expected.clone();
        parts.push(p);
        assert_clean_failure(case, &run(&["align", "--observations", p]), &parts);
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// Files that are not JSON, or not readable as a file, at all.
#[test]
fn align_observations_malformed_json() {
    let good = good_observations();
    // (case, file contents, expected message parts besides the file name)
    check_observation_cases(
        "obs-malformed",
        &[
            ("empty file", vec![], vec!["malformed JSON", "EOF"]),
            ("whitespace only", b"  \n".to_vec(), vec!["malformed JSON"]),
            (
                "truncated at a third",
                good.as_bytes()[..good.len() / 3].to_vec(),
                vec!["malformed JSON", "EOF"],
            ),
            ("truncated before the end", good.as_bytes()[..good.len() - 1].to_vec(), vec!["malformed JSON"]),
            ("not JSON", b"views: 3".to_vec(), vec!["malformed JSON"]),
            (
                "binary, not UTF-8",
                vec![0xff, 0xfe, 0x00, 0x89, b'P', b'N', b'G'],
                vec!["cannot read", "UTF-8"],
            ),
            ("an array, not an object", b"[1, 2, 3]".to_vec(), vec!["malformed JSON", "invalid type"]),
            ("null", b"null".to_vec(), vec!["malformed JSON", "invalid type"]),
            ("NaN literal", good.replacen("3.0", "NaN", 1).into_bytes(), vec!["malformed JSON"]),
            (
                "deeply nested",
                format!("{}{}", "[".repeat(10_000), "]".repeat(10_000)).into_bytes(),
                vec!["malformed JSON"],
            ),
        ],
    );
    // Not a readable file.
    let dir = tmp_dir("obs-unreadable");
    let d = dir.to_str().unwrap();
    assert_clean_failure("a directory", &run(&["align", "--observations", d]), &[d, "cannot read"]);
    let missing = dir.join("missing.json");
    let m = missing.to_str().unwrap();
    assert_clean_failure("missing file", &run(&["align", "--observations", m]), &[m, "cannot read"]);
    std::fs::remove_dir_all(&dir).ok();
}

/// An error longer than 300 characters (here a long missing path) is cut to one line of
/// at most 300 that names the file holding its full text; with `--out` that file is
/// `error.txt` there.
#[test]
fn long_errors_are_cut_and_written_in_full() {
    let dir = tmp_dir("long-error");
    let missing = dir.join(format!("{}.json", "a-very-long-file-name".repeat(16)));
    let m = missing.to_str().unwrap();
    let out_dir = dir.join("out");
    std::fs::create_dir_all(&out_dir).unwrap();
    let out = run(&["align", "--observations", m, "--out", out_dir.to_str().unwrap()]);
    assert_clean_failure("long missing path", &out, &["a-very-long-file-name", "full message"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    let full = std::fs::read_to_string(out_dir.join("error.txt")).unwrap_or_default();
    assert!(
        stderr.contains("error.txt") && full.contains(m) && full.contains("cannot read"),
        "{stderr}\n{full}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// JSON of the wrong shape: wrong types, missing or unknown fields, a wrong format tag.
#[test]
fn align_observations_wrong_types_and_fields() {
    check_observation_cases(
        "obs-fields",
        &[
            (
                "wrong type: pan is a string",
                edited(|v| v["views"][0]["encoders"]["pan"] = json!("x")),
                vec!["invalid type"],
            ),
            ("wrong type: views is an object", edited(|v| v["views"] = json!({})), vec!["invalid type"]),
            (
                "wrong type: pixel is a string",
                edited(|v| v["views"][0]["left"][0][1] = json!("1")),
                vec!["invalid type"],
            ),
            (
                "wrong type: observation has 2 numbers",
                edited(|v| v["views"][0]["left"][0] = json!([1, 2.0])),
                vec!["invalid length"],
            ),
            (
                "missing field: format",
                edited(|v| drop(v.as_object_mut().unwrap().remove("format"))),
                vec!["missing field `format`"],
            ),
            (
                "missing field: encoders",
                edited(|v| drop(v["views"][1].as_object_mut().unwrap().remove("encoders"))),
                vec!["missing field `encoders`"],
            ),
            (
                "missing field: verge_right",
                edited(|v| drop(v["views"][1]["encoders"].as_object_mut().unwrap().remove("verge_right"))),
                vec!["missing field `verge_right`"],
            ),
            ("unknown field", edited(|v| v["extra"] = json!(1)), vec!["unknown field `extra`"]),
            (
                "wrong format tag",
                edited(|v| v["format"] = json!("headalign-observations/9")),
                vec!["unsupported format"],
            ),
        ],
    );
}

/// Numbers out of their range: encoders, pixels, track ids and image sizes.
#[test]
fn align_observations_numbers_out_of_range() {
    let good = good_observations();
    check_observation_cases(
        "obs-numbers",
        &[
            (
                "infinite encoder (1e999)",
                good.replacen("3.0", "1e999", 1).into_bytes(),
                vec!["number out of range"],
            ),
            (
                "huge encoder 1e308",
                edited(|v| v["views"][1]["encoders"]["elevation"] = json!(1e308)),
                vec!["beyond +-3600"],
            ),
            ("huge pixel 1e308", edited(|v| v["views"][1]["left"][0][1] = json!(1e308)), vec!["outside"]),
            ("negative pixel", edited(|v| v["views"][1]["left"][0][2] = json!(-3.0)), vec!["outside"]),
            (
                "track id beyond u64",
                good.replacen("[0,", "[99999999999999999999,", 1).into_bytes(),
                vec!["malformed JSON"],
            ),
            (
                "negative track id",
                edited(|v| v["views"][0]["left"][0][0] = json!(-1)),
                vec!["malformed JSON"],
            ),
            (
                "fractional track id",
                edited(|v| v["views"][0]["left"][0][0] = json!(1.5)),
                vec!["malformed JSON"],
            ),
            ("negative image size", edited(|v| v["image_size"] = json!([-768, 576])), vec!["malformed JSON"]),
            (
                "zero image size",
                edited(|v| v["image_size"] = json!([0, 576])),
                vec!["not a valid image size"],
            ),
            (
                "image size beyond u32",
                edited(|v| v["image_size"] = json!([1e10, 576])),
                vec!["malformed JSON"],
            ),
            (
                "huge image size",
                edited(|v| v["image_size"] = json!([4_000_000_000u32, 576])),
                vec!["not a valid image size"],
            ),
            (
                "image size with 3 numbers",
                edited(|v| v["image_size"] = json!([768, 576, 3])),
                vec!["malformed JSON"],
            ),
        ],
    );
}

/// Well-formed sessions whose views do not fit together.
#[test]
fn align_observations_inconsistent_views() {
    check_observation_cases(
        "obs-views",
        &[
            ("no views", edited(|v| v["views"] = json!([])), vec!["needs at least 3"]),
            ("empty view name", edited(|v| v["views"][0]["name"] = json!(" ")), vec!["empty name"]),
            (
                "duplicate view name",
                edited(|v| v["views"][1]["name"] = json!("initial")),
                vec!["appears twice"],
            ),
            ("duplicate track", edited(|v| v["views"][0]["left"][1][0] = json!(0)), vec!["appears twice"]),
            (
                "no tracks at all",
                edited(|v| {
                    for view in v["views"].as_array_mut().unwrap() {
                        view["left"] = json!([]);
                        view["right"] = json!([]);
                    }
                }),
                vec!["too few tracks"],
            ),
        ],
    );
}

fn textured(w: u32, h: u32, seed: u32) -> GrayImage {
    let data = (0..w * h).map(|i| ((i.wrapping_mul(7919).wrapping_add(seed * 31)) % 251) as u8).collect();
    GrayImage::new(w, h, data).unwrap()
}

fn view_json(name: &str, elevation: f64) -> String {
    json!({"name": name, "encoders": {"pan": 0.0, "elevation": elevation, "verge_left": 0.0, "verge_right": 0.0}})
        .to_string()
}

/// Three 64 x 48 textured views, as `demo --images --save` lays them out.
fn image_session(dir: &Path) {
    for (i, (name, elev)) in [("initial", 0.0), ("elevation", 3.0), ("pan", 0.0)].into_iter().enumerate() {
        let sub = dir.join(format!("{i:02}-{name}"));
        std::fs::create_dir_all(&sub).unwrap();
        textured(64, 48, i as u32).save(&sub.join("left.png")).unwrap();
        textured(64, 48, i as u32 + 7).save(&sub.join("right.png")).unwrap();
        std::fs::write(sub.join("view.json"), view_json(name, elev)).unwrap();
    }
}

fn crc32(data: &[u8]) -> u32 {
    let mut c = 0xffff_ffffu32;
    for &b in data {
        c ^= u32::from(b);
        for _ in 0..8 {
            c = if c & 1 != 0 { 0xedb8_8320 ^ (c >> 1) } else { c >> 1 };
        }
    }
    !c
}

fn png_chunk(png: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
    png.extend_from_slice(&(data.len() as u32).to_be_bytes());
    let start = png.len();
    png.extend_from_slice(kind);
    png.extend_from_slice(data);
    let crc = crc32(&png[start..]);
    png.extend_from_slice(&crc.to_be_bytes());
}

/// A valid PNG signature and header declaring `w x h` 8-bit grey, then nothing.
fn png_header(w: u32, h: u32) -> Vec<u8> {
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = w.to_be_bytes().to_vec();
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[8, 0, 0, 0, 0]);
    png_chunk(&mut png, b"IHDR", &ihdr);
    png
}

/// A PNG declaring `w x h` with a few bytes of (zlib-stored, empty) image data: a tiny
/// file that would decode to a huge image.
fn png_bomb(w: u32, h: u32) -> Vec<u8> {
    let mut png = png_header(w, h);
    png_chunk(&mut png, b"IDAT", &[0x78, 0x01, 0x01, 0x00, 0x00, 0xff, 0xff, 0x00, 0x00, 0x00, 0x01]);
    png_chunk(&mut png, b"IEND", &[]);
    png
}

type Setup = Box<dyn Fn(&Path)>;

/// A case that writes `bytes` to the file `rel` of the session.
fn write_file(rel: &'static str, bytes: Vec<u8>) -> Setup {
    Box::new(move |d: &Path| std::fs::write(d.join(rel), &bytes).unwrap())
}

/// A case that replaces the elevation view's view.json by `text`.
fn view_json_case(text: &'static str) -> Setup {
    write_file("01-elevation/view.json", text.as_bytes().to_vec())
}

/// A good textured PNG written to `root/good.png`: its path and its bytes.
fn good_png(root: &Path) -> (PathBuf, Vec<u8>) {
    let p = root.join("good.png");
    textured(64, 48, 3).save(&p).unwrap();
    let bytes = std::fs::read(&p).unwrap();
    (p, bytes)
}

/// Each case breaks a good session (`image_session`) of its own under `root`, and
/// `align --images DIR` must fail cleanly naming the folder and the case's expected parts
/// (the file, then the problem).
fn check_image_cases(root: &Path, cases: &[(&str, Setup, Vec<&str>)]) {
    for (i, (case, setup, expected)) in cases.iter().enumerate() {
        let dir = root.join(format!("case{i}"));
        image_session(&dir);
        setup(&dir);
        let d = dir.to_str().unwrap();
        let out = run(&["align", "--images", d]);
        let mut parts = expected.clone();
        parts.push(d);
        assert_clean_failure(case, &out, &parts);
    }
}

/// A view's view.json broken: malformed, the wrong shape, numbers out of range, names
/// that are empty or taken, not a file.
#[test]
fn align_images_bad_view_json() {
    let root = tmp_dir("images-json");
    check_image_cases(
        &root,
        &[
            ("view.json empty", view_json_case(""), vec!["01-elevation/view.json", "EOF"]),
            (
                "view.json truncated",
                view_json_case("{\"name\": \"elevation\", \"encoders\": {\"pan\": 0"),
                vec!["01-elevation/view.json", "EOF"],
            ),
            (
                "view.json not an object",
                view_json_case("[]"),
                vec!["01-elevation/view.json", "invalid length"],
            ),
            (
                "view.json wrong type",
                view_json_case(r#"{"name": 5, "encoders": {}}"#),
                vec!["01-elevation/view.json", "invalid type"],
            ),
            (
                "view.json missing encoders",
                view_json_case(r#"{"name": "e"}"#),
                vec!["01-elevation/view.json", "missing field `encoders`"],
            ),
            (
                "view.json missing joint",
                view_json_case(r#"{"name": "e", "encoders": {"pan": 0, "elevation": 0, "verge_left": 0}}"#),
                vec!["01-elevation/view.json", "missing field `verge_right`"],
            ),
            (
                "view.json NaN",
                view_json_case(
                    r#"{"name": "e", "encoders": {"pan": NaN, "elevation": 0, "verge_left": 0, "verge_right": 0}}"#,
                ),
                vec!["01-elevation/view.json"],
            ),
            (
                "view.json inf",
                view_json_case(
                    r#"{"name": "e", "encoders": {"pan": -1e400, "elevation": 0, "verge_left": 0, "verge_right": 0}}"#,
                ),
                vec!["01-elevation/view.json", "out of range"],
            ),
            (
                "view.json 1e308",
                view_json_case(
                    r#"{"name": "e", "encoders": {"pan": 1e308, "elevation": 0, "verge_left": 0, "verge_right": 0}}"#,
                ),
                vec!["01-elevation/view.json", "beyond"],
            ),
            (
                "view.json i64 overflow",
                view_json_case(
                    r#"{"name": "e", "encoders": {"pan": 9223372036854775808000, "elevation": 0, "verge_left": 0, "verge_right": 0}}"#,
                ),
                vec!["01-elevation/view.json", "beyond"],
            ),
            (
                "view.json empty name",
                view_json_case(
                    r#"{"name": "", "encoders": {"pan": 0, "elevation": 0, "verge_left": 0, "verge_right": 0}}"#,
                ),
                vec!["01-elevation/view.json", "name is empty"],
            ),
            (
                // A repeated name is known by its folder name (older sessions repeat a
                // stage's names); an error only when that is taken too.
                "view.json duplicate name and folder name",
                Box::new(|d: &Path| {
                    let json = |elevation: u32| {
                        format!(
                            r#"{{"name": "01-elevation", "encoders": {{"pan": 0, "elevation": {elevation}, "verge_left": 0, "verge_right": 0}}}}"#
                        )
                    };
                    std::fs::write(d.join("00-initial/view.json"), json(0)).unwrap();
                    std::fs::write(d.join("01-elevation/view.json"), json(3)).unwrap();
                }),
                vec!["01-elevation/view.json", "also the name of", "its folder name"],
            ),
            (
                "view.json is a directory",
                Box::new(|d: &Path| {
                    std::fs::remove_file(d.join("01-elevation/view.json")).unwrap();
                    std::fs::create_dir(d.join("01-elevation/view.json")).unwrap();
                }),
                vec!["01-elevation/view.json", "cannot read"],
            ),
        ],
    );
    std::fs::remove_dir_all(&root).ok();
}

/// A view's images missing, not images, truncated, declaring absurd sizes, blank, or of
/// sizes that do not match.
#[test]
fn align_images_bad_image_files() {
    let root = tmp_dir("images-files");
    let (_, good) = good_png(&root);
    check_image_cases(
        &root,
        &[
            (
                "missing image",
                Box::new(|d: &Path| std::fs::remove_file(d.join("02-pan/left.png")).unwrap()),
                vec!["02-pan/left.png", "No such file"],
            ),
            (
                "image is a directory",
                Box::new(|d: &Path| {
                    std::fs::remove_file(d.join("02-pan/right.png")).unwrap();
                    std::fs::create_dir(d.join("02-pan/right.png")).unwrap();
                }),
                vec!["02-pan/right.png", "directory"],
            ),
            ("empty PNG", write_file("00-initial/left.png", vec![]), vec!["00-initial/left.png"]),
            (
                "not a PNG",
                write_file("00-initial/left.png", b"hello, world".to_vec()),
                vec!["00-initial/left.png", "format"],
            ),
            (
                "truncated PNG",
                write_file("00-initial/right.png", good[..good.len() / 2].to_vec()),
                vec!["00-initial/right.png"],
            ),
            (
                "PNG header only",
                write_file("00-initial/right.png", png_header(64, 48)),
                vec!["00-initial/right.png"],
            ),
            (
                "PNG declaring 1e6 x 1e6",
                write_file("00-initial/left.png", png_header(1_000_000, 1_000_000)),
                vec!["00-initial/left.png", "limit"],
            ),
            (
                "PNG declaring 8000 x 8000 (a decompression bomb)",
                write_file("00-initial/left.png", png_bomb(8000, 8000)),
                vec!["00-initial/left.png", "declares 8000x8000 pixels"],
            ),
            (
                "PNG declaring zero width",
                write_file("00-initial/left.png", png_header(0, 48)),
                vec!["00-initial/left.png"],
            ),
            (
                "blank image",
                Box::new(|d: &Path| {
                    GrayImage::filled(64, 48, 90).save(&d.join("01-elevation/left.png")).unwrap()
                }),
                vec!["01-elevation/left.png", "blank"],
            ),
            (
                "left and right sizes differ",
                Box::new(|d: &Path| textured(60, 48, 1).save(&d.join("01-elevation/right.png")).unwrap()),
                vec!["01-elevation/left.png", "01-elevation/right.png", "same size"],
            ),
            (
                "view size differs from the first",
                Box::new(|d: &Path| {
                    textured(32, 48, 1).save(&d.join("02-pan/left.png")).unwrap();
                    textured(32, 48, 2).save(&d.join("02-pan/right.png")).unwrap();
                }),
                vec!["02-pan/left.png", "first view"],
            ),
        ],
    );
    std::fs::remove_dir_all(&root).ok();
}

/// Folders that are not sessions, or sessions whose images cannot be tracked.
#[test]
fn align_images_bad_folders() {
    let root = tmp_dir("images-folders");
    check_image_cases(
        &root,
        &[
            (
                "no view folders",
                Box::new(|d: &Path| {
                    for v in ["00-initial", "01-elevation", "02-pan"] {
                        std::fs::remove_dir_all(d.join(v)).unwrap();
                    }
                }),
                vec!["holds no view folders"],
            ),
            (
                "textured but too small to track",
                Box::new(|d: &Path| {
                    for v in ["00-initial", "01-elevation", "02-pan"] {
                        textured(4, 3, 1).save(&d.join(v).join("left.png")).unwrap();
                        textured(4, 3, 2).save(&d.join(v).join("right.png")).unwrap();
                    }
                }),
                vec!["view 'initial'"],
            ),
            ("random texture: nothing matches", Box::new(|_: &Path| {}), vec!["view '"]),
        ],
    );
    let missing = root.join("missing");
    let m = missing.to_str().unwrap();
    assert_clean_failure(
        "missing folder",
        &run(&["align", "--images", m]),
        &[m, "cannot read session folder"],
    );
    let (file, _) = good_png(&root);
    let f = file.to_str().unwrap();
    assert_clean_failure(
        "a file, not a folder",
        &run(&["align", "--images", f]),
        &[f, "cannot read session folder"],
    );
    std::fs::remove_dir_all(&root).ok();
}

/// The flags of a recording (`--topics`, `--every`, `--from`, ...; `replay`'s
/// `--rotation`, ...) given for a folder that is no recording are an error naming them and
/// what the folder is, not ignored; a folder of stereo pairs takes `--every` (and refuses 0).
#[test]
fn recording_flags_on_other_folders() {
    let root = tmp_dir("recording-flags");
    let session = root.join("session");
    image_session(&session);
    let pairs = root.join("pairs");
    std::fs::create_dir_all(&pairs).unwrap();
    for (i, side) in [(0, "left"), (1, "right")] {
        textured(64, 48, i).save(&pairs.join(format!("{side}00.png"))).unwrap();
    }
    let (s, p) = (session.to_str().unwrap(), pairs.to_str().unwrap());
    let cases: [(&str, Vec<&str>, Vec<&str>); 6] = [
        (
            "replay, image session, moves",
            vec!["replay", s, "--rotation", "5", "--auto-rotation"],
            vec!["--rotation, --auto-rotation apply only to a recording of a head run", s],
        ),
        (
            "align, image session",
            vec!["align", "--images", s, "--every", "2"],
            vec!["--every applies only", s],
        ),
        (
            "replay, image session",
            vec!["replay", s, "--from", "1"],
            vec!["--from applies only", "recorded session"],
        ),
        (
            "calibrate, image session",
            vec!["calibrate", s, "--topics", "a,b", "--to", "3"],
            vec!["--topics, --to apply only to a recording", "an image session"],
        ),
        (
            "calibrate, pairs",
            vec!["calibrate", p, "--joint", "pan=a"],
            vec!["--joint applies only", "stereo pairs"],
        ),
        (
            "calibrate, pairs, every 0",
            vec!["calibrate", p, "--every", "0"],
            vec!["--every must be at least 1"],
        ),
    ];
    for (case, args, expected) in cases {
        assert_clean_failure(case, &run(&args), &expected);
    }
    std::fs::remove_dir_all(&root).ok();
}

/// `--lens-terms` without a lens model to estimate is an error, not ignored, in every
/// command that takes it; so is the radial-tangential `k3` (`5`) of the equidistant model.
#[test]
fn lens_terms_without_a_lens() {
    let root = tmp_dir("lens-terms");
    let r = root.to_str().unwrap();
    let cases: [(&str, Vec<&str>); 4] = [
        ("calibrate, a known lens", vec!["calibrate", r, "--lens-from", "recording", "--lens-terms", "4"]),
        ("calibrate, --lens pinhole", vec!["calibrate", r, "--lens", "pinhole", "--lens-terms", "5"]),
        ("demo", vec!["demo", "--images", "--lens-terms", "4"]),
        ("align", vec!["align", "--observations", r, "--lens-terms", "4"]),
    ];
    for (case, args) in cases {
        assert_clean_failure(case, &run(&args), &["--lens-terms needs a lens model"]);
    }
    assert_clean_failure(
        "calibrate, equidistant with k3",
        &run(&["calibrate", r, "--lens", "equidistant", "--lens-terms", "5"]),
        &["adds no coefficient to the equidistant model"],
    );
    std::fs::remove_dir_all(&root).ok();
}

#[test]
fn demo_scenario_bad_input_table() {
    let dir = tmp_dir("scenario");
    let cases: Vec<(&str, &str, Vec<&str>)> = vec![
        ("truncated TOML", "noise_px = ", vec!["TOML"]),
        ("not TOML", "{\"noise_px\": 1}", vec!["TOML"]),
        ("wrong type", "noise_px = \"loud\"", vec!["invalid type"]),
        ("unknown key", "nosie_px = 1.0", vec!["unknown field `nosie_px`"]),
        ("NaN", "noise_px = nan", vec!["noise_px"]),
        ("inf", "rotation_deg = inf", vec!["rotation_deg"]),
        ("i64 overflow", "points = 99999999999999999999", vec!["TOML"]),
        ("too many points", "points = 1000000000000", vec!["points must be in"]),
        ("negative size", "image_size = [-768, 576]", vec!["image_size"]),
        ("huge image", "image_size = [4000000000, 576]", vec!["image_size must be at most"]),
        ("negative seed", "seed = -1", vec!["seed"]),
        ("wrong table type", "render = 3", vec!["render"]),
        ("bad render option", "[render]\nsupersampling = 1000", vec!["supersampling"]),
    ];
    for (i, (case, text, expected)) in cases.iter().enumerate() {
        let path = dir.join(format!("case{i}.toml"));
        std::fs::write(&path, text).unwrap();
        let p = path.to_str().unwrap();
        let mut parts = expected.clone();
        parts.push(p);
        assert_clean_failure(case, &run(&["demo", "--scenario", p, "--json"]), &parts);
    }
    // Values the scenario accepts but the simulated run cannot use: a clean one-line
    // error naming the problem (the scenario was read, so the file is not named).
    for (case, text, expected) in [
        ("noise 1e308", "noise_px = 1e308", "too few tracks"),
        ("baseline 1e308", "baseline_m = 1e308", "could not place"),
        ("drive 1e308", "drive_m = 1e308", "drive distance must be finite"),
        ("encoder noise 1e308", "encoder_noise_deg = 1e308", "cannot reach"),
    ] {
        let path = dir.join("run.toml");
        std::fs::write(&path, text).unwrap();
        assert_clean_failure(
            case,
            &run(&["demo", "--scenario", path.to_str().unwrap(), "--json"]),
            &[expected],
        );
    }
    let d = dir.to_str().unwrap();
    assert_clean_failure("a directory", &run(&["demo", "--scenario", d]), &[d, "cannot read"]);
    let m = dir.join("missing.toml");
    let m = m.to_str().unwrap();
    assert_clean_failure("missing file", &run(&["demo", "--scenario", m]), &[m, "cannot read"]);
    // Writing where it cannot.
    let out = dir.join("no/such/dir/session.json");
    let o = out.to_str().unwrap();
    assert_clean_failure(
        "simulate into a missing folder",
        &run(&["simulate", "--out", o]),
        &[o, "cannot write"],
    );
    assert_clean_failure("simulate onto a folder", &run(&["simulate", "--out", d]), &[d, "directory"]);
    std::fs::remove_dir_all(&dir).ok();
}
