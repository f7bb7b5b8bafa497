//! Align: is the beam on each PSD, how far from centre is the spot, the follower's jog,
//! home and the zero reference, the beam alignment over the travel (stations, the check,
//! the screws to turn, the beam's angle), and the follower's error map (the map in use, its
//! stop-and-go mapping's progress, the summary of the map made). At 80×24 the PSD plots give
//! way to the alignment, and the alignment and the follower map take turns (`v`); from 120
//! columns they are side by side.

use super::live::psd_row;
use super::{TALL, Theme, WIDE, bar, date_utc, panel};
use crate::console::app::{AdviceView, AlignPanel, App, StationSpot, StoredAlignment};
use crate::service::api::snapshot::Snapshot;
use ratatui::Frame;
use ratatui::layout::{Constraint, Layout, Rect};
use ratatui::text::{Line, Span};
use ratatui::widgets::{Paragraph, Wrap};

/// A spot within this fraction of the half-size from centre counts as centred.
pub const CENTRED: f64 = 0.05;
/// Beyond this fraction it is far off (drawn as a warning).
pub const FAR: f64 = 0.3;

pub fn render(frame: &mut Frame, area: Rect, app: &App) {
    let theme = Theme {
        color: app.opts.color,
    };
    let snap = app.snapshot.as_ref();
    let bottom = if area.height >= TALL {
        let [top, bottom, aligning] = Layout::vertical([
            Constraint::Min(6),
            Constraint::Length(12),
            Constraint::Length(12),
        ])
        .areas(area);
        psd_row(frame, top, snap, theme);
        render_lower(frame, aligning, app, theme);
        bottom
    } else {
        let [bottom, aligning] =
            Layout::vertical([Constraint::Length(10), Constraint::Min(6)]).areas(area);
        render_lower(frame, aligning, app, theme);
        bottom
    };
    let [hints, follower] =
        Layout::horizontal([Constraint::Percentage(55), Constraint::Percentage(45)]).areas(bottom);
    frame.render_widget(
        Paragraph::new(centring(snap, theme))
            .wrap(Wrap { trim: true })
            .block(panel("Beam and centring")),
        hints,
    );
    frame.render_widget(
        Paragraph::new(follower_lines(app, snap, theme))
            .wrap(Wrap { trim: true })
            .block(panel("Follower and zero")),
        follower,
    );
}

fn side(v: f64, pos: &'static str, neg: &'static str) -> &'static str {
    if v >= 0.0 { pos } else { neg }
}

/// One line per PSD: beam present, and where the spot is from centre.
pub fn centring(snap: Option<&Snapshot>, theme: Theme) -> Vec<Line<'static>> {
    let Some(p) = snap.and_then(|s| s.psd.as_ref()) else {
        return vec![Line::styled("no PSD frame yet", theme.dim())];
    };
    let mut lines = Vec::new();
    for k in 0..3 {
        let name = Span::styled(format!("PSD{} ", k + 1), theme.bold());
        let line = match p.spots_um[k] {
            None => Line::from(vec![
                name,
                Span::styled(
                    format!("no beam (SUM {:.2} V): check the path", p.sums_v[k]),
                    theme.bad(),
                ),
            ]),
            Some([x, y]) => {
                let half = if p.half_size_um[k] > 0.0 {
                    p.half_size_um[k]
                } else {
                    5000.0
                };
                let off = x.abs().max(y.abs()) / half;
                let text = if off <= CENTRED {
                    "beam on, centred".to_string()
                } else {
                    format!(
                        "beam on, spot {:.0} µm {} and {:.0} µm {}",
                        x.abs(),
                        side(x, "right", "left"),
                        y.abs(),
                        side(y, "up", "down"),
                    )
                };
                let style = if off <= CENTRED {
                    theme.ok()
                } else if off <= FAR {
                    ratatui::style::Style::new()
                } else {
                    theme.warn()
                };
                Line::from(vec![name, Span::styled(text, style)])
            }
        };
        lines.push(line);
    }
    lines.push(Line::styled(
        format!("centred: within {:.0} % of the half-size", CENTRED * 100.0),
        theme.dim(),
    ));
    lines
}

fn follower_lines(app: &App, snap: Option<&Snapshot>, theme: Theme) -> Vec<Line<'static>> {
    let mut lines = Vec::new();
    if let Some(s) = snap {
        let f = &s.follower;
        lines.push(Line::from(vec![
            Span::raw(format!(
                "{} ",
                if f.state.is_empty() { "?" } else { &f.state }
            )),
            super::live::homed_span(f, "NOT homed (h)", theme),
        ]));
        lines.push(Line::raw(format!(
            "at {}{}",
            f.position_mm
                .map(|p| format!("{p:.4} mm"))
                .unwrap_or_else(|| "?".into()),
            f.target_mm
                .map(|t| format!(", target {t:.4} mm"))
                .unwrap_or_default()
        )));
        let zeroed = s.live.as_ref().is_some_and(|l| l.zeroed);
        lines.push(if zeroed {
            Line::styled("zero reference set (c clears)", theme.ok())
        } else {
            Line::styled("no zero reference (z sets it here)", theme.warn())
        });
        // The follower's own error map in use (issue 14): without one, the stage's errors
        // (µm along, roll from its straightness) enter the six.
        lines.push(match &s.tracking.follower_map {
            Some(m) => Line::styled(
                format!(
                    "map {}, {}, {}",
                    m.name,
                    m.created.get(..10).unwrap_or(&m.created),
                    m.source
                ),
                theme.ok(),
            ),
            None => Line::styled("no follower map (follower import)", theme.warn()),
        });
    }
    lines.push(Line::raw(format!("jog step {} mm", app.jog_step_mm)));
    lines.push(Line::styled("h home  j/k jog −/+  [ ] step", theme.dim()));
    lines.push(Line::styled(
        "z zero  c clear  x stop  r reset",
        theme.dim(),
    ));
    if app.read_only() {
        lines.push(Line::styled(
            "read-only (viewer): keys disabled",
            theme.warn(),
        ));
    }
    lines
}

/// The beam alignment and the follower map: side by side when wide, else the one chosen.
fn render_lower(frame: &mut Frame, area: Rect, app: &App, theme: Theme) {
    if area.width >= WIDE {
        let [left, right] =
            Layout::horizontal([Constraint::Percentage(50), Constraint::Percentage(50)])
                .areas(area);
        render_alignment(frame, left, app, theme);
        render_follower_map(frame, right, app, "", theme);
        return;
    }
    match app.follower.panel {
        AlignPanel::Beam => render_alignment(frame, area, app, theme),
        AlignPanel::Follower => render_follower_map(frame, area, app, "  v alignment", theme),
    }
}

fn render_follower_map(frame: &mut Frame, area: Rect, app: &App, more: &str, theme: Theme) {
    let width = area.width.saturating_sub(2) as usize;
    let title = format!("Follower map: i certificate  m map / stop  l level  u check{more}");
    frame.render_widget(
        Paragraph::new(follower_map_lines(app, width, theme))
            .wrap(Wrap { trim: true })
            .block(panel(&title)),
        area,
    );
}

/// `text` cut to `width` characters, "…" marking the cut.
fn fit(text: &str, width: usize) -> String {
    if text.chars().count() <= width {
        return text.to_string();
    }
    let mut out: String = text.chars().take(width.saturating_sub(1)).collect();
    out.push('…');
    out
}

fn minutes(s: f64) -> String {
    if s < 90.0 {
        format!("{s:.0} s")
    } else if s < 5400.0 {
        format!("{:.1} min", s / 60.0)
    } else {
        format!("{:.1} h", s / 3600.0)
    }
}

/// The map in use, then the mapping (progress, time, its outcome) or the certificate last
/// imported: the status lines cut to the panel's width, the summary wrapped.
pub fn follower_map_lines(app: &App, width: usize, theme: Theme) -> Vec<Line<'static>> {
    let mut lines = Vec::new();
    let snap = app.snapshot.as_ref();
    lines.push(match snap.and_then(|s| s.tracking.follower_map.as_ref()) {
        Some(m) => Line::styled(
            fit(
                &format!(
                    "in use: map {} {}, {}, {}",
                    m.id,
                    m.name,
                    m.created.get(..10).unwrap_or(&m.created),
                    m.source
                ),
                width,
            ),
            theme.ok(),
        ),
        None => Line::styled(
            "no map in use: i imports the certificate, m maps the follower",
            theme.warn(),
        ),
    });
    let summary = |lines: &mut Vec<Line<'static>>, title: String, summary: &[String]| {
        lines.push(Line::styled(fit(&title, width), theme.bold()));
        // Wrapped: the summary comes last, so what the panel cannot hold is its end.
        lines.extend(summary.iter().map(|l| Line::raw(l.clone())));
    };
    match app.mapping() {
        Some(m) if m.state == "interrupted" => {
            lines.push(Line::styled(
                fit(m.error.as_deref().unwrap_or("interrupted"), width),
                theme.warn(),
            ));
        }
        Some(m) => {
            let frac = m.stops_done as f64 / m.stops_planned.max(1) as f64;
            lines.push(Line::from(vec![
                Span::styled(format!("{} ", m.state), theme.bold()),
                Span::raw(format!(
                    "stop {} of {} {} {} kept, {} skipped",
                    m.stops_done,
                    m.stops_planned,
                    bar(frac, 10),
                    m.steps_kept,
                    m.skipped
                )),
            ]));
            lines.push(Line::raw(fit(
                &format!(
                    "{} of machine time, {} left; dwell {:.1} s a stop",
                    minutes(m.elapsed_s),
                    minutes(m.left_s),
                    m.dwell_s
                ),
                width,
            )));
            lines.push(Line::styled(
                fit(
                    &format!(
                        "{} {:.1}–{:.1} mm by {} mm, {} passes, {} frames a side; {}",
                        m.axis, m.from_mm, m.to_mm, m.step_mm, m.passes, m.frames, m.cnc
                    ),
                    width,
                ),
                theme.dim(),
            ));
            if m.out_of_plan > 0 {
                lines.push(Line::styled(
                    fit(
                        &format!(
                            "{} steps not the plan's moves: is the CNC running this program?",
                            m.out_of_plan
                        ),
                        width,
                    ),
                    theme.warn(),
                ));
            }
            if let Some(e) = &m.error {
                lines.push(Line::styled(fit(e, width), theme.warn()));
            }
            if let Some(id) = m.map_id {
                summary(&mut lines, format!("map {id} made and in use:"), &m.summary);
            }
        }
        None => {
            if let Some((title, s)) = &app.follower.imported {
                summary(&mut lines, format!("{title}:"), s);
            }
        }
    }
    if let Some(l) = app.level() {
        let n = l.stations.len();
        lines.push(Line::from(vec![
            Span::styled(format!("level {} ", l.state), theme.bold()),
            Span::raw(fit(
                &format!(
                    "{} of {n} stations {} {}",
                    l.taken,
                    bar(l.taken as f64 / n.max(1) as f64, 10),
                    minutes(l.elapsed_s)
                ),
                width.saturating_sub(l.state.len() + 7),
            )),
        ]));
        if !l.prompt.is_empty() {
            let style = if l.awaiting_reading.is_some() {
                theme.warn()
            } else {
                theme.dim()
            };
            let more = if l.awaiting_reading.is_some() {
                " (l)"
            } else {
                ""
            };
            lines.push(Line::styled(
                fit(&format!("{}{more}", l.prompt), width),
                style,
            ));
        }
        if let Some(e) = &l.error {
            lines.push(Line::styled(fit(e, width), theme.warn()));
        }
        if let Some(id) = l.map_id {
            summary(
                &mut lines,
                format!("map {id} fitted with the level and in use:"),
                &l.summary,
            );
        }
    }
    lines
}

fn render_alignment(frame: &mut Frame, area: Rect, app: &App, theme: Theme) {
    frame.render_widget(
        Paragraph::new(alignment_lines(app, theme))
            .wrap(Wrap { trim: true })
            .block(panel("Beam alignment over the travel")),
        area,
    );
}

fn spot_text(k: usize, s: Option<StationSpot>) -> String {
    match s {
        None => format!("PSD{} no spot (t)", k + 1),
        Some(s) => format!(
            "PSD{} {:+.2} {:+.2}{}",
            k + 1,
            s.x,
            s.y,
            if s.from_target { " target" } else { "" }
        ),
    }
}

/// An advice's lines: the check, the screws to turn, the beam's angle to the travel.
fn advice_lines(adv: &AdviceView, theme: Theme, lines: &mut Vec<Line<'static>>) {
    if adv.passed {
        lines.push(Line::from(vec![
            Span::styled("✓ CHECK PASSED: ", theme.ok()),
            Span::raw(adv.check.clone()),
        ]));
    } else {
        lines.push(Line::from(vec![
            Span::styled("check not passed: ", theme.warn()),
            Span::raw(adv.check.clone()),
        ]));
    }
    if adv.passed && !adv.turns.is_empty() {
        lines.push(Line::styled(
            "optional, to centre the spots further:",
            theme.dim(),
        ));
    }
    for t in &adv.turns {
        lines.push(Line::styled(t.clone(), theme.bold()));
    }
    if !adv.turns.is_empty() && !adv.passed {
        lines.push(Line::styled(
            format!("then: {} (read both ends again)", adv.after),
            theme.dim(),
        ));
    }
    lines.push(Line::raw(match adv.misalignment_urad {
        Some([y, p]) => format!("beam to travel: yaw {y:+.0} µrad, pitch {p:+.0} µrad"),
        None => "beam to travel: not known (PSD3 not read at both ends)".into(),
    }));
}

/// The check first (it decides what to do), the screws to turn, the beam's angle, the stations
/// read, then the span and the keys.
pub fn alignment_lines(app: &App, theme: Theme) -> Vec<Line<'static>> {
    let a = &app.align;
    let (from, to) = app.align_span();
    let mut lines = Vec::new();
    match (&a.advice, &a.stored) {
        (Some(adv), _) => advice_lines(adv, theme, &mut lines),
        // After a restart of the console or the service, until a station is read: the
        // alignment the pre-run check judges, in brief (its check and the beam's angle).
        (None, StoredAlignment::Found { unix_us, advice }) if a.stations.is_empty() => {
            lines.push(Line::styled(
                format!(
                    "stored alignment of {} over {}–{} mm, {} UTC (the pre-run check's):",
                    app.plan.spec.axis,
                    advice.span_mm.0,
                    advice.span_mm.1,
                    date_utc(*unix_us)
                ),
                theme.dim(),
            ));
            let brief = AdviceView {
                turns: Vec::new(),
                ..advice.clone()
            };
            advice_lines(&brief, theme, &mut lines);
        }
        (None, stored) => {
            lines.push(Line::styled(
                "no advice yet: read both ends (n, f), then a",
                theme.dim(),
            ));
            if *stored == StoredAlignment::None && a.stations.is_empty() {
                lines.push(Line::styled(
                    format!("no alignment of {} stored", app.plan.spec.axis),
                    theme.dim(),
                ));
            }
        }
    }
    if a.stations.is_empty() {
        lines.push(Line::styled("no station read", theme.dim()));
    }
    for st in &a.stations {
        let spots: Vec<String> = (0..3).map(|k| spot_text(k, st.spots[k])).collect();
        let style = if st.spots.iter().any(Option::is_none) {
            theme.warn()
        } else {
            ratatui::style::Style::new()
        };
        lines.push(Line::styled(
            format!("at {:.1} mm: {} (mm)", st.at_mm, spots.join("  ")),
            style,
        ));
    }
    lines.push(Line::styled(
        format!("span {from}–{to} mm (s)  n/f read near/far  t target  a advice  e erase  v map"),
        theme.dim(),
    ));
    lines
}
