//! A chart drawn in a box (origin top-left, y down, points) on a `Canvas`: the PDF page
//! (`layout`), an SVG document (the HTML and Markdown reports, the run report's charts) or a
//! raster (`raster`, their PNGs), from one piece of code: every chart the product draws goes
//! through here. Title above, the plot area with ticks and axis labels, translucent bands
//! under the lines, markers on them (hollow on a dashed line, a "before"), and the legend
//! **below** the plot area so it never covers data.

use super::doc::{Chart, ChartBand, colour};
use super::pdf::{Font, text_width};
use std::fmt::Write as _;

/// Where a text's x is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Anchor {
    Start,
    Middle,
    End,
}

/// The radius of a marker (points).
pub const MARKER_R: f64 = 1.8;

/// Where a chart is drawn: the PDF page, an SVG document or a raster. Coordinates are the chart box's
/// (origin top-left, y down, points).
pub trait Canvas {
    /// An open polyline.
    fn line(&mut self, pts: &[(f64, f64)], rgb: (u8, u8, u8), width: f64, dashed: bool);
    /// A small circle centred at (x, y), filled or `hollow` (its outline).
    fn marker(&mut self, x: f64, y: f64, rgb: (u8, u8, u8), hollow: bool);
    /// A closed polygon filled at `opacity` (0 to 1), not stroked.
    fn band(&mut self, pts: &[(f64, f64)], rgb: (u8, u8, u8), opacity: f64);
    /// Text with its baseline at y; `up` turns it to read upwards.
    fn text(&mut self, at: (f64, f64), text: &str, style: TextStyle);
}

/// How a chart's text is set.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TextStyle {
    pub size: f64,
    pub bold: bool,
    pub anchor: Anchor,
    pub up: bool,
}

impl TextStyle {
    /// The embedded font it is set in.
    pub fn font(&self) -> Font {
        if self.bold { Font::Bold } else { Font::Regular }
    }

    /// How far `text` starts before its anchor (points), as the font's shaping measures it.
    pub fn anchor_shift(&self, text: &str) -> f64 {
        match self.anchor {
            Anchor::Start => 0.0,
            Anchor::Middle => text_width(text, self.font(), self.size) / 2.0,
            Anchor::End => text_width(text, self.font(), self.size),
        }
    }

    fn plain(size: f64, anchor: Anchor) -> TextStyle {
        TextStyle {
            size,
            bold: false,
            anchor,
            up: false,
        }
    }
}

const TICK_SIZE: f64 = 7.0;
const TITLE_SIZE: f64 = 9.0;
const LEGEND_SIZE: f64 = 7.5;
const GRID: (u8, u8, u8) = (220, 220, 220);
const AXIS: (u8, u8, u8) = (60, 60, 60);

/// Tick values for [lo, hi]: about `want` steps of 1, 2 or 5 × 10^k.
pub fn ticks(lo: f64, hi: f64, want: usize) -> Vec<f64> {
    let span = (hi - lo).abs().max(1e-12);
    let raw = span / want.max(1) as f64;
    let mag = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * mag)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * mag);
    let first = (lo / step).ceil() as i64;
    let last = (hi / step).floor() as i64;
    (first..=last).map(|i| i as f64 * step).collect()
}

/// Decimals that show a tick step exactly.
fn tick_decimals(ticks: &[f64]) -> usize {
    let step = match ticks {
        [a, b, ..] => (b - a).abs(),
        _ => 1.0,
    };
    if step >= 1.0 {
        0
    } else {
        (-step.log10().floor()) as usize
    }
}

fn tick_label(v: f64, decimals: usize) -> String {
    super::text::fixed(v, decimals).replace('-', "−")
}

/// The data range with a margin; a flat line gets ±1 around it.
fn range(vals: impl Iterator<Item = f64>) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in vals.filter(|v| v.is_finite()) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    if hi - lo < 1e-9 {
        return (lo - 1.0, hi + 1.0);
    }
    let pad = (hi - lo) * 0.06;
    (lo - pad, hi + pad)
}

/// Legend rows: each entry's text placed left to right, wrapping at `width`.
fn legend_rows(chart: &Chart, width: f64) -> Vec<Vec<(usize, f64)>> {
    let mut rows: Vec<Vec<(usize, f64)>> = vec![Vec::new()];
    let mut x = 0.0;
    for (i, l) in chart.lines.iter().enumerate() {
        if l.label.is_empty() {
            continue;
        }
        let w = 22.0 + text_width(&l.label, Font::Regular, LEGEND_SIZE) + 14.0;
        if x > 0.0 && x + w > width {
            rows.push(Vec::new());
            x = 0.0;
        }
        if let Some(r) = rows.last_mut() {
            r.push((i, x));
        }
        x += w;
    }
    rows
}

/// The height a chart of width `w` needs with a plot area `plot_h` high.
pub fn height(chart: &Chart, w: f64, plot_h: f64) -> f64 {
    16.0 + plot_h + 30.0 + 12.0 * legend_rows(chart, w - 50.0).len() as f64
}

/// Draw `chart` on `c`, in a box `w` wide whose plot area is `plot_h` high.
pub fn draw(chart: &Chart, w: f64, plot_h: f64, c: &mut impl Canvas) {
    c.text(
        (0.0, 10.0),
        &chart.title,
        TextStyle {
            bold: true,
            ..TextStyle::plain(TITLE_SIZE, Anchor::Start)
        },
    );
    let (left, top) = (50.0, 16.0);
    let (pw, ph) = (w - left - 8.0, plot_h);
    let band_xs = chart
        .bands
        .iter()
        .flat_map(|b| b.points.iter().map(|p| p.0));
    let band_ys = chart
        .bands
        .iter()
        .flat_map(|b| b.points.iter().flat_map(|p| [p.1, p.2]));
    let (x0, x1) = range(
        chart
            .lines
            .iter()
            .flat_map(|l| l.points.iter().map(|p| p.0))
            .chain(band_xs),
    );
    let (y0, y1) = range(
        chart
            .lines
            .iter()
            .flat_map(|l| l.points.iter().map(|p| p.1))
            .chain(band_ys),
    );
    let sx = |x: f64| left + (x - x0) / (x1 - x0) * pw;
    let sy = |y: f64| top + ph - (y - y0) / (y1 - y0) * ph;

    let xt = ticks(x0, x1, 8);
    let yt = ticks(y0, y1, 6);
    let (xd, yd) = (tick_decimals(&xt), tick_decimals(&yt));
    for &t in &yt {
        let y = sy(t);
        c.line(&[(left, y), (left + pw, y)], GRID, 0.4, false);
        c.text(
            (left - 3.0, y + 2.5),
            &tick_label(t, yd),
            TextStyle::plain(TICK_SIZE, Anchor::End),
        );
    }
    for &t in &xt {
        let x = sx(t);
        c.line(&[(x, top), (x, top + ph)], GRID, 0.4, false);
        c.text(
            (x, top + ph + 9.0),
            &tick_label(t, xd),
            TextStyle::plain(TICK_SIZE, Anchor::Middle),
        );
    }
    if y0 < 0.0 && y1 > 0.0 {
        c.line(
            &[(left, sy(0.0)), (left + pw, sy(0.0))],
            (150, 150, 150),
            0.6,
            false,
        );
    }
    c.line(
        &[
            (left, top),
            (left + pw, top),
            (left + pw, top + ph),
            (left, top + ph),
            (left, top),
        ],
        AXIS,
        0.6,
        false,
    );
    c.text(
        (left + pw / 2.0, top + ph + 20.0),
        &chart.x_label,
        TextStyle::plain(TICK_SIZE, Anchor::Middle),
    );
    c.text(
        (10.0, top + ph / 2.0),
        &chart.y_label,
        TextStyle {
            up: true,
            ..TextStyle::plain(TICK_SIZE, Anchor::Middle)
        },
    );

    if chart.lines.is_empty() && chart.bands.is_empty() {
        c.text(
            (left + pw / 2.0, top + ph / 2.0),
            "no data",
            TextStyle::plain(TITLE_SIZE, Anchor::Middle),
        );
    }
    for b in &chart.bands {
        c.band(&band_outline(b, sx, sy), colour(b.colour), b.opacity);
    }
    for l in &chart.lines {
        let rgb = colour(l.colour);
        let pts: Vec<(f64, f64)> = l.points.iter().map(|&(x, y)| (sx(x), sy(y))).collect();
        c.line(&pts, rgb, 1.1, l.dashed);
        if l.markers {
            for &(x, y) in &pts {
                c.marker(x, y, rgb, l.dashed);
            }
        }
    }

    let mut y = top + ph + 32.0;
    for row in legend_rows(chart, pw) {
        for (i, x) in row {
            let l = &chart.lines[i];
            let rgb = colour(l.colour);
            let lx = left + x;
            c.line(&[(lx, y - 2.5), (lx + 18.0, y - 2.5)], rgb, 1.1, l.dashed);
            if l.markers {
                c.marker(lx + 9.0, y - 2.5, rgb, l.dashed);
            }
            c.text(
                (lx + 22.0, y),
                &l.label,
                TextStyle::plain(LEGEND_SIZE, Anchor::Start),
            );
        }
        y += 12.0;
    }
}

/// A band's outline in the box: along its tops, back along its bottoms.
fn band_outline(
    b: &ChartBand,
    sx: impl Fn(f64) -> f64,
    sy: impl Fn(f64) -> f64,
) -> Vec<(f64, f64)> {
    b.points
        .iter()
        .map(|&(x, _, hi)| (sx(x), sy(hi)))
        .chain(b.points.iter().rev().map(|&(x, lo, _)| (sx(x), sy(lo))))
        .collect()
}

/// A canvas drawn on with its origin moved to `at` of another's.
struct Shifted<'a, C: Canvas> {
    inner: &'a mut C,
    at: (f64, f64),
}

impl<C: Canvas> Canvas for Shifted<'_, C> {
    fn line(&mut self, pts: &[(f64, f64)], rgb: (u8, u8, u8), width: f64, dashed: bool) {
        let moved: Vec<(f64, f64)> = pts.iter().map(|&p| self.moved(p)).collect();
        self.inner.line(&moved, rgb, width, dashed);
    }
    fn marker(&mut self, x: f64, y: f64, rgb: (u8, u8, u8), hollow: bool) {
        let (x, y) = self.moved((x, y));
        self.inner.marker(x, y, rgb, hollow);
    }
    fn band(&mut self, pts: &[(f64, f64)], rgb: (u8, u8, u8), opacity: f64) {
        let moved: Vec<(f64, f64)> = pts.iter().map(|&p| self.moved(p)).collect();
        self.inner.band(&moved, rgb, opacity);
    }
    fn text(&mut self, at: (f64, f64), text: &str, style: TextStyle) {
        let at = self.moved(at);
        self.inner.text(at, text, style);
    }
}

impl<C: Canvas> Shifted<'_, C> {
    fn moved(&self, (x, y): (f64, f64)) -> (f64, f64) {
        (x + self.at.0, y + self.at.1)
    }
}

/// A sheet of charts under a title, `cols` to a row, each `w` wide with a plot area `plot_h`
/// high: its size (points).
pub fn sheet_size(charts: &[Chart], cols: usize, w: f64, plot_h: f64) -> (f64, f64) {
    let cols = cols.max(1);
    (
        cols as f64 * (w + SHEET_GAP) + SHEET_GAP,
        SHEET_TITLE_H
            + row_heights(charts, cols, w, plot_h)
                .map(|h| h + SHEET_GAP)
                .sum::<f64>(),
    )
}

/// Each row's height on a sheet: its tallest chart's.
fn row_heights(
    charts: &[Chart],
    cols: usize,
    w: f64,
    plot_h: f64,
) -> impl Iterator<Item = f64> + '_ {
    charts
        .chunks(cols.max(1))
        .map(move |row| row.iter().map(|c| height(c, w, plot_h)).fold(0.0, f64::max))
}

const SHEET_GAP: f64 = 10.0;
const SHEET_TITLE_H: f64 = 26.0;

/// Draw the sheet ([`sheet_size`]) on `c`.
pub fn draw_sheet(
    title: &str,
    charts: &[Chart],
    cols: usize,
    w: f64,
    plot_h: f64,
    c: &mut impl Canvas,
) {
    let cols = cols.max(1);
    c.text(
        (SHEET_GAP, 17.0),
        title,
        TextStyle {
            bold: true,
            ..TextStyle::plain(12.0, Anchor::Start)
        },
    );
    let mut y = SHEET_TITLE_H;
    for (row, h) in charts
        .chunks(cols)
        .zip(row_heights(charts, cols, w, plot_h))
    {
        let mut x = SHEET_GAP;
        for chart in row {
            draw(
                chart,
                w,
                plot_h,
                &mut Shifted {
                    inner: c,
                    at: (x, y),
                },
            );
            x += w + SHEET_GAP;
        }
        y += h + SHEET_GAP;
    }
}

/// An SVG document being drawn.
struct Svg(String);

fn hex((r, g, b): (u8, u8, u8)) -> String {
    format!("#{r:02x}{g:02x}{b:02x}")
}

impl Canvas for Svg {
    fn line(&mut self, pts: &[(f64, f64)], rgb: (u8, u8, u8), width: f64, dashed: bool) {
        let d: Vec<String> = pts.iter().map(|(x, y)| format!("{x:.1},{y:.1}")).collect();
        let _ = writeln!(
            self.0,
            "<polyline points=\"{}\" fill=\"none\" stroke=\"{}\" stroke-width=\"{width}\"{}/>",
            d.join(" "),
            hex(rgb),
            if dashed {
                " stroke-dasharray=\"3 2\""
            } else {
                ""
            }
        );
    }
    fn marker(&mut self, x: f64, y: f64, rgb: (u8, u8, u8), hollow: bool) {
        let paint = if hollow {
            format!("fill=\"none\" stroke=\"{}\" stroke-width=\"0.8\"", hex(rgb))
        } else {
            format!("fill=\"{}\"", hex(rgb))
        };
        let _ = writeln!(
            self.0,
            "<circle cx=\"{x:.1}\" cy=\"{y:.1}\" r=\"{MARKER_R}\" {paint}/>"
        );
    }
    fn band(&mut self, pts: &[(f64, f64)], rgb: (u8, u8, u8), opacity: f64) {
        let d: Vec<String> = pts.iter().map(|(x, y)| format!("{x:.1},{y:.1}")).collect();
        let _ = writeln!(
            self.0,
            "<polygon points=\"{}\" fill=\"{}\" fill-opacity=\"{opacity:.2}\" stroke=\"none\"/>",
            d.join(" "),
            hex(rgb)
        );
    }
    fn text(&mut self, (x, y): (f64, f64), text: &str, st: TextStyle) {
        let a = match st.anchor {
            Anchor::Start => "start",
            Anchor::Middle => "middle",
            Anchor::End => "end",
        };
        let rot = if st.up {
            format!(" transform=\"rotate(-90 {x:.1} {y:.1})\"")
        } else {
            String::new()
        };
        let _ = writeln!(
            self.0,
            "<text x=\"{x:.1}\" y=\"{y:.1}\" font-size=\"{}\" text-anchor=\"{a}\"{}{rot}>{}</text>",
            st.size,
            if st.bold { " font-weight=\"bold\"" } else { "" },
            super::text::html(text)
        );
    }
}

/// A standalone chart's size (points): the chart `w` wide with a plot area `plot_h` high, and
/// a margin round it.
pub fn standalone_size(chart: &Chart, w: f64, plot_h: f64) -> (f64, f64) {
    (
        w + 2.0 * SHEET_GAP,
        height(chart, w, plot_h) + 2.0 * SHEET_GAP,
    )
}

/// Draw a standalone chart ([`standalone_size`]) on `c`.
pub fn draw_standalone(chart: &Chart, w: f64, plot_h: f64, c: &mut impl Canvas) {
    let at = (SHEET_GAP, SHEET_GAP);
    draw(chart, w, plot_h, &mut Shifted { inner: c, at });
}

/// The chart as a standalone SVG document ([`standalone_size`]).
pub fn svg(chart: &Chart, w: f64, plot_h: f64) -> String {
    let (sw, sh) = standalone_size(chart, w, plot_h);
    let mut s = Svg::open(sw, sh);
    draw_standalone(chart, w, plot_h, &mut s);
    s.close()
}

/// The sheet ([`draw_sheet`]) as a standalone SVG document.
pub fn sheet_svg(title: &str, charts: &[Chart], cols: usize, w: f64, plot_h: f64) -> String {
    let (sw, sh) = sheet_size(charts, cols, w, plot_h);
    let mut s = Svg::open(sw, sh);
    draw_sheet(title, charts, cols, w, plot_h, &mut s);
    s.close()
}

impl Svg {
    /// A document `w` × `h` points on white, its text in the family the PDF embeds (a viewer
    /// without DejaVu Sans falls back to its own sans-serif).
    fn open(w: f64, h: f64) -> Svg {
        Svg(format!(
            "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w:.0}\" height=\"{h:.0}\" \
             viewBox=\"0 0 {w:.0} {h:.0}\" font-family=\"DejaVu Sans, sans-serif\">\n\
             <rect width=\"100%\" height=\"100%\" fill=\"#ffffff\"/>\n"
        ))
    }

    fn close(mut self) -> String {
        self.0.push_str("</svg>\n");
        self.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_round() {
        assert_eq!(
            ticks(0.0, 1000.0, 8),
            vec![0.0, 200.0, 400.0, 600.0, 800.0, 1000.0]
        );
        let t = ticks(-0.13, 0.22, 6);
        assert_eq!(t, vec![-0.1, 0.0, 0.1, 0.2]);
        assert_eq!(tick_decimals(&t), 1);
        assert_eq!(tick_decimals(&ticks(-1.3, 2.2, 6)), 0);
    }
}
