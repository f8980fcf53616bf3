//! `calibrate::track_views_reporting` on rendered views: one progress call per view, in
//! order, with the route taken and the number of views, and the same tracks as
//! `track_views` (the callback observes, it does not steer).

use headalign::calibrate::{CalibrateOptions, Route, TrackingProgress, track_views, track_views_reporting};
use headalign::tracking::FrontEndOptions;
use headalign_platform::{ImagingHead, Joint, StereoHead, StereoImages};
use headalign_sim::{Scenario, SimulatedHead};

/// The initial view and views after the scenario's pan and elevation (seed 5).
fn rendered_views() -> Vec<(String, StereoImages)> {
    let mut s = Scenario { seed: 5, ..Scenario::default() };
    s.render.use_photos = false; // procedural textures: progress does not depend on them
    let mut head = SimulatedHead::new(s.clone()).unwrap();
    let e0 = head.read_encoders().unwrap();
    let mut views = Vec::new();
    for (name, enc) in [
        ("initial", e0),
        ("pan", e0.moved(Joint::Pan, s.rotation_deg)),
        ("elevation", e0.moved(Joint::Elevation, s.rotation_deg)),
    ] {
        head.move_to(&enc).unwrap();
        views.push((name.to_string(), head.capture_images().unwrap()));
    }
    views
}

#[test]
fn progress_is_reported_once_per_view_in_order() {
    let views = rendered_views();
    let (front, options) = (FrontEndOptions::default(), CalibrateOptions::default());
    let mut calls: Vec<TrackingProgress> = Vec::new();
    let tracked = track_views_reporting(&views, &front, &options, &mut |p| calls.push(p)).unwrap();
    let expected: Vec<TrackingProgress> =
        (1..=3).map(|done| TrackingProgress { route: Route::Reference, done, total: 3 }).collect();
    assert_eq!(calls, expected);
    let plain = track_views(&views, &front, &options).unwrap();
    assert_eq!(tracked.route, plain.route);
    let tracks = |t: &headalign::calibrate::TrackedViews| -> Vec<usize> {
        t.views.iter().map(|v| v.capture.left.len() + v.capture.right.len()).collect()
    };
    assert_eq!(tracks(&tracked), tracks(&plain));
}
