//! What a rotation change does to depth, and the verdict ([`super`] module docs, "Depth
//! error" and "Verdict").
//!
//! The disparity shift ([`disparity_shift_px`]): with the given rectification applied to
//! the images of the turned camera, a point seen at rectified right pixel `p` (a point far
//! away: a rotation moves every depth alike) appears at `K' R2 dR R2^T K'^-1 p`; its
//! horizontal shift is the error of every disparity measured there. The shift's root mean
//! square over a 9 x 9 grid of the image is the disparity error `dd` (pixels). The depth
//! error at depth `Z` is `dd / d` with `d = f' B / Z` the disparity (first order: the
//! relative change of depth for a small shift), in percent; `f'` the rectified focal
//! length (pixels), `B` the baseline (metres).

use headalign_geometry::rectify::Rectification;
use nalgebra::{Matrix3, Rotation3, Vector3};
use serde::Serialize;

/// The depths of [`DepthErrors`], metres.
pub const DEPTHS_M: [f64; 4] = [1.0, 2.0, 5.0, 10.0];

/// Predicted depth error caused by a rotation change at 1, 2, 5 and 10 m, percent.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct DepthErrors {
    /// At 1 m.
    #[serde(rename = "1")]
    pub at_1m: f64,
    /// At 2 m.
    #[serde(rename = "2")]
    pub at_2m: f64,
    /// At 5 m.
    #[serde(rename = "5")]
    pub at_5m: f64,
    /// At 10 m.
    #[serde(rename = "10")]
    pub at_10m: f64,
}

impl DepthErrors {
    /// The errors of a disparity shift `shift_px` with rectified focal length `focal_px`
    /// and baseline `baseline_m`.
    pub fn of_shift(shift_px: f64, focal_px: f64, baseline_m: f64) -> Self {
        let pct = |z: f64| 100.0 * shift_px * z / (focal_px * baseline_m);
        Self {
            at_1m: pct(DEPTHS_M[0]),
            at_2m: pct(DEPTHS_M[1]),
            at_5m: pct(DEPTHS_M[2]),
            at_10m: pct(DEPTHS_M[3]),
        }
    }

    /// The error at `z` metres (linear in `z`, from the one at 1 m).
    pub fn at(&self, z: f64) -> f64 {
        self.at_1m * z
    }
}

/// Grid points per image side of [`disparity_shift_px`].
pub const GRID: usize = 9;

/// The root-mean-square horizontal shift (pixels) over the image of the given
/// rectification `rect` (image size `size`) caused by turning the right camera by `dR`
/// (module docs).
pub fn disparity_shift_px(rect: &Rectification, size: [u32; 2], dr: &Rotation3<f64>) -> f64 {
    let k = rect.p_right.fixed_view::<3, 3>(0, 0).into_owned();
    let Some(k_inv) = k.try_inverse() else { return f64::NAN };
    let r2: Matrix3<f64> = rect.rect_from_right;
    let m = k * r2 * dr.matrix() * r2.transpose() * k_inv;
    let mut sum = 0.0;
    for i in 0..GRID {
        for j in 0..GRID {
            let x = size[0] as f64 * (i as f64 + 0.5) / GRID as f64;
            let y = size[1] as f64 * (j as f64 + 0.5) / GRID as f64;
            let p = m * Vector3::new(x, y, 1.0);
            let dx = p.x / p.z - x;
            sum += dx * dx;
        }
    }
    (sum / (GRID * GRID) as f64).sqrt()
}
