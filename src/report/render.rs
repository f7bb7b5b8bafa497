//! The acceptance document as HTML (self-contained: inline style and inline SVG charts, no
//! scripts) and as Markdown (charts as SVG files beside it, named by `chart_file`).

use super::chart;
use super::doc::{Block, Document, Table};
use super::text::{html as h, md};
use std::fmt::Write as _;

/// Chart width (points) in both renderings.
const CHART_W: f64 = 640.0;
const CHART_PLOT_H: f64 = 220.0;

/// "chart-3.svg": the file of the document's third chart.
pub fn chart_file(n: usize) -> String {
    format!("chart-{n}.svg")
}

/// Each chart of `doc` as (file name, SVG), in order.
pub fn chart_svgs(doc: &Document) -> Vec<(String, String)> {
    doc.blocks
        .iter()
        .filter_map(|b| match b {
            Block::Chart(c) => Some(chart::svg(c, CHART_W, CHART_PLOT_H)),
            _ => None,
        })
        .enumerate()
        .map(|(i, s)| (chart_file(i + 1), s))
        .collect()
}

const STYLE: &str = "body{font-family:\"DejaVu Sans\",Verdana,sans-serif;font-size:14px;max-width:60em;\
margin:2em auto;color:#111}h1{font-size:1.6em;margin-bottom:0}h2{font-size:1.2em;margin-top:1.6em;\
border-bottom:1px solid #999}h3{font-size:1em}table{border-collapse:collapse;margin:.5em 0}\
th,td{padding:2px 10px;border-bottom:1px solid #ddd;text-align:left}td.n,th.n{text-align:right;\
font-variant-numeric:tabular-nums}p.note{font-size:.85em;color:#333}.sig{display:flex;gap:3em;\
margin:2.5em 0 .5em}.sig div{border-top:1px solid #000;min-width:16em;padding-top:2px;font-size:.8em}";

fn html_table(out: &mut String, t: &Table) {
    out.push_str("<table>\n<tr>");
    for c in &t.columns {
        let cls = if c.numeric { " class=\"n\"" } else { "" };
        let _ = write!(out, "<th{cls}>{}</th>", h(&c.title));
    }
    out.push_str("</tr>\n");
    for row in &t.rows {
        out.push_str("<tr>");
        for (cell, c) in row.iter().zip(&t.columns) {
            let cls = if c.numeric { " class=\"n\"" } else { "" };
            let _ = write!(out, "<td{cls}>{}</td>", h(cell));
        }
        out.push_str("</tr>\n");
    }
    out.push_str("</table>\n");
    if let Some(n) = &t.note {
        let _ = writeln!(out, "<p class=\"note\">{}</p>", h(n));
    }
}

/// The HTML report.
pub fn html(doc: &Document) -> String {
    let mut out = format!(
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<title>{}</title>\n\
         <style>{STYLE}</style>\n</head>\n<body>\n<h1>{}</h1>\n<p>{}</p>\n",
        h(&doc.title),
        h(&doc.title),
        h(&doc.subtitle)
    );
    for b in &doc.blocks {
        match b {
            Block::Heading(s) => {
                let _ = writeln!(out, "<h2>{}</h2>", h(s));
            }
            Block::Subheading(s) => {
                let _ = writeln!(out, "<h3>{}</h3>", h(s));
            }
            Block::Paragraph(s) => {
                let _ = writeln!(out, "<p>{}</p>", h(s));
            }
            Block::Fields(rows) => {
                out.push_str("<table>\n");
                for (k, v) in rows {
                    let _ = writeln!(out, "<tr><th>{}</th><td>{}</td></tr>", h(k), h(v));
                }
                out.push_str("</table>\n");
            }
            Block::Table(t) => html_table(&mut out, t),
            Block::Chart(c) => {
                let _ = writeln!(
                    out,
                    "<figure>\n{}<figcaption class=\"note\">{}</figcaption>\n</figure>",
                    chart::svg(c, CHART_W, CHART_PLOT_H),
                    h(&c.note)
                );
            }
            Block::Signatures(roles) => {
                for r in roles {
                    let _ = writeln!(
                        out,
                        "<h3>{}</h3>\n<div class=\"sig\"><div>Name and signature</div><div>Date</div></div>",
                        h(r)
                    );
                }
            }
        }
    }
    out.push_str("</body>\n</html>\n");
    out
}

fn md_table(out: &mut String, t: &Table) {
    let titles: Vec<String> = t.columns.iter().map(|c| md(&c.title)).collect();
    let _ = writeln!(out, "| {} |", titles.join(" | "));
    let rule: Vec<&str> = t
        .columns
        .iter()
        .map(|c| if c.numeric { "---:" } else { "---" })
        .collect();
    let _ = writeln!(out, "|{}|", rule.join("|"));
    for row in &t.rows {
        let cells: Vec<String> = row.iter().map(|c| md(c)).collect();
        let _ = writeln!(out, "| {} |", cells.join(" | "));
    }
    out.push('\n');
    if let Some(n) = &t.note {
        let _ = writeln!(out, "{}\n", md(n));
    }
}

/// The Markdown report; its charts are the files `chart_svgs` names.
pub fn markdown(doc: &Document) -> String {
    let mut out = format!("# {}\n\n{}\n\n", md(&doc.title), md(&doc.subtitle));
    let mut charts = 0;
    for b in &doc.blocks {
        match b {
            Block::Heading(s) => {
                let _ = writeln!(out, "## {}\n", md(s));
            }
            Block::Subheading(s) => {
                let _ = writeln!(out, "### {}\n", md(s));
            }
            Block::Paragraph(s) => {
                let _ = writeln!(out, "{}\n", md(s));
            }
            Block::Fields(rows) => {
                out.push_str("| | |\n|---|---|\n");
                for (k, v) in rows {
                    let _ = writeln!(out, "| **{}** | {} |", md(k), md(v));
                }
                out.push('\n');
            }
            Block::Table(t) => md_table(&mut out, t),
            Block::Chart(c) => {
                charts += 1;
                let _ = writeln!(
                    out,
                    "![{}]({})\n\n{}\n",
                    md(&c.title),
                    chart_file(charts),
                    md(&c.note)
                );
            }
            Block::Signatures(roles) => {
                for r in roles {
                    let _ = writeln!(
                        out,
                        "**{}**\n\nName and signature: ______________________  Date: ____________\n",
                        md(r)
                    );
                }
            }
        }
    }
    out
}
