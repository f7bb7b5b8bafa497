//! Live: the three PSD spots in their active areas with SUM bars, the six errors with their
//! standard deviations, the follower (position, CiA 402 state), tracking, and the links.

use super::{TALL, Theme, WIDE, panel, psd, signed};
use crate::console::app::App;
use crate::service::api::snapshot::{LinkView, Snapshot};
use crate::units::{DOF_MEANING, DOF_NAMES};
use ratatui::Frame;
use ratatui::layout::{Constraint, Layout, Rect};
use ratatui::text::{Line, Span};
use ratatui::widgets::{Paragraph, Wrap};

pub fn render(frame: &mut Frame, area: Rect, app: &App) {
    let theme = Theme {
        color: app.opts.color,
    };
    let snap = app.snapshot.as_ref();
    let wide = area.width >= WIDE;
    let bottom_h = if area.height >= TALL { 13 } else { 11 };
    let [top, bottom] =
        Layout::vertical([Constraint::Min(6), Constraint::Length(bottom_h)]).areas(area);
    psd_row(frame, top, snap, theme);
    if wide {
        let [e, f, l] = Layout::horizontal([
            Constraint::Percentage(38),
            Constraint::Percentage(32),
            Constraint::Percentage(30),
        ])
        .areas(bottom);
        errors(frame, e, snap, true, theme);
        follower(frame, f, snap, theme);
        links(frame, l, snap, true, theme);
    } else {
        let [e, s] = Layout::horizontal([Constraint::Percentage(50), Constraint::Percentage(50)])
            .areas(bottom);
        errors(frame, e, snap, false, theme);
        state_compact(frame, s, snap, theme);
    }
}

/// The three PSDs side by side.
pub fn psd_row(frame: &mut Frame, area: Rect, snap: Option<&Snapshot>, theme: Theme) {
    let cols = Layout::horizontal([Constraint::Ratio(1, 3); 3]).split(area);
    for (k, col) in cols.iter().enumerate() {
        psd::render(frame, *col, k, snap.and_then(|s| s.psd.as_ref()), theme);
    }
}

/// Why the snapshot has no live errors, in the order an engineer would check.
pub fn why_no_errors(snap: Option<&Snapshot>) -> String {
    let Some(s) = snap else {
        return "no live errors: no snapshot from the service yet".into();
    };
    let io = &s.links.io;
    let Some(p) = s.psd.as_ref().filter(|_| io.state == "up") else {
        let detail = io
            .detail
            .as_deref()
            .map(|d| format!(" ({d})"))
            .unwrap_or_default();
        return format!(
            "no live errors: no frames from the I/O module at {}: link {}{detail}",
            io.peer, io.state
        );
    };
    let dark: Vec<String> = (0..3)
        .filter(|&k| p.spots_um[k].is_none())
        .map(|k| format!("PSD{}", k + 1))
        .collect();
    if !dark.is_empty() {
        return format!(
            "no live errors: no spot on {} (beam blocked, head knocked, or the follower away from the spot)",
            dark.join(", ")
        );
    }
    if !p.valid {
        return format!(
            "no live errors: the newest frame is {:.0} ms old (the I/O module stalls)",
            p.age_ms
        );
    }
    if !s.tracking.valid {
        return "no live errors: PSD2's stitch is not referenced: home the follower (screen 2, h)"
            .into();
    }
    "no live errors yet: the averaging window is filling".into()
}

pub(super) fn errors(
    frame: &mut Frame,
    area: Rect,
    snap: Option<&Snapshot>,
    wide: bool,
    theme: Theme,
) {
    let live = snap.and_then(|s| s.live.as_ref());
    let mut lines = Vec::new();
    match live {
        None => lines.push(Line::styled(why_no_errors(snap), theme.warn())),
        Some(l) => {
            for k in 0..6 {
                let (unit, dec) = if k < 3 { ("µm", 3) } else { ("″", 2) };
                let mut spans = vec![Span::styled(format!("{:<3}", DOF_NAMES[k]), theme.bold())];
                if wide {
                    spans.push(Span::styled(format!("{:<26}", DOF_MEANING[k]), theme.dim()));
                }
                spans.push(Span::raw(format!(
                    "{:>10} ± {:.dec$} {unit}",
                    signed(Some(l.errors[k]), dec),
                    l.sd[k],
                )));
                lines.push(Line::from(spans));
            }
            lines.push(Line::raw(format!(
                "{} frames, travel {:.3} mm",
                l.frames, l.travel_mm
            )));
            lines.push(Line::from(vec![
                Span::raw(match l.nominal_mm {
                    Some(n) => format!("nominal {n:.3} mm"),
                    None => "no nominal: dy undefined".into(),
                }),
                Span::raw(", "),
                if l.zeroed {
                    Span::styled("zeroed", theme.ok())
                } else {
                    Span::styled("not zeroed", theme.warn())
                },
            ]));
        }
    }
    frame.render_widget(
        Paragraph::new(lines)
            .wrap(Wrap { trim: true })
            .block(panel("Six errors")),
        area,
    );
}

fn yes_no(b: bool, yes: &'static str, no: &'static str, theme: Theme) -> Span<'static> {
    if b {
        Span::styled(yes, theme.ok())
    } else {
        Span::styled(no, theme.bad())
    }
}

/// Whether the follower is homed, or how long its homing has been going (a homing after a
/// restart takes up to a minute: the console said only "NOT homed" meanwhile).
pub fn homed_span(
    f: &crate::service::api::snapshot::FollowerView,
    not: &'static str,
    theme: Theme,
) -> Span<'static> {
    match (f.homed, f.busy.as_deref(), f.busy_s) {
        (true, _, _) => Span::styled("homed", theme.ok()),
        (false, Some("home"), Some(s)) => Span::styled(
            format!(
                "homing for {}",
                super::duration(std::time::Duration::from_secs(s.max(0.0) as u64))
            ),
            theme.warn(),
        ),
        (false, _, _) => Span::styled(not, theme.bad()),
    }
}

fn follower_lines(s: &Snapshot, theme: Theme) -> Vec<Line<'static>> {
    let f = &s.follower;
    let t = &s.tracking;
    let mut lines = vec![
        Line::from(vec![
            Span::styled("follower ", theme.bold()),
            Span::raw(format!("node {} ", f.node_id)),
            if f.state == "Operation enabled" {
                Span::styled(f.state.clone(), theme.ok())
            } else {
                Span::styled(
                    if f.state.is_empty() {
                        "unknown".to_string()
                    } else {
                        f.state.clone()
                    },
                    theme.warn(),
                )
            },
        ]),
        Line::from(vec![
            Span::raw(format!(
                "  at {} ",
                f.position_mm
                    .map(|p| format!("{p:.4} mm"))
                    .unwrap_or_else(|| "?".into())
            )),
            homed_span(f, "NOT homed", theme),
            Span::raw(", heartbeat "),
            yes_no(f.heartbeat_ok, "ok", "LOST", theme),
        ]),
    ];
    if let Some(e) = &f.last_emcy {
        lines.push(Line::styled(format!("  EMCY {e}"), theme.warn()));
    }
    lines.push(Line::from(vec![
        Span::styled("tracking ", theme.bold()),
        Span::raw(format!("{} ", t.strategy)),
        yes_no(t.valid, "referenced", "NOT referenced", theme),
        Span::raw(if t.at_rest { ", at rest" } else { ", moving" }),
    ]));
    lines.push(Line::raw(format!(
        "  PSD2 at {:.4} mm ±{:.2} µm",
        t.follower_mm, t.sd_um[0]
    )));
    lines.push(Line::raw(format!("  {} handovers", t.handovers)));
    lines
}

fn follower(frame: &mut Frame, area: Rect, snap: Option<&Snapshot>, theme: Theme) {
    let lines = match snap {
        Some(s) => follower_lines(s, theme),
        None => vec![Line::styled("no snapshot yet", theme.dim())],
    };
    frame.render_widget(
        Paragraph::new(lines).block(panel("Follower and tracking")),
        area,
    );
}

fn link_line(name: &str, l: &LinkView, detailed: bool, theme: Theme) -> Vec<Line<'static>> {
    let state = if l.state.is_empty() { "?" } else { &l.state };
    let style = if l.state == "up" {
        theme.ok()
    } else {
        theme.bad()
    };
    let mut first = vec![
        Span::styled(format!("{name:<4}"), theme.bold()),
        Span::styled(state.to_string(), style),
    ];
    if detailed {
        first.push(Span::raw(format!("  {}", l.peer)));
    }
    let mut lines = vec![Line::from(first)];
    if detailed {
        // A link without request/reply timing (the CAN bus: the rate is its TPDOs) shows none.
        lines.push(Line::raw(
            if l.latency_p50_us == 0.0 && l.latency_p99_us == 0.0 {
                format!("    {:.0}/s", l.rate_hz)
            } else {
                format!(
                    "    {:.0}/s  p50 {:.0} µs  p99 {:.0} µs",
                    l.rate_hz, l.latency_p50_us, l.latency_p99_us
                )
            },
        ));
        lines.push(Line::raw(format!(
            "    {} errors, {} reconnects",
            l.errors, l.reconnects
        )));
    }
    if let Some(d) = &l.detail {
        lines.push(Line::styled(format!("    {d}"), theme.warn()));
    }
    lines
}

fn frames_line(s: &Snapshot) -> Line<'static> {
    match &s.psd {
        Some(p) => Line::raw(format!(
            "frames {:.0}/s, {} invalid, {} late",
            p.rate_hz, p.invalid_frames, p.late_frames
        )),
        None => Line::raw("frames: none yet"),
    }
}

fn links(frame: &mut Frame, area: Rect, snap: Option<&Snapshot>, detailed: bool, theme: Theme) {
    let lines = match snap {
        Some(s) => {
            let mut v = link_line("I/O", &s.links.io, detailed, theme);
            v.extend(link_line("CAN", &s.links.can, detailed, theme));
            v.push(frames_line(s));
            v
        }
        None => vec![Line::styled("no snapshot yet", theme.dim())],
    };
    frame.render_widget(Paragraph::new(lines).block(panel("Links")), area);
}

/// Follower, tracking and links in one panel (80 columns).
fn state_compact(frame: &mut Frame, area: Rect, snap: Option<&Snapshot>, theme: Theme) {
    let lines = match snap {
        Some(s) => {
            let mut v = follower_lines(s, theme);
            let io = &s.links.io;
            let can = &s.links.can;
            v.push(Line::from(vec![
                Span::styled("I/O ", theme.bold()),
                Span::styled(
                    io.state.clone(),
                    if io.state == "up" {
                        theme.ok()
                    } else {
                        theme.bad()
                    },
                ),
                Span::raw(format!(" p99 {:.0} µs  ", io.latency_p99_us)),
                Span::styled("CAN ", theme.bold()),
                Span::styled(
                    can.state.clone(),
                    if can.state == "up" {
                        theme.ok()
                    } else {
                        theme.bad()
                    },
                ),
            ]));
            v.push(frames_line(s));
            v
        }
        None => vec![Line::styled("no snapshot yet", theme.dim())],
    };
    frame.render_widget(Paragraph::new(lines).block(panel("Follower, links")), area);
}

#[cfg(test)]
mod tests {
    use super::why_no_errors;
    use crate::service::api::snapshot::{PsdView, Snapshot};

    #[test]
    fn live_says_why_it_has_no_errors() {
        assert_eq!(
            why_no_errors(None),
            "no live errors: no snapshot from the service yet"
        );
        let mut s = Snapshot::default();
        s.links.io.peer = "192.168.1.20:502".into();
        s.links.io.state = "down".into();
        s.links.io.detail = Some("connection refused".into());
        assert_eq!(
            why_no_errors(Some(&s)),
            "no live errors: no frames from the I/O module at 192.168.1.20:502: link down (connection refused)"
        );
        s.links.io.state = "up".into();
        s.links.io.detail = None;
        s.psd = Some(PsdView {
            spots_um: [Some([0.0; 2]), None, None],
            ..PsdView::default()
        });
        assert!(
            why_no_errors(Some(&s))
                .starts_with("no live errors: no spot on PSD2, PSD3 (beam blocked"),
            "{}",
            why_no_errors(Some(&s))
        );
        s.psd = Some(PsdView {
            spots_um: [Some([0.0; 2]); 3],
            valid: false,
            age_ms: 430.0,
            ..PsdView::default()
        });
        assert_eq!(
            why_no_errors(Some(&s)),
            "no live errors: the newest frame is 430 ms old (the I/O module stalls)"
        );
        s.psd.as_mut().unwrap().valid = true;
        assert!(why_no_errors(Some(&s)).contains("home the follower"));
        s.tracking.valid = true;
        assert!(why_no_errors(Some(&s)).contains("window is filling"));
    }
}
