//! Left-right matches of one stereo capture, shared by every route that pools them
//! (the verge/tilt route's stereo geometry, the free-motion calibration, the robot's rig
//! views, the facing-plane detector), and the root mean square used to report residuals.
//!
//! No degrees of freedom: a join of the left and right track observations on their track
//! id. Units: pixels, as observed. Pitfall: a track seen twice in one image keeps its
//! last pixel (the trackers never emit that).

use std::collections::HashMap;

use headalign_platform::StereoCapture;
use nalgebra::Point2;

/// A stereo match: track id, left pixel, right pixel.
pub(crate) type StereoMatch = (u64, Point2<f64>, Point2<f64>);

/// Pixel of each track in one image's observations.
fn to_map(obs: &[headalign_platform::TrackObservation]) -> HashMap<u64, Point2<f64>> {
    obs.iter().map(|o| (o.track, o.pixel)).collect()
}

/// Stereo matches (track, left, right) of a capture, sorted by track id.
pub(crate) fn stereo_matches(c: &StereoCapture) -> Vec<StereoMatch> {
    let right = to_map(&c.right);
    let mut m: Vec<_> =
        c.left.iter().filter_map(|o| right.get(&o.track).map(|r| (o.track, o.pixel, *r))).collect();
    m.sort_by_key(|x| x.0);
    m
}

/// Root mean square of `values` (0 when there are none).
pub(crate) fn rms(values: impl Iterator<Item = f64>) -> f64 {
    let (mut s, mut n) = (0.0, 0usize);
    for v in values {
        s += v * v;
        n += 1;
    }
    if n == 0 { 0.0 } else { (s / n as f64).sqrt() }
}
