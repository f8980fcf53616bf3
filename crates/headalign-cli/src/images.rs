//! `headalign demo --images`: the verge/tilt procedure on rendered images with the real
//! front end (no simulator-provided correspondences): verging (paper section 6), then the
//! captures, tracking, estimation, alignment and checks of the point-mode procedure, and
//! with `--save DIR` every captured view (PNG + `view.json`), the annotated images of
//! the paper's Figure 6 and `report.html`.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result};
use headalign::alignment::AlignmentSolution;
use headalign::estimate::{EstimationOptions, RigCalibration};
use headalign::frontend::{FrontEndOptions, TrackingHead};
use headalign::imaging::{VergingOptions, verge_to_common_view};
use headalign::observations::View;
use headalign::procedure::{VergeTiltOptions, VergeTiltOutcome, VergeTiltRun};
use headalign_platform::StereoImages;
use headalign_sim::{AlignmentErrors, CalibrationErrors, Scenario, SimulatedHead, calibration_errors};
use headalign_vision::draw::{BLUE, Canvas, GREEN, MAGENTA, RED, YELLOW};
use serde_json::{Value, json};

use crate::report_html::{AlignmentResults, HtmlReport, REPORT_FILE};

/// What the image-mode demo measured, for the caller's report.
pub struct ImageDemo {
    /// The JSON object (same `errors` / `before` keys as the point-mode demo).
    pub json: Value,
}

/// Run verging and the verge/tilt procedure on rendered images.
pub fn run(scenario: &Scenario, save: Option<&Path>) -> Result<ImageDemo> {
    let t0 = Instant::now();
    let mut head = SimulatedHead::new(scenario.clone()).map_err(|e| anyhow::anyhow!("simulator: {e}"))?;
    let before = head.alignment_errors(&head.encoders());
    let verging = verge_to_common_view(&mut head, &VergingOptions::default()).context("verging")?;
    let options = VergeTiltOptions {
        rotation_deg: scenario.rotation_deg,
        verge_rotation_deg: scenario.rotation_deg,
        // The default estimation seed, as `align --images` uses: a replay of the saved
        // views then reproduces this run bit for bit.
        estimation: EstimationOptions::default(),
        ..VergeTiltOptions::default()
    };
    let mut run = VergeTiltRun::default();
    let (outcome, images, tracking) = {
        let mut tracking_head = TrackingHead::new(&mut head, FrontEndOptions::default())?;
        let outcome = run.run(&mut tracking_head, &options);
        (outcome, std::mem::take(&mut tracking_head.images), tracking_head.tracking.clone())
    };
    // Whatever happened, the captured views are written first.
    if let Some(dir) = save {
        save_views(dir, &run, &images)?;
    }
    let outcome = outcome.context("verge/tilt procedure on images")?;
    if let Some(dir) = save {
        annotate(dir, &run, &images, &outcome)?;
    }
    let total = t0.elapsed().as_secs_f64();
    let after = head.alignment_errors(&head.encoders());
    let st = &outcome.calibration.bundle.state;
    let truth = head.truth().clone();
    let cal = calibration_errors(&truth.left, &truth.right, &st.left, &st.right);
    let true_aligned = head.aligned_encoders();
    let unavoidable_r = head.alignment_errors(&true_aligned).elev_err_r_deg;
    let (errors, before) = (errors_json(&after, unavoidable_r, &cal, None), before_json(&before));
    if let Some(dir) = save {
        write_report(dir, scenario, &run, &outcome, &before, &errors)?;
    }
    let json = json!({
        "mode": "images",
        "errors": errors,
        "before": before,
        "estimate": {
            "left": {"fx": st.left.fx, "fy": st.left.fy, "cx": st.left.cx, "cy": st.left.cy},
            "right": {"fx": st.right.fx, "fy": st.right.fy, "cx": st.right.cx, "cy": st.right.cy},
            "aligned_encoders": serde_json::to_value(outcome.solution.aligned_encoders)?,
            "aligned_sigma_deg": serde_json::to_value(outcome.sigmas)?,
            "fixation_px": {"left": outcome.solution.fixation_px_left, "right": outcome.solution.fixation_px_right},
        },
        "truth": {
            "left": {"fx": truth.left.fx, "fy": truth.left.fy, "cx": truth.left.cx, "cy": truth.left.cy},
            "right": {"fx": truth.right.fx, "fy": truth.right.fy, "cx": truth.right.cx, "cy": truth.right.cy},
            "aligned_encoders": serde_json::to_value(true_aligned)?,
        },
        "images": {
            "verging": serde_json::to_value(&verging)?,
            "tracking": serde_json::to_value(&tracking)?,
            "views": run.views.iter().map(|v| v.name.clone()).collect::<Vec<_>>(),
        },
        "report": serde_json::to_value(&outcome.calibration.report)?,
        "checks": serde_json::to_value(&outcome.checks)?,
        "timings": {"estimation_s": outcome.estimation_seconds, "total_s": total},
    });
    Ok(ImageDemo { json })
}

/// The `errors` member of the demo's JSON: the alignment errors after alignment, the
/// right camera's unavoidable part and the excess over it, and the calibration errors.
pub fn errors_json(
    after: &AlignmentErrors,
    unavoidable_r: f64,
    cal: &CalibrationErrors,
    recon_err_pct: Option<f64>,
) -> serde_json::Map<String, Value> {
    let mut m = before_json(after);
    for (k, v) in [
        ("elev_err_r_unavoidable_deg", json!(unavoidable_r)),
        ("elev_err_r_excess_deg", json!(after.elev_err_r_deg - unavoidable_r)),
        ("f_err_pct", json!(cal.f_err_pct)),
        ("aspect_err_pct", json!(cal.aspect_err_pct)),
        ("pp_err_pct", json!(cal.pp_err_pct)),
        ("recon_err_pct", json!(recon_err_pct)),
    ] {
        m.insert(k.to_string(), v);
    }
    m
}

/// The four alignment errors, as the demo's `before` member names them.
pub fn before_json(e: &AlignmentErrors) -> serde_json::Map<String, Value> {
    let mut m = serde_json::Map::new();
    for (k, v) in [
        ("verge_err_l_deg", e.verge_err_l_deg),
        ("verge_err_r_deg", e.verge_err_r_deg),
        ("elev_err_l_deg", e.elev_err_l_deg),
        ("elev_err_r_deg", e.elev_err_r_deg),
    ] {
        m.insert(k.to_string(), json!(v));
    }
    m
}

/// Each captured view as `DIR/NN-name/{left,right}.png` + `view.json`.
fn save_views(dir: &Path, run: &VergeTiltRun, images: &[StereoImages]) -> Result<()> {
    for (i, (pair, view)) in images.iter().zip(&run.views).enumerate() {
        let sub = dir.join(format!("{:02}-{}", i, view.name));
        std::fs::create_dir_all(&sub).with_context(|| format!("cannot create {}", sub.display()))?;
        pair.left.save(&sub.join("left.png"))?;
        pair.right.save(&sub.join("right.png"))?;
        let meta = json!({
            "name": view.name,
            "encoders": serde_json::to_value(pair.encoders)?,
            "image_size": pair.image_size(),
            "tracked": {"left": view.capture.left.len(), "right": view.capture.right.len()},
        });
        let path = sub.join("view.json");
        std::fs::write(&path, serde_json::to_string_pretty(&meta)? + "\n")
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(())
}

/// The paper's Figure 6 on the reference view (stereo pair side by side): features used by
/// the adjustment (green; others red), the invariant lines of the pan (horizon, blue) and
/// elevation (yellow) rotations, and the fixation point (magenta). `view0` is the tracked
/// reference view, `first` its images.
pub fn figure6(
    first: &StereoImages,
    view0: &View,
    calib: &RigCalibration,
    solution: &AlignmentSolution,
) -> Canvas {
    let used: std::collections::HashSet<u64> =
        calib.observations.iter().filter(|o| o.view == 0).map(|o| calib.point_tracks[o.point]).collect();
    let lines = &solution.invariant_lines;
    let fixation = [solution.fixation_px_left, solution.fixation_px_right];
    let mut halves = Vec::new();
    for (k, (image, list)) in
        [(&first.left, &view0.capture.left), (&first.right, &view0.capture.right)].into_iter().enumerate()
    {
        let mut c = Canvas::from_gray(image);
        for o in list {
            let colour = if used.contains(&o.track) { GREEN } else { RED };
            c.circle([o.pixel.x, o.pixel.y], 3.0, colour, 1);
        }
        let (pan, elevation) = if k == 0 {
            (lines.pan_left, lines.elevation_left)
        } else {
            (lines.pan_right, lines.elevation_right)
        };
        c.image_line(pan, BLUE, 2);
        c.image_line(elevation, YELLOW, 2);
        c.circle(fixation[k], 12.0, MAGENTA, 2);
        c.cross(fixation[k], 18.0, MAGENTA, 2);
        halves.push(c);
    }
    Canvas::beside(&halves[0], &halves[1])
}

/// Caption of `figure6.png` in the reports.
pub const FIGURE6_CAPTION: &str = "figure6.png: the first view (left | right) as the paper's Figure 6: features the bundle adjustment used (green) and not (red), the invariant lines of the pan (blue) and elevation (yellow) rotations, and the fixation point (magenta).";

/// `figure6.png` (see [`figure6`]) and `aligned.png`, the last check view with the image
/// centres marked.
fn annotate(
    dir: &Path,
    run: &VergeTiltRun,
    images: &[StereoImages],
    outcome: &VergeTiltOutcome,
) -> Result<()> {
    let (Some(first), Some(view0)) = (images.first(), run.views.first()) else { return Ok(()) };
    figure6(first, view0, &outcome.calibration, &outcome.solution).save(&dir.join("figure6.png"))?;
    if let Some(last) = images.last() {
        let mut c = Canvas::side_by_side(&last.left, &last.right);
        let [w, h] = last.image_size();
        let centre = [(f64::from(w) - 1.0) / 2.0, (f64::from(h) - 1.0) / 2.0];
        let dx = f64::from(w);
        for p in [centre, [centre[0] + dx, centre[1]]] {
            c.cross(p, 20.0, MAGENTA, 2);
        }
        c.save(&dir.join("aligned.png"))?;
    }
    Ok(())
}

/// `DIR/report.html`: the numbers, the errors against the truth, the annotated images
/// and links to every saved view.
fn write_report(
    dir: &Path,
    scenario: &Scenario,
    run: &VergeTiltRun,
    outcome: &VergeTiltOutcome,
    before: &serde_json::Map<String, Value>,
    errors: &serde_json::Map<String, Value>,
) -> Result<()> {
    let mut rep = HtmlReport::new("headalign demo --images");
    rep.intro(&format!(
        "Simulated head, seed {}, rendered {} x {} images, vision front end (verging, FAST+BRIEF features, matching); {} deg rotations; {} views captured.",
        scenario.seed,
        scenario.image_size[0],
        scenario.image_size[1],
        scenario.rotation_deg,
        run.views.len()
    ));
    rep.alignment_results(&AlignmentResults {
        calibration: &outcome.calibration,
        image_size: scenario.image_size,
        baseline_m: None,
        verge_axes: &outcome.verge_axes,
        reference: outcome.calibration.reference_encoders,
        solution: &outcome.solution,
        sigmas: &outcome.sigmas,
    })?;
    rep.errors_vs_truth(before, errors);
    rep.figures(
        "Annotated images",
        &[
            ("figure6.png".into(), FIGURE6_CAPTION.into()),
            (
                "aligned.png".into(),
                "aligned.png: the last view, after alignment, with the image centres marked (magenta)."
                    .into(),
            ),
        ],
    );
    let links = run
        .views
        .iter()
        .enumerate()
        .flat_map(|(i, v)| {
            ["left", "right"]
                .map(|side| (format!("{i:02}-{}/{side}.png", v.name), format!("{i:02} {} {side}", v.name)))
        })
        .collect();
    rep.links(
        "Captured views",
        "Every captured view (PNG and view.json in each folder): headalign align --images DIR replays them.",
        links,
    );
    rep.write(&dir.join(REPORT_FILE))
}
