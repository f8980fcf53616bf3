//! Annotated images (the paper's Figure 6): a colour canvas over a grey image with lines,
//! image lines given as homogeneous 3-vectors (clipped to the image), circles and crosses.
//!
//! What it computes: pixels only; nothing is estimated. Coordinates are pixels with
//! `(0, 0)` the centre of the top-left pixel; shapes partly outside the canvas are
//! clipped, shapes wholly outside draw nothing (never an error: an annotation must not
//! fail a run). Lines are drawn with a DDA (one sample per pixel along the major axis)
//! and a square brush of the given width.

use std::path::Path;

use crate::{GrayImage, VisionError};

/// An RGB colour.
pub type Rgb = [u8; 3];

/// Red.
pub const RED: Rgb = [230, 25, 25];
/// Green.
pub const GREEN: Rgb = [20, 200, 40];
/// Blue.
pub const BLUE: Rgb = [40, 90, 255];
/// Yellow.
pub const YELLOW: Rgb = [250, 220, 0];
/// Cyan.
pub const CYAN: Rgb = [0, 210, 230];
/// Magenta.
pub const MAGENTA: Rgb = [230, 0, 200];

/// A colour image to draw on.
#[derive(Clone)]
pub struct Canvas {
    width: u32,
    height: u32,
    data: Vec<u8>,
}

impl Canvas {
    /// A canvas showing a grey image.
    pub fn from_gray(image: &GrayImage) -> Self {
        let data = image.pixels().iter().flat_map(|&v| [v, v, v]).collect();
        Self { width: image.width(), height: image.height(), data }
    }

    /// Two images side by side (left, then right), e.g. a stereo pair. Heights may differ.
    pub fn side_by_side(left: &GrayImage, right: &GrayImage) -> Self {
        let (w, h) = (left.width() + right.width(), left.height().max(right.height()));
        let mut c = Self { width: w, height: h, data: vec![0; 3 * w as usize * h as usize] };
        for (img, x0) in [(left, 0), (right, left.width())] {
            for y in 0..img.height() {
                for (x, &v) in img.row(y).iter().enumerate() {
                    c.put(x0 as i64 + x as i64, i64::from(y), [v, v, v]);
                }
            }
        }
        c
    }

    /// Two canvases side by side (`left`, then `right`); heights may differ.
    pub fn beside(left: &Canvas, right: &Canvas) -> Self {
        let (w, h) = (left.width + right.width, left.height.max(right.height));
        let mut c = Self { width: w, height: h, data: vec![0; 3 * w as usize * h as usize] };
        for (src, x0) in [(left, 0), (right, left.width)] {
            for y in 0..src.height {
                for x in 0..src.width {
                    if let Some(px) = src.get(x, y) {
                        c.put(i64::from(x0 + x), i64::from(y), px);
                    }
                }
            }
        }
        c
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Colour of pixel `(x, y)`, `None` outside.
    pub fn get(&self, x: u32, y: u32) -> Option<Rgb> {
        (x < self.width && y < self.height).then(|| {
            let i = 3 * (y as usize * self.width as usize + x as usize);
            [self.data[i], self.data[i + 1], self.data[i + 2]]
        })
    }

    fn put(&mut self, x: i64, y: i64, c: Rgb) {
        if x < 0 || y < 0 || x >= i64::from(self.width) || y >= i64::from(self.height) {
            return;
        }
        let i = 3 * (y as usize * self.width as usize + x as usize);
        self.data[i..i + 3].copy_from_slice(&c);
    }

    fn dot(&mut self, x: f64, y: f64, c: Rgb, width: u32) {
        let r = i64::from(width.max(1)) / 2;
        let (xi, yi) = ((x + 0.5).floor() as i64, (y + 0.5).floor() as i64);
        for dy in -r..=r {
            for dx in -r..=r {
                self.put(xi + dx, yi + dy, c);
            }
        }
    }

    /// A segment from `a` to `b`.
    pub fn line(&mut self, a: [f64; 2], b: [f64; 2], c: Rgb, width: u32) {
        if !(a.iter().chain(&b).all(|v| v.is_finite())) {
            return;
        }
        // Clip to a generous box first so a far endpoint does not cost millions of steps.
        let Some((a, b)) = clip_segment(a, b, self.width, self.height) else { return };
        let steps = (b[0] - a[0]).abs().max((b[1] - a[1]).abs()).ceil().max(1.0) as usize;
        for i in 0..=steps {
            let t = i as f64 / steps as f64;
            self.dot(a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), c, width);
        }
    }

    /// The image line `l = (a, b, c)` (`a x + b y + c = 0`), clipped to the canvas.
    pub fn image_line(&mut self, l: [f64; 3], c: Rgb, width: u32) {
        let (w, h) = (f64::from(self.width) - 0.5, f64::from(self.height) - 0.5);
        let mut pts: Vec<[f64; 2]> = Vec::new();
        if l[1].abs() > 1e-12 {
            for x in [-0.5, w] {
                let y = -(l[0] * x + l[2]) / l[1];
                if (-0.5..=h).contains(&y) {
                    pts.push([x, y]);
                }
            }
        }
        if l[0].abs() > 1e-12 {
            for y in [-0.5, h] {
                let x = -(l[1] * y + l[2]) / l[0];
                if (-0.5..=w).contains(&x) {
                    pts.push([x, y]);
                }
            }
        }
        if pts.len() >= 2 {
            let (a, b) = (pts[0], pts[pts.len() - 1]);
            self.line(a, b, c, width);
        }
    }

    /// A circle of radius `r` around `centre`.
    pub fn circle(&mut self, centre: [f64; 2], r: f64, c: Rgb, width: u32) {
        if !(centre.iter().all(|v| v.is_finite()) && r.is_finite() && r > 0.0) {
            return;
        }
        let n = (2.0 * std::f64::consts::PI * r).ceil().clamp(8.0, 4096.0) as usize;
        for i in 0..n {
            let t = 2.0 * std::f64::consts::PI * i as f64 / n as f64;
            self.dot(centre[0] + r * t.cos(), centre[1] + r * t.sin(), c, width);
        }
    }

    /// A cross of half-size `s` at `centre`.
    pub fn cross(&mut self, centre: [f64; 2], s: f64, c: Rgb, width: u32) {
        let [x, y] = centre;
        self.line([x - s, y], [x + s, y], c, width);
        self.line([x, y - s], [x, y + s], c, width);
    }

    /// Write a PNG.
    pub fn save(&self, path: &Path) -> Result<(), VisionError> {
        let img = image::RgbImage::from_raw(self.width, self.height, self.data.clone()).ok_or_else(|| {
            VisionError::Write { path: path.to_path_buf(), why: "buffer does not match size".into() }
        })?;
        img.save(path).map_err(|e| VisionError::Write { path: path.to_path_buf(), why: e.to_string() })
    }
}

/// Liang-Barsky clip of a segment to the canvas box (with a one-pixel margin).
fn clip_segment(a: [f64; 2], b: [f64; 2], w: u32, h: u32) -> Option<([f64; 2], [f64; 2])> {
    let (xmin, ymin, xmax, ymax) = (-1.5, -1.5, f64::from(w) + 0.5, f64::from(h) + 0.5);
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, q) in [(-dx, a[0] - xmin), (dx, xmax - a[0]), (-dy, a[1] - ymin), (dy, ymax - a[1])] {
        if p == 0.0 {
            if q < 0.0 {
                return None;
            }
        } else {
            let r = q / p;
            if p < 0.0 {
                t0 = t0.max(r);
            } else {
                t1 = t1.min(r);
            }
        }
    }
    (t0 <= t1).then(|| ([a[0] + t0 * dx, a[1] + t0 * dy], [a[0] + t1 * dx, a[1] + t1 * dy]))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shapes_land_where_asked_and_clip() {
        let img = GrayImage::filled(40, 30, 100);
        let mut c = Canvas::from_gray(&img);
        assert_eq!(c.get(0, 0), Some([100, 100, 100]));
        c.line([2.0, 5.0], [30.0, 5.0], RED, 1);
        assert_eq!(c.get(2, 5), Some(RED));
        assert_eq!(c.get(30, 5), Some(RED));
        assert_eq!(c.get(16, 5), Some(RED));
        assert_eq!(c.get(16, 6), Some([100, 100, 100]));
        // y = 20 as a homogeneous line (0, 1, -20) spans the whole width.
        c.image_line([0.0, 1.0, -20.0], GREEN, 1);
        assert_eq!(c.get(0, 20), Some(GREEN));
        assert_eq!(c.get(39, 20), Some(GREEN));
        c.circle([20.0, 15.0], 5.0, BLUE, 1);
        assert_eq!(c.get(25, 15), Some(BLUE));
        c.cross([10.0, 25.0], 2.0, YELLOW, 1);
        assert_eq!(c.get(10, 23), Some(YELLOW));
        // Far outside, infinite or NaN: nothing drawn, no panic.
        let before = c.data.clone();
        c.line([1e12, 1e12], [2e12, -5e12], RED, 3);
        c.line([f64::NAN, 0.0], [1.0, 1.0], RED, 1);
        c.image_line([0.0, 0.0, 1.0], RED, 1);
        c.circle([1e9, 0.0], 3.0, RED, 1);
        assert_eq!(before, c.data);
        // A segment crossing the canvas from far away is clipped and drawn.
        c.line([-1e9, 10.0], [1e9, 10.0], MAGENTA, 1);
        assert_eq!(c.get(0, 10), Some(MAGENTA));
        assert_eq!(c.get(39, 10), Some(MAGENTA));
    }

    #[test]
    fn side_by_side_and_save() {
        let a = GrayImage::filled(4, 3, 10);
        let b = GrayImage::filled(5, 2, 200);
        let c = Canvas::side_by_side(&a, &b);
        assert_eq!((c.width(), c.height()), (9, 3));
        let d = Canvas::beside(&Canvas::from_gray(&a), &Canvas::from_gray(&b));
        assert!(d.data == c.data);
        assert_eq!(c.get(3, 0), Some([10, 10, 10]));
        assert_eq!(c.get(4, 1), Some([200, 200, 200]));
        assert_eq!(c.get(4, 2), Some([0, 0, 0]));
        let p = crate::test_util::scratch_dir("draw").join("side-by-side.png");
        c.save(&p).unwrap();
        assert!(std::fs::metadata(&p).unwrap().len() > 0);
        std::fs::remove_file(&p).ok();
    }
}
