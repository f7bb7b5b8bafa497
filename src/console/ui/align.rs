//! Align: is the beam on each PSD, how far from centre is the spot, the follower's jog,
//! home and the zero reference, and the beam alignment over the travel (stations, the check,
//! the screws to turn, the beam's angle). At 80×24 the PSD plots give way to the alignment.

use super::live::psd_row;
use super::{TALL, Theme, panel};
use crate::console::app::{App, StationSpot};
use crate::service::snapshot::Snapshot;
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
        render_alignment(frame, aligning, app, theme);
        bottom
    } else {
        let [bottom, aligning] =
            Layout::vertical([Constraint::Length(10), Constraint::Min(6)]).areas(area);
        render_alignment(frame, aligning, app, theme);
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
            if f.homed {
                Span::styled("homed", theme.ok())
            } else {
                Span::styled("NOT homed (h)", theme.warn())
            },
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

/// The check first (it decides what to do), the screws to turn, the beam's angle, the stations
/// read, then the span and the keys.
pub fn alignment_lines(app: &App, theme: Theme) -> Vec<Line<'static>> {
    let a = &app.align;
    let (from, to) = app.align_span();
    let mut lines = Vec::new();
    match &a.advice {
        None => lines.push(Line::styled(
            "no advice yet: read both ends (n, f), then a",
            theme.dim(),
        )),
        Some(adv) => {
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
        format!("span {from}–{to} mm (s)  n/f read near/far  t target  a advice  e erase"),
        theme.dim(),
    ));
    lines
}
