//! PNG and SVG line plots of an experiment: RMS error against the swept parameter, one
//! solid line with circles per series, and its Cramer-Rao bound as a thin dashed line with
//! triangles in the same colour (an efficient estimator's curve lies on its bound, so a
//! solid bound would hide under it). A series whose points coincide with an earlier
//! series' (within [`COINCIDENT_FRACTION`] of the y range at every x; e.g. the right
//! camera's elevation excess, which equals the left camera's elevation error to first
//! order) is drawn dashed too, so that the earlier one stays visible.
//!
//! Both files come from one drawing routine over plotters' bitmap and SVG backends
//! (800 x 500 px). The bitmap backend draws text with a TrueType font from the machine's
//! fontconfig (DejaVu Sans here); the SVG backend writes text elements and needs no font.

use std::path::Path;

use anyhow::{Result, anyhow};
use plotters::coord::Shift;
use plotters::element::DashedPathElement;
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

/// Two series coincide when their points differ by less than this fraction of the plot's
/// y range at every x (0.5 %: under half a line width at 500 px high).
const COINCIDENT_FRACTION: f64 = 0.005;

/// Dash length and gap of a dashed line, in pixels.
const DASH: (i32, i32) = (8, 5);

/// Whether `a` and `b` have the same x values and y values within `tol` everywhere.
fn coincident(a: &[(f64, f64)], b: &[(f64, f64)], tol: f64) -> bool {
    !a.is_empty()
        && a.len() == b.len()
        && a.iter().zip(b).all(|(p, q)| p.0 == q.0 && (p.1 - q.1).abs() <= tol)
}

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
    // The measured curves drawn so far, for the coincidence test.
    let mut drawn: Vec<Vec<(f64, f64)>> = Vec::new();
    for c in curves {
        let colour = Palette99::pick(c.colour).to_rgba();
        let pts: Vec<(f64, f64)> =
            c.points.iter().copied().filter(|p| p.0.is_finite() && p.1.is_finite()).collect();
        let width = if c.bound { 1 } else { 2 };
        let style = colour.stroke_width(width);
        let covers_earlier = drawn.iter().any(|d| coincident(&pts, d, COINCIDENT_FRACTION * y1));
        let dashed = c.bound || covers_earlier;
        let series = if dashed {
            chart.draw_series(DashedLineSeries::new(pts.clone(), DASH.0, DASH.1, style))
        } else {
            chart.draw_series(LineSeries::new(pts.clone(), style))
        };
        series.map_err(err)?.label(c.label.clone()).legend(move |(x, y)| {
            let ends = vec![(x, y), (x + 20, y)];
            if dashed {
                DashedPathElement::new(ends, DASH.0 - 2, DASH.1 - 2, style).into_dyn()
            } else {
                PathElement::new(ends, style).into_dyn()
            }
        });
        if c.bound {
            chart
                .draw_series(pts.iter().map(|&p| TriangleMarker::new(p, 4, colour.filled())))
                .map_err(err)?;
        } else {
            chart.draw_series(pts.iter().map(|&p| Circle::new(p, 3, colour.filled()))).map_err(err)?;
            drawn.push(pts);
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn coincident_needs_equal_x_and_close_y_everywhere() {
        let a = [(0.0, 0.0), (1.0, 0.25), (3.0, 0.762)];
        // The fig5 elevation pair: equal to 3 digits at every noise level.
        let b = [(0.0, 0.0), (1.0, 0.2531), (3.0, 0.7624)];
        assert!(coincident(&a, &b, 0.005 * 0.84));
        // One level apart by more than the tolerance.
        let c = [(0.0, 0.0), (1.0, 0.25), (3.0, 0.74)];
        assert!(!coincident(&a, &c, 0.005 * 0.84));
        // Other x values, other lengths, nothing to compare.
        assert!(!coincident(&a, &[(0.0, 0.0), (2.0, 0.25), (3.0, 0.762)], 1.0));
        assert!(!coincident(&a, &a[..2], 1.0));
        assert!(!coincident(&[], &[], 1.0));
    }

    /// Polylines stroked in colour `colour` of the palette in an SVG written by `draw`.
    fn strokes_in(svg: &str, colour: usize) -> usize {
        let (r, g, b) = Palette99::pick(colour).rgb();
        svg.matches(&format!("<polyline fill=\"none\" opacity=\"1\" stroke=\"#{r:02X}{g:02X}{b:02X}\""))
            .count()
    }

    #[test]
    fn bounds_and_coincident_series_are_dashed() {
        let dir = std::env::temp_dir().join(format!("headalign-plot-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let line = |colour, bound, y: f64| Curve {
            label: format!("curve {colour} {bound}"),
            points: vec![(0.0, 0.0), (1.0, y), (2.0, f64::NAN), (3.0, 3.0 * y)],
            colour,
            bound,
        };
        let svg_of = |curves: &[Curve]| {
            write_plots(&dir.join("p"), "t", "x", "y", curves).unwrap();
            assert!(std::fs::metadata(dir.join("p.png")).unwrap().len() > 1000);
            std::fs::read_to_string(dir.join("p.svg")).unwrap()
        };
        // Apart: series 1 is one solid polyline (and its legend's line).
        let apart = svg_of(&[line(0, false, 0.25), line(1, false, 0.5)]);
        assert_eq!(strokes_in(&apart, 1), 2);
        // On series 0: dashed, many segments.
        let on = svg_of(&[line(0, false, 0.25), line(1, false, 0.2501)]);
        assert!(strokes_in(&on, 1) > 10, "{}", strokes_in(&on, 1));
        // A bound is dashed even where it lies apart from its series.
        let bound = svg_of(&[line(0, false, 0.25), line(1, true, 0.5)]);
        assert!(strokes_in(&bound, 1) > 10, "{}", strokes_in(&bound, 1));
        std::fs::remove_dir_all(&dir).ok();
    }
}
