//! `axiscomp decouple`: readings CSV on standard input → errors CSV on standard output.

use super::{InputError, load_layout};
use anyhow::{Context, Result};
use axiscomp::calibrate::CalibrationFile;
use axiscomp::decouple::{Decoupler, Method, SolveOptions, Source};
use axiscomp::units::{MM_PER_UM, readings_from_um};
use axiscomp::util::csv::NumericCsv;
use std::io::{Read, Write};
use std::path::PathBuf;

const READING_COLUMNS: [&str; 6] = ["X1_um", "Y1_um", "X2_um", "Y2_um", "X3_um", "Y3_um"];
const OUT_HEADER: &str = "dx_um,dy_um,dz_um,ex_arcsec,ey_arcsec,ez_arcsec,sd_dx_um,sd_dy_um,sd_dz_um,sd_ex_arcsec,sd_ey_arcsec,sd_ez_arcsec";

#[derive(clap::Args, Debug)]
#[command(group(clap::ArgGroup::new("source").required(true).args(["calibration", "simulated"])))]
pub struct Args {
    /// Calibration file from `calibrate fit`.
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// Use the layout's own model (no calibration).
    #[arg(long)]
    pub simulated: bool,
    /// Layout file (default: configs/optics/reference.toml).
    #[arg(long)]
    pub layout: Option<PathBuf>,
    /// PSD noise per axis for the standard deviations (µm); default: the calibration's noise,
    /// or 1 µm with --simulated.
    #[arg(long)]
    pub sigma_um: Option<f64>,
    /// One-shot linear decoupling with β(D) instead of Gauss–Newton (model sources only).
    #[arg(long)]
    pub linear: bool,
}

pub fn run(a: Args) -> Result<()> {
    let layout = load_layout(a.layout.as_deref())?;
    if let Some(s) = a.sigma_um
        && !(s.is_finite() && s > 0.0)
    {
        return Err(
            InputError(format!("--sigma-um {s}: give a positive noise level in µm")).into(),
        );
    }
    let method = if a.linear {
        Method::Linear
    } else {
        Method::Nonlinear
    };
    let mut dec = match &a.calibration {
        Some(path) => {
            let cal = CalibrationFile::load(path, &layout)?;
            let mut d = cal.decoupler(&layout)?;
            if d.method == Method::Nonlinear {
                d.method = method;
            }
            d
        }
        None => Decoupler {
            source: Source::Simulated(layout.clone()),
            method,
            sigma_mm: [MM_PER_UM; 6],
            options: SolveOptions::default(),
        },
    };
    if let Some(s) = a.sigma_um {
        dec.sigma_mm = [s * MM_PER_UM; 6];
        if let Source::Linear { linear, .. } = &mut dec.source {
            **linear = axiscomp::decouple::Linear::new(linear.beta, linear.offset, &dec.sigma_mm)?;
        }
    }
    let mut text = String::new();
    std::io::stdin()
        .read_to_string(&mut text)
        .context("reading standard input")?;
    let csv = NumericCsv::parse(
        &text,
        "standard input",
        &READING_COLUMNS,
        &["travel_mm", "follower_mm"],
    )?;
    let mut ranges: Vec<_> = READING_COLUMNS
        .iter()
        .map(|c| (*c, axiscomp::calibrate::poses::READING_UM))
        .collect();
    ranges.extend(["travel_mm", "follower_mm"].map(|c| (c, axiscomp::util::range::POSITION_MM)));
    csv.check_ranges(&ranges)?;
    let cols: Vec<usize> = READING_COLUMNS.iter().filter_map(|c| csv.col(c)).collect();
    let (tcol, fcol) = (csv.col("travel_mm"), csv.col("follower_mm"));
    let stdout = std::io::stdout();
    let mut out = stdout.lock();
    writeln!(out, "{OUT_HEADER}")?;
    let mut failed = 0;
    for (line, row) in &csv.rows {
        let r = readings_from_um(std::array::from_fn(|k| row[cols[k]]));
        let travel = tcol.map(|c| row[c]).unwrap_or(0.0);
        let follower = fcol.map(|c| row[c]).unwrap_or(0.0);
        match dec.decouple(&r, travel, follower) {
            Ok(est) => {
                let e = est.errors.to_user();
                let sd = est.sd().to_user();
                let fields: Vec<String> = e.iter().chain(&sd).map(|x| format!("{x:.6}")).collect();
                writeln!(out, "{}", fields.join(","))?;
            }
            Err(err) => {
                failed += 1;
                eprintln!("axiscomp: standard input line {line}: {err}");
                writeln!(out, "{}", [""; 12].join(","))?;
            }
        }
    }
    if failed > 0 {
        anyhow::bail!(
            "{failed} of {} rows could not be decoupled (empty rows in the output)",
            csv.rows.len()
        );
    }
    Ok(())
}
