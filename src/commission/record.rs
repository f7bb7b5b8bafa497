//! The machine record's file (issue 27): what a machine is, as its builder writes it down
//! before commissioning: a name, the kinematic chain, the travels, the tool offset the
//! volumetric figures are taken with, the optical squares' certificates, and how each axis is
//! measured. One reader, [`MachineRecord::from_toml`], in two stages as the configuration is
//! read (DESIGN §8): serde takes the file as written (`RawRecord`, unknown keys refused), then
//! every value is checked against its range and named when it is not.
//!
//! ```toml
//! name = "VMC 1000 serial 4711"
//! chain = "workpiece – X – Y – bed – Z – tool"   # or "X Y bed Z", dashes optional
//! travel_mm = [1000, 600, 500]
//! tool_mm = [0, 0, -150]
//! target_every_mm = 20
//! runs = 2
//!
//! [squares.XY]    # the optical square used for C0Y, as its certificate states it
//! id = "OS-2231"
//! deviation_arcsec = 0.4    # the turn is 90° + this
//! u_arcsec = 0.29           # standard uncertainty
//! [squares.ZX]
//! # ...
//! [squares.YZ]
//! # ...
//! ```

use crate::comp::mapping::MachineAxis;
use crate::machine::Chain;
use crate::machine::squareness::{SquareCertificate, SquarePair};
use crate::units::RAD_PER_ARCSEC;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use thiserror::Error;

/// Why a machine record was refused: the key and what to do.
#[derive(Debug, Error, Clone, PartialEq)]
#[error("machine record{}: {}{problem}", if origin.is_empty() { String::new() } else { format!(" {origin}") }, if key.is_empty() { String::new() } else { format!("{key}: ") })]
pub struct RecordError {
    /// The file, when the record came from one.
    pub origin: String,
    pub key: String,
    pub problem: String,
}

/// The file as written.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
struct RawRecord {
    name: String,
    chain: String,
    travel_mm: [f64; 3],
    #[serde(default)]
    tool_mm: [f64; 3],
    #[serde(default = "default_every")]
    target_every_mm: f64,
    #[serde(default = "default_runs")]
    runs: u32,
    #[serde(default)]
    squares: BTreeMap<String, RawSquare>,
}

fn default_every() -> f64 {
    20.0
}

fn default_runs() -> u32 {
    2
}

#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
struct RawSquare {
    id: String,
    deviation_arcsec: f64,
    u_arcsec: f64,
}

/// A machine as its builder describes it: validated.
#[derive(Clone, Debug, PartialEq)]
pub struct MachineRecord {
    pub name: String,
    pub chain: Chain,
    /// Travel of X, Y, Z (mm), each from 0.
    pub travel_mm: [f64; 3],
    /// The tool offset from the spindle's gauge point (mm, machine frame).
    pub tool_mm: [f64; 3],
    /// A target every this far on each axis (mm).
    pub target_every_mm: f64,
    /// Bidirectional runs per set-up.
    pub runs: u32,
    /// The square used for each pair (`SquarePair::index` order).
    pub squares: [SquareCertificate; 3],
}

/// The longest travel a record takes (mm).
const MAX_TRAVEL_MM: f64 = 10_000.0;
/// The largest square deviation a certificate may state (arcsec): a pentaprism is made to a
/// few arcseconds; more is a unit or sign slip.
const MAX_DEVIATION_ARCSEC: f64 = 60.0;

impl MachineRecord {
    /// Read a record from its TOML text; `origin` names the file in errors.
    pub fn from_toml(text: &str, origin: &str) -> Result<MachineRecord, RecordError> {
        let err = |key: &str, problem: String| RecordError {
            origin: origin.to_string(),
            key: key.to_string(),
            problem,
        };
        let raw: RawRecord = toml::from_str(text).map_err(|e| {
            err(
                "",
                format!(
                    "{}: correct the file (its keys: name, chain, travel_mm, tool_mm, target_every_mm, runs, [squares.XY], [squares.ZX], [squares.YZ])",
                    e.message().trim_end_matches('\n')
                ),
            )
        })?;
        let name = raw.name.trim().to_string();
        if name.is_empty() {
            return Err(err(
                "name",
                "is empty: name the machine (its serial, say)".into(),
            ));
        }
        let chain = parse_chain(&raw.chain).map_err(|p| err("chain", p))?;
        for (k, &t) in raw.travel_mm.iter().enumerate() {
            if !(t > 0.0 && t <= MAX_TRAVEL_MM) {
                return Err(err(
                    "travel_mm",
                    format!(
                        "{} is {t} mm: give each axis's travel in mm, above 0 and at most {MAX_TRAVEL_MM:.0}",
                        MachineAxis::ALL[k]
                    ),
                ));
            }
        }
        if raw
            .tool_mm
            .iter()
            .any(|v| !v.is_finite() || v.abs() > 2000.0)
        {
            return Err(err(
                "tool_mm",
                format!(
                    "({}, {}, {}) mm: give the tool offset's three components in mm, each within ±2000",
                    raw.tool_mm[0], raw.tool_mm[1], raw.tool_mm[2]
                ),
            ));
        }
        let shortest = raw.travel_mm.iter().fold(f64::INFINITY, |a, &b| a.min(b));
        if !(raw.target_every_mm >= 1.0 && raw.target_every_mm <= shortest / 4.0) {
            return Err(err(
                "target_every_mm",
                format!(
                    "is {} mm: between 1 mm and a quarter of the shortest travel ({:.1} mm), so that each axis has five targets or more",
                    raw.target_every_mm,
                    shortest / 4.0
                ),
            ));
        }
        if !(1..=crate::run::plan::MAX_RUNS).contains(&raw.runs) {
            return Err(err(
                "runs",
                format!(
                    "is {}: from 1 to {} bidirectional runs per set-up",
                    raw.runs,
                    crate::run::plan::MAX_RUNS
                ),
            ));
        }
        let mut squares = Vec::new();
        for pair in SquarePair::ALL {
            let key = format!("squares.{pair}");
            let s = raw.squares.get(&pair.to_string()).ok_or_else(|| {
                err(
                    &key,
                    format!(
                        "is missing: copy the certificate of the optical square used for {} ({pair}): id, deviation_arcsec, u_arcsec",
                        pair.name()
                    ),
                )
            })?;
            if s.id.trim().is_empty() {
                return Err(err(
                    &format!("{key}.id"),
                    "is empty: the certificate's number".into(),
                ));
            }
            if !(s.deviation_arcsec.is_finite() && s.deviation_arcsec.abs() <= MAX_DEVIATION_ARCSEC)
            {
                return Err(err(
                    &format!("{key}.deviation_arcsec"),
                    format!(
                        "is {}″: the certificate's deviation from 90° in arcseconds, within ±{MAX_DEVIATION_ARCSEC:.0}",
                        s.deviation_arcsec
                    ),
                ));
            }
            if !(s.u_arcsec > 0.0 && s.u_arcsec <= 10.0) {
                return Err(err(
                    &format!("{key}.u_arcsec"),
                    format!(
                        "is {}″: the certificate's standard uncertainty in arcseconds, above 0 and at most 10",
                        s.u_arcsec
                    ),
                ));
            }
            squares.push(SquareCertificate {
                id: s.id.trim().to_string(),
                deviation_rad: s.deviation_arcsec * RAD_PER_ARCSEC,
                u_rad: s.u_arcsec * RAD_PER_ARCSEC,
            });
        }
        if let Some(other) = raw
            .squares
            .keys()
            .find(|k| !SquarePair::ALL.iter().any(|p| p.to_string() == **k))
        {
            return Err(err(
                &format!("squares.{other}"),
                "is not a pair: the pairs are XY, ZX and YZ".into(),
            ));
        }
        let squares: [SquareCertificate; 3] = squares
            .try_into()
            .map_err(|_| err("squares", "three certificates are needed".into()))?;
        Ok(MachineRecord {
            name,
            chain,
            travel_mm: raw.travel_mm,
            tool_mm: raw.tool_mm,
            target_every_mm: raw.target_every_mm,
            runs: raw.runs,
            squares,
        })
    }

    /// The record as TOML: reads back with [`MachineRecord::from_toml`] to the same record.
    pub fn to_toml(&self) -> String {
        let raw = RawRecord {
            name: self.name.clone(),
            chain: self.chain.to_string(),
            travel_mm: self.travel_mm,
            tool_mm: self.tool_mm,
            target_every_mm: self.target_every_mm,
            runs: self.runs,
            squares: SquarePair::ALL
                .iter()
                .map(|p| {
                    let c = &self.squares[p.index()];
                    (
                        p.to_string(),
                        RawSquare {
                            id: c.id.clone(),
                            deviation_arcsec: c.deviation_rad / RAD_PER_ARCSEC,
                            u_arcsec: c.u_rad / RAD_PER_ARCSEC,
                        },
                    )
                })
                .collect(),
        };
        toml::to_string(&raw).unwrap_or_else(|e| {
            unreachable!("a record of strings, numbers and tables serialises: {e}")
        })
    }
}

/// A chain as written: the three axes from the workpiece to the tool, with `bed` where the
/// machine's bed sits among them; `workpiece` and `tool` at the ends may be written or not,
/// the words apart by spaces, dashes (-, –) or commas.
pub fn parse_chain(s: &str) -> Result<Chain, String> {
    let words: Vec<&str> = s
        .split(|c: char| c.is_whitespace() || c == '-' || c == '–' || c == ',')
        .filter(|w| !w.is_empty())
        .collect();
    let mut inner: &[&str] = &words;
    if inner
        .first()
        .is_some_and(|w| w.eq_ignore_ascii_case("workpiece"))
    {
        inner = &inner[1..];
    }
    if inner.last().is_some_and(|w| w.eq_ignore_ascii_case("tool")) {
        inner = &inner[..inner.len() - 1];
    }
    let how =
        "write it from the workpiece to the tool, e.g. \"workpiece – X – Y – bed – Z – tool\"";
    let beds: Vec<usize> = (0..inner.len())
        .filter(|&i| inner[i].eq_ignore_ascii_case("bed"))
        .collect();
    if beds.len() != 1 || inner.len() != 4 {
        return Err(format!("\"{s}\" is not three axes and one bed: {how}"));
    }
    let mut order = Vec::new();
    for w in inner.iter().filter(|w| !w.eq_ignore_ascii_case("bed")) {
        order.push(
            MachineAxis::from_letter(&w.to_ascii_uppercase())
                .ok_or_else(|| format!("\"{w}\" in \"{s}\" is not an axis (X, Y or Z): {how}"))?,
        );
    }
    let order: [MachineAxis; 3] = order
        .try_into()
        .map_err(|_| format!("\"{s}\" does not name three axes: {how}"))?;
    Chain::new(order, beds[0]).map_err(|e| e.to_string())
}
