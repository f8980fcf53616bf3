//! Descriptor matching: brute-force Hamming nearest neighbours with a mutual
//! (cross) check and Lowe's ratio test, free or guided by geometry.
//!
//! - [`match_descriptors`]: every `a` against every `b`.
//! - [`match_epipolar`]: guided by a fundamental matrix `F` with `x_r^T F x_l = 0` (left
//!   image first, as in `docs/how-it-works.md#2-estimation`): a right feature is a candidate for a left
//!   feature only if it lies within `band_px` pixels of the epipolar line `F x_l`.
//! - [`match_predicted`] / [`match_homography`]: guided by a predicting map `x_b ~ G(x_a)`
//!   (e.g. the infinite homography of a known rotation): candidates lie within `radius_px`
//!   of the prediction.
//!
//! In all cases the nearest neighbour of `a` (among its candidates) must be closer than
//! `max_distance` bits and closer than `ratio` times the second nearest (Lowe 2004; the
//! test is skipped if there is no second candidate), and, with `mutual`, `a` must also be
//! the nearest candidate of its `b` (cross check, as OpenCV's `BFMatcher(crossCheck)`).
//! Ties go to the lower index, so results are deterministic.
//!
//! Speed: one pass over the `na x nb` distance matrix computes both directions (row best
//! and second best, column best), split over rayon chunks of rows. The Hamming distance is
//! four XORs and four popcounts; on x86-64 the kernel is compiled a second time with the
//! `popcnt` instruction enabled and chosen at run time (the baseline x86-64 target lacks
//! it, and the bit-twiddling fallback is several times slower). Guided matching checks the
//! cheap geometric test before the distance, so it is faster than free matching.
//!
//! Units: distances in bits (0..256), bands and radii in pixels.

use rayon::prelude::*;

use crate::VisionError;
use crate::features::{Descriptor, Features};

/// One correspondence: `a` indexes the first set, `b` the second.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Match {
    /// Index into the first (left / query) set.
    pub a: usize,
    /// Index into the second (right / train) set.
    pub b: usize,
    /// Hamming distance, bits.
    pub distance: u32,
}

/// Options of the matchers.
#[derive(Clone, Debug, PartialEq)]
pub struct MatchOptions {
    /// Largest accepted distance, bits of 256 (default 64).
    pub max_distance: u32,
    /// Lowe ratio: best must be `< ratio * second best` (default 0.8; 1.0 disables).
    pub ratio: f32,
    /// Require mutual nearest neighbours (default true).
    pub mutual: bool,
}

impl Default for MatchOptions {
    fn default() -> Self {
        Self { max_distance: 64, ratio: 0.8, mutual: true }
    }
}

impl MatchOptions {
    /// Check the options.
    pub fn validate(&self) -> Result<(), VisionError> {
        if !(self.ratio > 0.0 && self.ratio <= 1.0) {
            return Err(VisionError::InvalidOptions(format!("ratio must be in (0, 1], got {}", self.ratio)));
        }
        Ok(())
    }
}

#[derive(Clone, Copy)]
struct RowBest {
    j: u32,
    d1: u32,
    d2: u32,
}

const NONE: u32 = u32::MAX;

/// Scan rows `a0..a0 + a.len()` against all of `b`; updates column bests `(dist, i)`.
#[inline(always)]
fn scan<F: Fn(usize, usize) -> bool>(
    a: &[Descriptor],
    a0: usize,
    b: &[Descriptor],
    allowed: &F,
    rows: &mut Vec<RowBest>,
    cols: &mut [(u32, u32)],
) {
    for (ii, da) in a.iter().enumerate() {
        let i = a0 + ii;
        let mut best = RowBest { j: NONE, d1: NONE, d2: NONE };
        for (j, (db, col)) in b.iter().zip(cols.iter_mut()).enumerate() {
            if !allowed(i, j) {
                continue;
            }
            let d = da.hamming(db);
            if d < best.d1 {
                best.d2 = best.d1;
                best.d1 = d;
                best.j = j as u32;
            } else if d < best.d2 {
                best.d2 = d;
            }
            if d < col.0 {
                *col = (d, i as u32);
            }
        }
        rows.push(best);
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "popcnt")]
unsafe fn scan_popcnt<F: Fn(usize, usize) -> bool>(
    a: &[Descriptor],
    a0: usize,
    b: &[Descriptor],
    allowed: &F,
    rows: &mut Vec<RowBest>,
    cols: &mut [(u32, u32)],
) {
    scan(a, a0, b, allowed, rows, cols)
}

fn scan_dispatch<F: Fn(usize, usize) -> bool>(
    a: &[Descriptor],
    a0: usize,
    b: &[Descriptor],
    allowed: &F,
    rows: &mut Vec<RowBest>,
    cols: &mut [(u32, u32)],
) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("popcnt") {
            // SAFETY: the CPU supports popcnt (checked just above), which is the only
            // requirement of the target_feature function.
            unsafe { scan_popcnt(a, a0, b, allowed, rows, cols) };
            return;
        }
    }
    scan(a, a0, b, allowed, rows, cols)
}

/// The shared matcher: nearest neighbours under `allowed(i, j)`.
fn match_core<F: Fn(usize, usize) -> bool + Sync>(
    a: &[Descriptor],
    b: &[Descriptor],
    allowed: F,
    options: &MatchOptions,
) -> Result<Vec<Match>, VisionError> {
    options.validate()?;
    if a.is_empty() || b.is_empty() {
        return Ok(Vec::new());
    }
    const CHUNK: usize = 128;
    type ChunkResult = (Vec<RowBest>, Vec<(u32, u32)>);
    let parts: Vec<ChunkResult> = a
        .par_chunks(CHUNK)
        .enumerate()
        .map(|(c, chunk)| {
            let mut rows = Vec::with_capacity(chunk.len());
            let mut cols = vec![(NONE, NONE); b.len()];
            scan_dispatch(chunk, c * CHUNK, b, &allowed, &mut rows, &mut cols);
            (rows, cols)
        })
        .collect();
    // Merge column bests (chunks in order, so ties keep the lower row index).
    let mut cols = vec![(NONE, NONE); b.len()];
    for (_, pc) in &parts {
        for (m, p) in cols.iter_mut().zip(pc) {
            if p.0 < m.0 {
                *m = *p;
            }
        }
    }
    let mut out = Vec::new();
    for (i, r) in parts.iter().flat_map(|(rows, _)| rows).enumerate() {
        if r.j == NONE || r.d1 > options.max_distance {
            continue;
        }
        if r.d2 != NONE && r.d1 as f32 >= options.ratio * r.d2 as f32 {
            continue;
        }
        if options.mutual && cols[r.j as usize].1 as usize != i {
            continue;
        }
        out.push(Match { a: i, b: r.j as usize, distance: r.d1 });
    }
    Ok(out)
}

/// Brute-force matching of every `a` against every `b` (see the module docs).
pub fn match_descriptors(
    a: &[Descriptor],
    b: &[Descriptor],
    options: &MatchOptions,
) -> Result<Vec<Match>, VisionError> {
    match_core(a, b, |_, _| true, options)
}

fn check_features(f: &Features, name: &str) -> Result<(), VisionError> {
    if f.keypoints.len() != f.descriptors.len() {
        return Err(VisionError::InvalidInput(format!(
            "{name} features have {} keypoints but {} descriptors",
            f.keypoints.len(),
            f.descriptors.len()
        )));
    }
    Ok(())
}

/// Matching guided by a fundamental matrix (row-major, `x_r^T F x_l = 0`): right feature
/// `j` is a candidate for left feature `i` if its distance to the epipolar line `F x_l`
/// is at most `band_px` pixels. `Match::a` indexes `left`, `Match::b` indexes `right`.
pub fn match_epipolar(
    left: &Features,
    right: &Features,
    f_right_left: &[[f64; 3]; 3],
    band_px: f64,
    options: &MatchOptions,
) -> Result<Vec<Match>, VisionError> {
    check_features(left, "left")?;
    check_features(right, "right")?;
    if !(band_px.is_finite() && band_px >= 0.0) {
        return Err(VisionError::InvalidOptions(format!("band must be finite and >= 0, got {band_px}")));
    }
    if f_right_left.iter().flatten().any(|v| !v.is_finite()) {
        return Err(VisionError::InvalidInput("fundamental matrix has non-finite entries".into()));
    }
    let f = f_right_left;
    // Normalised lines (a, b, c) with a^2 + b^2 = 1; degenerate lines allow nothing.
    let lines: Vec<Option<[f64; 3]>> = left
        .keypoints
        .iter()
        .map(|k| {
            let (x, y) = (f64::from(k.x), f64::from(k.y));
            let l = [0, 1, 2].map(|r| f[r][0] * x + f[r][1] * y + f[r][2]);
            let n = l[0].hypot(l[1]);
            (n > 1e-12).then(|| [l[0] / n, l[1] / n, l[2] / n])
        })
        .collect();
    let pts: Vec<[f64; 2]> = right.keypoints.iter().map(|k| [f64::from(k.x), f64::from(k.y)]).collect();
    let allowed = |i: usize, j: usize| {
        lines[i].is_some_and(|l| (l[0] * pts[j][0] + l[1] * pts[j][1] + l[2]).abs() <= band_px)
    };
    match_core(&left.descriptors, &right.descriptors, allowed, options)
}

/// Matching guided by a predicting map: `b` feature `j` is a candidate for `a` feature `i`
/// if it lies within `radius_px` of `predict(x_i)` (`None` = no prediction, no match).
pub fn match_predicted<P: Fn([f64; 2]) -> Option<[f64; 2]>>(
    a: &Features,
    b: &Features,
    predict: P,
    radius_px: f64,
    options: &MatchOptions,
) -> Result<Vec<Match>, VisionError> {
    check_features(a, "first")?;
    check_features(b, "second")?;
    if !(radius_px.is_finite() && radius_px >= 0.0) {
        return Err(VisionError::InvalidOptions(format!("radius must be finite and >= 0, got {radius_px}")));
    }
    let pred: Vec<Option<[f64; 2]>> = a
        .keypoints
        .iter()
        .map(|k| predict([f64::from(k.x), f64::from(k.y)]).filter(|p| p[0].is_finite() && p[1].is_finite()))
        .collect();
    let pts: Vec<[f64; 2]> = b.keypoints.iter().map(|k| [f64::from(k.x), f64::from(k.y)]).collect();
    let r2 = radius_px * radius_px;
    let allowed = |i: usize, j: usize| {
        pred[i].is_some_and(|p| (p[0] - pts[j][0]).powi(2) + (p[1] - pts[j][1]).powi(2) <= r2)
    };
    match_core(&a.descriptors, &b.descriptors, allowed, options)
}

/// [`match_predicted`] with a homography `x_b ~ G x_a` (row-major, any scale or sign).
/// Points mapped to (near) infinity have no prediction.
pub fn match_homography(
    a: &Features,
    b: &Features,
    g_b_a: &[[f64; 3]; 3],
    radius_px: f64,
    options: &MatchOptions,
) -> Result<Vec<Match>, VisionError> {
    if g_b_a.iter().flatten().any(|v| !v.is_finite()) {
        return Err(VisionError::InvalidInput("homography has non-finite entries".into()));
    }
    let g = *g_b_a;
    let predict = move |p: [f64; 2]| {
        let v = [0, 1, 2].map(|r| g[r][0] * p[0] + g[r][1] * p[1] + g[r][2]);
        (v[2].abs() > 1e-12).then(|| [v[0] / v[2], v[1] / v[2]])
    };
    match_predicted(a, b, predict, radius_px, options)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::features::tests::rect_scene;
    use crate::features::{FeatureOptions, detect_and_describe};
    use proptest::prelude::*;

    /// Reference implementation: the definition, written plainly.
    fn naive(a: &[Descriptor], b: &[Descriptor], o: &MatchOptions) -> Vec<Match> {
        let mut out = Vec::new();
        for (i, da) in a.iter().enumerate() {
            let mut ds: Vec<(u32, usize)> = b.iter().enumerate().map(|(j, db)| (da.hamming(db), j)).collect();
            ds.sort();
            let (d1, j) = ds[0];
            if d1 > o.max_distance || (ds.len() > 1 && d1 as f32 >= o.ratio * ds[1].0 as f32) {
                continue;
            }
            let back = a.iter().enumerate().map(|(k, dk)| (dk.hamming(&b[j]), k)).min().map(|p| p.1);
            if o.mutual && back != Some(i) {
                continue;
            }
            out.push(Match { a: i, b: j, distance: d1 });
        }
        out
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(40))]
        #[test]
        fn brute_force_equals_definition(seed in any::<u64>(), na in 1usize..300, nb in 1usize..300) {
            let mut s = seed | 1;
            let mut rnd = || { s ^= s << 13; s ^= s >> 7; s ^= s << 17; s };
            // Few distinct bits so that near neighbours and ties occur.
            let mut desc = |_| Descriptor([rnd() & rnd(), rnd() & 0xFF, 0, rnd() & rnd() & rnd()]);
            let a: Vec<Descriptor> = (0..na).map(&mut desc).collect();
            let b: Vec<Descriptor> = (0..nb).map(&mut desc).collect();
            for o in [MatchOptions::default(), MatchOptions { max_distance: 256, ratio: 1.0, mutual: false }] {
                prop_assert_eq!(match_descriptors(&a, &b, &o).unwrap(), naive(&a, &b, &o));
            }
        }
    }

    fn pair() -> (Features, Features) {
        let a = rect_scene(400, 300, 20, 30, 2, 5);
        let b = rect_scene(400, 300, 27, 35, 2, 5);
        let o = FeatureOptions::default();
        (detect_and_describe(&a, &o).unwrap(), detect_and_describe(&b, &o).unwrap())
    }

    /// Fraction of matches whose b point is at a's point minus the scene shift (7, 5).
    fn correct(a: &Features, b: &Features, m: &[Match]) -> f64 {
        let ok = m
            .iter()
            .filter(|m| {
                let (ka, kb) = (a.keypoints[m.a], b.keypoints[m.b]);
                (kb.x - ka.x + 7.0).hypot(kb.y - ka.y + 5.0) < 1.5
            })
            .count();
        ok as f64 / m.len().max(1) as f64
    }

    #[test]
    fn descriptors_of_a_shifted_image_match() {
        let (a, b) = pair();
        let m = match_descriptors(&a.descriptors, &b.descriptors, &MatchOptions::default()).unwrap();
        assert!(m.len() > 300, "{} matches", m.len());
        let c = correct(&a, &b, &m);
        assert!(c > 0.9, "correct fraction {c}");
    }

    #[test]
    fn guided_matching_respects_band_and_radius() {
        let (a, b) = pair();
        let o = MatchOptions::default();
        // Pure image translation t = (-7, -5): epipole at infinity e = (7, 5, 0), F = [e]x.
        let f = [[0.0, 0.0, 5.0], [0.0, 0.0, -7.0], [-5.0, 7.0, 0.0]];
        let band = 1.5;
        let m = match_epipolar(&a, &b, &f, band, &o).unwrap();
        assert!(m.len() > 300 && correct(&a, &b, &m) > 0.95, "{} {}", m.len(), correct(&a, &b, &m));
        for mm in &m {
            let (ka, kb) = (a.keypoints[mm.a], b.keypoints[mm.b]);
            let (xa, ya, xb, yb) = (f64::from(ka.x), f64::from(ka.y), f64::from(kb.x), f64::from(kb.y));
            let l = [0, 1, 2].map(|r| f[r][0] * xa + f[r][1] * ya + f[r][2]);
            let d = (l[0] * xb + l[1] * yb + l[2]).abs() / l[0].hypot(l[1]);
            assert!(d <= band + 1e-9, "distance to epipolar line {d}");
        }
        // A wrong F (epipolar lines 20 px off) finds (almost) nothing right.
        let wrong = [[0.0, 0.0, 5.0], [0.0, 0.0, -7.0], [-5.0, 7.0, 20.0 * 74f64.sqrt()]];
        let mw = match_epipolar(&a, &b, &wrong, band, &o).unwrap();
        assert!(correct(&a, &b, &mw) * (mw.len() as f64) < 10.0, "{}", mw.len());
        // Homography prediction x_b = x_a - (7, 5), radius 3 px.
        let g = [[1.0, 0.0, -7.0], [0.0, 1.0, -5.0], [0.0, 0.0, 1.0]];
        let m = match_homography(&a, &b, &g, 3.0, &o).unwrap();
        assert!(m.len() > 300 && correct(&a, &b, &m) > 0.97);
        for mm in &m {
            let (ka, kb) = (a.keypoints[mm.a], b.keypoints[mm.b]);
            assert!((kb.x - ka.x + 7.0).hypot(kb.y - ka.y + 5.0) <= 3.0 + 1e-4);
        }
        // Errors and degenerate input.
        assert!(match_epipolar(&a, &b, &f, -1.0, &o).is_err());
        assert!(match_epipolar(&a, &b, &[[f64::NAN; 3]; 3], 1.0, &o).is_err());
        assert!(match_predicted(&a, &b, |_| None, 3.0, &o).unwrap().is_empty());
        let bad = MatchOptions { ratio: 0.0, ..Default::default() };
        assert!(match_descriptors(&a.descriptors, &b.descriptors, &bad).is_err());
        assert!(match_descriptors(&[], &b.descriptors, &o).unwrap().is_empty());
        let broken = Features { keypoints: a.keypoints.clone(), descriptors: vec![] };
        assert!(matches!(match_homography(&broken, &b, &g, 3.0, &o), Err(VisionError::InvalidInput(_))));
    }
}
