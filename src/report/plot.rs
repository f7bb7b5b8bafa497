//! Plots of the errors against position, as SVG text or PNG files.
//!
//! Each chart shows, per approach direction, the mean as a line with a marker at every target,
//! over a translucent ±2s band; a grey line marks zero. Axis labels carry the unit (mm; µm or
//! arcsec), the title the error's name. Comparisons draw the "before" set dashed with hollow
//! markers under the "after" set. Colours: ↑ blue, ↓ red.
//!
//! Text is laid out with the built-in DejaVu Sans, registered with plotters' `ab_glyph` font
//! table as "sans-serif" on first use; the SVG names the family "sans-serif", so a viewer
//! renders it with its own sans-serif font.

use super::text::arrow;
use super::{Comparison, Dof, DofResult, ReportError, Series, validate_series};
use crate::run::Direction;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::{FontStyle, register_font};
use std::ops::Range;
use std::path::Path;
use std::sync::OnceLock;

/// Size (px) of a one-error chart and of a comparison.
pub const CHART_SIZE: (u32, u32) = (1000, 560);
/// Size (px) of the six-error sheet (3 × 2 charts).
pub const SIX_SIZE: (u32, u32) = (1500, 1000);

const FONT: &[u8] = include_bytes!("fonts/DejaVuSans.ttf");
const FAMILY: &str = "sans-serif";

const UP: RGBColor = RGBColor(31, 119, 180);
const DOWN: RGBColor = RGBColor(214, 39, 40);
const UP_BEFORE: RGBColor = RGBColor(120, 160, 200);
const DOWN_BEFORE: RGBColor = RGBColor(220, 130, 120);
const ZERO_LINE: RGBColor = RGBColor(150, 150, 150);

/// Register the font once; every drawing calls this first.
fn font() -> Result<(), ReportError> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| register_font(FAMILY, FontStyle::Normal, FONT).is_ok());
    if ok { Ok(()) } else { Err(ReportError::Font) }
}

/// Font sizes and margins of one chart.
#[derive(Clone, Copy)]
struct Look {
    caption: u32,
    label: u32,
    desc: u32,
    margin: u32,
    x_area: u32,
    y_area: u32,
    marker: u32,
}

const LARGE: Look = Look {
    caption: 26,
    label: 15,
    desc: 17,
    margin: 14,
    x_area: 48,
    y_area: 72,
    marker: 4,
};

const SMALL: Look = Look {
    caption: 20,
    label: 13,
    desc: 14,
    margin: 10,
    x_area: 42,
    y_area: 64,
    marker: 3,
};

/// One line on a chart.
struct Line<'a> {
    series: &'a Series,
    color: RGBColor,
    label: String,
    /// Dashed line, hollow markers, fainter band: the "before" of a comparison.
    before: bool,
}

/// One chart.
struct Chart<'a> {
    dof: Dof,
    title: String,
    lines: Vec<Line<'a>>,
}

fn color(d: Direction, before: bool) -> RGBColor {
    match (d, before) {
        (Direction::Up, false) => UP,
        (Direction::Down, false) => DOWN,
        (Direction::Up, true) => UP_BEFORE,
        (Direction::Down, true) => DOWN_BEFORE,
    }
}

fn result_chart(r: &DofResult) -> Chart<'_> {
    Chart {
        dof: r.dof,
        title: r.dof.title(),
        lines: r
            .series
            .iter()
            .map(|s| Line {
                series: s,
                color: color(s.direction, false),
                label: format!("{} mean ±2s", arrow(s.direction)),
                before: false,
            })
            .collect(),
    }
}

fn comparison_chart(c: &Comparison) -> Chart<'_> {
    let mut lines = Vec::new();
    for (label, list, before) in [
        (&c.before_label, &c.before, true),
        (&c.after_label, &c.after, false),
    ] {
        for s in list {
            lines.push(Line {
                series: s,
                color: color(s.direction, before),
                label: format!("{label} {}", arrow(s.direction)),
                before,
            });
        }
    }
    Chart {
        dof: c.dof,
        title: format!("{}: {} vs {}", c.dof.title(), c.before_label, c.after_label),
        lines,
    }
}

/// A series' points in user units, sorted by position: (x mm, mean, s).
fn points(dof: Dof, s: &Series) -> Vec<(f64, f64, f64)> {
    let mut p: Vec<(f64, f64, f64)> = (0..s.positions_mm.len())
        .map(|i| {
            (
                s.positions_mm[i],
                dof.to_user(s.mean[i]),
                dof.to_user(s.s[i]).abs(),
            )
        })
        .collect();
    p.sort_by(|a, b| a.0.total_cmp(&b.0));
    p
}

/// Axis ranges covering every band and zero, with a margin.
fn ranges(chart: &Chart<'_>) -> (Range<f64>, Range<f64>) {
    let (mut x0, mut x1) = (f64::INFINITY, f64::NEG_INFINITY);
    let (mut y0, mut y1) = (0.0_f64, 0.0_f64);
    for line in &chart.lines {
        for (x, m, s) in points(chart.dof, line.series) {
            x0 = x0.min(x);
            x1 = x1.max(x);
            y0 = y0.min(m - 2.0 * s);
            y1 = y1.max(m + 2.0 * s);
        }
    }
    if x0 > x1 {
        (x0, x1) = (0.0, 1.0);
    }
    if x1 - x0 < 1e-9 {
        (x0, x1) = (x0 - 1.0, x1 + 1.0);
    }
    if y1 - y0 < 1e-9 {
        (y0, y1) = (y0 - 1.0, y1 + 1.0);
    }
    let (dx, dy) = (0.02 * (x1 - x0), 0.08 * (y1 - y0));
    (x0 - dx..x1 + dx, y0 - dy..y1 + dy)
}

fn fail(what: &str) -> impl Fn(String) -> ReportError + '_ {
    move |detail| ReportError::Plot {
        what: what.to_string(),
        detail,
    }
}

fn text<E: std::fmt::Display>(e: E) -> String {
    e.to_string()
}

/// Draw one chart into `area`.
fn draw_chart<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    chart: &Chart<'_>,
    look: Look,
) -> Result<(), String> {
    let (xr, yr) = ranges(chart);
    let span = xr.end - xr.start;
    let x_decimals = if span >= 20.0 {
        0
    } else if span >= 2.0 {
        1
    } else {
        2
    };
    let x_format = move |x: &f64| super::text::fixed(*x, x_decimals);
    let mut ctx = ChartBuilder::on(area)
        .caption(&chart.title, (FAMILY, look.caption))
        .margin(look.margin)
        .x_label_area_size(look.x_area)
        .y_label_area_size(look.y_area)
        .build_cartesian_2d(xr.clone(), yr.clone())
        .map_err(text)?;
    ctx.configure_mesh()
        .x_desc("position (mm)")
        .y_desc(format!("{} ({})", chart.dof.name(), chart.dof.unit()))
        .x_labels(10)
        .y_labels(8)
        .x_label_formatter(&x_format)
        .max_light_lines(2)
        .label_style((FAMILY, look.label))
        .axis_desc_style((FAMILY, look.desc))
        .bold_line_style(RGBColor(215, 215, 215))
        .light_line_style(RGBColor(240, 240, 240))
        .draw()
        .map_err(text)?;
    if yr.start < 0.0 && yr.end > 0.0 {
        ctx.draw_series(LineSeries::new(
            [(xr.start, 0.0), (xr.end, 0.0)],
            ZERO_LINE.stroke_width(1),
        ))
        .map_err(text)?;
    }
    if chart.lines.is_empty() {
        let centre = ((xr.start + xr.end) / 2.0, (yr.start + yr.end) / 2.0);
        let style = TextStyle::from((FAMILY, look.caption).into_font()).pos(
            plotters::style::text_anchor::Pos::new(
                plotters::style::text_anchor::HPos::Center,
                plotters::style::text_anchor::VPos::Center,
            ),
        );
        ctx.plotting_area()
            .draw(&Text::new("no data", centre, style))
            .map_err(text)?;
        return Ok(());
    }
    for line in &chart.lines {
        let pts = points(chart.dof, line.series);
        let band: Vec<(f64, f64)> = pts
            .iter()
            .map(|&(x, m, s)| (x, m + 2.0 * s))
            .chain(pts.iter().rev().map(|&(x, m, s)| (x, m - 2.0 * s)))
            .collect();
        let alpha = if line.before { 0.10 } else { 0.20 };
        ctx.draw_series(std::iter::once(Polygon::new(
            band,
            line.color.mix(alpha).filled(),
        )))
        .map_err(text)?;
        let style = line.color.stroke_width(2);
        let means = pts.iter().map(|&(x, m, _)| (x, m));
        let anno = if line.before {
            ctx.draw_series(DashedLineSeries::new(means, 10, 6, style))
        } else {
            ctx.draw_series(LineSeries::new(means, style))
        }
        .map_err(text)?;
        anno.label(line.label.as_str())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 24, y)], style));
        let marker = if line.before {
            line.color.stroke_width(1)
        } else {
            line.color.filled()
        };
        ctx.draw_series(
            pts.iter()
                .map(|&(x, m, _)| Circle::new((x, m), look.marker, marker)),
        )
        .map_err(text)?;
    }
    ctx.configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .label_font((FAMILY, look.label))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK.mix(0.4))
        .draw()
        .map_err(text)?;
    Ok(())
}

/// Draw the six-error sheet: dx dy dz on top, ex ey ez below; a missing error says "no data".
fn draw_six<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    results: &[DofResult],
    title: &str,
) -> Result<(), String> {
    let body = root
        .margin(10, 0, 0, 0)
        .titled(title, (FAMILY, 30))
        .map_err(text)?;
    for (cell, dof) in body.split_evenly((2, 3)).iter().zip(Dof::ALL) {
        let chart = match results.iter().find(|r| r.dof == dof) {
            Some(r) => result_chart(r),
            None => Chart {
                dof,
                title: dof.title(),
                lines: Vec::new(),
            },
        };
        draw_chart(cell, &chart, SMALL)?;
    }
    Ok(())
}

fn svg_of(
    size: (u32, u32),
    draw: impl FnOnce(&DrawingArea<SVGBackend<'_>, Shift>) -> Result<(), String>,
) -> Result<String, String> {
    let mut out = String::new();
    {
        let root = SVGBackend::with_string(&mut out, size).into_drawing_area();
        root.fill(&WHITE).map_err(text)?;
        draw(&root)?;
        root.present().map_err(text)?;
    }
    Ok(out)
}

fn png_to(
    path: &Path,
    size: (u32, u32),
    draw: impl FnOnce(&DrawingArea<BitMapBackend<'_>, Shift>) -> Result<(), String>,
) -> Result<(), String> {
    let root = BitMapBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE).map_err(text)?;
    draw(&root)?;
    root.present().map_err(text)
}

/// One error against position, as SVG text (`CHART_SIZE`).
pub fn dof_svg(r: &DofResult) -> Result<String, ReportError> {
    font()?;
    validate_series(r.dof, &r.series)?;
    let chart = result_chart(r);
    svg_of(CHART_SIZE, |a| draw_chart(a, &chart, LARGE)).map_err(fail(r.dof.name()))
}

/// One error against position, as a PNG file (`CHART_SIZE`).
pub fn dof_png(r: &DofResult, path: &Path) -> Result<(), ReportError> {
    font()?;
    validate_series(r.dof, &r.series)?;
    let chart = result_chart(r);
    let label = path.display().to_string();
    png_to(path, CHART_SIZE, |a| draw_chart(a, &chart, LARGE)).map_err(fail(&label))
}

/// The six errors of a run on one sheet, as SVG text (`SIX_SIZE`).
pub fn six_svg(results: &[DofResult], title: &str) -> Result<String, ReportError> {
    font()?;
    for r in results {
        validate_series(r.dof, &r.series)?;
    }
    svg_of(SIX_SIZE, |a| draw_six(a, results, title)).map_err(fail("six errors"))
}

/// The six errors of a run on one sheet, as a PNG file (`SIX_SIZE`).
pub fn six_png(results: &[DofResult], title: &str, path: &Path) -> Result<(), ReportError> {
    font()?;
    for r in results {
        validate_series(r.dof, &r.series)?;
    }
    let label = path.display().to_string();
    png_to(path, SIX_SIZE, |a| draw_six(a, results, title)).map_err(fail(&label))
}

/// A before/after comparison of one error, as SVG text (`CHART_SIZE`).
pub fn comparison_svg(c: &Comparison) -> Result<String, ReportError> {
    font()?;
    validate_series(c.dof, &c.before)?;
    validate_series(c.dof, &c.after)?;
    let chart = comparison_chart(c);
    svg_of(CHART_SIZE, |a| draw_chart(a, &chart, LARGE)).map_err(fail(c.dof.name()))
}

/// A before/after comparison of one error, as a PNG file (`CHART_SIZE`).
pub fn comparison_png(c: &Comparison, path: &Path) -> Result<(), ReportError> {
    font()?;
    validate_series(c.dof, &c.before)?;
    validate_series(c.dof, &c.after)?;
    let chart = comparison_chart(c);
    let label = path.display().to_string();
    png_to(path, CHART_SIZE, |a| draw_chart(a, &chart, LARGE)).map_err(fail(&label))
}
