//! Publish: the stored tables (`table_list`), the selected one's values against what the PLC
//! holds (`table_status`, its staging area read back) point by point, generating tables from a
//! finished run, and publishing with the axis name typed, the handshake's outcome shown.

use super::{TALL, Theme, WIDE, date_utc, panel};
use crate::console::app::{App, PublishState};
use crate::service::tables::{ActiveView, StatusView, TableView};
use ratatui::Frame;
use ratatui::layout::{Constraint, Layout, Rect};
use ratatui::style::Color;
use ratatui::symbols::Marker;
use ratatui::text::{Line, Span};
use ratatui::widgets::{Axis, Chart, Dataset, GraphType, Paragraph, Wrap};

pub fn render(frame: &mut Frame, area: Rect, app: &App) {
    let theme = Theme {
        color: app.opts.color,
    };
    let p = &app.publish;
    let list_rows = if area.height >= TALL { 10 } else { 4 };
    let list_h = (p.tables.len().clamp(1, list_rows) + 3) as u16;
    if area.width >= WIDE {
        let [left, right] =
            Layout::horizontal([Constraint::Length(78), Constraint::Min(30)]).areas(area);
        let [list, status] =
            Layout::vertical([Constraint::Length(list_h), Constraint::Min(6)]).areas(left);
        tables(frame, list, app, true, theme);
        plc(frame, status, p, theme);
        if area.height >= TALL {
            let [c, v] =
                Layout::vertical([Constraint::Percentage(50), Constraint::Min(6)]).areas(right);
            chart(frame, c, p, theme);
            values(frame, v, p, true, theme);
        } else {
            values(frame, right, p, true, theme);
        }
    } else {
        let [list, rest] =
            Layout::vertical([Constraint::Length(list_h), Constraint::Min(6)]).areas(area);
        tables(frame, list, app, false, theme);
        let [v, s] = Layout::horizontal([Constraint::Length(40), Constraint::Min(20)]).areas(rest);
        values(frame, v, p, false, theme);
        plc(frame, s, p, theme);
    }
}

fn publication(t: &TableView) -> String {
    match &t.last_publication {
        Some(p) => format!("seq {} {}", p.sequence, p.result),
        None => "never published".into(),
    }
}

/// The stored tables, or the run picker while generating.
fn tables(frame: &mut Frame, area: Rect, app: &App, wide: bool, theme: Theme) {
    let p = &app.publish;
    let rows = (area.height as usize).saturating_sub(3).max(1);
    let mut lines = Vec::new();
    if let Some(pick) = p.picking {
        let runs = PublishState::runs(&app.results);
        lines.push(Line::styled(
            "Generate tables from which run? ↑/↓ pick, Enter generates, Esc cancels",
            theme.accent(),
        ));
        if !app.results.listed {
            lines.push(Line::styled("asking the service…", theme.dim()));
        } else if runs.is_empty() {
            lines.push(Line::styled(
                "no finished runs: measure one on screen 4",
                theme.dim(),
            ));
        }
        let first = pick.saturating_sub(rows.saturating_sub(1));
        for (i, r) in runs.iter().enumerate().skip(first).take(rows) {
            let line = format!(
                "run {:<4} {} {:>4} captures  {}",
                r.id,
                r.axis,
                r.captures,
                date_utc(r.created_us)
            );
            lines.push(if i == pick {
                Line::styled(line, theme.selected())
            } else {
                Line::raw(line)
            });
        }
        frame.render_widget(Paragraph::new(lines).block(panel("Generate")), area);
        return;
    }
    let title = match &p.map {
        Some(m) => format!("Tables (map {m})"),
        None => "Tables".into(),
    };
    lines.push(Line::styled(
        if wide {
            "  id  name kind          axis pts  range µm         run  latest publication"
        } else {
            "  id  name kind         pts  run  latest"
        },
        theme.dim(),
    ));
    if !p.listed {
        lines.push(Line::styled("asking the service…", theme.dim()));
    } else if p.tables.is_empty() {
        lines.push(Line::styled(
            "no stored tables: g generates them from a finished run",
            theme.dim(),
        ));
    }
    let first = p.selected.saturating_sub(rows.saturating_sub(1));
    let held = match &p.status {
        Some(Ok(s)) => s.table_id,
        _ => None,
    };
    for (i, t) in p.tables.iter().enumerate().skip(first).take(rows) {
        let mark = if Some(t.id) == held { "●" } else { " " };
        let run = t.source_run.map(|r| r.to_string()).unwrap_or("—".into());
        let text = if wide {
            format!(
                "{mark}{:>3}  {:<4} {:<13} {:<4} {:>3}  {:>+6.1} … {:>+6.1}  {:>4}  {}",
                t.id,
                t.name,
                t.kind,
                t.axis,
                t.points,
                t.min_um,
                t.max_um,
                run,
                publication(t)
            )
        } else {
            format!(
                "{mark}{:>3}  {:<4} {:<12} {:>3} {:>4}  {}",
                t.id,
                t.name,
                t.kind,
                t.points,
                run,
                publication(t)
            )
        };
        lines.push(if i == p.selected {
            Line::styled(text, theme.selected())
        } else {
            Line::raw(text)
        });
    }
    frame.render_widget(Paragraph::new(lines).block(panel(&title)), area);
}

/// The table the PLC applies for `t`'s kind and axis (issue 15: not the one staging area).
fn active_for<'a>(p: &'a PublishState, t: &TableView) -> Option<&'a ActiveView> {
    match &p.status {
        Some(Ok(StatusView { active, .. })) => {
            active.iter().find(|a| a.kind == t.kind && a.axis == t.axis)
        }
        _ => None,
    }
}

/// The PLC's values for `t`'s kind and axis when they can be set against `t` point by point:
/// the active table of that kind and axis; from a service that does not list them, the
/// staging area when it holds that kind and axis.
fn plc_values<'a>(p: &'a PublishState, t: &TableView) -> Option<&'a [f64]> {
    let same = |v: &'a [f64]| (v.len() == t.values_um.len() && !v.is_empty()).then_some(v);
    if let Some(a) = active_for(p, t) {
        return same(&a.values_um);
    }
    match &p.status {
        Some(Ok(StatusView {
            staged: Some(s),
            active_source,
            ..
        })) if active_source.is_empty() && staged_is(s, t) => same(&s.values_um),
        _ => None,
    }
}

/// Whether the staging area holds a table of `t`'s kind acting on `t`'s axis.
fn staged_is(s: &crate::service::tables::StagedView, t: &TableView) -> bool {
    use crate::plc::table::{axis_code, kind_code};
    let kind = crate::service::stored::kind_from_name(&t.kind).map(kind_code);
    let axis = crate::comp::MachineAxis::from_letter(&t.axis).map(axis_code);
    kind == Some(s.kind) && axis == Some(s.axis)
}

/// Rounded to 2 decimals, never "-0.00".
fn r2(v: f64) -> f64 {
    (v * 100.0).round() / 100.0 + 0.0
}

/// Position → the table's value, the PLC's, and the difference.
fn values(frame: &mut Frame, area: Rect, p: &PublishState, wide: bool, theme: Theme) {
    let Some(t) = p.selected_table() else {
        frame.render_widget(
            Paragraph::new(Line::styled("no table selected", theme.dim())).block(panel("Values")),
            area,
        );
        return;
    };
    let theirs = plc_values(p, t);
    // A composed table says what it is made of (issue 15) here, beside its values, where
    // there is room at 80×24 too: wrapped to the panel.
    let composed = if t.composition.starts_with("composed") {
        wrap(&t.composition, area.width.saturating_sub(2) as usize)
    } else {
        Vec::new()
    };
    let mut lines = vec![Line::styled(
        format!(
            "{:>8}  {:>8}  {:>8}  {:>6}",
            "pos mm", "table µm", "PLC µm", "Δ µm"
        ),
        theme.dim(),
    )];
    let rows = (area.height as usize).saturating_sub(4 + composed.len());
    let n = t.values_um.len();
    // Every point when they fit, else evenly spaced ones (the last always).
    let step = n.div_ceil(rows.max(1)).max(1);
    let mut differing = 0usize;
    let mut worst = 0f64;
    if let Some(v) = theirs {
        for (a, b) in t.values_um.iter().zip(v) {
            let d = b - a;
            if d.abs() > 0.05 {
                differing += 1;
            }
            worst = worst.max(d.abs());
        }
    }
    for k in (0..n).filter(|k| k % step == 0 || *k + 1 == n) {
        let pos = t.start_mm + t.interval_mm * k as f64;
        let mine = t.values_um[k];
        let (plc, diff, style) = match theirs {
            Some(v) => {
                let d = v[k] - mine;
                let style = if d.abs() > 0.05 {
                    theme.warn()
                } else {
                    ratatui::style::Style::new()
                };
                (
                    format!("{:>+8.2}", v[k]),
                    format!("{:>+6.2}", d + 0.0),
                    style,
                )
            }
            None => ("—".into(), "".into(), ratatui::style::Style::new()),
        };
        lines.push(Line::from(vec![
            Span::raw(format!("{pos:>8.1}  {:>+8.2}  {plc:>8}  ", r2(mine))),
            Span::styled(diff, style),
        ]));
    }
    let held = active_for(p, t);
    let held_name = held.map_or_else(String::new, |a| match a.table_id {
        Some(id) => format!("table {id}"),
        None => format!("sequence {}", a.sequence),
    });
    let summary = match (theirs, &p.status) {
        (Some(_), _) if held.is_none() && differing == 0 => Line::styled(
            format!("the PLC's staging area equals table {} (±0.05 µm)", t.id),
            theme.ok(),
        ),
        (Some(_), _) if differing == 0 => Line::styled(
            format!(
                "the PLC's {} {} ({held_name}) equals table {} (±0.05 µm)",
                t.kind, t.axis, t.id
            ),
            theme.ok(),
        ),
        (Some(_), _) => Line::styled(
            if held.is_some() {
                format!("{differing} of {n} points differ from {held_name}, by up to {worst:.2} µm")
            } else {
                format!("{differing} of {n} points differ, by up to {worst:.2} µm")
            },
            theme.warn(),
        ),
        (None, Some(Ok(_))) => Line::styled(
            match held {
                Some(a) if !a.values_um.is_empty() => format!(
                    "the PLC's {held_name} has {} points, table {} has {n}: no diff",
                    a.values_um.len(),
                    t.id
                ),
                Some(_) => format!("the PLC applies {held_name}, not in the store: no diff"),
                None => format!("the PLC applies no {} table for {}", t.kind, t.axis),
            },
            theme.dim(),
        ),
        _ => Line::styled("the PLC's values unknown", theme.dim()),
    };
    lines.insert(0, summary);
    for (k, c) in composed.into_iter().enumerate() {
        lines.insert(1 + k, Line::styled(c, theme.accent()));
    }
    let title = format!(
        "Table {} {} axis {}, {} pts{}",
        t.id,
        t.name,
        t.axis,
        n,
        if wide && t.down_um.is_some() {
            " (+ profile)"
        } else {
            ""
        }
    );
    frame.render_widget(Paragraph::new(lines).block(panel(&title)), area);
}

/// `text` in lines of at most `w` columns, broken at spaces (a longer word cut).
fn wrap(text: &str, w: usize) -> Vec<String> {
    let w = w.max(1);
    let mut out: Vec<String> = Vec::new();
    let mut line = String::new();
    for word in text.split_whitespace() {
        let word: String = word.chars().take(w).collect();
        let (lw, ww) = (line.chars().count(), word.chars().count());
        if lw > 0 && lw + 1 + ww > w {
            out.push(std::mem::take(&mut line));
        }
        if !line.is_empty() {
            line.push(' ');
        }
        line.push_str(&word);
    }
    if !line.is_empty() {
        out.push(line);
    }
    out
}

/// The selected table's values against position, and the PLC's.
fn chart(frame: &mut Frame, area: Rect, p: &PublishState, theme: Theme) {
    let Some(t) = p.selected_table() else {
        frame.render_widget(panel("Chart"), area);
        return;
    };
    let pts = |v: &[f64]| -> Vec<(f64, f64)> {
        v.iter()
            .enumerate()
            .map(|(k, y)| (t.start_mm + t.interval_mm * k as f64, *y))
            .collect()
    };
    let mine = pts(&t.values_um);
    let theirs = plc_values(p, t).map(pts).unwrap_or_default();
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for (_, y) in mine.iter().chain(&theirs) {
        lo = lo.min(*y);
        hi = hi.max(*y);
    }
    if !lo.is_finite() || hi - lo < 1e-6 {
        (lo, hi) = (lo.min(0.0) - 1.0, hi.max(0.0) + 1.0);
    }
    let x_end = t.start_mm + t.interval_mm * t.values_um.len().saturating_sub(1) as f64;
    let mut sets = vec![
        Dataset::default()
            .name(format!("table {}", t.id))
            .marker(Marker::Braille)
            .graph_type(GraphType::Line)
            .style(theme.fg(Color::Cyan))
            .data(&mine),
    ];
    if !theirs.is_empty() {
        sets.push(
            Dataset::default()
                .name("PLC")
                .marker(Marker::Dot)
                .graph_type(GraphType::Scatter)
                .style(theme.fg(Color::Yellow))
                .data(&theirs),
        );
    }
    let title = format!("{} e (µm) against {} (mm)", t.name, t.base_axis);
    let c = Chart::new(sets)
        .block(panel(&title))
        .x_axis(
            Axis::default()
                .bounds([t.start_mm, x_end.max(t.start_mm + 1e-6)])
                .labels([format!("{:.0}", t.start_mm), format!("{x_end:.0}")]),
        )
        .y_axis(
            Axis::default()
                .bounds([lo, hi])
                .labels([format!("{lo:+.1}"), format!("{hi:+.1}")]),
        );
    frame.render_widget(c, area);
}

/// What the PLC holds, the publication under way or its outcome, and the keys.
fn plc(frame: &mut Frame, area: Rect, p: &PublishState, theme: Theme) {
    let mut lines = Vec::new();
    match &p.status {
        None => lines.push(Line::styled("asking the PLC…", theme.dim())),
        Some(Err(e)) => lines.push(Line::styled(e.clone(), theme.bad())),
        Some(Ok(s)) => {
            let style = match s.verdict.as_str() {
                "matches" => theme.ok(),
                "empty" => theme.dim(),
                _ => theme.warn(),
            };
            lines.push(Line::styled(s.message.clone(), style));
            let ready = if s.plc.ready == 1 {
                "ready"
            } else {
                "NOT READY"
            };
            lines.push(Line::raw(if s.plc.active_sequence == 0 {
                format!("PLC {ready}, empty: no table applied yet")
            } else {
                format!(
                    "PLC {ready}, active sequence {}; last commit: {} sequence {}",
                    s.plc.active_sequence, s.plc.status, s.plc.status_sequence
                )
            }));
            if let Some(st) = &s.staged {
                lines.push(Line::raw(format!(
                    "staged: sequence {}, CRC {}, {} points",
                    st.sequence, st.crc, st.points
                )));
                if let Some(why) = &st.invalid {
                    lines.push(Line::styled(
                        format!("staged table invalid: {why}"),
                        theme.bad(),
                    ));
                }
            }
            lines.push(Line::styled(s.source.clone(), theme.dim()));
            for a in &s.active {
                lines.push(Line::raw(format!(
                    "active: {} {} {} seq {} {}{}{}",
                    a.table_id
                        .map_or_else(|| "(not stored)".into(), |i| format!("table {i}")),
                    a.kind,
                    a.axis,
                    a.sequence,
                    a.published_us.map(date_utc).unwrap_or_default(),
                    a.source_run
                        .map(|r| format!(" run {r}"))
                        .unwrap_or_default(),
                    if a.read_back { " (read back)" } else { "" }
                )));
            }
        }
    }
    lines.push(Line::raw(""));
    if let Some(run) = p.generating {
        lines.push(Line::styled(
            format!("generating tables from run {run}…"),
            theme.accent(),
        ));
    }
    if let Some(id) = p.publishing {
        lines.push(Line::styled(
            format!("publishing table {id}… (handshake with the PLC)"),
            theme.accent(),
        ));
    }
    match &p.outcome {
        Some(Ok(o)) => {
            let (style, head) = match o.result.as_str() {
                "committed" => (
                    theme.ok(),
                    format!(
                        "✓ table {} committed as sequence {}",
                        o.table_id, o.sequence
                    ),
                ),
                "rejected" => (
                    theme.bad(),
                    format!(
                        "✗ table {} rejected by the PLC, code {}",
                        o.table_id,
                        o.code.map(|c| c.to_string()).unwrap_or("?".into())
                    ),
                ),
                other => (theme.bad(), format!("✗ table {} {other}", o.table_id)),
            };
            lines.push(Line::styled(head, style));
            lines.push(Line::raw(o.message.clone()));
            if o.result == "failed" && o.commit_sent {
                lines.push(Line::styled(
                    "the commit went out: the PLC may have applied it (r re-reads it)",
                    theme.warn(),
                ));
            }
        }
        Some(Err(e)) => lines.push(Line::styled(format!("✗ {e}"), theme.bad())),
        None => {}
    }
    lines.push(Line::styled(
        "g generate  p publish  r reload  ↑/↓ table",
        theme.dim(),
    ));
    frame.render_widget(
        Paragraph::new(lines)
            .wrap(Wrap { trim: true })
            .block(panel("PLC")),
        area,
    );
}
