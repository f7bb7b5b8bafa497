//! `[comp.<controller>]`: each exporter's controller settings, in two stages (raw from the
//! configuration layers, then checked into the exporters' options). CLI flags override them.
//! Defaults are the documented ones (`src/config/defaults.toml`).

use super::fanuc::ValueRange;
use super::heidenhain::{Backlash, Family};
use super::linuxcnc::Units;
use super::mitsubishi::Mode;
use super::siemens::{EndHandling, SiemensControl};
use crate::util::range::{POSITION_MM, Range};
use serde::{Deserialize, Serialize};

/// `[comp.siemens]`
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawSiemens {
    /// "840d" or "828d" (828D/808D: CEC tables fixed at 200 points).
    pub control: String,
    /// The machine axis name (MD10000); empty: the control's default, X1/Y1/Z1.
    pub machine_axis: String,
    /// The base axis's machine name for CEC; empty: its default.
    pub input_axis: String,
    pub encoder: u8,
    /// MD38000 $MA_MM_ENC_COMP_MAX_POINTS.
    pub enc_comp_max_points: usize,
    /// MD18342 $MN_MM_CEC_MAX_POINTS[t].
    pub cec_max_points: usize,
    pub cec_table: usize,
    /// "hold" or "zero".
    pub ends: String,
}

impl Default for RawSiemens {
    fn default() -> Self {
        RawSiemens {
            control: "840d".into(),
            machine_axis: String::new(),
            input_axis: String::new(),
            encoder: 0,
            enc_comp_max_points: 125,
            cec_max_points: 200,
            cec_table: 0,
            ends: "hold".into(),
        }
    }
}

/// `[comp.fanuc]`
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawFanuc {
    /// "0i" (−128..127), "legacy" (±7), "30i" (−32768..32767).
    pub family: String,
    /// Controlled axis number; 0: X 1, Y 2, Z 3.
    pub axis_number: u8,
    /// Parameter 3620; absent: the most negative point is number 0.
    pub reference_number: Option<u16>,
    pub max_number: u16,
    pub max_points: usize,
    pub input_increment_mm: f64,
    pub detection_unit_mm: f64,
    pub magnification: u8,
    /// The axis's maximum feed rate: the interval must be at least this / 7500.
    pub max_feed_mm_min: f64,
    /// Parameter 3626 for bidirectional tables; absent: after the positive set.
    pub negative_start: Option<u16>,
}

impl Default for RawFanuc {
    fn default() -> Self {
        RawFanuc {
            family: "0i".into(),
            axis_number: 0,
            reference_number: None,
            max_number: 1023,
            max_points: 128,
            input_increment_mm: 0.001,
            detection_unit_mm: 0.001,
            magnification: 1,
            max_feed_mm_min: 24000.0,
            negative_start: None,
        }
    }
}

/// `[comp.linuxcnc]`
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawLinuxcnc {
    /// "mm" or "inch": the machine's `[TRAJ]LINEAR_UNITS`.
    pub units: String,
    /// The joints the axis drives (two for a gantry); empty: X 0, Y 1, Z 2.
    pub joints: Vec<u8>,
    pub max_points: usize,
}

impl Default for RawLinuxcnc {
    fn default() -> Self {
        RawLinuxcnc {
            units: "mm".into(),
            joints: Vec::new(),
            max_points: 256,
        }
    }
}

/// `[comp.heidenhain]`
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawHeidenhain {
    /// "tnc640" (TNC 640 / MANUALplus 620) or "tnc4xx" (TNC 4xx / iTNC 530).
    pub family: String,
    /// The compensated axis's key in CfgAxes/axisList; empty: its letter.
    pub axis_key: String,
    pub max_points: usize,
    /// The machine datum's position in the measured coordinates (mm).
    pub datum_mm: f64,
    /// "negative" (e↓) or "reversal" (e↓ − e↑).
    pub backlash: String,
}

impl Default for RawHeidenhain {
    fn default() -> Self {
        RawHeidenhain {
            family: "tnc640".into(),
            axis_key: String::new(),
            max_points: 256,
            datum_mm: 0.0,
            backlash: "negative".into(),
        }
    }
}

/// `[comp.beckhoff]`
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawBeckhoff {
    /// Logical axis number; 0: X 1, Y 2, Z 3.
    pub axis_number: u16,
    /// Logical axis name; empty: the letter.
    pub axis_name: String,
    /// P-COMP-00059.
    pub max_points: usize,
}

impl Default for RawBeckhoff {
    fn default() -> Self {
        RawBeckhoff {
            axis_number: 0,
            axis_name: String::new(),
            max_points: super::beckhoff::MAX_POINTS,
        }
    }
}

/// `[comp.mitsubishi]`
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawMitsubishi {
    /// "absolute" or "incremental".
    pub mode: String,
    pub output_unit_mm: f64,
    pub scale: u8,
    pub first_number: u16,
    pub max_points: usize,
}

impl Default for RawMitsubishi {
    fn default() -> Self {
        RawMitsubishi {
            mode: "absolute".into(),
            output_unit_mm: 0.001,
            scale: 1,
            first_number: 1,
            max_points: 1024,
        }
    }
}

/// `[comp]`
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawComp {
    pub siemens: RawSiemens,
    pub fanuc: RawFanuc,
    pub linuxcnc: RawLinuxcnc,
    pub heidenhain: RawHeidenhain,
    pub beckhoff: RawBeckhoff,
    pub mitsubishi: RawMitsubishi,
}

/// Checked `[comp]`: the raw values with their words turned into the exporters' types.
#[derive(Clone, Debug, PartialEq)]
pub struct CompSettings {
    pub raw: RawComp,
    pub siemens_control: SiemensControl,
    pub siemens_ends: EndHandling,
    pub fanuc_range: ValueRange,
    pub linuxcnc_units: Units,
    pub heidenhain_family: Family,
    pub heidenhain_backlash: Backlash,
    pub mitsubishi_mode: Mode,
}

/// One word of a closed set, or (key, what to write).
fn word<T: Copy>(key: &str, v: &str, set: &[(&str, T)]) -> Result<T, (String, String)> {
    set.iter()
        .find(|(w, _)| *w == v)
        .map(|(_, t)| *t)
        .ok_or_else(|| {
            let names: Vec<String> = set.iter().map(|(w, _)| format!("\"{w}\"")).collect();
            (
                key.to_string(),
                format!("\"{v}\" is not one of {}", names.join(", ")),
            )
        })
}

pub fn siemens_control(v: &str) -> Result<SiemensControl, (String, String)> {
    word(
        "comp.siemens.control",
        v,
        &[
            ("840d", SiemensControl::S840d),
            ("828d", SiemensControl::S828d),
        ],
    )
}

pub fn fanuc_family(v: &str) -> Result<ValueRange, (String, String)> {
    word(
        "comp.fanuc.family",
        v,
        &[
            ("0i", ValueRange::Int8),
            ("legacy", ValueRange::Pm7),
            ("30i", ValueRange::Int16),
        ],
    )
}

pub fn linuxcnc_units(v: &str) -> Result<Units, (String, String)> {
    word(
        "comp.linuxcnc.units",
        v,
        &[("mm", Units::Mm), ("inch", Units::Inch)],
    )
}

pub fn heidenhain_family(v: &str) -> Result<Family, (String, String)> {
    word(
        "comp.heidenhain.family",
        v,
        &[("tnc640", Family::Tnc640), ("tnc4xx", Family::Tnc4xx)],
    )
}

pub fn mitsubishi_mode(v: &str) -> Result<Mode, (String, String)> {
    word(
        "comp.mitsubishi.mode",
        v,
        &[
            ("absolute", Mode::Absolute),
            ("incremental", Mode::Incremental),
        ],
    )
}

/// Check `[comp]`; an error is (key, problem).
pub fn validate(raw: &RawComp) -> Result<CompSettings, (String, String)> {
    // A control's units: down to 1 nm (IS-D and finer), up to 1 mm.
    let unit = Range::new(1e-6, 1.0, "mm");
    for (key, v, r) in [
        (
            "comp.fanuc.input_increment_mm",
            raw.fanuc.input_increment_mm,
            unit,
        ),
        (
            "comp.fanuc.detection_unit_mm",
            raw.fanuc.detection_unit_mm,
            unit,
        ),
        (
            "comp.fanuc.max_feed_mm_min",
            raw.fanuc.max_feed_mm_min,
            Range::new(1.0, 1e6, "mm/min"),
        ),
        (
            "comp.mitsubishi.output_unit_mm",
            raw.mitsubishi.output_unit_mm,
            unit,
        ),
        (
            "comp.heidenhain.datum_mm",
            raw.heidenhain.datum_mm,
            POSITION_MM,
        ),
    ] {
        r.check(v).map_err(|p| (key.to_string(), p))?;
    }
    if !(1..=100).contains(&raw.fanuc.magnification) {
        return Err((
            "comp.fanuc.magnification".into(),
            format!(
                "{} is outside parameter 3623's 1 to 100",
                raw.fanuc.magnification
            ),
        ));
    }
    Ok(CompSettings {
        siemens_control: siemens_control(&raw.siemens.control)?,
        siemens_ends: word(
            "comp.siemens.ends",
            &raw.siemens.ends,
            &[("hold", EndHandling::Hold), ("zero", EndHandling::Zero)],
        )?,
        fanuc_range: fanuc_family(&raw.fanuc.family)?,
        linuxcnc_units: linuxcnc_units(&raw.linuxcnc.units)?,
        heidenhain_family: heidenhain_family(&raw.heidenhain.family)?,
        heidenhain_backlash: word(
            "comp.heidenhain.backlash",
            &raw.heidenhain.backlash,
            &[
                ("negative", Backlash::Negative),
                ("reversal", Backlash::Reversal),
            ],
        )?,
        mitsubishi_mode: word(
            "comp.mitsubishi.mode",
            &raw.mitsubishi.mode,
            &[
                ("absolute", Mode::Absolute),
                ("incremental", Mode::Incremental),
            ],
        )?,
        raw: raw.clone(),
    })
}
