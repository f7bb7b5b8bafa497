//! Machine: the whole machine's commissioning plan (`machine`): each set-up with its state and
//! run, the selected set-up's steps at the machine, the run picker while attaching, the
//! squarenesses measured so far and the 21-error model's predicted volumetric error.

use super::{Theme, date_utc, panel};
use crate::console::app::App;
use ratatui::Frame;
use ratatui::layout::{Constraint, Layout, Rect};
use ratatui::text::Line;
use ratatui::widgets::{Paragraph, Wrap};

pub fn render(frame: &mut Frame, area: Rect, app: &App) {
    let theme = Theme {
        color: app.opts.color,
    };
    let m = &app.machine;
    let Some(v) = &m.view else {
        let text = match &m.error {
            Some(e) => vec![
                Line::styled(e.clone(), theme.warn()),
                Line::raw(""),
                Line::raw(
                    "Store the machine's record: n and its path on the service's host, or axiscomp machine new FILE, then r.",
                ),
            ],
            None => vec![Line::styled("asking the service…", theme.dim())],
        };
        frame.render_widget(
            Paragraph::new(text)
                .wrap(Wrap { trim: true })
                .block(panel("Machine")),
            area,
        );
        return;
    };
    let [plan, steps, fit] = Layout::vertical([
        Constraint::Length(v.setups.len() as u16 + 3),
        Constraint::Min(6),
        Constraint::Length(6),
    ])
    .areas(area);
    let mut lines = vec![Line::styled(
        format!(
            "{}, X {:.0} × Y {:.0} × Z {:.0} mm",
            v.chain, v.travel_mm[0], v.travel_mm[1], v.travel_mm[2]
        ),
        theme.dim(),
    )];
    for (i, s) in v.setups.iter().enumerate() {
        let state = match (s.run_id, s.state.as_str()) {
            (Some(r), _) => format!("✓ measured by run {r}"),
            (None, "next") => "▶ next".into(),
            (None, other) => format!("  {other}"),
        };
        let line = format!("{:<52} {state}", s.title);
        lines.push(if i == m.selected {
            Line::styled(line, theme.selected())
        } else if s.state == "next" {
            Line::styled(line, theme.accent())
        } else {
            Line::raw(line)
        });
    }
    frame.render_widget(
        Paragraph::new(lines).block(panel(&format!("Machine {}: {}", v.id, v.name))),
        plan,
    );
    if let Some(pick) = m.picking {
        let runs = m.runs(&app.results);
        let mut lines = vec![Line::styled(
            format!(
                "Which run measured set-up {}? ↑/↓ pick, Enter attaches, Esc cancels",
                m.next().map_or(String::new(), |s| s.title.clone())
            ),
            theme.accent(),
        )];
        if !app.results.listed {
            lines.push(Line::styled("asking the service…", theme.dim()));
        } else if runs.is_empty() {
            lines.push(Line::styled(
                "no finished run of this axis: measure it on screen 4 (Measure)",
                theme.dim(),
            ));
        }
        for (i, r) in runs.iter().enumerate() {
            let line = format!(
                "run {:<4} {} {:>4} captures  {}  {}",
                r.id,
                r.axis,
                r.captures,
                date_utc(r.created_us),
                r.notes
            );
            lines.push(if i == pick {
                Line::styled(line, theme.selected())
            } else {
                Line::raw(line)
            });
        }
        frame.render_widget(Paragraph::new(lines).block(panel("Attach")), steps);
    } else if let Some(s) = v.setups.get(m.selected) {
        let mut lines: Vec<Line> = s
            .steps
            .iter()
            .enumerate()
            .map(|(i, step)| Line::raw(format!("{}. {step}", i + 1)))
            .collect();
        lines.push(Line::raw(""));
        lines.push(Line::styled(
            match (s.run_id, s.state.as_str()) {
                (Some(r), _) => format!("Measured by run {r}."),
                (None, "next") => format!(
                    "Plan: {} targets, {} bidirectional runs over {:.0} mm: p puts it on Measure (4) to start; then a attaches the run.",
                    s.plan.targets,
                    s.plan.runs,
                    s.plan.end_mm - s.plan.start_mm
                ),
                _ => "After the set-ups before it.".into(),
            },
            theme.dim(),
        ));
        frame.render_widget(
            Paragraph::new(lines)
                .wrap(Wrap { trim: true })
                .block(panel(&format!("Set-up {}", s.title))),
            steps,
        );
    }
    let mut lines: Vec<Line> = v
        .squareness
        .iter()
        .map(|q| {
            Line::raw(format!(
                "{} ({}) {:+.2}″ ± {:.2}″ (k = 2), square {}",
                q.name, q.pair, q.value_arcsec, q.expanded_arcsec, q.square
            ))
        })
        .collect();
    match (&v.predicted, &v.no_model) {
        (Some(p), _) => lines.push(Line::styled(
            format!(
                "Model: the tool point off by {:.1} µm largest, {:.1} µm RMS uncompensated ({} points); axiscomp machine export --id {} writes the controls' files",
                p.max_um, p.rms_um, p.points, v.id
            ),
            theme.accent(),
        )),
        (None, Some(why)) => lines.push(Line::styled(why.clone(), theme.dim())),
        (None, None) => {}
    }
    frame.render_widget(
        Paragraph::new(lines)
            .wrap(Wrap { trim: true })
            .block(panel("Squareness and model")),
        fit,
    );
}
