//! Float images, separable Gaussian blur and the 2x Gaussian pyramid used by pyramid
//! correlation (paper section 5 step 3: "repeatedly smoothing and subsampling by two",
//! after Burt and Adelson's Gaussian pyramid).
//!
//! - [`FloatImage`]: `f32` grey values (same scale as the 8-bit input, 0..255), row-major.
//! - [`gaussian_blur`]: separable Gaussian of standard deviation `sigma` pixels, kernel
//!   truncated at `ceil(3 sigma)`, borders replicated (clamp-to-edge).
//! - [`Pyramid`]: level 0 is the image itself; level `k + 1` is level `k` smoothed with the
//!   5-tap binomial kernel `[1 4 6 4 1] / 16` (sigma = 1 pixel of level `k`) and sampled at
//!   even pixels, so its size is `ceil(w / 2) x ceil(h / 2)`.
//!
//! Coordinates: pixel `x` of level `k + 1` sits exactly on pixel `2x` of level `k` (centres
//! aligned at `(0, 0)`), so a position or shift `p` at level `k` is `p * 2^k` at full
//! resolution. No half-pixel offset is needed, unlike the "average 2x2 blocks" pyramid.
//!
//! Pitfalls: the binomial kernel is not an ideal low-pass, so a little aliasing remains
//! (harmless for correlation peaks); clamped borders bias the outermost two pixels of
//! each level. Rows are processed in parallel with rayon once a level has more than
//! [`PARALLEL_MIN_PIXELS`] pixels (below that the thread hand-off costs more than it saves).

use rayon::prelude::*;

use crate::{GrayImage, VisionError};

/// Levels (or images) with fewer pixels than this are processed on one thread.
pub const PARALLEL_MIN_PIXELS: usize = 64 * 1024;

/// A grey image of `f32` values, row-major, `width x height` (both at least 1).
#[derive(Clone, PartialEq)]
pub struct FloatImage {
    width: usize,
    height: usize,
    data: Vec<f32>,
}

impl std::fmt::Debug for FloatImage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "FloatImage({}x{})", self.width, self.height)
    }
}

impl FloatImage {
    /// An image from its row-major values; errors if a side is zero or the buffer length
    /// is not `width * height`.
    pub fn new(width: usize, height: usize, data: Vec<f32>) -> Result<Self, VisionError> {
        if width == 0 || height == 0 {
            return Err(VisionError::InvalidImage(format!("zero size {width}x{height}")));
        }
        if data.len() != width * height {
            return Err(VisionError::InvalidImage(format!(
                "{width}x{height} needs {} values, got {}",
                width * height,
                data.len()
            )));
        }
        Ok(Self { width, height, data })
    }

    /// The 8-bit image as floats (0..255).
    pub fn from_gray(img: &GrayImage) -> Self {
        Self {
            width: img.width() as usize,
            height: img.height() as usize,
            data: img.pixels().iter().map(|&v| f32::from(v)).collect(),
        }
    }

    /// Round and clamp to 8 bits.
    pub fn to_gray(&self) -> GrayImage {
        let data = self.data.iter().map(|&v| v.round().clamp(0.0, 255.0) as u8).collect();
        // Sizes are non-zero and consistent by construction.
        GrayImage::new(self.width as u32, self.height as u32, data)
            .unwrap_or_else(|_| GrayImage::filled(1, 1, 0))
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// The row-major values.
    pub fn pixels(&self) -> &[f32] {
        &self.data
    }

    /// Row `y` (panics if `y >= height`, a programming error, never data).
    pub fn row(&self, y: usize) -> &[f32] {
        &self.data[y * self.width..(y + 1) * self.width]
    }

    /// Value at `(x, y)`, `None` outside the image.
    pub fn get(&self, x: usize, y: usize) -> Option<f32> {
        (x < self.width && y < self.height).then(|| self.data[y * self.width + x])
    }

    /// Mean value.
    pub fn mean(&self) -> f64 {
        self.data.iter().map(|&v| f64::from(v)).sum::<f64>() / self.data.len() as f64
    }
}

/// Sampled, normalised Gaussian kernel of standard deviation `sigma`, radius `ceil(3 sigma)`.
fn gaussian_kernel(sigma: f32) -> Vec<f32> {
    let r = (3.0 * sigma).ceil().max(1.0) as i32;
    let mut k: Vec<f32> = (-r..=r).map(|i| (-(i * i) as f32 / (2.0 * sigma * sigma)).exp()).collect();
    let s: f32 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= s);
    k
}

/// Convolve one row with an odd kernel, replicating the border.
fn convolve_row(src: &[f32], dst: &mut [f32], k: &[f32]) {
    let w = src.len() as isize;
    let r = (k.len() / 2) as isize;
    for (x, out) in dst.iter_mut().enumerate() {
        let x = x as isize;
        let mut acc = 0.0;
        if x >= r && x + r < w {
            let s = &src[(x - r) as usize..(x + r + 1) as usize];
            for (a, b) in s.iter().zip(k) {
                acc += a * b;
            }
        } else {
            for (i, kv) in k.iter().enumerate() {
                let xi = (x + i as isize - r).clamp(0, w - 1) as usize;
                acc += src[xi] * kv;
            }
        }
        *out = acc;
    }
}

/// Separable Gaussian blur of standard deviation `sigma` pixels (borders replicated).
/// Errors if `sigma` is not finite and positive.
pub fn gaussian_blur(img: &FloatImage, sigma: f32) -> Result<FloatImage, VisionError> {
    if !(sigma.is_finite() && sigma > 0.0) {
        return Err(VisionError::InvalidOptions(format!("blur sigma must be positive, got {sigma}")));
    }
    let k = gaussian_kernel(sigma);
    let (w, h) = (img.width, img.height);
    let r = k.len() / 2;
    let parallel = w * h >= PARALLEL_MIN_PIXELS;
    // Horizontal pass.
    let mut tmp = vec![0.0f32; w * h];
    let hpass = |(y, dst): (usize, &mut [f32])| convolve_row(img.row(y), dst, &k);
    if parallel {
        tmp.par_chunks_mut(w).enumerate().for_each(hpass);
    } else {
        tmp.chunks_mut(w).enumerate().for_each(hpass);
    }
    // Vertical pass: whole rows at a time so the inner loop runs along memory.
    let mut out = vec![0.0f32; w * h];
    let vpass = |(y, dst): (usize, &mut [f32])| {
        dst.iter_mut().for_each(|v| *v = 0.0);
        for (i, kv) in k.iter().enumerate() {
            let yi = (y as isize + i as isize - r as isize).clamp(0, h as isize - 1) as usize;
            let src = &tmp[yi * w..(yi + 1) * w];
            for (d, s) in dst.iter_mut().zip(src) {
                *d += kv * s;
            }
        }
    };
    if parallel {
        out.par_chunks_mut(w).enumerate().for_each(vpass);
    } else {
        out.chunks_mut(w).enumerate().for_each(vpass);
    }
    FloatImage::new(w, h, out)
}

/// Smooth with `[1 4 6 4 1] / 16` and keep even pixels: `ceil(w/2) x ceil(h/2)`.
/// Only the needed rows and columns are filtered.
pub fn downsample2(img: &FloatImage) -> FloatImage {
    const K: [f32; 5] = [1.0 / 16.0, 4.0 / 16.0, 6.0 / 16.0, 4.0 / 16.0, 1.0 / 16.0];
    let (w, h) = (img.width, img.height);
    let (wo, ho) = (w.div_ceil(2), h.div_ceil(2));
    let mut out = vec![0.0f32; wo * ho];
    let row_job = |(yo, dst): (usize, &mut [f32])| {
        // Vertical filter of the 5 source rows around 2*yo into a full-width scratch row.
        let mut col = vec![0.0f32; w];
        for (i, kv) in K.iter().enumerate() {
            let yi = (2 * yo as isize + i as isize - 2).clamp(0, h as isize - 1) as usize;
            for (c, s) in col.iter_mut().zip(img.row(yi)) {
                *c += kv * s;
            }
        }
        for (xo, d) in dst.iter_mut().enumerate() {
            let x = 2 * xo as isize;
            let mut acc = 0.0;
            for (i, kv) in K.iter().enumerate() {
                let xi = (x + i as isize - 2).clamp(0, w as isize - 1) as usize;
                acc += kv * col[xi];
            }
            *d = acc;
        }
    };
    if w * h >= PARALLEL_MIN_PIXELS {
        out.par_chunks_mut(wo).enumerate().for_each(row_job);
    } else {
        out.chunks_mut(wo).enumerate().for_each(row_job);
    }
    FloatImage { width: wo, height: ho, data: out }
}

/// A Gaussian pyramid: `level(0)` is the full-resolution image, each further level half
/// the size (see the module docs for the exact kernel and coordinates).
#[derive(Clone, Debug)]
pub struct Pyramid {
    levels: Vec<FloatImage>,
}

impl Pyramid {
    /// Build up to `levels` levels (at least 1). Building stops early once a side would
    /// drop below 2 pixels, so [`Pyramid::len`] may be smaller than asked.
    pub fn new(img: &GrayImage, levels: usize) -> Result<Self, VisionError> {
        Self::from_float(FloatImage::from_gray(img), levels)
    }

    /// As [`Pyramid::new`], from a float image.
    pub fn from_float(img: FloatImage, levels: usize) -> Result<Self, VisionError> {
        if levels == 0 {
            return Err(VisionError::InvalidOptions("a pyramid needs at least one level".into()));
        }
        let mut out = vec![img];
        while out.len() < levels {
            let last = &out[out.len() - 1];
            if last.width < 4 || last.height < 4 {
                break;
            }
            let next = downsample2(last);
            out.push(next);
        }
        Ok(Self { levels: out })
    }

    /// Number of levels.
    pub fn len(&self) -> usize {
        self.levels.len()
    }

    /// Always false (a pyramid has at least its full-resolution level).
    pub fn is_empty(&self) -> bool {
        self.levels.is_empty()
    }

    /// Level `k` (0 = full resolution); `None` beyond the last level.
    pub fn level(&self, k: usize) -> Option<&FloatImage> {
        self.levels.get(k)
    }

    /// All levels, finest first.
    pub fn levels(&self) -> &[FloatImage] {
        &self.levels
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(w: u32, h: u32) -> GrayImage {
        let data = (0..h).flat_map(|y| (0..w).map(move |x| ((x * 3 + y * 5) % 256) as u8)).collect();
        GrayImage::new(w, h, data).unwrap()
    }

    #[test]
    fn pyramid_level_sizes() {
        let p = Pyramid::new(&ramp(768, 577), 5).unwrap();
        let sizes: Vec<_> = p.levels().iter().map(|l| (l.width(), l.height())).collect();
        assert_eq!(sizes, vec![(768, 577), (384, 289), (192, 145), (96, 73), (48, 37)]);
        // Stops early on tiny images.
        let p = Pyramid::new(&ramp(5, 9), 10).unwrap();
        assert_eq!(p.len(), 2);
        assert_eq!((p.level(1).unwrap().width(), p.level(1).unwrap().height()), (3, 5));
        assert!(Pyramid::new(&ramp(5, 5), 0).is_err());
    }

    #[test]
    fn pyramid_values() {
        // A constant image stays constant (the kernel sums to one, borders replicate).
        let p = Pyramid::new(&GrayImage::filled(64, 48, 77), 4).unwrap();
        for l in p.levels() {
            assert!(l.pixels().iter().all(|&v| (v - 77.0).abs() < 1e-4));
        }
        // A linear ramp is reproduced exactly away from the border: the symmetric kernel
        // has zero first moment, so level 1 at x equals level 0 at 2x.
        let data: Vec<f32> = (0..40).flat_map(|y| (0..60).map(move |x| (x + 2 * y) as f32)).collect();
        let img = FloatImage::new(60, 40, data).unwrap();
        let l1 = downsample2(&img);
        for y in 2..l1.height() - 2 {
            for x in 2..l1.width() - 2 {
                let want = img.get(2 * x, 2 * y).unwrap();
                assert!((l1.get(x, y).unwrap() - want).abs() < 1e-3);
            }
        }
        // Level 1 of a checkerboard of period 2 is flat (the binomial kernel kills Nyquist).
        let data: Vec<f32> =
            (0..32).flat_map(|y| (0..32).map(move |x| if (x + y) % 2 == 0 { 200.0 } else { 0.0 })).collect();
        let l1 = downsample2(&FloatImage::new(32, 32, data).unwrap());
        for y in 2..14 {
            for x in 2..14 {
                assert!((l1.get(x, y).unwrap() - 100.0).abs() < 1e-3);
            }
        }
    }

    #[test]
    fn gaussian_blur_preserves_mean_and_smooths() {
        let img = FloatImage::from_gray(&ramp(300, 250));
        let b = gaussian_blur(&img, 1.5).unwrap();
        assert_eq!((b.width(), b.height()), (300, 250));
        let (m0, m1) = (img.mean(), b.mean());
        assert!((m0 - m1).abs() < 2.0, "{m0} {m1}");
        let var = |im: &FloatImage| {
            let m = im.mean();
            im.pixels().iter().map(|&v| (f64::from(v) - m).powi(2)).sum::<f64>()
        };
        assert!(var(&b) < var(&img));
        assert!(gaussian_blur(&img, 0.0).is_err());
        assert!(gaussian_blur(&img, f32::NAN).is_err());
        assert!(FloatImage::new(0, 3, vec![]).is_err());
        assert!(FloatImage::new(2, 3, vec![0.0; 5]).is_err());
    }
}
