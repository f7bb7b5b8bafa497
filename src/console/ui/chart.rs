//! One error against position as a chart: the mean per target for each approach direction
//! (+ and −), and a second run's dimmed for a before/after comparison. Shared by the Results
//! screen (six of them) and the Measure screen's live plot.

use super::Theme;
use crate::run::Direction;
use crate::service::results::DofView;
use ratatui::Frame;
use ratatui::layout::Rect;
use ratatui::style::{Color, Style};
use ratatui::symbols::Marker;
use ratatui::text::{Line, Span};
use ratatui::widgets::{Axis, Block, Chart, Dataset, GraphType, Paragraph};

/// The (position, mean) points of one direction's series.
fn points(d: &DofView, dir: Direction) -> Vec<(f64, f64)> {
    d.series
        .iter()
        .filter(|s| s.direction == dir)
        .flat_map(|s| s.positions_mm.iter().copied().zip(s.mean.iter().copied()))
        .filter(|(x, y)| x.is_finite() && y.is_finite())
        .collect()
}

/// Bounds over every point, padded; a flat or empty set gets a unit span.
pub(super) fn bounds(
    sets: &[&[(f64, f64)]],
    pick: impl Fn(&(f64, f64)) -> f64,
    pad: f64,
) -> [f64; 2] {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for p in sets.iter().flat_map(|s| s.iter()) {
        lo = lo.min(pick(p));
        hi = hi.max(pick(p));
    }
    if !lo.is_finite() {
        return [-1.0, 1.0];
    }
    let span = hi - lo;
    if span < 1e-9 {
        return [lo - 1.0, hi + 1.0];
    }
    [lo - span * pad, hi + span * pad]
}

/// Decimals that tell the ends of a span apart.
pub(super) fn decimals(span: f64) -> usize {
    if span >= 10.0 {
        0
    } else if span >= 1.0 {
        1
    } else if span >= 0.1 {
        2
    } else {
        3
    }
}

/// `v` with `dec` decimals, a value that rounds to zero as "0.0" (never "-0.0").
pub(super) fn fixed(v: f64, dec: usize) -> String {
    let scale = 10f64.powi(dec as i32);
    let r = (v * scale).round() / scale;
    format!("{:.dec$}", r + 0.0)
}

/// `dy positioning (µm)`, with `+`/`−` legends in the direction colours.
fn title(d: &DofView, selected: bool, before: bool, theme: Theme) -> Line<'static> {
    let name_style = if selected {
        theme.selected()
    } else {
        theme.bold()
    };
    let mut spans = vec![
        Span::raw(" "),
        Span::styled(d.name.clone(), name_style),
        Span::raw(format!(" {} ({}) ", d.meaning, d.unit)),
        Span::styled("+", Style::new().fg(theme.shape(Color::Green))),
        Span::raw(" "),
        Span::styled("−", Style::new().fg(theme.shape(Color::Cyan))),
    ];
    if before {
        spans.push(Span::styled(" ·before", theme.dim()));
    }
    spans.push(Span::raw(" "));
    Line::from(spans)
}

/// Draw `d` (and `before`, dimmed) into `area` with a bordered title.
pub fn render(
    frame: &mut Frame,
    area: Rect,
    d: &DofView,
    before: Option<&DofView>,
    selected: bool,
    theme: Theme,
) {
    let block = Block::bordered().title(title(d, selected, before.is_some(), theme));
    let up = points(d, Direction::Up);
    let down = points(d, Direction::Down);
    let (b_up, b_down) = match before {
        Some(b) => (points(b, Direction::Up), points(b, Direction::Down)),
        None => (Vec::new(), Vec::new()),
    };
    if up.is_empty() && down.is_empty() {
        let inner = block.inner(area);
        frame.render_widget(block, area);
        frame.render_widget(
            Paragraph::new(Line::styled("no captures yet", theme.dim())),
            inner,
        );
        return;
    }
    let sets: [&[(f64, f64)]; 4] = [&up, &down, &b_up, &b_down];
    let xb = bounds(&sets, |p| p.0, 0.02);
    let yb = bounds(&sets, |p| p.1, 0.1);
    let dim = Style::new().fg(theme.shape(Color::DarkGray));
    let mut datasets = Vec::new();
    for (data, style) in [(&b_up, dim), (&b_down, dim)] {
        if !data.is_empty() {
            datasets.push(
                Dataset::default()
                    .marker(Marker::Dot)
                    .graph_type(GraphType::Line)
                    .style(style)
                    .data(data),
            );
        }
    }
    for (data, c) in [(&up, Color::Green), (&down, Color::Cyan)] {
        if !data.is_empty() {
            datasets.push(
                Dataset::default()
                    .marker(Marker::Braille)
                    .graph_type(GraphType::Line)
                    .style(Style::new().fg(theme.shape(c)))
                    .data(data),
            );
        }
    }
    // Enough decimals for the span, and no "-0.0".
    let dec = decimals(yb[1] - yb[0]);
    let ylabel = move |v: f64| Span::styled(fixed(v, dec), theme.dim());
    let xlabel = |v: f64| Span::styled(fixed(v, 1), theme.dim());
    let chart = Chart::new(datasets)
        .block(block)
        .legend_position(None)
        .x_axis(Axis::default().bounds(xb).labels([
            xlabel(xb[0]),
            Span::styled("mm", theme.dim()),
            xlabel(xb[1]),
        ]))
        .y_axis(
            Axis::default()
                .bounds(yb)
                .labels([ylabel(yb[0]), ylabel(yb[1])]),
        );
    frame.render_widget(chart, area);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounds_pad_and_survive_flat_or_empty_sets() {
        let a = [(0.0, 1.0), (10.0, 3.0)];
        assert_eq!(bounds(&[&a], |p| p.1, 0.5), [0.0, 4.0]);
        assert_eq!(bounds(&[&[(5.0, 2.0)]], |p| p.1, 0.1), [1.0, 3.0]);
        assert_eq!(bounds(&[&[]], |p| p.0, 0.1), [-1.0, 1.0]);
    }

    #[test]
    fn label_decimals_follow_the_span() {
        assert_eq!(decimals(25.0), 0);
        assert_eq!(decimals(2.5), 1);
        assert_eq!(decimals(0.25), 2);
        assert_eq!(decimals(0.025), 3);
        assert_eq!(fixed(-0.04, 1), "0.0");
        assert_eq!(fixed(-0.06, 1), "-0.1");
        assert_eq!(fixed(8.2, 0), "8");
    }
}
