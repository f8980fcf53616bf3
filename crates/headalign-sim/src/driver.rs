//! The simulated robot behind the head protocol: the server of the example driver
//! `headalign-sim-driver` (its flags are [`DriverOptions`]' fields). An example driver that speaks the headalign head protocol
//! (`docs/head-protocol.md`, JSON lines on stdin/stdout, `headalign-head/2`) and fronts
//! the simulator: the simulated robot of `headalign demo --images` (same scenario for the
//! same `--seed`, the room with its near panels), rendering each capture to PNG files in
//! `--out` (default: a fresh temporary folder, removed at exit). It answers `hello` with
//! the capabilities of a head on a base and serves `drive` and `steer`;
//! `headalign run --head-cmd "headalign-sim-driver --seed 1" --stages ...` then runs the
//! same procedure on the same images as `headalign demo --images --seed 1 --stages ...`.
//! `--no-base` answers as a version-1 driver of a head alone; `--near-panels 0` gives the
//! plain room of `demo --images --stages verge-tilt`. `--scenario FILE` simulates the
//! scenario of a file (as `demo --scenario`: a lens, the pan axis' tilt from the floor).
//!
//! The simulator's truth stays on this side of the protocol: `--truth FILE` writes, at
//! `bye` (or when headalign closes the pipe), the robot's true alignment errors at its
//! final position, with the member names of `demo --json`'s `errors` (`pan_err_deg`,
//! `steer_err_deg`, `verge_err_l_deg`, ...; degrees), so that a run through the protocol
//! can be scored.
//!
//! For tests of the error paths it can misbehave on purpose at its N-th request (1 =
//! `hello`): `--die-at N` ([`DriverError::Crash`]: the binary exits with status 3 and a
//! message on stderr, writing no truth), `--garble-at N`
//! (answer with a line that is not JSON), `--sleep-at N --sleep-s S` (answer S seconds
//! late).

use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};

use headalign_platform::{Encoders, ImagingHead, StereoHead, Vehicle};
use serde_json::{Map, Value, json};
use thiserror::Error;

use crate::{AlignmentErrors, Scenario, SimulatedRobot};

/// What the driver simulates and how it misbehaves (the flags of `headalign-sim-driver`).
#[derive(Debug, Clone)]
pub struct DriverOptions {
    /// Scenario seed (as `headalign demo --seed`). The binary's default: 1.
    pub seed: u64,
    /// Tall textured panels about 1 m ahead; `None`: the scenario file's, else
    /// [`Scenario::ROBOT_NEAR_PANELS`] (the demo's robot stages).
    pub near_panels: Option<usize>,
    /// A scenario file (TOML, as `headalign demo --scenario`); `seed` and `near_panels`
    /// apply over it. `None`: the default scenario.
    pub scenario: Option<PathBuf>,
    /// Answer as a version-1 driver of a head alone (no base: no drive, no steer).
    pub no_base: bool,
    /// At the end, write the robot's true alignment errors to this JSON file.
    pub truth: Option<PathBuf>,
    /// Folder for the captured PNGs; `None`: a temporary folder, removed at exit.
    pub out: Option<PathBuf>,
    /// Crash on receiving this request (1 = hello): [`DriverError::Crash`].
    pub die_at: Option<u64>,
    /// Answer this request with a line that is not JSON.
    pub garble_at: Option<u64>,
    /// Answer this request late, by `sleep_s` seconds.
    pub sleep_at: Option<u64>,
    /// Delay of `sleep_at`, seconds. The binary's default: 60.
    pub sleep_s: f64,
}

/// Why the driver stopped.
#[derive(Debug, Error)]
pub enum DriverError {
    /// A file, the scenario or the pipe failed; one line.
    #[error("{0}")]
    Failed(String),
    /// The crash asked for by `die_at`: nothing more is written.
    #[error("simulated crash at request {request}")]
    Crash {
        /// The request (1 = hello).
        request: u64,
    },
}

impl From<String> for DriverError {
    fn from(why: String) -> Self {
        Self::Failed(why)
    }
}

/// The simulated robot behind the protocol and what the driver reports of it.
struct Sim {
    robot: SimulatedRobot,
    /// Serve the base's operations (`--no-base` off).
    base: bool,
    /// The errors at the start, for the truth file.
    before: Map<String, Value>,
    /// Folder of the PNGs.
    out: PathBuf,
    captures: u64,
}

/// Serve the head protocol on stdin/stdout until `bye` or the end of input, then write the
/// truth file (`options.truth`) and remove a temporary image folder.
pub fn serve(args: &DriverOptions) -> Result<(), DriverError> {
    let from_file = match &args.scenario {
        Some(path) => {
            let text =
                std::fs::read_to_string(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
            Scenario::from_toml_str(&text).map_err(|e| format!("{}: {e}", path.display()))?
        }
        None => Scenario::default(),
    };
    // The robot stages need near panels: the file's, else the robot demo's.
    let panels = match from_file.near_panels {
        0 => Scenario::ROBOT_NEAR_PANELS,
        n => n,
    };
    let scenario = Scenario { seed: args.seed, near_panels: args.near_panels.unwrap_or(panels), ..from_file };
    scenario.validate().map_err(|e| e.to_string())?;
    let robot = SimulatedRobot::new(scenario).map_err(|e| e.to_string())?;
    let (out, temporary) = match &args.out {
        Some(d) => (d.clone(), false),
        None => (std::env::temp_dir().join(format!("headalign-sim-driver-{}", std::process::id())), true),
    };
    std::fs::create_dir_all(&out).map_err(|e| format!("cannot create {}: {e}", out.display()))?;
    let before = errors_now(&robot, !args.no_base);
    let mut sim = Sim { robot, base: !args.no_base, before, out: out.clone(), captures: 0 };
    let result = lines(args, &mut sim);
    if let Err(DriverError::Crash { .. }) = result {
        return result; // as a crashed driver: no truth, the images left where they are
    }
    // The truth first: headalign waits only briefly for the driver to exit after `bye`.
    let written = args.truth.as_deref().map_or(Ok(()), |path| write_truth(&sim, args.seed, path));
    if temporary {
        let _ = std::fs::remove_dir_all(&out);
    }
    result.and(written)
}

/// Answer each request line; a crash asked for (`die_at`) returns at once.
fn lines(args: &DriverOptions, sim: &mut Sim) -> Result<(), DriverError> {
    let stdin = std::io::stdin();
    let mut stdout = std::io::stdout();
    let mut count = 0u64;
    for line in stdin.lock().lines() {
        let line = line.map_err(|e| e.to_string())?;
        count += 1;
        if args.die_at == Some(count) {
            return Err(DriverError::Crash { request: count });
        }
        if args.sleep_at == Some(count) {
            std::thread::sleep(std::time::Duration::from_secs_f64(args.sleep_s.max(0.0)));
        }
        let answer = match serde_json::from_str::<Value>(&line) {
            Ok(request) => answer(sim, &request),
            Err(e) => json!({"id": Value::Null, "ok": false, "error": format!("bad request: {e}")}),
        };
        let text =
            if args.garble_at == Some(count) { "this is not JSON".to_string() } else { answer.to_string() };
        writeln!(stdout, "{text}").and_then(|()| stdout.flush()).map_err(|e| e.to_string())?;
        if answer["bye"] == json!(true) {
            break;
        }
    }
    Ok(())
}

/// The answer to one request.
fn answer(sim: &mut Sim, request: &Value) -> Value {
    let id = request["id"].clone();
    let fail = |e: String| json!({"id": id, "ok": false, "error": e});
    let number = |key: &str| request[key].as_f64().ok_or_else(|| format!("'{key}' must be a number"));
    let robot = &mut sim.robot;
    match (request["op"].as_str(), sim.base) {
        (Some("hello"), base) => {
            let mut a = json!({
                "id": id, "ok": true, "protocol": if base { "headalign-head/2" } else { "headalign-head/1" },
                "name": format!("simulator seed {}", robot.head().scenario().seed),
                "image_size": robot.image_size(),
            });
            if base {
                a["capabilities"] = json!(["head", "base"]);
            }
            a
        }
        (Some("read"), base) => match robot.read_encoders() {
            Ok(e) if base => {
                json!({"id": id, "ok": true, "encoders": e, "steering_deg": robot.steering_encoder_deg()})
            }
            Ok(e) => json!({"id": id, "ok": true, "encoders": e}),
            Err(e) => fail(e.to_string()),
        },
        (Some("move"), _) => match serde_json::from_value::<Encoders>(request["target"].clone()) {
            Ok(target) => match robot.move_to(&target) {
                Ok(()) => json!({"id": id, "ok": true}),
                Err(e) => fail(e.to_string()),
            },
            Err(e) => fail(format!("bad target: {e}")),
        },
        (Some("capture"), _) => {
            let images = match robot.capture_images() {
                Ok(i) => i,
                Err(e) => return fail(e.to_string()),
            };
            sim.captures += 1;
            let left = sim.out.join(format!("{:04}-left.png", sim.captures));
            let right = sim.out.join(format!("{:04}-right.png", sim.captures));
            if let Err(e) = images.left.save(&left).and_then(|()| images.right.save(&right)) {
                return fail(format!("cannot write the images: {e}"));
            }
            json!({"id": id, "ok": true, "encoders": images.encoders, "left": left, "right": right})
        }
        // Wheel odometry: the simulated robot drives exactly what it is told (no slip).
        (Some("drive"), true) => {
            match number("distance_m").and_then(|d| robot.drive(d).map(|()| d).map_err(|e| e.to_string())) {
                Ok(d) => json!({"id": id, "ok": true, "odometry": {"distance_m": d}}),
                Err(e) => fail(e),
            }
        }
        (Some("steer"), true) => {
            match number("target_deg").and_then(|t| robot.steer_to(t).map_err(|e| e.to_string())) {
                Ok(()) => json!({"id": id, "ok": true}),
                Err(e) => fail(e),
            }
        }
        (Some("bye"), _) => json!({"id": id, "ok": true, "bye": true}),
        (other, _) => fail(format!("unknown op {other:?}")),
    }
}

/// The alignment errors of `demo --json`'s `errors` at the robot's current readings:
/// the four of the cameras, and with a base the pan and steering errors (degrees).
fn errors_now(robot: &SimulatedRobot, base: bool) -> Map<String, Value> {
    let head = robot.head();
    let enc = head.encoders();
    let AlignmentErrors { verge_err_l_deg, verge_err_r_deg, elev_err_l_deg, elev_err_r_deg } =
        head.alignment_errors(&enc);
    let mut m = Map::new();
    for (k, v) in [
        ("verge_err_l_deg", json!(verge_err_l_deg)),
        ("verge_err_r_deg", json!(verge_err_r_deg)),
        ("elev_err_l_deg", json!(elev_err_l_deg)),
        ("elev_err_r_deg", json!(elev_err_r_deg)),
        ("pan_err_deg", json!(base.then(|| robot.pan_err_deg(&enc)))),
        ("steer_err_deg", json!(base.then(|| robot.steer_err_deg(robot.steering_encoder_deg())))),
    ] {
        m.insert(k.into(), v);
    }
    m
}

/// `--truth FILE`: the errors at the final position (`errors`, plus the right camera's
/// unavoidable elevation error and the excess over it, as the demo reports them), the
/// errors at the start (`before`), the final readings and the truth they are judged by.
fn write_truth(sim: &Sim, seed: u64, path: &Path) -> Result<(), DriverError> {
    let head = sim.robot.head();
    let mut errors = errors_now(&sim.robot, sim.base);
    let true_aligned = head.aligned_encoders();
    let unavoidable_r = head.alignment_errors(&true_aligned).elev_err_r_deg;
    let elev_r = head.alignment_errors(&head.encoders()).elev_err_r_deg;
    errors.insert("elev_err_r_unavoidable_deg".into(), json!(unavoidable_r));
    errors.insert("elev_err_r_excess_deg".into(), json!(elev_r - unavoidable_r));
    let truth = json!({
        "format": "headalign-sim-truth/1",
        "seed": seed,
        "errors": errors,
        "before": sim.before,
        "final_encoders": head.encoders(),
        "steering_encoder_deg": sim.base.then(|| sim.robot.steering_encoder_deg()),
        "odometer_m": sim.robot.odometer_m(),
        "truth": {
            "aligned_encoders": true_aligned,
            "steer_zero_deg": sim.robot.truth().steer_zero_deg,
            "wheelbase_m": sim.robot.truth().wheelbase_m,
            "pan_tilt_deg": sim.robot.truth().pan_tilt_deg(),
        },
    });
    let text = serde_json::to_string_pretty(&truth).map_err(|e| e.to_string())? + "\n";
    Ok(std::fs::write(path, text).map_err(|e| format!("cannot write {}: {e}", path.display()))?)
}
