//! A recorded head run ([`super`] module docs, "A recorded head run"): the moments the
//! head stood still, where the verge/tilt views start, and a head that plays the still
//! views back to a procedure.
//!
//! Degrees of freedom: none. Units: encoder readings in degrees; [`STILL_DEG`] and the
//! playback tolerance are per joint. Pitfalls: two captures whose readings differ by
//! less than [`STILL_DEG`] with no motion between them in the recording are one still
//! view (a continuous stream cannot tell them apart); moves that small are below the
//! estimation's own [`MOVED_DEG`] and carry no rotation to measure anyway.

use std::path::PathBuf;

use headalign_platform::{
    Encoders, ImagingHead, Joint, PlatformError, StereoCapture, StereoHead, StereoImages,
};

use crate::session::RecordedView;
use headalign::AlignError;
use headalign::verge_tilt::MOVED_DEG;

/// Pairs whose readings stay within this of a run's first pair, per joint, belong to one
/// still view, degrees: half the estimation's [`MOVED_DEG`], so that two still views
/// differ by a rotation the estimation can see.
pub const STILL_DEG: f64 = MOVED_DEG / 2.0;

/// A run of fewer pairs than this is the head passing through, not standing still (three
/// frames: 0.1 s at 30 Hz).
pub const MIN_STILL_PAIRS: usize = 3;

fn largest_difference(a: &Encoders, b: &Encoders) -> f64 {
    Joint::ALL.iter().map(|&j| (a.get(j) - b.get(j)).abs()).fold(0.0, f64::max)
}

/// One view per still run of `views` (in time order): runs of at least
/// [`MIN_STILL_PAIRS`] pairs whose readings stay within [`STILL_DEG`] of the run's first
/// pair; the middle pair of the run stands for it.
pub fn still_views(views: Vec<RecordedView>) -> Vec<RecordedView> {
    let mut runs = Vec::new();
    let mut i = 0;
    while i < views.len() {
        let e0 = views[i].images.encoders;
        let mut j = i + 1;
        while j < views.len() && largest_difference(&views[j].images.encoders, &e0) <= STILL_DEG {
            j += 1;
        }
        if j - i >= MIN_STILL_PAIRS {
            runs.push(i + (j - i) / 2);
        }
        i = j;
    }
    views.into_iter().enumerate().filter(|(k, _)| runs.contains(k)).map(|(_, v)| v).collect()
}

/// Does `b` rotate `joint` alone relative to `a` (by more than [`MOVED_DEG`], the other
/// joints within it)?
fn rotates_alone(a: &Encoders, b: &Encoders, joint: Joint) -> bool {
    Joint::ALL.iter().all(|&j| {
        let d = (b.get(j) - a.get(j)).abs();
        if j == joint { d > MOVED_DEG } else { d <= MOVED_DEG }
    })
}

/// The verge/tilt views of a head run's still views: from the first still view that a
/// later one rotates about pan alone and another about elevation alone (the procedure's
/// initial view; the verging before it changed the right vergence, so no earlier view
/// has both). The views after it that moved a vergence are what the estimation uses to
/// measure the vergence axes; later checks come after those and are not used.
pub fn verge_tilt_views(still: Vec<RecordedView>) -> Result<Vec<RecordedView>, AlignError> {
    let enc = |v: &RecordedView| v.images.encoders;
    let start = (0..still.len()).find(|&i| {
        let later = &still[i + 1..];
        let e0 = enc(&still[i]);
        later.iter().any(|v| rotates_alone(&e0, &enc(v), Joint::Pan))
            && later.iter().any(|v| rotates_alone(&e0, &enc(v), Joint::Elevation))
    });
    match start {
        Some(i) => Ok(still.into_iter().skip(i).collect()),
        None => Err(AlignError::Recording(format!(
            "no still view of the recording is followed by a rotation of pan alone and one of elevation alone ({} still views of at least {MIN_STILL_PAIRS} pairs within {STILL_DEG} deg): record the head's verge/tilt procedure with its joint states",
            still.len()
        ))),
    }
}

/// A recorded head run played back as a head. It stands at a still view (at first the
/// first one). A move within `tolerance_deg` of that view's readings (per joint) keeps it
/// there; any other move leaves it, and the next capture goes to the first later still
/// view within `tolerance_deg` of the last target: captures take the still views in
/// order, a repeated capture without leaving takes the same view again, and a move
/// through a place where the recording never stopped (a return to the start between two
/// rotations) needs no still view of its own. Reads return the readings of the view it
/// stands at, or after leaving, of the view the target will find (the target itself if
/// none). A capture the recording does not hold is an error naming the target and where
/// the playback stood.
#[derive(Debug)]
pub struct PlaybackHead {
    views: Vec<RecordedView>,
    at: usize,
    target: Option<Encoders>,
    tolerance_deg: f64,
    source: PathBuf,
}

impl PlaybackHead {
    /// Play `views` (at least one; the still views of a recording) with a move tolerance
    /// per joint, degrees (positive).
    pub fn new(views: Vec<RecordedView>, tolerance_deg: f64) -> Result<Self, AlignError> {
        if !(tolerance_deg.is_finite() && tolerance_deg > 0.0) {
            return Err(AlignError::InvalidOption(format!(
                "move tolerance must be a positive number of degrees, got {tolerance_deg}"
            )));
        }
        let Some(first) = views.first() else {
            return Err(AlignError::Recording("the recording holds no still view to play back".into()));
        };
        let source = first.folder.clone();
        Ok(Self { views, at: 0, target: None, tolerance_deg, source })
    }

    /// Index of the still view the playback stands at (the last one captured).
    pub fn position(&self) -> usize {
        self.at
    }

    /// The still views played.
    pub fn views(&self) -> &[RecordedView] {
        &self.views
    }

    /// The first still view after the current one within the tolerance of `target`.
    fn find(&self, target: &Encoders) -> Option<usize> {
        (self.at + 1..self.views.len())
            .find(|&k| largest_difference(&self.views[k].images.encoders, target) <= self.tolerance_deg)
    }
}

impl StereoHead for PlaybackHead {
    fn image_size(&self) -> [u32; 2] {
        self.views[self.at].images.image_size()
    }

    fn read_encoders(&mut self) -> Result<Encoders, PlatformError> {
        Ok(match self.target {
            None => self.views[self.at].images.encoders,
            Some(t) => self.find(&t).map_or(t, |k| self.views[k].images.encoders),
        })
    }

    fn move_to(&mut self, target: &Encoders) -> Result<(), PlatformError> {
        let here = largest_difference(&self.views[self.at].images.encoders, target) <= self.tolerance_deg;
        if !(here && self.target.is_none()) {
            self.target = Some(*target);
        }
        Ok(())
    }

    fn capture(&mut self) -> Result<StereoCapture, PlatformError> {
        Err(PlatformError::Device(format!(
            "'{}' is a recording of images: play it back in image mode",
            self.source.display()
        )))
    }
}

impl ImagingHead for PlaybackHead {
    fn capture_images(&mut self) -> Result<StereoImages, PlatformError> {
        if let Some(t) = self.target.take() {
            let Some(k) = self.find(&t) else {
                return Err(PlatformError::Device(format!(
                    "playback of '{}': no still view after {} is within {} deg of the target {}: the recorded run did not capture there (a different procedure, rotation or seed?)",
                    self.source.display(),
                    self.views[self.at].name,
                    self.tolerance_deg,
                    serde_json::to_string(&t).unwrap_or_default()
                )));
            };
            self.at = k;
        }
        Ok(self.views[self.at].images.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use headalign_platform::GrayImage;

    fn view(name: &str, pan: f64, elevation: f64, verge_right: f64) -> RecordedView {
        let e = Encoders { pan, elevation, verge_left: 0.0, verge_right };
        let img = GrayImage::filled(4, 4, 9);
        RecordedView {
            name: name.into(),
            stage: None,
            folder: PathBuf::from("bag"),
            images: StereoImages::new(e, img.clone(), img).unwrap(),
        }
    }

    /// A head run: verging (the right vergence steps), the initial view, elevation, pan,
    /// verge, with frames in motion between them.
    #[test]
    fn still_views_and_the_start_of_the_verge_tilt_views() {
        let mut stream = Vec::new();
        let mut still = |n: &str, p, e, v, count: usize| {
            for k in 0..count {
                // Encoder jitter well below STILL_DEG.
                stream.push(view(&format!("{n}{k}"), p + 0.001 * k as f64, e, v));
            }
        };
        still("v", 0.0, 0.0, 0.0, 4);
        still("m", 0.0, 0.0, 0.5, 1); // passing through
        still("w", 0.0, 0.0, 1.0, 3);
        still("i", 0.0, 0.0, 1.2, 5);
        still("m", 0.0, 1.5, 1.2, 2); // a short stop is motion too
        still("e", 0.0, 3.0, 1.2, 4);
        still("p", 3.0, 0.0, 1.2, 4);
        still("g", 0.0, 0.0, 4.2, 4);
        let s = still_views(stream);
        let names: Vec<&str> = s.iter().map(|v| v.name.as_str()).collect();
        assert_eq!(names, ["v2", "w1", "i2", "e2", "p2", "g2"]);
        let vt = verge_tilt_views(s.clone()).unwrap();
        assert_eq!(vt[0].name, "i2");
        assert_eq!(vt.len(), 4);
        let e = verge_tilt_views(s[..3].to_vec()).unwrap_err().to_string();
        assert!(e.contains("no still view") && e.contains("3 still views"), "{e}");
        // Playback: captures take the still views in order; a move that stays keeps the
        // view, a return to the start between two rotations needs no view of its own, a
        // capture the run never made is named.
        let mut head = PlaybackHead::new(s[2..].to_vec(), 0.05).unwrap();
        let at = |pan: f64, elevation: f64| Encoders { pan, elevation, verge_left: 0.0, verge_right: 1.2 };
        assert_eq!(head.capture_images().unwrap().encoders.verge_right, 1.2);
        head.move_to(&at(0.002, 0.0)).unwrap();
        assert_eq!(head.capture_images().unwrap(), head.views()[0].images);
        head.move_to(&at(0.0, 3.0)).unwrap();
        assert_eq!(head.read_encoders().unwrap().elevation, 3.0);
        assert_eq!((head.capture_images().unwrap().encoders.elevation, head.position()), (3.0, 1));
        head.move_to(&at(0.0, 0.0)).unwrap();
        assert_eq!(head.read_encoders().unwrap(), at(0.0, 0.0));
        head.move_to(&at(3.0, 0.0)).unwrap();
        assert_eq!(head.capture_images().unwrap().encoders.pan, 3.002);
        assert_eq!(head.position(), 2);
        // Back to the elevation view: it lies behind, so the capture is not found.
        head.move_to(&at(0.0, 3.0)).unwrap();
        let e = head.capture_images().unwrap_err().to_string();
        assert!(e.contains("did not capture there") && e.contains("after p2"), "{e}");
    }
}
