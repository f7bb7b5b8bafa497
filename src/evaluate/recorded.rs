//! What a run records of its uncertainty budget's inputs when it starts, so that a report
//! made from the store years later states the same budget (ISO/TR 230-9) the run had: the
//! follower error map in use (by its store id, and where the follower's encoder stood
//! against the carriage), the calibration's own standard uncertainty, the drift check's
//! range, the temperature inputs and PSD2's sensitivities through the run's decoupling.
//!
//! It lives in the run's configuration snapshot (`runs.config_json`) under the key
//! [`KEY`]; no schema change. A run stored before runs recorded it has no such key: its
//! report names those terms "not recorded". Each input is either stated or not, and when not
//! the record says why in words (`{"not_stated": "no drift check …"}`). User units
//! throughout (µm, arcsec, K), as every file of the project.

use crate::units::DOF_TO_USER;
use serde::{Deserialize, Serialize};

/// The key of the run configuration's object that holds the record.
pub const KEY: &str = "budget";

/// One input: its value, or why there is none.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Stated<T> {
    Stated(T),
    NotStated(String),
}

impl<T> Stated<T> {
    /// The value, when stated.
    pub fn value(&self) -> Option<&T> {
        match self {
            Stated::Stated(v) => Some(v),
            Stated::NotStated(_) => None,
        }
    }
}

/// The follower error map a run used.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RecordedMap {
    /// Its id in the store.
    pub id: i64,
    pub name: String,
    /// `certificate`, `self-calibration` or `both`.
    pub source: String,
    /// When it was stored (RFC 3339, UTC).
    pub created: String,
    /// How much more the follower's encoder read than the carriage's measured position when
    /// the run started (mm): the map is indexed by the encoder, the budget's points by the
    /// carriage. `None`: the carriage's position was not measured then (no zero reference);
    /// the encoder is taken to read the carriage's position.
    #[serde(default)]
    pub encoder_offset_mm: Option<f64>,
}

/// The calibration's own standard uncertainty per DOF.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RecordedCalibration {
    /// Its id in the store, when it is there.
    #[serde(default)]
    pub id: Option<i64>,
    /// dx, dy, dz in µm; ex, ey, ez in arcsec (k = 1).
    pub u_um_arcsec: [f64; 6],
    /// How the values were made, in words.
    pub source: String,
}

impl RecordedCalibration {
    /// The values in internal units (mm, rad).
    pub fn internal(&self) -> [f64; 6] {
        std::array::from_fn(|k| self.u_um_arcsec[k] / DOF_TO_USER[k])
    }
}

/// The drift check's result (ISO 230-2: the head reads the carriage at rest at the
/// reference for the test's duration).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RecordedDrift {
    /// The range E_VE per DOF: µm and arcsec.
    pub range_um_arcsec: [f64; 6],
    /// How long it read (s), when known.
    #[serde(default)]
    pub duration_s: Option<f64>,
}

impl RecordedDrift {
    /// The range in internal units (mm, rad).
    pub fn internal(&self) -> [f64; 6] {
        std::array::from_fn(|k| self.range_um_arcsec[k] / DOF_TO_USER[k])
    }
}

/// The temperature terms' inputs; the mean departure from 20 °C is the captures' own (their
/// material temperature), so a report computes it from them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RecordedThermal {
    /// The axis scale's expansion coefficient and its standard uncertainty, µm/(m·K).
    pub alpha_um_per_m_k: f64,
    pub u_alpha_um_per_m_k: f64,
    /// The material temperature sensor's standard uncertainty (K).
    pub u_temperature_k: f64,
}

/// The record.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RecordedBudget {
    pub follower_map: Stated<RecordedMap>,
    /// With no map: the follower stage's specification the run's budget stated instead,
    /// ±µm along its axis and ±µm vertical straightness (rectangular).
    #[serde(default)]
    pub follower_spec_um: Option<[f64; 2]>,
    pub calibration: Stated<RecordedCalibration>,
    pub drift: Stated<RecordedDrift>,
    pub thermal: Stated<RecordedThermal>,
    /// |∂e_k/∂X2| and |∂e_k/∂Y2| through the run's own decoupling at mid-travel (internal
    /// units per mm of PSD2 reading); `None`: a report takes them from the layout.
    #[serde(default)]
    pub psd2_sensitivity: Option<[[f64; 2]; 6]>,
}

/// What a stored run says of its budget's inputs.
#[derive(Clone, Debug, PartialEq)]
pub enum Recorded {
    /// The run recorded them.
    Yes(Box<RecordedBudget>),
    /// A run stored before runs recorded them.
    No,
    /// The record is there but cannot be read (why, in words).
    Unreadable(String),
}

impl Recorded {
    /// From a run's configuration snapshot.
    pub fn of_config(config: &serde_json::Value) -> Recorded {
        match config.get(KEY) {
            None | Some(serde_json::Value::Null) => Recorded::No,
            Some(v) => match serde_json::from_value::<RecordedBudget>(v.clone()) {
                Ok(r) => Recorded::Yes(Box::new(r)),
                Err(e) => Recorded::Unreadable(e.to_string()),
            },
        }
    }

    /// The record, when there is one.
    pub fn budget(&self) -> Option<&RecordedBudget> {
        match self {
            Recorded::Yes(r) => Some(r),
            _ => None,
        }
    }

    /// Why an input is not known, for a run without a readable record.
    pub fn missing(&self) -> Option<String> {
        match self {
            Recorded::Yes(_) => None,
            Recorded::No => Some(
                "not recorded: the run was stored before runs recorded their budget's inputs"
                    .into(),
            ),
            Recorded::Unreadable(e) => Some(format!(
                "not recorded: the run's record of its budget's inputs cannot be read ({e})"
            )),
        }
    }
}

impl RecordedBudget {
    /// As the value of [`KEY`] in a run's configuration.
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::to_value(self).unwrap_or(serde_json::Value::Null)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> RecordedBudget {
        RecordedBudget {
            follower_map: Stated::Stated(RecordedMap {
                id: 3,
                name: "vendor.csv".into(),
                source: "certificate".into(),
                created: "2026-01-02T03:04:05Z".into(),
                encoder_offset_mm: Some(-1.25),
            }),
            follower_spec_um: None,
            calibration: Stated::Stated(RecordedCalibration {
                id: Some(2),
                u_um_arcsec: [0.1, 0.2, 0.3, 0.4, 0.5, 0.6],
                source: "hold-out".into(),
            }),
            drift: Stated::NotStated("no drift check".into()),
            thermal: Stated::NotStated("no material temperature sensor".into()),
            psd2_sensitivity: None,
        }
    }

    #[test]
    fn the_record_reads_back_from_a_run_configuration() {
        let r = sample();
        let config = serde_json::json!({"dialect": "iso", KEY: r.to_json()});
        assert_eq!(
            Recorded::of_config(&config),
            Recorded::Yes(Box::new(r.clone()))
        );
        // The form a reader of the store sees.
        assert_eq!(config[KEY]["drift"]["not_stated"], "no drift check");
        assert_eq!(config[KEY]["follower_map"]["stated"]["id"], 3);
        let cal = r.calibration.value().expect("stated").internal();
        assert!((cal[1] - 0.2e-3).abs() < 1e-15);
        assert!((cal[4] - 0.5 * crate::units::RAD_PER_ARCSEC).abs() < 1e-18);
    }

    #[test]
    fn a_run_without_the_key_is_not_recorded_and_a_bad_one_says_why() {
        let old = serde_json::json!({"capture": {}, "dialect": "iso"});
        assert_eq!(Recorded::of_config(&old), Recorded::No);
        assert!(
            Recorded::No
                .missing()
                .is_some_and(|m| m.starts_with("not recorded"))
        );
        let bad = serde_json::json!({KEY: {"calibration": 3}});
        let r = Recorded::of_config(&bad);
        assert!(matches!(r, Recorded::Unreadable(_)), "{r:?}");
        assert!(r.missing().is_some_and(|m| m.contains("cannot be read")));
    }
}
