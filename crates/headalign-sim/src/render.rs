//! Ray-cast renderer of the textured room: what a simulated camera sees, as an 8-bit
//! grey image.
//!
//! Camera model: any model of the geometry crate's lens table, a [`Distortion`] (its
//! `crate::lens` rows: the pinhole, radial-tangential `k1 k2 p1 p2 k3` (OpenCV
//! `plumb_bob`), equidistant fisheye `k1..k4` (OpenCV `fisheye`), the double sphere `xi
//! alpha`): a point `X` in the camera frame (x right, y down, z forward) is seen at `K m`,
//! `m` the model's projection ([`project`]). The image is rendered **in the distorted
//! model**: each sample position is mapped by `K^-1` to the model's image plane and
//! undistorted by [`Distortion::undistort`] (Newton with the analytic Jacobian), or, for a
//! model whose field reaches beyond 90 deg (the table's `max_half_fov_deg`), unprojected
//! to a bearing. Before rendering, [`check_invertible`] refuses a lens whose radial
//! profile (the table's `radial_profile`) is not strictly increasing out to the image's
//! farthest corner (a strong barrel folds over: the inverse is not unique), or, for the
//! equidistant model, whose corner rays would lie 90 deg or more off the axis (behind the
//! pinhole plane).
//!
//! The TOML table `[render.distortion]` holds `kind` (default radtan; any spelling
//! [`LensKind::parse`] accepts) and the model's coefficients by name (`k1 k2 p1 p2 k3`,
//! `k1 k2 k3 k4`, `xi alpha`; default 0; a non-zero coefficient the model does not have is
//! an error). A file with `k1, k2`
//! only is the two-term radial lens `x (1 + k1 r^2 + k2 r^4)`: its projections are those
//! of the same lens written as `(1 + r^2 (k1 + r^2 k2))`, within 1e-12 px (rounding; the
//! rendered sample rays within 1e-11 px, Newton's tolerance: see the test
//! `radial_two_term_lens_matches_the_written_out_formula`), and all-zero coefficients
//! are the plain pinhole, bit for bit.
//!
//! Per pixel: `s x s` samples (`supersampling`, default 2) on a regular sub-grid; each
//! sample's ray hits the nearest textured quad (brute force over the candidate quads of
//! its 32x16-pixel tile: quads are culled per camera when seen from their back side and
//! per tile when their clipped projection's bounding box misses the tile's rays); the
//! texture is sampled trilinearly with a footprint `depth / (f * s * sqrt(cos))` metres
//! (`cos` between ray and normal: the geometric mean of the two axes of the stretched
//! footprint — sharper than the conservative maximum at grazing angles, with the
//! supersampling absorbing what aliasing is left). The samples are averaged, then an
//! optional Gaussian blur (`blur_sigma_px`, separable, edges clamped) and Gaussian sensor
//! noise (`noise_sigma_grey`, grey levels, seeded per row so the result does not depend
//! on the thread count) are applied, and the result is rounded and clamped to u8.
//!
//! Pixel convention as in the rest of the workspace: (0, 0) is the centre of the
//! top-left pixel. A ray that hits nothing (impossible inside the closed room) gives
//! grey 128. Rows are rendered in parallel (rayon). Timing: see `benches/render.rs`.
//!
//! Pitfalls: the texture footprint uses the mean focal length, not the lens's local
//! magnification (a fisheye's border is sampled slightly too sharp); the equidistant lens
//! with all coefficients zero is `theta_d = theta`, not the pinhole.

use headalign_geometry::camera::Intrinsics;
use headalign_geometry::distortion::{Distortion, LensKind};
use headalign_vision::GrayImage;
use nalgebra::{Isometry3, Point2, Point3, Vector2, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};

use crate::SimError;
use crate::texture::TexturedQuad;

/// Largest absolute value of a lens coefficient the options accept (beyond it no real
/// lens, and the Newton inverse would need far more steps).
pub const MAX_LENS_COEFFICIENT: f64 = 2.0;

/// Serde of [`RenderOptions::distortion`] as its TOML / JSON table (module docs): `kind`
/// by the model's short name, then the named values of the geometry crate's JSON form
/// ([`Distortion::named_values`]); read back by any name of the lens table, missing
/// coefficients zero, a coefficient the model lacks an error.
mod lens_table {
    use super::*;
    use serde::ser::SerializeMap;

    pub fn serialize<S: serde::Serializer>(d: &Distortion, s: S) -> Result<S::Ok, S::Error> {
        let values = d.named_values();
        let mut map = s.serialize_map(Some(values.len() + 1))?;
        map.serialize_entry("kind", d.kind.kalibr_name())?;
        for (name, v) in values {
            map.serialize_entry(name, &v)?;
        }
        map.end()
    }

    pub fn deserialize<'de, D: serde::Deserializer<'de>>(de: D) -> Result<Distortion, D::Error> {
        /// The table: the model's name and named values.
        #[derive(Deserialize)]
        struct LensTable {
            kind: Option<String>,
            #[serde(flatten)]
            values: std::collections::BTreeMap<String, f64>,
        }
        let t = LensTable::deserialize(de)?;
        let kind = match t.kind.as_deref() {
            None => LensKind::default(),
            Some(name) => LensKind::parse(name).ok_or_else(|| {
                let names: Vec<&str> =
                    headalign_geometry::lens::MODELS.iter().map(|m| m.names().short).collect();
                serde::de::Error::custom(format!("distortion kind '{name}' is none of {}", names.join(", ")))
            })?,
        };
        Distortion::from_named_values(kind, t.values.iter().map(|(n, v)| (n.as_str(), *v)))
            .map_err(serde::de::Error::custom)
    }
}

/// Pixel of a point in the camera frame through `K` and `distortion` (the lens model's
/// projection, [`Distortion::project_pixel`]); `None` outside the model's validity region
/// (for the pinhole-plane models a point not in front, `z <= 0`). No image bounds check.
/// The pinhole (all coefficients zero, radial-tangential) is `K (X.x / X.z, X.y / X.z, 1)`
/// exactly.
pub fn project(k: &Intrinsics, distortion: &Distortion, point_in_cam: &Point3<f64>) -> Option<Point2<f64>> {
    distortion.project_pixel(k, &point_in_cam.coords)
}

/// True if the renderer casts the lens's rays as bearings ([`render_clean`]): the models
/// whose field reaches beyond 90 deg (the double sphere); the others keep the
/// pinhole-plane rays `(x, y, 1)` and their tile culling.
fn casts_bearings(distortion: &Distortion) -> bool {
    distortion.kind.model().max_half_fov_deg() > 90.0
}

/// Steps of the radial-profile scan of [`check_invertible`] (in the undistorted radius,
/// or the ray angle of the equidistant model).
const PROFILE_STEPS: usize = 20_000;

/// Check that `distortion` can be inverted over an image of `image_size` pixels seen
/// through `k`: the radial profile (radius or ray angle to distorted radius, tangential
/// terms left out) increases strictly until it passes the farthest image corner's
/// distorted radius, the equidistant corner rays stay below 90 deg, and every image
/// corner and edge midpoint undistorts. The error names the lens and the radius.
pub fn check_invertible(
    distortion: &Distortion,
    k: &Intrinsics,
    image_size: [u32; 2],
) -> Result<(), SimError> {
    if distortion.is_zero() {
        return Ok(());
    }
    let (w, h) = (f64::from(image_size[0]), f64::from(image_size[1]));
    let probes: Vec<Point2<f64>> = [(-0.5, -0.5), (w - 0.5, -0.5), (-0.5, h - 0.5), (w - 0.5, h - 0.5)]
        .into_iter()
        .chain([
            (0.5 * w - 0.5, -0.5),
            (0.5 * w - 0.5, h - 0.5),
            (-0.5, 0.5 * h - 0.5),
            (w - 0.5, 0.5 * h - 0.5),
        ])
        .map(|(x, y)| Point2::new(x, y))
        .collect();
    let rd_max = probes.iter().map(|p| k.unproject(p).xy().norm()).fold(0.0, f64::max);
    let fail = |why: String| {
        SimError::Render(format!(
            "distortion {distortion:?} is not invertible over the image (normalised radius {rd_max:.3}): {why}"
        ))
    };
    // The profile's argument (the lens table's `profile_end`, `radial_profile`): the
    // undistorted radius up to 100 (radial-tangential), the ray angle up to 90 deg
    // (equidistant), or up to 180 deg (a model of wider field: the image-plane radius of
    // the ray at that angle, NaN outside the model's region).
    let wide = casts_bearings(distortion);
    let (model, params) = (distortion.kind.model(), distortion.params());
    let end = model.profile_end();
    let profile = |a: f64| model.radial_profile(&params, a);
    let step = end / PROFILE_STEPS as f64;
    let mut prev = 0.0;
    let mut reached = false;
    for i in 1..PROFILE_STEPS {
        let v = profile(step * i as f64);
        if v.is_nan() || v <= prev {
            return Err(fail(format!("the radial profile turns back at {prev:.3}")));
        }
        if v >= rd_max {
            reached = true;
            break;
        }
        prev = v;
    }
    if !reached {
        return Err(fail(format!("the lens never reaches the image corners (at most {prev:.3})")));
    }
    for p in &probes {
        if wide {
            distortion.unproject_pixel(k, p).map_err(|e| fail(e.to_string()))?;
        } else {
            distortion.undistort_pixel(k, p).map_err(|e| fail(e.to_string()))?;
        }
    }
    Ok(())
}

/// Options of the renderer. Defaults: 2x2 supersampling, blur 0.5 px, noise 2 grey
/// levels, no distortion, 5 mm texels, photographs from [`crate::texture::default_data_dir`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RenderOptions {
    /// Samples per pixel along each axis (1 to 8). Default 2.
    pub supersampling: u32,
    /// Standard deviation of the Gaussian blur after sampling, pixels (0: none). Default 0.5.
    pub blur_sigma_px: f64,
    /// Standard deviation of the Gaussian sensor noise, grey levels (0: none). Default 2.
    pub noise_sigma_grey: f64,
    /// Lens model of both cameras (module docs; TOML `[render.distortion]` with `kind`
    /// and the coefficients). Default the pinhole. The point captures of the simulated
    /// head use it too, so both modes see the same cameras.
    #[serde(with = "lens_table")]
    pub distortion: Distortion,
    /// Texture resolution, metres per texel. Default 0.005 (the room is seen from 1.5 to
    /// 6 m: one pixel covers 2 to 9 mm).
    pub metres_per_texel: f64,
    /// Texture resolution of the near panels (`near_panels`), metres per texel. Default
    /// 0.0015: they are seen from about 1 m, where one pixel covers 1.4 mm; at 5 mm a
    /// photograph's pixel would be magnified to 4-7 image pixels and its corners blurred
    /// away (a poster at reading distance shows its print, not a magnified blur).
    pub near_metres_per_texel: f64,
    /// Use the texture photographs (else procedural textures only). Default true.
    pub use_photos: bool,
    /// Data directory holding `opencv_samples/textures` and `skimage_data/textures`;
    /// `None` (default) means `data/` at the workspace root. A missing
    /// folder is not an error: procedural textures replace the photographs.
    pub data_dir: Option<PathBuf>,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            supersampling: 2,
            blur_sigma_px: 0.5,
            noise_sigma_grey: 2.0,
            distortion: Distortion::default(),
            metres_per_texel: 0.005,
            near_metres_per_texel: 0.0015,
            use_photos: true,
            data_dir: None,
        }
    }
}

impl RenderOptions {
    /// Options with neither blur nor noise (for exact comparisons).
    pub fn clean() -> Self {
        Self { blur_sigma_px: 0.0, noise_sigma_grey: 0.0, ..Self::default() }
    }

    /// Every problem with the options, as messages naming the field.
    pub fn problems(&self) -> Vec<String> {
        let mut p = Vec::new();
        if !(1..=8).contains(&self.supersampling) {
            p.push(format!("render.supersampling must be in 1..=8, got {}", self.supersampling));
        }
        if !(self.blur_sigma_px.is_finite() && (0.0..=20.0).contains(&self.blur_sigma_px)) {
            p.push(format!("render.blur_sigma_px must be in [0, 20], got {}", self.blur_sigma_px));
        }
        if !(self.noise_sigma_grey.is_finite() && self.noise_sigma_grey >= 0.0) {
            p.push(format!("render.noise_sigma_grey must be >= 0, got {}", self.noise_sigma_grey));
        }
        let d = self.distortion;
        if !d.params().iter().all(|v| v.is_finite() && v.abs() <= MAX_LENS_COEFFICIENT) {
            p.push(format!(
                "render.distortion coefficients must be finite and in [-{MAX_LENS_COEFFICIENT}, {MAX_LENS_COEFFICIENT}], got {d:?}"
            ));
        } else if let Err(e) = d.validate() {
            p.push(format!("render.distortion: {e}"));
        }
        if !(self.metres_per_texel.is_finite() && (1e-4..=0.1).contains(&self.metres_per_texel)) {
            p.push(format!("render.metres_per_texel must be in [1e-4, 0.1], got {}", self.metres_per_texel));
        }
        if !(self.near_metres_per_texel.is_finite() && (1e-4..=0.1).contains(&self.near_metres_per_texel)) {
            p.push(format!(
                "render.near_metres_per_texel must be in [1e-4, 0.1], got {}",
                self.near_metres_per_texel
            ));
        }
        p
    }

    /// Check the options.
    pub fn validate(&self) -> Result<(), SimError> {
        let p = self.problems();
        if p.is_empty() { Ok(()) } else { Err(SimError::InvalidScenario(p.join("; "))) }
    }

    /// The data directory to search for photographs, `None` if photographs are not wanted.
    pub fn resolved_data_dir(&self) -> Option<PathBuf> {
        self.use_photos.then(|| self.data_dir.clone().unwrap_or_else(crate::texture::default_data_dir))
    }
}

/// One camera to render.
#[derive(Clone, Copy, Debug)]
pub struct CameraView<'a> {
    /// Intrinsics.
    pub k: &'a Intrinsics,
    /// Lens model.
    pub distortion: &'a Distortion,
    /// Pose: camera frame to world.
    pub world_from_cam: &'a Isometry3<f64>,
    /// `[width, height]`, pixels.
    pub image_size: [u32; 2],
}

/// A quad expressed in one camera's frame, with what the inner loop needs.
#[derive(Clone, Copy)]
struct CamQuad {
    index: usize,
    corner: Vector3<f64>,
    u: Vector3<f64>,
    v: Vector3<f64>,
    normal: Vector3<f64>,
    /// `normal . corner` (negative: the camera sees the front side).
    plane: f64,
    size: [f64; 2],
    /// Bounding box of the (z >= Z_NEAR clipped) projection in undistorted normalised
    /// coordinates: [x_min, y_min, x_max, y_max].
    bbox: [f64; 4],
}

const Z_NEAR: f64 = 1e-6;
const TILE_W: usize = 32;
const TILE_H: usize = 16;

fn cam_quads(quads: &[TexturedQuad], cam_from_world: &Isometry3<f64>) -> Vec<CamQuad> {
    let mut out = Vec::new();
    for (index, tq) in quads.iter().enumerate() {
        let q = &tq.quad;
        let corner = (cam_from_world * q.corner).coords;
        let u = cam_from_world.rotation * q.u;
        let v = cam_from_world.rotation * q.v;
        let normal = u.cross(&v);
        let plane = normal.dot(&corner);
        if plane >= 0.0 {
            continue; // seen from behind (or edge on): never the first hit.
        }
        // Clip the polygon against z >= Z_NEAR (Sutherland-Hodgman, one plane).
        let corners = [
            corner,
            corner + u * q.size_m[0],
            corner + u * q.size_m[0] + v * q.size_m[1],
            corner + v * q.size_m[1],
        ];
        let mut bbox = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
        let mut any = false;
        for i in 0..4 {
            let (a, b) = (corners[i], corners[(i + 1) % 4]);
            let mut add = |p: Vector3<f64>| {
                let (x, y) = (p.x / p.z, p.y / p.z);
                bbox = [bbox[0].min(x), bbox[1].min(y), bbox[2].max(x), bbox[3].max(y)];
                any = true;
            };
            if a.z >= Z_NEAR {
                add(a);
            }
            if (a.z >= Z_NEAR) != (b.z >= Z_NEAR) {
                let t = (Z_NEAR - a.z) / (b.z - a.z);
                add(a + (b - a) * t);
            }
        }
        if any {
            out.push(CamQuad { index, corner, u, v, normal, plane, size: q.size_m, bbox });
        }
    }
    out
}

/// Render one camera's view of the textured quads: the mean of the samples per pixel,
/// before blur and noise, as f32 grey values, row-major. A sample whose position does not
/// undistort (impossible after [`check_invertible`]) is an error naming it.
fn render_clean(
    quads: &[TexturedQuad],
    view: &CameraView<'_>,
    supersampling: u32,
) -> Result<Vec<f32>, SimError> {
    let [w, h] = view.image_size;
    let (w, h) = (w as usize, h as usize);
    let cam_from_world = view.world_from_cam.inverse();
    let cquads = cam_quads(quads, &cam_from_world);
    let k = view.k;
    let dist = view.distortion;
    if casts_bearings(dist) {
        return render_bearings(quads, view, supersampling);
    }
    let ss = supersampling.max(1) as usize;
    let inv_ss = 1.0 / ss as f64;
    let focal_ss = k.mean_focal() * ss as f64;
    let mut image = vec![0f32; w * h];
    let failed = AtomicBool::new(false);
    image.par_chunks_mut(w * TILE_H).enumerate().for_each(|(band, rows)| {
        let y_start = band * TILE_H;
        let band_h = rows.len() / w;
        let mut rays: Vec<(f64, f64)> = Vec::with_capacity(TILE_W * TILE_H * ss * ss);
        let mut candidates: Vec<CamQuad> = Vec::with_capacity(cquads.len());
        for x_start in (0..w).step_by(TILE_W) {
            let tile_w = TILE_W.min(w - x_start);
            rays.clear();
            let mut tb = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
            for dy in 0..band_h {
                for dx in 0..tile_w {
                    for sy in 0..ss {
                        for sx in 0..ss {
                            let px = (x_start + dx) as f64 + (sx as f64 + 0.5) * inv_ss - 0.5;
                            let py = (y_start + dy) as f64 + (sy as f64 + 0.5) * inv_ss - 0.5;
                            let yd = (py - k.cy) / k.fy;
                            let xd = (px - k.cx - k.skew * yd) / k.fx;
                            let (x, y) = if dist.is_zero() {
                                (xd, yd)
                            } else {
                                match dist.undistort(&Vector2::new(xd, yd)) {
                                    Ok(u) => (u.x, u.y),
                                    Err(_) => {
                                        failed.store(true, Ordering::Relaxed);
                                        (xd, yd)
                                    }
                                }
                            };
                            tb = [tb[0].min(x), tb[1].min(y), tb[2].max(x), tb[3].max(y)];
                            rays.push((x, y));
                        }
                    }
                }
            }
            candidates.clear();
            candidates.extend(cquads.iter().filter(|q| {
                q.bbox[0] <= tb[2] && q.bbox[2] >= tb[0] && q.bbox[1] <= tb[3] && q.bbox[3] >= tb[1]
            }));
            let per_pixel = ss * ss;
            for dy in 0..band_h {
                for dx in 0..tile_w {
                    let mut sum = 0f32;
                    let base = (dy * tile_w + dx) * per_pixel;
                    for &(x, y) in &rays[base..base + per_pixel] {
                        sum += shade(quads, &candidates, x, y, focal_ss);
                    }
                    rows[dy * w + x_start + dx] = sum / per_pixel as f32;
                }
            }
        }
    });
    if failed.load(Ordering::Relaxed) {
        return Err(SimError::Render(format!(
            "distortion {dist:?}: a sample position of the image does not undistort"
        )));
    }
    Ok(image)
}

/// [`render_clean`] for a lens whose rays may lie beyond 90 deg (the double sphere):
/// each sample position unprojected to its unit bearing by the lens model
/// ([`Distortion::unproject_pixel`]), cast against every quad facing the camera (no tile
/// culling: the pinhole-plane bounding boxes do not hold rays behind the camera).
fn render_bearings(
    quads: &[TexturedQuad],
    view: &CameraView<'_>,
    supersampling: u32,
) -> Result<Vec<f32>, SimError> {
    let [w, h] = view.image_size;
    let (w, h) = (w as usize, h as usize);
    let cam_from_world = view.world_from_cam.inverse();
    let all: Vec<CamQuad> = quads
        .iter()
        .enumerate()
        .filter_map(|(index, tq)| {
            let q = &tq.quad;
            let corner = (cam_from_world * q.corner).coords;
            let u = cam_from_world.rotation * q.u;
            let v = cam_from_world.rotation * q.v;
            let normal = u.cross(&v);
            let plane = normal.dot(&corner);
            let bbox = [f64::NEG_INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::INFINITY];
            (plane < 0.0).then_some(CamQuad { index, corner, u, v, normal, plane, size: q.size_m, bbox })
        })
        .collect();
    let (k, dist) = (view.k, view.distortion);
    let ss = supersampling.max(1) as usize;
    let inv_ss = 1.0 / ss as f64;
    let focal_ss = k.mean_focal() * ss as f64;
    let failed = AtomicBool::new(false);
    let mut image = vec![0f32; w * h];
    image.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, out) in row.iter_mut().enumerate() {
            let mut sum = 0f32;
            for sy in 0..ss {
                for sx in 0..ss {
                    let px = x as f64 + (sx as f64 + 0.5) * inv_ss - 0.5;
                    let py = y as f64 + (sy as f64 + 0.5) * inv_ss - 0.5;
                    match dist.unproject_pixel(k, &Point2::new(px, py)) {
                        Ok(d) => sum += shade_ray(quads, &all, &d, focal_ss),
                        Err(_) => failed.store(true, Ordering::Relaxed),
                    }
                }
            }
            *out = sum / (ss * ss) as f32;
        }
    });
    if failed.load(Ordering::Relaxed) {
        return Err(SimError::Render(format!(
            "distortion {dist:?}: a sample position of the image has no ray"
        )));
    }
    Ok(image)
}

/// Grey value seen along the ray `(x, y, 1)` (camera frame).
#[inline]
fn shade(quads: &[TexturedQuad], candidates: &[CamQuad], x: f64, y: f64, focal_ss: f64) -> f32 {
    shade_ray(quads, candidates, &Vector3::new(x, y, 1.0), focal_ss)
}

/// Grey value seen along the ray `d` (camera frame; `(x, y, 1)` for the pinhole-plane
/// models, a unit bearing for the wide ones: `best_t` is then the distance, which the
/// footprint uses as its depth).
#[inline]
fn shade_ray(quads: &[TexturedQuad], candidates: &[CamQuad], d: &Vector3<f64>, focal_ss: f64) -> f32 {
    let d = *d;
    let mut best_t = f64::INFINITY;
    let mut best: Option<(&CamQuad, f64, f64, f64)> = None;
    for q in candidates {
        let denom = q.normal.dot(&d);
        if denom >= 0.0 {
            continue;
        }
        let t = q.plane / denom;
        if t <= 0.0 || t >= best_t {
            continue;
        }
        let rel = d * t - q.corner;
        let a = rel.dot(&q.u);
        let b = rel.dot(&q.v);
        if a < 0.0 || b < 0.0 || a > q.size[0] || b > q.size[1] {
            continue;
        }
        best_t = t;
        best = Some((q, a, b, denom));
    }
    let Some((q, a, b, denom)) = best else { return 128.0 };
    let tq = &quads[q.index];
    let inv_mpt = 1.0 / tq.metres_per_texel;
    let cos = (-denom / d.norm()).max(1e-3);
    // best_t is the depth (d.z = 1).
    let footprint_texels = best_t / focal_ss / cos.sqrt() * inv_mpt;
    tq.texture.sample((a * inv_mpt) as f32, (b * inv_mpt) as f32, footprint_texels as f32)
}

/// Separable Gaussian blur (kernel radius `ceil(3 sigma)`, edges clamped), in place.
fn gaussian_blur(image: &mut [f32], w: usize, h: usize, sigma: f64) {
    if sigma <= 0.0 {
        return;
    }
    let radius = (3.0 * sigma).ceil() as isize;
    let mut kernel: Vec<f32> =
        (-radius..=radius).map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp() as f32).collect();
    let total: f32 = kernel.iter().sum();
    kernel.iter_mut().for_each(|v| *v /= total);
    let clamp = |i: isize, n: usize| i.clamp(0, n as isize - 1) as usize;
    // Horizontal.
    let mut tmp = vec![0f32; w * h];
    tmp.par_chunks_mut(w).zip(image.par_chunks(w)).for_each(|(out, row)| {
        for (x, o) in out.iter_mut().enumerate() {
            let mut acc = 0.0;
            for (j, kv) in kernel.iter().enumerate() {
                acc += kv * row[clamp(x as isize + j as isize - radius, w)];
            }
            *o = acc;
        }
    });
    // Vertical.
    image.par_chunks_mut(w).enumerate().for_each(|(y, out)| {
        out.iter_mut().for_each(|v| *v = 0.0);
        for (j, kv) in kernel.iter().enumerate() {
            let src = clamp(y as isize + j as isize - radius, h);
            let row = &tmp[src * w..(src + 1) * w];
            for (o, s) in out.iter_mut().zip(row) {
                *o += kv * s;
            }
        }
    });
}

/// Render one camera's view: sample, blur, add noise (seeded by `noise_seed`; each row
/// draws from its own ChaCha8 stream), round to u8.
pub fn render_view(
    quads: &[TexturedQuad],
    view: &CameraView<'_>,
    options: &RenderOptions,
    noise_seed: u64,
) -> Result<GrayImage, SimError> {
    options.validate()?;
    let [w, h] = view.image_size;
    if w == 0 || h == 0 || !view.k.is_finite() || view.k.fx <= 0.0 || view.k.fy <= 0.0 {
        return Err(SimError::Render(format!("bad camera: size [{w}, {h}], intrinsics {:?}", view.k)));
    }
    check_invertible(view.distortion, view.k, view.image_size)?;
    let mut image = render_clean(quads, view, options.supersampling)?;
    let (w, h) = (w as usize, h as usize);
    gaussian_blur(&mut image, w, h, options.blur_sigma_px);
    let sigma = options.noise_sigma_grey as f32;
    let data: Vec<u8> = image
        .par_chunks(w)
        .enumerate()
        .flat_map_iter(|(y, row)| {
            let mut rng = (sigma > 0.0).then(|| {
                let mut r = ChaCha8Rng::seed_from_u64(noise_seed);
                r.set_stream(y as u64);
                r
            });
            row.iter()
                .map(move |&v| {
                    let n: f32 = rng.as_mut().map_or(0.0, |r| r.sample::<f32, _>(StandardNormal));
                    (v + sigma * n).round().clamp(0.0, 255.0) as u8
                })
                .collect::<Vec<u8>>()
        })
        .collect();
    GrayImage::new(w as u32, h as u32, data).map_err(|e| SimError::Render(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Scenario, SimulatedHead};
    use headalign_platform::{Encoders, StereoHead};
    use std::collections::HashMap;
    use std::sync::{Arc, Mutex, OnceLock};

    /// A head of `seed` rendering without blur or noise through `distortion`, at its
    /// start. Its textures are baked once per (seed, distortion) and shared by the tests
    /// (each clones a head baked before any render): baking draws from its own stream,
    /// seeded by the scenario alone, so a clone renders what a fresh head would, bit for
    /// bit. `deterministic_with_the_seed_and_noise_advances` builds its heads afresh: it
    /// tests that construction.
    fn clean_head(seed: u64, distortion: Distortion) -> SimulatedHead {
        type Heads = Mutex<HashMap<(u64, LensKind, [u64; 6]), Arc<OnceLock<SimulatedHead>>>>;
        static HEADS: OnceLock<Heads> = OnceLock::new();
        let key = (seed, distortion.kind, distortion.params().map(f64::to_bits));
        let slot = HEADS.get_or_init(Default::default).lock().unwrap().entry(key).or_default().clone();
        slot.get_or_init(|| {
            let render = RenderOptions { distortion, ..RenderOptions::clean() };
            let mut head = SimulatedHead::new(Scenario { seed, render, ..Scenario::default() }).unwrap();
            head.textured_scene();
            head
        })
        .clone()
    }

    /// Bilinear grey value at a sub-pixel position (inside the image).
    fn at(img: &GrayImage, x: f64, y: f64) -> f64 {
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let g = |xi: f64, yi: f64| f64::from(img.get(xi as u32, yi as u32).unwrap_or(0));
        let top = g(x0, y0) * (1.0 - fx) + g(x0 + 1.0, y0) * fx;
        let bottom = g(x0, y0 + 1.0) * (1.0 - fx) + g(x0 + 1.0, y0 + 1.0) * fx;
        top * (1.0 - fy) + bottom * fy
    }

    /// ZNCC of two (2r+1)^2 windows sampled bilinearly at sub-pixel centres.
    fn zncc(a: &GrayImage, pa: Point2<f64>, b: &GrayImage, pb: Point2<f64>, r: i32) -> f64 {
        let (mut va, mut vb) = (Vec::new(), Vec::new());
        for dy in -r..=r {
            for dx in -r..=r {
                va.push(at(a, pa.x + f64::from(dx), pa.y + f64::from(dy)));
                vb.push(at(b, pb.x + f64::from(dx), pb.y + f64::from(dy)));
            }
        }
        let n = va.len() as f64;
        let (ma, mb) = (va.iter().sum::<f64>() / n, vb.iter().sum::<f64>() / n);
        let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
        for (x, y) in va.iter().zip(&vb) {
            sab += (x - ma) * (y - mb);
            saa += (x - ma) * (x - ma);
            sbb += (y - mb) * (y - mb);
        }
        sab / (saa * sbb).sqrt().max(1e-12)
    }

    /// A fisheye-like equidistant lens (Kannala-Brandt coefficients of the size a real
    /// wide-angle lens has, e.g. TUM VI's `pinhole-equi` cameras).
    fn fisheye() -> Distortion {
        Distortion::equidistant([0.0035, 0.0007, -0.0021, 0.0002])
    }

    /// The old simulator lens, written out: `x (1 + k1 r^2 + k2 r^4)`, and its inverse by
    /// Newton on the radius.
    fn two_term(k1: f64, k2: f64, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        let f = 1.0 + k1 * r2 + k2 * r2 * r2;
        (x * f, y * f)
    }

    /// Scenario files with `k1, k2` only: projections (what the point captures see)
    /// agree with the two-term formula within 1e-12 px (not bit for bit: the geometry
    /// crate evaluates `1 + r^2 (k1 + r^2 k2)`, one rounding apart), and the renderer's
    /// sample rays distort back onto their pixels within 1e-11 px (Newton stops at 1e-14
    /// normalised, 7e-12 px at f = 720: the old radial Newton's tolerance too), over a
    /// grid of the image; the pinhole (no table) is bit for bit.
    #[test]
    fn radial_two_term_lens_matches_the_written_out_formula() {
        let k = Scenario::default().left;
        let (k1, k2) = (-0.2, 0.05);
        let d: Distortion =
            toml::from_str::<RenderOptions>("[distortion]\nk1 = -0.2\nk2 = 0.05\n").unwrap().distortion;
        assert_eq!(d, Distortion::radial(k1, k2));
        for iy in 0..=12 {
            for ix in 0..=16 {
                let (px, py) = (f64::from(ix) * 48.0 - 0.5, f64::from(iy) * 48.0 - 0.5);
                let ray = k.unproject(&Point2::new(px, py));
                let p = Point3::new(ray.x * 2.0, ray.y * 2.0, 2.0);
                let (xd, yd) = two_term(k1, k2, ray.x, ray.y);
                let want = Point2::new(k.fx * xd + k.skew * yd + k.cx, k.fy * yd + k.cy);
                let got = project(&k, &d, &p).unwrap();
                assert!((got - want).norm() < 1e-12, "({px}, {py}): {got:?} vs {want:?}");
                // The sample ray of pixel (px, py): distorting it back lands on the pixel.
                let u = d.undistort(&Vector2::new(ray.x, ray.y)).unwrap();
                let (bx, by) = two_term(k1, k2, u.x, u.y);
                let back = Point2::new(k.fx * bx + k.skew * by + k.cx, k.fy * by + k.cy);
                assert!((back - Point2::new(px, py)).norm() < 1e-11, "({px}, {py}): {back:?}");
                let pinhole = project(&k, &Distortion::default(), &p).unwrap();
                assert_eq!(pinhole, k.project_unchecked(&p));
            }
        }
    }

    /// Both models: a pixel's ray through the inverse map projects back onto the pixel
    /// (1e-9 px: Newton stops at 1e-14 normalised), over the whole image; the profile
    /// check accepts realistic lenses and refuses a folding barrel and a fisheye whose
    /// corners would see 90 deg off the axis, with errors, not panics.
    #[test]
    fn render_project_round_trip_and_invertibility_for_both_models() {
        let k = Scenario::default().left;
        let lenses = [
            Distortion::from_params(LensKind::RadialTangential, [-0.3, 0.08, 0.001, -0.0015, 0.01, 0.0]),
            fisheye(),
        ];
        for d in lenses {
            check_invertible(&d, &k, [768, 576]).unwrap();
            for iy in 0..=12 {
                for ix in 0..=16 {
                    let pixel = Point2::new(f64::from(ix) * 48.0 - 0.5, f64::from(iy) * 48.0 - 0.5);
                    let ray = k.unproject(&pixel);
                    let u = d.undistort(&Vector2::new(ray.x, ray.y)).unwrap();
                    let back = project(&k, &d, &Point3::new(u.x * 3.0, u.y * 3.0, 3.0)).unwrap();
                    assert!((back - pixel).norm() < 1e-9, "{d:?} {pixel:?}: {back:?}");
                }
            }
        }
        // Strong barrel folds over: r (1 - r^2) peaks at r = 1/sqrt 3, value 0.385 < 0.68.
        let e = check_invertible(&Distortion::radial(-1.0, 0.0), &k, [768, 576]).unwrap_err();
        assert!(e.to_string().contains("turns back"), "{e}");
        // An equidistant lens at f = 100 px: the corner is 4.8 rad off in theta_d.
        let wide = Intrinsics::new(100.0, 100.0, 384.0, 288.0);
        assert!(check_invertible(&fisheye(), &wide, [768, 576]).is_err());
        assert!(check_invertible(&Distortion::default(), &wide, [768, 576]).is_ok());
    }

    /// The TOML table: `kind` by any name of the lens table (the double sphere's `xi
    /// alpha` too), missing coefficients zero, unknown kinds and keys refused, and a
    /// non-zero coefficient the model does not have refused.
    #[test]
    fn lens_table_reads_every_model() {
        let o: RenderOptions =
            toml::from_str("[distortion]\nkind = \"equidistant\"\nk1 = 0.01\nk4 = 0.001\n").unwrap();
        assert_eq!(o.distortion, Distortion::equidistant([0.01, 0.0, 0.0, 0.001]));
        let o: RenderOptions = toml::from_str("[distortion]\nkind = \"fisheye\"\n").unwrap();
        assert_eq!(o.distortion.kind, LensKind::Equidistant);
        let o: RenderOptions = toml::from_str("[distortion]\nkind = \"radtan\"\np1 = 0.001\n").unwrap();
        assert_eq!(
            o.distortion,
            Distortion::from_params(LensKind::RadialTangential, [0.0, 0.0, 0.001, 0.0, 0.0, 0.0])
        );
        let o: RenderOptions =
            toml::from_str("[distortion]\nkind = \"ds\"\nxi = -0.15\nalpha = 0.55\n").unwrap();
        assert_eq!(o.distortion, Distortion::double_sphere(-0.15, 0.55));
        assert!(toml::from_str::<RenderOptions>("[distortion]\nkind = \"fov\"\n").is_err());
        assert!(toml::from_str::<RenderOptions>("[distortion]\nk5 = 0.1\n").is_err());
        assert!(
            toml::from_str::<RenderOptions>("[distortion]\nkind = \"equidistant\"\np1 = 0.001\n").is_err()
        );
        // Written and read back.
        let o = RenderOptions { distortion: fisheye(), ..RenderOptions::default() };
        let text = toml::to_string(&o).unwrap();
        assert_eq!(toml::from_str::<RenderOptions>(&text).unwrap(), o, "{text}");
    }

    #[test]
    fn image_has_size_and_texture_everywhere() {
        for seed in [1, 2, 3] {
            let mut head = clean_head(seed, Distortion::default());
            let (left, right) = head.render_stereo().unwrap();
            assert_eq!(left.size(), [768, 576]);
            let report = head.textured_scene().report.clone();
            // The photographs are in the repository (data/): all of them load.
            assert_eq!(report.photos_loaded.len(), crate::texture::PHOTO_FILES.len(), "{report:?}");
            assert!(!report.procedural_fallback);
            for img in [&left, &right] {
                let (mut textured, mut blocks) = (0, 0);
                for by in 0..576 / 32 {
                    for bx in 0..768 / 32 {
                        let mut v = Vec::with_capacity(1024);
                        for y in by * 32..by * 32 + 32 {
                            for x in bx * 32..bx * 32 + 32 {
                                v.push(f64::from(img.get(x, y).unwrap()));
                            }
                        }
                        let m = v.iter().sum::<f64>() / 1024.0;
                        let sd = (v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / 1024.0).sqrt();
                        blocks += 1;
                        // 4 grey levels: well above quantisation (0.3), a flat wall would be ~0.
                        if sd > 4.0 {
                            textured += 1;
                        }
                    }
                }
                assert!(textured as f64 > 0.95 * blocks as f64, "seed {seed}: {textured}/{blocks} textured");
            }
        }
    }

    #[test]
    fn procedural_only_also_has_texture() {
        let render = RenderOptions { data_dir: Some("/nonexistent".into()), ..RenderOptions::clean() };
        let mut head = SimulatedHead::new(Scenario { render, ..Scenario::default() }).unwrap();
        let (left, _) = head.render_stereo().unwrap();
        assert!(head.textured_scene().report.procedural_fallback);
        let px = left.pixels();
        let m = px.iter().map(|&v| f64::from(v)).sum::<f64>() / px.len() as f64;
        let sd = (px.iter().map(|&v| (f64::from(v) - m).powi(2)).sum::<f64>() / px.len() as f64).sqrt();
        assert!(sd > 15.0, "{sd}");
    }

    /// Left and right patches at the exact projections of scene points correlate, and the
    /// correlation peaks at the projection: the renderer and the camera model agree.
    fn check_consistency(head: &mut SimulatedHead, enc: &Encoders) {
        let (left, right) = head
            .render_stereo_with(
                enc,
                &RenderOptions { distortion: head.scenario().render.distortion, ..RenderOptions::clean() },
                0,
            )
            .unwrap();
        let points: Vec<Point3<f64>> = head.scene_points().iter().map(|(_, p)| *p).collect();
        let (mut checked, mut good) = (0, 0);
        let mut offsets = Vec::new();
        for p in points {
            let (Some(pl), Some(pr)) = head.exact_pixels(enc, &p) else { continue };
            let inside = |q: &Point2<f64>| q.x > 12.0 && q.y > 12.0 && q.x < 755.0 && q.y < 563.0;
            if !inside(&pl) || !inside(&pr) {
                continue;
            }
            checked += 1;
            let r = 5;
            let c0 = zncc(&left, pl, &right, pr, r);
            // Sub-pixel peak along x and y by a parabola through shifts -1, 0, +1.
            let peak = |axis: Vector3<f64>| {
                let s =
                    |d: f64| zncc(&left, pl, &right, Point2::new(pr.x + d * axis.x, pr.y + d * axis.y), r);
                let (m, p) = (s(-1.0), s(1.0));
                let curv = m + p - 2.0 * c0;
                (c0 > m && c0 > p, if curv < 0.0 { 0.5 * (m - p) / curv } else { 1.0 })
            };
            let (okx, dx) = peak(Vector3::x());
            let (oky, dy) = peak(Vector3::y());
            if c0 > 0.8 && okx && oky {
                good += 1;
                offsets.push(dx.abs().max(dy.abs()));
            }
        }
        assert!(checked >= 50, "{checked}");
        // Some points are hidden from one camera by a box edge (first hits from the head
        // centre only) or sit on a surface boundary: most, not all, must pass.
        assert!(good as f64 >= 0.85 * checked as f64, "{good}/{checked}");
        offsets.sort_by(f64::total_cmp);
        let median = offsets[offsets.len() / 2];
        assert!(median < 0.2, "median sub-pixel peak offset {median}");
    }

    #[test]
    fn left_right_patches_agree_at_the_projections() {
        for seed in [1, 4] {
            let mut head = clean_head(seed, Distortion::default());
            check_consistency(&mut head, &Encoders::default());
            check_consistency(
                &mut head,
                &Encoders { pan: 10.0, elevation: -3.0, verge_left: 2.0, verge_right: -1.0 },
            );
        }
    }

    #[test]
    fn distorted_images_agree_with_the_distorted_projection() {
        let mut head = clean_head(2, Distortion::radial(-0.2, 0.05));
        check_consistency(&mut head, &Encoders::default());
    }

    /// An equidistant (fisheye) image: the patches at the projections of the scene
    /// points correlate left to right and peak there, out to the image corners (points
    /// 12 px from the border), so the rendered image's content lands where [`project`]
    /// says; a radial-tangential lens with tangential terms likewise.
    #[test]
    fn equidistant_images_agree_with_the_projection() {
        let mut head = clean_head(2, fisheye());
        check_consistency(&mut head, &Encoders::default());
        let tangential =
            Distortion::from_params(LensKind::RadialTangential, [-0.3, 0.08, 0.001, -0.0015, 0.0, 0.0]);
        let mut head = clean_head(3, tangential);
        check_consistency(&mut head, &Encoders::default());
    }

    #[test]
    fn deterministic_with_the_seed_and_noise_advances() {
        let mut a = SimulatedHead::new(Scenario::default()).unwrap();
        let mut b = SimulatedHead::new(Scenario::default()).unwrap();
        let first = a.render_stereo().unwrap();
        assert_eq!(first, b.render_stereo().unwrap());
        // The next render draws new noise.
        let second = a.render_stereo().unwrap();
        assert_ne!(first.0, second.0);
        let diff: f64 = first
            .0
            .pixels()
            .iter()
            .zip(second.0.pixels())
            .map(|(&x, &y)| (f64::from(x) - f64::from(y)).powi(2))
            .sum::<f64>()
            / first.0.pixels().len() as f64;
        // Two independent noises of 2 grey levels: difference variance 8 (plus rounding).
        assert!((diff.sqrt() - 8f64.sqrt()).abs() < 0.3, "{}", diff.sqrt());
        let mut c = SimulatedHead::new(Scenario::default().with_seed(2)).unwrap();
        assert_ne!(first, c.render_stereo().unwrap());
        // Moving the head changes the view.
        a.move_to(&Encoders { pan: 5.0, ..Encoders::default() }).unwrap();
        let opts = RenderOptions::clean();
        let moved = a.render_stereo_with(&a.encoders(), &opts, 0).unwrap();
        let still = b.render_stereo_with(&Encoders::default(), &opts, 0).unwrap();
        assert_ne!(moved.0, still.0);
    }

    #[test]
    fn distortion_changes_pixels_away_from_the_centre_only() {
        let mut head = clean_head(1, Distortion::default());
        let enc = Encoders::default();
        let plain = head.render_stereo_with(&enc, &RenderOptions::clean(), 0).unwrap().0;
        let d = RenderOptions { distortion: Distortion::radial(-0.2, 0.0), ..RenderOptions::clean() };
        let distorted = head.render_stereo_with(&enc, &d, 0).unwrap().0;
        let k = head.truth().left;
        let (mut centre_max, mut far_diff, mut far_n) = (0i32, 0.0, 0);
        for y in 0..576u32 {
            for x in 0..768u32 {
                let r = ((f64::from(x) - k.cx).powi(2) + (f64::from(y) - k.cy).powi(2)).sqrt();
                let diff =
                    (i32::from(plain.get(x, y).unwrap()) - i32::from(distorted.get(x, y).unwrap())).abs();
                if r < 3.0 {
                    centre_max = centre_max.max(diff);
                } else if r > 250.0 {
                    far_diff += f64::from(diff);
                    far_n += 1;
                }
            }
        }
        // Within 3 px of the principal point the shift is < 3 * 0.2 * (3/700)^2 px.
        assert!(centre_max <= 1, "{centre_max}");
        assert!(far_diff / f64::from(far_n) > 5.0, "{}", far_diff / f64::from(far_n));
        // Not invertible over the image: an error, not a panic.
        let bad = RenderOptions { distortion: Distortion::radial(-1.9, 0.0), ..RenderOptions::clean() };
        assert!(matches!(head.render_stereo_with(&enc, &bad, 0), Err(SimError::Render(_))));
    }

    #[test]
    fn options_validate_names_fields() {
        RenderOptions::default().validate().unwrap();
        let bad = RenderOptions {
            supersampling: 0,
            blur_sigma_px: -1.0,
            noise_sigma_grey: f64::NAN,
            metres_per_texel: 0.0,
            distortion: Distortion::radial(f64::INFINITY, 0.0),
            ..RenderOptions::default()
        };
        let Err(SimError::InvalidScenario(msg)) = bad.validate() else { panic!("accepted") };
        for key in ["supersampling", "blur_sigma_px", "noise_sigma_grey", "metres_per_texel", "distortion"] {
            assert!(msg.contains(key), "{key}: {msg}");
        }
    }
}
