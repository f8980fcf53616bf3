//! Textures for the rendered room: one baked, mip-mapped grey texture per surface.
//!
//! Each surface ([`crate::quad::PlanarQuad`]) gets its own texture covering it at
//! `metres_per_texel` (default 5 mm), so nothing repeats across surfaces and the scene
//! has texture at every scale. A texel value is
//! `128 + 36 * (gain * (photo + noise + patches) + offset)`, clamped to `[0, 255]`:
//! - `photo`: one of the texture photographs of the repository's `data/` folder
//!   (`opencv_samples/textures`, `skimage_data/textures`; their READMEs credit them), turned
//!   grey, normalised to zero mean and unit standard deviation, tiled (repeat) at a random
//!   scale of 1 to 2 texels per photo pixel (never minified, so baking does not alias)
//!   and a random offset. If no photograph can be read, a procedural mosaic (random grey
//!   cells of 4 to 12 cm) takes its place and the [`TextureReport`] says so.
//! - `noise`: value noise (white noise on a square lattice, bilinearly interpolated) at
//!   wavelengths 1.5 cm, 5 cm, 18 cm, 60 cm and 2 m, so that no area is flat at any
//!   viewing distance of the scene (1.5 to 6 m: one pixel is 2 to 9 mm).
//! - `patches`: random rectangles (5 to 50 cm, about 2 per square metre) shifted up or
//!   down in grey: straight edges and corners, as posters and furniture give.
//! - `gain`, `offset`: per surface, so that neighbouring surfaces differ in brightness and
//!   contrast (faces of a box are distinguishable).
//!
//! Mip-mapping: level `l + 1` is the 2x2 box average of level `l` (odd sides: the last
//! texel is repeated), down to one texel. [`Texture::sample`] is trilinear: bilinear in
//! the two levels nearest `log2(footprint in texels)`, blended. Texel `(i, j)` covers
//! `[i, i + 1) x [j, j + 1)` in texture coordinates (its centre at `i + 0.5`); outside
//! the texture, coordinates are clamped.
//!
//! Randomness: everything is drawn from the RNG handed to [`bake_textures`], so the same
//! seed gives the same textures. Pitfall: baking takes about 0.1 s for the default room
//! (about 10 million texels, parallel over rows); the simulated head bakes lazily, on the
//! first render only.

use std::path::{Path, PathBuf};

use headalign_vision::GrayImage;
use rand::{Rng, RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::quad::PlanarQuad;

/// The photograph files looked for under the data directory (relative paths).
pub const PHOTO_FILES: [&str; 12] = [
    "opencv_samples/textures/baboon.jpg",
    "opencv_samples/textures/building.jpg",
    "opencv_samples/textures/fruits.jpg",
    "opencv_samples/textures/starry_night.jpg",
    "skimage_data/textures/astronaut.png",
    "skimage_data/textures/brick.png",
    "skimage_data/textures/camera.png",
    "skimage_data/textures/chelsea.png",
    "skimage_data/textures/coffee.png",
    "skimage_data/textures/grass.png",
    "skimage_data/textures/gravel.png",
    "skimage_data/textures/rocket.jpg",
];

/// The default data directory: `data/` at the workspace root (data/README.md). The path
/// is fixed at build time, so a built or installed binary reads the photographs of the
/// checkout it was built from; without them [`bake_textures`] falls back to procedural
/// textures and its [`TextureReport`] says so.
pub fn default_data_dir() -> PathBuf {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../../data")).to_path_buf()
}

/// What the texture baking used.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TextureReport {
    /// The data directory searched for photographs (`None` if photographs were not wanted).
    pub data_dir: Option<PathBuf>,
    /// Photographs loaded (relative paths).
    pub photos_loaded: Vec<String>,
    /// Photographs that could not be read, with the reason.
    pub photos_failed: Vec<(String, String)>,
    /// True if no photograph was available and the procedural mosaic replaced them.
    pub procedural_fallback: bool,
    /// Total texels at level 0 over all surfaces.
    pub texels: usize,
}

/// A photograph as zero-mean, unit-variance grey values.
#[derive(Clone)]
struct Photo {
    width: usize,
    height: usize,
    data: Vec<f32>,
}

impl Photo {
    fn from_gray(img: &GrayImage) -> Option<Self> {
        let data: Vec<f32> = img.pixels().iter().map(|&v| f32::from(v)).collect();
        let n = data.len() as f64;
        let mean = data.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
        let var = data.iter().map(|&v| (f64::from(v) - mean).powi(2)).sum::<f64>() / n;
        if var.is_nan() || var <= 1.0 {
            return None;
        }
        let (mean, inv_std) = (mean as f32, (1.0 / var.sqrt()) as f32);
        Some(Self {
            width: img.width() as usize,
            height: img.height() as usize,
            data: data.into_iter().map(|v| (v - mean) * inv_std).collect(),
        })
    }

    /// Bilinear sample with wrap-around; `x`, `y` in photo pixels (centres at integers).
    fn sample_wrapped(&self, x: f32, y: f32) -> f32 {
        let (w, h) = (self.width as f32, self.height as f32);
        let x = x.rem_euclid(w);
        let y = y.rem_euclid(h);
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (x0, y0) = ((x0 as usize).min(self.width - 1), (y0 as usize).min(self.height - 1));
        let x1 = if x0 + 1 == self.width { 0 } else { x0 + 1 };
        let y1 = if y0 + 1 == self.height { 0 } else { y0 + 1 };
        let at = |xi: usize, yi: usize| self.data[yi * self.width + xi];
        let top = at(x0, y0) + fx * (at(x1, y0) - at(x0, y0));
        let bottom = at(x0, y1) + fx * (at(x1, y1) - at(x0, y1));
        top + fy * (bottom - top)
    }
}

/// Load the photographs found under `data_dir`; the report lists what was read.
fn load_photos(data_dir: &Path, report: &mut TextureReport) -> Vec<Photo> {
    let mut photos = Vec::new();
    for rel in PHOTO_FILES {
        match GrayImage::load(&data_dir.join(rel)) {
            Ok(img) => match Photo::from_gray(&img) {
                Some(p) => {
                    photos.push(p);
                    report.photos_loaded.push(rel.to_string());
                }
                None => report.photos_failed.push((rel.to_string(), "flat image".to_string())),
            },
            Err(e) => report.photos_failed.push((rel.to_string(), e.to_string())),
        }
    }
    photos
}

/// One mip level, row-major grey texels.
#[derive(Clone)]
struct MipLevel {
    width: usize,
    height: usize,
    data: Vec<u8>,
}

impl MipLevel {
    #[inline]
    fn bilinear(&self, s: f32, t: f32) -> f32 {
        // Texel centres at i + 0.5.
        let x = (s - 0.5).clamp(0.0, (self.width - 1) as f32);
        let y = (t - 0.5).clamp(0.0, (self.height - 1) as f32);
        let (x0, y0) = (x as usize, y as usize);
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let x1 = (x0 + 1).min(self.width - 1);
        let y1 = (y0 + 1).min(self.height - 1);
        let (r0, r1) = (y0 * self.width, y1 * self.width);
        let d = &self.data;
        let a = f32::from(d[r0 + x0]);
        let b = f32::from(d[r0 + x1]);
        let c = f32::from(d[r1 + x0]);
        let e = f32::from(d[r1 + x1]);
        let top = a + fx * (b - a);
        let bottom = c + fx * (e - c);
        top + fy * (bottom - top)
    }

    fn half(&self) -> Self {
        let (w, h) = (self.width.div_ceil(2).max(1), self.height.div_ceil(2).max(1));
        let mut data = vec![0u8; w * h];
        for (j, row) in data.chunks_mut(w).enumerate() {
            let (y0, y1) = ((2 * j).min(self.height - 1), (2 * j + 1).min(self.height - 1));
            for (i, out) in row.iter_mut().enumerate() {
                let (x0, x1) = ((2 * i).min(self.width - 1), (2 * i + 1).min(self.width - 1));
                let sum = u32::from(self.data[y0 * self.width + x0])
                    + u32::from(self.data[y0 * self.width + x1])
                    + u32::from(self.data[y1 * self.width + x0])
                    + u32::from(self.data[y1 * self.width + x1]);
                *out = ((sum + 2) / 4) as u8;
            }
        }
        Self { width: w, height: h, data }
    }
}

/// A mip-mapped grey texture (level 0 first).
#[derive(Clone)]
pub struct Texture {
    levels: Vec<MipLevel>,
}

impl std::fmt::Debug for Texture {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let [w, h] = self.size();
        write!(f, "Texture({w}x{h}, {} levels)", self.levels.len())
    }
}

impl Texture {
    /// A texture from level-0 texels (row-major); `None` if the sizes do not match or a
    /// side is zero. The mip levels are built here.
    pub fn from_texels(width: usize, height: usize, data: Vec<u8>) -> Option<Self> {
        if width == 0 || height == 0 || data.len() != width * height {
            return None;
        }
        let mut levels = vec![MipLevel { width, height, data }];
        while let Some(last) = levels.last() {
            if last.width == 1 && last.height == 1 {
                break;
            }
            let next = last.half();
            levels.push(next);
        }
        Some(Self { levels })
    }

    /// `[width, height]` of level 0, texels.
    pub fn size(&self) -> [usize; 2] {
        [self.levels[0].width, self.levels[0].height]
    }

    /// Number of mip levels.
    pub fn levels(&self) -> usize {
        self.levels.len()
    }

    /// Level-0 texels, row-major.
    pub fn texels(&self) -> &[u8] {
        &self.levels[0].data
    }

    /// Trilinear sample at texture coordinates `(s, t)` (level-0 texels) for a footprint
    /// of `footprint` level-0 texels per sample (1 or less: plain bilinear at level 0).
    #[inline]
    pub fn sample(&self, s: f32, t: f32, footprint: f32) -> f32 {
        let lod = if footprint > 1.0 { footprint.log2() } else { 0.0 };
        let max_level = (self.levels.len() - 1) as f32;
        let lod = lod.min(max_level);
        let l0 = lod.floor();
        let frac = lod - l0;
        let l0 = l0 as usize;
        let scale0 = 1.0 / (1u32 << l0) as f32;
        let v0 = self.levels[l0].bilinear(s * scale0, t * scale0);
        if frac < 1e-3 || l0 + 1 >= self.levels.len() {
            return v0;
        }
        let v1 = self.levels[l0 + 1].bilinear(s * scale0 * 0.5, t * scale0 * 0.5);
        v0 + frac * (v1 - v0)
    }
}

/// A surface with its texture: texture coordinates of the point `corner + a u + b v` are
/// `(a, b) / metres_per_texel`.
#[derive(Clone, Debug)]
pub struct TexturedQuad {
    /// The geometry, world frame.
    pub quad: PlanarQuad,
    /// The texture (level 0 covers the whole quad).
    pub texture: std::sync::Arc<Texture>,
    /// Texture scale, metres per level-0 texel.
    pub metres_per_texel: f64,
}

/// The rendered world: the room's quads with their textures, and how they were made.
#[derive(Clone, Debug)]
pub struct TexturedScene {
    /// Floor, ceiling, walls, then the boxes' faces (as [`crate::scene::Room::quads`]).
    pub quads: Vec<TexturedQuad>,
    /// What the baking used (photographs or the procedural fallback).
    pub report: TextureReport,
}

/// Value-noise octave: lattice of uniform values of unit variance, spacing `cells_per_texel^-1`.
struct Octave {
    cols: usize,
    values: Vec<f32>,
    cells_per_texel: f32,
    amplitude: f32,
}

impl Octave {
    fn new(width: usize, height: usize, wavelength_texels: f32, amplitude: f32, rng: &mut impl Rng) -> Self {
        let cells_per_texel = 1.0 / wavelength_texels.max(1.0);
        let cols = (width as f32 * cells_per_texel).ceil() as usize + 2;
        let rows = (height as f32 * cells_per_texel).ceil() as usize + 2;
        // Uniform on [-sqrt 3, sqrt 3]: unit variance.
        let values = (0..cols * rows).map(|_| (rng.random::<f32>() * 2.0 - 1.0) * 1.732).collect();
        Self { cols, values, cells_per_texel, amplitude }
    }

    /// Add this octave to one texture row.
    fn add_row(&self, j: usize, row: &mut [f32]) {
        let y = j as f32 * self.cells_per_texel;
        let y0 = y as usize;
        let fy = y - y0 as f32;
        let (r0, r1) = (&self.values[y0 * self.cols..], &self.values[(y0 + 1) * self.cols..]);
        for (i, out) in row.iter_mut().enumerate() {
            let x = i as f32 * self.cells_per_texel;
            let x0 = x as usize;
            let fx = x - x0 as f32;
            let top = r0[x0] + fx * (r0[x0 + 1] - r0[x0]);
            let bottom = r1[x0] + fx * (r1[x0 + 1] - r1[x0]);
            *out += self.amplitude * (top + fy * (bottom - top));
        }
    }
}

/// Noise wavelengths (metres) and amplitudes (in units of the photo's standard deviation).
const OCTAVES: [(f64, f32); 5] = [(0.015, 0.35), (0.05, 0.4), (0.18, 0.4), (0.6, 0.35), (2.0, 0.3)];
/// Grey level per unit of the texture signal.
const CONTRAST: f32 = 36.0;
/// Largest texture side; larger quads get coarser texels.
const MAX_SIDE: usize = 4096;

/// Bake one texture per quad. `data_dir = None` means procedural only. The RNG draws
/// every random choice (photo, scale, offset, noise, patches, gain) in quad order.
pub fn bake_textures(
    quads: &[PlanarQuad],
    metres_per_texel: f64,
    data_dir: Option<&Path>,
    rng: &mut ChaCha8Rng,
) -> (Vec<TexturedQuad>, TextureReport) {
    let scales = vec![metres_per_texel; quads.len()];
    bake_textures_scaled(quads, &scales, data_dir, rng)
}

/// [`bake_textures`] with a texel size per quad (`metres_per_texel[i]` for `quads[i]`;
/// missing entries take the last). The random draws are the same whatever the sizes.
pub fn bake_textures_scaled(
    quads: &[PlanarQuad],
    metres_per_texel: &[f64],
    data_dir: Option<&Path>,
    rng: &mut ChaCha8Rng,
) -> (Vec<TexturedQuad>, TextureReport) {
    let mut report = TextureReport { data_dir: data_dir.map(Path::to_path_buf), ..Default::default() };
    let photos = data_dir.map(|d| load_photos(d, &mut report)).unwrap_or_default();
    report.procedural_fallback = photos.is_empty();
    let mut out = Vec::with_capacity(quads.len());
    for (i, quad) in quads.iter().enumerate() {
        let wanted = metres_per_texel.get(i).or(metres_per_texel.last()).copied().unwrap_or(0.005);
        let mpt = wanted.max(quad.size_m[0].max(quad.size_m[1]) / (MAX_SIDE - 2) as f64);
        let width = (quad.size_m[0] / mpt).ceil() as usize + 1;
        let height = (quad.size_m[1] / mpt).ceil() as usize + 1;
        let mut quad_rng = ChaCha8Rng::seed_from_u64(rng.random::<u64>());
        let texels = bake_one(width, height, mpt, &photos, &mut quad_rng);
        report.texels += texels.len();
        if let Some(texture) = Texture::from_texels(width, height, texels) {
            out.push(TexturedQuad {
                quad: *quad,
                texture: std::sync::Arc::new(texture),
                metres_per_texel: mpt,
            });
        }
    }
    (out, report)
}

/// Level-0 texels of one surface of `width x height` texels of `mpt` metres.
fn bake_one(width: usize, height: usize, mpt: f64, photos: &[Photo], rng: &mut ChaCha8Rng) -> Vec<u8> {
    let octaves: Vec<Octave> =
        OCTAVES.iter().map(|&(wl, amp)| Octave::new(width, height, (wl / mpt) as f32, amp, rng)).collect();
    let gain = 0.75 + 0.5 * rng.random::<f32>();
    let offset = 0.8 * (rng.random::<f32>() - 0.5);
    // Base layer: photo (tiled) or procedural mosaic.
    let photo = (!photos.is_empty()).then(|| {
        let idx = rng.random_range(0..photos.len());
        let texels_per_pixel = 1.0 + 0.5 * rng.random::<f32>();
        let (ox, oy) = (rng.random::<f32>() * 1000.0, rng.random::<f32>() * 1000.0);
        (&photos[idx], 1.0 / texels_per_pixel, ox, oy)
    });
    let mosaic = photo.is_none().then(|| {
        let cell_m = 0.04 + 0.08 * rng.random::<f64>();
        Octave::new(width, height, (cell_m / mpt) as f32, 0.8, rng)
    });
    let mut signal = vec![0f32; width * height];
    signal.par_chunks_mut(width).enumerate().for_each(|(j, row)| {
        if let Some((p, pixels_per_texel, ox, oy)) = &photo {
            let y = j as f32 * pixels_per_texel + oy;
            for (i, out) in row.iter_mut().enumerate() {
                *out = p.sample_wrapped(i as f32 * pixels_per_texel + ox, y);
            }
        }
        if let Some(m) = &mosaic {
            // Nearest cell (blocky): a mosaic of constant cells with sharp edges.
            let y = (j as f32 * m.cells_per_texel) as usize;
            for (i, out) in row.iter_mut().enumerate() {
                let x = (i as f32 * m.cells_per_texel) as usize;
                *out += m.amplitude * m.values[y * m.cols + x];
            }
        }
        for o in &octaves {
            o.add_row(j, row);
        }
    });
    // Patches: about 2 per square metre, 5 to 50 cm.
    let area = width as f64 * height as f64 * mpt * mpt;
    let count = (2.0 * area).round() as usize + 1;
    for _ in 0..count {
        let (sw, sh) = (0.05 + 0.45 * rng.random::<f64>(), 0.05 + 0.45 * rng.random::<f64>());
        let (pw, ph) = (((sw / mpt) as usize).max(1), ((sh / mpt) as usize).max(1));
        let x0 = rng.random_range(0..width);
        let y0 = rng.random_range(0..height);
        let shift = if rng.random::<bool>() { 0.6 } else { -0.6 } * (0.5 + rng.random::<f32>());
        for row in signal.chunks_mut(width).skip(y0).take(ph) {
            for v in row.iter_mut().skip(x0).take(pw) {
                *v += shift;
            }
        }
    }
    signal
        .into_iter()
        .map(|v| (128.0 + CONTRAST * (gain * v + offset)).round().clamp(0.0, 255.0) as u8)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mip_levels_average_and_sampling_is_exact_on_ramps() {
        // A horizontal ramp: bilinear sampling reproduces it exactly inside.
        let (w, h) = (64usize, 8usize);
        let data: Vec<u8> = (0..w * h).map(|k| (k % w) as u8 * 2).collect();
        let t = Texture::from_texels(w, h, data).unwrap();
        assert_eq!(t.levels(), 7);
        for s in [3.0f32, 10.25, 40.5, 60.0] {
            let expected = 2.0 * (s - 0.5);
            assert!((t.sample(s, 4.0, 1.0) - expected).abs() < 1e-4, "{s}");
        }
        // Level 1 of a ramp is the ramp at half resolution: trilinear agrees to rounding.
        for s in [8.0f32, 20.0, 40.0] {
            assert!((t.sample(s, 4.0, 2.0) - t.sample(s, 4.0, 1.0)).abs() < 1.01, "{s}");
        }
        assert!(Texture::from_texels(0, 3, vec![]).is_none());
        assert!(Texture::from_texels(2, 2, vec![0; 3]).is_none());
    }

    #[test]
    fn procedural_fallback_when_the_folder_is_missing() {
        let quad = PlanarQuad {
            corner: nalgebra::Point3::origin(),
            u: nalgebra::Vector3::x(),
            v: nalgebra::Vector3::y(),
            size_m: [1.0, 0.5],
        };
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let missing = Path::new("/nonexistent/headalign/data");
        let (tex, report) = bake_textures(&[quad], 0.005, Some(missing), &mut rng);
        assert!(report.procedural_fallback);
        assert_eq!(report.photos_failed.len(), PHOTO_FILES.len());
        assert_eq!(tex.len(), 1);
        assert_eq!(tex[0].texture.size(), [201, 101]);
        let px = tex[0].texture.texels();
        let mean = px.iter().map(|&v| f64::from(v)).sum::<f64>() / px.len() as f64;
        let sd = (px.iter().map(|&v| (f64::from(v) - mean).powi(2)).sum::<f64>() / px.len() as f64).sqrt();
        assert!(sd > 15.0, "{sd}");
    }
}
