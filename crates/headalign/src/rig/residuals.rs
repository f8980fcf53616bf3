//! Structure in the final reprojection residuals of a self-calibration: the symptom of
//! data that do not fit the model (a lens model that cannot follow the real lens, tracks
//! with position-dependent errors), which the linearised sigmas cannot see.
//!
//! What it computes, per camera, on the final adjustment's observations:
//! - **rings**: the observations in [`RINGS`] rings of equal width in the distance from the
//!   principal point (to the farthest observation); per ring the count, the RMS residual
//!   per coordinate and the mean of the residual's radial component (pixels);
//! - **regions**: a [`GRID`] x [`GRID`] grid over the image; per cell the mean residual
//!   vector;
//! - a chi-square of those means against the noise: `sum_ring n m^2 / sigma^2` (one degree
//!   of freedom per ring with at least [`MIN_PER_BIN`] observations) and
//!   `sum_cell n |m|^2 / sigma^2` (two per cell). Under the model, with independent errors
//!   of standard deviation `sigma` (the adjustment's own noise estimate), each is
//!   chi-square distributed (slightly less: the fit absorbs part of any pattern).
//!
//! A statistic beyond the 99.9 % quantile (Wilson-Hilferty approximation), or an outer
//! ring whose RMS is more than [`RMS_GROWTH_WARN`] times the inner one's, is a
//! [`ResidualStructure::warnings`] entry naming the symptom; the report then widens the
//! intrinsics' and lens sigmas by `sqrt(chi2 / dof)` of the worse statistic (a variance
//! inflation for lack of fit: the scatter the model leaves unexplained is treated as
//! noise of the same size).
//!
//! Units: pixels; chi-squares dimensionless. Degrees of freedom: none estimated.
//!
//! Pitfalls: a point seen twice absorbs much of its own residual, so the statistics are
//! conservative (they under-state a pattern); the rings use the estimated principal point
//! (its error is itself part of what they test). Sigmas widened here are a lack-of-fit
//! correction, not a model of the error: the warning says what to change (the lens
//! model, or the data at the border).

use headalign_geometry::bundle::{BundleObservation, RigState, Side, residual_pixels};
use serde::Serialize;

/// Rings of the radial statistic.
pub const RINGS: usize = 5;
/// Cells per side of the region grid.
pub const GRID: usize = 3;
/// Bins with fewer observations are left out of the statistics.
pub const MIN_PER_BIN: usize = 20;
/// Outer over inner ring RMS above which the report warns.
pub const RMS_GROWTH_WARN: f64 = 1.5;

/// One ring of [`CameraResiduals::rings`].
#[derive(Debug, Clone, Serialize)]
pub struct Ring {
    /// Outer radius, pixels from the principal point.
    pub outer_px: f64,
    /// Observations.
    pub count: usize,
    /// RMS residual per coordinate, pixels.
    pub rms_px: f64,
    /// Mean radial component (positive: predicted farther out than observed), pixels.
    pub mean_radial_px: f64,
}

/// The statistics of one camera.
#[derive(Debug, Clone, Serialize)]
pub struct CameraResiduals {
    /// `left` or `right`.
    pub camera: String,
    /// Rings from the centre out.
    pub rings: Vec<Ring>,
    /// Chi-square of the rings' mean radial residuals, and its degrees of freedom.
    pub radial_chi2: f64,
    /// Degrees of freedom of `radial_chi2`.
    pub radial_dof: usize,
    /// Chi-square of the grid cells' mean residual vectors.
    pub region_chi2: f64,
    /// Degrees of freedom of `region_chi2`.
    pub region_dof: usize,
    /// RMS of the outermost over the innermost populated ring.
    pub rms_growth: f64,
}

impl CameraResiduals {
    /// Whether the mean radial residuals by ring exceed their 99.9 % chi-square limit.
    pub fn radial_pattern(&self) -> bool {
        self.radial_dof > 0 && self.radial_chi2 > chi2_quantile_999(self.radial_dof)
    }

    /// Whether the mean residuals by image region exceed their 99.9 % chi-square limit.
    pub fn region_pattern(&self) -> bool {
        self.region_dof > 0 && self.region_chi2 > chi2_quantile_999(self.region_dof)
    }
}

/// Both cameras' statistics, the warnings and the widening applied.
#[derive(Debug, Clone, Serialize)]
pub struct ResidualStructure {
    /// Noise sigma of the chi-squares, pixels.
    pub sigma_px: f64,
    /// Left and right.
    pub cameras: Vec<CameraResiduals>,
    /// The factor the intrinsics' and lens sigmas were multiplied by (1: none).
    pub sigma_widening: f64,
    /// One entry per symptom found.
    pub warnings: Vec<String>,
}

/// The 99.9 % quantile of chi-square with `dof` degrees of freedom (Wilson-Hilferty).
pub(crate) fn chi2_quantile_999(dof: usize) -> f64 {
    let k = dof.max(1) as f64;
    let z = 3.090_232;
    let a = 2.0 / (9.0 * k);
    k * (1.0 - a + z * a.sqrt()).powi(3)
}

/// The statistics of the module docs for `state` on `observations` (`image_size` in
/// pixels, `sigma_px` the noise).
pub fn residual_structure(
    state: &RigState,
    observations: &[BundleObservation],
    image_size: [u32; 2],
    sigma_px: f64,
) -> ResidualStructure {
    let sigma = sigma_px.max(1e-9);
    let cameras: Vec<CameraResiduals> = [Side::Left, Side::Right]
        .into_iter()
        .map(|side| camera_residuals(state, observations, side, image_size, sigma))
        .collect();
    let mut warnings = Vec::new();
    let mut worst_ratio: f64 = 1.0;
    for c in &cameras {
        if c.radial_pattern() {
            let (ring, m) = c
                .rings
                .iter()
                .filter(|r| r.count >= MIN_PER_BIN)
                .map(|r| (r, r.mean_radial_px * (r.count as f64).sqrt() / sigma))
                .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
                .map_or((None, 0.0), |(r, z)| (Some(r), z));
            warnings.push(format!(
                "{} camera: the residuals have a radial pattern (chi-square {:.0} for {} rings, 99.9 % limit {:.0}; largest at {:.0} px from the centre, mean radial residual {:+.3} px, {m:+.1} sigmas): the lens model does not follow this lens, or the tracks there are biased; try another --lens model",
                c.camera,
                c.radial_chi2,
                c.radial_dof,
                chi2_quantile_999(c.radial_dof),
                ring.map_or(0.0, |r| r.outer_px),
                ring.map_or(0.0, |r| r.mean_radial_px)
            ));
            worst_ratio = worst_ratio.max(c.radial_chi2 / c.radial_dof as f64);
        }
        if c.region_pattern() {
            warnings.push(format!(
                "{} camera: the residuals differ by image region (chi-square {:.0} for {} degrees of freedom, 99.9 % limit {:.0}): part of the image does not fit the model",
                c.camera,
                c.region_chi2,
                c.region_dof,
                chi2_quantile_999(c.region_dof)
            ));
            worst_ratio = worst_ratio.max(c.region_chi2 / c.region_dof as f64);
        }
        if c.rms_growth > RMS_GROWTH_WARN {
            warnings.push(format!(
                "{} camera: the residuals grow towards the image border ({:.1} times the centre's RMS): the lens model or the tracking is worse there",
                c.camera, c.rms_growth
            ));
        }
    }
    let sigma_widening = worst_ratio.sqrt();
    if sigma_widening > 1.0 {
        warnings.push(format!(
            "the intrinsics' and lens sigmas are widened {sigma_widening:.2} times for this lack of fit"
        ));
    }
    ResidualStructure { sigma_px: sigma, cameras, sigma_widening, warnings }
}

/// The rings, cells and statistics of one camera.
fn camera_residuals(
    state: &RigState,
    observations: &[BundleObservation],
    side: Side,
    image_size: [u32; 2],
    sigma: f64,
) -> CameraResiduals {
    let k = if side == Side::Left { &state.left } else { &state.right };
    let (w, h) = (f64::from(image_size[0]).max(1.0), f64::from(image_size[1]).max(1.0));
    // (radius, radial component, residual) of each observation of this camera.
    let samples: Vec<(f64, f64, nalgebra::Vector2<f64>, f64, f64)> = observations
        .iter()
        .filter(|o| o.side == side)
        .filter_map(|o| {
            let r = residual_pixels(state, o)?;
            let d = nalgebra::Vector2::new(o.pixel.x - k.cx, o.pixel.y - k.cy);
            let radius = d.norm();
            let radial = if radius > 1e-9 { r.dot(&(d / radius)) } else { 0.0 };
            Some((radius, radial, r, o.pixel.x, o.pixel.y))
        })
        .collect();
    let max_radius = samples.iter().map(|s| s.0).fold(1e-9, f64::max);
    let mut ring_acc = [(0usize, 0.0f64, 0.0f64); RINGS];
    let mut cell_acc = [(0usize, nalgebra::Vector2::<f64>::zeros()); GRID * GRID];
    for &(radius, radial, r, x, y) in &samples {
        let i = ((radius / max_radius * RINGS as f64) as usize).min(RINGS - 1);
        ring_acc[i].0 += 1;
        ring_acc[i].1 += r.norm_squared();
        ring_acc[i].2 += radial;
        let gx = ((x / w * GRID as f64).max(0.0) as usize).min(GRID - 1);
        let gy = ((y / h * GRID as f64).max(0.0) as usize).min(GRID - 1);
        cell_acc[gy * GRID + gx].0 += 1;
        cell_acc[gy * GRID + gx].1 += r;
    }
    let rings: Vec<Ring> = ring_acc
        .iter()
        .enumerate()
        .map(|(i, &(n, ss, sr))| Ring {
            outer_px: max_radius * (i + 1) as f64 / RINGS as f64,
            count: n,
            rms_px: if n > 0 { (ss / (2 * n) as f64).sqrt() } else { 0.0 },
            mean_radial_px: if n > 0 { sr / n as f64 } else { 0.0 },
        })
        .collect();
    let populated: Vec<&Ring> = rings.iter().filter(|r| r.count >= MIN_PER_BIN).collect();
    let radial_chi2 =
        populated.iter().map(|r| r.count as f64 * r.mean_radial_px * r.mean_radial_px).sum::<f64>()
            / (sigma * sigma);
    let cells: Vec<&(usize, nalgebra::Vector2<f64>)> =
        cell_acc.iter().filter(|c| c.0 >= MIN_PER_BIN).collect();
    let region_chi2 = cells.iter().map(|(n, s)| s.norm_squared() / *n as f64).sum::<f64>() / (sigma * sigma);
    let rms_growth = match (populated.first(), populated.last()) {
        (Some(a), Some(b)) if a.rms_px > 0.0 && populated.len() >= 2 => b.rms_px / a.rms_px,
        _ => 1.0,
    };
    let radial_dof = populated.len();
    CameraResiduals {
        camera: if side == Side::Left { "left" } else { "right" }.to_string(),
        rings,
        radial_chi2,
        radial_dof,
        region_chi2,
        region_dof: 2 * cells.len(),
        rms_growth,
    }
}

/// Multiply the sigmas of the intrinsics and lens coefficients (`left.*`, `right.*`) by
/// `f`: `C' = D C D`, `D` the factor on those parameters and 1 elsewhere.
pub(crate) fn widen_intrinsics(cov: &mut headalign_geometry::bundle::Covariance, f: f64) {
    let scale: Vec<f64> = cov
        .names
        .iter()
        .map(|n| if n.starts_with("left.") || n.starts_with("right.") { f } else { 1.0 })
        .collect();
    let m = &mut cov.matrix;
    for i in 0..m.nrows() {
        for j in 0..m.ncols() {
            m[(i, j)] *= scale.get(i).copied().unwrap_or(1.0) * scale.get(j).copied().unwrap_or(1.0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The Wilson-Hilferty quantile against tabulated chi-square 99.9 % points (5 dof:
    /// 20.52, 18 dof: 42.31); the approximation's relative error in this tail is about
    /// 1 % at 5 dof and falls with the degrees of freedom, so 1.5 % is the tolerance.
    #[test]
    fn quantile_matches_the_tables() {
        for (dof, table) in [(5, 20.52), (18, 42.31)] {
            let q = chi2_quantile_999(dof);
            assert!((q / table - 1.0).abs() < 0.015, "{dof}: {q} vs {table}");
        }
    }
}
