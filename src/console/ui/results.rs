//! Results: the stored runs, the six errors of one run per approach direction as charts, its
//! ISO 230-2 / 230-1 figures, and a before/after comparison with a second run. Everything is
//! the service's evaluation (`runs`, `run_result`); nothing is computed here.

use super::{TALL, Theme, WIDE, chart, date_utc, panel};
use crate::console::app::{App, ResultsView};
use crate::service::results::{DofView, RunResult};
use ratatui::Frame;
use ratatui::layout::{Constraint, Layout, Rect};
use ratatui::text::{Line, Span};
use ratatui::widgets::{Paragraph, Wrap};

pub fn render(frame: &mut Frame, area: Rect, app: &App) {
    let theme = Theme {
        color: app.opts.color,
    };
    let r = &app.results;
    if area.width >= WIDE {
        let [left, right] =
            Layout::horizontal([Constraint::Length(52), Constraint::Min(20)]).areas(area);
        let list_h = (r.runs.len().clamp(1, 8) + 3) as u16;
        let [list, figs] =
            Layout::vertical([Constraint::Length(list_h), Constraint::Min(3)]).areas(left);
        runs(frame, list, r, true, theme);
        figures(frame, figs, r, None, theme);
        match &r.shown {
            Some(shown) => charts(frame, right, shown, r, area.height >= TALL, theme),
            None => nothing_shown(frame, right, r, theme),
        }
    } else {
        let [left, right] =
            Layout::horizontal([Constraint::Min(30), Constraint::Length(38)]).areas(area);
        let list_h = (r.runs.len().clamp(1, 4) + 3) as u16;
        let [list, figs] =
            Layout::vertical([Constraint::Length(list_h), Constraint::Min(3)]).areas(right);
        runs(frame, list, r, false, theme);
        figures(frame, figs, r, Some(r.dof), theme);
        match &r.shown {
            Some(shown) => {
                let d = &shown.dofs.get(r.dof);
                let before = r.before.as_ref().and_then(|b| b.dofs.get(r.dof));
                match d {
                    Some(d) => chart::render(frame, left, d, before, true, theme),
                    None => nothing_shown(frame, left, r, theme),
                }
            }
            None => nothing_shown(frame, left, r, theme),
        }
    }
}

fn nothing_shown(frame: &mut Frame, area: Rect, r: &ResultsView, theme: Theme) {
    let mut lines = vec![Line::raw(if r.runs.is_empty() && r.listed {
        "No stored runs yet: measure one on screen 4."
    } else {
        "No run shown: ↑/↓ pick a run, Enter shows it."
    })];
    if let Some(e) = &r.error {
        lines.push(Line::styled(e.clone(), theme.bad()));
    }
    frame.render_widget(
        Paragraph::new(lines)
            .wrap(Wrap { trim: true })
            .block(panel("Results")),
        area,
    );
}

/// The stored runs, the highlighted one marked, the shown and compared ones named.
fn runs(frame: &mut Frame, area: Rect, r: &ResultsView, wide: bool, theme: Theme) {
    let shown = r.shown.as_ref().map(|s| s.run.id);
    let before = r.before.as_ref().map(|s| s.run.id);
    let mut lines = Vec::new();
    if !r.listed {
        lines.push(Line::styled("asking the service…", theme.dim()));
    } else if r.runs.is_empty() {
        lines.push(Line::styled("no stored runs", theme.dim()));
    }
    let rows = (area.height as usize).saturating_sub(2).max(1);
    // Keep the highlighted run in view.
    let first = r.selected.saturating_sub(rows.saturating_sub(1));
    for (i, run) in r.runs.iter().enumerate().skip(first).take(rows) {
        let mark = if Some(run.id) == shown {
            "▶"
        } else if Some(run.id) == before {
            "b"
        } else {
            " "
        };
        // The date, so a run is found years later (issue 15), at 80 columns too.
        let text = if wide {
            format!(
                "{mark} run {:<3} {} {:<8} {:>3} captures {}",
                run.id,
                run.axis,
                run.state,
                run.captures,
                date_utc(run.created_us)
            )
        } else {
            format!(
                "{mark}{:>3} {} {:<8} {:>3} {}",
                run.id,
                run.axis,
                run.state,
                run.captures,
                date_utc(run.created_us)
            )
        };
        let style = if i == r.selected {
            theme.selected()
        } else if run.state == "finished" {
            ratatui::style::Style::new()
        } else {
            theme.dim()
        };
        lines.push(Line::styled(text, style));
    }
    let title = if wide {
        "Stored runs (↑↓ Enter show, b compare, t trends)"
    } else {
        "Runs (Enter, b, t)"
    };
    frame.render_widget(Paragraph::new(lines).block(panel(title)), area);
}

/// Display columns of `s` (a combining mark, as in B̄, takes none).
fn width(s: &str) -> usize {
    Span::raw(s).width()
}

/// `name` in exactly `w` columns: padded, or cut with "…".
fn cut(name: &str, w: usize) -> String {
    let mut out = String::new();
    let mut used = 0;
    if width(name) > w {
        for c in name.chars() {
            let cw = width(c.encode_utf8(&mut [0; 4]));
            if used + cw + 1 > w {
                break;
            }
            out.push(c);
            used += cw;
        }
        out.push('…');
        used += 1;
    } else {
        out.push_str(name);
        used = width(name);
    }
    out.push_str(&" ".repeat(w.saturating_sub(used)));
    out
}

/// Short names of the service's figures, for narrow columns.
fn short(name: &str) -> Option<&'static str> {
    Some(match name {
        "straightness (least squares)" => "straight LS",
        "straightness (end points)" => "straight EP",
        "slope (beam alignment)" => "slope",
        "A (accuracy)" => "A accuracy",
        "E (systematic)" => "E systematic",
        "M (mean)" => "M mean",
        "R (repeatability)" => "R repeatab.",
        "B (reversal)" => "B reversal",
        "B̄ (mean reversal)" => "B̄ mean rev.",
        "max − min (mean)" => "range mean",
        "max − min (+)" => "range +",
        "max − min (−)" => "range −",
        _ => return None,
    })
}

/// The name in `w` columns: whole, or (`short`) its short form; cut if still too long.
fn fit(name: &str, w: usize, short_names: bool) -> String {
    let n = if short_names {
        short(name).unwrap_or(name)
    } else {
        name
    };
    cut(n, w)
}

fn figure_lines(
    d: &DofView,
    before: Option<&DofView>,
    width: usize,
    theme: Theme,
) -> Vec<Line<'static>> {
    let mut lines = Vec::new();
    let cols = if before.is_some() { 2 } else { 1 };
    // Narrow: arcsec as ″, values in 8 columns.
    let narrow = width < 48;
    let vw = if narrow { 8 } else { 9 };
    let unit_w = if narrow { 5 } else { 7 };
    let name_w = width.saturating_sub(2 + cols * vw + unit_w).max(6);
    // One naming for the whole list: short names as soon as one full name does not fit.
    let short_names = d.figures.iter().any(|f| self::width(&f.name) > name_w);
    for f in &d.figures {
        let mut spans = vec![Span::raw(format!(
            "  {}",
            fit(&f.name, name_w, short_names)
        ))];
        if let Some(b) = before {
            let v = b.figures.iter().find(|g| g.name == f.name).map(|g| g.value);
            spans.push(Span::styled(
                match v {
                    Some(v) => format!("{v:>vw$.2}"),
                    None => format!("{:>vw$}", "—"),
                },
                theme.dim(),
            ));
        }
        spans.push(Span::styled(format!("{:>vw$.2}", f.value), theme.bold()));
        let unit = if narrow && f.unit == "arcsec" {
            "″"
        } else {
            f.unit.as_str()
        };
        spans.push(Span::styled(format!(" {unit}"), theme.dim()));
        lines.push(Line::from(spans));
    }
    lines
}

/// The figures: of every error (wide), or of error `only`.
fn figures(frame: &mut Frame, area: Rect, r: &ResultsView, only: Option<usize>, theme: Theme) {
    let width = area.width.saturating_sub(2) as usize;
    let mut lines = Vec::new();
    match &r.shown {
        None => lines.push(Line::styled("no run shown", theme.dim())),
        Some(shown) => {
            lines.push(heading(shown, r.before.as_ref(), theme));
            if let Some(why) = &shown.incomplete {
                lines.push(Line::styled(why.clone(), theme.warn()));
            }
            for (k, d) in shown.dofs.iter().enumerate() {
                if only.is_some_and(|o| o != k) {
                    continue;
                }
                let before = r.before.as_ref().and_then(|b| b.dofs.get(k));
                lines.push(Line::from(vec![
                    Span::styled(d.name.clone(), theme.accent()),
                    Span::raw(format!(" {}", d.meaning)),
                ]));
                lines.extend(figure_lines(d, before, width, theme));
            }
        }
    }
    let title = if only.is_some() {
        "Figures (←→ error)"
    } else {
        "ISO 230-2 / 230-1 figures"
    };
    frame.render_widget(
        Paragraph::new(lines)
            .wrap(Wrap { trim: false })
            .block(panel(title)),
        area,
    );
}

/// `run 2 X finished, 20 captures` and, when comparing, the column heads.
fn heading(shown: &RunResult, before: Option<&RunResult>, theme: Theme) -> Line<'static> {
    let mut spans = vec![Span::styled(
        format!(
            "run {} {} {}, {} captures",
            shown.run.id, shown.run.axis, shown.run.state, shown.run.captures
        ),
        theme.bold(),
    )];
    if let Some(b) = before {
        spans.push(Span::styled(
            format!("; before: run {}", b.run.id),
            theme.dim(),
        ));
    }
    Line::from(spans)
}

/// The six charts in a grid (2×3 when tall, else 3×2), the selected error marked.
fn charts(
    frame: &mut Frame,
    area: Rect,
    shown: &RunResult,
    r: &ResultsView,
    tall: bool,
    theme: Theme,
) {
    let (cols, rows) = if tall { (2, 3) } else { (3, 2) };
    let row_areas = Layout::vertical(vec![Constraint::Ratio(1, rows); rows as usize]).split(area);
    for (i, row) in row_areas.iter().enumerate() {
        let cells = Layout::horizontal(vec![Constraint::Ratio(1, cols); cols as usize]).split(*row);
        for (j, cell) in cells.iter().enumerate() {
            let k = i * cols as usize + j;
            if let Some(d) = shown.dofs.get(k) {
                let before = r.before.as_ref().and_then(|b| b.dofs.get(k));
                chart::render(frame, *cell, d, before, k == r.dof, theme);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_fill_their_columns_whatever_the_glyphs() {
        assert_eq!(cut("B̄ (mean reversal)", 20), "B̄ (mean reversal)   ");
        assert_eq!(width(&cut("B̄ (mean reversal)", 20)), 20);
        assert_eq!(cut("straightness (least squares)", 10), "straightn…");
        assert_eq!(fit("R (repeatability)", 13, true), "R repeatab.  ");
        assert_eq!(fit("R (repeatability)", 20, false), "R (repeatability)   ");
        // An unknown name has no short form: cut.
        assert_eq!(fit("something else entirely", 8, true), "somethi…");
    }
}
