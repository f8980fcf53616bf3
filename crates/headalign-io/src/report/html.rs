//! `report.html`: one self-contained page (plain HTML and CSS, no scripts, no external
//! files other than the images it shows) with the numbers of a run and its annotated
//! images, written beside the run's other outputs.
//!
//! What it shows: the calibration (both `K`s with standard deviations, pixels; the rig
//! rotation in degrees and translation in metres or baselines), the head geometry (pan
//! and elevation axes as lines in the reference left camera frame with the direction's
//! standard deviation in degrees; the vergence axes if a vergence moved), the alignment
//! (reference and aligned encoder readings with standard deviations, degrees; fixation
//! points, pixels), the estimation's fit (matches, inliers, RMS reprojection, pixels),
//! and, when the run was simulated, the errors against the simulator's truth before and
//! after alignment. Nothing is estimated here.
//!
//! Use: build an [`HtmlReport`], add [`AlignmentResults`] (any procedure that produced a
//! [`RigCalibration`] and an [`AlignmentSolution`] can: `align`, `demo --images`, a
//! replay), optionally [`HtmlReport::errors_vs_truth`], figures and free sections, then
//! [`HtmlReport::write`]. [`write_session_report`] writes the report files of a recorded
//! image-mode run (`report.html`, `figure6.png`, `aligned.png`, the calibration files).
//!
//! Pitfalls: every piece of text (view names, file names, numbers) is HTML-escaped;
//! images are referenced by a path relative to the report (the report and its images are
//! moved together), never embedded, to keep the page small; a non-finite number is shown
//! as "-" rather than "NaN".

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::ReportError;
use crate::export::CalibrationFiles as _;
use crate::session::RecordedView;
use headalign::alignment::{AlignmentSolution, VergeAxes};
use headalign::calibration::{IntrinsicSigmas, StereoCalibration, TranslationUnit};
use headalign::facing_plane::SceneCheck;
use headalign::image_mode::{self, ImageRun};
use headalign::observations::View;
use headalign::procedure::AlignmentSigmas;
use headalign::procedure::{PlanarOutcome, RouteOutcome, VergeTiltOutcome};
use headalign::verge_tilt::{RigCalibration, axes_of};
use headalign_geometry::so3::Line;
use headalign_platform::{Encoders, Joint, StereoImages};
use headalign_vision::draw::{Canvas, MAGENTA};
use serde_json::{Map, Value};

/// The result of building or writing a report.
type Result<T> = std::result::Result<T, ReportError>;

/// The file name the commands write.
pub const REPORT_FILE: &str = "report.html";

/// Everything a run measured that the report shows.
pub struct AlignmentResults<'a> {
    /// The rig calibration (bundle adjustment with covariance).
    pub calibration: &'a RigCalibration,
    /// Image size `[width, height]`, pixels.
    pub image_size: [u32; 2],
    /// Baseline length in metres, if known (the translation is in baselines otherwise).
    pub baseline_m: Option<f64>,
    /// The vergence axes (measured or not).
    pub verge_axes: &'a VergeAxes,
    /// Encoder readings of the reference (first) view, degrees.
    pub reference: Encoders,
    /// The alignment solve.
    pub solution: &'a AlignmentSolution,
    /// Standard deviations of the aligned readings, degrees.
    pub sigmas: &'a AlignmentSigmas,
}

/// One block of a section.
enum Block {
    Paragraph(String),
    Table { header: Vec<String>, rows: Vec<Vec<String>> },
    Figure { src: String, caption: String },
    Links(Vec<(String, String)>),
}

struct Section {
    heading: String,
    blocks: Vec<Block>,
}

/// A report under construction; [`HtmlReport::to_html`] renders it.
pub struct HtmlReport {
    title: String,
    intro: Vec<String>,
    sections: Vec<Section>,
}

/// HTML-escape text (element content and double-quoted attribute values).
pub fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            _ => out.push(c),
        }
    }
    out
}

/// `v` with `prec` decimals, "-" if not finite.
fn num(v: f64, prec: usize) -> String {
    if v.is_finite() { format!("{v:.prec$}") } else { "-".into() }
}

/// `v ± s` with `prec` decimals (the sigma with one more), or just `v` without a sigma.
fn pm(v: f64, s: Option<f64>, prec: usize) -> String {
    match s {
        Some(s) if s.is_finite() => format!("{} ± {}", num(v, prec), num(s, prec + 1)),
        _ => num(v, prec),
    }
}

fn vec3(v: [f64; 3], prec: usize) -> String {
    format!("({}, {}, {})", num(v[0], prec), num(v[1], prec), num(v[2], prec))
}

fn line_dir(l: &Line) -> [f64; 3] {
    [l.direction.x, l.direction.y, l.direction.z]
}

fn line_point(l: &Line) -> [f64; 3] {
    [l.point.x, l.point.y, l.point.z]
}

impl HtmlReport {
    /// An empty report with a title.
    pub fn new(title: &str) -> Self {
        Self { title: title.to_string(), intro: Vec::new(), sections: Vec::new() }
    }

    /// A paragraph under the title.
    pub fn intro(&mut self, text: &str) -> &mut Self {
        self.intro.push(text.to_string());
        self
    }

    fn section(&mut self, heading: &str) -> &mut Section {
        self.sections.push(Section { heading: heading.to_string(), blocks: Vec::new() });
        let last = self.sections.len() - 1;
        &mut self.sections[last]
    }

    /// A section with a table (cells are plain text; they are escaped).
    pub fn table(&mut self, heading: &str, note: Option<&str>, header: &[&str], rows: Vec<Vec<String>>) {
        let s = self.section(heading);
        if let Some(n) = note {
            s.blocks.push(Block::Paragraph(n.to_string()));
        }
        s.blocks.push(Block::Table { header: header.iter().map(|h| h.to_string()).collect(), rows });
    }

    /// A section of figures: `(path relative to the report, caption)`.
    pub fn figures(&mut self, heading: &str, figures: &[(String, String)]) {
        let s = self.section(heading);
        for (src, caption) in figures {
            s.blocks.push(Block::Figure { src: src.clone(), caption: caption.clone() });
        }
    }

    /// A section listing links: `(path relative to the report, text)`.
    pub fn links(&mut self, heading: &str, note: &str, links: Vec<(String, String)>) {
        let s = self.section(heading);
        s.blocks.push(Block::Paragraph(note.to_string()));
        s.blocks.push(Block::Links(links));
    }

    /// The calibration, head geometry, alignment and fit of a run.
    pub fn alignment_results(&mut self, r: &AlignmentResults) -> Result<()> {
        let stereo = StereoCalibration::from_rig(r.calibration, r.image_size, r.baseline_m)
            .map_err(|source| ReportError::Step { what: "report: calibration", source })?;
        self.stereo_calibration(&stereo);
        self.head(r)?;
        self.alignment(r);
        let rep = &r.calibration.report;
        self.table(
            "Fit",
            None,
            &["quantity", "value"],
            vec![
                vec![
                    "stereo matches (inliers / all)".into(),
                    format!("{} / {}", rep.stereo_inliers, rep.stereo_matches),
                ],
                vec!["stereo RMS (px)".into(), num(rep.stereo_rms_px, 3)],
                vec![
                    "bundle: points, observations, iterations".into(),
                    format!("{}, {}, {}", rep.bundle_points, rep.bundle_observations, rep.bundle_iterations),
                ],
                vec![
                    "bundle RMS reprojection, start → end (px)".into(),
                    format!("{} → {}", num(rep.initial_rms_px, 3), num(rep.final_rms_px, 3)),
                ],
                vec!["estimated image noise σ (px)".into(), num(rep.sigma_px, 3)],
            ],
        );
        Ok(())
    }

    /// The calibration sections alone (both `K`s with sigmas, the rig): for commands
    /// that calibrate without a head (e.g. a fixed rig).
    pub fn stereo_calibration(&mut self, c: &StereoCalibration) {
        let rows = |k: &headalign_geometry::camera::Intrinsics, s: &IntrinsicSigmas| {
            [
                pm(k.fx, s.fx, 2),
                pm(k.fy, s.fy, 2),
                pm(k.cx, s.cx, 2),
                pm(k.cy, s.cy, 2),
                pm(k.skew, s.skew, 3),
            ]
        };
        let (l, r) = (rows(&c.left, &c.sigmas[0]), rows(&c.right, &c.sigmas[1]));
        let names = ["fx", "fy", "cx", "cy", "skew"];
        let table: Vec<Vec<String>> =
            (0..5).map(|i| vec![names[i].into(), l[i].clone(), r[i].clone()]).collect();
        self.table(
            "Calibration",
            Some(&format!(
                "Intrinsics in pixels (± one standard deviation from the bundle adjustment's covariance), {} x {} images, {}.",
                c.image_size[0],
                c.image_size[1],
                lens_note(&c.distortion)
            )),
            &["parameter", "left camera", "right camera"],
            table,
        );
        let (unit, scale_note) = match c.unit {
            TranslationUnit::Metres => {
                ("m", " The translation is in metres (the baseline length was given).")
            }
            TranslationUnit::Baselines => (
                "baselines",
                " The translation is in baselines: self-calibration fixes no scale (give --baseline-m for metres).",
            ),
        };
        let rot = c.right_from_left.rotation;
        let axis = rot.axis().map_or([0.0, 0.0, 1.0], |a| [a.x, a.y, a.z]);
        let t = c.right_from_left.translation.vector;
        self.table(
            "Stereo rig",
            Some(&format!(
                "The pose that maps points in the left camera's frame to the right camera's.{scale_note}"
            )),
            &["quantity", "value"],
            vec![
                vec!["rotation angle (deg)".into(), num(rot.angle().to_degrees(), 4)],
                vec!["rotation axis".into(), vec3(axis, 4)],
                vec![format!("translation ({unit})"), vec3([t.x, t.y, t.z], 5)],
                vec![format!("baseline ({unit})"), num(t.norm(), 5)],
            ],
        );
    }

    fn head(&mut self, r: &AlignmentResults) -> Result<()> {
        let (pan, elev) = axes_of(&r.calibration.bundle.state).ok_or(ReportError::HeadAxes)?;
        let cov = &r.calibration.bundle.covariance;
        let dir_sigma =
            |i: usize| match (cov.sigma(&format!("axis{i}.dir0")), cov.sigma(&format!("axis{i}.dir1"))) {
                (Some(a), Some(b)) => Some(a.hypot(b).to_degrees()),
                _ => None,
            };
        let pt_sigma =
            |i: usize| match (cov.sigma(&format!("axis{i}.pt0")), cov.sigma(&format!("axis{i}.pt1"))) {
                (Some(a), Some(b)) => Some(a.hypot(b)),
                _ => None,
            };
        let mut rows = Vec::new();
        for (name, line, i) in [("pan", &pan, 0), ("elevation", &elev, 1)] {
            rows.push(vec![
                name.into(),
                vec3(line_dir(line), 4),
                dir_sigma(i).map_or("-".into(), |s| num(s, 3)),
                vec3(line_point(line), 3),
                pt_sigma(i).map_or("-".into(), |s| num(s, 4)),
            ]);
        }
        for (name, line) in [("verge left", &r.verge_axes.left), ("verge right", &r.verge_axes.right)] {
            rows.push(match line {
                Some(l) => {
                    vec![name.into(), vec3(line_dir(l), 4), "-".into(), vec3(line_point(l), 3), "-".into()]
                }
                None => {
                    vec![name.into(), "not measured (nominal)".into(), "-".into(), "-".into(), "-".into()]
                }
            });
        }
        self.table(
            "Head geometry",
            Some("Joint axes as lines in the left camera frame of the first view: unit direction, and the point closest to the origin in baselines; σ of the direction in degrees, of the point in baselines."),
            &["axis", "direction", "σ dir (deg)", "point (baselines)", "σ point"],
            rows,
        );
        Ok(())
    }

    fn alignment(&mut self, r: &AlignmentResults) {
        let a = r.solution.aligned_encoders;
        let s = r.sigmas;
        let sig = |j: Joint| match j {
            Joint::Elevation => Some(s.elevation_deg),
            Joint::VergeLeft => Some(s.verge_left_deg),
            Joint::VergeRight => Some(s.verge_right_deg),
            Joint::Pan => None,
        };
        let rows = Joint::ALL
            .iter()
            .map(|&j| {
                let note = if j == Joint::Pan { " (set by the pan stage)" } else { "" };
                vec![
                    format!("{}{note}", joint_name(j)),
                    num(r.reference.get(j), 3),
                    pm(a.get(j), sig(j), 3),
                    num(a.get(j) - r.reference.get(j), 3),
                ]
            })
            .collect();
        self.table(
            "Alignment",
            Some("Encoder readings (degrees) at which both cameras look parallel, horizontal and forward; ± one standard deviation."),
            &["joint", "first view", "aligned", "change"],
            rows,
        );
        let sol = r.solution;
        let fx = |p: [f64; 2]| format!("({}, {})", num(p[0], 2), num(p[1], 2));
        self.table(
            "What alignment leaves",
            None,
            &["quantity", "value"],
            vec![
                vec!["fixation point, left image (px)".into(), fx(sol.fixation_px_left)],
                vec!["fixation point, right image (px)".into(), fx(sol.fixation_px_right)],
                vec![
                    "right elevation error no joint can remove (deg)".into(),
                    num(sol.predicted_elev_err_r_deg, 4),
                ],
                vec![
                    "roll left / right (deg)".into(),
                    format!("{} / {}", num(sol.roll_left_deg, 3), num(sol.roll_right_deg, 3)),
                ],
                vec![
                    "vergence axes".into(),
                    if sol.verge_axes_measured { "measured".into() } else { "assumed nominal".into() },
                ],
            ],
        );
    }

    /// A section comparing errors against the simulator's truth: the keys of `after`
    /// (alignment errors in degrees, calibration errors in percent) with `before` beside
    /// them where it has the key; known keys first, in reading order, then any others.
    pub fn errors_vs_truth(&mut self, before: &Map<String, Value>, after: &Map<String, Value>) {
        const KNOWN: [(&str, &str); 10] = [
            ("verge_err_l_deg", "left vergence (deg)"),
            ("verge_err_r_deg", "right vergence (deg)"),
            ("elev_err_l_deg", "left elevation (deg)"),
            ("elev_err_r_deg", "right elevation (deg)"),
            ("elev_err_r_unavoidable_deg", "  of which no joint can remove (deg)"),
            ("elev_err_r_excess_deg", "  excess over that (deg)"),
            ("f_err_pct", "worst focal length (%)"),
            ("aspect_err_pct", "worst aspect ratio (%)"),
            ("pp_err_pct", "worst principal point (% of f)"),
            ("recon_err_pct", "reconstruction (%)"),
        ];
        let cell = |v: Option<&Value>| v.and_then(Value::as_f64).map_or("-".into(), |x| num(x, 4));
        let row = |k: &str, label: &str| {
            vec![label.to_string(), k.to_string(), cell(before.get(k)), cell(after.get(k))]
        };
        let mut rows: Vec<Vec<String>> =
            KNOWN.iter().filter(|(k, _)| after.contains_key(*k)).map(|(k, label)| row(k, label)).collect();
        rows.extend(after.keys().filter(|k| !KNOWN.iter().any(|(n, _)| n == k)).map(|k| row(k, k)));
        self.table(
            "Errors against the simulator's truth",
            Some("Simulated run: the simulator knows the true head. Alignment errors are the angles between each camera's optical axis and where it should point; calibration errors compare the estimated intrinsics with the true ones."),
            &["error", "key (JSON)", "before", "after"],
            rows,
        );
    }

    /// The page.
    pub fn to_html(&self) -> String {
        let mut h = String::new();
        let t = escape(&self.title);
        let _ = write!(
            h,
            "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<title>{t}</title>\n<style>{CSS}</style>\n</head>\n<body>\n<h1>{t}</h1>\n"
        );
        for p in &self.intro {
            let _ = writeln!(h, "<p>{}</p>", escape(p));
        }
        for s in &self.sections {
            let _ = writeln!(h, "<section>\n<h2>{}</h2>", escape(&s.heading));
            for b in &s.blocks {
                match b {
                    Block::Paragraph(p) => {
                        let _ = writeln!(h, "<p>{}</p>", escape(p));
                    }
                    Block::Table { header, rows } => {
                        h.push_str("<table>\n<thead><tr>");
                        for c in header {
                            let _ = write!(h, "<th>{}</th>", escape(c));
                        }
                        h.push_str("</tr></thead>\n<tbody>\n");
                        for row in rows {
                            h.push_str("<tr>");
                            for (i, c) in row.iter().enumerate() {
                                let class = if i == 0 { "" } else { " class=\"n\"" };
                                let _ = write!(h, "<td{class}>{}</td>", escape(c));
                            }
                            h.push_str("</tr>\n");
                        }
                        h.push_str("</tbody>\n</table>\n");
                    }
                    Block::Figure { src, caption } => {
                        let (src, caption) = (escape(src), escape(caption));
                        let _ = writeln!(
                            h,
                            "<figure><a href=\"{src}\"><img src=\"{src}\" alt=\"{caption}\"></a><figcaption>{caption}</figcaption></figure>"
                        );
                    }
                    Block::Links(links) => {
                        h.push_str("<ul class=\"links\">\n");
                        for (href, text) in links {
                            let _ = writeln!(h, "<li><a href=\"{}\">{}</a></li>", escape(href), escape(text));
                        }
                        h.push_str("</ul>\n");
                    }
                }
            }
            h.push_str("</section>\n");
        }
        let _ = write!(h, "<footer>headalign {}</footer>\n</body>\n</html>\n", env!("CARGO_PKG_VERSION"));
        h
    }

    /// Write the page to `path`.
    pub fn write(&self, path: &Path) -> Result<()> {
        std::fs::write(path, self.to_html())
            .map_err(|source| ReportError::Write { path: path.to_path_buf(), source })
    }
}

/// `align --out DIR`'s report: `DIR/report.html`, and with an image session
/// `DIR/figure6.png` (the first view annotated). `source` is the session read (named in
/// the report), `views` the tracked views, `recorded` the images if it was an image
/// session. Returns the files written.
pub fn write_align_report(
    dir: &Path,
    source: Option<&PathBuf>,
    views: &[View],
    recorded: Option<&[RecordedView]>,
    results: &AlignmentResults,
) -> Result<Vec<PathBuf>> {
    let mut written = Vec::new();
    let mut rep = HtmlReport::new("headalign align");
    let names: Vec<&str> = views.iter().map(|v| v.name.as_str()).collect();
    rep.intro(&format!(
        "Session {} ({}): {} views ({}).",
        source.map_or("-".into(), |p| p.display().to_string()),
        if recorded.is_some() { "recorded images, vision front end" } else { "observations" },
        views.len(),
        names.join(", ")
    ));
    rep.alignment_results(results)?;
    if let (Some(rec), Some(view0)) = (recorded.and_then(|r| r.first()), views.first()) {
        let path = dir.join("figure6.png");
        headalign::image_mode::figure6(&rec.images, view0, results.calibration, results.solution)
            .save(&path)?;
        written.push(path);
        rep.figures(
            "Annotated images",
            &[("figure6.png".into(), headalign::image_mode::FIGURE6_CAPTION.into())],
        );
    }
    let path = dir.join(REPORT_FILE);
    rep.write(&path)?;
    written.push(path);
    Ok(written)
}

fn joint_name(j: Joint) -> &'static str {
    match j {
        Joint::Pan => "pan",
        Joint::Elevation => "elevation",
        Joint::VergeLeft => "verge left",
        Joint::VergeRight => "verge right",
    }
}

const CSS: &str = "
body { font-family: system-ui, -apple-system, 'Segoe UI', Helvetica, Arial, sans-serif; max-width: 1100px;
       margin: 2em auto; padding: 0 1em; color: #222; line-height: 1.45; }
h1 { font-size: 1.6em; border-bottom: 2px solid #3a6ea5; padding-bottom: .2em; }
h2 { font-size: 1.2em; margin-top: 1.6em; color: #3a6ea5; }
table { border-collapse: collapse; margin: .5em 0 1em; }
th, td { border: 1px solid #ccd; padding: .25em .7em; }
th { background: #eef2f8; text-align: left; }
td.n { font-family: ui-monospace, 'DejaVu Sans Mono', Menlo, Consolas, monospace; text-align: right; white-space: nowrap; }
tbody tr:nth-child(even) { background: #f8f9fb; }
figure { margin: 1em 0; }
figure img { max-width: 100%; border: 1px solid #ccd; }
figcaption { font-size: .9em; color: #555; }
ul.links { columns: 3; font-size: .9em; }
footer { margin-top: 3em; font-size: .8em; color: #888; }
";

/// How the report names the lens model: none, or each camera's model (OpenCV's name where
/// it has one, `OpenCV plumb_bob`, else the lens table's short name) and coefficients.
fn lens_note(d: &[headalign_geometry::distortion::Distortion; 2]) -> String {
    if d.iter().all(|x| x.is_zero()) {
        return "no lens distortion".into();
    }
    let model = |x: &headalign_geometry::distortion::Distortion| {
        let names = x.kind.model().names();
        names.opencv.map_or_else(|| names.short.to_string(), |o| format!("OpenCV {o}"))
    };
    let one = |x: &headalign_geometry::distortion::Distortion| {
        let values: Vec<String> = x
            .kind
            .coefficient_names()
            .iter()
            .zip(x.coefficients())
            .map(|(n, v)| format!("{n} {v:.5}"))
            .collect();
        values.join(", ")
    };
    if d[0].kind == d[1].kind {
        format!("lens distortion ({}): left {}; right {}", model(&d[0]), one(&d[0]), one(&d[1]))
    } else {
        format!(
            "lens distortion: left ({}) {}; right ({}) {}",
            model(&d[0]),
            one(&d[0]),
            model(&d[1]),
            one(&d[1])
        )
    }
}

/// The text line of a scene check: `scene: kind (why)`.
pub fn scene_line(check: &SceneCheck) -> String {
    format!("scene: {} ({})", check.kind.name(), check.why)
}

/// The report files of a recorded image-mode run in its session folder `dir`: on the
/// planar route `aligned.png` and a `report.html` of its numbers; on the general route
/// `figure6.png`, `aligned.png`, `report.html` and, for a run with a lens model, the
/// calibration files in `dir/calibration/` (their paths returned). `json` is the run's
/// report (its title, and the errors against the truth when simulated).
pub fn write_session_report(
    dir: &Path,
    run: &ImageRun,
    route: &RouteOutcome,
    json: &Value,
) -> Result<Option<Vec<PathBuf>>> {
    let o = match route {
        RouteOutcome::General(o, _) => o,
        RouteOutcome::Planar(p) => {
            aligned_image(dir, run)?;
            write_planar_report(dir, &info_title(json), run, p, json)?;
            return Ok(None);
        }
    };
    annotate(dir, run, o)?;
    write_report(dir, &info_title(json), run, o, json)?;
    if o.calibration.report.lens.is_none() {
        return Ok(None);
    }
    Ok(Some(write_calibration_files(dir, run, o)?))
}

/// `figure6.png` ([`image_mode::figure6`]) and `aligned.png` ([`aligned_image`]).
fn annotate(dir: &Path, run: &ImageRun, outcome: &VergeTiltOutcome) -> Result<()> {
    let images = &run.images;
    let (Some(first), Some(view0)) = (images.first(), run.run.views.first()) else { return Ok(()) };
    image_mode::figure6(first, view0, &outcome.calibration, &outcome.solution)
        .save(&dir.join("figure6.png"))?;
    aligned_image(dir, run)
}

/// `aligned.png`: the last check view with the image centres marked.
fn aligned_image(dir: &Path, run: &ImageRun) -> Result<()> {
    if let Some(last) = run.images.last() {
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

/// The report's title line from the run's JSON (simulated or not).
fn info_title(json: &Value) -> String {
    if json.get("truth").is_some() {
        "headalign demo --images (simulated head)".into()
    } else {
        "headalign: verge/tilt alignment on images".into()
    }
}

/// `DIR/report.html`: the numbers, the errors against the truth when the run was
/// simulated (the JSON's `before` and `errors` members), the annotated images and links
/// to every captured view of the session.
fn write_report(
    dir: &Path,
    title: &str,
    run: &ImageRun,
    outcome: &VergeTiltOutcome,
    json: &Value,
) -> Result<()> {
    let (image_size, mut rep) = report_with_intro(dir, title, run);
    rep.alignment_results(&AlignmentResults {
        calibration: &outcome.calibration,
        image_size,
        baseline_m: None,
        verge_axes: &outcome.verge_axes,
        reference: outcome.calibration.reference_encoders,
        solution: &outcome.solution,
        sigmas: &outcome.sigmas,
    })?;
    if let (Some(Value::Object(before)), Some(Value::Object(errors))) =
        (json.get("before"), json.get("errors"))
    {
        rep.errors_vs_truth(before, errors);
    }
    rep.figures(
        "Annotated images",
        &[
            ("figure6.png".into(), image_mode::FIGURE6_CAPTION.into()),
            (
                "aligned.png".into(),
                "aligned.png: the last view, after alignment, with the image centres marked (magenta)."
                    .into(),
            ),
        ],
    );
    rep.links("Captured views", VIEW_LINKS_NOTE, view_links(dir));
    rep.write(&dir.join(REPORT_FILE))
}

/// The note above the captured views' links in `report.html`.
const VIEW_LINKS_NOTE: &str =
    "Every captured view (PNG and view.json in each folder): headalign replay DIR re-runs them.";

/// Links to both images of every view folder of the session `dir`, in order.
fn view_links(dir: &Path) -> Vec<(String, String)> {
    let mut folders: Vec<String> = std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .filter_map(std::result::Result::ok)
                .filter(|e| e.path().join("view.json").is_file())
                .filter_map(|e| e.file_name().to_str().map(str::to_string))
                .collect()
        })
        .unwrap_or_default();
    folders.sort();
    folders
        .iter()
        .flat_map(|f| ["left", "right"].map(|side| (format!("{f}/{side}.png"), format!("{f} {side}"))))
        .collect()
}

/// The session report's page with its introduction (image size, views, folder), and the
/// image size.
fn report_with_intro(dir: &Path, title: &str, run: &ImageRun) -> ([u32; 2], HtmlReport) {
    let image_size = run.images.first().map_or([0, 0], StereoImages::image_size);
    let mut rep = HtmlReport::new(title);
    rep.intro(&format!(
        "{} x {} images, vision front end (verging, FAST+BRIEF features, matching); {} verge/tilt views captured; session folder {}.",
        image_size[0],
        image_size[1],
        run.run.views.len(),
        dir.display()
    ));
    (image_size, rep)
}

/// `DIR/report.html` of a planar-route run: its numbers ([`planar_sections`]),
/// the errors against the truth when simulated, `aligned.png` and the captured views.
fn write_planar_report(
    dir: &Path,
    title: &str,
    run: &ImageRun,
    outcome: &headalign::procedure::PlanarOutcome,
    json: &Value,
) -> Result<()> {
    let (_, mut rep) = report_with_intro(dir, title, run);
    planar_sections(&mut rep, outcome);
    if let (Some(Value::Object(before)), Some(Value::Object(errors))) =
        (json.get("before"), json.get("errors"))
    {
        rep.errors_vs_truth(before, errors);
    }
    rep.figures(
        "Annotated images",
        &[(
            "aligned.png".into(),
            "aligned.png: the check view after alignment, with the image centres marked (magenta).".into(),
        )],
    );
    rep.links("Captured views", VIEW_LINKS_NOTE, view_links(dir));
    rep.write(&dir.join(REPORT_FILE))
}

/// `DIR/calibration/`: the calibration files `calibrate --out` and `align --out` write
/// (OpenCV YAML, ROS `camera_info`, Kalibr camchain, JSON; `StereoCalibration::write_all`)
/// with the estimated lenses; written by a run with a lens model (`--lens`), so that the
/// pinhole runs' sessions hold what they always held. The paths written.
fn write_calibration_files(dir: &Path, run: &ImageRun, outcome: &VergeTiltOutcome) -> Result<Vec<PathBuf>> {
    let image_size = run.images.first().map_or([0, 0], StereoImages::image_size);
    let stereo = headalign::calibration::StereoCalibration::from_rig(&outcome.calibration, image_size, None)
        .map_err(|source| ReportError::Step { what: "calibration files", source })?;
    Ok(stereo.write_all(&dir.join("calibration"))?)
}

/// The planar route's sections of a `report.html`: the scene and route, each camera's
/// intrinsics, the aligned readings, the check after the move and what is undetermined.
fn planar_sections(rep: &mut HtmlReport, out: &PlanarOutcome) {
    let cal = &out.calibration;
    rep.intro(&scene_line(&cal.scene));
    rep.intro("Planar route (paper section 3.3): each camera from its own plane homographies; the robot stages are skipped (they need the 3D reconstruction a plane does not give).");
    let pm = |v: f64, s: Option<f64>| format!("{v:.2} ± {:.2}", s.unwrap_or(f64::NAN));
    let rows = [("left", &cal.left), ("right", &cal.right)]
        .iter()
        .map(|(name, c)| {
            let k = &c.intrinsics;
            vec![
                name.to_string(),
                pm(k.fx, c.sigma("fx")),
                pm(k.fy, c.sigma("fy")),
                pm(k.cx, c.sigma("cx")),
                pm(k.cy, c.sigma("cy")),
                format!("{:.3}", c.rms_px),
                c.points.to_string(),
            ]
        })
        .collect();
    rep.table(
        "Intrinsics",
        Some("Pixels, 1-sigma from the planar model's covariance."),
        &["camera", "fx", "fy", "cx", "cy", "rms (px)", "points"],
        rows,
    );
    let (a, s) = (out.solution.aligned_encoders, out.sigmas);
    let rows = [
        ("elevation", a.elevation, s.elevation_deg),
        ("verge_left", a.verge_left, s.verge_left_deg),
        ("verge_right", a.verge_right, s.verge_right_deg),
    ]
    .iter()
    .map(|(n, v, s)| vec![n.to_string(), format!("{v:.4}"), format!("{s:.4}")])
    .collect();
    rep.table("Aligned readings", None, &["reading", "value (deg)", "sigma (deg)"], rows);
    if let Some(c) = out.checks.last() {
        let m = c.measured;
        let rows = [
            ("verge left", m.verge_err_l_deg),
            ("verge right", m.verge_err_r_deg),
            ("elevation left", m.elev_err_l_deg),
            ("elevation right", m.elev_err_r_deg),
        ]
        .iter()
        .map(|(n, v)| vec![n.to_string(), format!("{v:+.4}")])
        .collect();
        let note = format!(
            "Each camera against its own estimated axes; unmodelled rotation left {:.4} deg, right {:.4} deg. Not checked: {}.",
            c.left.unmodelled_rotation_deg,
            c.right.unmodelled_rotation_deg,
            c.unchecked.join("; ")
        );
        rep.table("Check after the move", Some(&note), &["error", "measured (deg)"], rows);
    } else if let Some(why) = &out.check_failure {
        rep.table("Check after the move", Some(&format!("Not made: {why}.")), &["error"], Vec::new());
    }
    let rows = cal.undetermined.iter().map(|u| vec![u.clone()]).collect();
    rep.table(
        "Undetermined",
        Some("What a plane cannot give: reported, never a number."),
        &["quantity"],
        rows,
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_is_escaped_and_numbers_formatted() {
        assert_eq!(escape("<a href=\"x\">&'"), "&lt;a href=&quot;x&quot;&gt;&amp;&#39;");
        assert_eq!(pm(700.1234, Some(0.5), 2), "700.12 ± 0.500");
        assert_eq!(pm(1.0, Some(f64::NAN), 1), "1.0");
        assert_eq!(num(f64::INFINITY, 2), "-");
        let mut r = HtmlReport::new("t <script>");
        r.intro("view 'a&b'");
        r.figures("F", &[("x\".png".into(), "<cap>".into())]);
        r.table("T", None, &["k", "v"], vec![vec!["<k>".into(), "1.5".into()]]);
        let h = r.to_html();
        assert!(!h.contains("<script>") && h.contains("t &lt;script&gt;"));
        assert!(h.contains("view &#39;a&amp;b&#39;") && h.contains("src=\"x&quot;.png\""));
        assert!(h.contains("<td>&lt;k&gt;</td><td class=\"n\">1.5</td>"));
        assert!(h.starts_with("<!DOCTYPE html>") && h.trim_end().ends_with("</html>"));
    }
}
