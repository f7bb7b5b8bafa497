//! Calibrate: the calibration in use and the one waiting (`calibration`), fitting a pose set on
//! the service's host (`calibration_fit`), and what to judge it by — the residual RMS per
//! reading channel against the noise, rank and condition number, the hold-out RMS per DOF, the
//! model fit — before accepting or rejecting it. Every number is the service's.
//! A hexapod run (`hexapod_status`) shows as it goes: pose i of N, machine time, time left,
//! the controller's error in its words, then the hold-out against the Cramér–Rao bound.

use super::{Theme, WIDE, panel};
use crate::console::app::{App, CalSummary, HexapodView};
use ratatui::Frame;
use ratatui::layout::{Constraint, Layout, Rect};
use ratatui::text::{Line, Span};
use ratatui::widgets::{Paragraph, Wrap};

const CHANNELS: [&str; 6] = ["X1", "Y1", "X2", "Y2", "X3", "Y3"];
const DOFS: [&str; 6] = ["dx µm", "dy µm", "dz µm", "ex ″", "ey ″", "ez ″"];

pub fn render(frame: &mut Frame, area: Rect, app: &App) {
    let theme = Theme {
        color: app.opts.color,
    };
    let c = &app.calibrate;
    let wide = area.width >= WIDE;
    // Two borders, the state line, where (two rows: paths are long), the keys; an error
    // (two rows) and the judgement (three) when there are.
    let hex_rows = match &c.hexapod {
        Some(h) if h.state != "idle" => {
            6 + if h.error.is_some() { 2 } else { 0 } + if h.ratio.is_some() { 3 } else { 0 }
        }
        _ => 3,
    };
    let [top, hex, rest] = Layout::vertical([
        Constraint::Length(if wide { 7 } else { 6 }),
        Constraint::Length(hex_rows),
        Constraint::Min(6),
    ])
    .areas(area);
    state(frame, top, app, wide, theme);
    hexapod(frame, hex, c.hexapod.as_ref(), wide, theme);
    match &c.pending {
        Some(p) => judge(frame, rest, p, wide, theme),
        None => {
            let mut lines = vec![Line::raw(if c.fitting {
                "fitting… (the model fit takes up to a few seconds)"
            } else {
                "No calibration waiting. f fits a pose set: a CSV on the service's host, as \
                 `axiscomp calibrate simulate` writes it or a hexapod run exported so."
            })];
            if let Some(a) = &c.active {
                lines.push(Line::raw(""));
                lines.push(Line::styled("The calibration in use:", theme.dim()));
                lines.extend(figures(a, wide, theme));
            }
            frame.render_widget(
                Paragraph::new(lines)
                    .wrap(Wrap { trim: false })
                    .block(panel("Pending")),
                rest,
            );
        }
    }
}

fn describe(s: &CalSummary) -> String {
    format!(
        "{}, {} decoupling, {} poses ({} fit, {} hold-out), travel {:.0}…{:.0} mm",
        s.source, s.decoupling, s.poses, s.fit_poses, s.holdout_poses, s.travel_mm.0, s.travel_mm.1
    )
}

fn state(frame: &mut Frame, area: Rect, app: &App, _wide: bool, theme: Theme) {
    let c = &app.calibrate;
    let mut lines = Vec::new();
    if !c.loaded {
        lines.push(Line::styled("asking the service…", theme.dim()));
    }
    let in_use = match (&c.active, c.active_id) {
        (Some(a), Some(id)) => format!("stored calibration {id}: {}", describe(a)),
        (Some(a), None) => format!("configured: {}", describe(a)),
        (None, _) if c.loaded => "the nominal layout (no calibration)".into(),
        (None, _) => "—".into(),
    };
    lines.push(Line::from(vec![
        Span::styled("in use   ", theme.bold()),
        Span::raw(in_use),
    ]));
    let pending = match (&c.pending, c.fitting) {
        (_, true) => Span::styled(
            format!(
                "fitting {}…",
                c.fit_path.clone().unwrap_or_else(|| "a pose set".into())
            ),
            theme.accent(),
        ),
        (Some(p), false) => Span::styled(describe(p), theme.warn()),
        (None, false) => Span::styled("none", theme.dim()),
    };
    lines.push(Line::from(vec![
        Span::styled("pending  ", theme.bold()),
        pending,
    ]));
    if let Some(e) = &c.error {
        lines.push(Line::styled(e.clone(), theme.bad()));
    }
    lines.push(Line::styled(
        if app.read_only() {
            "read-only (viewer): fitting, accepting and rejecting need the operator role"
        } else {
            "h hexapod run  f fit a pose set  a accept  x reject  r reload  ? help"
        },
        theme.dim(),
    ));
    frame.render_widget(
        Paragraph::new(lines)
            .wrap(Wrap { trim: true })
            .block(panel("Calibration")),
        area,
    );
}

/// Seconds as the console writes durations.
fn duration_words(s: f64) -> String {
    super::duration(std::time::Duration::from_secs_f64(s.max(0.0)))
}

fn hexapod(frame: &mut Frame, area: Rect, h: Option<&HexapodView>, wide: bool, theme: Theme) {
    let mut lines = Vec::new();
    match h {
        None => lines.push(Line::styled("asking the service…", theme.dim())),
        Some(h) if h.state == "idle" => lines.push(Line::styled(
            "No run: h calibrates with the hexapod (plan, fit, hold-out, accept).",
            theme.dim(),
        )),
        Some(h) => {
            let pct = if h.total > 0 {
                100.0 * h.done as f64 / h.total as f64
            } else {
                0.0
            };
            let state_style = match h.state.as_str() {
                "failed" => theme.bad(),
                "stopped" | "stopping" => theme.warn(),
                "done" => theme.ok(),
                _ => theme.accent(),
            };
            let mut first = vec![
                Span::styled(format!("{:<9}", h.state), state_style),
                Span::raw(format!(
                    "pose {} of {} ({pct:.0} %)  machine time {}",
                    h.done,
                    h.total,
                    duration_words(h.machine_s)
                )),
            ];
            match (h.state.as_str(), h.eta_s) {
                ("running", Some(eta)) => {
                    first.push(Span::raw(format!("  remaining ~{}", duration_words(eta))))
                }
                ("fitting", _) => first.push(Span::raw(format!(
                    "  fitting (iteration {})",
                    h.fit_iteration
                ))),
                _ => {}
            }
            lines.push(Line::from(first));
            lines.push(Line::styled(
                format!(
                    "{}  plan {}  in {}{}",
                    if h.controller.is_empty() {
                        "hexapod"
                    } else {
                        &h.controller
                    },
                    if h.plan.is_empty() {
                        "default"
                    } else {
                        &h.plan
                    },
                    h.out,
                    if h.reconnects > 0 {
                        format!("  {} link reconnects", h.reconnects)
                    } else {
                        String::new()
                    }
                ),
                theme.dim(),
            ));
            if let Some(e) = &h.error {
                lines.push(Line::styled(e.clone(), theme.bad()));
            }
            if let (Some(r), Some(rms), Some(b)) = (&h.ratio, &h.holdout_rms, &h.crlb) {
                let w = if wide { 10 } else { 7 };
                let worst = r.iter().cloned().fold(0.0, f64::max);
                lines.push(Line::raw(row("hold-out", rms, w)));
                lines.push(Line::raw(row("C–R bound", b, w)));
                lines.push(Line::styled(
                    format!(
                        "{}  worst {worst:.2}× the bound ({} poses, {} frames held out)",
                        row("ratio", r, w),
                        h.holdout_poses,
                        h.holdout_frames
                    ),
                    if worst <= 1.2 {
                        theme.ok()
                    } else {
                        theme.warn()
                    },
                ));
            }
            let keys = match h.state.as_str() {
                "running" => "s stop",
                "stopped" | "failed" => "u resume  h start another",
                _ => "h start another",
            };
            lines.push(Line::styled(keys, theme.dim()));
        }
    }
    frame.render_widget(
        Paragraph::new(lines)
            .wrap(Wrap { trim: true })
            .block(panel("Hexapod run")),
        area,
    );
}

fn row(label: &str, v: &[f64; 6], w: usize) -> String {
    let mut s = format!("{label:<10}");
    for x in v {
        s.push_str(&format!("{x:>w$.2}"));
    }
    s
}

/// The figures to judge a calibration by.
fn figures(p: &CalSummary, wide: bool, theme: Theme) -> Vec<Line<'static>> {
    let w = if wide { 10 } else { 7 };
    let head = |names: &[&str; 6]| {
        let mut s = format!("{:<10}", "");
        for n in names {
            s.push_str(&format!("{n:>w$}"));
        }
        Line::styled(s, theme.dim())
    };
    let mut lines = vec![
        Line::styled("residual RMS per reading (µm)", theme.bold()),
        head(&CHANNELS),
        Line::raw(row("noise", &p.noise_um, w)),
        Line::raw(row("linear", &p.linear_residual_um, w)),
    ];
    if let Some(m) = &p.model_residual_um {
        // The model's residuals should be at the noise.
        let at_noise = m
            .iter()
            .zip(&p.noise_um)
            .all(|(r, n)| *r <= 2.0 * n.max(1e-9));
        lines.push(Line::styled(
            row("model", m, w),
            if at_noise { theme.ok() } else { theme.warn() },
        ));
    }
    let cond_style = if p.rank < 7 || p.condition_number > 1e6 {
        theme.warn()
    } else {
        ratatui::style::Style::new()
    };
    lines.push(Line::styled(
        format!(
            "rank {} of 7, condition number {:.3e}",
            p.rank, p.condition_number
        ),
        cond_style,
    ));
    if p.linear_holdout.is_some() || p.model_holdout.is_some() {
        lines.push(Line::styled("hold-out RMS per DOF", theme.bold()));
        lines.push(head(&DOFS));
        if let Some(h) = &p.linear_holdout {
            lines.push(Line::raw(row("linear", h, w)));
        }
        if let Some(h) = &p.model_holdout {
            lines.push(Line::raw(row("model", h, w)));
        }
    }
    match (p.model_iterations, p.model_converged, p.model_params) {
        (Some(it), conv, params) => {
            let conv = conv.unwrap_or(false);
            lines.push(Line::styled(
                format!(
                    "model fit: {it} iterations, {}{}",
                    if conv { "converged" } else { "NOT converged" },
                    params
                        .map(|(f, g)| format!(", {f} parameters, {g} well determined"))
                        .unwrap_or_default()
                ),
                if conv {
                    ratatui::style::Style::new()
                } else {
                    theme.bad()
                },
            ));
        }
        (None, ..) => lines.push(Line::styled("no model fit: linear decoupling", theme.dim())),
    }
    lines
}

fn judge(frame: &mut Frame, area: Rect, p: &CalSummary, wide: bool, theme: Theme) {
    let mut lines = figures(p, wide, theme);
    if let Some(h) = p.here {
        lines.push(Line::raw(format!(
            "reads here: dx {:+.1} dy {:+.1} dz {:+.1} µm, ex {:+.1} ey {:+.1} ez {:+.1}″",
            h[0], h[1], h[2], h[3], h[4], h[5]
        )));
    }
    if p.concerns.is_empty() {
        lines.push(Line::styled(
            "a accepts it (stores it, decouples with it, clears the zero); x rejects it",
            theme.accent(),
        ));
    } else {
        lines.push(Line::styled("IMPLAUSIBLE for this head:", theme.bad()));
        lines.extend(
            p.concerns
                .iter()
                .map(|c| Line::styled(c.clone(), theme.warn())),
        );
        lines.push(Line::styled(
            "x rejects it; A accepts it anyway (the override, logged)",
            theme.accent(),
        ));
    }
    frame.render_widget(
        Paragraph::new(lines)
            .wrap(Wrap { trim: false })
            .block(panel(&format!("Pending: {}", p.source))),
        area,
    );
}
