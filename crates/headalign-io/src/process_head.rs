//! A head driven by a child process over a JSON-lines protocol on its stdin/stdout
//! (`docs/head-protocol.md`, protocol `headalign-head/2`): the way a user's own hardware
//! plugs in without linking Rust code. [`ProcessHead`] implements [`StereoHead`],
//! [`ImagingHead`] and [`Vehicle`] (the last only works when the driver has a base).
//!
//! Each request is one JSON object on one line, `{"id": N, "op": "...", ...}` with `op`
//! one of `hello` (sent once at start: the answer gives the image size and what the
//! driver can do, `capabilities`: `["head"]` for a head alone, `["head", "base"]` for a
//! head on a robot base), `read`, `move` (`target`: encoder readings, degrees),
//! `capture`, and for a base `drive` (`distance_m`, metres, signed) and `steer`
//! (`target_deg`: the steering encoder reading to turn to, degrees), then `bye`. The
//! driver answers each request with one line `{"id": N, "ok": true, ...}` (`read` and
//! `capture` carry `encoders`, and `read` of a base `steering_deg`; `capture` carries
//! `left` and `right`: paths of 8-bit PNG images the driver wrote, absolute or relative
//! to headalign's working directory; `drive` may carry `odometry`, what the base measured
//! of the drive) or `{"id": N, "ok": false, "error": "..."}`. Requests are strictly
//! sequential.
//!
//! Compatibility: `headalign-head/2` extends `headalign-head/1` (the capabilities and the
//! base's operations). A driver that answers `hello` as version 1 did (protocol
//! `headalign-head/1` or none, no capabilities) is a head alone, and headalign never
//! sends it a base's request: [`Vehicle`] calls then fail at once, and callers check
//! [`ProcessHead::has_base`] before a stage that needs a base.
//!
//! Failures are one-line [`PlatformError::Device`] messages naming the request (op and
//! id): no answer within [`ProcessHeadOptions::timeout`] (the driver is then killed), the
//! driver exited (its exit status and last stderr line are quoted), a malformed answer
//! (not JSON, wrong id, missing or non-finite fields, unreadable images, wrong image
//! size), or the driver's own error. After a failure the head is broken: every later
//! request fails with the same message (a procedure never continues on a head in an
//! unknown state).
//!
//! Implementation: a reader thread turns the driver's stdout into lines on a channel
//! (`recv_timeout` gives the timeouts; a line longer than [`MAX_LINE_BYTES`] is an
//! error, not an allocation), another keeps the last lines of its stderr. Dropping the
//! head sends `bye`, closes stdin, waits briefly and kills a driver that has not exited.

use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Read, Write};
use std::path::PathBuf;
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError, channel};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use headalign_platform::{
    Encoders, GrayImage, ImagingHead, Odometry, PlatformError, StereoCapture, StereoHead, StereoImages,
    Vehicle,
};
use serde::Deserialize;
use serde_json::{Value, json};

/// The protocol this version speaks (sent in `hello`; the driver echoes it).
pub const PROTOCOL: &str = "headalign-head/2";

/// The protocols whose drivers this version drives: version 1 (a head alone) and
/// version 2 (capabilities, a base).
pub const COMPATIBLE_PROTOCOLS: [&str; 2] = ["headalign-head/1", PROTOCOL];

/// The capability of a driver with a robot base (`drive`, `steer`, `read` with
/// `steering_deg`).
pub const CAPABILITY_BASE: &str = "base";

/// Answers longer than this are an error (a driver writing garbage must not exhaust
/// memory), bytes.
pub const MAX_LINE_BYTES: u64 = 1 << 20;

/// Stderr lines of the driver kept for error messages.
const STDERR_TAIL: usize = 5;

/// Options of [`ProcessHead`].
#[derive(Debug, Clone)]
pub struct ProcessHeadOptions {
    /// Longest wait for one answer (default 30 s: a real head's move plus a capture).
    pub timeout: Duration,
}

impl Default for ProcessHeadOptions {
    fn default() -> Self {
        Self { timeout: Duration::from_secs(30) }
    }
}

impl ProcessHeadOptions {
    /// Check the options.
    pub fn validate(&self) -> Result<(), PlatformError> {
        if self.timeout.is_zero() {
            return Err(PlatformError::InvalidCommand("the head timeout must be positive".into()));
        }
        Ok(())
    }
}

/// Split a command line into program and arguments: words separated by white space;
/// single quotes keep everything literally, double quotes keep white space, a backslash
/// outside single quotes escapes the next character. No other shell syntax.
pub fn split_command_line(line: &str) -> Result<Vec<String>, PlatformError> {
    let mut words = Vec::new();
    let mut word = String::new();
    let mut in_word = false;
    let mut chars = line.chars();
    let mut quote: Option<char> = None;
    while let Some(c) = chars.next() {
        match (quote, c) {
            (Some('\''), '\'') | (Some('"'), '"') => quote = None,
            (Some('\''), c) => word.push(c),
            (_, '\\') => match chars.next() {
                Some(n) => {
                    word.push(n);
                    in_word = true;
                }
                None => return Err(PlatformError::InvalidCommand(format!("'{line}' ends with a backslash"))),
            },
            (Some(_), c) => word.push(c),
            (None, '\'' | '"') => {
                quote = Some(c);
                in_word = true;
            }
            (None, c) if c.is_whitespace() => {
                if in_word {
                    words.push(std::mem::take(&mut word));
                    in_word = false;
                }
            }
            (None, c) => {
                word.push(c);
                in_word = true;
            }
        }
    }
    if quote.is_some() {
        return Err(PlatformError::InvalidCommand(format!("unclosed quote in '{line}'")));
    }
    if in_word {
        words.push(word);
    }
    if words.is_empty() {
        return Err(PlatformError::InvalidCommand("empty head command".into()));
    }
    Ok(words)
}

/// One line from the driver, or why there is none.
enum Line {
    Text(String),
    TooLong,
    ReadError(String),
}

#[derive(Deserialize)]
struct Hello {
    image_size: [u32; 2],
    #[serde(default)]
    name: Option<String>,
    #[serde(default)]
    protocol: Option<String>,
    /// Absent (version 1): a head alone. Unknown capabilities are ignored.
    #[serde(default)]
    capabilities: Option<Vec<String>>,
}

#[derive(Deserialize)]
struct SteeringAnswer {
    steering_deg: f64,
}

#[derive(Deserialize)]
struct DriveAnswer {
    #[serde(default)]
    odometry: Option<Odometry>,
}

#[derive(Deserialize)]
struct ReadAnswer {
    encoders: Encoders,
}

#[derive(Deserialize)]
struct CaptureAnswer {
    encoders: Encoders,
    left: PathBuf,
    right: PathBuf,
}

/// A head behind a driver process (module documentation).
pub struct ProcessHead {
    command: String,
    child: Child,
    stdin: Option<ChildStdin>,
    lines: Receiver<Line>,
    stderr_tail: Arc<Mutex<VecDeque<String>>>,
    next_id: u64,
    image_size: [u32; 2],
    name: String,
    options: ProcessHeadOptions,
    broken: Option<String>,
    base: bool,
    odometry: Option<Odometry>,
}

impl std::fmt::Debug for ProcessHead {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ProcessHead").field("command", &self.command).field("name", &self.name).finish()
    }
}

impl ProcessHead {
    /// Start the driver (`command_line`, split by [`split_command_line`]) and greet it.
    pub fn spawn(command_line: &str, options: ProcessHeadOptions) -> Result<Self, PlatformError> {
        options.validate()?;
        let words = split_command_line(command_line)?;
        let mut child = Command::new(&words[0])
            .args(&words[1..])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| PlatformError::Device(format!("cannot start head driver '{}': {e}", words[0])))?;
        let (Some(stdout), Some(stderr)) = (child.stdout.take(), child.stderr.take()) else {
            let _ = child.kill();
            return Err(PlatformError::Device("head driver: no stdout/stderr pipe".into()));
        };
        let (tx, lines) = channel();
        std::thread::spawn(move || {
            let mut reader = BufReader::new(stdout);
            loop {
                let mut buf = Vec::new();
                match reader.by_ref().take(MAX_LINE_BYTES + 1).read_until(b'\n', &mut buf) {
                    Ok(0) => break,
                    Ok(_) if buf.len() as u64 > MAX_LINE_BYTES => {
                        let _ = tx.send(Line::TooLong);
                        break;
                    }
                    Ok(_) => {
                        let text = String::from_utf8_lossy(&buf).trim_end().to_string();
                        if tx.send(Line::Text(text)).is_err() {
                            break;
                        }
                    }
                    Err(e) => {
                        let _ = tx.send(Line::ReadError(e.to_string()));
                        break;
                    }
                }
            }
        });
        let stderr_tail = Arc::new(Mutex::new(VecDeque::new()));
        let tail = Arc::clone(&stderr_tail);
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines() {
                let Ok(line) = line else { break };
                if let Ok(mut t) = tail.lock() {
                    if t.len() == STDERR_TAIL {
                        t.pop_front();
                    }
                    t.push_back(line);
                }
            }
        });
        let stdin = child.stdin.take();
        let mut head = Self {
            command: command_line.to_string(),
            child,
            stdin,
            lines,
            stderr_tail,
            next_id: 1,
            image_size: [0, 0],
            name: String::new(),
            options,
            broken: None,
            base: false,
            odometry: None,
        };
        let answer = head.request("hello", json!({"protocol": PROTOCOL}))?;
        let hello: Hello = head.parse("hello", head.next_id - 1, answer)?;
        let [w, h] = hello.image_size;
        if w == 0 || h == 0 || w > 100_000 || h > 100_000 {
            return Err(head.fail(format!("malformed answer to 'hello': image_size {w} x {h}")));
        }
        if let Some(p) = hello.protocol
            && !COMPATIBLE_PROTOCOLS.contains(&p.as_str())
        {
            return Err(head.fail(format!(
                "the driver speaks '{p}', headalign speaks '{PROTOCOL}' (and drives '{}' drivers)",
                COMPATIBLE_PROTOCOLS[0]
            )));
        }
        head.image_size = hello.image_size;
        head.name = hello.name.unwrap_or_default();
        head.base = hello.capabilities.is_some_and(|c| c.iter().any(|c| c == CAPABILITY_BASE));
        Ok(head)
    }

    /// True if the driver said in `hello` that the head rides on a base (capability
    /// `base`): the robot stages can drive it.
    pub fn has_base(&self) -> bool {
        self.base
    }

    /// The error of a base's request to a driver without one (nothing is sent).
    fn no_base(&self, op: &str) -> PlatformError {
        let name = if self.name.is_empty() { self.command.as_str() } else { self.name.as_str() };
        PlatformError::Device(format!(
            "head driver '{name}' has no base (its 'hello' answer lists no \"{CAPABILITY_BASE}\" capability): cannot {op}"
        ))
    }

    /// The driver's name from its `hello` answer (empty if it gave none).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The driver's command line.
    pub fn command(&self) -> &str {
        &self.command
    }

    fn stderr_last(&self) -> Option<String> {
        self.stderr_tail.lock().ok().and_then(|t| t.back().cloned())
    }

    /// Mark the head broken with `message` and return the error.
    fn fail(&mut self, message: String) -> PlatformError {
        let full = format!("head driver: {message}");
        self.broken = Some(full.clone());
        PlatformError::Device(full)
    }

    fn exited(&mut self, op: &str, id: u64) -> PlatformError {
        // The driver closed its stdout; give it a moment to exit and report its status.
        let deadline = Instant::now() + Duration::from_millis(500);
        let status = loop {
            match self.child.try_wait() {
                Ok(Some(s)) => break Some(s.to_string()),
                Ok(None) if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(10)),
                _ => break None,
            }
        };
        // Let the stderr thread catch the last words.
        std::thread::sleep(Duration::from_millis(20));
        let last = self.stderr_last().map(|l| format!("; its last message: '{l}'")).unwrap_or_default();
        let status = status.unwrap_or_else(|| "closed its output".into());
        self.fail(format!("the driver exited ({status}) before answering '{op}' (request {id}){last}"))
    }

    /// Send one request and wait for its answer (the whole answer object, `ok` checked).
    fn request(&mut self, op: &str, mut body: Value) -> Result<Value, PlatformError> {
        if let Some(msg) = &self.broken {
            return Err(PlatformError::Device(format!("{msg} (no further requests: '{op}' refused)")));
        }
        let id = self.next_id;
        self.next_id += 1;
        if let Some(m) = body.as_object_mut() {
            m.insert("id".into(), json!(id));
            m.insert("op".into(), json!(op));
        }
        let line = format!("{body}\n");
        let sent = match self.stdin.as_mut() {
            Some(stdin) => stdin.write_all(line.as_bytes()).and_then(|()| stdin.flush()),
            None => Err(std::io::Error::other("stdin closed")),
        };
        if sent.is_err() {
            return Err(self.exited(op, id));
        }
        let answer = match self.lines.recv_timeout(self.options.timeout) {
            Ok(Line::Text(t)) => t,
            Ok(Line::TooLong) => {
                let _ = self.child.kill();
                return Err(self.fail(format!(
                    "malformed answer to '{op}' (request {id}): a line longer than {MAX_LINE_BYTES} bytes"
                )));
            }
            Ok(Line::ReadError(e)) => {
                return Err(self.fail(format!("cannot read the answer to '{op}' (request {id}): {e}")));
            }
            Err(RecvTimeoutError::Timeout) => {
                let _ = self.child.kill();
                let _ = self.child.wait();
                return Err(self.fail(format!(
                    "no answer to '{op}' (request {id}) within {:.1} s; the driver was stopped",
                    self.options.timeout.as_secs_f64()
                )));
            }
            Err(RecvTimeoutError::Disconnected) => return Err(self.exited(op, id)),
        };
        let shown: String = answer.chars().take(80).collect();
        let malformed = |why: String| format!("malformed answer to '{op}' (request {id}): {why}: '{shown}'");
        let value: Value = match serde_json::from_str(&answer) {
            Ok(v @ Value::Object(_)) => v,
            Ok(_) => return Err(self.fail(malformed("not a JSON object".into()))),
            Err(e) => return Err(self.fail(malformed(format!("not JSON ({e})")))),
        };
        if value.get("id").and_then(Value::as_u64) != Some(id) {
            return Err(self.fail(malformed(format!("expected \"id\": {id}"))));
        }
        match value.get("ok").and_then(Value::as_bool) {
            Some(true) => Ok(value),
            Some(false) => {
                let why = value.get("error").and_then(Value::as_str).unwrap_or("(no message)").to_string();
                Err(self.fail(format!("'{op}' (request {id}) failed: {why}")))
            }
            None => Err(self.fail(malformed("no boolean \"ok\"".into()))),
        }
    }

    fn parse<T: for<'de> Deserialize<'de>>(
        &mut self,
        op: &str,
        id: u64,
        v: Value,
    ) -> Result<T, PlatformError> {
        serde_json::from_value(v)
            .map_err(|e| self.fail(format!("malformed answer to '{op}' (request {id}): {e}")))
    }

    fn checked(&mut self, op: &str, id: u64, e: Encoders) -> Result<Encoders, PlatformError> {
        if e.is_finite() {
            Ok(e)
        } else {
            Err(self.fail(format!("malformed answer to '{op}' (request {id}): non-finite encoder readings")))
        }
    }

    fn load(&mut self, id: u64, path: &std::path::Path) -> Result<GrayImage, PlatformError> {
        let img = GrayImage::load(path).map_err(|e| {
            self.fail(format!("answer to 'capture' (request {id}): cannot read '{}': {e}", path.display()))
        })?;
        if img.size() != self.image_size {
            let [w, h] = self.image_size;
            return Err(self.fail(format!(
                "answer to 'capture' (request {id}): '{}' is {}x{}, the driver announced {w}x{h}",
                path.display(),
                img.width(),
                img.height()
            )));
        }
        Ok(img)
    }
}

impl StereoHead for ProcessHead {
    fn image_size(&self) -> [u32; 2] {
        self.image_size
    }

    fn read_encoders(&mut self) -> Result<Encoders, PlatformError> {
        let v = self.request("read", json!({}))?;
        let id = self.next_id - 1;
        let a: ReadAnswer = self.parse("read", id, v)?;
        self.checked("read", id, a.encoders)
    }

    fn move_to(&mut self, target: &Encoders) -> Result<(), PlatformError> {
        if !target.is_finite() {
            return Err(PlatformError::InvalidCommand(format!("non-finite encoder target {target:?}")));
        }
        self.request("move", json!({"target": target}))?;
        Ok(())
    }

    /// Point captures are not part of the protocol: the procedures use image mode.
    fn capture(&mut self) -> Result<StereoCapture, PlatformError> {
        Err(PlatformError::Device(
            "head driver: the protocol captures images only (use an image-mode procedure)".into(),
        ))
    }
}

impl ImagingHead for ProcessHead {
    fn capture_images(&mut self) -> Result<StereoImages, PlatformError> {
        let v = self.request("capture", json!({}))?;
        let id = self.next_id - 1;
        let a: CaptureAnswer = self.parse("capture", id, v)?;
        let encoders = self.checked("capture", id, a.encoders)?;
        let left = self.load(id, &a.left)?;
        let right = self.load(id, &a.right)?;
        StereoImages::new(encoders, left, right)
    }
}

/// The base's operations (protocol version 2, capability `base`).
impl Vehicle for ProcessHead {
    fn drive(&mut self, distance_m: f64) -> Result<(), PlatformError> {
        if !self.base {
            return Err(self.no_base("drive"));
        }
        if !distance_m.is_finite() {
            return Err(PlatformError::InvalidCommand(format!("non-finite drive distance {distance_m}")));
        }
        self.odometry = None;
        let v = self.request("drive", json!({"distance_m": distance_m}))?;
        let id = self.next_id - 1;
        let a: DriveAnswer = self.parse("drive", id, v)?;
        if a.odometry.is_some_and(|o| !o.is_finite()) {
            return Err(self.fail(format!("malformed answer to 'drive' (request {id}): non-finite odometry")));
        }
        self.odometry = a.odometry;
        Ok(())
    }

    fn steer_to(&mut self, encoder_deg: f64) -> Result<(), PlatformError> {
        if !self.base {
            return Err(self.no_base("steer"));
        }
        if !encoder_deg.is_finite() {
            return Err(PlatformError::InvalidCommand(format!("non-finite steering target {encoder_deg}")));
        }
        self.request("steer", json!({"target_deg": encoder_deg}))?;
        Ok(())
    }

    /// A `read` request; the answer's `steering_deg`.
    fn read_steering(&mut self) -> Result<f64, PlatformError> {
        if !self.base {
            return Err(self.no_base("read the steering"));
        }
        let v = self.request("read", json!({}))?;
        let id = self.next_id - 1;
        let a: SteeringAnswer = self.parse("read", id, v)?;
        if !a.steering_deg.is_finite() {
            return Err(
                self.fail(format!("malformed answer to 'read' (request {id}): non-finite steering_deg"))
            );
        }
        Ok(a.steering_deg)
    }

    fn last_odometry(&self) -> Option<Odometry> {
        self.odometry
    }
}

impl Drop for ProcessHead {
    fn drop(&mut self) {
        if self.broken.is_none()
            && let Some(stdin) = self.stdin.as_mut()
        {
            let id = self.next_id;
            let _ = stdin.write_all(format!("{}\n", json!({"id": id, "op": "bye"})).as_bytes());
            let _ = stdin.flush();
        }
        self.stdin = None;
        let deadline = Instant::now() + Duration::from_secs(1);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn command_lines_split_like_a_shell_would_for_simple_cases() {
        let w = split_command_line("drv --port /dev/ttyUSB0").unwrap();
        assert_eq!(w, ["drv", "--port", "/dev/ttyUSB0"]);
        let w = split_command_line(r#"  "my driver" 'a b' c\ d "" e"#).unwrap();
        assert_eq!(w, ["my driver", "a b", "c d", "", "e"]);
        assert!(split_command_line("   ").is_err());
        assert!(split_command_line("a 'b").unwrap_err().to_string().contains("unclosed quote"));
        assert!(split_command_line("a \\").is_err());
    }

    /// A driver written in shell: each test gives its answers; `sh` exists on every
    /// machine this runs on (Unix).
    #[cfg(unix)]
    fn sh_head(script: &str, timeout_ms: u64) -> Result<ProcessHead, PlatformError> {
        let dir = std::env::temp_dir().join(format!("headalign-ph-{}", std::process::id()));
        std::fs::create_dir_all(&dir).map_err(|e| PlatformError::Device(e.to_string()))?;
        static N: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let path = dir.join(format!("drv-{n}.sh"));
        std::fs::write(&path, script).map_err(|e| PlatformError::Device(e.to_string()))?;
        let opts = ProcessHeadOptions { timeout: Duration::from_millis(timeout_ms) };
        ProcessHead::spawn(&format!("sh '{}'", path.display()), opts)
    }

    #[cfg(unix)]
    const HELLO: &str = r#"read l; echo '{"id":1,"ok":true,"image_size":[64,48],"name":"sh"}'"#;

    #[cfg(unix)]
    #[test]
    fn driver_failures_are_one_line_errors_naming_the_request() {
        // A good read, then a malformed answer; the head stays broken afterwards.
        let script = format!(
            "{HELLO}\nread l; echo '{{\"id\":2,\"ok\":true,\"encoders\":{{\"pan\":1,\"elevation\":2,\"verge_left\":3,\"verge_right\":4}}}}'\nread l; echo 'garbage'\nread l\n"
        );
        let mut h = sh_head(&script, 5000).unwrap();
        assert_eq!(h.image_size(), [64, 48]);
        assert_eq!(h.name(), "sh");
        assert_eq!(h.read_encoders().unwrap().verge_right, 4.0);
        let e = h.read_encoders().unwrap_err().to_string();
        assert!(e.contains("malformed answer to 'read' (request 3)") && e.contains("garbage"), "{e}");
        let e2 = h.move_to(&Encoders::default()).unwrap_err().to_string();
        assert!(e2.contains("refused"), "{e2}");
        // Exit mid-run: status and last stderr line are quoted.
        let script = format!("{HELLO}\nread l; echo 'motor stalled' >&2; exit 3\n");
        let mut h = sh_head(&script, 5000).unwrap();
        let e = h.move_to(&Encoders::default()).unwrap_err().to_string();
        assert!(
            e.contains("exited") && e.contains("'move' (request 2)") && e.contains("motor stalled"),
            "{e}"
        );
        assert!(e.contains('3'), "{e}");
        // Timeout.
        let script = format!("{HELLO}\nread l; sleep 10\n");
        let mut h = sh_head(&script, 300).unwrap();
        let t0 = Instant::now();
        let e = h.capture_images().unwrap_err().to_string();
        assert!(e.contains("no answer to 'capture' (request 2) within 0.3 s"), "{e}");
        assert!(t0.elapsed() < Duration::from_secs(5));
        // The driver's own error, a wrong id, non-finite readings, a missing image.
        for (answer, expect) in [
            (r#"{"id":2,"ok":false,"error":"joint limit"}"#, "'read' (request 2) failed: joint limit"),
            (r#"{"id":7,"ok":true}"#, "expected \"id\": 2"),
            (
                r#"{"id":2,"ok":true,"encoders":{"pan":1e999,"elevation":0,"verge_left":0,"verge_right":0}}"#,
                "number out of range",
            ),
            (r#"{"id":2,"ok":true,"encoders":{"pan":"x"}}"#, "malformed answer to 'read'"),
            (r#"[1,2]"#, "not a JSON object"),
        ] {
            let script = format!("{HELLO}\nread l; echo '{answer}'\nread l\n");
            let mut h = sh_head(&script, 5000).unwrap();
            let e = h.read_encoders().unwrap_err().to_string();
            assert!(e.contains(expect), "{answer}: {e}");
            assert_eq!(e.lines().count(), 1);
        }
        let script = format!(
            "{HELLO}\nread l; echo '{{\"id\":2,\"ok\":true,\"encoders\":{{\"pan\":0,\"elevation\":0,\"verge_left\":0,\"verge_right\":0}},\"left\":\"/nonexistent/l.png\",\"right\":\"/nonexistent/r.png\"}}'\nread l\n"
        );
        let mut h = sh_head(&script, 5000).unwrap();
        let e = h.capture_images().unwrap_err().to_string();
        assert!(e.contains("/nonexistent/l.png") && e.contains("request 2"), "{e}");
        // A driver that cannot start, or answers hello badly.
        let e = ProcessHead::spawn("/nonexistent/driver --x", ProcessHeadOptions::default()).unwrap_err();
        assert!(e.to_string().contains("cannot start head driver '/nonexistent/driver'"), "{e}");
        let e = sh_head("read l; echo '{\"id\":1,\"ok\":true,\"image_size\":[0,4]}'\nread l\n", 5000)
            .unwrap_err()
            .to_string();
        assert!(e.contains("image_size 0 x 4"), "{e}");
        let e = sh_head("read l; echo '{\"id\":1,\"ok\":true,\"image_size\":[4,4],\"protocol\":\"headalign-head/3\"}'\nread l\n", 5000)
            .unwrap_err()
            .to_string();
        assert!(e.contains("the driver speaks 'headalign-head/3'"), "{e}");
    }

    /// A version-1 driver is a head alone: a base's call fails at once with one line and
    /// sends nothing (the next request is still answered). A driver with the `base`
    /// capability drives, steers and reads its steering; odometry is kept.
    #[cfg(unix)]
    #[test]
    fn a_base_is_driven_only_when_the_driver_has_one() {
        let script = format!(
            "{HELLO}\nread l; echo '{{\"id\":2,\"ok\":true,\"encoders\":{{\"pan\":1,\"elevation\":2,\"verge_left\":3,\"verge_right\":4}}}}'\nread l\n"
        );
        let mut h = sh_head(&script, 5000).unwrap();
        assert!(!h.has_base());
        let e = h.drive(0.1).unwrap_err().to_string();
        assert!(e.contains("has no base") && e.contains("cannot drive") && !e.contains('\n'), "{e}");
        assert!(h.steer_to(1.0).is_err() && h.read_steering().is_err());
        assert_eq!(h.read_encoders().unwrap().pan, 1.0);
        let hello = r#"read l; echo '{"id":1,"ok":true,"image_size":[64,48],"protocol":"headalign-head/2","capabilities":["head","base","lidar"]}'"#;
        let script = format!(
            "{hello}\nread l; echo '{{\"id\":2,\"ok\":true,\"odometry\":{{\"distance_m\":0.099}}}}'\nread l; echo '{{\"id\":3,\"ok\":true}}'\nread l; echo '{{\"id\":4,\"ok\":true,\"encoders\":{{\"pan\":0,\"elevation\":0,\"verge_left\":0,\"verge_right\":0}},\"steering_deg\":20.5}}'\nread l; echo '{{\"id\":5,\"ok\":true}}'\nread l; echo '{{\"id\":6,\"ok\":true,\"odometry\":{{\"distance_m\":1e999}}}}'\nread l\n"
        );
        let mut h = sh_head(&script, 5000).unwrap();
        assert!(h.has_base());
        h.drive(0.1).unwrap();
        assert_eq!(h.last_odometry(), Some(Odometry { distance_m: 0.099, heading_deg: None }));
        h.steer_to(20.0).unwrap();
        assert_eq!(h.read_steering().unwrap(), 20.5);
        h.drive(-0.1).unwrap();
        assert_eq!(h.last_odometry(), None);
        let e = h.drive(0.1).unwrap_err().to_string();
        assert!(e.contains("malformed answer to 'drive' (request 6)"), "{e}");
    }
}
