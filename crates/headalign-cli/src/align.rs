//! `headalign align`: the estimation on an observation session (`--observations`) or on
//! the verge/tilt views of a recorded session or recording (`--images`, tracked by the
//! front end): calibration, axes and aligned readings on the route the scene allows
//! ([`headalign::procedure::align_session_detecting`]), printed, as JSON, or written as
//! calibration files (`--out`).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use headalign::alignment::NOMINAL_VERGE_WARNING;
use headalign::calibrate::image_noise::MeasuredVariances;
use headalign::observations::View;
use headalign::procedure::{
    AlignmentSigmas, PlanarSessionAlignment, SessionAlignment, SessionRoute, align_session_detecting,
    session_model_fit,
};
use headalign::verge_tilt::{EstimationOptions, ModelFit, RigCalibration, axes_of};
use headalign_geometry::bootstrap::BootstrapOptions;
use headalign_geometry::camera::Intrinsics;
use headalign_geometry::so3::Line;
use headalign_io::observations::read_session;
use headalign_io::report::{html as report_html, schema, write_align_files};
use headalign_io::session::RecordedView;
use headalign_platform::Encoders;
use serde_json::json;

use crate::{flags, images, recording};

#[derive(Args)]
pub struct AlignArgs {
    /// Observation session (JSON, format headalign-observations/1).
    #[arg(long, required_unless_present = "images", conflicts_with = "images")]
    observations: Option<PathBuf>,
    /// A recorded session instead (as `demo`, `run` and `simulate --images` write), or a
    /// ROS 2 bag of a head run; its verge/tilt views are tracked by the image front end.
    // `session::estimation_views`: verging, probes and robot stages are skipped; a
    // point-mode session's recorded points are used as they are. A bag's views are its
    // still views from the verge/tilt start (`recording::align_views`).
    #[arg(long)]
    images: Option<PathBuf>,
    /// How a recording is read (bags, EuRoC folders).
    #[command(flatten)]
    recording: recording::RecordingArgs,
    /// Print one JSON object instead of the table.
    #[arg(long)]
    json: bool,
    /// Write the calibration files here (OpenCV, ROS, Kalibr, head axes, aligned
    /// readings) and report.html.
    // `StereoCalibration::write_all`, then head.json, alignment.json and
    // `report_html::write_align_report` (figure6.png with --images).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Baseline length in metres, to write the rig translation in metres (otherwise in
    /// baselines).
    #[arg(long)]
    baseline_m: Option<f64>,
    /// Widen the sigmas to a bootstrap over point tracks with this many replicates (off
    /// by default).
    #[arg(long, value_parser = headalign_eval::parse_replicates)]
    bootstrap: Option<BootstrapOptions>,
    /// The lens model estimated (default: a recorded session's own; auto for images,
    /// pinhole for observations).
    #[arg(long, value_parser = flags::parse_lens)]
    lens: Option<headalign::calibrate::LensChoice>,
    /// Lens coefficients estimated: `radial` (k1 k2), `4` or `5` (as `calibrate --lens-terms`).
    #[arg(long, value_parser = flags::parse_terms)]
    lens_terms: Option<headalign_geometry::distortion::DistortionTerms>,
}

impl AlignArgs {
    /// The lens of the estimate: the flags over a recorded session's (`session.json`'s
    /// `lens`; the pinhole for sessions without one and for observation files; `auto` for
    /// a recording's images).
    fn lens(&self) -> Result<images::LensArgs> {
        let recorded = match &self.images {
            Some(dir) if dir.join("session.json").is_file() => {
                images::LensArgs::of_session(&headalign_io::session::read_session_info(dir)?)?
            }
            Some(_) => images::LensArgs::default(),
            None => images::LensArgs::pinhole(),
        };
        let lens = images::LensArgs { lens: self.lens, lens_terms: self.lens_terms }.over(recorded);
        lens.validate()?;
        Ok(lens)
    }
}

pub fn sigma(calib: &RigCalibration, name: &str) -> Option<f64> {
    calib.bundle.covariance.sigma(name)
}

pub fn run(args: &AlignArgs) -> Result<()> {
    let lens = args.lens()?;
    let (views, recorded, measured) = read_align_views(args)?;
    // Errors past reading name the session too.
    let session = args
        .observations
        .as_ref()
        .or(args.images.as_ref())
        .map_or(String::new(), |p| p.display().to_string());
    let (mut a, scene) = match estimate_alignment(&views, args.bootstrap, lens, &session)? {
        AlignRoute::General(a, scene) => (a, scene),
        AlignRoute::Planar(p, seconds) => return align_planar(args, &p, seconds),
    };
    a.fit = measured.map(|m| session_model_fit(&a.alignment.calibration, &views, &m));
    let (pan, elev) = axes_of(&a.alignment.calibration.bundle.state).context("axes")?;
    let axes = schema::head_axes_json(&a.alignment.calibration, &pan, &elev, &a.alignment.verge_axes);
    let mut written = Vec::new();
    if let Some(dir) = &args.out {
        let source = args.observations.as_ref().or(args.images.as_ref());
        let (rec, baseline) = (recorded.as_deref(), args.baseline_m);
        written = write_align_files(dir, &a.alignment, &views, rec, &axes, baseline, source)?;
    }
    if args.json {
        let files = written.iter().map(|p| p.display().to_string()).collect();
        let (fit, warnings) = (a.fit.as_ref(), align_warnings(&a));
        let report =
            schema::AlignReport::general(&a.alignment, &scene, axes, fit, warnings, files, a.seconds)?;
        say!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    say!("{}", report_html::scene_line(&scene));
    print_alignment(&a, &pan, &elev, &written);
    Ok(())
}

/// `align` on a planar or far scene: the planar route's report (JSON or lines); with
/// `--out`, `alignment.json` only (the calibration files and `head.json` need the rig's
/// translation and the axes' positions, which a plane leaves undetermined).
fn align_planar(args: &AlignArgs, p: &PlanarSessionAlignment, seconds: f64) -> Result<()> {
    let cal = &p.calibration;
    let mut written = Vec::new();
    if let Some(dir) = &args.out {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        let path = dir.join("alignment.json");
        let value = schema::alignment_file("planar", p.reference, &p.solution, p.sigmas, &cal.undetermined);
        value.write(&path)?;
        written.push(path);
    }
    let not_written = "calibration files and head.json: not written (the rig's translation and the axes' positions are undetermined on a plane)";
    if args.json {
        let mut warnings = vec![not_written.to_string()];
        if !p.solution.verge_axes_measured {
            warnings.push(NOMINAL_VERGE_WARNING.to_string());
        }
        let files = written.iter().map(|p| p.display().to_string()).collect();
        let report = schema::AlignReport::planar(p, warnings, files, seconds)?;
        say!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    say!("{}", report_html::scene_line(&cal.scene));
    say!("planar route (paper section 3.3): each camera from its own plane homographies");
    for (name, c) in [("left ", &cal.left), ("right", &cal.right)] {
        let k = &c.intrinsics;
        say!(
            "{name} K = [[{:.2}, 0, {:.2}], [0, {:.2}, {:.2}], [0, 0, 1]]  rms {:.3} px, {} points",
            k.fx,
            k.cx,
            k.fy,
            k.cy,
            c.rms_px,
            c.points
        );
    }
    say!("undetermined: {}", cal.undetermined.join("; "));
    let (e, sig) = (p.solution.aligned_encoders, p.sigmas);
    say!("{}", aligned_readings_line(&e, &sig));
    if !p.solution.verge_axes_measured {
        say!("warning: {NOMINAL_VERGE_WARNING}");
    }
    say!("{not_written}");
    for p in &written {
        say!("wrote {}", p.display());
    }
    Ok(())
}

/// The views of `align`'s session: an observation session, or the verge/tilt views of a
/// recorded image session tracked by the front end (then also the recorded views).
/// The views `align` estimates from, the recorded views they came from (image input) and
/// the front end's localisation noise of each view by name (image sessions).
type AlignViews = (Vec<View>, Option<Vec<RecordedView>>, Option<MeasuredVariances>);

fn read_align_views(args: &AlignArgs) -> Result<AlignViews> {
    match (&args.observations, &args.images) {
        (Some(file), _) => Ok((read_session(file)?, None, None)),
        (None, Some(dir)) => {
            use headalign_io::session::{estimation_views, read_image_session, read_point_session};
            // The verge/tilt views (verging captures and robot stages are recorded too, but
            // the rig is not the same there).
            let recorded = headalign_io::recordings::detect(dir).is_some();
            if !recorded {
                args.recording.only_for_recordings(dir, "an image or point session", false)?;
            }
            if headalign_io::session::is_point_session(dir) {
                let r = estimation_views(read_point_session(dir)?, |v| v.stage.as_deref());
                return Ok((r.into_iter().map(|v| v.view).collect(), None, None));
            }
            let r = if recorded {
                recording::align_views(dir, &args.recording)?
            } else {
                estimation_views(read_image_session(dir)?, |v| v.stage.as_deref())
            };
            let (views, tracking) = headalign_io::session::track_session_reporting(
                &r,
                &headalign::tracking::FrontEndOptions::default(),
            )?;
            let measured =
                views.iter().zip(tracking).map(|(v, t)| (v.name.clone(), t.localisation)).collect();
            Ok((views, Some(r), Some(measured)))
        }
        (None, None) => bail!("give --observations FILE or --images DIR"),
    }
}

/// What `align` estimated from a session.
struct AlignEstimate {
    /// The model-fit checks (image sessions only).
    fit: Option<ModelFit>,
    /// The calibration, the alignment and their sigmas.
    alignment: SessionAlignment,
    /// Wall time of the estimation, seconds.
    seconds: f64,
}

/// What `align` estimated, by route.
enum AlignRoute {
    /// The general route and the scene check that chose it.
    General(Box<AlignEstimate>, headalign::facing_plane::SceneCheck),
    /// The planar route (a planar or far scene) and its wall time, seconds.
    Planar(Box<PlanarSessionAlignment>, f64),
}

/// [`align_session_detecting`] on `views` with the estimation options of `align`; errors
/// name `session`.
fn estimate_alignment(
    views: &[View],
    bootstrap: Option<BootstrapOptions>,
    lens: images::LensArgs,
    session: &str,
) -> Result<AlignRoute> {
    let t0 = Instant::now();
    let estimation = lens.apply(EstimationOptions { bootstrap, ..EstimationOptions::default() });
    let route = align_session_detecting(views, &estimation).with_context(|| format!("session {session}"))?;
    let seconds = t0.elapsed().as_secs_f64();
    let (a, scene) = match route {
        SessionRoute::General(a, scene) => (a, scene),
        SessionRoute::Planar(p) => return Ok(AlignRoute::Planar(p, seconds)),
    };
    Ok(AlignRoute::General(Box::new(AlignEstimate { fit: None, alignment: *a, seconds }), scene))
}

/// `align`'s warnings: the model's misfit to the images, nominal vergence axes.
fn align_warnings(a: &AlignEstimate) -> Vec<String> {
    let mut w: Vec<String> = a.fit.iter().flat_map(|f| f.warnings.clone()).collect();
    if !a.alignment.solution.verge_axes_measured {
        w.push(NOMINAL_VERGE_WARNING.to_string());
    }
    w
}

/// `align`'s summary: intrinsics, fixation point, axes, aligned readings, files written.
fn print_alignment(a: &AlignEstimate, pan: &Line, elev: &Line, written: &[PathBuf]) {
    let (calib, solution, sig) = (&a.alignment.calibration, &a.alignment.solution, &a.alignment.sigmas);
    let state = &calib.bundle.state;
    let show_k = |name: &str, k: &Intrinsics| {
        say!(
            "{name} K = [[{:.2}, {:.3}, {:.2}], [0, {:.2}, {:.2}], [0, 0, 1]]",
            k.fx,
            k.skew,
            k.cx,
            k.fy,
            k.cy
        );
    };
    show_k("left ", &state.left);
    show_k("right", &state.right);
    if let Some(line) = schema::lens_json(calib).and_then(|l| images::lens_line(&json!({ "lens": l }))) {
        say!("{line}");
    }
    let (fl, fr) = (a.alignment.fixation_sigmas.left_px, a.alignment.fixation_sigmas.right_px);
    say!(
        "fixation point: left ({:.2}, {:.2}) +- ({:.2}, {:.2}) px, right ({:.2}, {:.2}) +- ({:.2}, {:.2}) px",
        solution.fixation_px_left[0],
        solution.fixation_px_left[1],
        fl[0],
        fl[1],
        solution.fixation_px_right[0],
        solution.fixation_px_right[1],
        fr[0],
        fr[1]
    );
    let d = |l: &Line| format!("({:+.4}, {:+.4}, {:+.4})", l.direction.x, l.direction.y, l.direction.z);
    say!("pan axis direction {}   elevation axis direction {}", d(pan), d(elev));
    let e = solution.aligned_encoders;
    say!("{}", aligned_readings_line(&e, sig));
    if let Some(b) = &calib.report.bootstrap {
        say!("{}", bootstrap_line(b));
    }
    for w in align_warnings(a) {
        say!("warning: {w}");
    }
    for p in written {
        say!("wrote {}", p.display());
    }
}

/// One line on what the bootstrap of the covariance did.
pub fn bootstrap_line(b: &headalign::verge_tilt::BootstrapReport) -> String {
    format!(
        "bootstrap: {} replicates ({} failed), sigmas widened by up to x{:.3} (median bootstrap / linearised {:.3})",
        b.replicates, b.failed, b.max_widening, b.median_ratio
    )
}

/// `aligned readings: ...` with each reading's sigma, degrees.
fn aligned_readings_line(e: &Encoders, sig: &AlignmentSigmas) -> String {
    format!(
        "aligned readings: elevation {:.3} +- {:.3} deg, verge_left {:.3} +- {:.3} deg, verge_right {:.3} +- {:.3} deg",
        e.elevation, sig.elevation_deg, e.verge_left, sig.verge_left_deg, e.verge_right, sig.verge_right_deg
    )
}
