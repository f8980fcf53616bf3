//! CDR (OMG DDS-XTypes "XCDR"), the serialisation ROS 2 uses for messages, and the three
//! message types a recording needs: `sensor_msgs/msg/Image`, `sensor_msgs/msg/CompressedImage`
//! and `sensor_msgs/msg/JointState`.
//!
//! ## The encoding
//!
//! A serialised message starts with a 4-byte encapsulation header: a 2-byte representation
//! identifier (big-endian on the wire) and 2 option bytes. Accepted identifiers:
//! `0x0000` CDR_BE and `0x0001` CDR_LE (XCDR1, what ROS 2's rmw implementations write),
//! `0x0006` CDR2_BE and `0x0007` CDR2_LE (XCDR2 plain, for final types such as every ROS
//! message). Parameter-list and delimited encodings are refused by name.
//!
//! After the header, every primitive of size `n` starts at an offset (counted from the end
//! of the header, not from the start of the buffer) that is a multiple of `n`; XCDR2 caps
//! that alignment at 4 (an `f64` aligns to 4). A string is a `uint32` length that counts
//! the terminating NUL, the bytes, then the NUL. A sequence is a `uint32` element count,
//! then the elements, each aligned as its type. Integers have the byte order of the
//! identifier.
//!
//! ## The messages (ROS 2 definitions)
//!
//! ```text
//! std_msgs/Header:   builtin_interfaces/Time stamp {int32 sec, uint32 nanosec}, string frame_id
//! Image:             Header header, uint32 height, uint32 width, string encoding,
//!                    uint8 is_bigendian, uint32 step, uint8[] data
//! CompressedImage:   Header header, string format, uint8[] data
//! JointState:        Header header, string[] name, float64[] position, float64[] velocity,
//!                    float64[] effort
//! ```
//!
//! Degrees of freedom: none (a decoder). Units: stamps in nanoseconds since the epoch of
//! the recording's clock; joint positions as recorded (radians for revolute joints; the
//! caller converts). Pitfalls: an empty sequence of `float64` has no alignment padding in
//! the writers this was checked against (Fast-CDR, Cyclone DDS), but writers differ, so the
//! joint-state decoder reads only `name` and `position` and never depends on what follows;
//! every length is checked against the bytes left before anything is allocated, so a
//! corrupt message is an error, never a huge allocation or a panic.

use thiserror::Error;

/// A malformed or unsupported CDR message.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum CdrError {
    /// The message ends before a field.
    #[error("message truncated: {field} needs {needed} bytes at offset {offset}, {left} left")]
    Truncated {
        /// The field being read.
        field: &'static str,
        /// Bytes it needs.
        needed: usize,
        /// Offset in the message (after the encapsulation header).
        offset: usize,
        /// Bytes left.
        left: usize,
    },
    /// An encapsulation this decoder does not read.
    #[error("unsupported CDR encapsulation 0x{0:04x} (CDR_LE/BE and CDR2_LE/BE plain are supported)")]
    Encapsulation(u16),
    /// A string that is not NUL-terminated UTF-8.
    #[error("{0}: not a NUL-terminated UTF-8 string")]
    BadString(&'static str),
    /// A value that contradicts another (sizes, counts).
    #[error("{0}")]
    Inconsistent(String),
}

/// A cursor over one CDR-encoded message.
#[derive(Debug, Clone)]
pub struct CdrReader<'a> {
    /// The payload after the encapsulation header.
    body: &'a [u8],
    pos: usize,
    little: bool,
    max_align: usize,
}

impl<'a> CdrReader<'a> {
    /// Start reading `message` (encapsulation header included).
    pub fn new(message: &'a [u8]) -> Result<Self, CdrError> {
        let Some(head) = message.get(..4) else {
            return Err(CdrError::Truncated {
                field: "encapsulation header",
                needed: 4,
                offset: 0,
                left: message.len(),
            });
        };
        let id = u16::from_be_bytes([head[0], head[1]]);
        let (little, max_align) = match id {
            0x0000 => (false, 8),
            0x0001 => (true, 8),
            0x0006 => (false, 4),
            0x0007 => (true, 4),
            other => return Err(CdrError::Encapsulation(other)),
        };
        Ok(Self { body: &message[4..], pos: 0, little, max_align })
    }

    /// Bytes left after the cursor.
    pub fn remaining(&self) -> usize {
        self.body.len().saturating_sub(self.pos)
    }

    fn align(&mut self, size: usize) {
        let a = size.min(self.max_align);
        if a > 1 {
            self.pos = self.pos.div_ceil(a) * a;
        }
    }

    fn take(&mut self, n: usize, field: &'static str) -> Result<&'a [u8], CdrError> {
        let left = self.remaining();
        if n > left {
            return Err(CdrError::Truncated { field, needed: n, offset: self.pos, left });
        }
        let s = &self.body[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    fn array<const N: usize>(&mut self, field: &'static str) -> Result<[u8; N], CdrError> {
        self.align(N);
        let s = self.take(N, field)?;
        let mut a = [0u8; N];
        a.copy_from_slice(s);
        if self.little != cfg!(target_endian = "little") {
            a.reverse();
        }
        Ok(a)
    }

    /// One `uint8`.
    pub fn u8(&mut self, field: &'static str) -> Result<u8, CdrError> {
        Ok(self.take(1, field)?[0])
    }

    /// One `uint32`.
    pub fn u32(&mut self, field: &'static str) -> Result<u32, CdrError> {
        Ok(u32::from_ne_bytes(self.array(field)?))
    }

    /// One `int32`.
    pub fn i32(&mut self, field: &'static str) -> Result<i32, CdrError> {
        Ok(i32::from_ne_bytes(self.array(field)?))
    }

    /// One `float64`.
    pub fn f64(&mut self, field: &'static str) -> Result<f64, CdrError> {
        Ok(f64::from_ne_bytes(self.array(field)?))
    }

    /// A sequence length, checked against the bytes left (each element at least
    /// `min_element_bytes`).
    fn count(&mut self, field: &'static str, min_element_bytes: usize) -> Result<usize, CdrError> {
        let n = self.u32(field)? as usize;
        let left = self.remaining();
        if n.saturating_mul(min_element_bytes) > left {
            return Err(CdrError::Truncated {
                field,
                needed: n.saturating_mul(min_element_bytes),
                offset: self.pos,
                left,
            });
        }
        Ok(n)
    }

    /// A `string`.
    pub fn string(&mut self, field: &'static str) -> Result<String, CdrError> {
        let n = self.count(field, 1)?;
        if n == 0 {
            // Some writers encode the empty string as length 0 (no NUL).
            return Ok(String::new());
        }
        let bytes = self.take(n, field)?;
        match bytes.split_last() {
            Some((0, text)) => {
                std::str::from_utf8(text).map(str::to_string).map_err(|_| CdrError::BadString(field))
            }
            _ => Err(CdrError::BadString(field)),
        }
    }

    /// A `uint8[]`, borrowed.
    pub fn bytes(&mut self, field: &'static str) -> Result<&'a [u8], CdrError> {
        let n = self.count(field, 1)?;
        self.take(n, field)
    }

    /// A `string[]`.
    pub fn strings(&mut self, field: &'static str) -> Result<Vec<String>, CdrError> {
        // Each string is at least its 4-byte length.
        let n = self.count(field, 4)?;
        (0..n).map(|_| self.string(field)).collect()
    }

    /// A `float64[]`.
    pub fn f64s(&mut self, field: &'static str) -> Result<Vec<f64>, CdrError> {
        let n = self.count(field, 8)?;
        (0..n).map(|_| self.f64(field)).collect()
    }
}

/// `std_msgs/Header`: the stamp in nanoseconds and the frame id.
#[derive(Debug, Clone, PartialEq)]
pub struct Header {
    /// `stamp.sec * 1e9 + stamp.nanosec`.
    pub stamp_ns: i64,
    /// `frame_id`.
    pub frame_id: String,
}

/// Read a `std_msgs/Header`.
pub fn header(r: &mut CdrReader<'_>) -> Result<Header, CdrError> {
    let sec = r.i32("header.stamp.sec")?;
    let nanosec = r.u32("header.stamp.nanosec")?;
    if nanosec >= 1_000_000_000 {
        return Err(CdrError::Inconsistent(format!("header.stamp.nanosec {nanosec} is not below 1e9")));
    }
    let frame_id = r.string("header.frame_id")?;
    Ok(Header { stamp_ns: i64::from(sec) * 1_000_000_000 + i64::from(nanosec), frame_id })
}

/// The header alone of a message that starts with one (every stamped message): cheap, for
/// indexing a recording.
pub fn stamp_only(message: &[u8]) -> Result<Header, CdrError> {
    header(&mut CdrReader::new(message)?)
}

/// `sensor_msgs/msg/Image`, its pixel data borrowed.
#[derive(Debug, Clone, PartialEq)]
pub struct Image<'a> {
    /// The header.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// The pixel encoding (`mono8`, `mono16`, `rgb8`, `bgr8`, ...).
    pub encoding: String,
    /// Multi-byte pixels are big-endian.
    pub is_bigendian: bool,
    /// Bytes per row.
    pub step: u32,
    /// The pixels, `step * height` bytes.
    pub data: &'a [u8],
}

/// Decode a `sensor_msgs/msg/Image`.
pub fn image(message: &[u8]) -> Result<Image<'_>, CdrError> {
    let mut r = CdrReader::new(message)?;
    let header = header(&mut r)?;
    let height = r.u32("height")?;
    let width = r.u32("width")?;
    let encoding = r.string("encoding")?;
    let is_bigendian = r.u8("is_bigendian")? != 0;
    let step = r.u32("step")?;
    let data = r.bytes("data")?;
    if (data.len() as u64) < u64::from(step) * u64::from(height) {
        return Err(CdrError::Inconsistent(format!(
            "image data holds {} bytes, fewer than step {step} x height {height}",
            data.len()
        )));
    }
    Ok(Image { header, height, width, encoding, is_bigendian, step, data })
}

/// `sensor_msgs/msg/CompressedImage`, its data borrowed.
#[derive(Debug, Clone, PartialEq)]
pub struct CompressedImage<'a> {
    /// The header.
    pub header: Header,
    /// The format (`png`, `jpeg`, `mono8; jpeg compressed mono8`, ...).
    pub format: String,
    /// The compressed bytes.
    pub data: &'a [u8],
}

/// Decode a `sensor_msgs/msg/CompressedImage`.
pub fn compressed_image(message: &[u8]) -> Result<CompressedImage<'_>, CdrError> {
    let mut r = CdrReader::new(message)?;
    let header = header(&mut r)?;
    let format = r.string("format")?;
    let data = r.bytes("data")?;
    Ok(CompressedImage { header, format, data })
}

/// `sensor_msgs/msg/JointState`: names and positions (velocity and effort are not read).
#[derive(Debug, Clone, PartialEq)]
pub struct JointState {
    /// The header.
    pub header: Header,
    /// Joint names.
    pub name: Vec<String>,
    /// Positions, one per name (radians or metres, as recorded).
    pub position: Vec<f64>,
}

/// Decode a `sensor_msgs/msg/JointState` (header, `name`, `position`).
pub fn joint_state(message: &[u8]) -> Result<JointState, CdrError> {
    let mut r = CdrReader::new(message)?;
    let header = header(&mut r)?;
    let name = r.strings("name")?;
    let position = r.f64s("position")?;
    if position.len() != name.len() {
        return Err(CdrError::Inconsistent(format!(
            "joint state has {} names but {} positions",
            name.len(),
            position.len()
        )));
    }
    Ok(JointState { header, name, position })
}

/// Writes CDR messages (XCDR1, little or big endian): what a ROS 2 publisher sends, for
/// tests and tools that write recordings.
#[derive(Debug, Clone)]
pub struct CdrWriter {
    buf: Vec<u8>,
    little: bool,
}

impl CdrWriter {
    /// A message with the CDR_LE (`little`) or CDR_BE header.
    pub fn new(little: bool) -> Self {
        Self { buf: vec![0, u8::from(little), 0, 0], little }
    }

    fn align(&mut self, n: usize) {
        while !(self.buf.len() - 4).is_multiple_of(n) {
            self.buf.push(0);
        }
    }

    fn put<const N: usize>(&mut self, le: [u8; N], be: [u8; N]) {
        self.align(N);
        self.buf.extend_from_slice(if self.little { &le } else { &be });
    }

    /// One `uint8`.
    pub fn u8(&mut self, v: u8) -> &mut Self {
        self.buf.push(v);
        self
    }

    /// One `uint32`.
    pub fn u32(&mut self, v: u32) -> &mut Self {
        self.put(v.to_le_bytes(), v.to_be_bytes());
        self
    }

    /// One `int32`.
    pub fn i32(&mut self, v: i32) -> &mut Self {
        self.put(v.to_le_bytes(), v.to_be_bytes());
        self
    }

    /// One `float64`.
    pub fn f64(&mut self, v: f64) -> &mut Self {
        self.put(v.to_le_bytes(), v.to_be_bytes());
        self
    }

    /// A `string` (length with the NUL, the bytes, the NUL).
    pub fn string(&mut self, s: &str) -> &mut Self {
        self.u32(s.len() as u32 + 1);
        self.buf.extend_from_slice(s.as_bytes());
        self.buf.push(0);
        self
    }

    /// A `uint8[]`.
    pub fn bytes(&mut self, b: &[u8]) -> &mut Self {
        self.u32(b.len() as u32);
        self.buf.extend_from_slice(b);
        self
    }

    /// A `std_msgs/Header` at `stamp_ns` (non-negative).
    pub fn header(&mut self, stamp_ns: i64, frame_id: &str) -> &mut Self {
        self.i32((stamp_ns.div_euclid(1_000_000_000)) as i32);
        self.u32(stamp_ns.rem_euclid(1_000_000_000) as u32);
        self.string(frame_id)
    }

    /// The message.
    pub fn finish(&self) -> Vec<u8> {
        self.buf.clone()
    }
}

/// A `sensor_msgs/msg/Image` message (CDR_LE), rows packed (`step = width * bytes per pixel`).
pub fn encode_image(
    stamp_ns: i64,
    frame_id: &str,
    width: u32,
    height: u32,
    encoding: &str,
    data: &[u8],
) -> Vec<u8> {
    let step = if height == 0 { 0 } else { (data.len() / height as usize) as u32 };
    let mut w = CdrWriter::new(true);
    w.header(stamp_ns, frame_id).u32(height).u32(width).string(encoding).u8(0).u32(step).bytes(data);
    w.finish()
}

/// A `sensor_msgs/msg/CompressedImage` message (CDR_LE).
pub fn encode_compressed_image(stamp_ns: i64, frame_id: &str, format: &str, data: &[u8]) -> Vec<u8> {
    let mut w = CdrWriter::new(true);
    w.header(stamp_ns, frame_id).string(format).bytes(data);
    w.finish()
}

/// A `sensor_msgs/msg/JointState` message (CDR_LE or BE) with empty velocity and effort.
pub fn encode_joint_state(stamp_ns: i64, names: &[&str], position: &[f64], little: bool) -> Vec<u8> {
    let mut w = CdrWriter::new(little);
    w.header(stamp_ns, "");
    w.u32(names.len() as u32);
    for n in names {
        w.string(n);
    }
    w.u32(position.len() as u32);
    for &p in position {
        w.f64(p);
    }
    w.u32(0).u32(0);
    w.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A JointState laid out byte by byte from the rules above (CDR_LE): the header ends
    /// at offset 13 ("" frame id: length 1 and the NUL), the name count aligns to 16, the
    /// name "pan" (length 4 with its NUL) ends at 28, the position count sits at 28 and the
    /// float64 aligns to 32 (relative to the payload, not the buffer: the buffer offset is
    /// 36, not a multiple of 8). Independent of the writer, so a shared mistake of writer
    /// and reader is caught.
    #[test]
    fn joint_state_alignment_follows_the_spec() {
        let mut m = vec![0x00, 0x01, 0x00, 0x00];
        m.extend_from_slice(&7i32.to_le_bytes()); // sec @0
        m.extend_from_slice(&5u32.to_le_bytes()); // nanosec @4
        m.extend_from_slice(&1u32.to_le_bytes()); // frame_id length @8
        m.push(0); // NUL @12
        m.extend_from_slice(&[0, 0, 0]); // pad to 16
        m.extend_from_slice(&1u32.to_le_bytes()); // name count @16
        m.extend_from_slice(&4u32.to_le_bytes()); // "pan" length @20
        m.extend_from_slice(b"pan\0"); // @24
        m.extend_from_slice(&1u32.to_le_bytes()); // position count @28
        m.extend_from_slice(&0.25f64.to_le_bytes()); // @32, already aligned
        m.extend_from_slice(&0u32.to_le_bytes()); // velocity
        m.extend_from_slice(&0u32.to_le_bytes()); // effort
        let js = joint_state(&m).unwrap();
        assert_eq!(js.header.stamp_ns, 7_000_000_005);
        assert_eq!((js.name.as_slice(), js.position.as_slice()), (&["pan".to_string()][..], &[0.25][..]));
        assert_eq!(encode_joint_state(7_000_000_005, &["pan"], &[0.25], true), m);
        // The same in big endian: only the byte order changes.
        let be = encode_joint_state(7_000_000_005, &["pan"], &[0.25], false);
        assert_eq!(joint_state(&be).unwrap(), js);
        // XCDR2: an f64 aligns to 4 only. With the name "abcd" (length 5 with its NUL) the
        // name ends at 29, the position count sits at 32 and the f64 at 36, where XCDR1
        // would pad to 40.
        let mut w = CdrWriter::new(true);
        w.header(0, "").u32(1).string("abcd").u32(1);
        let mut xcdr2 = w.finish();
        xcdr2[1] = 0x07;
        xcdr2.extend_from_slice(&1.5f64.to_le_bytes());
        assert_eq!(joint_state(&xcdr2).unwrap().position, [1.5]);
    }

    #[test]
    fn image_round_trips_and_bad_messages_are_errors() {
        let data: Vec<u8> = (0..12).collect();
        let m = encode_image(1_500_000_000, "cam0", 4, 3, "mono8", &data);
        let img = image(&m).unwrap();
        assert_eq!((img.width, img.height, img.step, img.encoding.as_str()), (4, 3, 4, "mono8"));
        assert_eq!(
            (img.data, img.header.frame_id.as_str(), img.header.stamp_ns),
            (&data[..], "cam0", 1_500_000_000)
        );
        // Every truncation is an error, never a panic.
        for n in 0..m.len() {
            assert!(image(&m[..n]).is_err(), "truncated at {n}");
        }
        let c = encode_compressed_image(-5, "", "png", &[1, 2, 3]);
        let ci = compressed_image(&c).unwrap();
        assert_eq!((ci.header.stamp_ns, ci.format.as_str(), ci.data), (-5, "png", &[1u8, 2, 3][..]));
        // A parameter-list encapsulation is named.
        let mut pl = m.clone();
        pl[1] = 0x03;
        assert_eq!(image(&pl).unwrap_err(), CdrError::Encapsulation(3));
        // A huge declared count is refused before any allocation.
        let mut w = CdrWriter::new(true);
        w.header(0, "").u32(u32::MAX);
        assert!(matches!(joint_state(&w.finish()), Err(CdrError::Truncated { .. })));
    }

    proptest::proptest! {
        /// Any bytes after a valid header decode to a message or an error, never a panic
        /// (the fuzz target `ros2_message` does the same without the header).
        #[test]
        fn arbitrary_messages_never_panic(body in proptest::collection::vec(proptest::num::u8::ANY, 0..200), little: bool) {
            let mut m = vec![0, u8::from(little), 0, 0];
            m.extend_from_slice(&body);
            let _ = image(&m);
            let _ = compressed_image(&m);
            let _ = joint_state(&m);
        }
    }
}
