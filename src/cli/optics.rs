//! `axiscomp optics trace|jacobian`.

use super::{InputError, load_layout};
use anyhow::{Context, Result};
use axiscomp::decouple;
use axiscomp::optics::{Layout, Pose};
use axiscomp::units::{DOF_NAMES, DOF_UNITS, Errors6, MM_PER_UM, READING_NAMES};
use clap::Subcommand;
use serde_json::{Value, json};
use std::io::{BufRead, Write};
use std::path::PathBuf;

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Trace poses read as JSON lines on standard input:
    /// {"errors":[dx_um,dy_um,dz_um,ex_arcsec,ey_arcsec,ez_arcsec],"travel_mm":D,"follower_mm":d}.
    /// Writes one JSON line per input line: {"readings_um":[X1,Y1,X2,Y2,X3,Y3],"valid":[..],"reasons":[..]}.
    Trace {
        /// Layout file (default: configs/optics/reference.toml).
        #[arg(long)]
        layout: Option<PathBuf>,
    },
    /// The 6×6 sensitivity table, singular values, condition number and Cramér–Rao bound.
    Jacobian {
        /// Layout file (default: configs/optics/reference.toml).
        #[arg(long)]
        layout: Option<PathBuf>,
        /// Nominal travel D (mm).
        #[arg(long, default_value_t = 0.0)]
        travel_mm: f64,
        /// Follower position d (mm); default: d = D (spot centred on PSD2).
        #[arg(long)]
        follower_mm: Option<f64>,
        /// PSD noise per axis (µm) for the Cramér–Rao bound.
        #[arg(long, default_value_t = 1.0)]
        sigma_um: f64,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
    },
}

pub fn run(c: Command) -> Result<()> {
    match c {
        Command::Trace { layout } => {
            let layout = load_layout(layout.as_deref())?;
            let stdin = std::io::stdin();
            let stdout = std::io::stdout();
            let (lines, refused) = trace_stream(&layout, stdin.lock(), &mut stdout.lock())?;
            if refused > 0 {
                return Err(InputError(format!(
                    "{refused} of {lines} input lines were refused (see the messages above)"
                ))
                .into());
            }
            Ok(())
        }
        Command::Jacobian {
            layout,
            travel_mm,
            follower_mm,
            sigma_um,
            json,
        } => {
            let layout = load_layout(layout.as_deref())?;
            if !(sigma_um.is_finite() && sigma_um > 0.0) {
                return Err(InputError(format!(
                    "--sigma-um {sigma_um}: give a positive noise level in µm"
                ))
                .into());
            }
            jacobian_report(
                &layout,
                travel_mm,
                follower_mm.unwrap_or(travel_mm),
                sigma_um,
                json,
            )
        }
    }
}

/// One parsed input line of `optics trace`.
struct TraceInput {
    errors: Errors6,
    travel: f64,
    follower: f64,
}

fn parse_trace_line(line: &str) -> Result<TraceInput, String> {
    let v: Value = serde_json::from_str(line).map_err(|e| {
        format!(
            "not valid JSON ({e}): give {{\"errors\":[6 numbers],\"travel_mm\":D,\"follower_mm\":d}}"
        )
    })?;
    let obj = v.as_object().ok_or_else(|| {
        "expected a JSON object {\"errors\":[6 numbers],\"travel_mm\":D,\"follower_mm\":d}"
            .to_string()
    })?;
    for k in obj.keys() {
        if !["errors", "travel_mm", "follower_mm"].contains(&k.as_str()) {
            return Err(format!(
                "unknown field \"{k}\": the fields are errors, travel_mm, follower_mm"
            ));
        }
    }
    let errors = obj.get("errors").ok_or(
        "field \"errors\" is missing: give [dx_um,dy_um,dz_um,ex_arcsec,ey_arcsec,ez_arcsec]",
    )?;
    let arr = errors.as_array().ok_or_else(|| {
        format!("field \"errors\": expected an array of 6 numbers, found {errors}")
    })?;
    if arr.len() != 6 {
        return Err(format!(
            "field \"errors\": expected 6 numbers, found {}",
            arr.len()
        ));
    }
    let mut e = [0.0; 6];
    for (k, x) in arr.iter().enumerate() {
        e[k] = x.as_f64().filter(|f| f.is_finite()).ok_or_else(|| {
            format!(
                "field \"errors\" item {} ({}): expected a number, found {x}",
                k + 1,
                DOF_NAMES[k]
            )
        })?;
    }
    let num = |key: &str| -> Result<f64, String> {
        match obj.get(key) {
            None => Ok(0.0),
            Some(x) => x
                .as_f64()
                .filter(|f| f.is_finite())
                .ok_or_else(|| format!("field \"{key}\": expected a number (mm), found {x}")),
        }
    };
    Ok(TraceInput {
        errors: Errors6::from_user(e),
        travel: num("travel_mm")?,
        follower: num("follower_mm")?,
    })
}

/// Trace every line of `input`; returns (lines read, lines refused). A refused line gets an
/// `{"error": ...}` line on the output (so outputs stay aligned with inputs) and a message on
/// standard error naming the line.
pub fn trace_stream(
    layout: &Layout,
    input: impl BufRead,
    out: &mut impl Write,
) -> Result<(usize, usize)> {
    let (mut lines, mut refused) = (0, 0);
    for (i, line) in input.lines().enumerate() {
        let line = line.context("reading standard input")?;
        if line.trim().is_empty() {
            continue;
        }
        lines += 1;
        let value = match parse_trace_line(&line) {
            Ok(t) => {
                let r = layout.forward(&Pose::new(t.errors, t.travel, t.follower));
                let mut readings = Vec::with_capacity(6);
                let mut valid = Vec::with_capacity(3);
                let mut reasons = Vec::with_capacity(3);
                for s in &r.psd {
                    match s {
                        Ok(s) => {
                            readings.push(json!(s.x / MM_PER_UM));
                            readings.push(json!(s.y / MM_PER_UM));
                            valid.push(true);
                            reasons.push(Value::Null);
                        }
                        Err(inv) => {
                            readings.push(Value::Null);
                            readings.push(Value::Null);
                            valid.push(false);
                            reasons.push(json!(layout.describe(inv)));
                        }
                    }
                }
                json!({"readings_um": readings, "valid": valid, "reasons": reasons})
            }
            Err(msg) => {
                refused += 1;
                eprintln!("axiscomp: standard input line {}: {msg}", i + 1);
                json!({"error": format!("line {}: {msg}", i + 1)})
            }
        };
        writeln!(out, "{value}").context("writing standard output")?;
    }
    Ok((lines, refused))
}

fn jacobian_report(
    layout: &Layout,
    travel: f64,
    follower: f64,
    sigma_um: f64,
    as_json: bool,
) -> Result<()> {
    let pose = Pose::new(Errors6::ZERO, travel, follower);
    let j = decouple::jacobian(layout, &pose)?;
    let ju = decouple::to_user_units(&j);
    let (sv, cond) = decouple::conditioning(&ju);
    let bound = decouple::crlb(&j, sigma_um * MM_PER_UM)
        .ok_or_else(|| anyhow::anyhow!("the sensitivity matrix is singular at this pose"))?
        .to_user();
    if as_json {
        let rows: Vec<Vec<f64>> = (0..6)
            .map(|r| (0..6).map(|c| ju[(r, c)]).collect())
            .collect();
        let crlb: serde_json::Map<String, Value> = DOF_NAMES
            .iter()
            .zip(bound)
            .map(|(n, b)| (n.to_string(), json!(b)))
            .collect();
        println!(
            "{}",
            json!({
                "layout": layout.name, "travel_mm": travel, "follower_mm": follower,
                "rows": READING_NAMES, "cols": DOF_NAMES,
                "units": "um per um (dx,dy,dz), um per arcsec (ex,ey,ez)",
                "jacobian": rows, "singular_values": sv, "condition_number": cond,
                "sigma_um": sigma_um, "crlb": crlb,
            })
        );
        return Ok(());
    }
    println!(
        "sensitivity of layout {} at travel D = {travel} mm, follower d = {follower} mm",
        layout.name
    );
    println!("(µm of reading per µm of dx, dy, dz and per arcsec of ex, ey, ez)");
    print!("{:>4}", "");
    for n in DOF_NAMES {
        print!("{n:>11}");
    }
    println!();
    for r in 0..6 {
        print!("{:>4}", READING_NAMES[r]);
        for c in 0..6 {
            print!("{:>11.5}", ju[(r, c)]);
        }
        println!();
    }
    print!("singular values:");
    for s in sv {
        print!(" {s:.5}");
    }
    println!();
    println!("condition number: {cond:.3}");
    println!("Cramér–Rao bound for σ = {sigma_um} µm per PSD axis:");
    for k in 0..6 {
        println!("  {:<3}{:>10.4} {}", DOF_NAMES[k], bound[k], DOF_UNITS[k]);
    }
    Ok(())
}
