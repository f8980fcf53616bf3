//! PNG and SVG line plots of an experiment: RMS error against the swept parameter, one
//! solid line with circles per series, and its Cramer-Rao bound as a thin line with
//! triangles in the same colour.
//!
//! Both files come from one drawing routine over plotters' bitmap and SVG backends
//! (800 x 500 px). The bitmap backend draws text with a TrueType font from the machine's
//! fontconfig (DejaVu Sans here); the SVG backend writes text elements and needs no font.

use std::path::Path;

use anyhow::{Result, anyhow};
use plotters::coord::Shift;
use plotters::prelude::*;

/// One curve: label, points `(x, y)` (non-finite y skipped), and whether it is a bound.
pub struct Curve {
    /// Legend label.
    pub label: String,
    /// Points.
    pub points: Vec<(f64, f64)>,
    /// Colour index (a series and its bound share one).
    pub colour: usize,
    /// Draw as a bound (thin, triangles).
    pub bound: bool,
}

const SIZE: (u32, u32) = (800, 500);

/// Write `stem.png` and `stem.svg`.
pub fn write_plots(stem: &Path, title: &str, x_label: &str, y_label: &str, curves: &[Curve]) -> Result<()> {
    let png = stem.with_extension("png");
    let svg = stem.with_extension("svg");
    {
        let root = BitMapBackend::new(&png, SIZE).into_drawing_area();
        draw(&root, title, x_label, y_label, curves)?;
        root.present().map_err(|e| anyhow!("{}: {e}", png.display()))?;
    }
    {
        let root = SVGBackend::new(&svg, SIZE).into_drawing_area();
        draw(&root, title, x_label, y_label, curves)?;
        root.present().map_err(|e| anyhow!("{}: {e}", svg.display()))?;
    }
    Ok(())
}

fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    x_label: &str,
    y_label: &str,
    curves: &[Curve],
) -> Result<()> {
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| anyhow!("plot '{title}': {e}");
    root.fill(&WHITE).map_err(err)?;
    let finite =
        || curves.iter().flat_map(|c| c.points.iter()).filter(|p| p.0.is_finite() && p.1.is_finite());
    let (mut x0, mut x1, mut y1) = (f64::INFINITY, f64::NEG_INFINITY, 0.0f64);
    for &(x, y) in finite() {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y1 = y1.max(y);
    }
    if !x0.is_finite() {
        (x0, x1) = (0.0, 1.0);
    } else if x1 <= x0 {
        x1 = x0 + 1.0;
    }
    let y1 = if y1 > 0.0 { 1.1 * y1 } else { 1.0 };
    let pad = 0.03 * (x1 - x0);
    let mut chart = ChartBuilder::on(root)
        .caption(title, ("sans-serif", 20))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d((x0 - pad)..(x1 + pad), 0.0..y1)
        .map_err(err)?;
    chart.configure_mesh().x_desc(x_label).y_desc(y_label).light_line_style(WHITE).draw().map_err(err)?;
    for c in curves {
        let colour = Palette99::pick(c.colour).to_rgba();
        let pts: Vec<(f64, f64)> =
            c.points.iter().copied().filter(|p| p.0.is_finite() && p.1.is_finite()).collect();
        let width = if c.bound { 1 } else { 2 };
        chart
            .draw_series(LineSeries::new(pts.clone(), colour.stroke_width(width)))
            .map_err(err)?
            .label(c.label.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(width)));
        if c.bound {
            chart
                .draw_series(pts.iter().map(|&p| TriangleMarker::new(p, 4, colour.filled())))
                .map_err(err)?;
        } else {
            chart.draw_series(pts.iter().map(|&p| Circle::new(p, 3, colour.filled()))).map_err(err)?;
        }
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(err)?;
    Ok(())
}
