//! Where a calibration spends its time: seconds per stage ([`Stage`]), recorded by the
//! library itself ([`time`]) and read as the difference of two snapshots
//! ([`StageTimes::now`], [`StageTimes::since`]); [`crate::calibrate::calibrate_views`]
//! reports its own in [`crate::calibrate::ViewsCalibration::timing`].
//!
//! What is counted: each call of [`time`] adds its elapsed wall time to its stage,
//! exclusive of the stages timed inside it on the same thread (a 3D-homography fit inside
//! a lens-grid score counts as "3D homographies", the rest of the score as "lens
//! choice"). Work that rayon runs on another thread counts where that thread's own
//! [`time`] calls put it: the closures of the calibration's parallel loops over lenses,
//! starts and views are timed in their stage; the finer ones (the two images of a view's
//! corner detection, the views' triangulation, the bootstrap's replicates inside
//! `headalign-geometry`) count only on the thread that started them. The sum over stages
//! is therefore thread-seconds: with one thread it is the wall time of the timed stages,
//! with `n` threads up to `n` times it (a thread waiting in a parallel loop keeps counting
//! its own stage), less what the finer loops ran elsewhere.
//!
//! Units: seconds (from nanosecond counters), and calls.
//!
//! Pitfalls: the counters are process-wide (atomics), so two calibrations running at the
//! same time in one process (tests) see each other's seconds in their differences; the
//! benchmark and the command-line tool run one at a time. Timing costs two clock reads per
//! call: stages are coarse (a RANSAC, an adjustment), never per point.

use std::cell::RefCell;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use serde::Serialize;

/// The stages of a calibration (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Stage {
    /// Reading images from disk (the caller's: the library reads no file).
    Reading,
    /// Corners, stereo matching, tracking across views, patch refinement.
    FrontEnd,
    /// The stereo fundamental matrix (RANSAC, refinement), the projective frame and the
    /// triangulation of each view's matches.
    StereoF,
    /// The 3D homographies from the reference view (RANSAC, polish, re-selection).
    Homographies,
    /// The point set, the linear self-calibration and the rigid start.
    Starts,
    /// The rig bundle adjustments from the starts and over every point.
    Adjustment,
    /// Choosing a lens: the lens grid's scoring and the candidates' refits.
    LensChoice,
    /// The sigmas: the bootstrap over tracks and the checks against the residuals and the
    /// images' noise that widen the covariance.
    Covariance,
}

impl Stage {
    /// Every stage, in the order of a calibration.
    pub const ALL: [Stage; 8] = [
        Stage::Reading,
        Stage::FrontEnd,
        Stage::StereoF,
        Stage::Homographies,
        Stage::Starts,
        Stage::Adjustment,
        Stage::LensChoice,
        Stage::Covariance,
    ];

    /// The stage's name in tables.
    pub fn label(self) -> &'static str {
        match self {
            Stage::Reading => "reading",
            Stage::FrontEnd => "front end",
            Stage::StereoF => "stereo F (RANSAC, triangulation)",
            Stage::Homographies => "3D homographies",
            Stage::Starts => "starts (linear, rigid)",
            Stage::Adjustment => "bundle adjustments",
            Stage::LensChoice => "lens choice",
            Stage::Covariance => "covariance (bootstrap, checks)",
        }
    }

    fn index(self) -> usize {
        self as usize
    }
}

const STAGES: usize = Stage::ALL.len();

static NANOS: [AtomicU64; STAGES] = [const { AtomicU64::new(0) }; STAGES];
static CALLS: [AtomicU64; STAGES] = [const { AtomicU64::new(0) }; STAGES];

thread_local! {
    /// The stages open on this thread, innermost last, each with the instant its
    /// exclusive time last resumed.
    static OPEN: RefCell<Vec<(Stage, Instant)>> = const { RefCell::new(Vec::new()) };
}

fn add(stage: Stage, from: Instant, to: Instant) {
    let nanos = u64::try_from(to.saturating_duration_since(from).as_nanos()).unwrap_or(u64::MAX);
    NANOS[stage.index()].fetch_add(nanos, Ordering::Relaxed);
}

/// Closes the innermost open stage when dropped (also on unwinding).
struct Open;

impl Drop for Open {
    fn drop(&mut self) {
        let end = Instant::now();
        OPEN.with(|open| {
            let mut open = open.borrow_mut();
            if let Some((stage, start)) = open.pop() {
                add(stage, start, end);
            }
            if let Some(outer) = open.last_mut() {
                outer.1 = end;
            }
        });
    }
}

/// Run `f` as a call of `stage` (module docs: its time exclusive of the stages timed
/// inside it on this thread).
pub fn time<T>(stage: Stage, f: impl FnOnce() -> T) -> T {
    let now = Instant::now();
    OPEN.with(|open| {
        let mut open = open.borrow_mut();
        if let Some(&(outer, start)) = open.last() {
            add(outer, start, now);
        }
        open.push((stage, now));
    });
    CALLS[stage.index()].fetch_add(1, Ordering::Relaxed);
    let _open = Open;
    f()
}

/// Seconds and calls per stage ([`Stage::ALL`] order): a snapshot of the process's
/// counters, or the difference of two.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTimes {
    /// Seconds per stage.
    pub seconds: [f64; STAGES],
    /// Calls per stage.
    pub calls: [u64; STAGES],
}

impl StageTimes {
    /// The counters so far.
    pub fn now() -> Self {
        let mut t = Self::default();
        for i in 0..STAGES {
            t.seconds[i] = NANOS[i].load(Ordering::Relaxed) as f64 * 1e-9;
            t.calls[i] = CALLS[i].load(Ordering::Relaxed);
        }
        t
    }

    /// The seconds and calls since the snapshot `before`.
    pub fn since(before: &StageTimes) -> Self {
        let now = Self::now();
        let mut t = Self::default();
        for i in 0..STAGES {
            t.seconds[i] = now.seconds[i] - before.seconds[i];
            t.calls[i] = now.calls[i].saturating_sub(before.calls[i]);
        }
        t
    }

    /// Seconds of `stage`.
    pub fn seconds_of(&self, stage: Stage) -> f64 {
        self.seconds[stage.index()]
    }

    /// Calls of `stage`.
    pub fn calls_of(&self, stage: Stage) -> u64 {
        self.calls[stage.index()]
    }

    /// The seconds of every stage together (thread-seconds, module docs).
    pub fn total(&self) -> f64 {
        self.seconds.iter().sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A nested stage's time is its own, not its parent's: the inner sleep lands in
    /// the inner stage. Other tests may time stages concurrently, so only lower bounds are
    /// checked (a sleep lasts at least its duration).
    #[test]
    fn nested_stages_count_exclusively() {
        let before = StageTimes::now();
        time(Stage::Reading, || {
            std::thread::sleep(std::time::Duration::from_millis(20));
            time(Stage::Covariance, || std::thread::sleep(std::time::Duration::from_millis(200)));
        });
        let t = StageTimes::since(&before);
        assert!(t.seconds_of(Stage::Reading) >= 0.02, "{t:?}");
        assert!(t.seconds_of(Stage::Covariance) >= 0.2, "{t:?}");
        assert!(t.calls_of(Stage::Reading) >= 1 && t.calls_of(Stage::Covariance) >= 1);
        // The parent was paused while the child ran: with no other test timing
        // Stage::Reading (the library never does), its time is its own 20 ms plus the
        // sleep's overshoot, far below the 220 ms it would be if the child counted too.
        assert!(t.seconds_of(Stage::Reading) < 0.2, "{t:?}");
    }
}
