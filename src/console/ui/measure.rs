//! Measure: the plan (edited in place), start and abort, the run's progress with ETA, the
//! captures per target in cycle order, and a live plot of the captured values so far (the
//! service's `run_result` of the run under way; `e` picks the error).

use super::{TALL, Theme, WIDE, bar, duration, panel};
use crate::console::app::{App, Field, RunProgress};
use crate::run::{Direction, Plan};
use ratatui::Frame;
use ratatui::layout::{Constraint, Layout, Rect};
use ratatui::text::{Line, Span};
use ratatui::widgets::{Paragraph, Wrap};

pub fn render(frame: &mut Frame, area: Rect, app: &App) {
    let theme = Theme {
        color: app.opts.color,
    };
    let wide = area.width >= WIDE;
    let [left, right] = Layout::horizontal([
        Constraint::Length(if wide { 62 } else { 38 }),
        Constraint::Min(20),
    ])
    .areas(area);
    if wide && area.height >= TALL {
        // Room for the live errors beside the plan while the run goes.
        let [p, e] = Layout::vertical([Constraint::Min(15), Constraint::Length(11)]).areas(left);
        plan(frame, p, app, wide, theme);
        super::live::errors(frame, e, app.snapshot.as_ref(), true, theme);
    } else {
        plan(frame, left, app, wide, theme);
    }
    progress(frame, right, app, wide, theme);
}

/// As many numbers as fit in `width` columns after `prefix`, then "…".
fn fitting(prefix: &str, values: &[f64], width: usize) -> String {
    let mut out = prefix.to_string();
    for (i, v) in values.iter().enumerate() {
        let item = format!(" {v:.1}");
        let room = if i + 1 == values.len() { 0 } else { 2 };
        if out.chars().count() + item.len() + room > width {
            out.push_str(" …");
            return out;
        }
        out.push_str(&item);
    }
    out
}

fn plan(frame: &mut Frame, area: Rect, app: &App, wide: bool, theme: Theme) {
    let form = &app.plan;
    let inner_w = area.width.saturating_sub(2) as usize;
    let mut lines = Vec::new();
    for (i, f) in Field::ALL.iter().enumerate() {
        let selected = i == form.selected;
        let value = match (&form.editing, selected) {
            (Some(buf), true) => format!("{buf}▏"),
            _ => f.get(&form.spec),
        };
        let line = Line::from(vec![
            Span::raw(if selected { "▶ " } else { "  " }),
            Span::raw(format!("{:<11}", f.label())),
            Span::styled(
                format!("{value:>10}"),
                if selected {
                    theme.selected()
                } else {
                    theme.bold()
                },
            ),
            Span::styled(format!(" {}", f.unit()), theme.dim()),
        ]);
        lines.push(line);
    }
    match form.checked() {
        Ok(p) => {
            lines.push(Line::styled(
                if wide {
                    format!(
                        "✓ {} captures ({} targets × 2 directions × {} runs)",
                        p.capture_count(),
                        p.targets.len(),
                        p.spec.runs
                    )
                } else {
                    format!("✓ {} captures", p.capture_count())
                },
                theme.ok(),
            ));
            let warnings = if wide {
                p.warnings()
            } else {
                p.warnings_brief()
            };
            for w in warnings {
                lines.push(Line::styled(format!("⚠ {w}"), theme.warn()));
            }
            lines.push(Line::styled(
                fitting("targets (mm):", &p.targets, inner_w),
                theme.dim(),
            ));
        }
        Err(e) => lines.push(Line::styled(format!("✗ {e}"), theme.bad())),
    }
    let hint = if form.editing.is_some() {
        "Enter keeps  Esc drops"
    } else if app.read_only() {
        "read-only (viewer): s, a disabled"
    } else {
        "↑↓ select  Enter edit  s start  e plot"
    };
    lines.push(Line::styled(hint, theme.dim()));
    frame.render_widget(
        Paragraph::new(lines)
            .wrap(Wrap { trim: false })
            .block(panel("Plan (ISO 230-2)")),
        area,
    );
}

fn progress(frame: &mut Frame, area: Rect, app: &App, wide: bool, theme: Theme) {
    let block = panel("Run");
    let inner = block.inner(area);
    frame.render_widget(block, area);
    let Some(r) = &app.run else {
        let mut lines = vec![Line::raw("No run seen yet.")];
        lines.push(Line::styled(
            "Edit the plan on the left, then s to start it.",
            theme.dim(),
        ));
        frame.render_widget(Paragraph::new(lines).wrap(Wrap { trim: true }), inner);
        return;
    };
    let [head, grid] = Layout::vertical([Constraint::Length(5), Constraint::Min(0)]).areas(inner);
    frame.render_widget(
        Paragraph::new(head_lines(r, inner.width, theme)).wrap(Wrap { trim: true }),
        head,
    );
    let lines = match &r.plan {
        Some(p) => target_grid(p, r.captures, wide, theme),
        None => vec![Line::styled(
            "Per-target progress shows for runs started from this console (the plan is known).",
            theme.dim(),
        )],
    };
    let grid_h = (lines.len() as u16).min(grid.height);
    let [grid, plot] =
        Layout::vertical([Constraint::Length(grid_h), Constraint::Min(0)]).areas(grid);
    frame.render_widget(Paragraph::new(lines).wrap(Wrap { trim: false }), grid);
    if plot.height >= 5 {
        match r.live.as_ref().and_then(|l| l.dofs.get(app.live_dof)) {
            Some(d) => super::chart::render(frame, plot, d, None, false, theme),
            None => frame.render_widget(
                Paragraph::new(Line::styled(
                    "live plot: waiting for the captures",
                    theme.dim(),
                )),
                plot,
            ),
        }
    }
}

fn head_lines(r: &RunProgress, width: u16, theme: Theme) -> Vec<Line<'static>> {
    let state_style = match r.state.as_str() {
        "running" => theme.accent(),
        "finished" | "complete" | "completed" => theme.ok(),
        _ => theme.warn(),
    };
    let mut lines = vec![Line::from(vec![
        Span::styled(format!("run {} ", r.run_id), theme.bold()),
        Span::styled(r.state.clone(), state_style),
        Span::raw(match r.missing {
            Some(m) if r.running() => format!(", {m} missing"),
            _ => String::new(),
        }),
    ])];
    lines.push(match r.expected {
        Some(e) => {
            let counts = format!(" {}/{} ({:.0} %)", r.captures, e, r.fraction() * 100.0);
            let w = (width as usize)
                .saturating_sub(counts.chars().count() + 1)
                .min(60);
            Line::from(vec![
                Span::styled(bar(r.fraction(), w), theme.ok()),
                Span::raw(counts),
            ])
        }
        None => Line::raw(format!("{} captures", r.captures)),
    });
    if let (true, Some(why)) = (r.running(), &r.paused) {
        lines.push(Line::styled(format!("PAUSED: {why}"), theme.warn()));
    }
    let machine = r.machine_time();
    lines.push(Line::raw(match (r.running(), r.eta(), machine) {
        (true, Some(eta), Some(m)) => {
            format!("ETA {}; machine time {} so far", duration(eta), duration(m))
        }
        (true, Some(eta), None) => format!(
            "ETA {} (watched for {})",
            duration(eta),
            duration(r.watched())
        ),
        (true, None, Some(m)) => {
            format!(
                "ETA after the next capture; machine time {} so far",
                duration(m)
            )
        }
        (true, None, None) => "ETA after the next capture".into(),
        (false, _, Some(m)) => format!("ended after {} of machine time", duration(m)),
        (false, _, None) => "ended".into(),
    }));
    if let Some(n) = &r.notes {
        lines.push(Line::styled(n.clone(), theme.dim()));
    }
    if let Some(p) = &r.program {
        lines.push(Line::styled(format!("program {p}"), theme.dim()));
    }
    lines
}

/// One row per run and direction, one cell per target, filled in cycle order up to
/// `captures` (make-up passes may fill out of order; the count is exact, the cells are not).
fn target_grid(p: &Plan, captures: usize, wide: bool, theme: Theme) -> Vec<Line<'static>> {
    let mut lines = vec![Line::styled("captures in cycle order", theme.dim())];
    if wide {
        let header: String = p.targets.iter().map(|t| format!("{t:>7.1}")).collect();
        lines.push(Line::styled(format!("{:<9}{header}", "mm"), theme.dim()));
    }
    let mut k = 0usize;
    for run in 1..=p.spec.runs {
        for dir in [Direction::Up, Direction::Down] {
            let arrow = if dir == Direction::Up { "↑" } else { "↓" };
            let mut spans = vec![Span::raw(format!("run {run:<2} {arrow} "))];
            let n = p.targets.len();
            let mut cells = vec![false; n];
            for i in 0..n {
                let idx = if dir == Direction::Up { i } else { n - 1 - i };
                cells[idx] = k < captures;
                k += 1;
            }
            for done in cells {
                let cell = if wide {
                    if done { "      ■" } else { "      □" }
                } else if done {
                    "■"
                } else {
                    "□"
                };
                spans.push(Span::styled(
                    cell,
                    if done { theme.ok() } else { theme.dim() },
                ));
            }
            lines.push(Line::from(spans));
        }
    }
    lines
}
