//! ROS 2 bags in MCAP ([`super`] module docs): what `ros2 bag record` writes with the
//! `mcap` storage plugin, read with the `mcap` crate.
//!
//! ## The file
//!
//! A bag is a directory with `metadata.yaml` and one or more `.mcap` files (several when
//! the recording was split), or a `.mcap` file alone; the files are read in name order and
//! `metadata.yaml` is not needed. Records are read linearly ([`mcap::sans_io::LinearReader`],
//! streaming: a bag is never held in memory whole); the summary section is not used, but
//! a file that does not end with its footer and magic (a recording cut short) is an
//! error. Chunks are decompressed here:
//! `zstd` (rosbag2's default) with `ruzstd`, `lz4` with `lz4_flex`, both pure Rust (the
//! `mcap` crate's own compression features build the C libraries), or uncompressed.
//!
//! A channel is used when its `message_encoding` is `cdr` and its schema (encoding
//! `ros2msg` or `ros2idl`) is named `sensor_msgs/msg/Image`, `sensor_msgs/msg/CompressedImage`
//! or `sensor_msgs/msg/JointState` (the ROS 1 spelling without `msg/` is accepted too).
//! Messages are decoded by [`super::cdr`].
//!
//! ## Reading
//!
//! Two passes over the files: the first reads every image message's header stamp and
//! every joint state, which decides the pairs and the selection; the second decodes only
//! the images of the selected pairs. An image message is identified by its topic and its
//! ordinal on that topic, which both passes count the same way.
//!
//! Images: `Image` in `mono8`, `mono16` (scaled to 8 bits by the smallest power of two
//! that brings the image's maximum under 256: 10-, 12- and 16-bit data keep their
//! proportions), `rgb8` and `bgr8` (grey with the Rec. 709 weights, as a colour PNG is
//! read); `CompressedImage` in `png` or `jpeg` (the format string, e.g. `mono8; jpeg
//! compressed mono8`, must name one). Rows honour `step`; multi-byte pixels honour
//! `is_bigendian`.
//!
//! Degrees of freedom: none. Units: stamps in nanoseconds, joint positions in radians
//! (converted to degrees when the encoders are interpolated). Pitfalls: channel ids are per file
//! (a split bag repeats them with other meanings); a corrupt record length or chunk size
//! is an error before anything that large is allocated.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::io::Read;
use std::path::{Path, PathBuf};

use headalign_platform::{GrayImage, Joint};
use mcap::records::Record;
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};

use super::cdr;
use super::{
    JointSeries, Pair, Recording, RecordingFormat, RecordingOptions, Stamped, build_views, encoders_at,
    pair_streams, secs, select_pairs,
};
use headalign::AlignError;

/// A decompressed chunk may hold at most this many bytes (corrupt sizes are refused before
/// allocating); rosbag2 writes chunks of about 1 MB.
pub const MAX_CHUNK_BYTES: u64 = 1 << 30;

/// The message types read from a bag.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MessageKind {
    /// `sensor_msgs/msg/Image`.
    Image,
    /// `sensor_msgs/msg/CompressedImage`.
    CompressedImage,
    /// `sensor_msgs/msg/JointState`.
    JointState,
}

impl MessageKind {
    /// The kind of a schema name (`sensor_msgs/msg/Image` or `sensor_msgs/Image`, ...).
    pub fn from_schema(name: &str) -> Option<Self> {
        let short = name.strip_prefix("sensor_msgs/")?;
        match short.strip_prefix("msg/").unwrap_or(short) {
            "Image" => Some(Self::Image),
            "CompressedImage" => Some(Self::CompressedImage),
            "JointState" => Some(Self::JointState),
            _ => None,
        }
    }

    fn is_image(self) -> bool {
        matches!(self, Self::Image | Self::CompressedImage)
    }
}

/// A topic of the bag: its schema name and message encoding (from its channels).
#[derive(Debug, Clone, PartialEq)]
pub struct TopicInfo {
    /// The schema name (`sensor_msgs/msg/Image`), empty without a schema.
    pub schema: String,
    /// The channel's message encoding (`cdr` in a ROS 2 bag).
    pub message_encoding: String,
    /// Messages on it.
    pub messages: usize,
}

impl TopicInfo {
    /// The kind of message, if it is one read here (CDR-encoded, a known schema).
    pub fn kind(&self) -> Option<MessageKind> {
        (self.message_encoding == "cdr").then(|| MessageKind::from_schema(&self.schema)).flatten()
    }
}

/// The `.mcap` files of a bag at `path` (a file, or a directory's files in name order).
pub fn bag_files(path: &Path) -> Result<Vec<PathBuf>, AlignError> {
    if path.is_file() {
        return Ok(vec![path.to_path_buf()]);
    }
    let entries = std::fs::read_dir(path)
        .map_err(|e| AlignError::Recording(format!("cannot read '{}': {e}", path.display())))?;
    let mut files: Vec<PathBuf> = Vec::new();
    let mut sqlite = false;
    for p in entries.filter_map(Result::ok).map(|e| e.path()) {
        match p.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase).as_deref() {
            Some("mcap") => files.push(p),
            Some("db3") => sqlite = true,
            _ => {}
        }
    }
    files.sort();
    if files.is_empty() {
        let why = if sqlite {
            "holds a sqlite3 bag (.db3): convert it with `ros2 bag convert` to the mcap storage"
        } else {
            "holds no .mcap file"
        };
        return Err(AlignError::Recording(format!("'{}' {why}", path.display())));
    }
    Ok(files)
}

/// Decompress one chunk's records (`compression` as the chunk names it).
fn decompress(compression: &str, data: &[u8], size: u64, origin: &str) -> Result<Vec<u8>, AlignError> {
    let bad = |m: String| AlignError::Recording(format!("'{origin}': {m}"));
    if size > MAX_CHUNK_BYTES {
        return Err(bad(format!("a chunk declares {size} bytes, more than the {MAX_CHUNK_BYTES} accepted")));
    }
    let size = size as usize;
    let out = match compression {
        "" => data.to_vec(),
        "zstd" => {
            let mut out = vec![0u8; size];
            let n = ruzstd::decoding::FrameDecoder::new()
                .decode_all(data, &mut out)
                .map_err(|e| bad(format!("zstd chunk: {e}")))?;
            out.truncate(n);
            out
        }
        "lz4" => {
            let mut out = Vec::with_capacity(size);
            lz4_flex::frame::FrameDecoder::new(data)
                .take(size as u64 + 1)
                .read_to_end(&mut out)
                .map_err(|e| bad(format!("lz4 chunk: {e}")))?;
            out
        }
        other => {
            return Err(bad(format!("chunk compression '{other}' is not supported (zstd, lz4 or none)")));
        }
    };
    if out.len() != size {
        return Err(bad(format!("a chunk decompressed to {} bytes, its header says {size}", out.len())));
    }
    Ok(out)
}

/// What [`scan`] calls for each message: topic, topic info, CDR bytes.
pub type Visit<'a> = dyn FnMut(&str, &TopicInfo, &[u8]) -> Result<(), AlignError> + 'a;

/// The records of one file, streamed: schemas and channels are resolved, and each
/// message is passed to `visit` with its topic and channel.
struct Scanner<'a> {
    origin: String,
    schemas: HashMap<u16, String>,
    channels: HashMap<u16, (String, TopicInfo)>,
    visit: &'a mut Visit<'a>,
    topics: &'a mut BTreeMap<String, TopicInfo>,
}

impl Scanner<'_> {
    fn record(&mut self, opcode: u8, body: &[u8]) -> Result<(), AlignError> {
        let bad = |e: mcap::McapError| AlignError::Recording(format!("'{}': {e}", self.origin));
        match opcode {
            mcap::records::op::SCHEMA
            | mcap::records::op::CHANNEL
            | mcap::records::op::MESSAGE
            | mcap::records::op::CHUNK => {}
            _ => return Ok(()),
        }
        match mcap::parse_record(opcode, body).map_err(bad)? {
            Record::Schema { header, .. } => {
                self.schemas.insert(header.id, header.name);
            }
            Record::Channel(c) => {
                let schema = self.schemas.get(&c.schema_id).cloned().unwrap_or_default();
                let info = TopicInfo { schema, message_encoding: c.message_encoding, messages: 0 };
                self.topics.entry(c.topic.clone()).or_insert_with(|| info.clone());
                self.channels.insert(c.id, (c.topic, info));
            }
            Record::Message { header, data } => {
                let Some((topic, info)) = self.channels.get(&header.channel_id) else {
                    return Err(AlignError::Recording(format!(
                        "'{}': a message on channel {} that was never declared",
                        self.origin, header.channel_id
                    )));
                };
                if let Some(t) = self.topics.get_mut(topic) {
                    t.messages += 1;
                }
                (self.visit)(topic, info, &data)?;
            }
            Record::Chunk { header, data } => {
                let records = decompress(&header.compression, &data, header.uncompressed_size, &self.origin)?;
                self.chunk(&records)?;
            }
            _ => {}
        }
        Ok(())
    }

    /// The records inside a decompressed chunk: opcode, u64 length, body.
    fn chunk(&mut self, mut records: &[u8]) -> Result<(), AlignError> {
        while !records.is_empty() {
            let (Some(&opcode), Some(len)) = (records.first(), records.get(1..9)) else {
                return Err(AlignError::Recording(format!(
                    "'{}': a chunk ends inside a record",
                    self.origin
                )));
            };
            let len = u64::from_le_bytes(len.try_into().unwrap_or([0xff; 8]));
            let rest = &records[9..];
            if len > rest.len() as u64 {
                return Err(AlignError::Recording(format!(
                    "'{}': a record in a chunk declares {len} bytes, {} left",
                    self.origin,
                    rest.len()
                )));
            }
            let (body, next) = rest.split_at(len as usize);
            self.record(opcode, body)?;
            records = next;
        }
        Ok(())
    }
}

/// Stream every message of the bag's files to `visit(topic, info, cdr bytes)`; returns
/// every topic seen.
pub fn scan(files: &[PathBuf], visit: &mut Visit<'_>) -> Result<BTreeMap<String, TopicInfo>, AlignError> {
    let mut topics = BTreeMap::new();
    for path in files {
        let origin = path.display().to_string();
        let io = |e: std::io::Error| AlignError::Recording(format!("cannot read '{origin}': {e}"));
        let mut file = std::fs::File::open(path).map_err(io)?;
        let size = file.metadata().map_err(io)?.len();
        let mut read_so_far = 0u64;
        let options = LinearReaderOptions::default().with_emit_chunks(true);
        let mut reader = LinearReader::new_with_options(options);
        let mut scanner = Scanner {
            origin: origin.clone(),
            schemas: HashMap::new(),
            channels: HashMap::new(),
            visit: &mut *visit,
            topics: &mut topics,
        };
        while let Some(event) = reader.next_event() {
            match event
                .map_err(|e| AlignError::Recording(format!("'{origin}': not a readable MCAP file: {e}")))?
            {
                LinearReadEvent::ReadRequest(need) => {
                    // A corrupt length asks for more than the file holds: refuse it
                    // before allocating.
                    let need = need.min((size - read_so_far.min(size)) as usize).max(1);
                    let n = file.read(reader.insert(need)).map_err(io)?;
                    read_so_far += n as u64;
                    reader.notify_read(n);
                }
                LinearReadEvent::Record { data, opcode } => scanner.record(opcode, data)?,
            }
        }
    }
    Ok(topics)
}

/// Which of the bag's topics are the left and right images (module docs of [`super`]).
fn image_topics(
    topics: &BTreeMap<String, TopicInfo>,
    options: &RecordingOptions,
    origin: &str,
) -> Result<[String; 2], AlignError> {
    let images: Vec<&String> =
        topics.iter().filter(|(_, t)| t.kind().is_some_and(MessageKind::is_image)).map(|(n, _)| n).collect();
    let listing = || {
        if images.is_empty() {
            "none".to_string()
        } else {
            images.iter().map(|s| s.as_str()).collect::<Vec<_>>().join(", ")
        }
    };
    let Some(wanted) = &options.topics else {
        return match images.as_slice() {
            [l, r] => Ok([(*l).clone(), (*r).clone()]),
            _ => Err(AlignError::Recording(format!(
                "bag '{origin}' has {} image topics ({}): name the left and right ones with --topics LEFT,RIGHT",
                images.len(),
                listing()
            ))),
        };
    };
    for name in wanted {
        check_topic(topics, name, MessageKind::is_image, "sensor_msgs/msg/Image or CompressedImage", origin)
            .map_err(|e| AlignError::Recording(format!("{e} (image topics: {})", listing())))?;
    }
    Ok(wanted.clone())
}

/// A requested topic must exist, be CDR and of a wanted kind; one-line errors otherwise.
fn check_topic(
    topics: &BTreeMap<String, TopicInfo>,
    name: &str,
    wanted: fn(MessageKind) -> bool,
    wanted_name: &str,
    origin: &str,
) -> Result<(), String> {
    let Some(t) = topics.get(name) else {
        return Err(format!("bag '{origin}' has no topic '{name}'"));
    };
    if t.message_encoding != "cdr" {
        return Err(format!(
            "topic '{name}' of bag '{origin}' is encoded as '{}', not 'cdr' (a ROS 2 bag's encoding)",
            t.message_encoding
        ));
    }
    if !t.kind().is_some_and(wanted) {
        return Err(format!("topic '{name}' of bag '{origin}' is '{}', not {wanted_name}", t.schema));
    }
    Ok(())
}

/// An 8-bit grey image from a decoded `Image` (module docs for the encodings).
pub fn gray_from_image(img: &cdr::Image<'_>) -> Result<GrayImage, String> {
    let (w, h) = (img.width as usize, img.height as usize);
    if w == 0 || h == 0 || w > 100_000 || h > 100_000 {
        return Err(format!("image size {w}x{h} is not a valid size"));
    }
    let bytes_per_pixel = match img.encoding.as_str() {
        "mono8" => 1,
        "mono16" => 2,
        "rgb8" | "bgr8" => 3,
        other => {
            return Err(format!(
                "unsupported image encoding '{other}' (mono8, mono16, rgb8 and bgr8 are read)"
            ));
        }
    };
    let step = img.step as usize;
    if step < w * bytes_per_pixel {
        return Err(format!("step {step} is less than width {w} x {bytes_per_pixel} bytes"));
    }
    if img.data.len() < (h - 1) * step + w * bytes_per_pixel {
        return Err(format!("{} bytes of pixels are too few for {h} rows of step {step}", img.data.len()));
    }
    let rows = (0..h).map(|y| &img.data[y * step..y * step + w * bytes_per_pixel]);
    let pixels: Vec<u8> = match img.encoding.as_str() {
        "mono8" => rows.flat_map(|r| r.iter().copied()).collect(),
        "mono16" => {
            let value = |p: &[u8]| {
                if img.is_bigendian {
                    u16::from_be_bytes([p[0], p[1]])
                } else {
                    u16::from_le_bytes([p[0], p[1]])
                }
            };
            let wide: Vec<u16> = rows.flat_map(|r| r.chunks_exact(2).map(value)).collect();
            let max = wide.iter().copied().max().unwrap_or(0);
            let shift = (16 - max.leading_zeros()).saturating_sub(8);
            wide.iter().map(|&v| (v >> shift) as u8).collect()
        }
        enc => {
            let (ri, bi) = if enc == "rgb8" { (0, 2) } else { (2, 0) };
            rows.flat_map(|r| {
                r.chunks_exact(3).map(move |p| {
                    let y = 2126 * u32::from(p[ri]) + 7152 * u32::from(p[1]) + 722 * u32::from(p[bi]);
                    ((y + 5000) / 10_000) as u8
                })
            })
            .collect()
        }
    };
    GrayImage::new(img.width, img.height, pixels).map_err(|e| e.to_string())
}

/// An 8-bit grey image from one message of `kind`.
fn decode_image(kind: MessageKind, data: &[u8]) -> Result<GrayImage, String> {
    match kind {
        MessageKind::Image => gray_from_image(&cdr::image(data).map_err(|e| e.to_string())?),
        _ => {
            let c = cdr::compressed_image(data).map_err(|e| e.to_string())?;
            let f = c.format.to_ascii_lowercase();
            if f.contains("compresseddepth")
                || !(f.contains("png") || f.contains("jpeg") || f.contains("jpg"))
            {
                return Err(format!(
                    "unsupported compressed image format '{}' (png and jpeg are read)",
                    c.format
                ));
            }
            GrayImage::decode(c.data).map_err(|e| e.to_string())
        }
    }
}

/// The first pass: image stamps per image topic, joint samples per joint name.
#[derive(Default)]
struct Index {
    stamps: HashMap<String, Vec<Stamped>>,
    joints: HashMap<String, JointSeries>,
    joint_messages: usize,
}

/// Read a bag ([`super::read_recording`] checked the options).
pub(crate) fn read(path: &Path, options: &RecordingOptions) -> Result<Recording, AlignError> {
    let files = bag_files(path)?;
    let origin = path.display().to_string();
    let mut index = Index::default();
    let topics = scan(&files, &mut |topic, info, data| {
        let at = |e: cdr::CdrError| AlignError::Recording(format!("bag '{origin}': topic '{topic}': {e}"));
        match info.kind() {
            Some(k) if k.is_image() => {
                let s = index.stamps.entry(topic.to_string()).or_default();
                let stamp_ns = cdr::stamp_only(data).map_err(at)?.stamp_ns;
                s.push(Stamped { stamp_ns, index: s.len() });
            }
            Some(MessageKind::JointState) if topic == options.joint_topic && !options.joints.is_empty() => {
                let js = cdr::joint_state(data).map_err(at)?;
                index.joint_messages += 1;
                for (name, &p) in js.name.iter().zip(&js.position) {
                    if p.is_finite() {
                        index.joints.entry(name.clone()).or_default().samples.push((js.header.stamp_ns, p));
                    }
                }
            }
            _ => {}
        }
        Ok(())
    })?;
    let names = image_topics(&topics, options, &origin)?;
    let mut notes = Vec::new();
    let joint_series = joint_series(&topics, &mut index, options, &origin, &mut notes)?;
    let stream = |n: &String| index.stamps.get(n).cloned().unwrap_or_default();
    let tolerance_ns = (options.pair_tolerance_s * 1e9).round() as i64;
    let pairs = pair_streams(stream(&names[0]), stream(&names[1]), tolerance_ns, &names, &mut notes)?;
    let selected = select_pairs(&pairs, options)?;
    let images = decode_selected(&files, &names, &selected, &origin)?;
    let items = selected.iter().zip(images).map(|(p, (left, right))| {
        let name = p.left.stamp_ns.to_string();
        let encoders = encoders_at(&joint_series, p.left.stamp_ns, &name, &options.joint_topic)?;
        Ok((name, encoders, left, right))
    });
    let views = build_views(path, items, &mut notes)?;
    Ok(Recording {
        format: RecordingFormat::Ros2Bag,
        source: path.to_path_buf(),
        topics: names,
        pairs_found: pairs.len(),
        views,
        notes,
    })
}

/// The mapped joints' series; errors for a missing topic or joint, a note for joint
/// states that are there but not used.
fn joint_series(
    topics: &BTreeMap<String, TopicInfo>,
    index: &mut Index,
    options: &RecordingOptions,
    origin: &str,
    notes: &mut Vec<String>,
) -> Result<Vec<(Joint, String, JointSeries)>, AlignError> {
    if options.joints.is_empty() {
        if let Some((name, _)) = topics.iter().find(|(_, t)| t.kind() == Some(MessageKind::JointState)) {
            notes.push(format!(
                "joint states on '{name}' not used (map them with --joint pan=NAME,elevation=NAME,...): every reading is zero"
            ));
        }
        return Ok(Vec::new());
    }
    let topic = &options.joint_topic;
    check_topic(topics, topic, |k| k == MessageKind::JointState, "sensor_msgs/msg/JointState", origin)
        .map_err(AlignError::Recording)?;
    let mut out = Vec::new();
    for (joint, name) in &options.joints {
        let Some(mut s) = index.joints.remove(name) else {
            let mut known: Vec<&String> = index.joints.keys().collect();
            known.sort();
            return Err(AlignError::Recording(format!(
                "joint '{name}' (for {}) is in none of the {} joint states on '{topic}' (joints: {})",
                joint.name(),
                index.joint_messages,
                known.iter().map(|s| s.as_str()).collect::<Vec<_>>().join(", ")
            )));
        };
        s.samples.sort_by_key(|x| x.0);
        out.push((*joint, name.clone(), s));
    }
    Ok(out)
}

/// The second pass: decode the images of the selected pairs, in the pairs' order.
fn decode_selected(
    files: &[PathBuf],
    names: &[String; 2],
    selected: &[Pair],
    origin: &str,
) -> Result<Vec<(GrayImage, GrayImage)>, AlignError> {
    let wanted: [HashSet<usize>; 2] =
        [selected.iter().map(|p| p.left.index).collect(), selected.iter().map(|p| p.right.index).collect()];
    let mut decoded: [HashMap<usize, GrayImage>; 2] = Default::default();
    let mut ordinal = [0usize; 2];
    scan(files, &mut |topic, info, data| {
        let Some(side) = names.iter().position(|n| n == topic) else { return Ok(()) };
        let k = ordinal[side];
        ordinal[side] += 1;
        if !wanted[side].contains(&k) {
            return Ok(());
        }
        let kind = info.kind().unwrap_or(MessageKind::Image);
        let img = decode_image(kind, data).map_err(|e| {
            let stamp = cdr::stamp_only(data).map(|h| h.stamp_ns).unwrap_or(0);
            AlignError::Recording(format!("bag '{origin}': topic '{topic}' at {:.6} s: {e}", secs(stamp)))
        })?;
        decoded[side].insert(k, img);
        Ok(())
    })?;
    selected
        .iter()
        .map(|p| {
            let mut take = |side: usize, k: usize| {
                decoded[side].remove(&k).ok_or_else(|| {
                    AlignError::Recording(format!(
                        "bag '{origin}': image {k} of '{}' vanished on the second read",
                        names[side]
                    ))
                })
            };
            Ok((take(0, p.left.index)?, take(1, p.right.index)?))
        })
        .collect()
}

/// The `ros2msg` definition of a message type (the type's fields, then each type it uses
/// after a line of `=`), as rosbag2 stores it in the schema record.
fn schema_definition(kind: MessageKind) -> (&'static str, String) {
    let rule = "=".repeat(80);
    let header = format!(
        "{rule}\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n{rule}\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
    );
    let (name, fields) = match kind {
        MessageKind::Image => (
            "sensor_msgs/msg/Image",
            "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n",
        ),
        MessageKind::CompressedImage => {
            ("sensor_msgs/msg/CompressedImage", "std_msgs/Header header\nstring format\nuint8[] data\n")
        }
        MessageKind::JointState => (
            "sensor_msgs/msg/JointState",
            "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n",
        ),
    };
    (name, format!("{fields}{header}"))
}

/// Writes a ROS 2 bag as one `.mcap` file the way rosbag2 lays it out (profile `ros2`,
/// schemas `ros2msg`, channels `cdr`), with uncompressed chunks: for tests and tools that
/// record. Messages are CDR bytes ([`super::cdr`]'s encoders).
pub struct BagWriter {
    writer: mcap::Writer<std::io::BufWriter<std::fs::File>>,
    path: PathBuf,
    schemas: HashMap<&'static str, u16>,
    channels: HashMap<String, u16>,
    sequence: u32,
}

impl BagWriter {
    /// Create the file at `path`.
    pub fn create(path: &Path) -> Result<Self, AlignError> {
        let err = |e: String| AlignError::Output(format!("cannot write '{}': {e}", path.display()));
        let file = std::fs::File::create(path).map_err(|e| err(e.to_string()))?;
        let writer = mcap::WriteOptions::new()
            .profile("ros2")
            .library("headalign")
            .compression(None)
            .create(std::io::BufWriter::new(file))
            .map_err(|e| err(e.to_string()))?;
        Ok(Self {
            writer,
            path: path.to_path_buf(),
            schemas: HashMap::new(),
            channels: HashMap::new(),
            sequence: 0,
        })
    }

    fn err(&self, e: impl std::fmt::Display) -> AlignError {
        AlignError::Output(format!("cannot write '{}': {e}", self.path.display()))
    }

    /// Write one message on `topic` (declared with `kind` the first time), logged at
    /// `log_time_ns`.
    pub fn write(
        &mut self,
        topic: &str,
        kind: MessageKind,
        log_time_ns: u64,
        cdr: &[u8],
    ) -> Result<(), AlignError> {
        let channel_id = match self.channels.get(topic) {
            Some(&id) => id,
            None => {
                let (name, definition) = schema_definition(kind);
                let schema_id = match self.schemas.get(name) {
                    Some(&id) => id,
                    None => {
                        let id = self
                            .writer
                            .add_schema(name, "ros2msg", definition.as_bytes())
                            .map_err(|e| self.err(e))?;
                        self.schemas.insert(name, id);
                        id
                    }
                };
                let id = self
                    .writer
                    .add_channel(schema_id, topic, "cdr", &BTreeMap::new())
                    .map_err(|e| self.err(e))?;
                self.channels.insert(topic.to_string(), id);
                id
            }
        };
        self.sequence += 1;
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence: self.sequence,
            log_time: log_time_ns,
            publish_time: log_time_ns,
        };
        self.writer.write_to_known_channel(&header, cdr).map_err(|e| self.err(e))
    }

    /// Write the summary and close the file.
    pub fn finish(mut self) -> Result<(), AlignError> {
        self.writer.finish().map_err(|e| self.err(e))?;
        let path = self.path.clone();
        let mut inner = self.writer.into_inner();
        std::io::Write::flush(&mut inner)
            .map_err(|e| AlignError::Output(format!("cannot write '{}': {e}", path.display())))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn encodings_become_grey() {
        let mk = |encoding: &str, step: u32, data: Vec<u8>, big: bool| {
            let header = cdr::Header { stamp_ns: 0, frame_id: String::new() };
            let img = cdr::Image {
                header,
                height: 2,
                width: 2,
                encoding: encoding.into(),
                is_bigendian: big,
                step,
                data: &data,
            };
            gray_from_image(&img).map(|g| g.pixels().to_vec())
        };
        // mono8 with a padded step of 3.
        assert_eq!(mk("mono8", 3, vec![1, 2, 99, 3, 4, 99], false).unwrap(), [1, 2, 3, 4]);
        // mono16 of 12-bit data (max 4095): shifted by 4; big-endian honoured.
        let le: Vec<u8> = [16u16, 32, 4095, 0].iter().flat_map(|v| v.to_le_bytes()).collect();
        assert_eq!(mk("mono16", 4, le, false).unwrap(), [1, 2, 255, 0]);
        let be: Vec<u8> = [16u16, 32, 4095, 0].iter().flat_map(|v| v.to_be_bytes()).collect();
        assert_eq!(mk("mono16", 4, be, true).unwrap(), [1, 2, 255, 0]);
        // rgb8 and bgr8: pure red and blue by Rec. 709.
        let red_blue = vec![255, 0, 0, 0, 0, 255, 0, 0, 0, 255, 255, 255];
        assert_eq!(mk("rgb8", 6, red_blue.clone(), false).unwrap(), [54, 18, 0, 255]);
        assert_eq!(mk("bgr8", 6, red_blue, false).unwrap(), [18, 54, 0, 255]);
        let e = mk("bayer_rggb8", 2, vec![0; 4], false).unwrap_err();
        assert!(e.contains("unsupported image encoding 'bayer_rggb8'"), "{e}");
        assert!(
            MessageKind::from_schema("sensor_msgs/msg/CompressedImage") == Some(MessageKind::CompressedImage)
        );
        assert!(MessageKind::from_schema("sensor_msgs/Image") == Some(MessageKind::Image));
        assert!(MessageKind::from_schema("std_msgs/msg/String").is_none());
    }
}
