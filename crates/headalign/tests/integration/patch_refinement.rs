//! The front end's patch refinement on a rendered pair, against the simulator's truth: a
//! reference view and one after a head rotation, tracked with and without refinement.
//! The truth of an observation is the true projection of the surface point under its
//! track's reference-left pixel (a ray cast through the true camera onto the true room):
//! the point the track stands for. Refinement must bring the observations closer to it.

use headalign::tracking::{FrontEndOptions, Tracker};
use headalign_platform::{Encoders, ImagingHead, Joint, StereoCapture, StereoHead, StereoImages};
use headalign_sim::{Scenario, SimulatedHead};
use nalgebra::{Point2, Point3, Vector3};

/// The rendered pair of both tests: seed 3 of the default room, the reference view and
/// one after a pan of the scenario's rotation, with the encoders' true readings.
struct RenderedPair {
    head: SimulatedHead,
    images: [StereoImages; 2],
    encoders: [Encoders; 2],
}

fn rendered_pair() -> RenderedPair {
    let mut s = Scenario { seed: 3, ..Scenario::default() };
    s.render.use_photos = false; // procedural textures: the measured numbers below are theirs
    let mut head = SimulatedHead::new(s.clone()).unwrap();
    let e0 = head.read_encoders().unwrap();
    let first = head.capture_images().unwrap();
    let t0 = head.encoders();
    head.move_to(&e0.moved(Joint::Pan, s.rotation_deg)).unwrap();
    let second = head.capture_images().unwrap();
    let t1 = head.encoders();
    RenderedPair { head, images: [first, second], encoders: [t0, t1] }
}

/// Every observation of the tracks defined by the reference-left corners of `captures`
/// except those defining ones, with its truth: `visit(view, side, track, observed, true)`
/// pixels. The truth is the true projection of the surface point cast through the
/// track's reference-left pixel.
fn for_each_observation(
    head: &SimulatedHead,
    captures: &[(&StereoCapture, &Encoders)],
    mut visit: impl FnMut(usize, usize, u64, Point2<f64>, Point2<f64>),
) {
    let truth = head.truth().clone();
    let (c0, e0) = captures[0];
    let (scene_from_left0, _) = head.scene_from_cameras(e0);
    for o in &c0.left {
        let ray = truth.left.inverse_matrix() * Vector3::new(o.pixel.x, o.pixel.y, 1.0);
        let origin = Point3::from(scene_from_left0.translation.vector);
        let Some(x) = head.room().cast(&origin, &(scene_from_left0.rotation * ray)) else { continue };
        for (vi, &(c, e)) in captures.iter().enumerate() {
            let (ql, qr) = head.exact_pixels(e, &x);
            for (side, list, q) in [(0, &c.left, ql), (1, &c.right, qr)] {
                if vi == 0 && side == 0 {
                    continue;
                }
                if let (Some(p), Some(q)) = (list.iter().find(|p| p.track == o.track), q) {
                    visit(vi, side, o.track, p.pixel, q);
                }
            }
        }
    }
}

#[test]
fn refined_observations_are_closer_to_the_truth() {
    let RenderedPair { head, images: [first, second], encoders: [t0, t1] } = rendered_pair();
    // (fraction over 1 px, median, count) of: all observations, the later left ones.
    let stats_of = |e: &mut Vec<f64>| {
        e.sort_by(f64::total_cmp);
        let over1 = e.iter().filter(|&&x| x > 1.0).count() as f64 / e.len().max(1) as f64;
        (over1, e.get(e.len() / 2).copied().unwrap_or(f64::NAN), e.len())
    };
    let mut stats = Vec::new();
    for (name, refine, stereo) in
        [("unrefined", false, false), ("default", true, false), ("stereo", true, true)]
    {
        let mut o = FrontEndOptions::default();
        if !refine {
            o.refine = None;
        }
        o.refine_stereo = stereo;
        let mut tracker = Tracker::new(o).unwrap();
        let (c0, _) = tracker.track(&first, "reference").unwrap();
        let (c1, report) = tracker.track(&second, "rotated").unwrap();
        if refine {
            assert!(report.refined[0] > 200 && report.refined[1] > 200, "{report:?}");
        }
        let mut e = Vec::new();
        for_each_observation(&head, &[(&c0, &t0), (&c1, &t1)], |vi, side, _, p, q| {
            e.push((vi, side, (p - q).norm()))
        });
        let mut all: Vec<f64> = e.iter().map(|x| x.2).collect();
        let mut later_left: Vec<f64> = e.iter().filter(|x| x.0 == 1 && x.1 == 0).map(|x| x.2).collect();
        let (a, l) = (stats_of(&mut all), stats_of(&mut later_left));
        eprintln!(
            "{name}: all {} observations, median {:.3} px, {:.1} % over 1 px; later left {}, median {:.3} px, {:.1} % over 1 px",
            a.2,
            a.1,
            100.0 * a.0,
            l.2,
            l.1,
            100.0 * l.0
        );
        stats.push((a, l));
    }
    // Unrefined corners: a median near 0.5 px and 10-25 % beyond 1 px (the detector's
    // independent sub-pixel fits); refined: the patch alignment's few hundredths plus the
    // renderer's aliasing. Bars with a wide margin for the scene and texture. The default
    // refines later views only, so its gain shows in the later left observations (the
    // right ones follow the reference right corner, itself unrefined); with stereo
    // partners refined too, in all of them.
    let (raw, default, stereo) = (stats[0], stats[1], stats[2]);
    for (name, (before, after)) in
        [("later left, default", (raw.1, default.1)), ("all, stereo", (raw.0, stereo.0))]
    {
        assert!(after.2 * 10 > before.2 * 7, "{name}: too many dropped: {} -> {}", before.2, after.2);
        assert!(after.1 < 0.5 * before.1, "{name}: median {:.3} -> {:.3} px", before.1, after.1);
        assert!(
            after.0 < 0.5 * before.0 && after.0 < 0.05,
            "{name}: over 1 px {:.3} -> {:.3}",
            before.0,
            after.0
        );
    }
}

/// The front end's localisation noise against the truth (module docs of
/// `headalign::tracking`, "Localisation noise"): on the rendered pair (2 grey levels of
/// noise, 0.5 px blur), every observation with a known variance except the tracks'
/// defining ones, per class (the reference right corners, aligned to their left partners;
/// the later left ones, aligned to the reference left; the later right ones, aligned to
/// the reference right, their variances added), the truth error normalised by the
/// predicted sigma. Measured: the normalised errors' median over its Gaussian value
/// (`sqrt(2 ln 2)`) 1.06, 1.06, 0.94, and the truth RMS over the predicted 1.48, 1.11,
/// 1.26 (a tail: the 95th percentile of the normalised error 3.0-3.4 against the
/// Gaussian 2.45). Bars: the median within 0.8-1.25 (the sampling spread of ~800 medians
/// is 4 %; the rest is the model's: interpolation and the stereo patches' perspective)
/// and the RMS below 2 (the tail, which the adjustment's re-selection removes).
#[test]
fn localisation_sigmas_match_the_truth_errors() {
    let RenderedPair { head, images: [first, second], encoders: [t0, t1] } = rendered_pair();
    let mut tracker = Tracker::new(FrontEndOptions::default()).unwrap();
    let (c0, r0) = tracker.track(&first, "reference").unwrap();
    let (c1, r1) = tracker.track(&second, "rotated").unwrap();
    assert!(r0.alignment_sigma_px[1].is_some() && r1.alignment_sigma_px[0].is_some(), "{r0:?} {r1:?}");
    let reports = [&r0, &r1];
    for o in &c0.left {
        // The defining observation: variance 0, no parent.
        let own = r0.localisation[0].get(&o.track);
        assert!(own.is_some_and(|l| l.var == 0.0 && l.parent.is_none()), "{own:?}");
    }
    // (view, side, squared error, predicted variance)
    let mut rows = Vec::new();
    for_each_observation(&head, &[(&c0, &t0), (&c1, &t1)], |vi, side, track, p, q| {
        if let Some(l) = reports[vi].localisation[side].get(&track) {
            rows.push((vi, side, (p - q).norm_squared(), l.var));
        }
    });
    for (vi, side) in [(0, 1), (1, 0), (1, 1)] {
        // Gross mismatches (over 1 px) are not localisation noise.
        let sel: Vec<&(usize, usize, f64, f64)> =
            rows.iter().filter(|r| r.0 == vi && r.1 == side && r.2 < 1.0).collect();
        assert!(sel.len() > 300, "view {vi} side {side}: {} observations", sel.len());
        let n = sel.len() as f64;
        let rms_ratio = (sel.iter().map(|r| r.2).sum::<f64>() / (2.0 * n)).sqrt()
            / (sel.iter().map(|r| r.3).sum::<f64>() / n).sqrt();
        let mut z: Vec<f64> = sel.iter().map(|r| (r.2 / r.3).sqrt()).collect();
        z.sort_by(f64::total_cmp);
        let median = z[z.len() / 2] / (2.0 * std::f64::consts::LN_2).sqrt();
        eprintln!(
            "view {vi} side {side}: {} observations, normalised median {median:.2}, RMS over predicted {rms_ratio:.2}",
            sel.len()
        );
        assert!((0.8..1.25).contains(&median) && rms_ratio < 2.0, "view {vi} side {side}");
    }
}
