//! Events: the service's alarms (active and recently cleared, from the snapshot), this
//! console's own requests and answers, and the place of the audit log, which waits for the
//! control API's `audit` request.

use super::{TALL, Theme, WIDE, clock_utc, panel};
use crate::console::app::App;
use ratatui::Frame;
use ratatui::layout::{Constraint, Layout, Rect};
use ratatui::text::{Line, Span};
use ratatui::widgets::{Paragraph, Wrap};

pub fn render(frame: &mut Frame, area: Rect, app: &App) {
    let theme = Theme {
        color: app.opts.color,
    };
    let (wide, tall) = (area.width >= WIDE, area.height >= TALL);
    let [alarms_area, rest] =
        Layout::vertical([Constraint::Percentage(50), Constraint::Min(4)]).areas(area);
    let (log_area, audit_area) = if wide {
        let [a, b] = Layout::horizontal([Constraint::Percentage(50), Constraint::Percentage(50)])
            .areas(rest);
        (a, b)
    } else {
        let [a, b] = Layout::vertical([
            Constraint::Min(3),
            Constraint::Length(if tall { 5 } else { 4 }),
        ])
        .areas(rest);
        (a, b)
    };
    alarms(frame, alarms_area, app, wide, theme);
    console_log(frame, log_area, app, theme);
    audit(frame, audit_area, theme);
}

fn alarms(frame: &mut Frame, area: Rect, app: &App, wide: bool, theme: Theme) {
    let mut lines = Vec::new();
    match &app.snapshot {
        None => lines.push(Line::styled("no snapshot yet", theme.dim())),
        Some(s) if s.alarms.is_empty() => {
            lines.push(Line::styled("no alarms", theme.ok()));
        }
        Some(s) => {
            for a in &s.alarms {
                let state = if a.active {
                    Span::styled("ACTIVE ", theme.bad())
                } else {
                    Span::styled("cleared", theme.dim())
                };
                let mut spans = vec![
                    Span::raw(format!("{} ", clock_utc(a.since_unix_us))),
                    state,
                    Span::styled(format!(" {:<15}", a.code), theme.bold()),
                ];
                if wide {
                    spans.push(Span::raw(format!(" {}", a.text)));
                    lines.push(Line::from(spans));
                } else {
                    lines.push(Line::from(spans));
                    lines.push(Line::raw(format!("  {}", a.text)));
                }
            }
        }
    }
    frame.render_widget(
        Paragraph::new(lines)
            .wrap(Wrap { trim: false })
            .block(panel("Alarms (UTC, newest first)")),
        area,
    );
}

fn console_log(frame: &mut Frame, area: Rect, app: &App, theme: Theme) {
    let lines: Vec<Line> = if app.log.is_empty() {
        vec![Line::styled(
            "no requests from this console yet",
            theme.dim(),
        )]
    } else {
        app.log
            .iter()
            .map(|l| {
                Line::from(vec![
                    Span::styled(
                        if l.unix_us > 0 {
                            format!("{} ", clock_utc(l.unix_us))
                        } else {
                            "         ".into()
                        },
                        theme.dim(),
                    ),
                    Span::styled(l.text.clone(), theme.level(l.level)),
                ])
            })
            .collect()
    };
    frame.render_widget(
        Paragraph::new(lines)
            .wrap(Wrap { trim: false })
            .block(panel("This console's requests")),
        area,
    );
}

/// The audit log's place: who changed what, from the store, once the API serves it.
fn audit(frame: &mut Frame, area: Rect, theme: Theme) {
    let lines = vec![
        Line::raw("Waits for the control API's `audit` request (who started,"),
        Line::raw("aborted, zeroed, published what, and when)."),
        Line::styled("Until then: journalctl -u axiscomp", theme.dim()),
    ];
    frame.render_widget(
        Paragraph::new(lines)
            .wrap(Wrap { trim: true })
            .block(panel("Audit log")),
        area,
    );
}
