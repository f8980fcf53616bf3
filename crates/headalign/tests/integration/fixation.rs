//! Fixation from zero prior knowledge (paper section 5) on the simulated head's rendered
//! images: focal guesses twice too large, the target must end within 1 px of the image
//! centre, checked against the simulator's truth — for a visible scene point and for
//! targets that start outside the image (left, right, above, below, diagonally).

use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};

use headalign::fixation::{Camera, FixationOptions, FixationReport, fixate};
use headalign_sim::{Scenario, SimulatedHead};
use nalgebra::{Point3, Vector3};

/// The simulated head of `seed` at its start. Its textures are baked once per seed and
/// shared by every case of that seed (the cases clone a head baked before any capture):
/// baking draws from its own stream (`SimulatedHead::textured_scene`), seeded by the
/// scenario alone, so a clone renders the images a fresh head would, bit for bit, and a
/// seed's cases pay for one bake instead of one each.
fn head(seed: u64) -> SimulatedHead {
    static HEADS: OnceLock<Mutex<HashMap<u64, Arc<OnceLock<SimulatedHead>>>>> = OnceLock::new();
    let slot = HEADS.get_or_init(Default::default).lock().unwrap().entry(seed).or_default().clone();
    slot.get_or_init(|| {
        let mut h = SimulatedHead::new(Scenario { seed, ..Scenario::default() }).unwrap();
        h.textured_scene();
        h
    })
    .clone()
}

fn centre(h: &SimulatedHead) -> [f64; 2] {
    let [w, hh] = h.scenario().image_size;
    [(f64::from(w) - 1.0) / 2.0, (f64::from(hh) - 1.0) / 2.0]
}

/// The true distance of `point` from the left image centre at the head's present pose.
fn true_error(h: &SimulatedHead, point: &Point3<f64>) -> f64 {
    let now = h.exact_pixels(&h.encoders(), point).0.expect("the target is in view at the end");
    let c = centre(h);
    (now.x - c[0]).hypot(now.y - c[1])
}

#[test]
fn fixates_a_visible_scene_point_within_a_pixel() {
    let mut h = head(3);
    let e0 = h.encoders();
    let c = centre(&h);
    // A scene point seen by the left camera about 250 px right of and 120 px above the
    // centre (away from the border so its patch is whole).
    let scene: Vec<Point3<f64>> = h.scene_points().iter().map(|(_, p)| *p).collect();
    let (point, pixel) = scene
        .iter()
        .filter_map(|p| h.exact_pixels(&e0, p).0.map(|px| (*p, px)))
        .min_by(|a, b| {
            let d = |px: &nalgebra::Point2<f64>| (px.x - c[0] - 250.0).hypot(px.y - c[1] + 120.0);
            d(&a.1).total_cmp(&d(&b.1))
        })
        .unwrap();
    let report = fixate(&mut h, Camera::Left, [pixel.x, pixel.y], &FixationOptions::default()).unwrap();
    let err = true_error(&h, &point);
    println!("visible target: true error {err:.3} px, {} moves", report.steps.len());
    // The bar: within 1 px of the centre (truth, not the tracker's own estimate).
    assert!(err < 1.0, "true error {err:.3} px after {} moves: {report:?}", report.steps.len());
    assert!(report.steps.len() >= 2, "the 2x focal guess needs more than one move");
}

/// Fixate the scene surface the left camera sees (or would see) at pixel `target` of its
/// start image, a pixel outside the image: the target is the first surface along that
/// pixel's ray, which is what the pixel means to a real head (a direction, and whatever
/// lies there). Returns the true final error, pixels, and the report.
fn fixate_outside(seed: u64, target: [f64; 2]) -> (f64, FixationReport) {
    let mut h = head(seed);
    let e0 = h.encoders();
    let (world_from_left, _) = h.world_from_cameras(&e0);
    let k = h.truth().left;
    let y = (target[1] - k.cy) / k.fy;
    let ray_in_cam = Vector3::new((target[0] - k.cx - k.skew * y) / k.fx, y, 1.0);
    let origin = Point3::from(world_from_left.translation.vector);
    let point = h.room().cast(&origin, &(world_from_left.rotation * ray_in_cam)).expect("a closed room");
    let [w, hh] = h.scenario().image_size;
    let outside = |v: f64, n: u32| v < -30.0 || v > f64::from(n) + 30.0;
    assert!(outside(target[0], w) || outside(target[1], hh), "the target starts outside the image");
    let report = fixate(&mut h, Camera::Left, target, &FixationOptions::default()).unwrap();
    let err = true_error(&h, &point);
    // The tracker's own final error is under its 0.3 px tolerance.
    assert!(report.final_error_px <= 0.3);
    (err, report)
}

/// Run the cases, print a table (cargo test -- --nocapture) and check the bar.
fn check(cases: &[(u64, [f64; 2])]) {
    let mut failures = Vec::new();
    for &(seed, target) in cases {
        let (err, report) = fixate_outside(seed, target);
        let alpha = report.alpha_px;
        println!(
            "seed {seed} target ({:.0}, {:.0}): true error {err:.3} px, {} moves, final alpha ({:.0}, {:.0})",
            target[0],
            target[1],
            report.steps.len(),
            alpha[0],
            alpha[1]
        );
        // The bar of issue 3: within 1 px of the centre by the simulator's truth, asserted
        // as it stands. Measured 0.04-0.89 px over these cases. The part above ~0.1 px (the
        // level with the axes through the optical centre) is the unseen target's depth:
        // the offset axes translate the camera while the target is carried outside the
        // image, and its depth is taken from its visible neighbours, which a ceiling
        // beyond a wall's top edge does not share (seeds 2, 3, 5 above: 0.7-0.9 px).
        if err >= 1.0 {
            failures.push(format!("seed {seed} target {target:?}: {err:.3} px"));
        }
    }
    assert!(failures.is_empty(), "over 1 px: {failures:?}");
}

// About 30 deg off the optical axis each (the image spans +-29 deg by +-22 deg).
const RIGHT: [f64; 2] = [900.0, 200.0];
const LEFT: [f64; 2] = [-150.0, 200.0];
const ABOVE: [f64; 2] = [300.0, -150.0];
const BELOW: [f64; 2] = [450.0, 730.0];
const UP_RIGHT: [f64; 2] = [880.0, -60.0];
const DOWN_LEFT: [f64; 2] = [-120.0, 640.0];

#[test]
fn fixates_targets_left_and_right_of_the_image() {
    check(&[1, 2, 3, 5].iter().flat_map(|&s| [(s, RIGHT), (s, LEFT)]).collect::<Vec<_>>());
}

#[test]
fn fixates_targets_above_and_below_the_image() {
    check(&[1, 2, 3, 5].iter().flat_map(|&s| [(s, ABOVE), (s, BELOW)]).collect::<Vec<_>>());
}

#[test]
fn fixates_targets_diagonally_outside_the_image() {
    check(&[(4, UP_RIGHT), (4, DOWN_LEFT), (6, UP_RIGHT), (6, DOWN_LEFT)]);
}
