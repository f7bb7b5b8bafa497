//! A chart's drawing as primitives in a box (origin top-left, y down, points), shared by the
//! PDF layout and the SVG of the HTML report: title above, the plot area with ticks and axis
//! labels, and the legend **below** the plot area so it never covers data.

use super::doc::{Chart, colour};
use super::pdf::{Font, text_width};
use std::fmt::Write as _;

/// Where a text's x is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Anchor {
    Start,
    Middle,
    End,
}

/// One drawing primitive.
#[derive(Clone, Debug, PartialEq)]
pub enum Prim {
    Line {
        pts: Vec<(f64, f64)>,
        rgb: (u8, u8, u8),
        width: f64,
        dashed: bool,
    },
    /// A small filled square centred at (x, y).
    Marker { x: f64, y: f64, rgb: (u8, u8, u8) },
    /// Text with its baseline at y; `up` turns it to read upwards.
    Text {
        x: f64,
        y: f64,
        text: String,
        size: f64,
        bold: bool,
        anchor: Anchor,
        up: bool,
    },
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

/// Draw `chart` into a box `w` wide whose plot area is `plot_h` high.
pub fn draw(chart: &Chart, w: f64, plot_h: f64) -> Vec<Prim> {
    let mut out = Vec::new();
    let text = |x, y, t: &str, size, bold, anchor, up| Prim::Text {
        x,
        y,
        text: t.to_string(),
        size,
        bold,
        anchor,
        up,
    };
    out.push(text(
        0.0,
        10.0,
        &chart.title,
        TITLE_SIZE,
        true,
        Anchor::Start,
        false,
    ));
    let (left, top) = (50.0, 16.0);
    let (pw, ph) = (w - left - 8.0, plot_h);
    let (x0, x1) = range(
        chart
            .lines
            .iter()
            .flat_map(|l| l.points.iter().map(|p| p.0)),
    );
    let (y0, y1) = range(
        chart
            .lines
            .iter()
            .flat_map(|l| l.points.iter().map(|p| p.1)),
    );
    let sx = |x: f64| left + (x - x0) / (x1 - x0) * pw;
    let sy = |y: f64| top + ph - (y - y0) / (y1 - y0) * ph;

    let xt = ticks(x0, x1, 8);
    let yt = ticks(y0, y1, 6);
    let (xd, yd) = (tick_decimals(&xt), tick_decimals(&yt));
    for &t in &yt {
        let y = sy(t);
        out.push(Prim::Line {
            pts: vec![(left, y), (left + pw, y)],
            rgb: GRID,
            width: 0.4,
            dashed: false,
        });
        out.push(text(
            left - 3.0,
            y + 2.5,
            &tick_label(t, yd),
            TICK_SIZE,
            false,
            Anchor::End,
            false,
        ));
    }
    for &t in &xt {
        let x = sx(t);
        out.push(Prim::Line {
            pts: vec![(x, top), (x, top + ph)],
            rgb: GRID,
            width: 0.4,
            dashed: false,
        });
        out.push(text(
            x,
            top + ph + 9.0,
            &tick_label(t, xd),
            TICK_SIZE,
            false,
            Anchor::Middle,
            false,
        ));
    }
    if y0 < 0.0 && y1 > 0.0 {
        out.push(Prim::Line {
            pts: vec![(left, sy(0.0)), (left + pw, sy(0.0))],
            rgb: (150, 150, 150),
            width: 0.6,
            dashed: false,
        });
    }
    out.push(Prim::Line {
        pts: vec![
            (left, top),
            (left + pw, top),
            (left + pw, top + ph),
            (left, top + ph),
            (left, top),
        ],
        rgb: AXIS,
        width: 0.6,
        dashed: false,
    });
    out.push(text(
        left + pw / 2.0,
        top + ph + 20.0,
        &chart.x_label,
        TICK_SIZE,
        false,
        Anchor::Middle,
        false,
    ));
    out.push(text(
        10.0,
        top + ph / 2.0,
        &chart.y_label,
        TICK_SIZE,
        false,
        Anchor::Middle,
        true,
    ));

    for l in &chart.lines {
        let rgb = colour(l.colour);
        out.push(Prim::Line {
            pts: l.points.iter().map(|&(x, y)| (sx(x), sy(y))).collect(),
            rgb,
            width: 1.1,
            dashed: l.dashed,
        });
        if l.markers {
            for &(x, y) in &l.points {
                out.push(Prim::Marker {
                    x: sx(x),
                    y: sy(y),
                    rgb,
                });
            }
        }
    }

    let mut y = top + ph + 32.0;
    for row in legend_rows(chart, pw) {
        for (i, x) in row {
            let l = &chart.lines[i];
            let rgb = colour(l.colour);
            let lx = left + x;
            out.push(Prim::Line {
                pts: vec![(lx, y - 2.5), (lx + 18.0, y - 2.5)],
                rgb,
                width: 1.1,
                dashed: l.dashed,
            });
            if l.markers {
                out.push(Prim::Marker {
                    x: lx + 9.0,
                    y: y - 2.5,
                    rgb,
                });
            }
            out.push(text(
                lx + 22.0,
                y,
                &l.label,
                LEGEND_SIZE,
                false,
                Anchor::Start,
                false,
            ));
        }
        y += 12.0;
    }
    out
}

/// The chart as a standalone SVG document `w` points wide.
pub fn svg(chart: &Chart, w: f64, plot_h: f64) -> String {
    let h = height(chart, w, plot_h);
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w:.0}\" height=\"{h:.0}\" \
         viewBox=\"0 0 {w:.0} {h:.0}\" font-family=\"Helvetica, Arial, sans-serif\">\n"
    );
    let hex = |(r, g, b): (u8, u8, u8)| format!("#{r:02x}{g:02x}{b:02x}");
    for p in draw(chart, w, plot_h) {
        match p {
            Prim::Line {
                pts,
                rgb,
                width,
                dashed,
            } => {
                let d: Vec<String> = pts.iter().map(|(x, y)| format!("{x:.1},{y:.1}")).collect();
                let _ = writeln!(
                    s,
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
            Prim::Marker { x, y, rgb } => {
                let _ = writeln!(
                    s,
                    "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"3\" height=\"3\" fill=\"{}\"/>",
                    x - 1.5,
                    y - 1.5,
                    hex(rgb)
                );
            }
            Prim::Text {
                x,
                y,
                text,
                size,
                bold,
                anchor,
                up,
            } => {
                let a = match anchor {
                    Anchor::Start => "start",
                    Anchor::Middle => "middle",
                    Anchor::End => "end",
                };
                let rot = if up {
                    format!(" transform=\"rotate(-90 {x:.1} {y:.1})\"")
                } else {
                    String::new()
                };
                let _ = writeln!(
                    s,
                    "<text x=\"{x:.1}\" y=\"{y:.1}\" font-size=\"{size}\" text-anchor=\"{a}\"{}{rot}>{}</text>",
                    if bold { " font-weight=\"bold\"" } else { "" },
                    super::text::html(&text)
                );
            }
        }
    }
    s.push_str("</svg>\n");
    s
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
