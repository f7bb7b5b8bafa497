//! `axiscomp evaluate --input captures.csv [--json]`: ISO 230-2 positioning figures from a
//! deviation table (`target_index,target_mm,run,direction,deviation_um`).
//!
//! JSON (µm, the contract scripts rely on): `{"targets":[{"x_up","x_down","x_mean","B","s_up",
//! "s_down","R_up","R_down","R"}, …], "axis":{"A","A_up","A_down","B","B_mean","R","R_up",
//! "R_down","E","E_up","E_down","M"}}`, targets in increasing target index, `null` for a
//! figure the data cannot define (one direction only; named on standard error).

use super::InputError;
use anyhow::Result;
use axiscomp::evaluate::input::parse_deviation_csv;
use axiscomp::evaluate::iso230_2::{self, Iso230_2};
use axiscomp::units::MM_PER_UM;
use serde_json::{Map, Value, json};
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Deviation table: target_index,target_mm,run,direction(+/-),deviation_um.
    #[arg(long)]
    pub input: PathBuf,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: Args) -> Result<()> {
    let text = std::fs::read_to_string(&a.input).map_err(|e| {
        InputError(format!(
            "--input {}: cannot read it ({e}): give a readable CSV file",
            a.input.display()
        ))
    })?;
    let name = a.input.display().to_string();
    let samples = parse_deviation_csv(&text, &name)?;
    let r = iso230_2::evaluate(&samples)?;
    let undefined = r.undefined();
    if a.json {
        println!("{}", serde_json::to_string_pretty(&to_json(&r))?);
        if !undefined.is_empty() {
            eprintln!(
                "axiscomp: one direction only ({}): {} and the per-target x_mean, B and R are null",
                if r.directions.has_up() { "+" } else { "-" },
                undefined.join(", ")
            );
        }
    } else {
        print!("{}", to_table(&r));
    }
    Ok(())
}

fn um(x: Option<f64>) -> Value {
    match x {
        Some(v) => json!(v / MM_PER_UM),
        None => Value::Null,
    }
}

/// The JSON contract.
fn to_json(r: &Iso230_2) -> Value {
    let targets: Vec<Value> = r
        .targets
        .iter()
        .map(|t| {
            let mut m = Map::new();
            for (k, v) in [
                ("x_up", t.x_up),
                ("x_down", t.x_down),
                ("x_mean", t.x_mean),
                ("B", t.b),
                ("s_up", t.s_up),
                ("s_down", t.s_down),
                ("R_up", t.r_up),
                ("R_down", t.r_down),
                ("R", t.r),
            ] {
                m.insert(k.into(), um(v));
            }
            Value::Object(m)
        })
        .collect();
    let mut axis = Map::new();
    for (k, v) in axis_rows(r) {
        axis.insert(k.into(), um(v));
    }
    json!({ "targets": targets, "axis": axis })
}

fn axis_rows(r: &Iso230_2) -> [(&'static str, Option<f64>); 12] {
    let a = &r.axis;
    [
        ("A", a.a),
        ("A_up", a.a_up),
        ("A_down", a.a_down),
        ("B", a.b),
        ("B_mean", a.b_mean),
        ("R", a.r),
        ("R_up", a.r_up),
        ("R_down", a.r_down),
        ("E", a.e),
        ("E_up", a.e_up),
        ("E_down", a.e_down),
        ("M", a.m),
    ]
}

const MEANING: [&str; 12] = [
    "bidirectional accuracy",
    "unidirectional accuracy, + direction",
    "unidirectional accuracy, - direction",
    "reversal value (max |B_i|)",
    "mean reversal value",
    "bidirectional repeatability",
    "unidirectional repeatability, +",
    "unidirectional repeatability, -",
    "bidirectional systematic positioning error",
    "unidirectional systematic positioning error, +",
    "unidirectional systematic positioning error, -",
    "mean bidirectional positional deviation range",
];

/// The readable table (µm).
fn to_table(r: &Iso230_2) -> String {
    let f = |x: Option<f64>| match x {
        Some(v) => format!("{:>10.4}", v / MM_PER_UM),
        None => format!("{:>10}", "-"),
    };
    let dirs = match r.directions {
        axiscomp::evaluate::Directions::Both => "both directions",
        axiscomp::evaluate::Directions::UpOnly => "+ direction only",
        axiscomp::evaluate::Directions::DownOnly => "- direction only",
    };
    let mut out = format!(
        "ISO 230-2 positioning: {} targets, {} runs per direction ({}), µm\n",
        r.targets.len(),
        r.runs.len(),
        dirs
    );
    out.push_str(&format!(
        "{:>6} {:>12}{:>10}{:>10}{:>10}{:>10}{:>10}{:>10}{:>10}{:>10}{:>10}\n",
        "target",
        "position_mm",
        "x_up",
        "x_down",
        "x_mean",
        "B",
        "s_up",
        "s_down",
        "R_up",
        "R_down",
        "R"
    ));
    for t in &r.targets {
        out.push_str(&format!(
            "{:>6} {:>12.4}{}{}{}{}{}{}{}{}{}\n",
            t.index,
            t.position_mm,
            f(t.x_up),
            f(t.x_down),
            f(t.x_mean),
            f(t.b),
            f(t.s_up),
            f(t.s_down),
            f(t.r_up),
            f(t.r_down),
            f(t.r)
        ));
    }
    out.push_str("\naxis\n");
    for ((name, v), meaning) in axis_rows(r).into_iter().zip(MEANING) {
        match v {
            Some(v) => out.push_str(&format!(
                "  {name:<7}{:>10.4} µm  {meaning}\n",
                v / MM_PER_UM
            )),
            None => out.push_str(&format!(
                "  {name:<7}{:>10}     {meaning}: undefined (one direction only)\n",
                "-"
            )),
        }
    }
    out
}
