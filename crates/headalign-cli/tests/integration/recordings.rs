//! The commands on recordings: `calibrate` on an EuRoC folder and a ROS 2 bag built from
//! the real EuRoC pairs in `data/euroc_v101_pairs` (the dataset's lens through
//! `--lens-from`), `align --images` on a bag of a head run, and the one-line errors of a
//! missing topic, an unsupported encoding and images with no partner.

use std::path::{Path, PathBuf};

use super::common::{assert_clean_failure, bin, data_dir, ok_json, tmp_dir};
use headalign_io::recordings::cdr::{encode_image, encode_joint_state};
use headalign_io::recordings::rosbag::{BagWriter, MessageKind};
use headalign_io::session::{STAGE_VERGE_TILT, SessionInfo, SessionWriter, ViewLabel};
use headalign_platform::{Encoders, GrayImage, ImagingHead, Joint, StereoHead, StereoImages};
use serde_json::Value;

fn euroc_data() -> PathBuf {
    data_dir().join("euroc_v101_pairs")
}

/// Pair 3, then pair 2 half a second later (one general motion of the rig: 15.6 deg,
/// 0.32 m; the data's README), at made-up EuRoC-like stamps.
const STAMPS: [(i64, u32); 2] = [(1_403_715_273_262_142_976, 3), (1_403_715_273_762_142_976, 2)];

/// An EuRoC folder `SEQ/mav0/cam{0,1}/` with `data.csv`, `data/<stamp>.png` and the
/// dataset's `sensor.yaml`, built from the shared pairs.
fn euroc_fixture(data: &Path) -> PathBuf {
    let seq = tmp_dir("euroc");
    for (cam, side, yaml) in [("cam0", "left", "cam0_sensor.yaml"), ("cam1", "right", "cam1_sensor.yaml")] {
        let dir = seq.join("mav0").join(cam);
        std::fs::create_dir_all(dir.join("data")).unwrap();
        let mut csv = String::from("#timestamp [ns],filename\n");
        for (stamp, pair) in STAMPS {
            std::fs::copy(
                data.join(format!("{side}_img_{pair}.png")),
                dir.join("data").join(format!("{stamp}.png")),
            )
            .unwrap();
            csv += &format!("{stamp},{stamp}.png\n");
        }
        std::fs::write(dir.join("data.csv"), csv).unwrap();
        std::fs::copy(data.join(yaml), dir.join("sensor.yaml")).unwrap();
    }
    seq
}

fn calibrate(input: &Path, extra: &[&str]) -> Value {
    let mut c = bin();
    c.arg("calibrate").arg(input).args(["--zero-skew", "--square-pixels", "--json"]).args(extra);
    ok_json(&c.output().unwrap())
}

/// The EuRoC folder of pairs 3 and 2 with the dataset's own lens (`--lens-from
/// recording`: its `sensor.yaml` files) calibrates to the dataset's Kalibr focal lengths
/// within 2 % (measured: left 455.99 px, -0.58 % of fu 458.654 and -0.29 % of fv
/// 457.296; right 455.94 px, -0.36 % and -0.04 %); the same files given by name, and the
/// same pairs in a ROS 2 bag, give the same calibration number for number (same pixels,
/// same lens, same seeds).
#[test]
fn euroc_folder_and_bag_calibrate_with_the_datasets_lens() {
    let data = euroc_data();
    let seq = euroc_fixture(&data);
    let own = calibrate(&seq, &["--lens-from", "recording"]);
    for (side, fu, fv) in [("left", 458.654, 457.296), ("right", 457.587, 456.134)] {
        let f = own[side]["fx"].as_f64().unwrap();
        for truth in [fu, fv] {
            let err = 100.0 * (f - truth) / truth;
            assert!(err.abs() < 2.0, "{side} f {f} vs {truth}: {err:.2} %");
        }
    }
    assert_eq!(own["report"]["views"].as_array().map(Vec::len), Some(2), "{}", own["report"]);
    let files =
        format!("{},{}", data.join("cam0_sensor.yaml").display(), data.join("cam1_sensor.yaml").display());
    let named = calibrate(&seq, &["--lens-from", &files]);
    // The pairs in a bag (mono8 Image, a left and a right topic).
    let bag = tmp_dir("euroc-bag").join("pairs.mcap");
    let mut w = BagWriter::create(&bag).unwrap();
    for (stamp, pair) in STAMPS {
        for (topic, side) in [("/cam0/image_raw", "left"), ("/cam1/image_raw", "right")] {
            let img = GrayImage::load(&data.join(format!("{side}_img_{pair}.png"))).unwrap();
            let msg = encode_image(stamp, side, img.width(), img.height(), "mono8", img.pixels());
            w.write(topic, MessageKind::Image, stamp as u64, &msg).unwrap();
        }
    }
    w.finish().unwrap();
    let from_bag = calibrate(&bag, &["--lens-from", &files]);
    for v in [&named, &from_bag] {
        for key in ["left", "right", "right_from_left", "distortion"] {
            assert_eq!(v[key], own[key], "{key}");
        }
    }
    // `recording` needs an EuRoC folder.
    let out = bin().arg("calibrate").arg(&bag).args(["--lens-from", "recording"]).output().unwrap();
    assert_clean_failure(&out, &["--lens-from recording", "is not an EuRoC folder"]);
    std::fs::remove_dir_all(seq).ok();
}

fn texture(k: u32) -> Vec<u8> {
    (0..64 * 48).map(|i| ((i * 7919 + k * 131) % 251) as u8).collect()
}

/// The three errors a user meets first, one line each.
#[test]
fn missing_topic_unsupported_encoding_and_no_partner_are_one_line_errors() {
    let dir = tmp_dir("errors");
    let write = |name: &str, encoding: &str, lag: i64| {
        let path = dir.join(name);
        let mut w = BagWriter::create(&path).unwrap();
        for k in 0..2 {
            let t = 1_000_000_000 + k * 50_000_000;
            for (topic, l) in [("/left/image", 0), ("/right/image", lag)] {
                w.write(
                    topic,
                    MessageKind::Image,
                    (t + l) as u64,
                    &encode_image(t + l, "", 64, 48, encoding, &texture(k as u32)),
                )
                .unwrap();
            }
        }
        w.finish().unwrap();
        path
    };
    let run = |path: &Path, extra: &[&str]| bin().arg("calibrate").arg(path).args(extra).output().unwrap();
    let good = write("good.mcap", "mono8", 0);
    assert_clean_failure(
        &run(&good, &["--topics", "/cam0/image_raw,/right/image"]),
        &[
            "error: recording: bag",
            "has no topic '/cam0/image_raw'",
            "image topics: /left/image, /right/image",
        ],
    );
    assert_clean_failure(
        &run(&write("yuv.mcap", "yuv422", 0), &[]),
        &[
            "topic '/left/image' at 1.000000 s",
            "unsupported image encoding 'yuv422' (mono8, mono16, rgb8 and bgr8",
        ],
    );
    assert_clean_failure(
        &run(&write("late.mcap", "mono8", 3_000_000), &[]),
        &["no image on '/left/image' has a partner on '/right/image' within 1 ms"],
    );
    assert_clean_failure(&run(&good, &["--joint", "pan=head_pan"]), &["has no topic '/joint_states'"]);
    std::fs::remove_dir_all(dir).ok();
}

/// A head run recorded as a ROS 2 bag would be: both cameras at 20 Hz while the head
/// stops at the verge/tilt procedure's readings (initial, elevation, pan, verge; three
/// frames each) and moves between them (a frame in motion each time), joint states at
/// 100 Hz in radians. `align --images BAG --joint ...` finds the four stops and estimates
/// what `align --images` estimates on the same views as a session (the readings pass
/// through radians, so equal to 1e-9 relative, not bit for bit).
#[test]
fn align_reads_a_bag_of_a_head_run() {
    let scenario = headalign_sim::Scenario { seed: 3, ..headalign_sim::Scenario::default() };
    let mut head = headalign_sim::SimulatedHead::new(scenario).unwrap();
    let e0 = head.read_encoders().unwrap();
    let plan = headalign::procedure::capture_plan(&e0, &headalign::procedure::VergeTiltOptions::default());
    let mut views: Vec<(String, StereoImages)> = Vec::new();
    for (name, enc) in &plan {
        head.move_to(enc).unwrap();
        views.push((name.clone(), head.capture_images().unwrap()));
    }
    let dir = tmp_dir("head-run");
    // The session.
    let session = dir.join("session");
    let mut s =
        SessionWriter::create(&session, &SessionInfo::new("verge-tilt-images", 3.0, 0, head.image_size()))
            .unwrap();
    for (name, pair) in &views {
        let label = ViewLabel { name, stage: STAGE_VERGE_TILT, commanded: None, vehicle: None };
        s.write_view(&label, pair.encoders, Some(pair), None).unwrap();
    }
    // The bag of the same run.
    let bag = dir.join("run.mcap");
    write_head_run_bag(&bag, &views);
    let align = |input: &Path, extra: &[&str]| {
        ok_json(&bin().args(["align", "--json", "--images"]).arg(input).args(extra).output().unwrap())
    };
    let joints = "pan=head_pan,elevation=head_tilt,verge_left=eye_left,verge_right=eye_right";
    let from_session = align(&session, &[]);
    let from_bag = align(&bag, &["--joint", joints]);
    let close = |a: &Value, b: &Value| {
        (a.as_f64().unwrap() - b.as_f64().unwrap()).abs() <= 1e-9 * a.as_f64().unwrap().abs().max(1.0)
    };
    for side in ["left", "right"] {
        for k in ["fx", "fy", "cx", "cy"] {
            assert!(
                close(&from_session[side][k], &from_bag[side][k]),
                "{side}.{k}: {} vs {}",
                from_session[side][k],
                from_bag[side][k]
            );
        }
    }
    for j in ["elevation", "verge_left", "verge_right"] {
        let (a, b) = (&from_session["aligned_encoders"][j], &from_bag["aligned_encoders"][j]);
        assert!(close(a, b), "{j}: {a} vs {b}");
    }
    std::fs::remove_dir_all(dir).ok();
}

/// The bag of a head run over `views`: view k stands still over [k s - 0.2 s, k s + 0.3 s]
/// then moves linearly to the next; joint states at 100 Hz in radians, three still
/// frames per view and one in motion.
fn write_head_run_bag(bag: &Path, views: &[(String, StereoImages)]) {
    let mut w = BagWriter::create(bag).unwrap();
    let t0: i64 = 1_700_000_000_000_000_000;
    let ms = 1_000_000i64;
    let names = ["head_pan", "head_tilt", "eye_left", "eye_right"];
    let reading = |t: i64| -> Encoders {
        let k = ((t - t0 + 200 * ms) / (1000 * ms)).clamp(0, views.len() as i64 - 1) as usize;
        let into = t - t0 - k as i64 * 1000 * ms;
        let a = views[k].1.encoders;
        match views.get(k + 1) {
            Some((_, next)) if into > 300 * ms => {
                let f = (into - 300 * ms) as f64 / (500 * ms) as f64;
                let b = next.encoders;
                let mix = |j: Joint| a.get(j) + f.min(1.0) * (b.get(j) - a.get(j));
                Encoders {
                    pan: mix(Joint::Pan),
                    elevation: mix(Joint::Elevation),
                    verge_left: mix(Joint::VergeLeft),
                    verge_right: mix(Joint::VergeRight),
                }
            }
            _ => a,
        }
    };
    for step in 0..=(views.len() as i64 * 100) {
        let t = t0 - 300 * ms + step * 10 * ms;
        let e = reading(t);
        let pos = Joint::ALL.map(|j| e.get(j).to_radians());
        w.write(
            "/joint_states",
            MessageKind::JointState,
            t as u64,
            &encode_joint_state(t, &names, &pos, true),
        )
        .unwrap();
    }
    for (k, (_, pair)) in views.iter().enumerate() {
        let base = t0 + k as i64 * 1000 * ms;
        // Three still frames, then one in motion (the next view's images: any will do).
        let moving = views.get(k + 1).map_or(pair, |(_, p)| p);
        for (t, p) in
            [(base, pair), (base + 50 * ms, pair), (base + 100 * ms, pair), (base + 550 * ms, moving)]
        {
            let [wd, ht] = p.image_size();
            for (topic, img) in [("/stereo/left", &p.left), ("/stereo/right", &p.right)] {
                w.write(
                    topic,
                    MessageKind::Image,
                    t as u64,
                    &encode_image(t, "", wd, ht, "mono8", img.pixels()),
                )
                .unwrap();
            }
        }
    }
    w.finish().unwrap();
}

/// `replay BAG`: a simulated head's verge/tilt run (`demo --images --stages verge-tilt`)
/// turned into the bag a `ros2 bag record` of it would be (three frames at each capture,
/// joint states in radians at every frame), played back under the image procedure:
/// the procedure finds every move it makes among the bag's still views and ends at the
/// live run's aligned readings. Not bit for bit: the readings pass through radians (1e-16
/// relative), and the last verging capture and the initial view, taken at one reading,
/// are one still view (the simulator renders them alike). Measured: 3e-12 deg apart (the
/// same with a bag written by Python's `mcap-ros2-support`); bound 1e-6 deg, far below
/// the readings' own sigmas (0.01 deg on rendered images) and far above rounding.
#[test]
fn replay_plays_back_a_bag_of_a_recorded_run() {
    let dir = tmp_dir("replay");
    let session = dir.join("session");
    let live = ok_json(
        &bin()
            .args(["demo", "--images", "--stages", "verge-tilt", "--json", "--session"])
            .arg(&session)
            .output()
            .unwrap(),
    );
    let views = headalign_io::session::read_image_session(&session).unwrap();
    let bag = dir.join("run.mcap");
    let mut w = BagWriter::create(&bag).unwrap();
    let names = ["pan", "tilt", "vl", "vr"];
    for (k, v) in views.iter().enumerate() {
        let base = 1_000_000_000_000 + k as i64 * 1_000_000_000;
        let e = v.images.encoders;
        let pos = Joint::ALL.map(|j| e.get(j).to_radians());
        let [wd, ht] = v.images.image_size();
        for t in [base, base + 50_000_000, base + 100_000_000] {
            w.write(
                "/joint_states",
                MessageKind::JointState,
                t as u64,
                &encode_joint_state(t, &names, &pos, true),
            )
            .unwrap();
            for (topic, img) in [("/left/image_raw", &v.images.left), ("/right/image_raw", &v.images.right)] {
                w.write(
                    topic,
                    MessageKind::Image,
                    t as u64,
                    &encode_image(t, "", wd, ht, "mono8", img.pixels()),
                )
                .unwrap();
            }
        }
    }
    w.finish().unwrap();
    let replayed = ok_json(
        &bin()
            .arg("replay")
            .arg(&bag)
            .args(["--json", "--joint", "pan=pan,elevation=tilt,verge_left=vl,verge_right=vr"])
            .output()
            .unwrap(),
    );
    for j in ["elevation", "verge_left", "verge_right"] {
        let (a, b) = (&live["estimate"]["aligned_encoders"][j], &replayed["estimate"]["aligned_encoders"][j]);
        let d = (a.as_f64().unwrap() - b.as_f64().unwrap()).abs();
        assert!(d < 1e-6, "{j}: live {a}, replayed {b}");
    }
    // Nine captures, the last verging one and the initial view at one reading: 8 still
    // views, every one used.
    assert_eq!((replayed["still_views"].as_u64(), replayed["still_views_used"].as_u64()), (Some(8), Some(8)));
    std::fs::remove_dir_all(dir).ok();
}
