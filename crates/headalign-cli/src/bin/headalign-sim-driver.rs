//! `headalign-sim-driver`: an example head driver that speaks the headalign head protocol
//! (`docs/head-protocol.md`, JSON lines on stdin/stdout) and fronts the simulator: the
//! simulated head of `headalign demo` (same scenario for the same `--seed`), rendering
//! each capture to PNG files in `--out` (default: a fresh temporary folder, removed at
//! exit). `headalign run --head-cmd "headalign-sim-driver --seed 1"` then runs the same
//! procedure on the same images as `headalign demo --images --seed 1`.
//!
//! For tests of the error paths it can misbehave on purpose at its N-th request (1 =
//! `hello`): `--die-at N` (exit with status 3 and a message on stderr), `--garble-at N`
//! (answer with a line that is not JSON), `--sleep-at N --sleep-s S` (answer S seconds
//! late).

use std::io::{BufRead, Write};
use std::path::PathBuf;

use clap::Parser;
use headalign_platform::{Encoders, ImagingHead, StereoHead};
use headalign_sim::{Scenario, SimulatedHead};
use serde_json::{Value, json};

#[derive(Parser)]
#[command(name = "headalign-sim-driver", about = "Example head driver fronting the simulator")]
struct Args {
    /// Scenario seed (as `headalign demo --seed`).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Folder for the captured PNGs (default: a temporary folder, removed at exit).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Exit with status 3 on receiving this request (1 = hello).
    #[arg(long)]
    die_at: Option<u64>,
    /// Answer this request with a line that is not JSON.
    #[arg(long)]
    garble_at: Option<u64>,
    /// Answer this request late, by --sleep-s seconds.
    #[arg(long)]
    sleep_at: Option<u64>,
    /// Delay of --sleep-at, seconds.
    #[arg(long, default_value_t = 60.0)]
    sleep_s: f64,
}

fn main() -> std::process::ExitCode {
    match serve(&Args::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("headalign-sim-driver: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn serve(args: &Args) -> Result<(), String> {
    let scenario = Scenario { seed: args.seed, ..Scenario::default() };
    scenario.validate().map_err(|e| e.to_string())?;
    let mut head = SimulatedHead::new(scenario.clone()).map_err(|e| e.to_string())?;
    let (out, temporary) = match &args.out {
        Some(d) => (d.clone(), false),
        None => (std::env::temp_dir().join(format!("headalign-sim-driver-{}", std::process::id())), true),
    };
    std::fs::create_dir_all(&out).map_err(|e| format!("cannot create {}: {e}", out.display()))?;
    let result = lines(args, &mut head, &scenario, &out);
    if temporary {
        let _ = std::fs::remove_dir_all(&out);
    }
    result
}

fn lines(
    args: &Args,
    head: &mut SimulatedHead,
    scenario: &Scenario,
    out: &std::path::Path,
) -> Result<(), String> {
    let stdin = std::io::stdin();
    let mut stdout = std::io::stdout();
    let mut count = 0u64;
    let mut captures = 0u64;
    for line in stdin.lock().lines() {
        let line = line.map_err(|e| e.to_string())?;
        count += 1;
        if args.die_at == Some(count) {
            eprintln!("headalign-sim-driver: simulated crash at request {count}");
            std::process::exit(3);
        }
        if args.sleep_at == Some(count) {
            std::thread::sleep(std::time::Duration::from_secs_f64(args.sleep_s.max(0.0)));
        }
        let answer = match serde_json::from_str::<Value>(&line) {
            Ok(request) => answer(head, scenario, out, &request, &mut captures),
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

fn answer(
    head: &mut SimulatedHead,
    scenario: &Scenario,
    out: &std::path::Path,
    request: &Value,
    captures: &mut u64,
) -> Value {
    let id = request["id"].clone();
    let fail = |e: String| json!({"id": id, "ok": false, "error": e});
    match request["op"].as_str() {
        Some("hello") => json!({
            "id": id, "ok": true, "protocol": "headalign-head/1",
            "name": format!("simulator seed {}", scenario.seed), "image_size": scenario.image_size,
        }),
        Some("read") => match head.read_encoders() {
            Ok(e) => json!({"id": id, "ok": true, "encoders": e}),
            Err(e) => fail(e.to_string()),
        },
        Some("move") => match serde_json::from_value::<Encoders>(request["target"].clone()) {
            Ok(target) => match head.move_to(&target) {
                Ok(()) => json!({"id": id, "ok": true}),
                Err(e) => fail(e.to_string()),
            },
            Err(e) => fail(format!("bad target: {e}")),
        },
        Some("capture") => {
            let images = match head.capture_images() {
                Ok(i) => i,
                Err(e) => return fail(e.to_string()),
            };
            *captures += 1;
            let left = out.join(format!("{:04}-left.png", captures));
            let right = out.join(format!("{:04}-right.png", captures));
            if let Err(e) = images.left.save(&left).and_then(|()| images.right.save(&right)) {
                return fail(format!("cannot write the images: {e}"));
            }
            json!({"id": id, "ok": true, "encoders": images.encoders, "left": left, "right": right})
        }
        Some("bye") => json!({"id": id, "ok": true, "bye": true}),
        other => fail(format!("unknown op {other:?}")),
    }
}
