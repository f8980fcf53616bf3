//! Recordings in the formats users record in, read into the same views a session folder
//! gives ([`crate::session::RecordedView`]), so that every command that reads a session
//! reads a recording too (`docs/formats.md#recordings-ros-2-bags-and-euroc-folders`).
//!
//! - **EuRoC / ASL folders** ([`euroc`]): `mav0/cam0/data/*.png` listed by
//!   `mav0/cam0/data.csv` (`#timestamp [ns],filename`), the same for `cam1`; each camera's
//!   `sensor.yaml` is a lens model ([`euroc::read_sensor_yaml`]).
//! - **ROS 2 bags in MCAP** ([`rosbag`]): a `.mcap` file or the bag directory holding it
//!   (with `metadata.yaml`); two image topics (`sensor_msgs/msg/Image` or
//!   `CompressedImage`, CDR-encoded: [`cdr`]) and optionally `sensor_msgs/msg/JointState`
//!   mapped onto the head's joints.
//!
//! ## Pairing and selection
//!
//! A left and a right image form a pair when their stamps (the header stamps of a bag,
//! the file timestamps of EuRoC) differ by at most [`RecordingOptions::pair_tolerance_s`]
//! (default 1 ms); pairing runs in time order and uses each image once. Images with no
//! partner are reported in [`Recording::notes`]; no pair at all is an error. The pairs are
//! then selected by a time range ([`RecordingOptions::from_s`], [`RecordingOptions::to_s`],
//! seconds after the first pair) and by taking every N-th ([`RecordingOptions::every`]).
//! Blank pairs (a covered lens, the first frames of an exposure loop) are left out with a
//! note.
//!
//! ## Joint states
//!
//! Each head joint mapped to a ROS joint name ([`RecordingOptions::joints`]) is read from
//! the joint-state topic and interpolated linearly at each pair's stamp (the left image's);
//! radians are converted to degrees. A pair outside the time range of a joint's samples is
//! an error naming the pair and the range: extrapolating encoders would invent readings.
//! Joints not mapped read zero, as do all joints of a recording without joint states.
//!
//! ## A recorded head run
//!
//! A bag recorded while the head ran a procedure is a continuous stream; a procedure's
//! captures are the moments the head stood still. [`still_views`] keeps one pair per run
//! of pairs whose readings stay within [`STILL_DEG`] of each other (at least
//! [`MIN_STILL_PAIRS`] pairs), [`verge_tilt_views`] finds where the verge/tilt views start,
//! and [`PlaybackHead`] serves the still views to a procedure as a head (`replay`).
//!
//! Degrees of freedom: none (readers). Units: stamps in nanoseconds inside, seconds in
//! options and messages, encoders in degrees. Pitfalls: the stamps of two unsynchronised
//! cameras differ by up to half a frame period, more than any sensible tolerance: such a
//! recording does not pair, by design (the rig would not be rigid between the two
//! exposures of a moving head).

pub mod cdr;
pub mod euroc;
mod head;
pub mod rosbag;

use std::path::{Path, PathBuf};

use headalign_platform::{Encoders, GrayImage, Joint, StereoImages};

pub use head::{MIN_STILL_PAIRS, PlaybackHead, STILL_DEG, still_views, verge_tilt_views};

use crate::session::RecordedView;
use headalign::AlignError;

/// The recording formats read here.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RecordingFormat {
    /// An EuRoC / ASL folder (`mav0/cam0/data.csv`, ...).
    Euroc,
    /// A ROS 2 bag in MCAP (a `.mcap` file or the bag directory).
    Ros2Bag,
}

impl RecordingFormat {
    /// A short name for messages and reports.
    pub fn name(self) -> &'static str {
        match self {
            Self::Euroc => "EuRoC/ASL folder",
            Self::Ros2Bag => "ROS 2 bag (MCAP)",
        }
    }
}

/// The recording format at `path`, if it is one: a `.mcap` file, a directory with a
/// `metadata.yaml` or `.mcap`/`.db3` files (a ROS 2 bag), or a directory with
/// `mav0/cam0/data.csv` or `cam0/data.csv` (EuRoC). `None` for anything else (a session
/// folder, a folder of stereo pairs).
pub fn detect(path: &Path) -> Option<RecordingFormat> {
    if path.is_file() {
        let mcap = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("mcap"));
        return mcap.then_some(RecordingFormat::Ros2Bag);
    }
    if !path.is_dir() {
        return None;
    }
    if path.join("mav0/cam0/data.csv").is_file() || path.join("cam0/data.csv").is_file() {
        return Some(RecordingFormat::Euroc);
    }
    let bag_file = |p: &Path| {
        p.extension().is_some_and(|e| e.eq_ignore_ascii_case("mcap") || e.eq_ignore_ascii_case("db3"))
    };
    let has_bag_file = std::fs::read_dir(path)
        .map(|d| d.filter_map(Result::ok).any(|e| bag_file(&e.path())))
        .unwrap_or(false);
    (path.join("metadata.yaml").is_file() || has_bag_file).then_some(RecordingFormat::Ros2Bag)
}

/// How a recording is read (module docs); [`RecordingOptions::validate`] checks it.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordingOptions {
    /// The left and right image topics of a bag, or camera folders of an EuRoC recording.
    /// Default `None`: the bag's two image topics in name order (an error if it has
    /// another number), EuRoC's `cam0` and `cam1`.
    pub topics: Option<[String; 2]>,
    /// The `sensor_msgs/msg/JointState` topic. Default `/joint_states`.
    pub joint_topic: String,
    /// Head joints and the ROS joint names they read (positions in radians). Default
    /// empty: no joint states are read, every reading is zero.
    pub joints: Vec<(Joint, String)>,
    /// Largest stamp difference of a left and a right image in one pair, seconds. Default
    /// 0.001.
    pub pair_tolerance_s: f64,
    /// Keep every N-th pair (after the time range). Default 1.
    pub every: usize,
    /// Keep the pairs from this many seconds after the first pair. Default: from the start.
    pub from_s: Option<f64>,
    /// Keep the pairs up to this many seconds after the first pair. Default: to the end.
    pub to_s: Option<f64>,
}

impl Default for RecordingOptions {
    fn default() -> Self {
        Self {
            topics: None,
            joint_topic: "/joint_states".to_string(),
            joints: Vec::new(),
            pair_tolerance_s: 0.001,
            every: 1,
            from_s: None,
            to_s: None,
        }
    }
}

impl RecordingOptions {
    /// Check the options: a tolerance in (0, 1] s, `every` at least 1, finite times with
    /// `from_s < to_s`, distinct non-empty topics, each head joint mapped once to a
    /// non-empty name.
    pub fn validate(&self) -> Result<(), AlignError> {
        let bad = |m: String| Err(AlignError::InvalidOption(m));
        if !(self.pair_tolerance_s.is_finite() && self.pair_tolerance_s > 0.0 && self.pair_tolerance_s <= 1.0)
        {
            return bad(format!("pair tolerance must be in (0, 1] s, got {} s", self.pair_tolerance_s));
        }
        if self.every == 0 {
            return bad("every: keep every N-th pair needs N >= 1".into());
        }
        for t in [self.from_s, self.to_s].into_iter().flatten() {
            if !t.is_finite() {
                return bad(format!("time range: {t} is not a finite number of seconds"));
            }
        }
        if let (Some(a), Some(b)) = (self.from_s, self.to_s)
            && a >= b
        {
            return bad(format!("time range: from {a} s must be before to {b} s"));
        }
        if let Some([l, r]) = &self.topics
            && (l.trim().is_empty() || r.trim().is_empty() || l == r)
        {
            return bad(format!("topics: two different non-empty names are needed, got '{l}' and '{r}'"));
        }
        for (i, (joint, name)) in self.joints.iter().enumerate() {
            if name.trim().is_empty() {
                return bad(format!("joint {}: the ROS joint name is empty", joint.name()));
            }
            if self.joints[..i].iter().any(|(j, _)| j == joint) {
                return bad(format!("joint {} is mapped twice", joint.name()));
            }
        }
        Ok(())
    }
}

/// A recording read into views.
#[derive(Debug, Clone)]
pub struct Recording {
    /// The format.
    pub format: RecordingFormat,
    /// The path read.
    pub source: PathBuf,
    /// The left and right topics (EuRoC: camera folders) used.
    pub topics: [String; 2],
    /// Pairs found before the time range and every-N selection.
    pub pairs_found: usize,
    /// The selected pairs in time order, named by their stamp in nanoseconds, with the
    /// encoders interpolated from the joint states (stage `None`).
    pub views: Vec<RecordedView>,
    /// What was left out and why (unpaired images, blank pairs, unused joint states).
    pub notes: Vec<String>,
}

/// Read the recording at `path` (its format detected by [`detect`]).
pub fn read_recording(path: &Path, options: &RecordingOptions) -> Result<Recording, AlignError> {
    options.validate()?;
    match detect(path) {
        Some(RecordingFormat::Euroc) => euroc::read(path, options),
        Some(RecordingFormat::Ros2Bag) => rosbag::read(path, options),
        None => Err(AlignError::Recording(format!(
            "'{}' is neither a ROS 2 bag (a .mcap file, or a folder with metadata.yaml) nor an EuRoC folder (mav0/cam0/data.csv)",
            path.display()
        ))),
    }
}

/// One image of a stream before pairing: its stamp and where to find it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Stamped {
    /// Nanoseconds.
    pub stamp_ns: i64,
    /// The image's index in its stream (a message ordinal, a CSV row).
    pub index: usize,
}

/// A left and a right image paired by stamp.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Pair {
    pub left: Stamped,
    pub right: Stamped,
}

/// Seconds from nanoseconds, for messages.
pub(crate) fn secs(ns: i64) -> f64 {
    ns as f64 * 1e-9
}

/// Pair two streams by stamp within `tolerance_ns` (module docs); the notes say how many
/// of each had no partner. No pair at all is an error naming both streams.
pub(crate) fn pair_streams(
    mut left: Vec<Stamped>,
    mut right: Vec<Stamped>,
    tolerance_ns: i64,
    names: &[String; 2],
    notes: &mut Vec<String>,
) -> Result<Vec<Pair>, AlignError> {
    left.sort_by_key(|s| (s.stamp_ns, s.index));
    right.sort_by_key(|s| (s.stamp_ns, s.index));
    let (mut pairs, mut lonely_left, mut lonely_right) = (Vec::new(), Vec::new(), Vec::new());
    let mut j = 0;
    for l in &left {
        while j < right.len() && right[j].stamp_ns < l.stamp_ns - tolerance_ns {
            lonely_right.push(right[j]);
            j += 1;
        }
        // Of two candidates within the tolerance take the nearer.
        while j + 1 < right.len()
            && (right[j + 1].stamp_ns - l.stamp_ns).abs() < (right[j].stamp_ns - l.stamp_ns).abs()
        {
            lonely_right.push(right[j]);
            j += 1;
        }
        if j < right.len() && (right[j].stamp_ns - l.stamp_ns).abs() <= tolerance_ns {
            pairs.push(Pair { left: *l, right: right[j] });
            j += 1;
        } else {
            lonely_left.push(*l);
        }
    }
    lonely_right.extend_from_slice(&right[j.min(right.len())..]);
    let tol_ms = tolerance_ns as f64 * 1e-6;
    if pairs.is_empty() {
        let first =
            |s: &[Stamped]| s.first().map_or("none".to_string(), |s| format!("{:.6} s", secs(s.stamp_ns)));
        return Err(AlignError::Recording(format!(
            "no image on '{}' has a partner on '{}' within {tol_ms} ms ({} and {} images, first stamps {} and {}): the cameras' stamps differ; widen the pair tolerance if they are synchronised",
            names[0],
            names[1],
            left.len(),
            right.len(),
            first(&left),
            first(&right)
        )));
    }
    for (lonely, name) in [(&lonely_left, &names[0]), (&lonely_right, &names[1])] {
        if let Some(s) = lonely.first() {
            notes.push(format!(
                "{} image(s) on '{name}' have no partner within {tol_ms} ms (the first at {:.6} s); left out",
                lonely.len(),
                secs(s.stamp_ns)
            ));
        }
    }
    Ok(pairs)
}

/// The pairs kept by the time range and every-N selection (module docs); an empty
/// selection is an error that gives the recording's span.
pub(crate) fn select_pairs(pairs: &[Pair], options: &RecordingOptions) -> Result<Vec<Pair>, AlignError> {
    let Some(first) = pairs.first() else { return Ok(Vec::new()) };
    let t0 = first.left.stamp_ns;
    let rel = |p: &Pair| secs(p.left.stamp_ns - t0);
    let kept: Vec<Pair> = pairs
        .iter()
        .filter(|p| options.from_s.is_none_or(|a| rel(p) >= a) && options.to_s.is_none_or(|b| rel(p) <= b))
        .copied()
        .enumerate()
        .filter(|(i, _)| i % options.every == 0)
        .map(|(_, p)| p)
        .collect();
    if kept.is_empty() {
        let span = pairs.last().map_or(0.0, rel);
        return Err(AlignError::Recording(format!(
            "no pair in the time range {} .. {} s: the {} pairs span 0 .. {span:.3} s after the first",
            options.from_s.map_or("start".into(), |v| v.to_string()),
            options.to_s.map_or("end".into(), |v| v.to_string()),
            pairs.len()
        )));
    }
    Ok(kept)
}

/// One joint's samples: (stamp ns, position as recorded), sorted by stamp.
#[derive(Debug, Clone, Default)]
pub(crate) struct JointSeries {
    pub samples: Vec<(i64, f64)>,
}

impl JointSeries {
    /// Linear interpolation at `t`; `None` outside the samples' range.
    pub fn at(&self, t: i64) -> Option<f64> {
        let s = &self.samples;
        let (first, last) = (s.first()?, s.last()?);
        if t < first.0 || t > last.0 {
            return None;
        }
        let k = s.partition_point(|&(ts, _)| ts < t);
        let (t1, v1) = s[k.min(s.len() - 1)];
        if t1 == t || k == 0 {
            return Some(v1);
        }
        let (t0, v0) = s[k - 1];
        let w = (t - t0) as f64 / (t1 - t0) as f64;
        Some(v0 + w * (v1 - v0))
    }
}

/// The encoders at `stamp_ns`: each mapped joint interpolated (radians to degrees), the
/// others zero. `view` and `topic` name the pair and the joint-state topic in errors.
pub(crate) fn encoders_at(
    series: &[(Joint, String, JointSeries)],
    stamp_ns: i64,
    view: &str,
    topic: &str,
) -> Result<Encoders, AlignError> {
    let mut e = Encoders::default();
    for (joint, name, s) in series {
        let Some(v) = s.at(stamp_ns) else {
            let (a, b) = (s.samples.first().map_or(0, |x| x.0), s.samples.last().map_or(0, |x| x.0));
            return Err(AlignError::Recording(format!(
                "pair {view} at {:.6} s lies outside the joint states of '{name}' on '{topic}' ({:.6} .. {:.6} s): record the joint states over the whole image stream",
                secs(stamp_ns),
                secs(a),
                secs(b)
            )));
        };
        e = e.moved(*joint, v.to_degrees());
    }
    Ok(e)
}

/// Build the views from decoded pairs: size checks against the first pair, blank pairs
/// left out with a note (all blank is an error). `images` yields, for each selected pair
/// in order, its name, encoders and two images.
pub(crate) fn build_views(
    source: &Path,
    pairs: impl IntoIterator<Item = Result<(String, Encoders, GrayImage, GrayImage), AlignError>>,
    notes: &mut Vec<String>,
) -> Result<Vec<RecordedView>, AlignError> {
    let mut views: Vec<RecordedView> = Vec::new();
    let mut blank = Vec::new();
    for item in pairs {
        let (name, encoders, left, right) = item?;
        if left.size() != right.size() {
            return Err(AlignError::Recording(format!(
                "'{}': pair {name}: the left image is {}x{} but the right is {}x{}",
                source.display(),
                left.width(),
                left.height(),
                right.width(),
                right.height()
            )));
        }
        if let Some(first) = views.first()
            && first.images.image_size() != left.size()
        {
            let [w, h] = first.images.image_size();
            return Err(AlignError::Recording(format!(
                "'{}': pair {name} is {}x{} but the first pair is {w}x{h}",
                source.display(),
                left.width(),
                left.height()
            )));
        }
        let is_blank = |img: &GrayImage| crate::session::check_image(img, &name).is_err();
        if is_blank(&left) || is_blank(&right) {
            blank.push(name);
            continue;
        }
        let images = StereoImages::new(encoders, left, right)
            .map_err(|e| AlignError::Recording(format!("'{}': pair {name}: {e}", source.display())))?;
        views.push(RecordedView { name, stage: None, folder: source.to_path_buf(), images });
    }
    if let Some(b) = blank.first() {
        if views.is_empty() {
            return Err(AlignError::Recording(format!(
                "'{}': every selected pair is blank (no texture; the first is {b})",
                source.display()
            )));
        }
        notes.push(format!("{} blank pair(s) left out (the first is {b})", blank.len()));
    }
    Ok(views)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stream(stamps: &[i64]) -> Vec<Stamped> {
        stamps.iter().enumerate().map(|(index, &stamp_ns)| Stamped { stamp_ns, index }).collect()
    }

    #[test]
    fn pairs_match_within_the_tolerance_and_lonely_images_are_reported() {
        let names = ["/l".to_string(), "/r".to_string()];
        let mut notes = Vec::new();
        // Right stamps 0.3 ms late; an extra left at 150 ms; a right at 410 ms nearer to
        // the left at 400 ms than the one at 399.5 ms... both within 1 ms: the nearer wins.
        let l = stream(&[0, 50_000_000, 100_000_000, 150_000_000, 400_000_000]);
        let r = stream(&[300_000, 50_300_000, 100_300_000, 399_000_000, 400_200_000]);
        let p = pair_streams(l, r, 1_000_000, &names, &mut notes).unwrap();
        let got: Vec<(usize, usize)> = p.iter().map(|p| (p.left.index, p.right.index)).collect();
        assert_eq!(got, [(0, 0), (1, 1), (2, 2), (4, 4)]);
        assert_eq!(notes.len(), 2, "{notes:?}");
        assert!(notes[0].contains("1 image(s) on '/l'") && notes[0].contains("0.150000 s"), "{notes:?}");
        assert!(notes[1].contains("1 image(s) on '/r'"), "{notes:?}");
        // Nothing pairs: one line naming both streams.
        let e = pair_streams(stream(&[0]), stream(&[5_000_000]), 1_000_000, &names, &mut notes)
            .unwrap_err()
            .to_string();
        assert!(e.contains("no image on '/l' has a partner on '/r' within 1 ms") && !e.contains('\n'), "{e}");
    }

    #[test]
    fn selection_and_interpolation() {
        let pairs: Vec<Pair> = (0..10)
            .map(|k| {
                let s = Stamped { stamp_ns: 1_000 + k * 100_000_000, index: k as usize };
                Pair { left: s, right: s }
            })
            .collect();
        let o = RecordingOptions {
            every: 2,
            from_s: Some(0.25),
            to_s: Some(0.85),
            ..RecordingOptions::default()
        };
        let kept: Vec<usize> = select_pairs(&pairs, &o).unwrap().iter().map(|p| p.left.index).collect();
        assert_eq!(kept, [3, 5, 7]);
        let o = RecordingOptions { from_s: Some(5.0), ..RecordingOptions::default() };
        assert!(select_pairs(&pairs, &o).unwrap_err().to_string().contains("span 0 .. 0.900 s"));
        let s = JointSeries { samples: vec![(0, 0.0), (10, 1.0), (20, 3.0)] };
        assert_eq!([s.at(0), s.at(5), s.at(10), s.at(15), s.at(20)], [0.0, 0.5, 1.0, 2.0, 3.0].map(Some));
        assert_eq!((s.at(-1), s.at(21)), (None, None));
        let series = vec![(Joint::Pan, "pan_joint".to_string(), s)];
        let e = encoders_at(&series, 15, "v", "/js").unwrap();
        assert!((e.pan - 2f64.to_degrees()).abs() < 1e-12 && e.elevation == 0.0);
        let err = encoders_at(&series, 25, "v", "/js").unwrap_err().to_string();
        assert!(err.contains("pair v") && err.contains("outside the joint states of 'pan_joint'"), "{err}");
    }

    #[test]
    fn options_are_validated() {
        assert!(RecordingOptions::default().validate().is_ok());
        let bad = [
            RecordingOptions { pair_tolerance_s: 0.0, ..Default::default() },
            RecordingOptions { every: 0, ..Default::default() },
            RecordingOptions { from_s: Some(2.0), to_s: Some(1.0), ..Default::default() },
            RecordingOptions { topics: Some(["/a".into(), "/a".into()]), ..Default::default() },
            RecordingOptions {
                joints: vec![(Joint::Pan, "a".into()), (Joint::Pan, "b".into())],
                ..Default::default()
            },
        ];
        for o in bad {
            assert!(o.validate().is_err(), "{o:?}");
        }
    }
}
