//! Self-calibration from a sequence: hundreds of views of a moving rig in which each view
//! overlaps only its neighbours, possibly in disconnected segments (`docs/formats.md#sequences`;
//! the chain of [`super`] with the reference view replaced by a view graph).
//!
//! Input: views whose track ids are chained through consecutive views (the front end's
//! [`TrackingMode::Previous`], or any observations whose ids name one scene point across
//! the views that see it). Chain, each step a pure function of the previous:
//! 1. the rig's views: those whose vergence readings equal the first view's (as
//!    [`super::calibrate_rig`]);
//! 2. keyframes by motion and overlap, the view graph of the tracks they share, its
//!    connected components (segments) and a spanning tree per segment rooted at its first
//!    keyframe, the segment's gauge ([`super::graph`]);
//! 3. the scene-depth check on every keyframe: a planar one is left out (the graph is
//!    rebuilt without it);
//! 4. one fundamental matrix from the stereo matches of all keyframes, the
//!    quasi-Euclidean frame, each keyframe's triangulation (as [`super::calibrate_rig`]):
//!    one projective frame for every segment, since the rig is one;
//! 5. per tree edge, the 3D homography from the parent keyframe to the child (3-point
//!    rigid RANSAC, DLT fallback, polished; [`super::motion`]), and each keyframe's motion
//!    from its gauge as the product along the tree, `H_gk = H_pk H_gp` (and the rigid
//!    motions likewise);
//! 6. the linear self-calibration from at most [`SequenceOptions::linear_motions`]
//!    composed motions, those that rotate by 15 deg or more with the fewest edges to their
//!    gauge first (the least drift; [`LINEAR_ROTATION_DEG`]); all in the one frame, so the
//!    segments' motions fix the plane at infinity and the conic together; and the rigid
//!    start;
//! 7. the adjustment of [`super::calibrate_rig`] over all keyframes of all segments: one
//!    pair of intrinsics, one rig, 6 dof per keyframe except the gauges, every segment's
//!    points in its gauge's frame (`BundleOptions::gauge_views`), both starts, the pass
//!    over every point;
//! 8. the report: the segments with their keyframes and links, each motion relative to
//!    its gauge (which entered the linear start), the views left out and why; with a lens
//!    model estimated, the focal-length and lens sigmas widened to the bootstrap spread
//!    over tracks as on the reference route ([`super::lens_sigmas`], the gauges held).
//!
//! Degrees of freedom: as [`super::calibrate_rig`] with `6 (K - S)` pose parameters for
//! `K` keyframes in `S` segments. Units: pixels, degrees, baselines.
//!
//! Cost: the views enter only through keyframe selection (linear in the observations);
//! the keyframes through the adjustment, whose Schur complement over the points is sparse
//! above 16 views (`headalign_geometry::bundle`): linear in the points and in the
//! keyframes but for the dense Cholesky of the reduced camera system (cubic in the
//! keyframes, small below a few hundred).
//!
//! Pitfalls: a composed motion carries the drift of the 3D homographies along its path:
//! it is only a start, the adjustment re-estimates every pose from the pixels. A segment
//! whose motions are all small or about one axis adds little: the sigmas say so. Track
//! ids shared by two segments (fewer than `min_link_tracks`: wrong links) are kept in the
//! segment of the keyframe that first reconstructed them only.
//!
//! [`TrackingMode::Previous`]: crate::tracking::TrackingMode::Previous
//! [`SequenceOptions::linear_motions`]: super::SequenceOptions::linear_motions

use headalign_geometry::camera::Intrinsics;
use headalign_geometry::homography3d::{Homography3, Quadruplet, TransferModel};
use headalign_platform::Joint;
use nalgebra::{Isometry3, Matrix4};
use serde::Serialize;

use super::bundle_starts::{self, Links};
use super::graph::{self, SegmentReport, ViewTracks};
use super::motion::{ViewMotion, fit_motion};
use super::rig_stereo::StereoGeometry;
use super::{
    CalibrateOptions, MotionCalibration, MotionReport, Seeded, depth, report, rig_bundle, rig_stereo,
};
use crate::error::AlignError;
use crate::observations::View;
use crate::verge_tilt::MOVED_DEG;

/// Stereo matches F's RANSAC scores at most (step 4; every `n`-th of the keyframes'):
/// thousands of matches of one rig determine F to far below a pixel, and the RANSAC's
/// cost grows with the matches it scores. The refinement runs over all of them.
pub const RANSAC_PAIRS: usize = 5000;

/// What the report says of a sequence ([`CalibrateReport::sequence`](super::CalibrateReport::sequence)).
#[derive(Debug, Clone, Serialize)]
pub struct SequenceReport {
    /// Views given.
    pub views: usize,
    /// Keyframes chosen (before the depth check and the segments).
    pub keyframes: usize,
    /// The segments that calibrated, in the adjustment's order.
    pub segments: Vec<SegmentReport>,
    /// Why the views were tracked as a sequence ([`super::TrackedViews::notes`]; empty
    /// when the views came tracked).
    pub tracking_notes: Vec<String>,
}

/// Self-calibrate the rig from a sequence of views (module docs): every segment adds its
/// motions to one calibration. Restarts with the next seeds as [`super::calibrate_rig`].
pub fn calibrate_sequence(
    views: &[View],
    options: &CalibrateOptions,
) -> Result<MotionCalibration, AlignError> {
    options.validate()?;
    let with_restarts =
        |o: &CalibrateOptions| super::with_restarts(o, |o, seeded| sequence_once(views, o, seeded));
    let mut result = if options.lens == super::LensChoice::Auto {
        super::lens_auto::choose_lens(options, with_restarts, None)?
    } else {
        with_restarts(options)?
    };
    super::widen_lens_sigmas(&mut result, options);
    super::fit_checks::check_and_widen(&mut result);
    result.report.image_noise = Some(super::ImageNoiseCheck::skipped(super::image_noise::NO_IMAGES));
    Ok(result)
}

/// The keyframes of the adjustment and how they link (steps 1-3).
struct Keyframes {
    /// The keyframes in the adjustment's order: per segment its gauge, then its tree.
    rig: Vec<View>,
    links: Links,
    /// The gauges after the first (slots).
    gauges: Vec<usize>,
    planarity: Vec<depth::PlaneCheck>,
    skipped: Vec<String>,
    report: SequenceReport,
}

/// Steps 1-3 (module docs): the rig's views, keyframes, depth check, segments and trees.
fn keyframes(views: &[View], options: &CalibrateOptions) -> Result<Keyframes, AlignError> {
    let so = &options.sequence;
    let Some(first) = views.first() else {
        return Err(AlignError::Observations("no views".into()));
    };
    let e0 = first.capture.encoders;
    let mut skipped = Vec::new();
    let mut rig_views: Vec<&View> = Vec::new();
    for v in views {
        let moved = [Joint::VergeLeft, Joint::VergeRight]
            .iter()
            .any(|&j| (v.capture.encoders.get(j) - e0.get(j)).abs() > MOVED_DEG);
        if moved {
            skipped.push(format!("{}: vergence moved (the rig changed)", v.name));
        } else {
            rig_views.push(v);
        }
    }
    let tracks: Vec<ViewTracks> = rig_views.iter().map(|v| ViewTracks::of(v)).collect();
    let chosen = graph::keyframes(&tracks, so);
    let key_views: Vec<View> = chosen.iter().map(|&k| rig_views[k].clone()).collect();
    let planarity = depth::check_planarity(&key_views, options);
    if !planarity.is_empty() && planarity.iter().all(|c| c.planar) {
        return Err(depth::planar_error(&planarity));
    }
    let mut keys = Vec::new();
    for (&k, c) in chosen.iter().zip(&planarity) {
        if c.planar {
            skipped.push(format!("{}: all stereo matches on one plane", rig_views[k].name));
        } else {
            keys.push(k);
        }
    }
    let counts = graph::shared_counts(&tracks, &keys);
    let (segments, alone) = graph::segments(keys.len(), &counts, so.min_link_tracks);
    for &pos in &alone {
        skipped.push(format!(
            "{}: shares fewer than {} stereo tracks with every other keyframe (no motion to calibrate from)",
            rig_views[keys[pos]].name, so.min_link_tracks
        ));
    }
    if segments.is_empty() {
        return Err(AlignError::MissingMotion(format!(
            "no two of the {} views share {} tracks seen by both cameras: self-calibration needs the rig in at least two positions that see the same scene (record views that overlap more, or track them in order)",
            rig_views.len(),
            so.min_link_tracks
        )));
    }
    let arranged = arrange(&rig_views, &chosen, &keys, &segments, &alone, &mut skipped);
    Ok(Keyframes {
        rig: arranged.rig,
        links: arranged.links,
        gauges: arranged.gauges,
        planarity,
        skipped,
        report: SequenceReport {
            views: views.len(),
            keyframes: chosen.len(),
            segments: arranged.reports,
            tracking_notes: Vec::new(),
        },
    })
}

/// The keyframes of the segments in the adjustment's order ([`arrange`]).
struct Arranged {
    rig: Vec<View>,
    links: Links,
    gauges: Vec<usize>,
    reports: Vec<SegmentReport>,
}

/// The adjustment's order of the keyframes (per segment its tree from the gauge), the
/// links, the gauges after the first, and each segment's report; every view is counted
/// with the last keyframe at or before it (`chosen`, before the depth check), and a view
/// whose keyframe went is added to `skipped`. `keys`: the keyframes kept (view indices),
/// `segments` and `alone` in positions of `keys`.
fn arrange(
    rig_views: &[&View],
    chosen: &[usize],
    keys: &[usize],
    segments: &[graph::Segment],
    alone: &[usize],
    skipped: &mut Vec<String>,
) -> Arranged {
    let mut between = vec![0usize; keys.len()];
    let mut represented_by = None;
    for (i, v) in rig_views.iter().enumerate() {
        if let Ok(c) = chosen.binary_search(&i) {
            represented_by = Some(c);
            continue;
        }
        let Some(c) = represented_by else { continue };
        match keys.binary_search(&chosen[c]) {
            Ok(pos) if !alone.contains(&pos) => between[pos] += 1,
            _ => {
                skipped.push(format!("{}: its keyframe '{}' was left out", v.name, rig_views[chosen[c]].name))
            }
        }
    }
    let mut rig = Vec::new();
    let (mut parent, mut segment, mut gauges) = (Vec::new(), Vec::new(), Vec::new());
    let mut reports = Vec::new();
    for (s, seg) in segments.iter().enumerate() {
        let base = rig.len();
        let slot_of = |pos: usize| seg.order.iter().position(|x| x.0 == pos).map(|i| base + i);
        let name = |pos: usize| rig_views[keys[pos]].name.clone();
        let mut seg_report = SegmentReport {
            gauge: name(seg.order[0].0),
            keyframes: Vec::new(),
            links: Vec::new(),
            between_keyframes: 0,
        };
        for &(pos, link) in &seg.order {
            rig.push(rig_views[keys[pos]].clone());
            seg_report.keyframes.push(name(pos));
            seg_report.between_keyframes += between[pos];
            segment.push(s);
            match link {
                Some((p, shared)) => {
                    parent.push(slot_of(p));
                    seg_report.links.push((name(pos), name(p), shared));
                }
                None => {
                    parent.push(None);
                    if base > 0 {
                        gauges.push(base);
                    }
                }
            }
        }
        reports.push(seg_report);
    }
    Arranged { rig, links: Links { parent, segment }, gauges, reports }
}

/// A motion that moves nothing: a segment gauge's, relative to itself.
fn identity_motion(view: &str) -> Result<ViewMotion, AlignError> {
    let h = Homography3(Matrix4::identity());
    let model =
        TransferModel::new(h).map_err(|cause| AlignError::Geometry { step: "identity".into(), cause })?;
    Ok(ViewMotion {
        model,
        rigid: Some(Isometry3::identity()),
        inlier_tracks: Vec::new(),
        report: MotionReport {
            view: view.to_string(),
            candidates: 0,
            inliers: 0,
            rms_transfer_px: 0.0,
            homography_rotation_deg: 0.0,
            relative_to: Some(view.to_string()),
            linear: false,
            rotation_deg: f64::NAN,
            axis: [f64::NAN; 3],
            translation_baselines: f64::NAN,
            along_axis_baselines: f64::NAN,
        },
    })
}

/// Step 5 (module docs): per keyframe after the first, its motion from its segment's
/// gauge, composed along the tree from the 3D homographies of the edges (the edge's
/// inliers, counts and transfer error stay with it); a gauge gets the identity. Sets
/// `seeded` when an edge fits no homography.
fn chain_motions(
    kf: &Keyframes,
    stereo: &StereoGeometry,
    options: &CalibrateOptions,
    seeded: &mut Option<Seeded>,
) -> Result<Vec<ViewMotion>, AlignError> {
    let est = &options.estimation;
    let recon = &stereo.recon;
    let n = kf.rig.len();
    // Per slot: the composed H and rigid motion from its gauge, and the gauge's name.
    let mut composed: Vec<(Matrix4<f64>, Option<Isometry3<f64>>, String)> = Vec::with_capacity(n);
    let mut motions = Vec::with_capacity(n.saturating_sub(1));
    for (slot, view) in kf.rig.iter().enumerate() {
        let Some(parent) = kf.links.parent[slot] else {
            composed.push((Matrix4::identity(), Some(Isometry3::identity()), view.name.clone()));
            if slot > 0 {
                motions.push(identity_motion(&view.name)?);
            }
            continue;
        };
        let (mut tracks, mut quads) = (Vec::new(), Vec::new());
        for (track, (x, l0, r0)) in &recon[parent] {
            if let Some((y, l1, r1)) = recon[slot].get(track) {
                tracks.push(*track);
                quads.push(Quadruplet { x: *x, y: *y, left0: *l0, right0: *r0, left1: *l1, right1: *r1 });
            }
        }
        if quads.len() < est.min_tracks {
            return Err(AlignError::TooFewTracks {
                what: format!(
                    "reconstructed in both keyframes '{}' and '{}'",
                    kf.rig[parent].name, view.name
                ),
                needed: est.min_tracks,
                got: quads.len(),
            });
        }
        let common = quads.len();
        let seed = est.seed.wrapping_add(slot as u64);
        let edge = fit_motion(&quads, &tracks, &stereo.frame, options, &view.name, seed)
            .inspect_err(|_| *seeded = Some(Seeded { common_tracks: common, fitting: 0 }))?;
        let (h_p, rigid_p, gauge) = composed[parent].clone();
        let h = edge.model.h.0 * h_p;
        let rigid = edge.rigid.zip(rigid_p).map(|(e, p)| e * p);
        composed.push((h, rigid, gauge.clone()));
        let model = TransferModel::new(Homography3(h))
            .map_err(|cause| AlignError::Geometry { step: "composed 3D homography".into(), cause })?;
        let angle = Homography3(h)
            .normalized_det()
            .map(|n| ((n.0.trace() - 2.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees())
            .unwrap_or(f64::NAN);
        let mut report = edge.report;
        report.homography_rotation_deg = angle;
        report.relative_to = Some(gauge);
        motions.push(ViewMotion { model, rigid, inlier_tracks: edge.inlier_tracks, report });
    }
    Ok(motions)
}

/// A composed motion rotating by this much (degrees) conditions the linear
/// self-calibration well ([`linear_choice`]): the one-motion rule asks for 20-30 deg, two
/// rotations about different axes work from 3 deg.
pub const LINEAR_ROTATION_DEG: f64 = 15.0;

/// Step 6's choice (module docs): at most `linear_motions` motions (not gauges) rotating by
/// `min_rotation_deg` or more: first those rotating by [`LINEAR_ROTATION_DEG`] or more
/// that are fewest tree edges from their gauge, then the others, largest rotation first.
/// Why: a composed motion carries the drift of every 3D homography along its path, so
/// the largest rotations of a long chain (the far end of a turning sequence) are the
/// least accurate; on the 200-view rendered sequence of `benches/sequence.rs` the eight
/// largest (near 180 deg, some 25 edges out) took the screening of the linear start 25
/// iterations, the eight nearest beyond 15 deg 14.
fn linear_choice(motions: &[ViewMotion], links: &Links, options: &CalibrateOptions) -> Vec<bool> {
    let depth = |slot: usize| {
        let (mut d, mut s) = (0usize, slot);
        while let Some(Some(p)) = links.parent.get(s) {
            d += 1;
            s = *p;
        }
        d
    };
    let mut candidates: Vec<(bool, usize, f64, usize)> = motions
        .iter()
        .enumerate()
        .filter(|(i, _)| links.parent.get(i + 1).is_some_and(Option::is_some))
        .map(|(i, m)| (i, m.report.homography_rotation_deg))
        .filter(|(_, a)| *a >= options.min_rotation_deg)
        .map(|(i, a)| (a < LINEAR_ROTATION_DEG, depth(i + 1), a, i))
        .collect();
    // Large enough first, then the fewest edges out, then the largest rotation.
    candidates.sort_by(|a, b| {
        a.0.cmp(&b.0)
            .then(if a.0 { std::cmp::Ordering::Equal } else { a.1.cmp(&b.1) })
            .then(b.2.total_cmp(&a.2))
            .then(a.3.cmp(&b.3))
    });
    let mut used = vec![false; motions.len()];
    for &(_, _, _, i) in candidates.iter().take(options.sequence.linear_motions) {
        used[i] = true;
    }
    used
}

/// One run of the sequence chain with the options' estimation seed (module docs).
fn sequence_once(
    views: &[View],
    options: &CalibrateOptions,
    seeded: &mut Option<Seeded>,
) -> Result<MotionCalibration, AlignError> {
    let kf = keyframes(views, options)?;
    let image_size = kf.rig[0].capture.image_size;
    let k0 = Intrinsics::rough_guess(image_size[0], image_size[1]);
    let est = &options.estimation;
    let stereo = rig_stereo::stereo_geometry_sampled(&kf.rig, &k0, est, Some(RANSAC_PAIRS))?;
    let motions = chain_motions(&kf, &stereo, options, seeded)?;
    let points = bundle_starts::point_set_linked(&kf.rig, &stereo.recon, &motions, &kf.links);
    let problem = bundle_starts::Problem {
        recon: &stereo.recon,
        point_tracks: &points.point_tracks,
        origin_slot: &points.origin_slot,
        min_tracks: est.min_tracks,
    };
    let used = linear_choice(&motions, &kf.links, options);
    let linear = bundle_starts::linear_start_from(&motions, used, &stereo.frame, &k0, &problem, options);
    let (linear_k, linear_error) = bundle_starts::linear_summary(&linear.state)?;
    let rigid = bundle_starts::rigid_start(&motions, &stereo.frame, &k0, &problem, options);
    let mut held = options.clone();
    held.estimation.bundle.gauge_views = kf.gauges.clone();
    // One or two motions: both starts to convergence (shallow valleys, as the reference
    // chain); more: the better screened start only.
    let moving = kf.links.parent.iter().filter(|p| p.is_some()).count();
    let starts = [linear.state, rigid];
    let adjusted = if moving <= 2 {
        rig_bundle::adjust_starts(starts, &points, &stereo.recon, &held, None, None)
    } else {
        rig_bundle::adjust_best_start(starts, &points, &stereo.recon, &held)
    };
    let adjusted = adjusted.inspect_err(|_| {
        *seeded = motions
            .iter()
            .enumerate()
            .filter(|(i, _)| kf.links.parent.get(i + 1).is_some_and(Option::is_some))
            .map(|(_, m)| Seeded { common_tracks: m.report.candidates, fitting: m.report.inliers })
            .min_by_key(|x| x.fitting);
    })?;
    // The report: the motions of the keyframes that are not gauges.
    let all_reports = report::adjusted_motions(&motions, &linear.used, &adjusted.last.state);
    let motion_reports: Vec<MotionReport> = all_reports
        .into_iter()
        .enumerate()
        .filter(|(i, _)| kf.links.parent.get(i + 1).is_some_and(Option::is_some))
        .map(|(_, r)| r)
        .collect();
    report::require_rotation(&motions, &motion_reports, options)?;
    let motions_fitted = motion_reports.len();
    let report = report::chain_report(
        report::ChainRun {
            views: kf.rig.iter().map(|v| v.name.clone()).collect(),
            skipped: kf.skipped,
            planarity: kf.planarity,
            stereo: &stereo,
            motions: motion_reports,
            motions_fitted,
            plane_conditioning: linear.plane_conditioning,
            conic_uniqueness: linear.conic_uniqueness,
            linear_k,
            linear_error,
            adjusted: &adjusted,
            points: points.point_tracks.len(),
            sequence: Some(kf.report),
        },
        options,
    );
    Ok(MotionCalibration {
        bundle: adjusted.last,
        point_tracks: points.point_tracks,
        observations: adjusted.observations,
        image_size,
        report,
    })
}
