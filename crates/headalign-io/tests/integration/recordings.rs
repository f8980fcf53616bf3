//! Reading ROS 2 bags (MCAP) written here with the `mcap` crate's writer
//! ([`BagWriter`]): image encodings, compressed images, joint-state interpolation,
//! chunks compressed as rosbag2 writes them, and the errors a user meets.

use std::path::{Path, PathBuf};

use headalign_io::recordings::cdr::{encode_compressed_image, encode_image, encode_joint_state};
use headalign_io::recordings::rosbag::{BagWriter, MessageKind};
use headalign_io::recordings::{RecordingOptions, read_recording};
use headalign_platform::{GrayImage, Joint};

fn temp(name: &str) -> PathBuf {
    crate::common::temp_dir("bag", name)
}

/// A textured 64x48 image, different for each `k` (no blank image).
fn texture(k: u32) -> GrayImage {
    let data = (0..64 * 48).map(|i| ((i * 7919 + k * 131) % 251) as u8).collect();
    GrayImage::new(64, 48, data).unwrap()
}

const T0: i64 = 1_700_000_000_000_000_000;
const FRAME_NS: i64 = 100_000_000;

/// Five pairs at 10 Hz (right stamps `right_lag_ns` later) as mono8 `Image`, and joint
/// states at 100 Hz from 50 ms before the first image to 50 ms after the last: `pan_joint`
/// = 0.1 rad/s x t, `tilt_joint` = -0.2 rad constant.
fn write_bag(path: &Path, right_lag_ns: i64, encoding: &str) {
    let mut bag = BagWriter::create(path).unwrap();
    for k in 0..=50 {
        let t = T0 - 50_000_000 + k * 10_000_000;
        let pan = 0.1 * (t - T0) as f64 * 1e-9;
        let msg = encode_joint_state(t, &["tilt_joint", "pan_joint"], &[-0.2, pan], k % 2 == 0);
        bag.write("/joint_states", MessageKind::JointState, t as u64, &msg).unwrap();
    }
    for k in 0..5u32 {
        let t = T0 + i64::from(k) * FRAME_NS;
        for (topic, lag, img) in [
            ("/stereo/left/image_raw", 0, texture(2 * k)),
            ("/stereo/right/image_raw", right_lag_ns, texture(2 * k + 1)),
        ] {
            let msg = encode_image(t + lag, "cam", 64, 48, encoding, img.pixels());
            bag.write(topic, MessageKind::Image, (t + lag) as u64, &msg).unwrap();
        }
    }
    bag.finish().unwrap();
}

fn joints() -> RecordingOptions {
    RecordingOptions {
        joints: vec![(Joint::Pan, "pan_joint".into()), (Joint::Elevation, "tilt_joint".into())],
        ..RecordingOptions::default()
    }
}

#[test]
fn a_mono8_bag_with_joint_states_reads_and_interpolates() {
    let dir = temp("mono8");
    let bag = dir.join("run.mcap");
    write_bag(&bag, 200_000, "mono8");
    let rec = read_recording(&bag, &joints()).unwrap();
    assert_eq!(rec.topics, ["/stereo/left/image_raw", "/stereo/right/image_raw"]);
    assert_eq!((rec.pairs_found, rec.views.len()), (5, 5));
    assert!(rec.notes.is_empty(), "{:?}", rec.notes);
    for (k, v) in rec.views.iter().enumerate() {
        assert_eq!(v.name, (T0 + k as i64 * FRAME_NS).to_string());
        assert_eq!(v.images.left, texture(2 * k as u32));
        assert_eq!(v.images.right, texture(2 * k as u32 + 1));
        // Interpolated at the left stamp: 0.1 rad/s, converted to degrees (the samples
        // are 10 ms apart and linear, so interpolation is exact to rounding).
        let pan = (0.1 * k as f64 * 0.1).to_degrees();
        assert!((v.images.encoders.pan - pan).abs() < 1e-9, "{} vs {pan}", v.images.encoders.pan);
        assert!((v.images.encoders.elevation - (-0.2f64).to_degrees()).abs() < 1e-12);
        assert_eq!((v.images.encoders.verge_left, v.images.encoders.verge_right), (0.0, 0.0));
    }
    // Every other pair, from 0.15 s on: pairs 2 and 4.
    let o = RecordingOptions { every: 2, from_s: Some(0.15), ..joints() };
    let names: Vec<String> = read_recording(&bag, &o).unwrap().views.into_iter().map(|v| v.name).collect();
    assert_eq!(names, [(T0 + 2 * FRAME_NS).to_string(), (T0 + 4 * FRAME_NS).to_string()]);
    // Without a joint mapping the readings are zero and the unused joint states noted.
    let rec = read_recording(&bag, &RecordingOptions::default()).unwrap();
    assert_eq!(rec.views[3].images.encoders, headalign_platform::Encoders::default());
    assert!(rec.notes[0].contains("joint states on '/joint_states' not used"), "{:?}", rec.notes);
    std::fs::remove_dir_all(&dir).ok();
}

/// Re-pack every chunk of an MCAP file with `compression` (`zstd` by `ruzstd`, `lz4` by
/// `lz4_flex`): rosbag2 writes zstd chunks by default, and the `mcap` crate here is built
/// without its C compressors. Other records are copied as they are (the summary's chunk
/// offsets go stale; the reader does not use them).
fn recompress(bytes: &[u8], compression: &str) -> Vec<u8> {
    let (magic, mut rest) = bytes.split_at(8);
    let mut out = magic.to_vec();
    let u64_at = |b: &[u8], at: usize| u64::from_le_bytes(b[at..at + 8].try_into().unwrap());
    while rest.len() > 8 {
        let (op, len) = (rest[0], u64_at(rest, 1) as usize);
        let body = &rest[9..9 + len];
        if op == 0x06 {
            // start, end, uncompressed size (3 x u64), crc (u32), compression (string),
            // records (u64 length + bytes).
            let name_len = u32::from_le_bytes(body[28..32].try_into().unwrap()) as usize;
            assert_eq!(name_len, 0, "the writer's chunks are uncompressed");
            let records = &body[40..];
            assert_eq!(u64_at(body, 32) as usize, records.len());
            let packed = match compression {
                "zstd" => {
                    ruzstd::encoding::compress_to_vec(records, ruzstd::encoding::CompressionLevel::Fastest)
                }
                _ => {
                    let mut enc = lz4_flex::frame::FrameEncoder::new(Vec::new());
                    std::io::Write::write_all(&mut enc, records).unwrap();
                    enc.finish().unwrap()
                }
            };
            let mut chunk = body[..28].to_vec();
            chunk.extend_from_slice(&(compression.len() as u32).to_le_bytes());
            chunk.extend_from_slice(compression.as_bytes());
            chunk.extend_from_slice(&(packed.len() as u64).to_le_bytes());
            chunk.extend_from_slice(&packed);
            out.push(op);
            out.extend_from_slice(&(chunk.len() as u64).to_le_bytes());
            out.extend_from_slice(&chunk);
        } else {
            out.extend_from_slice(&rest[..9 + len]);
        }
        rest = &rest[9 + len..];
    }
    out.extend_from_slice(rest);
    out
}

#[test]
fn zstd_and_lz4_chunks_and_a_bag_directory_read_the_same() {
    let dir = temp("compressed");
    let plain = dir.join("plain.mcap");
    write_bag(&plain, 0, "mono8");
    let want = read_recording(&plain, &joints()).unwrap().views;
    let bytes = std::fs::read(&plain).unwrap();
    for compression in ["zstd", "lz4"] {
        // A bag directory as `ros2 bag record` leaves it: metadata.yaml and the file.
        let bag = dir.join(format!("bag_{compression}"));
        std::fs::create_dir_all(&bag).unwrap();
        std::fs::write(
            bag.join("metadata.yaml"),
            "rosbag2_bagfile_information:\n  storage_identifier: mcap\n",
        )
        .unwrap();
        let packed = recompress(&bytes, compression);
        assert!(packed.len() < bytes.len(), "{compression} did not compress");
        std::fs::write(bag.join(format!("bag_{compression}_0.mcap")), &packed).unwrap();
        let got = read_recording(&bag, &joints()).unwrap().views;
        assert_eq!(got.len(), want.len());
        for (g, w) in got.iter().zip(&want) {
            assert_eq!((&g.name, &g.images), (&w.name, &w.images), "{compression}");
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn compressed_png_images_read() {
    let dir = temp("png");
    let bag = dir.join("png.mcap");
    let mut w = BagWriter::create(&bag).unwrap();
    for k in 0..2u32 {
        let t = T0 + i64::from(k) * FRAME_NS;
        for (topic, img) in
            [("/cam0/image_raw/compressed", texture(k)), ("/cam1/image_raw/compressed", texture(k + 7))]
        {
            let png = dir.join("tmp.png");
            img.save(&png).unwrap();
            let msg = encode_compressed_image(
                t,
                "cam",
                "mono8; png compressed mono8",
                &std::fs::read(&png).unwrap(),
            );
            w.write(topic, MessageKind::CompressedImage, t as u64, &msg).unwrap();
        }
    }
    w.finish().unwrap();
    let rec = read_recording(&bag, &RecordingOptions::default()).unwrap();
    assert_eq!(rec.views.len(), 2);
    assert_eq!((&rec.views[1].images.left, &rec.views[1].images.right), (&texture(1), &texture(8)));
    std::fs::remove_dir_all(&dir).ok();
}

/// Mistakes in the options: a missing topic, a topic of another type, a missing joint.
#[test]
fn a_users_mistakes_are_one_line_errors() {
    let dir = temp("errors");
    let good = dir.join("good.mcap");
    write_bag(&good, 0, "mono8");
    let err = |path: &Path, o: RecordingOptions| read_recording(path, &o).unwrap_err().to_string();
    let cases: Vec<(String, &[&str])> = vec![
        (
            err(
                &good,
                RecordingOptions {
                    topics: Some(["/cam0".into(), "/stereo/right/image_raw".into()]),
                    ..joints()
                },
            ),
            &["has no topic '/cam0'", "image topics: /stereo/left/image_raw, /stereo/right/image_raw"],
        ),
        (
            err(
                &good,
                RecordingOptions {
                    topics: Some(["/joint_states".into(), "/stereo/right/image_raw".into()]),
                    ..joints()
                },
            ),
            &["'/joint_states'", "is 'sensor_msgs/msg/JointState', not sensor_msgs/msg/Image"],
        ),
        (err(&good, RecordingOptions { joint_topic: "/js".into(), ..joints() }), &["has no topic '/js'"]),
        (
            err(&good, RecordingOptions { joints: vec![(Joint::VergeLeft, "eye_l".into())], ..joints() }),
            &["joint 'eye_l' (for verge_left)", "joints: pan_joint, tilt_joint"],
        ),
    ];
    for (e, parts) in &cases {
        assert!(!e.contains('\n'), "{e}");
        for p in *parts {
            assert!(e.contains(p), "'{e}' lacks '{p}'");
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// Mistakes in the data rather than the options: joint states that end early, an
/// unsupported encoding, unpaired images, a sqlite3 bag, a file that is not MCAP, a
/// truncated bag.
#[test]
fn bad_recordings_are_one_line_errors() {
    let dir = temp("bad-data");
    let good = dir.join("good.mcap");
    write_bag(&good, 0, "mono8");
    let err = |path: &Path, o: RecordingOptions| read_recording(path, &o).unwrap_err().to_string();
    // Images outside the joint states: a joint stream that ends early.
    let short = dir.join("short.mcap");
    let mut w = BagWriter::create(&short).unwrap();
    w.write(
        "/joint_states",
        MessageKind::JointState,
        0,
        &encode_joint_state(T0, &["pan_joint", "tilt_joint"], &[0.0, 0.0], true),
    )
    .unwrap();
    w.write(
        "/joint_states",
        MessageKind::JointState,
        0,
        &encode_joint_state(T0 + 1, &["pan_joint", "tilt_joint"], &[0.0, 0.0], true),
    )
    .unwrap();
    for topic in ["/l", "/r"] {
        for k in 0..2 {
            let t = T0 + k * FRAME_NS;
            w.write(
                topic,
                MessageKind::Image,
                t as u64,
                &encode_image(t, "", 64, 48, "mono8", texture(k as u32).pixels()),
            )
            .unwrap();
        }
    }
    w.finish().unwrap();
    let e = err(&short, joints());
    assert!(
        e.contains(&format!("pair {} ", T0 + FRAME_NS))
            && e.contains("outside the joint states of 'pan_joint'"),
        "{e}"
    );
    // An unsupported encoding names the topic and the encoding.
    let bayer = dir.join("bayer.mcap");
    write_bag(&bayer, 0, "bayer_rggb8");
    let e = err(&bayer, joints());
    assert!(
        e.contains("topic '/stereo/left/image_raw'")
            && e.contains("unsupported image encoding 'bayer_rggb8'"),
        "{e}"
    );
    // Images with no partner: the right camera 5 ms late, beyond the 1 ms tolerance.
    let late = dir.join("late.mcap");
    write_bag(&late, 5_000_000, "mono8");
    let e = err(&late, joints());
    assert!(
        e.contains(
            "no image on '/stereo/left/image_raw' has a partner on '/stereo/right/image_raw' within 1 ms"
        ),
        "{e}"
    );
    // A 6 ms tolerance pairs them.
    assert_eq!(
        read_recording(&late, &RecordingOptions { pair_tolerance_s: 0.006, ..joints() }).unwrap().views.len(),
        5
    );
    // A sqlite3 bag, and a file that is not MCAP.
    let sqlite = dir.join("sqlite_bag");
    std::fs::create_dir_all(&sqlite).unwrap();
    std::fs::write(sqlite.join("metadata.yaml"), "").unwrap();
    std::fs::write(sqlite.join("sqlite_bag_0.db3"), "").unwrap();
    assert!(err(&sqlite, joints()).contains("sqlite3 bag (.db3): convert it"));
    let junk = dir.join("junk.mcap");
    std::fs::write(&junk, b"not an mcap file at all").unwrap();
    assert!(err(&junk, joints()).contains("not a readable MCAP file"));
    // A truncated bag is an error, never a panic.
    let bytes = std::fs::read(&good).unwrap();
    for cut in [9, bytes.len() / 3, bytes.len() - 9] {
        std::fs::write(&junk, &bytes[..cut]).unwrap();
        assert!(read_recording(&junk, &joints()).is_err(), "cut at {cut}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// A bag written by an independent ROS 2 MCAP writer: Foxglove's Python
/// `mcap-ros2-support` (its own CDR serialiser, zstd chunks from the zstandard C library),
/// made by `python3 bench/ros2_bag.py fixture crates/headalign-io/tests/data/python_mcap_ros2.mcap`.
/// Every pixel and every interpolated reading is what the script wrote (its docstring
/// gives the formulas).
#[test]
fn a_bag_from_an_independent_writer_reads_exactly() {
    let path = crate::common::test_path("data/python_mcap_ros2.mcap");
    let o = RecordingOptions {
        joints: vec![(Joint::Pan, "pan_joint".into()), (Joint::Elevation, "tilt_joint".into())],
        ..RecordingOptions::default()
    };
    let rec = read_recording(&path, &o).unwrap();
    assert_eq!(rec.topics, ["/left/image_raw", "/right/image_raw"]);
    assert_eq!(rec.views.len(), 3);
    for (k, v) in rec.views.iter().enumerate() {
        assert_eq!(v.name, (10_000_000_000 + k as i64 * 100_000_000).to_string());
        for (side, img) in [&v.images.left, &v.images.right].into_iter().enumerate() {
            let want: Vec<u8> = (0..24)
                .flat_map(|y| (0..32).map(move |x| ((3 * x + 5 * y + 17 * k + 40 * side) % 256) as u8))
                .collect();
            assert_eq!(img.pixels(), &want[..], "view {k} side {side}");
        }
        let e = v.images.encoders;
        // 0.5 rad/s sampled every 10 ms and read back at a sample: exact to rounding.
        assert!((e.pan - (0.05 * k as f64).to_degrees()).abs() < 1e-9, "{}", e.pan);
        assert!((e.elevation - (-0.1f64).to_degrees()).abs() < 1e-12, "{}", e.elevation);
    }
}
