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

/// Does the 16-bit circle mask `m` contain 9 contiguous set bits (cyclically)?
#[inline]
fn arc9(m: u32) -> bool {
    let m = m | (m << 16);
    let mut r = m;
    for k in 1..9 {
        r &= m >> k;
    }
    r != 0
}

/// Full FAST-9 test of pixel `i` (index into `img`) for the polarities the pre-test left
/// open: score (the sum of `|p - c| - t` over the circle pixels of the winning polarity,
/// plus one), or 0 if not a corner. Masks first, scores only for a corner.
#[inline]
fn fast_full(img: &[u8], off: &[isize; 16], i: isize, t: i16, bright: bool, dark: bool) -> u16 {
    let c = i16::from(img[i as usize]);
    let (hi, lo) = (c + t, c - t);
    let p: [i16; 16] = off.map(|o| i16::from(img[(i + o) as usize]));
    let (mut mb, mut md) = (0u32, 0u32);
    for (k, &v) in p.iter().enumerate() {
        mb |= u32::from(v > hi) << k;
        md |= u32::from(v < lo) << k;
    }
    let mut s = 0u16;
    if bright && arc9(mb) {
        s = p.iter().map(|&v| (v - hi).max(0)).sum::<i16>() as u16 + 1;
    }
    if dark && arc9(md) {
        s = s.max(p.iter().map(|&v| (lo - v).max(0)).sum::<i16>() as u16 + 1);
    }
    s
}

/// FAST-9 score map of one row (`0` = not a corner). A branch-free pre-test over 32
/// pixels at a time (on bytes, so it vectorises) keeps only pixels where every antipodal
/// circle pair `(k, k + 8)` has a member brighter than `c + t` (a 9-arc of the 16-circle
/// always contains one of each antipodal pair, as in OpenCV's FAST) and at least 9 of the
/// 16 are brighter (or the same for darker than `c - t`).
fn fast_row(img: &[u8], w: usize, y: usize, border: usize, t: u8, out: &mut [u16]) {
    const L: usize = 32;
    let off: [isize; 16] = CIRCLE.map(|(dx, dy)| dy * w as isize + dx);
    let n = w - 2 * border;
    let start = y * w + border;
    let ring: [&[u8]; 16] = off.map(|o| {
        let s = (start as isize + o) as usize;
        &img[s..s + n]
    });
    let centre = &img[start..start + n];
    let full_chunks = n / L;
    for ch in 0..full_chunks {
        let x0 = ch * L;
        let c: &[u8; L] = centre[x0..x0 + L].try_into().unwrap_or(&[0; L]);
        let mut hi = [0u8; L];
        let mut lo = [0u8; L];
        for l in 0..L {
            hi[l] = c[l].saturating_add(t);
            lo[l] = c[l].saturating_sub(t);
        }
        let mut okb = [true; L];
        let mut okd = [true; L];
        let mut nb = [0u8; L];
        let mut nd = [0u8; L];
        for k in 0..8 {
            let a: &[u8; L] = ring[k][x0..x0 + L].try_into().unwrap_or(&[0; L]);
            let b: &[u8; L] = ring[k + 8][x0..x0 + L].try_into().unwrap_or(&[0; L]);
            for l in 0..L {
                let (ab, bb) = (a[l] > hi[l], b[l] > hi[l]);
                let (ad, bd) = (a[l] < lo[l], b[l] < lo[l]);
                okb[l] &= ab | bb;
                okd[l] &= ad | bd;
                nb[l] += u8::from(ab) + u8::from(bb);
                nd[l] += u8::from(ad) + u8::from(bd);
            }
        }
        let mut any = false;
        for l in 0..L {
            okb[l] &= nb[l] >= 9;
            okd[l] &= nd[l] >= 9;
            any |= okb[l] | okd[l];
        }
        if !any {
            continue;
        }
        for l in 0..L {
            if okb[l] || okd[l] {
                let x = x0 + l;
                out[border + x] = fast_full(img, &off, (start + x) as isize, i16::from(t), okb[l], okd[l]);
            }
        }
    }
    for x in full_chunks * L..n {
        out[border + x] = fast_full(img, &off, (start + x) as isize, i16::from(t), true, true);
    }
}

/// Gradient-product sums `(sxx, syy, sxy)` over the 7x7 window at `(x, y)` (central
/// differences). Each window row is 8 lanes wide (columns `x - 3 .. x + 4`, the last lane
/// zeroed) so the products vectorise; integer sums are exact. Needs `x >= 4`, `y >= 4` and
/// 5 pixels to the right and below (the feature border guarantees it).
#[inline]
fn structure7(img: &[u8], w: usize, x: usize, y: usize) -> (f32, f32, f32) {
    let (mut a, mut b, mut c) = ([0i32; 8], [0i32; 8], [0i32; 8]);
    for yy in y - 3..=y + 3 {
        let s = yy * w + x - 4;
        let row = &img[s..s + 10];
        let up = &img[s - w + 1..s - w + 9];
        let dn = &img[s + w + 1..s + w + 9];
        let mut gx = [0i32; 8];
        let mut gy = [0i32; 8];
        for l in 0..8 {
            gx[l] = i32::from(row[l + 2]) - i32::from(row[l]);
            gy[l] = i32::from(dn[l]) - i32::from(up[l]);
        }
        gx[7] = 0;
        gy[7] = 0;
        for l in 0..8 {
            a[l] += gx[l] * gx[l];
            b[l] += gy[l] * gy[l];
            c[l] += gx[l] * gy[l];
        }
    }
    let sum = |v: [i32; 8]| v.iter().sum::<i32>() as f32;
    (sum(a), sum(b), sum(c))
}

#[inline]
fn harris(img: &[u8], w: usize, x: usize, y: usize, k: f32) -> f32 {
    let (a, b, c) = structure7(img, w, x, y);
    a * b - c * c - k * (a + b) * (a + b)
}

/// Separable parabola vertex through three samples (offset of the maximum, clamped).
fn parabola(l: f32, c: f32, r: f32) -> f32 {
    let den = l - 2.0 * c + r;
    if den < 0.0 { (0.5 * (l - r) / den).clamp(-0.5, 0.5) } else { 0.0 }
}

/// Smooth with the 9-tap binomial kernel `[1 8 28 56 70 56 28 8 1] / 256` in y, then x
/// (borders replicated). Each pass sums in exact `u16` (`255 * 256 < 2^16`) and rounds to
/// 8 bits, so both run on 8 or 16 lanes; the intermediate rounding moves values by at most
/// half a grey level, which BRIEF's comparisons do not notice.
fn smooth_binomial9(img: &GrayImage) -> Vec<u8> {
    const K: [u16; 9] = [1, 8, 28, 56, 70, 56, 28, 8, 1];
    let (w, h) = (img.width() as usize, img.height() as usize);
    let src = img.pixels();
    let round = |v: u16| ((u32::from(v) + 128) >> 8) as u8;
    // Vertical pass, whole rows at a time.
    let vpass = |acc: &mut Vec<u16>, y: usize, dst: &mut [u8]| {
        acc.fill(0);
        for (i, k) in K.iter().enumerate() {
            let yi = (y as isize + i as isize - 4).clamp(0, h as isize - 1) as usize;
            for (a, s) in acc.iter_mut().zip(&src[yi * w..(yi + 1) * w]) {
                *a += k * u16::from(*s);
            }
        }
        for (d, a) in dst.iter_mut().zip(acc.iter()) {
            *d = round(*a);
        }
    };
    // Horizontal pass on a row padded by 4 replicated pixels per side.
    let hpass = |pad: &mut Vec<u8>, src: &[u8], dst: &mut [u8]| {
        pad[4..w + 4].copy_from_slice(src);
        let (first, last) = (src[0], src[w - 1]);
        pad[..4].fill(first);
        pad[w + 4..].fill(last);
        let t: [&[u8]; 9] = std::array::from_fn(|i| &pad[i..i + w]);
        for x in 0..w {
            let mut a = 0u16;
            for i in 0..9 {
                a += K[i] * u16::from(t[i][x]);
            }
            dst[x] = round(a);
        }
    };
    let mut tmp = vec![0u8; w * h];
    let mut out = vec![0u8; w * h];
    if rayon::current_num_threads() > 1 {
        tmp.par_chunks_mut(w).enumerate().for_each_init(|| vec![0u16; w], |acc, (y, d)| vpass(acc, y, d));
        out.par_chunks_mut(w)
            .zip(tmp.par_chunks(w))
            .for_each_init(|| vec![0u8; w + 8], |pad, (d, s)| hpass(pad, s, d));
    } else {
        let mut acc = vec![0u16; w];
        tmp.chunks_mut(w).enumerate().for_each(|(y, d)| vpass(&mut acc, y, d));
        let mut pad = vec![0u8; w + 8];
        out.chunks_mut(w).zip(tmp.chunks(w)).for_each(|(d, s)| hpass(&mut pad, s, d));
    }
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
    // Pattern pairs as index offsets in this image, once per call.
    let pairs: Vec<[isize; 2]> = brief_pattern()
        .iter()
        .map(|p| {
            let off = |dx: i8, dy: i8| isize::from(dy) * w as isize + isize::from(dx);
            [off(p[0], p[1]), off(p[2], p[3])]
        })
        .collect();
    let descriptors = kept
        .par_iter()
        .map(|kp| {
            let (x, y) = (kp.x.round() as isize, kp.y.round() as isize);
            let centre = y * w as isize + x;
            let mut d = [0u64; 4];
            for (word, chunk) in d.iter_mut().zip(pairs.chunks_exact(64)) {
                for (i, [a, c]) in chunk.iter().enumerate() {
                    let (a, c) = (smooth[(centre + a) as usize], smooth[(centre + c) as usize]);
                    *word |= u64::from(a < c) << i;
                }
            }
            Descriptor(d)
        })
        .collect();
    Ok(Features { keypoints: kept, descriptors })
}

/// FAST score map and 3x3 non-maximum suppression; candidates in raster order.
fn fast_nms(px: &[u8], w: usize, h: usize, b: usize, t: u8) -> Vec<(u32, u32)> {
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
            // Blocks of 16 scores; all-zero blocks (most) are skipped by an OR-reduction.
            for x0 in (b..w - b).step_by(16) {
                let x1 = (x0 + 16).min(w - b);
                if row[x0..x1].iter().fold(0, |a, &v| a | v) == 0 {
                    continue;
                }
                for x in x0..x1 {
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

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    fn xorshift(seed: u64) -> impl FnMut() -> u64 {
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        }
    }

    /// A `w x h` window at `(ox, oy)` of a large scene of random grey rectangles (many
    /// corners and junctions), plus independent uniform noise of +-`noise` grey levels.
    pub(crate) fn rect_scene(w: u32, h: u32, ox: u32, oy: u32, noise: u8, seed: u64) -> GrayImage {
        const SW: usize = 640;
        const SH: usize = 480;
        let mut rnd = xorshift(seed);
        let mut scene = vec![128u8; SW * SH];
        for _ in 0..900 {
            let (x0, y0) = ((rnd() % SW as u64) as usize, (rnd() % SH as u64) as usize);
            let (rw, rh) = (6 + (rnd() % 40) as usize, 6 + (rnd() % 40) as usize);
            let v = (rnd() % 256) as u8;
            for y in y0..(y0 + rh).min(SH) {
                for x in x0..(x0 + rw).min(SW) {
                    scene[y * SW + x] = v;
                }
            }
        }
        let mut nrnd = xorshift(seed ^ u64::from(ox * 7919 + oy * 104_729 + 1));
        let data = (0..h as usize)
            .flat_map(|y| (0..w as usize).map(move |x| (x, y)))
            .map(|(x, y)| {
                let v = i32::from(scene[(y + oy as usize) * SW + x + ox as usize]);
                let n = if noise == 0 {
                    0
                } else {
                    (nrnd() % (2 * u64::from(noise) + 1)) as i32 - i32::from(noise)
                };
                (v + n).clamp(0, 255) as u8
            })
            .collect();
        GrayImage::new(w, h, data).unwrap()
    }

    /// Fraction of `a`'s corners (that stay inside `b`'s detection area) re-detected in `b`
    /// within `tol` px after the scene moved by `-shift` (b = scene window at +shift).
    fn repeatability(a: &Features, b: &Features, shift: [f32; 2], w: f32, h: f32, tol: f32) -> f64 {
        let (mut n, mut hit) = (0, 0);
        for ka in &a.keypoints {
            let (x, y) = (ka.x - shift[0], ka.y - shift[1]);
            if x < 20.0 || y < 20.0 || x > w - 20.0 || y > h - 20.0 {
                continue;
            }
            n += 1;
            if b.keypoints.iter().any(|kb| (kb.x - x).powi(2) + (kb.y - y).powi(2) <= tol * tol) {
                hit += 1;
            }
        }
        hit as f64 / n.max(1) as f64
    }

    #[test]
    fn corners_repeat_under_a_known_shift() {
        let a = rect_scene(400, 300, 20, 30, 2, 5);
        let b = rect_scene(400, 300, 27, 35, 2, 5);
        let shift = [7.0, 5.0];
        // All corners (no cap): detection is local, so most come back; the independent
        // +-2 grey-level noise flips weak FAST candidates near the threshold (about 10 %).
        let all = FeatureOptions { max_features: 100_000, ..Default::default() };
        let (fa, fb) = (detect_and_describe(&a, &all).unwrap(), detect_and_describe(&b, &all).unwrap());
        assert!(fa.len() > 300, "{}", fa.len());
        let r = repeatability(&fa, &fb, shift, 400.0, 300.0, 1.0);
        eprintln!("uncapped repeatability {r}");
        assert!(r > 0.85, "uncapped repeatability {r}");
        // Default (1000 features, bucketed): the cap and the cell boundaries move with the
        // image, so some corners near the cut are exchanged; most still repeat.
        let def = FeatureOptions::default();
        let (fa, fb) = (detect_and_describe(&a, &def).unwrap(), detect_and_describe(&b, &def).unwrap());
        assert!(fa.len() <= 1000 && fa.len() == fa.descriptors.len());
        let r = repeatability(&fa, &fb, shift, 400.0, 300.0, 1.0);
        eprintln!("capped repeatability {r}");
        assert!(r > 0.75, "capped repeatability {r}");
        // Strongest first.
        assert!(fa.keypoints.windows(2).all(|p| p[0].response >= p[1].response));
    }

    #[test]
    fn bucketing_spreads_features() {
        let img = rect_scene(512, 384, 0, 0, 2, 9);
        let opts = FeatureOptions { max_features: 200, ..Default::default() };
        let f = detect_and_describe(&img, &opts).unwrap();
        assert_eq!(f.len(), 200);
        let mut cells = std::collections::HashSet::new();
        for k in &f.keypoints {
            cells.insert((k.x as usize / 64, k.y as usize / 64));
        }
        // 8x6 = 48 cells, quota 5 each: nearly every cell with corners is used.
        assert!(cells.len() >= 40, "{} cells", cells.len());
    }

    #[test]
    fn blank_small_and_bad_options() {
        let blank = GrayImage::filled(200, 100, 90);
        assert!(detect_and_describe(&blank, &FeatureOptions::default()).unwrap().is_empty());
        let small = GrayImage::filled(32, 100, 90);
        assert!(matches!(
            detect_and_describe(&small, &FeatureOptions::default()),
            Err(VisionError::InvalidInput(_))
        ));
        for bad in [
            FeatureOptions { border: 3, ..Default::default() },
            FeatureOptions { max_features: 0, ..Default::default() },
            FeatureOptions { fast_threshold: 0, ..Default::default() },
            FeatureOptions { harris_k: 0.3, ..Default::default() },
        ] {
            assert!(matches!(detect_and_describe(&blank, &bad), Err(VisionError::InvalidOptions(_))));
        }
    }

    #[test]
    fn fast_arc_test_and_pattern() {
        // A bright 9-pixel... single bright square corner: the pixel just outside the
        // corner of a dark square on a bright background is a FAST corner.
        let mut img = GrayImage::filled(40, 40, 200);
        for y in 20..40 {
            for x in 20..40 {
                img.pixels_mut()[y * 40 + x] = 20;
            }
        }
        let mut row = vec![0u16; 40];
        fast_row(img.pixels(), 40, 20, 3, 20, &mut row);
        assert!(row[20] > 0, "corner pixel of the dark square");
        assert_eq!(row[30], 0, "edge pixel is not a corner");
        let p = brief_pattern();
        assert!(p.iter().flatten().all(|v| v.abs() <= 13));
        assert!(p.iter().all(|q| q[0] != q[2] || q[1] != q[3]));
    }

    /// The textbook FAST-9 score (no pre-test): both polarities, all 16 circle pixels.
    fn naive_fast(img: &GrayImage, x: usize, y: usize, t: i16) -> u16 {
        let at = |dx: isize, dy: isize| {
            i16::from(img.get((x as isize + dx) as u32, (y as isize + dy) as u32).unwrap_or(0))
        };
        let c = at(0, 0);
        let p: Vec<i16> = CIRCLE.iter().map(|&(dx, dy)| at(dx, dy)).collect();
        let arc = |f: &dyn Fn(i16) -> bool| (0..16).any(|s| (0..9).all(|k| f(p[(s + k) % 16])));
        let mut score = 0;
        if arc(&|v| v > c + t) {
            score = p.iter().map(|&v| (v - c - t).max(0)).sum::<i16>() as u16 + 1;
        }
        if arc(&|v| v < c - t) {
            score = score.max(p.iter().map(|&v| (c - t - v).max(0)).sum::<i16>() as u16 + 1);
        }
        score
    }

    #[test]
    fn fast_pretest_loses_no_corner() {
        // The vectorised pre-tests (antipodal pairs, at least 9 of 16) are necessary
        // conditions only: scores must equal the textbook test at every pixel.
        for (seed, t) in [(1, 20u8), (2, 7), (3, 40)] {
            let img = rect_scene(150, 60, 10, 20, 12, seed);
            let w = 150;
            let mut row = vec![0u16; w];
            let mut corners = 0;
            for y in 3..57 {
                row.iter_mut().for_each(|v| *v = 0);
                fast_row(img.pixels(), w, y, 3, t, &mut row);
                for (x, &score) in row.iter().enumerate().take(w - 3).skip(3) {
                    assert_eq!(score, naive_fast(&img, x, y, i16::from(t)), "({x}, {y}) t {t}");
                    corners += usize::from(score > 0);
                }
            }
            assert!(corners > 20, "seed {seed}: only {corners} corners");
        }
    }

    #[test]
    fn binomial_smoothing_matches_float_convolution() {
        // Two passes, each rounded to 8 bits: within one grey level of the exact result.
        let img = rect_scene(90, 70, 5, 9, 30, 4);
        let got = smooth_binomial9(&img);
        let k = [1.0, 8.0, 28.0, 56.0, 70.0, 56.0, 28.0, 8.0, 1.0].map(|v: f64| v / 256.0);
        let at =
            |x: isize, y: isize| f64::from(img.get(x.clamp(0, 89) as u32, y.clamp(0, 69) as u32).unwrap());
        let mut worst: f64 = 0.0;
        for y in 0..70isize {
            for x in 0..90isize {
                let mut v = 0.0;
                for (j, kj) in k.iter().enumerate() {
                    for (i, ki) in k.iter().enumerate() {
                        v += kj * ki * at(x + i as isize - 4, y + j as isize - 4);
                    }
                }
                worst = worst.max((f64::from(got[(y * 90 + x) as usize]) - v).abs());
            }
        }
        assert!(worst <= 1.0, "worst {worst}");
    }
}
