//! Align: is the beam on each PSD, how far from centre is the spot, and the follower's jog,
//! home and the zero reference.

use super::live::psd_row;
use super::{TALL, Theme, panel};
use crate::console::app::App;
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
    let bottom_h = if area.height >= TALL { 12 } else { 10 };
    let [top, bottom] =
        Layout::vertical([Constraint::Min(6), Constraint::Length(bottom_h)]).areas(area);
    psd_row(frame, top, snap, theme);
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
    }
    lines.push(Line::raw(format!("jog step {} mm", app.jog_step_mm)));
    lines.push(Line::styled("h home  j/k jog −/+  [ ] step", theme.dim()));
    lines.push(Line::styled(
        "z zero  c clear  x stop  r reset",
        theme.dim(),
    ));
    if app.read_only() {
        lines.push(Line::styled(
            "read-only (viewer): these keys are disabled",
            theme.warn(),
        ));
    }
    lines
}
