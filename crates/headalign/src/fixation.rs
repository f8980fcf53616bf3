//! Image-driven head control with no calibration: verging both cameras onto the same part
//! of the scene (paper section 6) and fixating a target from zero prior knowledge (paper
//! section 5).
//!
//! **Verging** ([`verge_to_common_view`]): the right image is registered against the left
//! by heavily subsampled coarse-to-fine correlation (the shift of the whole image); the
//! right vergence turns by `atan(shift / f)` with a rough `f` (the image width) until the
//! shift is small. Only the overlap matters, so the search stops at a coarse pyramid level.
//!
//! **Fixation** ([`fixate`]): bring a target pixel to the image centre with the joints that
//! move one camera (its vergence horizontally, the elevation vertically), knowing nothing
//! of `K`. Each move turns by `atan((u - u0) / alpha_u)`, `atan((v - v0) / alpha_v)` with
//! overestimated `alpha` (so the first move falls short instead of overshooting); the
//! point's true new position is measured by pyramid correlation, and `alpha` is re-solved
//! exactly from the pinhole model `u - u0 = alpha tan(theta)`:
//! `t alpha^2 - (x - y) alpha + x y t = 0` with `x, y` the offsets before and after and
//! `t = tan(delta)`. Every move's image motion is measured as a plane homography through a
//! 16 x 12 grid of correlated patches over the whole image (found first around the
//! whole-image shift, then again with templates warped by the first fit). A target in view
//! is located by its own patch, taken in the image where it was first seen and warped by
//! the chained motion so that it looks as it should in the new image: a 20-30 deg move
//! stretches an edge patch by 10-20 %, which biased a plain template's peak by 0.5-1.2 px.
//! A target outside the image is approached through a visible point near the edge in its
//! direction (its move updates `alpha`); the target itself is carried from image to image
//! by the homography plus the local parallax (plane plus parallax, Hartley & Zisserman
//! 13.2: each patch's residual points to the epipole, scaled by its relative inverse depth;
//! the target takes the median of its 12 nearest patches) until it is inside, then
//! followed by its own patch to the centre.
//!
//! Units: pixels for positions and tolerances, degrees for encoder moves, `alpha` in
//! pixels (its sign absorbs the joint's direction: a move that goes the wrong way is
//! detected and corrected at the next step).
//! Pitfalls: the vertical and horizontal joints are treated as independent (true for
//! small angles; the loop absorbs the coupling). A target that starts outside the image
//! is a ray whose depth nobody has seen: the offset axes translate the camera (about
//! 1 cm per 10 deg here), so its image depends on that depth, which is taken from the
//! surfaces nearest it in the image; a target on another surface than its visible
//! neighbours (a ceiling beyond a wall's edge) keeps that depth error, measured up to
//! 0.9 px on the simulated head (0.1 px with the axes through the optical centre). For the
//! vanishing point of alignment use the calibrated solution of [`crate::alignment`]. A
//! textureless patch cannot be located (an error naming it); the elevation joint is
//! shared, so fixating with the right camera moves the left one too.

use headalign_geometry::homography2d::{Homography2, Homography2Estimator};
use headalign_geometry::ransac::{RansacOptions, ransac};
use headalign_platform::{Encoders, GrayImage, ImagingHead, Joint};
use headalign_vision::{
    PatchSearchOptions, Pyramid, RegistrationOptions, locate_patch_in_pyramids, register_translation,
};
use nalgebra::{Matrix3, Point2, Vector3};
use serde::Serialize;

use crate::AlignError;

/// Which camera a fixation moves.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Camera {
    /// Left camera: left vergence and elevation.
    Left,
    /// Right camera: right vergence and elevation.
    Right,
}

impl Camera {
    fn horizontal_joint(self) -> Joint {
        match self {
            Camera::Left => Joint::VergeLeft,
            Camera::Right => Joint::VergeRight,
        }
    }

    fn image(self, images: &headalign_platform::StereoImages) -> &GrayImage {
        match self {
            Camera::Left => &images.left,
            Camera::Right => &images.right,
        }
    }
}

fn vision(step: &str) -> impl Fn(headalign_vision::VisionError) -> AlignError + '_ {
    move |e| AlignError::Images(format!("{step}: {e}"))
}

fn centre_of(size: [u32; 2]) -> [f64; 2] {
    [(f64::from(size[0]) - 1.0) / 2.0, (f64::from(size[1]) - 1.0) / 2.0]
}

/// Options of [`verge_to_common_view`].
#[derive(Debug, Clone)]
pub struct VergingOptions {
    /// Rough focal length in pixels to turn shifts into angles (default: the image width).
    pub focal_guess_px: Option<f64>,
    /// Done when the horizontal shift is below this fraction of the image width
    /// (default 0.1).
    pub done_fraction: f64,
    /// Most vergence moves (default 6).
    pub max_moves: usize,
    /// The registration (default: [`RegistrationOptions::verging`], heavily subsampled).
    pub registration: RegistrationOptions,
}

impl Default for VergingOptions {
    fn default() -> Self {
        Self {
            focal_guess_px: None,
            done_fraction: 0.1,
            max_moves: 6,
            registration: RegistrationOptions::verging(),
        }
    }
}

/// One verging step.
#[derive(Debug, Clone, Serialize)]
pub struct VergeStep {
    /// Shift of the right image against the left (content at `x` in the left appears at
    /// `x + shift` in the right), pixels.
    pub shift_px: [f64; 2],
    /// Correlation peak.
    pub score: f64,
    /// Right vergence move made after this measurement, degrees (0 for the last).
    pub verge_right_move_deg: f64,
}

/// What [`verge_to_common_view`] did.
#[derive(Debug, Clone, Serialize)]
pub struct VergingReport {
    /// Each measurement and move.
    pub steps: Vec<VergeStep>,
    /// Encoder readings at the end.
    pub encoders: Encoders,
    /// Final horizontal overlap of the two images, fraction of the width.
    pub overlap_fraction: f64,
}

/// Verge the right camera until both images show the same part of the scene (paper
/// section 6). Convention: a positive right-vergence move turns the camera right (image
/// content moves left); if a move increases the shift, the direction is reversed.
pub fn verge_to_common_view<H: ImagingHead>(
    head: &mut H,
    options: &VergingOptions,
) -> Result<VergingReport, AlignError> {
    options.registration.validate().map_err(vision("verging options"))?;
    if !(options.done_fraction > 0.0 && options.done_fraction < 1.0) || options.max_moves == 0 {
        return Err(AlignError::InvalidOption("verging: done_fraction in (0, 1) and max_moves >= 1".into()));
    }
    let width = f64::from(head.image_size()[0]);
    let f = options.focal_guess_px.unwrap_or(width);
    if !(f.is_finite() && f > 0.0) {
        return Err(AlignError::InvalidOption(format!("verging focal guess must be positive, got {f}")));
    }
    let mut direction = 1.0;
    let mut steps: Vec<VergeStep> = Vec::new();
    loop {
        let images = head.capture_images()?;
        let reg = register_translation(&images.left, &images.right, &options.registration)
            .map_err(vision("verging registration of the right image against the left"))?;
        let shift = reg.shift;
        if let Some(prev) = steps.last()
            && shift[0].abs() > prev.shift_px[0].abs()
        {
            direction = -direction;
        }
        let done = shift[0].abs() <= options.done_fraction * width;
        if done || steps.len() >= options.max_moves {
            steps.push(VergeStep { shift_px: shift, score: reg.score, verge_right_move_deg: 0.0 });
            let encoders = head.read_encoders()?;
            if !done {
                return Err(AlignError::Images(format!(
                    "verging did not converge in {} moves: the right image is still shifted {:.0} px against the left",
                    options.max_moves, shift[0]
                )));
            }
            return Ok(VergingReport { steps, encoders, overlap_fraction: 1.0 - shift[0].abs() / width });
        }
        let delta = direction * (shift[0] / f).atan().to_degrees();
        steps.push(VergeStep { shift_px: shift, score: reg.score, verge_right_move_deg: delta });
        let e = head.read_encoders()?;
        head.move_to(&e.moved(Joint::VergeRight, delta))?;
    }
}

/// Options of [`fixate`].
#[derive(Debug, Clone)]
pub struct FixationOptions {
    /// Initial focal estimate, pixels (default: twice the image width, an overestimate as
    /// the paper recommends: moves then fall short and never overshoot).
    pub focal_guess_px: Option<f64>,
    /// Done when the target is this close to the centre, pixels (default 0.3).
    pub tolerance_px: f64,
    /// Most moves (default 20).
    pub max_moves: usize,
    /// A target counts as visible (and is located by its own patch) when it is at least
    /// this far inside the image, pixels (default 48; patches need room).
    pub edge_margin_px: f64,
    /// Patch search for the motion grid around the place the whole-image shift predicts,
    /// and for the aimed point (default: 25x25 templates, 24 px radius: the shift is
    /// measured, only parallax and rotation are left). The target's own patch is searched
    /// within 6 px of where the measured motion puts it.
    pub patch: PatchSearchOptions,
}

impl Default for FixationOptions {
    fn default() -> Self {
        Self {
            focal_guess_px: None,
            tolerance_px: 0.3,
            max_moves: 20,
            edge_margin_px: 48.0,
            patch: PatchSearchOptions { half_size: 12, search_radius: 24.0, ..PatchSearchOptions::default() },
        }
    }
}

/// One fixation move.
#[derive(Debug, Clone, Serialize)]
pub struct FixationStep {
    /// Encoder readings before the move.
    pub encoders: Encoders,
    /// Where the target was before the move, pixels (may be outside the image).
    pub target_px: [f64; 2],
    /// The point brought to the centre by this move (the target, or an edge point in its
    /// direction), pixels.
    pub aim_px: [f64; 2],
    /// Joint moves (horizontal, elevation), degrees.
    pub move_deg: [f64; 2],
    /// Focal estimates (horizontal, vertical) used for the move, pixels (signed).
    pub alpha_px: [f64; 2],
}

/// What [`fixate`] did.
#[derive(Debug, Clone, Serialize)]
pub struct FixationReport {
    /// Each move.
    pub steps: Vec<FixationStep>,
    /// Final target position (measured), pixels.
    pub final_target_px: [f64; 2],
    /// Distance of the final target from the image centre, pixels.
    pub final_error_px: f64,
    /// The image centre, pixels.
    pub centre_px: [f64; 2],
    /// Final focal estimates (horizontal, vertical), pixels (signed by joint direction).
    pub alpha_px: [f64; 2],
    /// Encoder readings at the end.
    pub encoders: Encoders,
}

/// The exact `alpha` from one move: offsets `x` before and `y` after a rotation by
/// `delta` (radians) about an axis through the centre; `None` if the move told nothing.
pub fn solve_alpha(x: f64, y: f64, delta: f64) -> Option<f64> {
    let t = delta.tan();
    if !(t.is_finite() && t.abs() > 1e-9) || (x - y).abs() < 1e-6 {
        return None;
    }
    let small = (x - y) / t;
    let disc = (x - y).powi(2) - 4.0 * t * t * x * y;
    if disc < 0.0 {
        return Some(small);
    }
    let roots = [((x - y) + disc.sqrt()) / (2.0 * t), ((x - y) - disc.sqrt()) / (2.0 * t)];
    roots.into_iter().filter(|a| a.is_finite()).min_by(|a, b| (a - small).abs().total_cmp(&(b - small).abs()))
}

fn inside(p: [f64; 2], size: [u32; 2], margin: f64) -> bool {
    p[0] >= margin
        && p[1] >= margin
        && p[0] <= f64::from(size[0]) - 1.0 - margin
        && p[1] <= f64::from(size[1]) - 1.0 - margin
}

/// Grid of patches (columns, rows) whose correlation measures the image motion of a move.
const MOTION_GRID: [u32; 2] = [16, 12];

/// `G x`, dehomogenised; `None` at infinity.
fn apply(g: &Matrix3<f64>, x: [f64; 2]) -> Option<[f64; 2]> {
    let p = g * Vector3::new(x[0], x[1], 1.0);
    (p.z.abs() > 1e-12 && p.z.is_finite()).then(|| [p.x / p.z, p.y / p.z])
}

/// The image motion of one move, measured on a grid of patches.
#[derive(Debug, Clone)]
struct ImageMotion {
    /// The plane homography from the image before to the image after (normalised).
    g: Matrix3<f64>,
    /// Patches within [`PARALLAX_MAX_PX`] of `g` (parallax kept, mismatches dropped):
    /// centre before, found position after, pixels.
    pairs: Vec<([f64; 2], [f64; 2])>,
}

fn grid_points(size: [u32; 2], margin: f64) -> Vec<[f64; 2]> {
    let mut grid = Vec::new();
    for i in 0..MOTION_GRID[0] {
        for j in 0..MOTION_GRID[1] {
            grid.push([
                margin
                    + (f64::from(size[0]) - 1.0 - 2.0 * margin) * f64::from(i)
                        / f64::from(MOTION_GRID[0] - 1),
                margin
                    + (f64::from(size[1]) - 1.0 - 2.0 * margin) * f64::from(j)
                        / f64::from(MOTION_GRID[1] - 1),
            ]);
        }
    }
    grid
}

fn fit_motion(pairs: Vec<([f64; 2], [f64; 2])>) -> Result<ImageMotion, AlignError> {
    if pairs.len() < 12 {
        return Err(AlignError::Images(format!(
            "fixation: only {} image patches could be followed across a move (need 12)",
            pairs.len()
        )));
    }
    let data: Vec<(Point2<f64>, Point2<f64>)> =
        pairs.iter().map(|(p, q)| (Point2::new(p[0], p[1]), Point2::new(q[0], q[1]))).collect();
    let opts = RansacOptions { threshold: 1.0, ..RansacOptions::default() };
    let r = ransac(&Homography2Estimator, &data, &opts).map_err(|e| {
        AlignError::Images(format!("fixation: no image motion fits the followed patches: {e}"))
    })?;
    let n = r.model.0.norm();
    let g = if n > 0.0 { r.model.0 / n } else { r.model.0 };
    let model = Homography2(g);
    let pairs = data
        .iter()
        .zip(&pairs)
        .filter(|((a, b), _)| model.transfer_error(a, b) <= PARALLAX_MAX_PX)
        .map(|(_, pq)| *pq)
        .collect();
    Ok(ImageMotion { g, pairs })
}

/// The image motion of a move from `a` to `b` (pyramids of the two images): the plane
/// homography through a [`MOTION_GRID`] of patches spread over the whole image, found
/// by correlation around `p + shift` (`shift`: the whole-image translation), then again
/// with templates warped by that first fit (see [`locate_warped`]). A head rotation moves
/// the image by `K R K^-1` exactly if the axes pass through the optical centre; the axis
/// offsets add a parallax, which the fit averages over the scene and [`carry`] corrects
/// locally. Support over the whole image matters: a homography fitted to the ten patches
/// nearest a target outside the image extrapolated it 1-2 px wrong (measured, even with no
/// axis offsets); one fitted over the whole image, to within about 0.1 px.
fn image_motion(
    a: &Pyramid,
    b: &Pyramid,
    shift: [f64; 2],
    options: &FixationOptions,
) -> Result<ImageMotion, AlignError> {
    let level0 = a.base();
    let size = [level0.width(), level0.height()];
    let grid = grid_points(size, options.edge_margin_px);
    let mut pairs = Vec::new();
    for &p in &grid {
        let pred = [p[0] + shift[0], p[1] + shift[1]];
        if !inside(pred, size, options.patch.half_size as f64 + 1.0) {
            continue;
        }
        if let Ok(found) = locate_patch_in_pyramids(a, p, b, Some(pred), &options.patch)
            && found.score > 0.8
        {
            pairs.push((p, found.position));
        }
    }
    let first = fit_motion(pairs)?;
    // Again through the first motion: the warped templates are not stretched by the
    // rotation, so their positions (and the parallax residuals) are unbiased.
    let mut pairs = Vec::new();
    for &p in &grid {
        if let Ok(q) = locate_warped(level0, p, b, &first.g, 3.0, options) {
            pairs.push((p, q));
        }
    }
    fit_motion(pairs)
}

/// Carry a point `x` of the image before a move (possibly outside it) into the image after
/// it: the homography of the whole image plus the local parallax (plane plus parallax,
/// Hartley & Zisserman section 13.2): each inlier patch's residual `r_i` from the
/// homography is `gamma_i (e - G p_i)` with `e` the epipole (homogeneous, found as the
/// point all residuals point to, least squares) and `gamma_i` its relative inverse depth.
/// The point takes the median `gamma` of its nearest patches (its own surface, most
/// likely: it has never been seen). Pixels; the correction is left out when the residuals
/// are below the correlation noise (a rotation about the optical centre).
fn carry(motion: &ImageMotion, x: [f64; 2]) -> Option<[f64; 2]> {
    let predicted = apply(&motion.g, x)?;
    let scale = 1e-3;
    let mut rows = Vec::new();
    let mut residuals = Vec::new();
    for (p, q) in &motion.pairs {
        let h = apply(&motion.g, *p)?;
        let r = [q[0] - h[0], q[1] - h[1]];
        let hs = [h[0] * scale, h[1] * scale];
        rows.push([-r[1], r[0], r[1] * hs[0] - r[0] * hs[1]]);
        residuals.push((*p, hs, r));
    }
    let rms = (residuals.iter().map(|(_, _, r)| r[0] * r[0] + r[1] * r[1]).sum::<f64>()
        / residuals.len().max(1) as f64)
        .sqrt();
    if rms < PARALLAX_NOISE_PX || residuals.len() < 12 {
        return Some(predicted);
    }
    let mut m = Matrix3::zeros();
    for row in &rows {
        let v = Vector3::new(row[0], row[1], row[2]);
        m += v * v.transpose();
    }
    let eig = m.symmetric_eigen();
    let (k, _) = eig.eigenvalues.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1))?;
    let e = eig.eigenvectors.column(k).into_owned();
    let toward = |hs: [f64; 2]| [e[0] - e[2] * hs[0], e[1] - e[2] * hs[1]];
    let mut near: Vec<(f64, f64)> = residuals
        .iter()
        .filter_map(|(p, hs, r)| {
            let v = toward(*hs);
            let vv = v[0] * v[0] + v[1] * v[1];
            (vv > 1e-18).then(|| ((p[0] - x[0]).hypot(p[1] - x[1]), (r[0] * v[0] + r[1] * v[1]) / vv))
        })
        .collect();
    near.sort_by(|a, b| a.0.total_cmp(&b.0));
    near.truncate(PARALLAX_NEIGHBOURS);
    if near.is_empty() {
        return Some(predicted);
    }
    let gamma = median(near.iter().map(|n| n.1).collect());
    let v = toward([predicted[0] * scale, predicted[1] * scale]);
    Some([predicted[0] + gamma * v[0], predicted[1] + gamma * v[1]])
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    if v.is_empty() { 0.0 } else { v[v.len() / 2] }
}

/// Patches further than this from the homography (pixels) are mismatches, not parallax.
const PARALLAX_MAX_PX: f64 = 3.0;

/// Smallest image displacement (pixels, per axis) of the aimed point that updates `alpha`.
const MIN_ALPHA_MOVE_PX: f64 = 5.0;

/// RMS residual (pixels) of the whole-image homography below which no parallax is modelled.
const PARALLAX_NOISE_PX: f64 = 0.03;
/// Patches whose median relative inverse depth a carried point takes.
const PARALLAX_NEIGHBOURS: usize = 12;

/// Where the patch around `point_a` of image `a` appears in image `b`, given the image
/// motion `g` (a to b, any homography close to the truth near the point): the template is
/// `a` resampled through `g^-1` (bilinear), so it looks as the patch should look in `b`
/// (a rotation of 20-30 deg stretches an edge patch by 10-20 % relative to the centre,
/// which biases a plain template's correlation peak by up to a pixel), then searched by
/// correlation within `radius` of `g(point_a)`.
fn locate_warped(
    a: &GrayImage,
    point_a: [f64; 2],
    b: &Pyramid,
    g: &Matrix3<f64>,
    radius: f64,
    options: &FixationOptions,
) -> Result<[f64; 2], AlignError> {
    let lost = || {
        AlignError::Images(format!(
            "fixation: the target's patch ({:.1}, {:.1}) cannot be followed",
            point_a[0], point_a[1]
        ))
    };
    let predicted = apply(g, point_a).ok_or_else(lost)?;
    let g_inv = g.try_inverse().ok_or_else(lost)?;
    let half = options.patch.half_size as i64 + 4;
    let q0 = [predicted[0].round() as i64, predicted[1].round() as i64];
    let side = (2 * half + 1) as usize;
    let (w, h) = (a.width() as i64, a.height() as i64);
    let mut data = Vec::with_capacity(side * side);
    for j in -half..=half {
        for i in -half..=half {
            let src = apply(&g_inv, [(q0[0] + i) as f64, (q0[1] + j) as f64]).ok_or_else(lost)?;
            let (x0, y0) = (src[0].floor(), src[1].floor());
            let (xi, yi) = (x0 as i64, y0 as i64);
            if !(x0.is_finite() && y0.is_finite()) || xi < 0 || yi < 0 || xi + 1 >= w || yi + 1 >= h {
                return Err(lost());
            }
            let (fx, fy) = (src[0] - x0, src[1] - y0);
            let px = |x: i64, y: i64| f64::from(a.pixels()[(y * w + x) as usize]);
            let v = (1.0 - fy) * ((1.0 - fx) * px(xi, yi) + fx * px(xi + 1, yi))
                + fy * ((1.0 - fx) * px(xi, yi + 1) + fx * px(xi + 1, yi + 1));
            // Rounded to grey levels like every image the head captures: the rounding
            // (0.29 grey levels RMS) is far below the sensor noise.
            data.push(v.round().clamp(0.0, 255.0) as u8);
        }
    }
    let levels = b.len();
    let template =
        GrayImage::new(side as u32, side as u32, data).map_err(vision("fixation: warped patch"))?;
    let template = Pyramid::new(&template, levels).map_err(vision("fixation: warped patch"))?;
    // The target sits at `predicted` in b's coordinates, i.e. at `predicted - q0 + half`
    // in the template's.
    let at = [predicted[0] - q0[0] as f64 + half as f64, predicted[1] - q0[1] as f64 + half as f64];
    let search = PatchSearchOptions { search_radius: radius, ..options.patch.clone() };
    let found = locate_patch_in_pyramids(&template, at, b, Some(predicted), &search)
        .map_err(vision("fixation: following the target"))?;
    Ok(found.position)
}

/// The fixation's options and target checked ([`fixate`]).
fn check_fixation_inputs(target_px: [f64; 2], options: &FixationOptions) -> Result<(), AlignError> {
    options.patch.validate().map_err(vision("fixation options"))?;
    if !(options.tolerance_px > 0.0 && options.edge_margin_px > options.patch.half_size as f64) {
        return Err(AlignError::InvalidOption(
            "fixation: tolerance must be positive and the edge margin larger than the patch half-size".into(),
        ));
    }
    if !target_px.iter().all(|v| v.is_finite()) {
        return Err(AlignError::InvalidOption("fixation target is not a finite pixel".into()));
    }
    Ok(())
}

/// The aim of the next move and its turn (radians, horizontal and elevation) from the
/// current `alpha`: a target in view is brought to the centre `c`. One outside is first
/// brought just inside the border (small moves, so little parallax while it is carried by
/// the image motion); a visible point near the edge in its direction (the aim) measures
/// each move for the update of alpha.
fn aim_and_turn(
    target: [f64; 2],
    c: [f64; 2],
    alpha: [f64; 2],
    patch_target: bool,
    edge_margin_px: f64,
) -> ([f64; 2], [f64; 2]) {
    if patch_target {
        return (target, [((target[0] - c[0]) / alpha[0]).atan(), ((target[1] - c[1]) / alpha[1]).atan()]);
    }
    let d = [target[0] - c[0], target[1] - c[1]];
    let along = |inset: f64| {
        let half = [c[0] - inset, c[1] - inset];
        let s = (half[0] / d[0].abs().max(1e-9)).min(half[1] / d[1].abs().max(1e-9)).min(1.0);
        [c[0] + s * d[0], c[1] + s * d[1]]
    };
    let (proxy, entry) = (along(edge_margin_px + 2.0), along(edge_margin_px + 12.0));
    let angle = |k: usize, p: [f64; 2]| ((p[k] - c[k]) / alpha[k]).atan();
    (proxy, [angle(0, target) - angle(0, entry), angle(1, target) - angle(1, entry)])
}

/// Update each axis' `alpha` from the aim's measured image motion (`aim` to `aim_after`)
/// under the turn `delta`. A move of a few pixels tells little about alpha (a 0.05 px
/// correlation error is 1 % of 5 px): only larger ones update it.
fn update_alpha(alpha: &mut [f64; 2], aim: [f64; 2], aim_after: [f64; 2], c: [f64; 2], delta: [f64; 2]) {
    for k in 0..2 {
        let moved = (aim_after[k] - aim[k]).abs();
        if moved >= MIN_ALPHA_MOVE_PX
            && let Some(a) = solve_alpha(aim[k] - c[k], aim_after[k] - c[k], delta[k])
        {
            alpha[k] = a;
        }
    }
}

/// Bring `target_px` (a pixel of `camera`'s current image; it may lie outside) to the
/// image centre without calibration (paper section 5). See the module documentation.
pub fn fixate<H: ImagingHead>(
    head: &mut H,
    camera: Camera,
    target_px: [f64; 2],
    options: &FixationOptions,
) -> Result<FixationReport, AlignError> {
    check_fixation_inputs(target_px, options)?;
    let size = head.image_size();
    let c = centre_of(size);
    let f = options.focal_guess_px.unwrap_or(2.0 * f64::from(size[0]));
    // Signed: +vergence turns right (content moves left), +elevation turns up (content
    // moves down). A wrong sign is corrected after the first move.
    let mut alpha = [f, -f];
    let mut images = head.capture_images()?;
    let mut target = target_px;
    // A target visible at the start is a scene point: its own patch follows it. One that
    // starts outside has no appearance (e.g. a vanishing point): it is carried by the
    // image motion of the whole view.
    let mut patch_target = inside(target, size, options.edge_margin_px);
    // Where the target's own patch was taken: every later position is measured against
    // this one image (chaining image to image would add each step's sub-pixel error).
    let mut anchor: Option<(GrayImage, [f64; 2], Matrix3<f64>)> =
        patch_target.then(|| (camera.image(&images).clone(), target, Matrix3::identity()));
    let mut steps = Vec::new();
    loop {
        let err = ((target[0] - c[0]).powi(2) + (target[1] - c[1]).powi(2)).sqrt();
        let visible = inside(target, size, options.edge_margin_px);
        if (err <= options.tolerance_px && visible) || steps.len() >= options.max_moves {
            let encoders = head.read_encoders()?;
            if err > options.tolerance_px {
                return Err(AlignError::Images(format!(
                    "fixation did not converge in {} moves: the target is {err:.2} px from the centre",
                    options.max_moves
                )));
            }
            return Ok(FixationReport {
                steps,
                final_target_px: target,
                final_error_px: err,
                centre_px: c,
                alpha_px: alpha,
                encoders,
            });
        }
        let (aim, delta) = aim_and_turn(target, c, alpha, patch_target, options.edge_margin_px);
        let move_deg = [delta[0].to_degrees(), delta[1].to_degrees()];
        let e = head.read_encoders()?;
        steps.push(FixationStep { encoders: e, target_px: target, aim_px: aim, move_deg, alpha_px: alpha });
        head.move_to(&e.moved(camera.horizontal_joint(), move_deg[0]).moved(Joint::Elevation, move_deg[1]))?;
        let next = head.capture_images()?;
        let (before, after) = (camera.image(&images), camera.image(&next));
        // The image shift of the move by whole-image pyramid correlation (paper section 5
        // step 3), then the image motion (a homography) from patches all over the image,
        // then the aim's own patch through that motion (it is always visible).
        let shift = register_translation(before, after, &RegistrationOptions::default())
            .map_err(vision("fixation: registering the images before and after a move"))?
            .shift;
        let levels = options.patch.max_levels.max(1);
        let pyr_before = Pyramid::new(before, levels).map_err(vision("fixation: image pyramid"))?;
        let pyr_after = Pyramid::new(after, levels).map_err(vision("fixation: image pyramid"))?;
        let motion = image_motion(&pyr_before, &pyr_after, shift, options)?;
        let aim_after =
            locate_warped(before, aim, &pyr_after, &motion.g, options.patch.search_radius, options)?;
        update_alpha(&mut alpha, aim, aim_after, c, delta);
        target = if let Some((anchor_image, anchor_px, anchor_motion)) = &mut anchor {
            // The motion from the anchor image to this one, chained: it only shapes the
            // template and centres the search; the target's position is its correlation
            // peak against the anchor image's patch.
            *anchor_motion = motion.g * *anchor_motion;
            let n = anchor_motion.norm();
            if n > 0.0 {
                *anchor_motion /= n;
            }
            locate_warped(anchor_image, *anchor_px, &pyr_after, anchor_motion, 6.0, options)?
        } else {
            carry(&motion, target)
                .ok_or_else(|| AlignError::Images("fixation: the target left the image plane".into()))?
        };
        // Once the carried target is in view, its own patch follows it from now on.
        if !patch_target && inside(target, size, options.edge_margin_px) {
            patch_target = true;
            anchor = Some((after.clone(), target, Matrix3::identity()));
        }
        images = next;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn alpha_from_one_move_is_exact() {
        for alpha in [500.0, 700.0, -650.0, 1400.0] {
            for (theta, delta) in [(0.2f64, 0.15f64), (-0.3, -0.1), (0.05, 0.2), (0.4, 0.4)] {
                let x = alpha * theta.tan();
                let y = alpha * (theta - delta).tan();
                let a = solve_alpha(x, y, delta).unwrap();
                // Exact model: 1e-9 relative (rounding of tan and the quadratic).
                assert!((a - alpha).abs() < 1e-9 * alpha.abs(), "{a} vs {alpha}");
            }
        }
        assert!(solve_alpha(10.0, 10.0, 0.1).is_none());
        assert!(solve_alpha(10.0, 5.0, 0.0).is_none());
    }

    /// A rotation-like homography (K R K^-1 of a 10 deg turn, f = 700).
    fn rotation_homography() -> Matrix3<f64> {
        let k = Matrix3::new(700.0, 0.0, 384.0, 0.0, 700.0, 288.0, 0.0, 0.0, 1.0);
        let r = nalgebra::Rotation3::from_euler_angles(0.03, 0.17, 0.01);
        let g = k * r.matrix() * k.try_inverse().unwrap();
        g / g.norm()
    }

    fn grid() -> Vec<[f64; 2]> {
        grid_points([768, 576], 48.0)
    }

    #[test]
    fn carry_is_exact_for_plane_plus_parallax() {
        let g = rotation_homography();
        for (e, gamma_near, gamma_far) in
            [([0.4, 2.5, 1.0], 0.8, 0.2), ([1.0, 0.1, 0.0], -1.5, 0.5), ([0.2, -0.3, 1.0], 0.0, 0.0)]
        {
            let e = Vector3::new(e[0], e[1], e[2]);
            let target = [-150.0, 200.0];
            // Every patch within 200 px of the target lies at one relative inverse depth, the
            // rest at another: the target takes its neighbours'.
            let pairs: Vec<([f64; 2], [f64; 2])> = grid()
                .into_iter()
                .map(|p| {
                    let h = apply(&g, p).unwrap();
                    let gamma = if (p[0] - target[0]).hypot(p[1] - target[1]) < 260.0 {
                        gamma_near
                    } else {
                        gamma_far
                    };
                    let v = [e[0] - e[2] * h[0] * 1e-3, e[1] - e[2] * h[1] * 1e-3];
                    (p, [h[0] + gamma * v[0], h[1] + gamma * v[1]])
                })
                .collect();
            let motion = ImageMotion { g, pairs };
            let got = carry(&motion, target).unwrap();
            let h = apply(&g, target).unwrap();
            let v = [e[0] - e[2] * h[0] * 1e-3, e[1] - e[2] * h[1] * 1e-3];
            let want = [h[0] + gamma_near * v[0], h[1] + gamma_near * v[1]];
            // Exact model, noise-free: rounding only.
            assert!((got[0] - want[0]).hypot(got[1] - want[1]) < 1e-9, "{got:?} vs {want:?}");
        }
    }

    /// A smooth texture (sum of sinusoids, wavelengths 12-100 px) seen through `g_inv`
    /// (pixel x of the image shows the texture at `g_inv x`), as an 8-bit image.
    fn textured(g_inv: &Matrix3<f64>) -> GrayImage {
        let waves = [
            [0.31, 0.12, 0.3, 20.0],
            [-0.07, 0.22, 1.1, 18.0],
            [0.05, -0.06, 2.0, 25.0],
            [0.5, 0.3, 0.7, 8.0],
            [-0.2, -0.45, 2.9, 8.0],
        ];
        let (w, h) = (320usize, 240usize);
        let data = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| {
                let p = apply(g_inv, [x as f64, y as f64]).unwrap();
                let v: f64 = waves.iter().map(|q| q[3] * (q[0] * p[0] + q[1] * p[1] + q[2]).sin()).sum();
                (128.0 + v).round() as u8
            })
            .collect();
        GrayImage::new(w as u32, h as u32, data).unwrap()
    }

    #[test]
    fn warped_template_finds_a_stretched_patch() {
        // Image b shows image a through a homography that stretches by 20 % and shears:
        // the patch at (150, 110) of a is at g(150, 110) in b.
        let g = Matrix3::new(1.2, 0.08, -20.0, -0.05, 1.1, 5.0, 2e-4, -1e-4, 1.0);
        let a = textured(&Matrix3::identity());
        let b_image = textured(&g.try_inverse().unwrap());
        let b = Pyramid::new(&b_image, 4).unwrap();
        let options = FixationOptions::default();
        let p = [150.3, 110.6];
        let want = apply(&g, p).unwrap();
        let got = locate_warped(&a, p, &b, &g, 6.0, &options).unwrap();
        // Noise-free and exactly warped: the sub-pixel peak fit of a smooth texture is good
        // to a few hundredths of a pixel.
        assert!((got[0] - want[0]).hypot(got[1] - want[1]) < 0.05, "{got:?} vs {want:?}");
        // A motion known only roughly (1.5 px off) still finds it: the search corrects it.
        let off = Matrix3::new(1.0, 0.0, 1.5, 0.0, 1.0, -1.0, 0.0, 0.0, 1.0) * g;
        let got = locate_warped(&a, p, &b, &off, 6.0, &options).unwrap();
        assert!((got[0] - want[0]).hypot(got[1] - want[1]) < 0.1, "{got:?} vs {want:?}");
        // A patch that leaves image a is an error, not a panic.
        assert!(locate_warped(&a, [3.0, 3.0], &b, &g, 6.0, &options).is_err());
    }
}
