//! Text shared by the HTML and Markdown renderers: file names, number formats, escaping, and
//! the rows both reports show.

use super::{BudgetTable, Dof, EnvSample, RunMeta, Series};
use crate::run::Direction;
use crate::util::time::rfc3339;

pub const HTML_FILE: &str = "report.html";
pub const MARKDOWN_FILE: &str = "report.md";
pub const SIX_SVG: &str = "six.svg";
pub const SIX_PNG: &str = "six.png";

/// Longest JSON value shown in a plan or configuration row.
const MAX_VALUE_CHARS: usize = 120;

/// "dy.png".
pub fn dof_file(dof: Dof, ext: &str) -> String {
    format!("{}.{ext}", dof.name())
}

/// "compare-dy.png".
pub fn comparison_file(dof: Dof, ext: &str) -> String {
    format!("compare-{}.{ext}", dof.name())
}

/// ↑ or ↓ (ISO 230-2).
pub fn arrow(d: Direction) -> &'static str {
    match d {
        Direction::Up => "↑",
        Direction::Down => "↓",
    }
}

/// The report's heading: "Run 12 — axis Y".
pub fn heading(m: &RunMeta) -> String {
    format!("Run {} — axis {}", m.run_id, m.axis)
}

/// The six-error sheet's title.
pub fn six_title(m: &RunMeta) -> String {
    format!("Run {}, axis {}: the six errors", m.run_id, m.axis)
}

/// UTC date and time of a µs timestamp.
pub fn date(unix_us: i64) -> String {
    rfc3339(unix_us.div_euclid(1_000_000))
}

/// An ISO 8601 UTC date and time to the second, for reading: "2026-11-30 12:14:54 UTC".
pub fn when(unix_us: i64) -> String {
    date(unix_us).replace('T', " ").replace('Z', " UTC")
}

/// `v` with `decimals` decimals, never "-0.000".
pub fn fixed(v: f64, decimals: usize) -> String {
    let s = format!("{v:.decimals$}");
    match s.strip_prefix('-') {
        Some(rest) if rest.chars().all(|c| c == '0' || c == '.') => rest.to_string(),
        _ => s,
    }
}

/// A value of a DOF in its user unit, for tables.
pub fn user(dof: Dof, internal: f64) -> String {
    fixed(dof.to_user(internal), 3)
}

/// Escape text for HTML element content and quoted attributes.
pub fn html(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// Escape text for one line of Markdown (a table cell, a heading, a list item): markup
/// characters are backslash-escaped, HTML is neutralised, line breaks become spaces.
pub fn md(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '\\' | '`' | '*' | '_' | '[' | ']' | '|' | '#' | '!' => {
                out.push('\\');
                out.push(c);
            }
            '\r' => {}
            '\n' => out.push(' '),
            c => out.push(c),
        }
    }
    out
}

/// Rows of a JSON snapshot (a run's plan, its configuration) in words: an object's entries
/// sorted by key, an object inside it opened into rows of its own (the plan's `spec`); numbers
/// at sensible precision (at most three decimals, trailing zeros dropped: 101.18, not 101.18033988749895), lists
/// of them comma-separated, null as "none", true and false as yes and no, long values
/// shortened. Anything else is one row named `name`. (The demo's report printed
/// `{"axis":"X","dwell_s":2.0,…}` and `[0.0,101.18033988749895,…]`.)
pub fn json_rows(name: &str, v: &serde_json::Value) -> Vec<(String, String)> {
    use serde_json::Value;
    fn number(x: f64) -> String {
        let t = format!("{x:.3}");
        let t = t.trim_end_matches('0').trim_end_matches('.');
        if t == "-0" { "0".into() } else { t.to_string() }
    }
    fn words(v: &Value) -> String {
        match v {
            Value::String(s) => s.clone(),
            Value::Number(n) => n.as_f64().map_or_else(|| n.to_string(), number),
            Value::Bool(true) => "yes".into(),
            Value::Bool(false) => "no".into(),
            Value::Null => "none".into(),
            Value::Array(a) => a.iter().map(words).collect::<Vec<_>>().join(", "),
            Value::Object(m) => m
                .iter()
                .map(|(k, v)| format!("{k} {}", words(v)))
                .collect::<Vec<_>>()
                .join(", "),
        }
    }
    let show = |v: &Value| -> String {
        let s = words(v);
        if s.chars().count() > MAX_VALUE_CHARS {
            let short: String = s.chars().take(MAX_VALUE_CHARS - 1).collect();
            format!("{short}…")
        } else {
            s
        }
    };
    match v {
        Value::Object(map) => {
            let mut rows: Vec<(String, String)> = Vec::new();
            for (k, v) in map {
                match v {
                    Value::Object(inner) => rows.extend(inner.iter().map(|(ik, iv)| {
                        let key = if map.contains_key(ik) {
                            format!("{k} {ik}")
                        } else {
                            ik.clone()
                        };
                        (key, show(iv))
                    })),
                    _ => rows.push((k.clone(), show(v))),
                }
            }
            rows.sort_by(|a, b| a.0.cmp(&b.0));
            rows
        }
        Value::Null => Vec::new(),
        other => vec![(name.to_string(), show(other))],
    }
}

/// The run's metadata rows: with its machine time once it started (from its start to its
/// end, or to now for a run still on the machine).
pub fn meta_rows(m: &RunMeta) -> Vec<(&'static str, String)> {
    let mut rows = vec![
        ("Run", m.run_id.to_string()),
        ("Axis", m.axis.clone()),
        ("State", m.state.clone()),
        ("Created", date(m.created_us)),
        ("Updated", date(m.updated_us)),
    ];
    let minutes = (m.updated_us - m.created_us).max(0) as f64 / 60e6;
    match m.state.as_str() {
        "planned" => {}
        "running" => rows.push((
            "Machine time",
            format!("{minutes:.1} min so far (to its last update)"),
        )),
        _ => rows.push((
            "Machine time",
            format!("{minutes:.1} min, from its start to its end"),
        )),
    }
    rows
}

/// One row of a per-point table.
pub struct PointRow {
    pub position: String,
    pub direction: &'static str,
    pub n: String,
    pub mean: String,
    pub s: String,
    pub two_s: String,
    /// The budget's combined standard uncertainty at the point, when the result has a
    /// budget (one uncertainty: U is k times it); else the captures' stated u (their mean).
    pub u: String,
    /// The budget's expanded uncertainty, when the result has a budget.
    pub expanded: Option<String>,
}

/// Column headings of the per-point table: u the standard uncertainty (the budget's
/// combined, or without one the captures' own); U, when a budget is given (`budget_k`), the
/// budget's expanded uncertainty.
pub fn point_headings(dof: Dof, budget_k: Option<f64>) -> Vec<String> {
    let u = dof.unit();
    let mut h = vec![
        "Target (mm)".into(),
        "Dir".into(),
        "n".into(),
        format!("Mean ({u})"),
        format!("s ({u})"),
        format!("2s ({u})"),
        format!("u, standard ({u})"),
    ];
    if let Some(k) = budget_k {
        h.push(format!("U, expanded k = {k} ({u})"));
    }
    h
}

/// The rows of a budget table: term, formula, largest standard uncertainty, source; then the
/// combined and expanded uncertainty.
pub fn budget_rows(dof: Dof, b: &BudgetTable) -> Vec<[String; 4]> {
    let v = |x: f64| fixed(x, 3);
    let mut rows: Vec<[String; 4]> = b
        .terms
        .iter()
        .map(|t| {
            [
                t.name.clone(),
                t.formula.clone(),
                v(t.largest),
                t.source.clone(),
            ]
        })
        .collect();
    rows.push([
        "combined standard uncertainty u".into(),
        "√(Σ u_i²)".into(),
        v(b.largest_combined),
        "the terms in quadrature (uncorrelated)".into(),
    ]);
    rows.push([
        format!("expanded uncertainty U (k = {})", b.k),
        format!("{}·u", b.k),
        v(b.largest_expanded),
        format!("largest over the points, in {}", dof.unit()),
    ]);
    rows
}

/// Column headings of a budget table.
pub fn budget_headings(dof: Dof) -> [String; 4] {
    [
        "Term".into(),
        "Formula".into(),
        format!("Largest u ({})", dof.unit()),
        "Source".into(),
    ]
}

/// The per-point rows of a result: by direction (↑ first), then by position.
pub fn point_rows(dof: Dof, series: &[Series], budget: Option<&BudgetTable>) -> Vec<PointRow> {
    let mut ordered: Vec<&Series> = series.iter().collect();
    ordered.sort_by_key(|s| s.direction);
    let mut rows = Vec::new();
    for s in ordered {
        let mut idx: Vec<usize> = (0..s.positions_mm.len()).collect();
        idx.sort_by(|&a, &b| s.positions_mm[a].total_cmp(&s.positions_mm[b]));
        for i in idx {
            rows.push(PointRow {
                position: fixed(s.positions_mm[i], 3),
                direction: arrow(s.direction),
                n: s.n[i].to_string(),
                mean: user(dof, s.mean[i]),
                s: user(dof, s.s[i]),
                two_s: user(dof, 2.0 * s.s[i]),
                u: match budget {
                    Some(b) => b
                        .at(s.positions_mm[i], s.direction)
                        .map_or_else(|| "—".to_string(), |p| fixed(p.combined, 3)),
                    None => {
                        s.u.as_ref()
                            .and_then(|u| u.get(i))
                            .map_or_else(|| "—".to_string(), |&u| user(dof, u))
                    }
                },
                expanded: budget.map(|b| {
                    b.expanded_at(s.positions_mm[i], s.direction)
                        .map_or_else(|| "—".to_string(), |x| fixed(x, 3))
                }),
            });
        }
    }
    rows
}

/// The terms a DOF's budget states anywhere (a term zero at every point is left out of the
/// per-point table; the budget table names it and why).
fn stated_terms(b: &BudgetTable) -> Vec<usize> {
    (0..b.terms.len())
        .filter(|&j| {
            b.points
                .iter()
                .any(|p| p.terms.get(j).is_some_and(|&t| t > 0.0))
        })
        .collect()
}

/// Column headings of the per-point budget: target, direction, each stated term's u, the
/// combined u and U.
pub fn budget_point_headings(dof: Dof, b: &BudgetTable) -> Vec<String> {
    let u = dof.unit();
    let mut h = vec!["Target (mm)".to_string(), "Dir".into()];
    h.extend(stated_terms(b).into_iter().map(|j| b.terms[j].name.clone()));
    h.push(format!("u ({u})"));
    h.push(format!("U, k = {} ({u})", b.k));
    h
}

/// The per-point budget, one row per point (↑ first, then by position): what each term
/// puts into that point's U.
pub fn budget_point_rows(b: &BudgetTable) -> Vec<Vec<String>> {
    let cols = stated_terms(b);
    let mut points: Vec<&super::BudgetPoint> = b.points.iter().collect();
    points.sort_by(|a, c| {
        a.direction
            .cmp(&c.direction)
            .then(a.position_mm.total_cmp(&c.position_mm))
    });
    points
        .into_iter()
        .map(|p| {
            let mut row = vec![fixed(p.position_mm, 3), arrow(p.direction).to_string()];
            row.extend(
                cols.iter()
                    .map(|&j| p.terms.get(j).map_or_else(|| "—".into(), |&t| fixed(t, 3))),
            );
            row.push(fixed(p.combined, 3));
            row.push(fixed(p.expanded, 3));
            row
        })
        .collect()
}

/// Column headings of the environment table.
pub const ENV_HEADINGS: [&str; 5] = [
    "Temperature",
    "Min (°C)",
    "Mean (°C)",
    "Max (°C)",
    "Samples",
];

/// Environment rows (material, air): min, mean, max, samples; "—" when not measured.
pub fn env_rows(samples: &[EnvSample]) -> Vec<[String; 5]> {
    let row = |name: &str, values: Vec<f64>| -> [String; 5] {
        if values.is_empty() {
            return [
                name.to_string(),
                "—".into(),
                "—".into(),
                "—".into(),
                "0".into(),
            ];
        }
        let min = values.iter().copied().fold(f64::INFINITY, f64::min);
        let max = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let mean = values.iter().sum::<f64>() / values.len() as f64;
        [
            name.to_string(),
            fixed(min, 2),
            fixed(mean, 2),
            fixed(max, 2),
            values.len().to_string(),
        ]
    };
    let finite = |f: fn(&EnvSample) -> Option<f64>| -> Vec<f64> {
        samples
            .iter()
            .filter_map(f)
            .filter(|v| v.is_finite())
            .collect()
    };
    vec![
        row("Material", finite(|s| s.material_c)),
        row("Air", finite(|s| s.air_c)),
    ]
}

/// "from … to …" of the samples, when there are any.
pub fn env_span(samples: &[EnvSample]) -> Option<String> {
    let first = samples.iter().map(|s| s.unix_us).min()?;
    let last = samples.iter().map(|s| s.unix_us).max()?;
    Some(format!("{} to {}", date(first), date(last)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fixed_never_shows_negative_zero() {
        assert_eq!(fixed(-0.0, 3), "0.000");
        assert_eq!(fixed(-0.0001, 3), "0.000");
        assert_eq!(fixed(-0.0015, 3), "-0.002");
        assert_eq!(fixed(12.5, 1), "12.5");
    }

    #[test]
    fn escaping() {
        assert_eq!(html(r#"<b>&"'"#), "&lt;b&gt;&amp;&quot;&#39;");
        assert_eq!(
            md("a|b *c* <x> & [l](u)\nnext"),
            r"a\|b \*c\* &lt;x&gt; &amp; \[l\](u) next"
        );
    }

    #[test]
    fn json_rows_flatten_the_top_level() {
        let v = serde_json::json!({"runs": 5, "name": "ISO", "targets": [0, 10]});
        assert_eq!(
            json_rows("plan", &v),
            [
                ("name".to_string(), "ISO".to_string()),
                ("runs".to_string(), "5".to_string()),
                ("targets".to_string(), "0, 10".to_string()),
            ]
        );
        // The demo's plan: its spec opened into rows, numbers at three decimals at most.
        let v = serde_json::json!({"reference_mm": 0.0, "spec": {"axis": "X", "dwell_s": 2.0,
            "reference_mm": null, "stability": true}, "targets": [0.0, 101.18033988749895, -0.0004]});
        assert_eq!(
            json_rows("plan", &v),
            [
                ("axis".to_string(), "X".to_string()),
                ("dwell_s".to_string(), "2".to_string()),
                ("reference_mm".to_string(), "0".to_string()),
                ("spec reference_mm".to_string(), "none".to_string()),
                ("stability".to_string(), "yes".to_string()),
                ("targets".to_string(), "0, 101.18, 0".to_string()),
            ]
        );
        assert_eq!(
            json_rows("plan", &serde_json::json!(3)),
            [("plan".to_string(), "3".to_string())]
        );
        let long = serde_json::json!({"k": "x".repeat(500)});
        assert_eq!(json_rows("c", &long)[0].1.chars().count(), MAX_VALUE_CHARS);
    }
}
