//! `[machine]` and `[acceptance]`: who and what an acceptance report is about (machine name,
//! serial number, customer, the scale's expansion coefficient for thermal normalisation) and
//! the tolerances it judges against. Raw (as written) then validated, like every section
//! (DESIGN §11); errors name the key.

use crate::util::range::{Range, num};
use serde::{Deserialize, Serialize};

/// `[machine]` as written.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawMachine {
    pub name: String,
    pub serial: String,
    pub customer: String,
    /// µm/(m·K) of the axis's scale; 0: positioning is not normalised to 20 °C.
    pub expansion_um_per_m_k: f64,
}

/// `[acceptance]` as written: tolerances, 0 = not specified.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawAcceptance {
    pub a_um: f64,
    pub e_um: f64,
    pub r_um: f64,
    pub b_um: f64,
    pub m_um: f64,
    pub straightness_um: f64,
    pub pitch_arcsec: f64,
    pub roll_arcsec: f64,
    pub yaw_arcsec: f64,
}

/// `[machine]`, validated.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MachineSettings {
    pub name: String,
    pub serial: String,
    pub customer: String,
    /// µm/(m·K); `None`: not configured.
    pub expansion_um_per_m_k: Option<f64>,
}

/// One tolerance: the figure it applies to, the limit in the figure's unit.
#[derive(Clone, Debug, PartialEq)]
pub struct Tolerance {
    /// "A", "E", "R", "B", "M", "straightness", "pitch", "roll", "yaw".
    pub figure: &'static str,
    pub limit: f64,
    pub unit: &'static str,
    /// The configuration key, for the report.
    pub key: &'static str,
}

/// `[acceptance]`, validated: the tolerances that were given.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AcceptanceSettings {
    pub tolerances: Vec<Tolerance>,
}

impl AcceptanceSettings {
    /// The tolerance of `figure`, when one is configured.
    pub fn of(&self, figure: &str) -> Option<&Tolerance> {
        self.tolerances.iter().find(|t| t.figure == figure)
    }
}

/// A tolerance in `unit`: 0 (not specified), or from a hundredth to `max`.
fn tolerance(key: &str, v: f64, max: f64, unit: &'static str) -> Result<f64, (String, String)> {
    Range::new(0.01, max, unit)
        .or_zero("not specified")
        .check(v)
        .map_err(|p| (key.to_string(), p))
}

/// Validate both sections; an error is (key, problem).
pub fn validate(
    m: &RawMachine,
    a: &RawAcceptance,
) -> Result<(MachineSettings, AcceptanceSettings), (String, String)> {
    let alpha = m.expansion_um_per_m_k;
    // Below a hundredth even Zerodur's 0.05 is far; above 100 no scale is.
    if alpha != 0.0 && !(0.01..=100.0).contains(&alpha) {
        return Err((
            "machine.expansion_um_per_m_k".into(),
            format!(
                "{} µm/(m·K) is not an expansion coefficient of a machine's scale \
                 (steel 11.5, cast iron 10.5, glass scales 8 to 10); give µm per metre and kelvin, \
                 0.01 to 100, or 0 to leave positioning as measured",
                num(alpha)
            ),
        ));
    }
    let machine = MachineSettings {
        name: m.name.trim().to_string(),
        serial: m.serial.trim().to_string(),
        customer: m.customer.trim().to_string(),
        expansion_um_per_m_k: (alpha > 0.0).then_some(alpha),
    };
    let mut tolerances = Vec::new();
    // Tolerances up to 10 mm or a degree: beyond them nothing is judged.
    for (figure, key, v, unit) in [
        ("A", "acceptance.a_um", a.a_um, "µm"),
        ("E", "acceptance.e_um", a.e_um, "µm"),
        ("R", "acceptance.r_um", a.r_um, "µm"),
        ("B", "acceptance.b_um", a.b_um, "µm"),
        ("M", "acceptance.m_um", a.m_um, "µm"),
        (
            "straightness",
            "acceptance.straightness_um",
            a.straightness_um,
            "µm",
        ),
        ("pitch", "acceptance.pitch_arcsec", a.pitch_arcsec, "arcsec"),
        ("roll", "acceptance.roll_arcsec", a.roll_arcsec, "arcsec"),
        ("yaw", "acceptance.yaw_arcsec", a.yaw_arcsec, "arcsec"),
    ] {
        let max = if unit == "µm" { 10_000.0 } else { 3600.0 };
        if tolerance(key, v, max, unit)? > 0.0 {
            tolerances.push(Tolerance {
                figure,
                limit: v,
                unit,
                key,
            });
        }
    }
    Ok((machine, AcceptanceSettings { tolerances }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_is_unspecified_and_negative_is_refused() {
        let a = RawAcceptance {
            e_um: 8.0,
            ..Default::default()
        };
        let (m, t) = validate(&RawMachine::default(), &a).unwrap();
        assert_eq!(m.expansion_um_per_m_k, None);
        assert_eq!(t.tolerances.len(), 1);
        assert_eq!(t.of("E").map(|t| t.limit), Some(8.0));
        let bad = RawAcceptance {
            r_um: -1.0,
            ..Default::default()
        };
        let (key, problem) = validate(&RawMachine::default(), &bad).unwrap_err();
        assert_eq!(key, "acceptance.r_um");
        assert_eq!(
            problem,
            "-1 µm is out of range: use 0 (not specified) or 0.01 to 10000 µm"
        );
        let m = RawMachine {
            expansion_um_per_m_k: 11.5e3,
            ..Default::default()
        };
        assert!(validate(&m, &RawAcceptance::default()).is_err());
    }
}
