//! The Markdown report: the same content as the HTML one, with the PNGs referenced by relative
//! path (they are written beside it). Every text from the input is escaped (`text::md`).

use super::RunReport;
use super::text::{self, md};
use std::fmt::Write;

/// A pipe table; the columns in `right` are right-aligned (numbers).
fn table(out: &mut String, headings: &[String], rows: &[Vec<String>], right: &[usize]) {
    out.push('|');
    for h in headings {
        let _ = write!(out, " {} |", md(h));
    }
    out.push_str("\n|");
    for i in 0..headings.len() {
        out.push_str(if right.contains(&i) { "---:|" } else { "---|" });
    }
    out.push('\n');
    for row in rows {
        out.push('|');
        for cell in row {
            let _ = write!(out, " {} |", md(cell));
        }
        out.push('\n');
    }
    out.push('\n');
}

fn kv(out: &mut String, rows: &[(impl AsRef<str>, String)]) {
    let rows: Vec<Vec<String>> = rows
        .iter()
        .map(|(k, v)| vec![k.as_ref().to_string(), v.clone()])
        .collect();
    table(out, &["Item".into(), "Value".into()], &rows, &[]);
}

/// Render the report.
pub fn render(r: &RunReport) -> String {
    let m = &r.meta;
    let mut out = String::new();
    let _ = writeln!(out, "# {}\n", md(&text::heading(m)));

    out.push_str("## Run\n\n");
    kv(&mut out, &text::meta_rows(m));
    if !m.plan.is_empty() {
        out.push_str("## Plan\n\n");
        kv(&mut out, &m.plan);
    }
    if !m.config.is_empty() {
        out.push_str("## Configuration\n\n");
        kv(&mut out, &m.config);
    }
    if !m.notes.trim().is_empty() {
        out.push_str("## Notes\n\n");
        for line in m.notes.trim().lines() {
            let _ = writeln!(out, "> {}  ", md(line.trim_end()));
        }
        out.push('\n');
    }

    if !r.dofs.is_empty() {
        out.push_str("## Overview\n\n");
        let _ = writeln!(out, "![{}]({})\n", md(&text::six_title(m)), text::SIX_PNG);
    }
    for d in &r.dofs {
        let title = d.dof.title();
        let _ = writeln!(out, "## {}\n", md(&title));
        let _ = writeln!(
            out,
            "![{}: mean per direction with ±2s band]({})\n",
            md(&title),
            text::dof_file(d.dof, "png")
        );
        if !d.figures.is_empty() {
            out.push_str("### Figures\n\n");
            let rows: Vec<Vec<String>> = d
                .figures
                .iter()
                .map(|f| vec![f.name.clone(), text::fixed(f.value, 3), f.unit.clone()])
                .collect();
            table(
                &mut out,
                &["Figure".into(), "Value".into(), "Unit".into()],
                &rows,
                &[1],
            );
        }
        if let Some(b) = &d.budget {
            out.push_str("### Uncertainty budget (ISO/TR 230-9)\n\n");
            let rows: Vec<Vec<String>> = text::budget_rows(d.dof, b)
                .into_iter()
                .map(|r| r.to_vec())
                .collect();
            table(&mut out, &text::budget_headings(d.dof), &rows, &[2]);
            if !b.points.is_empty() {
                let heads = text::budget_point_headings(d.dof, b);
                out.push_str("#### Per point: what each term puts into U\n\n");
                let right: Vec<usize> = (0..heads.len()).filter(|&j| j != 1).collect();
                table(&mut out, &heads, &text::budget_point_rows(b), &right);
            }
        }
        if !d.series.is_empty() {
            out.push_str("### Points\n\n");
            let rows: Vec<Vec<String>> = text::point_rows(d.dof, &d.series, d.budget.as_ref())
                .into_iter()
                .map(|p| {
                    let mut row = vec![
                        p.position,
                        p.direction.to_string(),
                        p.n,
                        p.mean,
                        p.s,
                        p.two_s,
                        p.u,
                    ];
                    row.extend(p.expanded);
                    row
                })
                .collect();
            table(
                &mut out,
                &text::point_headings(d.dof, d.budget.as_ref().map(|b| b.k)),
                &rows,
                &[0, 2, 3, 4, 5, 6, 7],
            );
        }
    }
    for c in &r.comparisons {
        let title = format!("{}: {} vs {}", c.dof.title(), c.before_label, c.after_label);
        let _ = writeln!(out, "## {}\n", md(&title));
        let _ = writeln!(
            out,
            "![{}]({})\n",
            md(&title),
            text::comparison_file(c.dof, "png")
        );
    }

    out.push_str("## Environment\n\n");
    if let Some(span) = text::env_span(&r.environment) {
        let _ = writeln!(out, "Samples from {}.\n", md(&span));
    }
    let rows: Vec<Vec<String>> = text::env_rows(&r.environment)
        .into_iter()
        .map(|row| row.to_vec())
        .collect();
    let headings: Vec<String> = text::ENV_HEADINGS.iter().map(|h| h.to_string()).collect();
    table(&mut out, &headings, &rows, &[1, 2, 3, 4]);
    // One trailing newline.
    while out.ends_with("\n\n") {
        out.pop();
    }
    out
}
