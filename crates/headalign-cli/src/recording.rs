//! Recordings on the command line: the flags that say how a ROS 2 bag or an EuRoC folder
//! is read (shared by `calibrate`, `align --images` and `replay`), `--lens-from`, and the
//! views each command takes from a recording ([`headalign_io::recordings`] does the reading).

use std::path::Path;

use anyhow::{Context, Result, bail};
use clap::Args;
use headalign::calibrate::LensModel;
use headalign_io::recordings::{
    self, PlaybackHead, Recording, RecordingFormat, RecordingOptions, euroc, still_views, verge_tilt_views,
};
use headalign_io::session::RecordedView;
use headalign_platform::Joint;

/// How a recording (ROS 2 bag, EuRoC folder) is read.
#[derive(Args, Clone, Debug)]
pub struct RecordingArgs {
    /// A bag's left and right image topics (EuRoC: camera folders), e.g.
    /// /cam0/image_raw,/cam1/image_raw; default: the bag's two image topics in name order.
    #[arg(long, value_name = "LEFT,RIGHT")]
    pub topics: Option<String>,
    /// Map head joints to a bag's joint states (radians), e.g. pan=head_pan,elevation=head_tilt.
    #[arg(long, value_name = "JOINT=NAME,...")]
    pub joint: Option<String>,
    /// The bag's sensor_msgs/JointState topic.
    #[arg(long, default_value = "/joint_states")]
    pub joint_topic: String,
    /// Largest stamp difference of a left and a right image in one pair, milliseconds.
    #[arg(long, default_value_t = 1.0)]
    pub pair_tolerance_ms: f64,
    /// Keep every N-th pair of a recording or a folder of stereo pairs.
    #[arg(long, default_value_t = 1)]
    pub every: usize,
    /// Keep a recording's pairs from this many seconds after its first pair.
    #[arg(long)]
    pub from: Option<f64>,
    /// Keep a recording's pairs up to this many seconds after its first pair.
    #[arg(long)]
    pub to: Option<f64>,
}

impl Default for RecordingArgs {
    fn default() -> Self {
        Self {
            topics: None,
            joint: None,
            joint_topic: "/joint_states".into(),
            pair_tolerance_ms: 1.0,
            every: 1,
            from: None,
            to: None,
        }
    }
}

/// `--joint pan=NAME,elevation=NAME,...`.
fn parse_joints(spec: &str) -> Result<Vec<(Joint, String)>> {
    spec.split(',')
        .filter(|s| !s.trim().is_empty())
        .map(|item| {
            let Some((joint, name)) = item.split_once('=') else {
                bail!("--joint: '{item}' is not JOINT=NAME (JOINT: pan, elevation, verge_left, verge_right)");
            };
            let joint = Joint::ALL.into_iter().find(|j| j.name() == joint.trim()).with_context(|| {
                format!(
                    "--joint: unknown head joint '{}' (pan, elevation, verge_left, verge_right)",
                    joint.trim()
                )
            })?;
            Ok((joint, name.trim().to_string()))
        })
        .collect()
}

impl RecordingArgs {
    /// An error naming the recording flags given (other than their defaults) for `dir`,
    /// which is `what` and not a recording (they would be ignored); `--every` is allowed
    /// where `every_applies` (a folder of stereo pairs keeps every N-th pair too).
    pub fn only_for_recordings(&self, dir: &Path, what: &str, every_applies: bool) -> Result<()> {
        let d = Self::default();
        crate::flags::refuse(
            &[
                ("--topics", self.topics.is_some()),
                ("--joint", self.joint.is_some()),
                ("--joint-topic", self.joint_topic != d.joint_topic),
                ("--pair-tolerance-ms", self.pair_tolerance_ms != d.pair_tolerance_ms),
                ("--every", self.every != d.every && !every_applies),
                ("--from", self.from.is_some()),
                ("--to", self.to.is_some()),
            ],
            &format!("a recording (a ROS 2 bag or an EuRoC folder); '{}' is {what}", dir.display()),
        )
    }

    /// The library's options from the flags.
    pub fn options(&self) -> Result<RecordingOptions> {
        let topics = match &self.topics {
            Some(t) => match t.split(',').map(str::trim).collect::<Vec<_>>().as_slice() {
                [l, r] => Some([l.to_string(), r.to_string()]),
                _ => bail!("--topics: expected LEFT,RIGHT (two names), got '{t}'"),
            },
            None => None,
        };
        let o = RecordingOptions {
            topics,
            joint_topic: self.joint_topic.clone(),
            joints: self.joint.as_deref().map(parse_joints).transpose()?.unwrap_or_default(),
            pair_tolerance_s: self.pair_tolerance_ms * 1e-3,
            every: self.every,
            from_s: self.from,
            to_s: self.to,
        };
        o.validate()?;
        Ok(o)
    }
}

/// Read the recording at `path`; its notes (what was left out) go to stderr.
pub fn read(path: &Path, args: &RecordingArgs) -> Result<Recording> {
    let options = args.options()?;
    let spin = crate::progress::spinner(format!("reading {}", path.display()));
    let rec = recordings::read_recording(path, &options);
    spin.finish_and_clear();
    let rec = rec?;
    for n in &rec.notes {
        eprintln!("note: {n}");
    }
    eprintln!(
        "{} '{}': {} of {} pairs ({} / {})",
        rec.format.name(),
        path.display(),
        rec.views.len(),
        rec.pairs_found,
        rec.topics[0],
        rec.topics[1]
    );
    Ok(rec)
}

/// The still views of a recorded head run (one per stop of the head).
fn still(path: &Path, args: &RecordingArgs) -> Result<Vec<RecordedView>> {
    let views = still_views(read(path, args)?.views);
    eprintln!("{} still views (the head at rest)", views.len());
    Ok(views)
}

/// `align --images RECORDING`: the verge/tilt views of a recorded head run.
pub fn align_views(path: &Path, args: &RecordingArgs) -> Result<Vec<RecordedView>> {
    Ok(verge_tilt_views(still(path, args)?)?)
}

/// `replay RECORDING`: the recorded head run as a head.
pub fn playback_head(path: &Path, args: &RecordingArgs, tolerance_deg: f64) -> Result<PlaybackHead> {
    Ok(PlaybackHead::new(still(path, args)?, tolerance_deg)?)
}

/// `--lens-from`: `recording` (an EuRoC folder's own `cam0/sensor.yaml` and
/// `cam1/sensor.yaml`) or `LEFT.yaml,RIGHT.yaml` (Kalibr/EuRoC `sensor.yaml` files). A
/// file's `resolution` must be the images' size.
pub fn lens_from(
    spec: &str,
    input: &Path,
    args: &RecordingArgs,
    image_size: [u32; 2],
) -> Result<[LensModel; 2]> {
    Ok(euroc::read_sensor_yaml_pair(&lens_paths(spec, input, args)?, image_size)?)
}

/// The two `sensor.yaml` files a `--lens-from` names, each read once to check it (before
/// any image is read: a wrong flag fails at once).
pub fn lens_paths(spec: &str, input: &Path, args: &RecordingArgs) -> Result<[std::path::PathBuf; 2]> {
    let paths: [std::path::PathBuf; 2] = if spec.trim() == "recording" {
        if recordings::detect(input) != Some(RecordingFormat::Euroc) {
            bail!(
                "--lens-from recording: '{}' is not an EuRoC folder with cam0/sensor.yaml; give LEFT.yaml,RIGHT.yaml",
                input.display()
            );
        }
        euroc::sensor_yaml_paths(input, &args.options()?)
    } else {
        match spec.split(',').map(str::trim).collect::<Vec<_>>().as_slice() {
            [l, r] => [l.into(), r.into()],
            _ => bail!("--lens-from: expected LEFT.yaml,RIGHT.yaml or 'recording', got '{spec}'"),
        }
    };
    for p in &paths {
        euroc::read_sensor_yaml(p)?;
    }
    Ok(paths)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flags_become_options() {
        let a = RecordingArgs {
            topics: Some("/l, /r".into()),
            joint: Some("pan=head_pan, elevation=head_tilt".into()),
            pair_tolerance_ms: 2.0,
            ..RecordingArgs::default()
        };
        let o = a.options().unwrap();
        assert_eq!(o.topics, Some(["/l".to_string(), "/r".to_string()]));
        assert_eq!(
            o.joints,
            [(Joint::Pan, "head_pan".to_string()), (Joint::Elevation, "head_tilt".to_string())]
        );
        assert!((o.pair_tolerance_s - 0.002).abs() < 1e-15);
        assert_eq!(RecordingArgs::default().options().unwrap(), RecordingOptions::default());
        for (joint, why) in [("tilt=x", "unknown head joint 'tilt'"), ("pan", "not JOINT=NAME")] {
            let e = RecordingArgs { joint: Some(joint.into()), ..RecordingArgs::default() }
                .options()
                .unwrap_err();
            assert!(e.to_string().contains(why), "{e}");
        }
        let e =
            RecordingArgs { topics: Some("/a".into()), ..RecordingArgs::default() }.options().unwrap_err();
        assert!(e.to_string().contains("LEFT,RIGHT"), "{e}");
    }
}
