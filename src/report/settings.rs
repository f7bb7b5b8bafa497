//! `[machine]` and `[acceptance]`: who and what an acceptance report is about (machine name,
//! serial number, customer, the scale's expansion coefficient for thermal normalisation) and
//! the tolerances it judges against. Raw (as written) then validated, like every section
//! (DESIGN §11); errors name the key.

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

fn non_negative(key: &str, v: f64) -> Result<f64, (String, String)> {
    if v.is_finite() && v >= 0.0 {
        Ok(v)
    } else {
        Err((
            key.to_string(),
            format!("{v} must be zero (not specified) or positive"),
        ))
    }
}

/// Validate both sections; an error is (key, problem).
pub fn validate(
    m: &RawMachine,
    a: &RawAcceptance,
) -> Result<(MachineSettings, AcceptanceSettings), (String, String)> {
    let alpha = non_negative("machine.expansion_um_per_m_k", m.expansion_um_per_m_k)?;
    if alpha > 100.0 {
        return Err((
            "machine.expansion_um_per_m_k".into(),
            format!(
                "{alpha} µm/(m·K) is not an expansion coefficient of a machine's scale \
                 (steel 11.5, cast iron 10.5, glass scales 8 to 10); give µm per metre and kelvin"
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
        if non_negative(key, v)? > 0.0 {
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
        assert!(problem.contains("-1 must be zero"), "{problem}");
        let m = RawMachine {
            expansion_um_per_m_k: 11.5e3,
            ..Default::default()
        };
        assert!(validate(&m, &RawAcceptance::default()).is_err());
    }
}
