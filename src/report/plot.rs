//! The run report's charts of the errors against position, as SVG text or PNG files, drawn by
//! the one chart code the PDF uses too (`chart`; PNG through `raster`).
//!
//! Each chart shows, per approach direction, the mean as a line with a marker at every target,
//! over a translucent ±2s band. Axis labels carry the unit (mm; µm or arcsec), the title the
//! error's name. Comparisons draw the "before" set dashed with hollow markers and a fainter
//! band under the "after" set. Colours: ↑ blue, ↓ red.

use super::chart;
use super::doc::{Chart, ChartBand, ChartLine};
use super::raster::Raster;
use super::text::arrow;
use super::{Comparison, Dof, DofResult, ReportError, Series, validate_series};
use crate::run::Direction;
use std::path::Path;

/// A one-error chart and a comparison: width and plot-area height (points).
const ONE: (f64, f64) = (500.0, 230.0);
/// The six-error sheet: three to a row, each this wide with this plot area (points).
const SIX: (f64, f64) = (330.0, 150.0);
/// Pixels per point in a PNG.
pub const PNG_SCALE: f64 = 2.0;

/// Palette colours (`doc::PALETTE`) of the two directions.
fn colour(d: Direction) -> usize {
    match d {
        Direction::Up => 0,
        Direction::Down => 3,
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

/// A series' mean line and its ±2s band onto `chart`.
fn add(chart: &mut Chart, dof: Dof, s: &Series, label: String, before: bool) {
    let pts = points(dof, s);
    let colour = colour(s.direction);
    chart.bands.push(ChartBand {
        colour,
        opacity: if before { 0.10 } else { 0.20 },
        points: pts
            .iter()
            .map(|&(x, m, s)| (x, m - 2.0 * s, m + 2.0 * s))
            .collect(),
    });
    chart.lines.push(ChartLine {
        label,
        colour,
        dashed: before,
        markers: true,
        points: pts.iter().map(|&(x, m, _)| (x, m)).collect(),
    });
}

fn empty(dof: Dof, title: String) -> Chart {
    Chart {
        title,
        x_label: "position (mm)".into(),
        y_label: format!("{} ({})", dof.name(), dof.unit()),
        lines: Vec::new(),
        bands: Vec::new(),
        note: String::new(),
    }
}

fn result_chart(r: &DofResult) -> Chart {
    let mut c = empty(r.dof, r.dof.title());
    for s in &r.series {
        add(
            &mut c,
            r.dof,
            s,
            format!("{} mean ±2s", arrow(s.direction)),
            false,
        );
    }
    c
}

fn comparison_chart(c: &Comparison) -> Chart {
    let title = format!("{}: {} vs {}", c.dof.title(), c.before_label, c.after_label);
    let mut chart = empty(c.dof, title);
    for (label, list, before) in [
        (&c.before_label, &c.before, true),
        (&c.after_label, &c.after, false),
    ] {
        for s in list {
            add(
                &mut chart,
                c.dof,
                s,
                format!("{label} {}", arrow(s.direction)),
                before,
            );
        }
    }
    chart
}

/// The six errors' charts in sheet order (dx dy dz, then ex ey ez); a missing one says "no
/// data".
fn six_charts(results: &[DofResult]) -> Vec<Chart> {
    Dof::ALL
        .iter()
        .map(|&dof| match results.iter().find(|r| r.dof == dof) {
            Some(r) => result_chart(r),
            None => empty(dof, dof.title()),
        })
        .collect()
}

/// Draw at `PNG_SCALE` and write the PNG to `path`.
fn write_png(
    path: &Path,
    (w, h): (f64, f64),
    draw: impl FnOnce(&mut Raster),
) -> Result<(), ReportError> {
    let fail = |detail: String| ReportError::Plot {
        what: path.display().to_string(),
        detail,
    };
    let mut r = Raster::new(w, h, PNG_SCALE).map_err(|e| fail(e.to_string()))?;
    draw(&mut r);
    let bytes = r.png().map_err(|e| fail(e.to_string()))?;
    std::fs::write(path, bytes).map_err(|source| ReportError::Write {
        path: path.display().to_string(),
        source,
    })
}

fn one_png(c: &Chart, path: &Path) -> Result<(), ReportError> {
    let size = chart::standalone_size(c, ONE.0, ONE.1);
    write_png(path, size, |r| chart::draw_standalone(c, ONE.0, ONE.1, r))
}

/// One error against position, as SVG text.
pub fn dof_svg(r: &DofResult) -> Result<String, ReportError> {
    validate_series(r.dof, &r.series)?;
    Ok(chart::svg(&result_chart(r), ONE.0, ONE.1))
}

/// One error against position, as a PNG file.
pub fn dof_png(r: &DofResult, path: &Path) -> Result<(), ReportError> {
    validate_series(r.dof, &r.series)?;
    one_png(&result_chart(r), path)
}

/// The six errors of a run on one sheet, as SVG text.
pub fn six_svg(results: &[DofResult], title: &str) -> Result<String, ReportError> {
    for r in results {
        validate_series(r.dof, &r.series)?;
    }
    Ok(chart::sheet_svg(
        title,
        &six_charts(results),
        3,
        SIX.0,
        SIX.1,
    ))
}

/// The six errors of a run on one sheet, as a PNG file.
pub fn six_png(results: &[DofResult], title: &str, path: &Path) -> Result<(), ReportError> {
    for r in results {
        validate_series(r.dof, &r.series)?;
    }
    let charts = six_charts(results);
    let size = chart::sheet_size(&charts, 3, SIX.0, SIX.1);
    write_png(path, size, |r| {
        chart::draw_sheet(title, &charts, 3, SIX.0, SIX.1, r)
    })
}

/// A before/after comparison of one error, as SVG text.
pub fn comparison_svg(c: &Comparison) -> Result<String, ReportError> {
    validate_series(c.dof, &c.before)?;
    validate_series(c.dof, &c.after)?;
    Ok(chart::svg(&comparison_chart(c), ONE.0, ONE.1))
}

/// A before/after comparison of one error, as a PNG file.
pub fn comparison_png(c: &Comparison, path: &Path) -> Result<(), ReportError> {
    validate_series(c.dof, &c.before)?;
    validate_series(c.dof, &c.after)?;
    one_png(&comparison_chart(c), path)
}
