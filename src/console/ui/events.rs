//! Events: the service's alarms (active and recently cleared, from the snapshot), this
//! console's own requests and answers, and the service's audit log (every operator request:
//! who, when, what; the control API's `audit`).

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
        Layout::vertical([Constraint::Percentage(40), Constraint::Min(4)]).areas(area);
    let (log_area, audit_area) = if wide {
        let [a, b] = Layout::horizontal([Constraint::Percentage(50), Constraint::Percentage(50)])
            .areas(rest);
        (a, b)
    } else {
        let [a, b] = Layout::vertical([
            Constraint::Min(3),
            Constraint::Length(if tall { 10 } else { 7 }),
        ])
        .areas(rest);
        (a, b)
    };
    alarms(frame, alarms_area, app, wide, theme);
    console_log(frame, log_area, app, theme);
    audit(frame, audit_area, app, theme);
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

/// A request as one line: `run_start X 0–8 mm, 5 targets, 2 runs`, `follower jog 0.1 mm`.
pub fn request_text(action: &str, d: &serde_json::Value) -> String {
    let num = |k: &str| d[k].as_f64().map(|v| format!("{v}"));
    match action {
        "run_start" => {
            let p = &d["plan"];
            format!(
                "run_start {} {}–{} mm, {} targets, {} runs",
                p["axis"].as_str().unwrap_or("?"),
                p["start_mm"],
                p["end_mm"],
                p["targets"],
                p["runs"]
            )
        }
        "follower" => {
            let mut t = format!("follower {}", d["action"].as_str().unwrap_or("?"));
            if let Some(mm) = num("mm") {
                t.push_str(&format!(" {mm} mm"));
            }
            t
        }
        "nominal" => match num("mm") {
            Some(mm) => format!("nominal {mm} mm"),
            None => "nominal cleared".into(),
        },
        "strategy" => format!("strategy {}", d["strategy"].as_str().unwrap_or("?")),
        other => other.to_string(),
    }
}

/// The service's audit log, newest first.
fn audit(frame: &mut Frame, area: Rect, app: &App, theme: Theme) {
    let lines: Vec<Line> = match &app.audit {
        None => vec![Line::styled("asking the service…", theme.dim())],
        Some(v) if v.is_empty() => vec![Line::styled("no operator requests yet", theme.dim())],
        Some(v) => v
            .iter()
            .map(|a| {
                Line::from(vec![
                    Span::styled(format!("{} ", clock_utc(a.unix_us)), theme.dim()),
                    Span::styled(
                        format!("{} ", a.user.as_deref().unwrap_or("?")),
                        theme.bold(),
                    ),
                    Span::raw(request_text(&a.action, &a.details)),
                ])
            })
            .collect(),
    };
    frame.render_widget(
        Paragraph::new(lines).block(panel("Audit log (UTC, newest first)")),
        area,
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn requests_read_as_one_line() {
        let plan = serde_json::json!({"plan": {"axis": "X", "start_mm": 0.0, "end_mm": 8.0,
            "targets": 5, "runs": 2}});
        assert_eq!(
            request_text("run_start", &plan),
            "run_start X 0.0–8.0 mm, 5 targets, 2 runs"
        );
        assert_eq!(
            request_text(
                "follower",
                &serde_json::json!({"action": "jog", "mm": -0.1})
            ),
            "follower jog -0.1 mm"
        );
        assert_eq!(
            request_text("nominal", &serde_json::json!({"mm": null})),
            "nominal cleared"
        );
        assert_eq!(request_text("zero", &serde_json::json!({})), "zero");
    }
}
