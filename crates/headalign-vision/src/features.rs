//! Corners and binary descriptors: FAST-9 corners ranked by the Harris response, spread
//! over the image by grid bucketing, refined to sub-pixel, and described by a 256-bit
//! BRIEF descriptor on a smoothed image.
//!
//! Why these (accuracy and speed for the alignment procedure):
//! - **FAST-9** (Rosten and Drummond 2006): a pixel is a corner candidate if 9 contiguous
//!   pixels of the radius-3 Bresenham circle are all brighter than `centre + t` or all darker
//!   than `centre - t`. A two-step early rejection (pixels 0/8, then 4/12: a 9-arc always
//!   contains one of two opposite pixels) discards most pixels after two reads; the 9-arc is
//!   then a bit test on a 16-bit mask. Candidates get the SAD score (sum of `|p - c| - t` over
//!   the arc's polarity) for 3x3 non-maximum suppression.
//! - **Harris ranking** (as ORB): FAST responds to edges and noise too; the Harris response
//!   `det(M) - k tr(M)^2` (`k` = 0.04, `M` = sum of gradient outer products over a 7x7
//!   window, central differences) ranks the survivors by corner strength; `R <= 0` (edges,
//!   flat) is dropped.
//! - **Grid bucketing**: cells of `grid_cell` pixels each get an equal quota of the
//!   strongest corners first, the remaining slots go to the strongest leftovers, so
//!   features cover the image (good for the fundamental matrix and for stereo overlap).
//! - **Sub-pixel**: a separable parabola through the Harris response at the 3x3 pixels
//!   around the corner (clamped to +-0.5 px). Cheap (about 2000 flops per kept corner).
//! - **BRIEF-256** (Calonder et al. 2010): 256 intensity comparisons between point pairs
//!   drawn once (fixed seed) from an isotropic Gaussian of standard deviation 31/5 px,
//!   clipped to +-13 px, on the image smoothed by the 9-tap binomial kernel (sigma = 1.41
//!   px, integer arithmetic). **Not steered**: head rotations between views are a few
//!   degrees at most, where unsteered BRIEF matches as well as ORB's steered version and
//!   is cheaper and more distinctive (steering costs the orientation estimate and some
//!   discriminative power). It is not rotation invariant beyond roughly +-10 degrees.
//!
//! Units: positions in pixels (`(0, 0)` = centre of the top-left pixel), FAST threshold in
//! grey levels, descriptor distances in bits (Hamming, 0..256).
//!
//! Pitfalls: no scale pyramid (the head's zoom does not change, so one scale suffices);
//! corners closer than `border` (16 px) to the edge are not reported, since the descriptor
//! pattern needs that margin; a blank image gives no features (not an error).

use rayon::prelude::*;

use crate::{GrayImage, VisionError};

/// FAST circle of radius 3, clockwise from the top.
const CIRCLE: [(isize, isize); 16] = [
    (0, -3),
    (1, -3),
    (2, -2),
    (3, -1),
    (3, 0),
    (3, 1),
    (2, 2),
    (1, 3),
    (0, 3),
    (-1, 3),
    (-2, 2),
    (-3, 1),
    (-3, 0),
    (-3, -1),
    (-2, -2),
    (-1, -3),
];

/// Smallest border that keeps FAST, Harris, sub-pixel and BRIEF inside the image.
pub const MIN_BORDER: usize = 16;

/// A detected corner.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Keypoint {
    /// Column, pixels (sub-pixel if refined).
    pub x: f32,
    /// Row, pixels.
    pub y: f32,
    /// Harris response at the integer position (grey levels^4; larger = stronger).
    pub response: f32,
}

/// A 256-bit binary descriptor.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub struct Descriptor(pub [u64; 4]);

impl Descriptor {
    /// Hamming distance in bits (0..256).
    #[inline]
    pub fn hamming(&self, other: &Descriptor) -> u32 {
        (self.0[0] ^ other.0[0]).count_ones()
            + (self.0[1] ^ other.0[1]).count_ones()
            + (self.0[2] ^ other.0[2]).count_ones()
            + (self.0[3] ^ other.0[3]).count_ones()
    }
}

/// Keypoints and their descriptors (same order, same length).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Features {
    /// The corners, strongest first.
    pub keypoints: Vec<Keypoint>,
    /// One descriptor per keypoint.
    pub descriptors: Vec<Descriptor>,
}

impl Features {
    /// Number of features.
    pub fn len(&self) -> usize {
        self.keypoints.len()
    }

    /// True if there are none.
    pub fn is_empty(&self) -> bool {
        self.keypoints.is_empty()
    }
}

/// Options of [`detect_and_describe`].
#[derive(Clone, Debug, PartialEq)]
pub struct FeatureOptions {
    /// FAST threshold, grey levels (default 20, as OpenCV's ORB). If fewer than
    /// `max_features / 2` candidates survive, detection is rerun once at half the threshold.
    pub fast_threshold: u8,
    /// Maximum number of features kept (default 1000).
    pub max_features: usize,
    /// Bucketing cell side, pixels (default 64; 0 disables bucketing).
    pub grid_cell: usize,
    /// Corners closer than this to the border are dropped (default and minimum 16).
    pub border: usize,
    /// Harris `k` (default 0.04).
    pub harris_k: f32,
    /// Refine positions to sub-pixel (default true).
    pub subpixel: bool,
}

impl Default for FeatureOptions {
    fn default() -> Self {
        Self {
            fast_threshold: 20,
            max_features: 1000,
            grid_cell: 64,
            border: MIN_BORDER,
            harris_k: 0.04,
            subpixel: true,
        }
    }
}

impl FeatureOptions {
    /// Check the options.
    pub fn validate(&self) -> Result<(), VisionError> {
        let bad = |m: String| Err(VisionError::InvalidOptions(m));
        if self.fast_threshold == 0 {
            return bad("fast_threshold must be at least 1".into());
        }
        if self.max_features == 0 {
            return bad("max_features must be at least 1".into());
        }
        if self.border < MIN_BORDER {
            return bad(format!("border must be at least {MIN_BORDER}, got {}", self.border));
        }
        if !(self.harris_k.is_finite() && self.harris_k > 0.0 && self.harris_k < 0.25) {
            return bad(format!("harris_k must be in (0, 0.25), got {}", self.harris_k));
        }
        Ok(())
    }
}

/// FAST-9 score map of one row (`0` = not a corner).
fn fast_row(img: &[u8], w: usize, y: usize, border: usize, t: i16, out: &mut [u16]) {
    let off: [isize; 16] = CIRCLE.map(|(dx, dy)| dy * w as isize + dx);
    let base = (y * w) as isize;
    for x in border..w - border {
        let i = base + x as isize;
        let c = i16::from(img[i as usize]);
        let (hi, lo) = (c + t, c - t);
        let px = |k: usize| i16::from(img[(i + off[k]) as usize]);
        let (p0, p8) = (px(0), px(8));
        if !(p0 > hi || p8 > hi || p0 < lo || p8 < lo) {
            continue;
        }
        let (p4, p12) = (px(4), px(12));
        let nb = u8::from(p0 > hi) + u8::from(p4 > hi) + u8::from(p8 > hi) + u8::from(p12 > hi);
        let nd = u8::from(p0 < lo) + u8::from(p4 < lo) + u8::from(p8 < lo) + u8::from(p12 < lo);
        if nb < 2 && nd < 2 {
            continue;
        }
        let (mut mb, mut md) = (0u32, 0u32);
        let (mut sb, mut sd) = (0u16, 0u16);
        for k in 0..16 {
            let p = px(k);
            if p > hi {
                mb |= 1 << k;
                sb += (p - hi) as u16;
            } else if p < lo {
                md |= 1 << k;
                sd += (lo - p) as u16;
            }
        }
        let arc9 = |m: u32| {
            let m = m | (m << 16);
            let mut r = m;
            for k in 1..9 {
                r &= m >> k;
            }
            r != 0
        };
        let mut s = 0u16;
        if arc9(mb) {
            s = sb + 1;
        }
        if arc9(md) {
            s = s.max(sd + 1);
        }
        out[x] = s;
    }
}

/// Gradient-product sums `(sxx, syy, sxy)` over the `(2r+1)^2` window at `(x, y)`.
#[inline]
fn structure(img: &[u8], w: usize, x: usize, y: usize, r: usize) -> (f32, f32, f32) {
    let (mut a, mut b, mut c) = (0i32, 0i32, 0i32);
    for yy in y - r..=y + r {
        let row = &img[yy * w..(yy + 1) * w];
        let up = &img[(yy - 1) * w..yy * w];
        let dn = &img[(yy + 1) * w..(yy + 2) * w];
        for xx in x - r..=x + r {
            let gx = i32::from(row[xx + 1]) - i32::from(row[xx - 1]);
            let gy = i32::from(dn[xx]) - i32::from(up[xx]);
            a += gx * gx;
            b += gy * gy;
            c += gx * gy;
        }
    }
    (a as f32, b as f32, c as f32)
}

#[inline]
fn harris(img: &[u8], w: usize, x: usize, y: usize, k: f32) -> f32 {
    let (a, b, c) = structure(img, w, x, y, 3);
    a * b - c * c - k * (a + b) * (a + b)
}

/// Separable parabola vertex through three samples (offset of the maximum, clamped).
fn parabola(l: f32, c: f32, r: f32) -> f32 {
    let den = l - 2.0 * c + r;
    if den < 0.0 { (0.5 * (l - r) / den).clamp(-0.5, 0.5) } else { 0.0 }
}

/// Smooth with the 9-tap binomial kernel `[1 8 28 56 70 56 28 8 1] / 256` in x and y
/// (integer arithmetic, borders replicated).
fn smooth_binomial9(img: &GrayImage) -> Vec<u8> {
    const K: [u32; 9] = [1, 8, 28, 56, 70, 56, 28, 8, 1];
    let (w, h) = (img.width() as usize, img.height() as usize);
    let src = img.pixels();
    let mut tmp = vec![0u16; w * h];
    let hpass = |(y, dst): (usize, &mut [u16])| {
        let row = &src[y * w..(y + 1) * w];
        for (x, d) in dst.iter_mut().enumerate() {
            let mut acc = 0u32;
            if x >= 4 && x + 4 < w {
                for (k, p) in K.iter().zip(&row[x - 4..x + 5]) {
                    acc += k * u32::from(*p);
                }
            } else {
                for (i, k) in K.iter().enumerate() {
                    let xi = (x as isize + i as isize - 4).clamp(0, w as isize - 1) as usize;
                    acc += k * u32::from(row[xi]);
                }
            }
            *d = acc as u16;
        }
    };
    tmp.par_chunks_mut(w).enumerate().for_each(hpass);
    let mut out = vec![0u8; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, dst)| {
        let mut acc = vec![0u32; w];
        for (i, k) in K.iter().enumerate() {
            let yi = (y as isize + i as isize - 4).clamp(0, h as isize - 1) as usize;
            for (a, s) in acc.iter_mut().zip(&tmp[yi * w..(yi + 1) * w]) {
                *a += k * u32::from(*s);
            }
        }
        for (d, a) in dst.iter_mut().zip(&acc) {
            *d = ((a + (1 << 15)) >> 16) as u8;
        }
    });
    out
}

/// The fixed BRIEF test pattern: 256 pairs `(x1, y1, x2, y2)` within +-13 px.
fn brief_pattern() -> &'static [[i8; 4]; 256] {
    static PATTERN: std::sync::OnceLock<[[i8; 4]; 256]> = std::sync::OnceLock::new();
    PATTERN.get_or_init(|| {
        // splitmix64 + Box-Muller: deterministic on every platform.
        let mut s: u64 = 0x5EED_B41E_F00D_2026;
        let mut uniform = || {
            s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = s;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^= z >> 31;
            ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let sigma = 31.0 / 5.0;
        let mut gauss = || {
            let (u, v) = (uniform(), uniform());
            let g = (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos() * sigma;
            g.round().clamp(-13.0, 13.0) as i8
        };
        let mut p = [[0i8; 4]; 256];
        for pair in p.iter_mut() {
            loop {
                *pair = [gauss(), gauss(), gauss(), gauss()];
                if pair[0] != pair[2] || pair[1] != pair[3] {
                    break;
                }
            }
        }
        p
    })
}

/// Detect FAST-9 corners ranked by Harris, bucket them, refine them and compute BRIEF-256
/// descriptors (see the module docs). Errors if the image is smaller than
/// `2 border + 1` on a side or the options are invalid; a textureless image gives no
/// features.
pub fn detect_and_describe(img: &GrayImage, options: &FeatureOptions) -> Result<Features, VisionError> {
    options.validate()?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let b = options.border;
    if w < 2 * b + 1 || h < 2 * b + 1 {
        return Err(VisionError::InvalidInput(format!(
            "image {w}x{h} is too small for features with a {b} px border"
        )));
    }
    let px = img.pixels();
    // Candidates after FAST and 3x3 non-maximum suppression.
    let mut t = options.fast_threshold;
    let mut cands = fast_nms(px, w, h, b, t);
    if cands.len() < options.max_features / 2 && t > 1 {
        t = (t / 2).max(1);
        cands = fast_nms(px, w, h, b, t);
    }
    // Harris ranking.
    let k = options.harris_k;
    let mut ranked: Vec<Keypoint> = cands
        .par_iter()
        .filter_map(|&(x, y)| {
            let r = harris(px, w, x as usize, y as usize, k);
            (r > 0.0).then_some(Keypoint { x: x as f32, y: y as f32, response: r })
        })
        .collect();
    ranked.sort_unstable_by(|a, b| {
        b.response.total_cmp(&a.response).then(a.y.total_cmp(&b.y)).then(a.x.total_cmp(&b.x))
    });
    let mut kept = bucket(&ranked, w, h, options.grid_cell, options.max_features);
    // Sub-pixel refinement.
    if options.subpixel {
        kept.par_iter_mut().for_each(|kp| {
            let (x, y) = (kp.x as usize, kp.y as usize);
            let c = kp.response;
            let dx = parabola(harris(px, w, x - 1, y, k), c, harris(px, w, x + 1, y, k));
            let dy = parabola(harris(px, w, x, y - 1, k), c, harris(px, w, x, y + 1, k));
            kp.x += dx;
            kp.y += dy;
        });
    }
    // Descriptors at the integer positions (the pattern is on the pixel grid).
    let smooth = smooth_binomial9(img);
    let pattern = brief_pattern();
    let descriptors = kept
        .par_iter()
        .map(|kp| {
            let (x, y) = (kp.x.round() as isize, kp.y.round() as isize);
            let centre = y * w as isize + x;
            let mut d = [0u64; 4];
            for (i, p) in pattern.iter().enumerate() {
                let a = smooth[(centre + isize::from(p[1]) * w as isize + isize::from(p[0])) as usize];
                let c = smooth[(centre + isize::from(p[3]) * w as isize + isize::from(p[2])) as usize];
                d[i / 64] |= u64::from(a < c) << (i % 64);
            }
            Descriptor(d)
        })
        .collect();
    Ok(Features { keypoints: kept, descriptors })
}

/// FAST score map and 3x3 non-maximum suppression; candidates in raster order.
fn fast_nms(px: &[u8], w: usize, h: usize, b: usize, t: u8) -> Vec<(u32, u32)> {
    let t = i16::from(t);
    let mut score = vec![0u16; w * h];
    score[b * w..(h - b) * w]
        .par_chunks_mut(w)
        .enumerate()
        .for_each(|(i, row)| fast_row(px, w, b + i, b, t, row));
    let score = &score;
    (b..h - b)
        .into_par_iter()
        .flat_map_iter(|y| {
            let mut out = Vec::new();
            let (up, row, dn) =
                (&score[(y - 1) * w..y * w], &score[y * w..(y + 1) * w], &score[(y + 1) * w..(y + 2) * w]);
            for x in b..w - b {
                let s = row[x];
                if s == 0 {
                    continue;
                }
                // Strictly greater than neighbours before in raster order, >= after: one
                // winner on plateaus.
                if s > up[x - 1]
                    && s > up[x]
                    && s > up[x + 1]
                    && s > row[x - 1]
                    && s >= row[x + 1]
                    && s >= dn[x - 1]
                    && s >= dn[x]
                    && s >= dn[x + 1]
                {
                    out.push((x as u32, y as u32));
                }
            }
            out
        })
        .collect()
}

/// Keep up to `max` corners (input sorted strongest first): each grid cell first gets an
/// equal quota, remaining slots go to the strongest leftovers. Output strongest first.
fn bucket(ranked: &[Keypoint], w: usize, h: usize, cell: usize, max: usize) -> Vec<Keypoint> {
    if cell == 0 || ranked.len() <= max {
        return ranked.iter().take(max).copied().collect();
    }
    let (gw, gh) = (w.div_ceil(cell), h.div_ceil(cell));
    let quota = max.div_ceil(gw * gh);
    let mut count = vec![0usize; gw * gh];
    let mut take = vec![false; ranked.len()];
    let mut n = 0;
    for (i, kp) in ranked.iter().enumerate() {
        let c = (kp.y as usize / cell) * gw + kp.x as usize / cell;
        if count[c] < quota && n < max {
            count[c] += 1;
            take[i] = true;
            n += 1;
        }
    }
    for t in take.iter_mut() {
        if n >= max {
            break;
        }
        if !*t {
            *t = true;
            n += 1;
        }
    }
    ranked.iter().zip(&take).filter(|(_, t)| **t).map(|(k, _)| *k).collect()
}
