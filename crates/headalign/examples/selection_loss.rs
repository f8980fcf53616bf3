//! Diagnostic (not a test): how much information the estimate's inlier selection loses
//! (`docs/efficiency.md`, nineteenth session). For each seed (fig5's protocol: 3 deg
//! rotations, 200 points, 10 % outliers, encoder readings with 0.01 deg of noise, head
//! position `(seed - 1) mod 3` as in `experiment fig5-verge-tilt`), the trial's captured
//! observations in the rig views are split into true inliers (within 5 noise sigmas of the
//! simulator's exact pixel) and outliers; it prints the true inliers the final adjustment
//! kept and left out, the outliers it kept, and three Cramer-Rao bounds of each focal
//! length, all at the truth (the noise-free run's state, the experiments' bound run: no
//! lone-observation gate) with the trial's noise: over every true inlier of the points the
//! noise-free run holds (`all`), over the true inliers the estimate kept (`kept`), and
//! `all` with the image border modelled (`window`, `BundleOptions::measurement_window`).
//! Last the RMS error over each RMS bound.
//! Pitfall: a point the noise-free run holds but did not adjust keeps the position it was
//! given, which may be wrong (a wrong stereo match); its exact pixels then claim
//! information at a wrong depth. Before `estimate::retriangulate_points_by_support` that
//! made `all` up to a third too small on some seeds.
//! `LIST=1` prints each seed's bounds beside the noise-free run's own (the experiments');
//! `LOST=1` every track left out entirely, with its true inliers per camera; `LOSTB=1`
//! the left-out true inliers of the points the noise-free run holds, with its count and
//! distance; `TRACK=ID` every capture of one track in the noise-free run; `MONO=1` the
//! bound with the tracks the noise-free run has no point for added at their exact
//! position (N-view DLT with the true cameras).
//! `cargo run --release -p headalign --example selection_loss -- FIRST_SEED SEEDS NOISE`
use std::collections::HashMap;

use headalign::procedure::VergeTiltRun;
use headalign_geometry::bundle::{BundleObservation, RobustLoss, Side, bundle_adjust};
use headalign_platform::{Encoders, StereoHead};
use headalign_sim::{Scenario, SimulatedHead};

mod common;

/// One track left out entirely (`LOST=1`): its true inliers per camera, and the views in
/// which the left and the right camera see it.
type LostTrack = ([usize; 2], std::collections::BTreeSet<usize>, std::collections::BTreeSet<usize>);

const NAMES: [&str; 4] = ["left.fx", "left.fy", "right.fx", "right.fy"];

struct Row {
    inliers: usize,
    kept_inliers: usize,
    kept_outliers: usize,
    /// Left-out true inliers whose point is not in the adjustment at all.
    lost_with_point: usize,
    err: [f64; 4],
    bound_all: [f64; 4],
    bound_kept: [f64; 4],
    bound_window: [f64; 4],
}

fn positions() -> [Encoders; 3] {
    [
        Encoders::default(),
        Encoders { pan: 4.0, elevation: 4.0, verge_left: 2.0, verge_right: -2.0 },
        Encoders { pan: -4.0, elevation: -4.0, verge_left: -2.0, verge_right: 2.0 },
    ]
}

fn trial(seed: u64, noise: f64) -> Option<Row> {
    let initial = positions()[((seed + 2) % 3) as usize];
    let sc = Scenario { seed, noise_px: noise, encoder_noise_deg: 0.01, ..Scenario::default() };
    let mut head = SimulatedHead::new(sc.clone()).ok()?;
    head.move_to(&initial).ok()?;
    let mut run = VergeTiltRun::default();
    let opts = common::trial_options(&sc, seed);
    let out = run.run(&mut head, &opts).ok()?;
    let clean_sc = Scenario { noise_px: 1e-300, encoder_noise_deg: 0.0, ..sc.clone() };
    // The noise-free run as the experiments' bound runs it: no lone-observation gate.
    let (clean_head, clean_run, clean) = {
        let mut h = SimulatedHead::new(clean_sc.clone()).ok()?;
        h.move_to(&initial).ok()?;
        let mut o = common::trial_options(&clean_sc, seed);
        o.estimation.lone_depth_gate = None;
        let mut r = VergeTiltRun::default();
        let out = r.run(&mut h, &o).ok()?;
        (h, r, out)
    };
    let c = &out.calibration;
    if !c.report.dropped_views.is_empty() || !clean.calibration.report.dropped_views.is_empty() {
        return None;
    }
    let clean_index: HashMap<u64, usize> =
        clean.calibration.point_tracks.iter().enumerate().map(|(i, t)| (*t, i)).collect();
    let kept: HashMap<(usize, bool, u64), ()> = c
        .observations
        .iter()
        .map(|o| ((o.view, o.side == Side::Right, c.point_tracks[o.point]), ()))
        .collect();
    let (mut all, mut kept_obs, mut kept_outliers, mut lost_with_point) = (Vec::new(), Vec::new(), 0, 0);
    let adjusted_tracks: std::collections::HashSet<u64> =
        c.observations.iter().map(|o| c.point_tracks[o.point]).collect();
    for (view, v) in run.views.iter().take_while(|v| v.name != "verge").enumerate() {
        // The exact pixels at the head's true pose for this view's (noisy) readings are not
        // known to the estimate; the simulator's exact capture at the commanded readings is.
        let exact = head.exact_capture(&v.capture.encoders);
        for (right, list, exact_list) in
            [(false, &v.capture.left, &exact.left), (true, &v.capture.right, &exact.right)]
        {
            let exact_of: HashMap<u64, _> = exact_list.iter().map(|e| (e.track, e.pixel)).collect();
            for o in list {
                let Some(x) = exact_of.get(&o.track) else { continue };
                let inlier = (o.pixel - x).norm() <= 5.0 * noise;
                let is_kept = kept.contains_key(&(view, right, o.track));
                if !inlier {
                    kept_outliers += usize::from(is_kept);
                    continue;
                }
                let Some(&point) = clean_index.get(&o.track) else { continue };
                let side = if right { Side::Right } else { Side::Left };
                let b = BundleObservation { point, view, side, pixel: *x };
                all.push(b);
                if is_kept {
                    kept_obs.push(b);
                } else if !adjusted_tracks.contains(&o.track) {
                    lost_with_point += 1;
                    if std::env::var("LOSTB").is_ok() {
                        let d = clean.calibration.bundle.state.points[point].coords.norm();
                        let in_clean =
                            clean.calibration.observations.iter().filter(|q| q.point == point).count();
                        println!(
                            "seed {seed} view {view} right {right} track {} in the clean run ({in_clean} obs there), distance {d:.2} baselines",
                            o.track
                        );
                    }
                }
            }
        }
    }
    let mut o = opts.estimation.bundle.clone();
    o.max_iterations = 0;
    o.robust = RobustLoss::None;
    o.noise_sigma_px = Some(noise);
    let st = &clean.calibration.bundle.state;
    let bound = |obs: &[BundleObservation], window: bool| -> Option<[f64; 4]> {
        let mut o = o.clone();
        if window {
            let [w, h] = sc.image_size.map(f64::from);
            o.measurement_window = Some([-0.5, -0.5, w - 0.5, h - 0.5]);
        }
        let r = bundle_adjust(st, obs, &o).map_err(|e| eprintln!("seed {seed}: {e}")).ok()?;
        Some(NAMES.map(|n| r.covariance.sigma(n).unwrap_or(f64::NAN)))
    };
    if let Some(track) = std::env::var("TRACK").ok().and_then(|t| t.parse::<u64>().ok()) {
        // Every capture of one track in the clean run: its error against the exact pixel.
        for (view, v) in clean_run.views.iter().take_while(|v| v.name != "verge").enumerate() {
            let exact = clean_head.exact_capture(&v.capture.encoders);
            for (side, list, ex) in
                [("L", &v.capture.left, &exact.left), ("R", &v.capture.right, &exact.right)]
            {
                if let (Some(o), Some(x)) =
                    (list.iter().find(|o| o.track == track), ex.iter().find(|o| o.track == track))
                {
                    println!(
                        "track {track} view {view} {side}: pixel ({:.1}, {:.1}) error {:.2} px",
                        o.pixel.x,
                        o.pixel.y,
                        (o.pixel - x.pixel).norm()
                    );
                }
            }
        }
        let cc = &clean.calibration;
        if let Some(i) = cc.point_tracks.iter().position(|t| *t == track) {
            let st = &cc.bundle.state;
            println!("clean state point {i}: {:?}", st.points[i].coords.as_slice());
            for q in cc.observations.iter().filter(|q| q.point == i) {
                println!("  in the clean adjustment: view {} {:?}", q.view, q.side);
            }
        }
    }
    if std::env::var("LOST").is_ok() {
        // Each point left out entirely: its true inlier observations per camera and the
        // views in which both cameras see it.
        let mut per: std::collections::BTreeMap<u64, LostTrack> = Default::default();
        for (view, v) in run.views.iter().take_while(|v| v.name != "verge").enumerate() {
            let exact = head.exact_capture(&v.capture.encoders);
            for (right, list, exact_list) in
                [(0, &v.capture.left, &exact.left), (1, &v.capture.right, &exact.right)]
            {
                let exact_of: HashMap<u64, _> = exact_list.iter().map(|e| (e.track, e.pixel)).collect();
                for o in list {
                    if adjusted_tracks.contains(&o.track) {
                        continue;
                    }
                    let Some(x) = exact_of.get(&o.track) else { continue };
                    if (o.pixel - x).norm() > 5.0 * noise {
                        continue;
                    }
                    let e = per.entry(o.track).or_default();
                    e.0[right] += 1;
                    if right == 0 {
                        e.1.insert(view);
                    } else {
                        e.2.insert(view);
                    }
                }
            }
        }
        for (t, (n, l, r)) in &per {
            let both = l.intersection(r).count();
            println!("seed {seed} lost track {t}: inliers L {} R {}, views with both {both}", n[0], n[1]);
        }
    }
    let t = head.truth();
    let e = &c.bundle.state;
    // The clean run's own observations, outliers it fitted left out with their points.
    let clean_obs: Vec<BundleObservation> = {
        let cc = &clean.calibration;
        let bad: std::collections::HashSet<usize> = cc
            .observations
            .iter()
            .filter(|q| {
                let v = &clean_run.views[q.view];
                let ex = clean_head.exact_capture(&v.capture.encoders);
                let list = if q.side == Side::Right { &ex.right } else { &ex.left };
                list.iter()
                    .find(|e| e.track == cc.point_tracks[q.point])
                    .is_none_or(|e| (e.pixel - q.pixel).norm() > 0.5)
            })
            .map(|q| q.point)
            .collect();
        cc.observations.iter().copied().filter(|q| !bad.contains(&q.point)).collect()
    };
    if std::env::var("MONO").is_ok() {
        // The tracks the noise-free run has no point for (seen by one camera only, or in
        // one view only), placed at their exact position by the N-view DLT with the true
        // cameras, and the bound with them added to the clean run's observations.
        use headalign_geometry::camera::{ProjectiveCamera, dehomogenise3};
        let mut by_track: std::collections::BTreeMap<u64, Vec<(usize, Side, nalgebra::Point2<f64>)>> =
            Default::default();
        for (view, v) in clean_run.views.iter().take_while(|v| v.name != "verge").enumerate() {
            let exact = clean_head.exact_capture(&v.capture.encoders);
            for (side, list) in [(Side::Left, &exact.left), (Side::Right, &exact.right)] {
                for e in list {
                    if !clean_index.contains_key(&e.track) {
                        by_track.entry(e.track).or_default().push((view, side, e.pixel));
                    }
                }
            }
        }
        let mut ext = st.clone();
        let mut obs = clean_obs.clone();
        let (mut added, mut added_obs, mut mono) = (0, 0, 0);
        for (_, list) in by_track {
            if list.len() < 3 {
                continue;
            }
            let cams: Vec<ProjectiveCamera> = list
                .iter()
                .map(|(v, side, _)| {
                    let cam_from_ref = st.motions.ref_from_cam(*v).inverse();
                    match side {
                        Side::Left => ProjectiveCamera::from_pose(&st.left, &cam_from_ref),
                        Side::Right => {
                            ProjectiveCamera::from_pose(&st.right, &(st.right_from_left * cam_from_ref))
                        }
                    }
                })
                .collect();
            let px: Vec<_> = list.iter().map(|x| x.2).collect();
            let Some(p) = headalign_geometry::triangulation::triangulate_views(&cams, &px)
                .ok()
                .and_then(|x| dehomogenise3(&x))
            else {
                continue;
            };
            let index = ext.points.len();
            ext.points.push(p);
            let new: Vec<BundleObservation> = list
                .iter()
                .map(|(v, side, x)| BundleObservation { point: index, view: *v, side: *side, pixel: *x })
                .collect();
            let worst = new
                .iter()
                .filter_map(|b| headalign_geometry::bundle::residual_pixels(&ext, b))
                .map(|r| r.norm())
                .fold(0.0, f64::max);
            if worst.is_nan() || worst >= 1e-3 {
                ext.points.pop();
                continue;
            }
            mono += usize::from(list.iter().all(|x| x.1 == list[0].1));
            added += 1;
            added_obs += new.len();
            obs.extend(new);
        }
        let r = bundle_adjust(&ext, &obs, &o).ok()?;
        let with = NAMES.map(|n| r.covariance.sigma(n).unwrap_or(f64::NAN));
        let without = bound(&clean_obs, false)?;
        println!(
            "seed {seed}: {added} tracks added ({mono} seen by one camera only), {added_obs} observations; bound left.fx {:.3} -> {:.3}, left.fy {:.3} -> {:.3}, right.fx {:.3} -> {:.3}, right.fy {:.3} -> {:.3}",
            without[0], with[0], without[1], with[1], without[2], with[2], without[3], with[3]
        );
    }
    let (ba, bk) = (bound(&all, false)?, bound(&kept_obs, false)?);
    let bc = bound(&clean_obs, false)?;
    if std::env::var("LIST").is_ok() {
        println!(
            "seed {seed}: clean run's bound {:.3} over {} obs (of {}); all {} obs, kept {} obs",
            bc[0],
            clean_obs.len(),
            clean.calibration.observations.len(),
            all.len(),
            kept_obs.len()
        );
    }
    if std::env::var("LIST").is_ok() {
        println!(
            "seed {seed}: left.fx error {:+.2} bound all {:.3} kept {:.3}",
            e.left.fx - t.left.fx,
            ba[0],
            bk[0]
        );
    }
    Some(Row {
        inliers: all.len(),
        kept_inliers: kept_obs.len(),
        kept_outliers,
        lost_with_point,
        err: [e.left.fx - t.left.fx, e.left.fy - t.left.fy, e.right.fx - t.right.fx, e.right.fy - t.right.fy],
        bound_all: ba,
        bound_kept: bk,
        bound_window: bound(&all, true)?,
    })
}

fn main() {
    let a: Vec<f64> = std::env::args().skip(1).filter_map(|s| s.parse().ok()).collect();
    let [first, seeds, noise] = [a[0], a[1], a[2]];
    let (first, seeds) = (first as u64, seeds as u64);
    let half = first + seeds / 2;
    let other =
        std::thread::spawn(move || (half..first + seeds).filter_map(|s| trial(s, noise)).collect::<Vec<_>>());
    let mut rows: Vec<Row> = (first..half).filter_map(|s| trial(s, noise)).collect();
    rows.extend(other.join().unwrap_or_default());
    let n = rows.len() as f64;
    let mean = |f: &dyn Fn(&Row) -> f64| rows.iter().map(f).sum::<f64>() / n;
    println!(
        "{} trials at {noise} px: true inliers {:.1}, kept {:.1} ({:.2} % left out), outliers kept {:.3} per trial; left out with their whole point {:.1}",
        rows.len(),
        mean(&|r| r.inliers as f64),
        mean(&|r| r.kept_inliers as f64),
        100.0 * (1.0 - mean(&|r| r.kept_inliers as f64) / mean(&|r| r.inliers as f64)),
        mean(&|r| r.kept_outliers as f64),
        mean(&|r| r.lost_with_point as f64)
    );
    let rms = |f: &dyn Fn(&Row) -> f64| (rows.iter().map(|r| f(r).powi(2)).sum::<f64>() / n).sqrt();
    for (i, name) in NAMES.iter().enumerate() {
        let (ba, bk, bw, er) = (
            rms(&|r| r.bound_all[i]),
            rms(&|r| r.bound_kept[i]),
            rms(&|r| r.bound_window[i]),
            rms(&|r| r.err[i]),
        );
        println!(
            "{name:>9}: RMS error {er:.2} px; bound all {ba:.2}, kept {bk:.2} ({:.3}x), window {bw:.2} ({:.3}x); error/bound all {:.3}, kept {:.3}, window {:.3}",
            bk / ba,
            bw / ba,
            er / ba,
            er / bk,
            er / bw
        );
    }
}
