//! The HTML report: one self-contained file (inline SVG and style, no scripts, no external
//! resources). Every text from the input is escaped. Void elements are written self-closed so
//! the file is also well-formed XML.

use super::text::{self, html};
use super::{Dof, RunReport};
use std::fmt::Write;

/// The SVG plots, rendered once and shared with the files written beside the report.
#[derive(Default)]
pub struct Svgs {
    pub six: Option<String>,
    /// In the order of `RunReport::dofs`.
    pub dofs: Vec<String>,
    /// In the order of `RunReport::comparisons`.
    pub comparisons: Vec<String>,
}

const STYLE: &str = "body { font-family: 'DejaVu Sans', sans-serif; margin: 2em; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em 0; }
th, td { border: 1px solid #bbb; padding: 0.2em 0.6em; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
figure { margin: 1em 0; }
svg { max-width: 100%; height: auto; }
.notes { white-space: pre-wrap; }";

/// A two-column table of (item, value).
fn kv_table(out: &mut String, rows: &[(impl AsRef<str>, String)]) {
    out.push_str("<table>\n");
    for (k, v) in rows {
        let _ = writeln!(
            out,
            "<tr><th>{}</th><td>{}</td></tr>",
            html(k.as_ref()),
            html(v)
        );
    }
    out.push_str("</table>\n");
}

fn grid(out: &mut String, headings: &[String], rows: &[Vec<(String, bool)>]) {
    out.push_str("<table>\n<tr>");
    for h in headings {
        let _ = write!(out, "<th>{}</th>", html(h));
    }
    out.push_str("</tr>\n");
    for row in rows {
        out.push_str("<tr>");
        for (cell, numeric) in row {
            if *numeric {
                let _ = write!(out, "<td class=\"num\">{}</td>", html(cell));
            } else {
                let _ = write!(out, "<td>{}</td>", html(cell));
            }
        }
        out.push_str("</tr>\n");
    }
    out.push_str("</table>\n");
}

fn figure(out: &mut String, svg: &str, caption: &str) {
    let _ = write!(
        out,
        "<figure>\n{}\n<figcaption>{}</figcaption>\n</figure>\n",
        svg.trim(),
        html(caption)
    );
}

fn section_id(dof: Dof) -> &'static str {
    dof.name()
}

/// Render the report.
pub fn render(r: &RunReport, svgs: &Svgs) -> String {
    let m = &r.meta;
    let heading = text::heading(m);
    let mut out = String::new();
    let _ = write!(
        out,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\" />\n\
         <title>{}</title>\n<style>\n{STYLE}\n</style>\n</head>\n<body>\n<h1>{}</h1>\n",
        html(&format!("axiscomp — {heading}")),
        html(&heading)
    );

    out.push_str("<h2>Run</h2>\n");
    kv_table(&mut out, &text::meta_rows(m));
    if !m.plan.is_empty() {
        out.push_str("<h2>Plan</h2>\n");
        kv_table(&mut out, &m.plan);
    }
    if !m.config.is_empty() {
        out.push_str("<h2>Configuration</h2>\n");
        kv_table(&mut out, &m.config);
    }
    if !m.notes.trim().is_empty() {
        let _ = write!(
            out,
            "<h2>Notes</h2>\n<p class=\"notes\">{}</p>\n",
            html(m.notes.trim())
        );
    }

    if let Some(six) = &svgs.six {
        out.push_str("<h2>Overview</h2>\n");
        figure(&mut out, six, &text::six_title(m));
    }
    for (d, svg) in r.dofs.iter().zip(&svgs.dofs) {
        let _ = writeln!(
            out,
            "<h2 id=\"{}\">{}</h2>",
            section_id(d.dof),
            html(&d.dof.title())
        );
        figure(
            &mut out,
            svg,
            &format!("{}: mean per direction with ±2s band", d.dof.title()),
        );
        if !d.figures.is_empty() {
            out.push_str("<h3>Figures</h3>\n");
            let rows: Vec<Vec<(String, bool)>> = d
                .figures
                .iter()
                .map(|f| {
                    vec![
                        (f.name.clone(), false),
                        (text::fixed(f.value, 3), true),
                        (f.unit.clone(), false),
                    ]
                })
                .collect();
            grid(
                &mut out,
                &["Figure".into(), "Value".into(), "Unit".into()],
                &rows,
            );
        }
        if let Some(b) = &d.budget {
            out.push_str("<h3>Uncertainty budget (ISO/TR 230-9)</h3>\n");
            let rows: Vec<Vec<(String, bool)>> = text::budget_rows(d.dof, b)
                .into_iter()
                .map(|r| {
                    let [a, f, v, s] = r;
                    vec![(a, false), (f, false), (v, true), (s, false)]
                })
                .collect();
            grid(&mut out, &text::budget_headings(d.dof), &rows);
            if !b.points.is_empty() {
                out.push_str("<h4>Per point: what each term puts into U</h4>\n");
                let rows: Vec<Vec<(String, bool)>> = text::budget_point_rows(b)
                    .into_iter()
                    .map(|r| {
                        r.into_iter()
                            .enumerate()
                            .map(|(j, c)| (c, j != 1))
                            .collect()
                    })
                    .collect();
                grid(&mut out, &text::budget_point_headings(d.dof, b), &rows);
            }
        }
        if !d.series.is_empty() {
            out.push_str("<h3>Points</h3>\n");
            let rows: Vec<Vec<(String, bool)>> =
                text::point_rows(d.dof, &d.series, d.budget.as_ref())
                    .into_iter()
                    .map(|p| {
                        let mut row = vec![
                            (p.position, true),
                            (p.direction.to_string(), false),
                            (p.n, true),
                            (p.mean, true),
                            (p.s, true),
                            (p.two_s, true),
                            (p.u, true),
                        ];
                        row.extend(p.expanded.map(|x| (x, true)));
                        row
                    })
                    .collect();
            grid(
                &mut out,
                &text::point_headings(d.dof, d.budget.as_ref().map(|b| b.k)),
                &rows,
            );
        }
    }
    for (c, svg) in r.comparisons.iter().zip(&svgs.comparisons) {
        let title = format!("{}: {} vs {}", c.dof.title(), c.before_label, c.after_label);
        let _ = writeln!(
            out,
            "<h2 id=\"compare-{}\">{}</h2>",
            section_id(c.dof),
            html(&title)
        );
        figure(&mut out, svg, &title);
    }

    out.push_str("<h2>Environment</h2>\n");
    if let Some(span) = text::env_span(&r.environment) {
        let _ = writeln!(out, "<p>{}</p>", html(&format!("Samples from {span}.")));
    }
    let rows: Vec<Vec<(String, bool)>> = text::env_rows(&r.environment)
        .into_iter()
        .map(|row| {
            row.into_iter()
                .enumerate()
                .map(|(i, cell)| (cell, i > 0))
                .collect()
        })
        .collect();
    let headings: Vec<String> = text::ENV_HEADINGS.iter().map(|h| h.to_string()).collect();
    grid(&mut out, &headings, &rows);
    out.push_str("</body>\n</html>\n");
    out
}
