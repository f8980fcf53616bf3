//! The view graph of a sequence ([`super::sequence`]): which views are keyframes, which
//! keyframes form connected segments, and the spanning tree along which each segment's
//! motions are chained.
//!
//! What it computes, from the track ids alone (no geometry):
//! - per view its *stereo tracks*, the ids seen by both cameras (what a 3D homography
//!   needs: a point reconstructed in both views);
//! - **keyframes**, walking the views in order: the first view, then a view whenever,
//!   since the last keyframe, the stereo tracks it still shares fall below
//!   [`SequenceOptions::keyframe_overlap`] of the keyframe's (overlap), or the median image
//!   motion of the shared tracks in the left camera reaches
//!   [`SequenceOptions::keyframe_flow_px`] (motion: rotation and parallax together, in
//!   pixels). A view that shares fewer than [`SequenceOptions::min_link_tracks`] with
//!   the last keyframe while the view before it still shares them with it makes that view
//!   the keyframe instead (the chain keeps its link); with neither, the chain breaks and
//!   the view starts a new run. The last view of a run becomes a keyframe too if it moved
//!   by [`END_FLOW_FRACTION`] of the flow threshold, so that a short run keeps its motion;
//! - the **graph**: keyframes are nodes, an edge joins two keyframes that share at least
//!   `min_link_tracks` stereo tracks (counted through an index from track to keyframes:
//!   linear in the observations for tracks that live a bounded number of views);
//! - **segments**: its connected components (union-find), in the order of their first
//!   view; a component of one keyframe has no motion and is left out;
//! - per segment a **spanning tree** rooted at its first keyframe (the segment's gauge),
//!   grown greedily by the edge with the most shared tracks (Prim's algorithm on the
//!   shared counts), so that each keyframe's motion is chained from the gauge through its
//!   best-linked neighbours.
//!
//! Units: pixels for the flow, fractions for the overlap, counts for links. Pitfalls:
//! with the front end's chained tracking ([`crate::tracking::TrackingMode::Previous`]) a
//! track id never returns once lost, so runs are the segments unless ids are global (an
//! observation file, a loop closure); the flow of a pure translation grows with the
//! nearness of the scene, that of a rotation with the focal length: the threshold mixes
//! both on purpose (both make the views differ).

use std::collections::HashMap;

use nalgebra::Point2;
use serde::Serialize;

use crate::error::AlignError;
use crate::observations::View;

/// A run's last view becomes a keyframe when its flow since the last keyframe reaches
/// this fraction of [`SequenceOptions::keyframe_flow_px`] (module docs): less motion adds
/// nothing to the calibration.
pub const END_FLOW_FRACTION: f64 = 0.25;

/// Options of the sequence route ([`super::calibrate_sequence`]).
#[derive(Debug, Clone)]
pub struct SequenceOptions {
    /// A view becomes a keyframe when it shares fewer than this fraction of the last
    /// keyframe's stereo tracks (default 0.35). Tracks chained through consecutive views
    /// wear out (every link loses some), so this fraction is reached after a few views
    /// even with little motion; consecutive keyframes then still share hundreds of tracks
    /// (270-570 on the rendered sequence of `benches/sequence.rs`), plenty for the 3D
    /// homography between them.
    pub keyframe_overlap: f64,
    /// A view becomes a keyframe when the median image motion of the tracks it shares
    /// with the last keyframe reaches this, pixels, left camera (default 60: 8 % of a
    /// 752-pixel image, 7.5 deg of rotation at a focal length of 460 px). Smaller motions
    /// make the 3D homography between keyframes mostly noise and cost adjustment time:
    /// on the 50-view rendered sequence 0.6 / 40 px gave 27 keyframes and 0.35 / 60 px
    /// 14, for the same focal length to 0.01 % and 11 % less CPU time over the whole
    /// command (13.2 -> 11.8 s).
    pub keyframe_flow_px: f64,
    /// Fewest stereo tracks two views must share to be linked (default 30: the 3D
    /// homography needs 12 inliers, and a link of a few dozen tracks is still a reliable
    /// one).
    pub min_link_tracks: usize,
    /// Most motions the linear self-calibration takes, those rotating most (default 8;
    /// every motion enters the adjustment).
    pub linear_motions: usize,
}

impl Default for SequenceOptions {
    fn default() -> Self {
        Self { keyframe_overlap: 0.35, keyframe_flow_px: 60.0, min_link_tracks: 30, linear_motions: 8 }
    }
}

impl SequenceOptions {
    /// Check every option.
    pub fn validate(&self) -> Result<(), AlignError> {
        if !(self.keyframe_overlap > 0.0 && self.keyframe_overlap <= 1.0) {
            return Err(AlignError::InvalidOption("keyframe_overlap must be in (0, 1]".into()));
        }
        if !(self.keyframe_flow_px.is_finite() && self.keyframe_flow_px > 0.0) {
            return Err(AlignError::InvalidOption("keyframe_flow_px must be positive".into()));
        }
        if self.min_link_tracks < 5 {
            return Err(AlignError::InvalidOption("min_link_tracks must be at least 5".into()));
        }
        if self.linear_motions == 0 {
            return Err(AlignError::InvalidOption("linear_motions must be at least 1".into()));
        }
        Ok(())
    }
}

/// Per view: its stereo tracks (sorted) and its left pixels by track (sorted by track).
pub(super) struct ViewTracks {
    stereo: Vec<u64>,
    left: Vec<(u64, Point2<f64>)>,
}

impl ViewTracks {
    pub(super) fn of(view: &View) -> Self {
        let mut left: Vec<(u64, Point2<f64>)> =
            view.capture.left.iter().map(|o| (o.track, o.pixel)).collect();
        left.sort_by_key(|x| x.0);
        left.dedup_by_key(|x| x.0);
        let mut right: Vec<u64> = view.capture.right.iter().map(|o| o.track).collect();
        right.sort_unstable();
        let stereo = left.iter().map(|x| x.0).filter(|t| right.binary_search(t).is_ok()).collect();
        Self { stereo, left }
    }

    /// Stereo tracks seen in both views.
    pub(super) fn shared(&self, other: &ViewTracks) -> usize {
        let (mut i, mut j, mut n) = (0, 0, 0);
        while i < self.stereo.len() && j < other.stereo.len() {
            match self.stereo[i].cmp(&other.stereo[j]) {
                std::cmp::Ordering::Less => i += 1,
                std::cmp::Ordering::Greater => j += 1,
                std::cmp::Ordering::Equal => {
                    n += 1;
                    i += 1;
                    j += 1;
                }
            }
        }
        n
    }

    /// Median left-image displacement (pixels) of the stereo tracks both views share;
    /// 0 if none.
    fn flow(&self, other: &ViewTracks) -> f64 {
        let pixel =
            |v: &ViewTracks, t: u64| v.left.binary_search_by_key(&t, |x| x.0).ok().map(|i| v.left[i].1);
        let mut d: Vec<f64> = self
            .stereo
            .iter()
            .filter(|t| other.stereo.binary_search(t).is_ok())
            .filter_map(|&t| Some((pixel(self, t)? - pixel(other, t)?).norm()))
            .collect();
        if d.is_empty() {
            return 0.0;
        }
        let mid = d.len() / 2;
        *d.select_nth_unstable_by(mid, f64::total_cmp).1
    }
}

/// The keyframes of views `0..n` (indices, ascending), module docs.
pub(super) fn keyframes(tracks: &[ViewTracks], o: &SequenceOptions) -> Vec<usize> {
    if tracks.is_empty() {
        return Vec::new();
    }
    let mut keys = vec![0];
    let mut last = 0;
    let end_flow = END_FLOW_FRACTION * o.keyframe_flow_px;
    let mut j = 1;
    while j < tracks.len() {
        let shared = tracks[last].shared(&tracks[j]);
        if shared < o.min_link_tracks {
            let before = j - 1;
            if before > last && tracks[before].shared(&tracks[j]) >= o.min_link_tracks {
                // The view before still links: it keeps the chain (j is looked at again).
                keys.push(before);
                last = before;
                continue;
            }
            // A break: the run ends at `before`, keeping its last motion; j starts afresh.
            if before > last && tracks[last].flow(&tracks[before]) >= end_flow {
                keys.push(before);
            }
            keys.push(j);
            last = j;
            j += 1;
            continue;
        }
        let overlap = shared as f64 / tracks[last].stereo.len().max(1) as f64;
        if overlap < o.keyframe_overlap || tracks[last].flow(&tracks[j]) >= o.keyframe_flow_px {
            keys.push(j);
            last = j;
        }
        j += 1;
    }
    let end = tracks.len() - 1;
    if end > last && tracks[last].flow(&tracks[end]) >= end_flow {
        keys.push(end);
    }
    keys
}

/// Stereo tracks shared by each pair of `keys` (indices into `tracks`) that share any,
/// as `(a, b) -> count` with `a < b` positions in `keys`.
pub(super) fn shared_counts(tracks: &[ViewTracks], keys: &[usize]) -> HashMap<(usize, usize), usize> {
    let mut by_track: HashMap<u64, Vec<usize>> = HashMap::new();
    for (pos, &k) in keys.iter().enumerate() {
        for &t in &tracks[k].stereo {
            by_track.entry(t).or_default().push(pos);
        }
    }
    let mut counts: HashMap<(usize, usize), usize> = HashMap::new();
    for list in by_track.values() {
        for (i, &a) in list.iter().enumerate() {
            for &b in &list[i + 1..] {
                *counts.entry((a.min(b), a.max(b))).or_default() += 1;
            }
        }
    }
    counts
}

/// One segment: positions in `keys` in spanning-tree order (the root, the gauge, first),
/// each with its parent position and the stereo tracks they share (`None` for the root).
#[derive(Debug, Clone)]
pub(super) struct Segment {
    pub(super) order: Vec<(usize, Option<(usize, usize)>)>,
}

/// The segments of the keyframes (module docs): connected components of the edges with at
/// least `min_link` shared tracks, each as its spanning tree from its first keyframe,
/// ordered by that keyframe; and the positions of the keyframes left alone.
pub(super) fn segments(
    n_keys: usize,
    counts: &HashMap<(usize, usize), usize>,
    min_link: usize,
) -> (Vec<Segment>, Vec<usize>) {
    let mut adjacency: Vec<Vec<(usize, usize)>> = vec![Vec::new(); n_keys];
    let mut edges: Vec<(&(usize, usize), &usize)> = counts.iter().filter(|(_, c)| **c >= min_link).collect();
    edges.sort_unstable();
    for (&(a, b), &c) in edges {
        adjacency[a].push((b, c));
        adjacency[b].push((a, c));
    }
    let mut placed = vec![false; n_keys];
    let (mut out, mut alone) = (Vec::new(), Vec::new());
    for root in 0..n_keys {
        if placed[root] {
            continue;
        }
        placed[root] = true;
        // Prim: the unplaced neighbour with the most shared tracks to any placed keyframe.
        let mut best: HashMap<usize, (usize, usize)> = HashMap::new();
        let mut order = vec![(root, None)];
        let mut frontier = root;
        loop {
            for &(n, c) in &adjacency[frontier] {
                if !placed[n] && best.get(&n).is_none_or(|&(_, b)| c > b) {
                    best.insert(n, (frontier, c));
                }
            }
            let Some((&next, &(parent, c))) = best
                .iter()
                .max_by(|a, b| (a.1.1, std::cmp::Reverse(*a.0)).cmp(&(b.1.1, std::cmp::Reverse(*b.0))))
            else {
                break;
            };
            best.remove(&next);
            placed[next] = true;
            order.push((next, Some((parent, c))));
            frontier = next;
        }
        if order.len() < 2 {
            alone.push(root);
        } else {
            out.push(Segment { order });
        }
    }
    (out, alone)
}

/// What the report says of a segment ([`super::SequenceReport`]).
#[derive(Debug, Clone, Serialize)]
pub struct SegmentReport {
    /// The segment's gauge: its first keyframe, at the identity; its motions are relative
    /// to it.
    pub gauge: String,
    /// Its keyframes in the adjustment's order (the gauge first).
    pub keyframes: Vec<String>,
    /// Each keyframe after the gauge: `[keyframe, parent, shared stereo tracks]`, the
    /// spanning tree its motion was chained along.
    pub links: Vec<(String, String, usize)>,
    /// Views of the segment's runs that are not keyframes (between keyframes: little
    /// motion and much overlap since the last one).
    pub between_keyframes: usize,
}

#[cfg(test)]
mod tests {
    use super::*;
    use headalign_platform::{Encoders, StereoCapture, TrackObservation};

    /// A view seeing tracks `ids`, all at pixel `(x, 100)` in both cameras.
    fn view(ids: impl Iterator<Item = u64>, x: f64) -> View {
        let obs: Vec<TrackObservation> =
            ids.map(|track| TrackObservation { track, pixel: Point2::new(x, 100.0) }).collect();
        View {
            name: String::new(),
            capture: StereoCapture {
                encoders: Encoders::default(),
                image_size: [752, 480],
                left: obs.clone(),
                right: obs,
            },
        }
    }

    /// A chain of 100-track windows sliding by 10 tracks a view, the image moving 5 px a
    /// view, thresholds 0.6 and 40 px: overlap falls below 0.6 after 5 views (flow 25 px), so every fifth view is
    /// a keyframe, and a run's last view is one when it moved 10 px (a quarter of 40)
    /// since the last; a gap in the ids breaks the chain into two segments (their
    /// keyframes also link past a neighbour when they share 30 tracks: the tree takes
    /// the better link); a view sharing nothing is left alone.
    #[test]
    fn keyframes_follow_overlap_and_segments_follow_links() {
        let mut views: Vec<View> = (0..13).map(|i| view(10 * i..10 * i + 100, 5.0 * i as f64)).collect();
        views.extend((0..8).map(|i| view(5000 + 10 * i..5100 + 10 * i, 5.0 * i as f64)));
        views.push(view(9000..9100, 0.0));
        let tracks: Vec<ViewTracks> = views.iter().map(ViewTracks::of).collect();
        let o =
            SequenceOptions { keyframe_overlap: 0.6, keyframe_flow_px: 40.0, ..SequenceOptions::default() };
        let keys = keyframes(&tracks, &o);
        assert_eq!(keys, vec![0, 5, 10, 12, 13, 18, 20, 21], "{keys:?}");
        let counts = shared_counts(&tracks, &keys);
        assert_eq!(
            (counts.get(&(0, 1)), counts.get(&(1, 3)), counts.get(&(0, 2))),
            (Some(&50), Some(&30), None)
        );
        let (segs, alone) = segments(keys.len(), &counts, o.min_link_tracks);
        let order = |s: &Segment| s.order.iter().map(|x| keys[x.0]).collect::<Vec<_>>();
        assert_eq!(segs.len(), 2);
        assert_eq!(order(&segs[0]), vec![0, 5, 10, 12]);
        assert_eq!(order(&segs[1]), vec![13, 18, 20]);
        assert_eq!(segs[0].order[1].1, Some((0, 50)));
        assert_eq!(segs[0].order[3].1, Some((2, 80)));
        assert_eq!(alone, vec![7]);
        // Flow alone: the same tracks moving 15 px a view reach 40 px at the third view.
        let still: Vec<View> = (0..7).map(|i| view(0..100, 15.0 * i as f64)).collect();
        let tracks: Vec<ViewTracks> = still.iter().map(ViewTracks::of).collect();
        assert_eq!(keyframes(&tracks, &o), vec![0, 3, 6]);
        assert!(SequenceOptions { keyframe_overlap: 0.0, ..o.clone() }.validate().is_err());
        assert!(SequenceOptions { min_link_tracks: 2, ..o }.validate().is_err());
    }
}
