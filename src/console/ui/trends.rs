//! The Results screen's trends view (`t`): every figure of the newest run's axis over its runs
//! and checks, each with its newest value and its state against its control limits; the figure
//! highlighted charted run by run (its values, the EWMA, the upper limit and the tolerance) with
//! what its drift calls for and the forecast. Everything is the service's (`trend`).

use super::chart::{bounds, decimals, fixed};
use super::{Theme, WIDE, date_utc, panel};
use crate::console::app::{App, FigureTrend, TrendsView};
use ratatui::Frame;
use ratatui::layout::{Constraint, Layout, Rect};
use ratatui::style::{Color, Style};
use ratatui::symbols::Marker;
use ratatui::text::{Line, Span};
use ratatui::widgets::{Axis, Block, Chart, Dataset, GraphType, Paragraph, Wrap};

pub fn render(frame: &mut Frame, area: Rect, app: &App) {
    let theme = Theme {
        color: app.opts.color,
    };
    let t = &app.trends;
    let Some(trend) = &t.trend else {
        let mut lines = vec![Line::styled(
            "asking the service for the trends…",
            theme.dim(),
        )];
        if let Some(e) = &t.error {
            lines = vec![Line::styled(e.clone(), theme.bad())];
        }
        lines.push(Line::raw("t: back to the runs"));
        frame.render_widget(
            Paragraph::new(lines)
                .wrap(Wrap { trim: true })
                .block(panel("Trends")),
            area,
        );
        return;
    };
    let title = format!(
        "Trends of axis {}: {} run{} under the same tables (↑↓, t runs)",
        trend.axis,
        trend.runs.len(),
        if trend.runs.len() == 1 { "" } else { "s" },
    );
    let detail_h = if area.width >= WIDE { 5 } else { 4 };
    if area.width >= WIDE {
        let [left, right] =
            Layout::horizontal([Constraint::Length(72), Constraint::Min(30)]).areas(area);
        list(frame, left, t, &title, true, theme);
        let [chart_a, detail_a] =
            Layout::vertical([Constraint::Min(6), Constraint::Length(detail_h)]).areas(right);
        if let Some(f) = t.figure() {
            chart(frame, chart_a, f, theme);
            detail(frame, detail_a, f, theme);
        }
    } else {
        let [top, bottom] =
            Layout::vertical([Constraint::Min(8), Constraint::Length(8)]).areas(area);
        let [chart_a, detail_a] =
            Layout::vertical([Constraint::Min(5), Constraint::Length(detail_h)]).areas(top);
        if let Some(f) = t.figure() {
            chart(frame, chart_a, f, theme);
            detail(frame, detail_a, f, theme);
        }
        list(frame, bottom, t, &title, false, theme);
    }
}

/// The state of a figure in a word or two.
fn state(f: &FigureTrend) -> (String, bool) {
    match (f.alarm_run, &f.no_limits) {
        (Some(run), _) => (format!("DRIFT since run {run}"), true),
        (None, Some(_)) => ("learning".into(), false),
        (None, None) => ("in control".into(), false),
    }
}

/// Every figure: its newest value and state, the highlighted one marked.
fn list(frame: &mut Frame, area: Rect, t: &TrendsView, title: &str, wide: bool, theme: Theme) {
    let figures = t.trend.as_ref().map_or(&[][..], |t| &t.figures[..]);
    let rows = (area.height as usize).saturating_sub(2).max(1);
    let first = t.selected.saturating_sub(rows.saturating_sub(1));
    let label_w = if wide { 30 } else { 34 };
    let lines: Vec<Line> = figures
        .iter()
        .enumerate()
        .skip(first)
        .take(rows)
        .map(|(i, f)| {
            let last = f.points.last().map_or(f64::NAN, |p| p.value);
            let (word, alarm) = state(f);
            let mark = if i == t.selected { "▶ " } else { "  " };
            let mut label = f.label();
            if label.chars().count() > label_w {
                label = label.chars().take(label_w - 1).collect::<String>() + "…";
            }
            let text = format!("{mark}{label:<label_w$} {last:>8.2} {:<6} ", f.unit);
            let style = if i == t.selected {
                theme.selected()
            } else {
                Style::new()
            };
            Line::from(vec![
                Span::styled(text, style),
                Span::styled(word, if alarm { theme.bad() } else { theme.dim() }),
            ])
        })
        .collect();
    frame.render_widget(Paragraph::new(lines).block(panel(title)), area);
}

/// The figure run by run: its values, the EWMA, the upper control limit and the tolerance.
fn chart(frame: &mut Frame, area: Rect, f: &FigureTrend, theme: Theme) {
    let idx = |i: usize| (i + 1) as f64;
    let values: Vec<(f64, f64)> = f
        .points
        .iter()
        .enumerate()
        .map(|(i, p)| (idx(i), p.value))
        .collect();
    let ewma: Vec<(f64, f64)> = f
        .points
        .iter()
        .enumerate()
        .filter_map(|(i, p)| p.ewma.map(|e| (idx(i), e)))
        .collect();
    let upper: Vec<(f64, f64)> = f
        .points
        .iter()
        .enumerate()
        .filter_map(|(i, p)| p.limits.map(|l| (idx(i), l[1])))
        .collect();
    let n = f.points.len().max(1);
    let tol: Vec<(f64, f64)> = f
        .tolerance
        .map(|t| vec![(1.0, t), (n as f64, t)])
        .unwrap_or_default();
    let mut title = vec![
        Span::raw(" "),
        Span::styled(f.label(), theme.bold()),
        Span::raw(format!(" ({})", f.unit)),
    ];
    let legend = [
        ("value", Color::Green, true),
        ("EWMA", Color::Cyan, true),
        ("limit", Color::Yellow, true),
        ("tolerance", Color::Red, f.tolerance.is_some()),
    ];
    for (name, c, _) in legend.iter().filter(|l| l.2) {
        title.push(Span::raw(" "));
        title.push(Span::styled(*name, Style::new().fg(theme.shape(*c))));
    }
    title.push(Span::raw(" "));
    let block = Block::bordered().title(Line::from(title));
    let sets: [&[(f64, f64)]; 4] = [&values, &ewma, &upper, &tol];
    let xb = if n > 1 { [1.0, n as f64] } else { [0.0, 2.0] };
    let yb = bounds(&sets, |p| p.1, 0.1);
    let mut datasets = Vec::new();
    for (data, c, marker, kind) in [
        (&tol, Color::Red, Marker::Braille, GraphType::Line),
        (&upper, Color::Yellow, Marker::Braille, GraphType::Line),
        (&ewma, Color::Cyan, Marker::Braille, GraphType::Line),
        (&values, Color::Green, Marker::Dot, GraphType::Scatter),
    ] {
        if !data.is_empty() {
            datasets.push(
                Dataset::default()
                    .marker(marker)
                    .graph_type(kind)
                    .style(Style::new().fg(theme.shape(c)))
                    .data(data),
            );
        }
    }
    let dec = decimals(yb[1] - yb[0]);
    let ylabel = move |v: f64| Span::styled(fixed(v, dec), theme.dim());
    let run = |i: usize| {
        f.points
            .get(i)
            .map_or(String::new(), |p| format!("run {}", p.run_id))
    };
    let chart = Chart::new(datasets)
        .block(block)
        .legend_position(None)
        .x_axis(Axis::default().bounds(xb).labels([
            Span::styled(run(0), theme.dim()),
            Span::styled(run(n - 1), theme.dim()),
        ]))
        .y_axis(
            Axis::default()
                .bounds(yb)
                .labels([ylabel(yb[0]), ylabel(yb[1])]),
        );
    frame.render_widget(chart, area);
}

/// The newest value against its limits, the alarm and what it calls for, the forecast.
fn detail(frame: &mut Frame, area: Rect, f: &FigureTrend, theme: Theme) {
    let mut lines = Vec::new();
    let unit = &f.unit;
    if let Some(p) = f.points.last() {
        let against = match (p.ewma, p.limits, &f.no_limits) {
            (Some(e), Some([_, hi]), _) => format!("EWMA {e:.2}, upper limit {hi:.2} {unit}"),
            (_, _, Some(why)) => format!("no limits yet: {why}"),
            _ => String::new(),
        };
        lines.push(Line::raw(format!(
            "run {} ({}): {:.2} {unit}; {against}",
            p.run_id,
            date_utc(p.unix_us),
            p.value
        )));
    }
    match (&f.alarm_run, &f.remedy) {
        (Some(run), Some(r)) => lines.push(Line::styled(
            format!("DRIFT since run {run}: {r}"),
            theme.bad(),
        )),
        _ => {
            if let (Some(m), Some(s)) = (f.mean, f.sigma) {
                lines.push(Line::styled(
                    format!(
                        "in control: limits from the history's mean {m:.2} and σ {s:.2} {unit}"
                    ),
                    theme.dim(),
                ));
            }
        }
    }
    match (f.tolerance, &f.forecast) {
        (Some(t), Some(fc)) => lines.push(Line::raw(match fc.crossing_unix_us {
            Some(at) => format!(
                "reaches {t} {unit} about {} (95 %: {} to {})",
                &date_utc(at)[..10],
                fc.crossing_low_unix_us
                    .map_or("?".into(), |x| date_utc(x)[..10].to_string()),
                fc.crossing_high_unix_us
                    .map_or("?".into(), |x| date_utc(x)[..10].to_string()),
            ),
            None => format!(
                "not heading for its tolerance {t} {unit} ({:+.3} {unit}/day over {} runs)",
                fc.slope_per_day, fc.points
            ),
        })),
        (Some(t), None) => lines.push(Line::styled(
            format!("no forecast against its tolerance {t} {unit} yet: 3 runs over a day or more"),
            theme.dim(),
        )),
        (None, _) => {}
    }
    frame.render_widget(Paragraph::new(lines).wrap(Wrap { trim: true }), area);
}
