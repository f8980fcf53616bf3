//! Every command's `--json` on every route against its schema in docs/formats.md ("JSON
//! on stdout"): the members documented there (parsed from its tables, so the docs and the
//! code cannot drift) are exactly the members printed, at the top level and in `errors`
//! and `before`. The routes: point mode and images, the general and the planar route
//! (`--scene far` and `wall`), the robot stages on and off, a session and a recording
//! replayed, self-calibration and known intrinsics. The image runs with robot stages are
//! the fixtures of `cli.rs` and `sessions.rs` (run once per test process).

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use super::common::{bin, driver, ok_json, tmp};
use serde_json::Value;

/// `headalign ARGS` that must succeed: its JSON.
fn json(args: &[&str]) -> Value {
    ok_json(&bin().args(args).output().unwrap())
}

fn path(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// The members of each schema in docs/formats.md: the first cell's backticked names of
/// each table row under `#### \`SCHEMA\``, with the members of the schema a section
/// extends ("Every member of `headalign-run/1`").
fn documented() -> BTreeMap<String, BTreeSet<String>> {
    let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/formats.md");
    let text = std::fs::read_to_string(&file).unwrap();
    let start = text.find("### JSON on stdout").expect("formats.md: no 'JSON on stdout' section");
    let section = &text[start..];
    let section = &section[..section[4..].find("\n### ").map_or(section.len(), |i| i + 4)];
    let ticked = |s: &str| -> Vec<String> { s.split('`').skip(1).step_by(2).map(str::to_string).collect() };
    let mut out: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    let mut current: Option<String> = None;
    for line in section.lines() {
        if let Some(h) = line.strip_prefix("#### ") {
            current = ticked(h).into_iter().next();
            continue;
        }
        let Some(schema) = &current else { continue };
        if line.starts_with("Every member of `") {
            let base = out.get(&ticked(line)[0]).cloned().expect("extends a schema documented above");
            out.entry(schema.clone()).or_default().extend(base);
        } else if line.starts_with("| `") {
            let first = line.split('|').nth(1).unwrap_or("");
            out.entry(schema.clone()).or_default().extend(ticked(first));
        }
    }
    out
}

/// The members a JSON object prints: its keys, and `errors.KEY` and `before.KEY` for the
/// keys of those objects.
fn members(v: &Value) -> BTreeSet<String> {
    let map = v.as_object().expect("a JSON object");
    let mut out: BTreeSet<String> = map.keys().cloned().collect();
    for nested in ["errors", "before"] {
        if let Some(m) = map.get(nested).and_then(Value::as_object) {
            out.extend(m.keys().map(|k| format!("{nested}.{k}")));
        }
    }
    out
}

/// `v` (what `what` printed) has the documented members of its schema, exactly.
fn check(docs: &BTreeMap<String, BTreeSet<String>>, what: &str, v: &Value) {
    let schema = v["schema"].as_str().unwrap_or_else(|| panic!("{what}: no schema member"));
    let want = docs.get(schema).unwrap_or_else(|| panic!("{what}: schema {schema} not in formats.md"));
    let got = members(v);
    let missing: Vec<_> = want.difference(&got).collect();
    let undocumented: Vec<_> = got.difference(want).collect();
    assert!(
        missing.is_empty() && undocumented.is_empty(),
        "{what} ({schema}): missing {missing:?}, not in formats.md {undocumented:?}"
    );
}

/// `v` (what `what` printed) has the documented members of its schema (for the other
/// modules' runs).
pub fn check_documented(what: &str, v: &Value) {
    check(&documented(), what, v);
}

/// The demo's `errors` hold every metric on every route, numbers where the route gives
/// them: the alignment errors always.
fn check_errors(what: &str, v: &Value) {
    for key in ["verge_err_l_deg", "verge_err_r_deg", "elev_err_l_deg", "elev_err_r_deg"] {
        assert!(v["errors"][key].is_number(), "{what}: errors.{key} = {}", v["errors"][key]);
    }
    for key in ["elev_err_r_unavoidable_deg", "elev_err_r_excess_deg", "f_err_pct", "pp_err_pct"] {
        assert!(v["errors"][key].is_number(), "{what}: errors.{key} = {}", v["errors"][key]);
    }
}

/// Point mode, the planar route (far and wall), and the commands that read their sessions.
#[test]
fn point_mode_and_planar_routes_print_their_schemas() {
    let docs = documented();
    for schema in ["headalign-demo/1", "headalign-run/1", "headalign-replay/1", "headalign-align/1"] {
        assert!(docs.contains_key(schema), "{schema} not documented");
    }
    let far = json(&[
        "demo",
        "--scene",
        "far",
        "--noise",
        "0",
        "--outliers",
        "0",
        "--stages",
        "verge-tilt",
        "--seed",
        "5",
        "--json",
    ]);
    assert_eq!(far["route"], "planar");
    check(&docs, "demo --scene far", &far);
    check_errors("demo --scene far", &far);
    assert!(far["errors"]["pan_err_deg"].is_null() && far["errors"]["recon_err_pct"].is_null());
    let general = json(&["demo", "--seed", "2", "--stages", "verge-tilt", "--json"]);
    assert_eq!(general["route"], "general");
    check(&docs, "demo --stages verge-tilt", &general);
    check_errors("demo --stages verge-tilt", &general);
    // Point mode with the robot stages, recorded, replayed and read by align and calibrate.
    let robot_dir = tmp("points-robot");
    let robot = json(&["demo", "--seed", "2", "--json", "--session", path(&robot_dir)]);
    check(&docs, "demo (robot stages)", &robot);
    assert!(robot["errors"]["pan_err_deg"].is_number() && robot["errors"]["steer_err_deg"].is_number());
    let replayed = json(&["replay", path(&robot_dir), "--json"]);
    check(&docs, "replay of a point session", &replayed);
    assert_eq!(replayed["pan"], robot["pan"]);
    let observations = robot_dir.join("observations.json");
    check(&docs, "align --observations", &json(&["align", "--observations", path(&observations), "--json"]));
    check(&docs, "calibrate (points)", &json(&["calibrate", path(&robot_dir), "--json"]));
    // A wall: the planar route in demo, replay and align.
    let wall_dir = tmp("points-wall");
    let wall =
        json(&["demo", "--scene", "wall", "--stages", "verge-tilt", "--json", "--session", path(&wall_dir)]);
    assert_eq!(wall["route"], "planar");
    check(&docs, "demo --scene wall", &wall);
    check_errors("demo --scene wall", &wall);
    check(&docs, "replay of a wall session", &json(&["replay", path(&wall_dir), "--json"]));
    let observations = wall_dir.join("observations.json");
    let a = json(&["align", "--observations", path(&observations), "--json"]);
    assert_eq!(a["route"], "planar");
    check(&docs, "align on a wall", &a);
    std::fs::remove_dir_all(&robot_dir).ok();
    std::fs::remove_dir_all(&wall_dir).ok();
}

/// `calibrate` by both routes (self-calibration, known intrinsics), and `replay` of a
/// calibration session, which prints `calibrate`'s schema.
#[test]
fn calibrate_routes_print_their_schema() {
    let docs = documented();
    let sim = tmp("simulate");
    let out = bin().args(["simulate", "--images", "--seed", "2", "--out", path(&sim)]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let files = tmp("calibration");
    let c = json(&["calibrate", path(&sim), "--json", "--out", path(&files)]);
    assert_eq!(c["route"], "self-calibration");
    check(&docs, "calibrate", &c);
    let yaml = files.join("opencv_stereo.yaml");
    let k = json(&["calibrate", path(&sim), "--json", "--intrinsics", path(&yaml)]);
    assert!(k["route"].as_str().is_some_and(|r| r.starts_with("known intrinsics")), "{}", k["route"]);
    check(&docs, "calibrate --intrinsics", &k);
    check(&docs, "replay of a calibration session", &json(&["replay", path(&sim), "--json"]));
    std::fs::remove_dir_all(&sim).ok();
    std::fs::remove_dir_all(&files).ok();
}

/// Image mode: the verge/tilt stage alone and with the robot stages (demo and run
/// through the protocol, and their replays), and the planar route on rendered images.
#[test]
fn image_routes_print_their_schemas() {
    let docs = documented();
    let image_demo = &super::cli::image_demo().json;
    check(&docs, "demo --images --stages verge-tilt", image_demo);
    check_errors("demo --images --stages verge-tilt", image_demo);
    let robot_demo = &super::sessions::robot_demo().json;
    check(&docs, "demo --images (robot stages)", robot_demo);
    assert!(robot_demo["errors"]["pan_err_deg"].is_number());
    let robot_run = super::sessions::robot_run();
    check(&docs, "run --stages (robot stages)", &robot_run.json);
    // A head alone, the verge/tilt stage only.
    let dir = tmp("run-head");
    let head = format!("'{}' --seed 4 --near-panels 0", driver());
    let run = json(&["run", "--head-cmd", &head, "--json", "--session", path(&dir)]);
    check(&docs, "run", &run);
    check(&docs, "replay of a run", &json(&["replay", path(&dir), "--json"]));
    check(&docs, "align --images", &json(&["align", "--images", path(&dir), "--json"]));
    // Rendered images of a wall: the planar route.
    let wall_dir = tmp("images-wall");
    let wall = json(&[
        "demo",
        "--images",
        "--scene",
        "wall",
        "--seed",
        "1",
        "--stages",
        "verge-tilt",
        "--json",
        "--session",
        path(&wall_dir),
    ]);
    assert_eq!(wall["route"], "planar");
    check(&docs, "demo --images --scene wall", &wall);
    check_errors("demo --images --scene wall", &wall);
    check(&docs, "replay of a wall image session", &json(&["replay", path(&wall_dir), "--json"]));
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_dir_all(&wall_dir).ok();
}
