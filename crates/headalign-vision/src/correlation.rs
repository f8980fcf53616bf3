//! Zero-mean normalised cross-correlation (ZNCC) and coarse-to-fine pyramid correlation
//! (paper section 5 step 3, "pyramid correlation"; section 6, verging on strongly
//! subsampled images).
//!
//! ZNCC of two equal-sized windows `a`, `b` of `n` pixels is
//! `sum((a - mean a)(b - mean b)) / sqrt(sum((a - mean a)^2) sum((b - mean b)^2))`, in
//! `[-1, 1]`, invariant to gain and offset of either window. It is undefined when a window
//! has no intensity variance: such input is reported as [`VisionError::Textureless`].
//!
//! Search (both [`register_translation`] and [`locate_patch`]), 2 degrees of freedom (an
//! integer-then-sub-pixel translation):
//! 1. build Gaussian pyramids of both images ([`crate::Pyramid`]);
//! 2. at the coarsest level, evaluate every shift in the search range (exhaustive);
//! 3. at each finer level, double the shift and evaluate only the 3x3 shifts around it
//!    (the paper's "+-1 pixel"); if the best of the nine lies on the edge of the 3x3 block the
//!    block is re-centred there (a few steps at most), which repairs a coarse level that
//!    was one pixel off without widening the search;
//! 4. at the finest level used, fit a 2D quadratic `f(x, y) = a + bx + cy + dx^2 + exy + fy^2`
//!    by least squares to the 3x3 scores around the peak and take its maximum (clamped to
//!    +-0.6 px; if the fit is not a maximum, fall back to the integer peak).
//!
//! Cost: no level is copied for the search. Full resolution is correlated on the 8-bit
//! pixels themselves with exact integer sums (`u32` per row chunk, `f64` across rows);
//! coarser levels are `f32` stored minus the mean of level 0 ([`Pyramid::offset`]), so
//! the cancellation in `sum(ab) - sum(a) sum(b) / n` stays small. At the exhaustively
//! searched level, window sums and sums of squares come from `f64` integral images (O(1)
//! per window) and only the cross term is summed per pixel (an `f32` dot product per row,
//! unrolled by 8 so it vectorises, rows accumulated in `f64`).
//!
//! Units: shifts and positions in full-resolution pixels; scores are ZNCC (unitless);
//! texture thresholds are standard deviations in grey levels (0..255 scale).
//!
//! Sub-pixel accuracy: a quadratic approximates the top of the correlation peak, whose
//! width is set by the image's autocorrelation. For smooth textures (peak several pixels
//! wide) the bias ("pixel locking") is a few hundredths of a pixel; for sharp, aliased
//! textures it grows towards 0.1-0.2 px. Registration of whole images assumes the motion is
//! a translation; after a head rotation that is true only near the image centre, which is
//! why fixation uses [`locate_patch`] on a patch around the target instead.
//!
//! Pitfalls: whole-image registration compares the overlap only, so very large shifts
//! (little overlap) are unreliable and are excluded by `max_shift_fraction`; repetitive
//! texture can make the coarsest level pick a wrong period (check `score`).

use rayon::prelude::*;

use crate::pyramid::{FloatImage, Pyramid};
use crate::{GrayImage, VisionError};

/// Per-pixel variance (grey levels^2) below which a window's ZNCC is treated as undefined
/// inside a search (numerical floor; the user-facing check is `min_texture_std`).
const SEARCH_VARIANCE_FLOOR: f64 = 1e-4;

/// [`register_translation`] builds no level whose shorter side is below this many pixels.
pub const MIN_COARSE_SIDE: usize = 24;

/// ZNCC of two equal-sized float images (whole images). Errors on mismatched sizes, or
/// (textureless) if either image has intensity standard deviation below 1e-3 grey levels.
pub fn zncc(a: &FloatImage, b: &FloatImage) -> Result<f64, VisionError> {
    if a.width() != b.width() || a.height() != b.height() {
        return Err(VisionError::InvalidInput(format!(
            "ZNCC needs equal sizes, got {}x{} and {}x{}",
            a.width(),
            a.height(),
            b.width(),
            b.height()
        )));
    }
    let (ma, mb) = (a.mean(), b.mean());
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (&x, &y) in a.pixels().iter().zip(b.pixels()) {
        let (x, y) = (f64::from(x) - ma, f64::from(y) - mb);
        sab += x * y;
        saa += x * x;
        sbb += y * y;
    }
    let n = a.pixels().len() as f64;
    for (name, s) in [("first", saa), ("second", sbb)] {
        if (s / n).sqrt() < 1e-3 {
            return Err(VisionError::Textureless(format!("the {name} window is constant")));
        }
    }
    Ok(sab / (saa * sbb).sqrt())
}

/// The pixels of one pyramid level, borrowed: level 0 as the 8-bit image itself, coarser
/// levels as `f32` (near zero mean, see [`Pyramid::offset`]).
#[derive(Clone, Copy)]
enum Pixels<'a> {
    Bytes(&'a [u8]),
    Floats(&'a [f32]),
}

/// One pyramid level prepared for correlation: borrowed pixels and, for the level
/// searched exhaustively, integral images.
struct Level<'a> {
    w: usize,
    h: usize,
    data: Pixels<'a>,
    /// Integrals of values and squared values, `(w + 1) x (h + 1)` (exhaustive level only).
    integrals: Option<(Vec<f64>, Vec<f64>)>,
}

impl<'a> Level<'a> {
    fn with(w: usize, h: usize, data: Pixels<'a>, with_integrals: bool) -> Self {
        let integrals = with_integrals.then(|| {
            let value = |i: usize| match data {
                Pixels::Bytes(d) => f64::from(d[i]),
                Pixels::Floats(d) => f64::from(d[i]),
            };
            let mut s1 = vec![0.0f64; (w + 1) * (h + 1)];
            let mut s2 = vec![0.0f64; (w + 1) * (h + 1)];
            for y in 0..h {
                let (mut r1, mut r2) = (0.0f64, 0.0f64);
                for x in 0..w {
                    let v = value(y * w + x);
                    r1 += v;
                    r2 += v * v;
                    let i = (y + 1) * (w + 1) + x + 1;
                    s1[i] = s1[i - (w + 1)] + r1;
                    s2[i] = s2[i - (w + 1)] + r2;
                }
            }
            (s1, s2)
        });
        Self { w, h, data, integrals }
    }

    /// Level `k` of a pyramid (`k` must exist).
    fn of(p: &'a Pyramid<'_>, k: usize, with_integrals: bool) -> Self {
        match p.coarse_level(k) {
            Some(l) => Self::with(l.width(), l.height(), Pixels::Floats(l.pixels()), with_integrals),
            None => {
                let b = p.base();
                let (w, h) = (b.width() as usize, b.height() as usize);
                Self::with(w, h, Pixels::Bytes(b.pixels()), with_integrals)
            }
        }
    }

    /// A placeholder for levels below the finest searched one (never read).
    fn empty() -> Self {
        Self { w: 0, h: 0, data: Pixels::Floats(&[]), integrals: None }
    }

    /// Sum and sum of squares over the half-open rectangle, if integrals exist.
    fn sums(&self, r: Rect) -> Option<(f64, f64)> {
        let (s1, s2) = self.integrals.as_ref()?;
        let s = self.w + 1;
        let at = |v: &[f64], x: usize, y: usize| v[y * s + x];
        let f = |v: &[f64]| at(v, r.x1, r.y1) - at(v, r.x0, r.y1) - at(v, r.x1, r.y0) + at(v, r.x0, r.y0);
        Some((f(s1), f(s2)))
    }
}

/// Half-open pixel rectangle `[x0, x1) x [y0, y1)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Rect {
    x0: usize,
    y0: usize,
    x1: usize,
    y1: usize,
}

impl Rect {
    fn area(&self) -> usize {
        (self.x1 - self.x0) * (self.y1 - self.y0)
    }
}

/// `f32` dot product unrolled by 8 (vectorises without fast-math).
#[inline]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for i in 0..8 {
            acc[i] += x[i] * y[i];
        }
    }
    let mut s: f32 = acc.iter().sum();
    for (x, y) in ra.iter().zip(rb) {
        s += x * y;
    }
    s
}

/// The five sums `(a, b, aa, bb, ab)` of two equal-length rows, 8 lanes at a time.
#[inline]
fn sums5(a: &[f32], b: &[f32]) -> [f32; 5] {
    let mut acc = [[0.0f32; 8]; 5];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for i in 0..8 {
            acc[0][i] += x[i];
            acc[1][i] += y[i];
            acc[2][i] += x[i] * x[i];
            acc[3][i] += y[i] * y[i];
            acc[4][i] += x[i] * y[i];
        }
    }
    let mut out = acc.map(|l| l.iter().sum::<f32>());
    for (x, y) in ra.iter().zip(rb) {
        out[0] += x;
        out[1] += y;
        out[2] += x * x;
        out[3] += y * y;
        out[4] += x * y;
    }
    out
}

/// Byte rows are summed in `u32` over chunks short enough not to overflow
/// (`4096 * 255^2 < 2^32`), then in `f64`: the byte sums are exact. The plain zipped loop
/// is what the vectoriser handles best (narrow multiplies, integer reductions): about 3x
/// faster than converting to `f32` lanes.
const BYTE_CHUNK: usize = 4096;

/// `f64` dot product of two byte rows (exact).
#[inline]
fn dot_u8(a: &[u8], b: &[u8]) -> f64 {
    let mut total = 0.0f64;
    for (a, b) in a.chunks(BYTE_CHUNK).zip(b.chunks(BYTE_CHUNK)) {
        let mut s = 0u32;
        for (&x, &y) in a.iter().zip(b) {
            s += u32::from(x) * u32::from(y);
        }
        total += f64::from(s);
    }
    total
}

/// The five sums `(a, b, aa, bb, ab)` of two equal-length byte rows (exact).
#[inline]
fn sums5_u8(a: &[u8], b: &[u8]) -> [f64; 5] {
    let mut out = [0.0f64; 5];
    for (a, b) in a.chunks(BYTE_CHUNK).zip(b.chunks(BYTE_CHUNK)) {
        let (mut s0, mut s1, mut s2, mut s3, mut s4) = (0u32, 0u32, 0u32, 0u32, 0u32);
        for (&x, &y) in a.iter().zip(b) {
            let (p, q) = (u32::from(x), u32::from(y));
            s0 += p;
            s1 += q;
            s2 += p * p;
            s3 += q * q;
            s4 += p * q;
        }
        for (o, v) in out.iter_mut().zip([s0, s1, s2, s3, s4]) {
            *o += f64::from(v);
        }
    }
    out
}

/// ZNCC of rectangle `r` of `a` against `r + d` of `b`; `None` if `r + d` leaves `b` or a
/// window is (numerically) constant.
fn zncc_rect(a: &Level, b: &Level, r: Rect, d: [i64; 2]) -> Option<f64> {
    let bx0 = r.x0 as i64 + d[0];
    let by0 = r.y0 as i64 + d[1];
    let bx1 = r.x1 as i64 + d[0];
    let by1 = r.y1 as i64 + d[1];
    if bx0 < 0 || by0 < 0 || bx1 > b.w as i64 || by1 > b.h as i64 || r.x1 > a.w || r.y1 > a.h {
        return None;
    }
    let rb = Rect { x0: bx0 as usize, y0: by0 as usize, x1: bx1 as usize, y1: by1 as usize };
    let n = r.area() as f64;
    if n < 4.0 {
        return None;
    }
    let yb = |y: usize| rb.y0 + (y - r.y0);
    let (sa, saa, sb, sbb, sab) = match (a.data, b.data) {
        (Pixels::Floats(da), Pixels::Floats(db)) => {
            let rows = |y: usize| {
                (&da[y * a.w + r.x0..y * a.w + r.x1], &db[yb(y) * b.w + rb.x0..yb(y) * b.w + rb.x1])
            };
            match (a.sums(r), b.sums(rb)) {
                (Some((sa, saa)), Some((sb, sbb))) => {
                    let mut sab = 0.0f64;
                    for y in r.y0..r.y1 {
                        let (ra, rbw) = rows(y);
                        sab += f64::from(dot(ra, rbw));
                    }
                    (sa, saa, sb, sbb, sab)
                }
                _ => {
                    let mut t = [0.0f64; 5];
                    for y in r.y0..r.y1 {
                        let (ra, rbw) = rows(y);
                        for (acc, v) in t.iter_mut().zip(sums5(ra, rbw)) {
                            *acc += f64::from(v);
                        }
                    }
                    (t[0], t[2], t[1], t[3], t[4])
                }
            }
        }
        (Pixels::Bytes(da), Pixels::Bytes(db)) => {
            let rows = |y: usize| {
                (&da[y * a.w + r.x0..y * a.w + r.x1], &db[yb(y) * b.w + rb.x0..yb(y) * b.w + rb.x1])
            };
            match (a.sums(r), b.sums(rb)) {
                (Some((sa, saa)), Some((sb, sbb))) => {
                    let sab = (r.y0..r.y1).map(rows).map(|(ra, rbw)| dot_u8(ra, rbw)).sum();
                    (sa, saa, sb, sbb, sab)
                }
                _ => {
                    let mut t = [0.0f64; 5];
                    for y in r.y0..r.y1 {
                        let (ra, rbw) = rows(y);
                        for (acc, v) in t.iter_mut().zip(sums5_u8(ra, rbw)) {
                            *acc += v;
                        }
                    }
                    (t[0], t[2], t[1], t[3], t[4])
                }
            }
        }
        // Both sides of a pair are the same level of equal-sized pyramids.
        _ => return None,
    };
    let va = saa - sa * sa / n;
    let vb = sbb - sb * sb / n;
    if va < SEARCH_VARIANCE_FLOOR * n || vb < SEARCH_VARIANCE_FLOOR * n {
        return None;
    }
    Some(((sab - sa * sb / n) / (va * vb).sqrt()).clamp(-1.0, 1.0))
}

/// The best integer shift at one level with its score and 3x3 neighbourhood.
#[derive(Clone, Copy, Debug)]
struct Peak {
    d: [i64; 2],
    score: f64,
}

/// Problem-specific geometry of a search: the rectangle of `a` compared for a shift.
type RectFor<'a> = dyn Fn(usize, [i64; 2]) -> Option<Rect> + Sync + 'a;

/// Score shifts, in parallel when the work is large.
fn score_all(
    a: &Level,
    b: &Level,
    level: usize,
    shifts: &[[i64; 2]],
    rect_for: &RectFor,
) -> Vec<([i64; 2], Option<f64>)> {
    let score = |d: &[i64; 2]| (*d, rect_for(level, *d).and_then(|r| zncc_rect(a, b, r, *d)));
    let work = shifts.len() * rect_for(level, [0, 0]).map_or(a.w * a.h, |r| r.area());
    if work >= 256 * 1024 && shifts.len() > 1 {
        shifts.par_iter().map(score).collect()
    } else {
        shifts.iter().map(score).collect()
    }
}

/// The best of many shifts (ties: first).
fn best_of(a: &Level, b: &Level, level: usize, shifts: &[[i64; 2]], rect_for: &RectFor) -> Option<Peak> {
    let mut best: Option<Peak> = None;
    for (d, s) in score_all(a, b, level, shifts, rect_for) {
        if let Some(s) = s
            && best.is_none_or(|p| s > p.score)
        {
            best = Some(Peak { d, score: s });
        }
    }
    best
}

fn block3(c: [i64; 2]) -> Vec<[i64; 2]> {
    (-1..=1).flat_map(|j| (-1..=1).map(move |i| [c[0] + i, c[1] + j])).collect()
}

/// Hill-climb 3x3 blocks from `start` until the best shift is the block centre (or
/// `max_steps` re-centrings). Returns the peak and, if centred, the 3x3 scores.
fn climb(
    a: &Level,
    b: &Level,
    level: usize,
    start: [i64; 2],
    rect_for: &RectFor,
    max_steps: usize,
) -> Option<(Peak, Option<[[f64; 3]; 3]>)> {
    let mut c = start;
    let mut memo: Vec<([i64; 2], Option<f64>)> = Vec::new();
    let mut last: Option<Peak> = None;
    for _ in 0..=max_steps {
        let shifts = block3(c);
        let todo: Vec<[i64; 2]> =
            shifts.iter().filter(|d| !memo.iter().any(|m| m.0 == **d)).copied().collect();
        memo.extend(score_all(a, b, level, &todo, rect_for));
        let get = |d: [i64; 2]| memo.iter().find(|m| m.0 == d).and_then(|m| m.1);
        let mut best: Option<Peak> = None;
        for d in &shifts {
            if let Some(sc) = get(*d)
                && best.is_none_or(|p| sc > p.score)
            {
                best = Some(Peak { d: *d, score: sc });
            }
        }
        let best = best?;
        last = Some(best);
        if best.d == c {
            let mut s = [[f64::NAN; 3]; 3];
            for d in shifts {
                s[(d[1] - c[1] + 1) as usize][(d[0] - c[0] + 1) as usize] = get(d).unwrap_or(f64::NAN);
            }
            return Some((best, Some(s)));
        }
        c = best.d;
    }
    last.map(|p| (p, None))
}

/// Maximum of the least-squares quadratic through a 3x3 block of scores `s[row][col]`,
/// as an offset from the centre, or `None` if the fit has no maximum there.
fn quadratic_peak(s: &[[f64; 3]; 3]) -> Option<[f64; 2]> {
    if s.iter().flatten().any(|v| !v.is_finite()) {
        return None;
    }
    let col = |i: usize| s[0][i] + s[1][i] + s[2][i];
    let row = |j: usize| s[j][0] + s[j][1] + s[j][2];
    let b = (col(2) - col(0)) / 6.0;
    let c = (row(2) - row(0)) / 6.0;
    let d = (col(0) + col(2) - 2.0 * col(1)) / 6.0;
    let f = (row(0) + row(2) - 2.0 * row(1)) / 6.0;
    let e = (s[0][0] + s[2][2] - s[0][2] - s[2][0]) / 4.0;
    // Maximum needs the Hessian [[2d, e], [e, 2f]] negative definite.
    let det = 4.0 * d * f - e * e;
    if !(d < 0.0 && det > 0.0) {
        return None;
    }
    let x = (-2.0 * f * b + e * c) / det;
    let y = (-2.0 * d * c + e * b) / det;
    Some([x.clamp(-0.6, 0.6), y.clamp(-0.6, 0.6)])
}

/// Result of a coarse-to-fine search, in the finest searched level's pixels.
struct SearchResult {
    shift: [f64; 2],
    score: f64,
    subpixel: bool,
}

/// The coarse-to-fine driver shared by registration and patch location.
fn coarse_to_fine(
    pairs: &[(Level, Level)],
    finest: usize,
    coarse_range: ([i64; 2], [i64; 2]),
    rect_for: &RectFor,
    subpixel: bool,
) -> Option<SearchResult> {
    let coarsest = pairs.len() - 1;
    let (lo, hi) = coarse_range;
    let shifts: Vec<[i64; 2]> = (lo[1]..=hi[1]).flat_map(|y| (lo[0]..=hi[0]).map(move |x| [x, y])).collect();
    let (a, b) = &pairs[coarsest];
    let mut peak = best_of(a, b, coarsest, &shifts, rect_for)?;
    let mut block = None;
    if coarsest == finest {
        let (p, s) = climb(a, b, coarsest, peak.d, rect_for, 2)?;
        peak = p;
        block = s;
    }
    for level in (finest..coarsest).rev() {
        let (a, b) = &pairs[level];
        let start = [2 * peak.d[0], 2 * peak.d[1]];
        let (p, s) = climb(a, b, level, start, rect_for, 4)?;
        peak = p;
        block = s;
    }
    let sub = if subpixel { block.as_ref().and_then(quadratic_peak) } else { None };
    let off = sub.unwrap_or([0.0, 0.0]);
    Some(SearchResult {
        shift: [peak.d[0] as f64 + off[0], peak.d[1] as f64 + off[1]],
        score: peak.score,
        subpixel: sub.is_some(),
    })
}

fn std_dev(img: &FloatImage) -> f64 {
    img.mean_std().1
}

/// Options of [`register_translation`].
#[derive(Clone, Debug, PartialEq)]
pub struct RegistrationOptions {
    /// Pyramid levels including full resolution (default 5: 768x576 -> 48x36 at the top).
    /// [`register_translation`] uses fewer if the coarsest level's shorter side would drop
    /// below [`MIN_COARSE_SIDE`] (but always more than `finest_level`).
    pub levels: usize,
    /// Finest level searched (default 0 = full resolution). Verging (paper section 6) stops
    /// at a coarse level, e.g. 3, since only a rough overlap is needed.
    pub finest_level: usize,
    /// Largest shift searched, as a fraction of the image side (default 0.5): the overlap
    /// of the two images is then at least half of each side.
    pub max_shift_fraction: f64,
    /// Images whose intensity standard deviation (grey levels) is below this are rejected
    /// as textureless (default 2.0).
    pub min_texture_std: f64,
    /// Fit a quadratic to the 3x3 peak neighbourhood (default true).
    pub subpixel: bool,
    /// Below the coarsest level only the central `fraction x fraction` part of the
    /// reference (within the overlap) is correlated (default 0.5, a quarter of the pixels,
    /// like a central template; 1.0 = the whole overlap). The exhaustive coarsest search
    /// always uses the whole overlap. Smaller is faster; the centre is also where a head
    /// rotation looks most like a translation.
    pub fine_window_fraction: f64,
}

impl Default for RegistrationOptions {
    fn default() -> Self {
        Self {
            levels: 5,
            finest_level: 0,
            max_shift_fraction: 0.5,
            min_texture_std: 2.0,
            subpixel: true,
            fine_window_fraction: 0.5,
        }
    }
}

impl RegistrationOptions {
    /// The paper's section 6 verging mode: a deep pyramid, stopping 3 levels above full
    /// resolution (8x subsampled; accuracy a few pixels, a fraction of the cost).
    pub fn verging() -> Self {
        Self { levels: 6, finest_level: 3, ..Self::default() }
    }

    /// Check the options.
    pub fn validate(&self) -> Result<(), VisionError> {
        let bad = |m: String| Err(VisionError::InvalidOptions(m));
        if self.levels == 0 {
            return bad("levels must be at least 1".into());
        }
        if self.finest_level >= self.levels {
            return bad(format!("finest_level {} must be below levels {}", self.finest_level, self.levels));
        }
        if !(self.max_shift_fraction > 0.0 && self.max_shift_fraction < 1.0) {
            return bad(format!("max_shift_fraction must be in (0, 1), got {}", self.max_shift_fraction));
        }
        if !(self.min_texture_std.is_finite() && self.min_texture_std >= 0.0) {
            return bad(format!("min_texture_std must be >= 0, got {}", self.min_texture_std));
        }
        if !(self.fine_window_fraction > 0.0 && self.fine_window_fraction <= 1.0) {
            return bad(format!("fine_window_fraction must be in (0, 1], got {}", self.fine_window_fraction));
        }
        Ok(())
    }
}

/// Result of [`register_translation`].
#[derive(Clone, Debug, PartialEq)]
pub struct Registration {
    /// Shift of the moved image relative to the reference, full-resolution pixels: the
    /// scene point at reference pixel `x` appears at `x + shift` in the moved image.
    pub shift: [f64; 2],
    /// ZNCC at the integer peak of the finest level searched.
    pub score: f64,
    /// Level at which the search stopped (0 = full resolution).
    pub finest_level: usize,
    /// Levels actually used (small images get fewer than asked).
    pub levels_used: usize,
    /// Whether the sub-pixel quadratic fit succeeded (otherwise `shift` is integer at
    /// `finest_level`).
    pub subpixel: bool,
}

/// Find the translation of `moved` relative to `reference` (equal sizes) by pyramid
/// correlation over the overlap of the two images (paper section 5 step 3).
pub fn register_translation(
    reference: &GrayImage,
    moved: &GrayImage,
    options: &RegistrationOptions,
) -> Result<Registration, VisionError> {
    options.validate()?;
    if reference.size() != moved.size() {
        return Err(VisionError::InvalidInput(format!(
            "registration needs equal image sizes, got {:?} and {:?}",
            reference.size(),
            moved.size()
        )));
    }
    // Stop the pyramid where the shorter side would drop below MIN_COARSE_SIDE pixels:
    // tinier levels have too little texture left for the exhaustive search.
    let mut levels = 1;
    let short = reference.width().min(reference.height()) as usize;
    while levels < options.levels && (short >> levels) >= MIN_COARSE_SIDE {
        levels += 1;
    }
    let levels = levels.max(options.finest_level + 1);
    let pa = Pyramid::new(reference, levels)?;
    let pb = Pyramid::new(moved, levels)?;
    register_pyramids(&pa, &pb, options)
}

/// As [`register_translation`], on prebuilt pyramids (e.g. when one image is reused).
pub fn register_pyramids(
    reference: &Pyramid,
    moved: &Pyramid,
    options: &RegistrationOptions,
) -> Result<Registration, VisionError> {
    options.validate()?;
    let n = reference.len().min(moved.len());
    if !(0..n).all(|k| reference.size(k) == moved.size(k)) {
        return Err(VisionError::InvalidInput("registration needs pyramids of equal sizes".into()));
    }
    let finest = options.finest_level.min(n - 1);
    for (name, p) in [("reference", reference), ("moved", moved)] {
        let s = match p.coarse_level(finest) {
            Some(l) => std_dev(l),
            None => p.base_mean_std().1,
        };
        if s < options.min_texture_std {
            return Err(VisionError::Textureless(format!(
                "the {name} image has intensity std {s:.3} grey levels (< {})",
                options.min_texture_std
            )));
        }
    }
    let pairs: Vec<(Level, Level)> = (0..n)
        .map(|k| {
            if k < finest {
                (Level::empty(), Level::empty())
            } else {
                (Level::of(reference, k, k == n - 1), Level::of(moved, k, k == n - 1))
            }
        })
        .collect();
    let dims: Vec<(usize, usize)> = pairs.iter().map(|(a, _)| (a.w, a.h)).collect();
    let coarsest = n - 1;
    let frac = options.fine_window_fraction;
    let rect_for = |level: usize, d: [i64; 2]| -> Option<Rect> {
        let (w, h) = dims[level];
        let (w, h) = (w as i64, h as i64);
        // Overlap of the two images for this shift...
        let (mut x0, mut x1) = ((-d[0]).max(0), w.min(w - d[0]));
        let (mut y0, mut y1) = ((-d[1]).max(0), h.min(h - d[1]));
        // ...and, below the exhaustive level, only its central part.
        if level < coarsest && frac < 1.0 {
            let (mx, my) = (((1.0 - frac) * 0.5 * w as f64) as i64, ((1.0 - frac) * 0.5 * h as f64) as i64);
            (x0, x1, y0, y1) = (x0.max(mx), x1.min(w - mx), y0.max(my), y1.min(h - my));
        }
        // At least an eighth of each side (and 2 pixels).
        if x1 - x0 < (w / 8).max(2) || y1 - y0 < (h / 8).max(2) {
            return None;
        }
        Some(Rect { x0: x0 as usize, y0: y0 as usize, x1: x1 as usize, y1: y1 as usize })
    };
    let (wc, hc) = dims[n - 1];
    let mx = ((options.max_shift_fraction * wc as f64).floor() as i64).max(1);
    let my = ((options.max_shift_fraction * hc as f64).floor() as i64).max(1);
    let r = coarse_to_fine(&pairs, finest, ([-mx, -my], [mx, my]), &rect_for, options.subpixel).ok_or_else(
        || VisionError::Textureless("no shift gave a defined correlation (overlaps have no variance)".into()),
    )?;
    let scale = (1u64 << finest) as f64;
    Ok(Registration {
        shift: [r.shift[0] * scale, r.shift[1] * scale],
        score: r.score,
        finest_level: finest,
        levels_used: n,
        subpixel: r.subpixel,
    })
}

/// Options of [`locate_patch`].
#[derive(Clone, Debug, PartialEq)]
pub struct PatchSearchOptions {
    /// Template half-size in full-resolution pixels: the template is
    /// `(2 half_size + 1)^2` (default 16 -> 33x33).
    pub half_size: usize,
    /// Search radius in full-resolution pixels around the predicted position, per axis
    /// (default 64).
    pub search_radius: f64,
    /// Maximum pyramid levels (default 4); fewer are used so that the template keeps a
    /// half-size of at least 3 pixels at the coarsest level.
    pub max_levels: usize,
    /// Templates whose standard deviation (grey levels) is below this are rejected as
    /// textureless (default 2.0).
    pub min_texture_std: f64,
    /// Fit a quadratic to the 3x3 peak neighbourhood (default true).
    pub subpixel: bool,
}

impl Default for PatchSearchOptions {
    fn default() -> Self {
        Self { half_size: 16, search_radius: 64.0, max_levels: 4, min_texture_std: 2.0, subpixel: true }
    }
}

impl PatchSearchOptions {
    /// Check the options.
    pub fn validate(&self) -> Result<(), VisionError> {
        let bad = |m: String| Err(VisionError::InvalidOptions(m));
        if self.half_size < 2 {
            return bad(format!("half_size must be at least 2, got {}", self.half_size));
        }
        if !(self.search_radius.is_finite() && self.search_radius >= 0.0) {
            return bad(format!("search_radius must be finite and >= 0, got {}", self.search_radius));
        }
        if self.max_levels == 0 {
            return bad("max_levels must be at least 1".into());
        }
        if !(self.min_texture_std.is_finite() && self.min_texture_std >= 0.0) {
            return bad(format!("min_texture_std must be >= 0, got {}", self.min_texture_std));
        }
        Ok(())
    }
}

/// Result of [`locate_patch`].
#[derive(Clone, Debug, PartialEq)]
pub struct PatchMatch {
    /// Where the point appears in image b (full-resolution pixels).
    pub position: [f64; 2],
    /// ZNCC at the integer peak (full resolution).
    pub score: f64,
    /// Pyramid levels used.
    pub levels_used: usize,
    /// Whether the sub-pixel quadratic fit succeeded.
    pub subpixel: bool,
}

/// Where is the patch around `point_a` of `image_a` in `image_b`? Searches
/// `+-search_radius` around `predicted_b` (default: `point_a` itself) by pyramid
/// correlation. This is the fixation step of paper section 5: `point_a` is the target
/// before the head moved, the result is the target after.
pub fn locate_patch(
    image_a: &GrayImage,
    point_a: [f64; 2],
    image_b: &GrayImage,
    predicted_b: Option<[f64; 2]>,
    options: &PatchSearchOptions,
) -> Result<PatchMatch, VisionError> {
    options.validate()?;
    let levels = patch_levels(options);
    let pa = Pyramid::new(image_a, levels)?;
    let pb = Pyramid::new(image_b, levels)?;
    locate_patch_in_pyramids(&pa, point_a, &pb, predicted_b, options)
}

fn patch_levels(options: &PatchSearchOptions) -> usize {
    let mut levels = 1;
    while levels < options.max_levels && (options.half_size >> levels) >= 3 {
        levels += 1;
    }
    levels
}

/// As [`locate_patch`], on prebuilt pyramids (they may have more levels than needed).
pub fn locate_patch_in_pyramids(
    pyr_a: &Pyramid,
    point_a: [f64; 2],
    pyr_b: &Pyramid,
    predicted_b: Option<[f64; 2]>,
    options: &PatchSearchOptions,
) -> Result<PatchMatch, VisionError> {
    options.validate()?;
    let n = patch_levels(options).min(pyr_a.len()).min(pyr_b.len());
    let predicted = predicted_b.unwrap_or(point_a);
    if !point_a.iter().chain(&predicted).all(|v| v.is_finite()) {
        return Err(VisionError::InvalidInput("patch point or prediction is not finite".into()));
    }
    let a0 = pyr_a.base();
    let r = options.half_size as f64;
    let (px, py) = (point_a[0].round(), point_a[1].round());
    if px - r < 0.0 || py - r < 0.0 || px + r >= a0.width() as f64 || py + r >= a0.height() as f64 {
        return Err(VisionError::InvalidInput(format!(
            "the {}x{} patch around ({:.1}, {:.1}) leaves image a ({}x{})",
            2 * options.half_size + 1,
            2 * options.half_size + 1,
            point_a[0],
            point_a[1],
            a0.width(),
            a0.height()
        )));
    }
    // Template rectangle per level: centred on round(p / 2^k), shrunk to fit if rounding
    // pushes it over the edge.
    let mut rects = Vec::with_capacity(n);
    for k in 0..n {
        let (lw, lh) = pyr_a.size(k).unwrap_or((0, 0));
        let s = (1u64 << k) as f64;
        let (cx, cy) = ((point_a[0] / s).round() as i64, (point_a[1] / s).round() as i64);
        let mut hk = (options.half_size >> k).max(1) as i64;
        while hk > 1 && (cx - hk < 0 || cy - hk < 0 || cx + hk >= lw as i64 || cy + hk >= lh as i64) {
            hk -= 1;
        }
        if cx - hk < 0 || cy - hk < 0 || cx + hk >= lw as i64 || cy + hk >= lh as i64 {
            return Err(VisionError::InvalidInput("patch leaves image a at a coarse level".into()));
        }
        rects.push(Rect {
            x0: (cx - hk) as usize,
            y0: (cy - hk) as usize,
            x1: (cx + hk + 1) as usize,
            y1: (cy + hk + 1) as usize,
        });
    }
    let t0 = rects[0];
    let s = {
        let (mut s1, mut s2) = (0u64, 0u64);
        for y in t0.y0..t0.y1 {
            for &v in &a0.row(y as u32)[t0.x0..t0.x1] {
                s1 += u64::from(v);
                s2 += u64::from(v) * u64::from(v);
            }
        }
        let m = t0.area() as i128;
        let var = (i128::from(s2) * m - i128::from(s1) * i128::from(s1)) as f64 / (m * m) as f64;
        var.max(0.0).sqrt()
    };
    if s < options.min_texture_std {
        return Err(VisionError::Textureless(format!(
            "the patch around ({:.1}, {:.1}) has intensity std {s:.3} grey levels (< {})",
            point_a[0], point_a[1], options.min_texture_std
        )));
    }
    let pairs: Vec<(Level, Level)> =
        (0..n).map(|k| (Level::of(pyr_a, k, k == n - 1), Level::of(pyr_b, k, k == n - 1))).collect();
    let rect_for = |level: usize, _d: [i64; 2]| Some(rects[level]);
    let c = n - 1;
    let sc = (1u64 << c) as f64;
    let centre = [(predicted[0] - point_a[0]) / sc, (predicted[1] - point_a[1]) / sc];
    let rad = (options.search_radius / sc).ceil() as i64;
    let lo = [centre[0].round() as i64 - rad, centre[1].round() as i64 - rad];
    let hi = [centre[0].round() as i64 + rad, centre[1].round() as i64 + rad];
    let res = coarse_to_fine(&pairs, 0, (lo, hi), &rect_for, options.subpixel).ok_or_else(|| {
        VisionError::InvalidInput(format!(
            "no position within {} px of ({:.1}, {:.1}) keeps the patch inside image b with texture",
            options.search_radius, predicted[0], predicted[1]
        ))
    })?;
    // Shift measured between template centre round(p) and its match; p moves with it.
    Ok(PatchMatch {
        position: [point_a[0] + res.shift[0], point_a[1] + res.shift[1]],
        score: res.score,
        levels_used: n,
        subpixel: res.subpixel,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth analytic texture (sum of sinusoids, wavelengths 10-120 px) sampled with the
    /// content moved by `shift`, quantised to 8 bits.
    pub(crate) fn smooth_texture(w: u32, h: u32, shift: [f64; 2], seed: u64) -> GrayImage {
        let mut st = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        let mut rnd = || {
            st ^= st << 13;
            st ^= st >> 7;
            st ^= st << 17;
            (st >> 11) as f64 / (1u64 << 53) as f64
        };
        let waves: Vec<[f64; 4]> = (0..12)
            .map(|_| {
                let lambda = 10.0 * (12.0f64).powf(rnd());
                let th = std::f64::consts::TAU * rnd();
                let k = std::f64::consts::TAU / lambda;
                [k * th.cos(), k * th.sin(), std::f64::consts::TAU * rnd(), 8.0 + 10.0 * rnd()]
            })
            .collect();
        let data = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| {
                let (u, v) = (x as f64 - shift[0], y as f64 - shift[1]);
                let s: f64 = waves.iter().map(|q| q[3] * (q[0] * u + q[1] * v + q[2]).sin()).sum();
                (128.0 + s).round().clamp(0.0, 255.0) as u8
            })
            .collect();
        GrayImage::new(w, h, data).unwrap()
    }

    #[test]
    fn zncc_identical_affine_and_textureless() {
        let a = FloatImage::from_gray(&smooth_texture(40, 30, [0.0, 0.0], 1));
        assert!((zncc(&a, &a).unwrap() - 1.0).abs() < 1e-12);
        let b = FloatImage::new(40, 30, a.pixels().iter().map(|v| 0.5 * v + 17.0).collect()).unwrap();
        assert!((zncc(&a, &b).unwrap() - 1.0).abs() < 1e-9);
        let c = FloatImage::new(40, 30, a.pixels().iter().map(|v| 300.0 - 2.0 * v).collect()).unwrap();
        assert!((zncc(&a, &c).unwrap() + 1.0).abs() < 1e-9);
        let flat = FloatImage::new(40, 30, vec![9.0; 1200]).unwrap();
        let e = zncc(&a, &flat).unwrap_err();
        assert!(matches!(e, VisionError::Textureless(_)), "{e}");
        let small = FloatImage::new(4, 3, vec![1.0; 12]).unwrap();
        assert!(matches!(zncc(&a, &small), Err(VisionError::InvalidInput(_))));
    }

    #[test]
    fn zncc_rect_matches_direct_formula() {
        let (ga, gb) = (smooth_texture(50, 40, [0.0, 0.0], 2), smooth_texture(50, 40, [3.0, -2.0], 3));
        let (a, b) = (FloatImage::from_gray(&ga), FloatImage::from_gray(&gb));
        fn fl(im: &FloatImage, ints: bool) -> Level<'_> {
            Level::with(50, 40, Pixels::Floats(im.pixels()), ints)
        }
        let (la, lb) = (fl(&a, true), fl(&b, true));
        let (ma, mb) = (fl(&a, false), fl(&b, false));
        let r = Rect { x0: 5, y0: 7, x1: 30, y1: 25 };
        let d = [4i64, -3];
        let got = zncc_rect(&la, &lb, r, d).unwrap();
        let wa: Vec<f32> = (r.y0..r.y1).flat_map(|y| a.row(y)[r.x0..r.x1].to_vec()).collect();
        let wb: Vec<f32> = (r.y0..r.y1)
            .flat_map(|y| {
                b.row((y as i64 + d[1]) as usize)
                    [(r.x0 as i64 + d[0]) as usize..(r.x1 as i64 + d[0]) as usize]
                    .to_vec()
            })
            .collect();
        let want =
            zncc(&FloatImage::new(25, 18, wa).unwrap(), &FloatImage::new(25, 18, wb).unwrap()).unwrap();
        assert!((got - want).abs() < 1e-5, "{got} {want}");
        let direct = zncc_rect(&ma, &mb, r, d).unwrap();
        assert!((direct - want).abs() < 1e-5, "{direct} {want}");
        // Byte levels (full resolution): exact integer sums, with and without integrals.
        for ints in [true, false] {
            let (la, lb) = (
                Level::with(50, 40, Pixels::Bytes(ga.pixels()), ints),
                Level::with(50, 40, Pixels::Bytes(gb.pixels()), ints),
            );
            let got = zncc_rect(&la, &lb, r, d).unwrap();
            assert!((got - want).abs() < 1e-9, "{got} {want}");
        }
        assert!(zncc_rect(&la, &lb, r, [30, 0]).is_none());
    }

    #[test]
    fn quadratic_peak_recovers_paraboloid_maximum() {
        let (x0, y0) = (0.23, -0.31);
        let f = |x: f64, y: f64| {
            1.0 - 0.2 * (x - x0).powi(2) - 0.1 * (y - y0).powi(2) - 0.05 * (x - x0) * (y - y0)
        };
        let mut s = [[0.0; 3]; 3];
        for (j, row) in s.iter_mut().enumerate() {
            for (i, v) in row.iter_mut().enumerate() {
                *v = f(i as f64 - 1.0, j as f64 - 1.0);
            }
        }
        let p = quadratic_peak(&s).unwrap();
        assert!((p[0] - x0).abs() < 1e-12 && (p[1] - y0).abs() < 1e-12, "{p:?}");
        assert!(quadratic_peak(&[[0.0; 3]; 3]).is_none());
    }

    #[test]
    fn registration_recovers_integer_and_subpixel_shifts() {
        let reference = smooth_texture(320, 240, [0.0, 0.0], 7);
        let opts = RegistrationOptions::default();
        // Integer shifts, including large ones found only by the coarsest level.
        for shift in [[0.0, 0.0], [13.0, -7.0], [-61.0, 42.0], [90.0, 5.0]] {
            let moved = smooth_texture(320, 240, shift, 7);
            let r = register_translation(&reference, &moved, &opts).unwrap();
            assert!(
                (r.shift[0] - shift[0]).abs() < 0.05 && (r.shift[1] - shift[1]).abs() < 0.05,
                "{shift:?} {r:?}"
            );
            assert!(r.score > 0.99);
        }
        // Sub-pixel: the quadratic fit of a smooth peak is biased by a few hundredths of a
        // pixel (pixel locking) plus 8-bit quantisation noise; 0.1 px is the stated bar.
        let mut worst: f64 = 0.0;
        for (i, shift) in
            [[0.5, 0.0], [2.3, -1.7], [-5.25, 3.6], [10.9, 0.45], [-0.8, -12.1]].iter().enumerate()
        {
            let moved = smooth_texture(320, 240, *shift, 7);
            let r = register_translation(&reference, &moved, &opts).unwrap();
            assert!(r.subpixel, "{i}");
            worst = worst.max((r.shift[0] - shift[0]).abs()).max((r.shift[1] - shift[1]).abs());
        }
        assert!(worst < 0.1, "worst sub-pixel error {worst}");
        // Verging mode: coarse, within a level-3 pixel (8 px).
        let moved = smooth_texture(320, 240, [37.0, -21.0], 7);
        let r = register_translation(&reference, &moved, &RegistrationOptions::verging()).unwrap();
        assert_eq!(r.finest_level, 3);
        assert!((r.shift[0] - 37.0).abs() < 8.0 && (r.shift[1] + 21.0).abs() < 8.0, "{r:?}");
    }

    #[test]
    fn registration_errors_are_named() {
        let a = smooth_texture(64, 48, [0.0, 0.0], 1);
        let blank = GrayImage::filled(64, 48, 128);
        let e = register_translation(&a, &blank, &RegistrationOptions::default()).unwrap_err();
        assert!(matches!(e, VisionError::Textureless(_)) && e.to_string().contains("moved"), "{e}");
        let small = smooth_texture(60, 48, [0.0, 0.0], 1);
        assert!(matches!(
            register_translation(&a, &small, &RegistrationOptions::default()),
            Err(VisionError::InvalidInput(_))
        ));
        let bad = RegistrationOptions { finest_level: 5, ..Default::default() };
        assert!(matches!(register_translation(&a, &a, &bad), Err(VisionError::InvalidOptions(_))));
        let bad = RegistrationOptions { max_shift_fraction: 1.5, ..Default::default() };
        assert!(bad.validate().is_err());
        // One-pixel images work without panicking (no shift but zero is possible).
        let one = GrayImage::filled(1, 1, 3);
        assert!(register_translation(&one, &one, &RegistrationOptions::default()).is_err());
    }

    #[test]
    fn locate_patch_follows_the_target() {
        let a = smooth_texture(320, 240, [0.0, 0.0], 11);
        let opts = PatchSearchOptions::default();
        for shift in [[0.0, 0.0], [25.0, -14.0], [-50.3, 31.7], [3.4, 2.2]] {
            let b = smooth_texture(320, 240, shift, 11);
            let p = [160.0, 120.0];
            let m = locate_patch(&a, p, &b, None, &opts).unwrap();
            let err = ((m.position[0] - p[0] - shift[0]).powi(2) + (m.position[1] - p[1] - shift[1]).powi(2))
                .sqrt();
            assert!(err < 0.15, "{shift:?} {m:?}");
            assert!(m.score > 0.98);
        }
        // A prediction lets a small search radius find a large motion.
        let b = smooth_texture(320, 240, [100.0, 40.0], 11);
        let small = PatchSearchOptions { search_radius: 10.0, ..Default::default() };
        let m = locate_patch(&a, [100.0, 100.0], &b, Some([198.0, 141.0]), &small).unwrap();
        assert!((m.position[0] - 200.0).abs() < 0.15 && (m.position[1] - 140.0).abs() < 0.15, "{m:?}");
        // Errors: patch off the image, blank patch, bad options.
        assert!(matches!(locate_patch(&a, [5.0, 100.0], &b, None, &opts), Err(VisionError::InvalidInput(_))));
        let blank = GrayImage::filled(320, 240, 0);
        let e = locate_patch(&blank, [160.0, 120.0], &b, None, &opts).unwrap_err();
        assert!(matches!(e, VisionError::Textureless(_)), "{e}");
        let bad = PatchSearchOptions { half_size: 1, ..Default::default() };
        assert!(matches!(
            locate_patch(&a, [160.0, 120.0], &b, None, &bad),
            Err(VisionError::InvalidOptions(_))
        ));
    }
}
