//! A follower map as the store keeps it: the map's TOML ([`FollowerMap::to_toml`]), the
//! certificate it was built from (a `[certificate]` table, so that a later self-calibration
//! combines with it) and the self-calibration's steps with the fit's settings (a
//! `[self_calibration_steps]` table, so that the map can be fitted again later: with a
//! level's stations, or by a newer fit).
//!
//! The steps are kept compactly, one CSV line per step in one string (`rows`), the columns
//! named in `columns`: encoder before and after (mm), PSD2's displacement along and vertical
//! (mm) and their variances (mm²), every number written so that it reads back exactly.
//! Maps stored before the steps were kept read back without them ([`StoredMap::steps`] is
//! `None`: such a map cannot be fitted again; map the follower anew).

use super::{Certificate, FollowerMap, MapError, MapSettings, Step};
use serde::{Deserialize, Serialize};

/// The key of the certificate's points in a stored map's TOML.
const CERTIFICATE_KEY: &str = "certificate";
/// The key of the self-calibration's steps.
const STEPS_KEY: &str = "self_calibration_steps";
/// The steps' columns, in order.
pub const STEP_COLUMNS: &str =
    "from_mm,to_mm,along_mm,vertical_mm,variance_along_mm2,variance_vertical_mm2";

/// The self-calibration's steps kept with a map, and the settings its fit took them with.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredSteps {
    pub settings: MapSettings,
    /// In the order taken.
    pub steps: Vec<Step>,
}

/// A map as the store keeps it.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredMap {
    pub map: FollowerMap,
    /// The certificate the map was built from, when it had one.
    pub certificate: Option<Certificate>,
    /// The self-calibration's steps, when they were kept (maps stored since they are).
    pub steps: Option<StoredSteps>,
}

/// The steps' table in the TOML.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSteps {
    lead_mm: f64,
    long_degree: usize,
    merge_mm: f64,
    columns: String,
    rows: String,
}

impl StoredSteps {
    fn to_raw(&self) -> RawSteps {
        let mut rows = String::with_capacity(self.steps.len() * 100);
        for s in &self.steps {
            // `{}` writes the shortest text that reads back to the same f64.
            rows.push_str(&format!(
                "{},{},{},{},{},{}\n",
                s.from_mm, s.to_mm, s.along_mm, s.vertical_mm, s.variance[0], s.variance[1]
            ));
        }
        RawSteps {
            lead_mm: self.settings.lead_mm,
            long_degree: self.settings.long_degree,
            merge_mm: self.settings.merge_mm,
            columns: STEP_COLUMNS.to_string(),
            rows,
        }
    }

    fn from_raw(raw: RawSteps, file: &str) -> Result<StoredSteps, MapError> {
        let bad = |problem: String| MapError::File {
            file: file.to_string(),
            problem: format!("{STEPS_KEY}: {problem}"),
        };
        if raw.columns.replace(' ', "") != STEP_COLUMNS {
            return Err(bad(format!(
                "columns \"{}\": expected \"{STEP_COLUMNS}\"",
                raw.columns
            )));
        }
        let settings = MapSettings {
            lead_mm: raw.lead_mm,
            long_degree: raw.long_degree,
            merge_mm: raw.merge_mm,
        };
        let lead_ok = settings.lead_mm.is_finite() && settings.lead_mm > 0.0;
        let merge_ok = settings.merge_mm.is_finite() && settings.merge_mm >= 0.0;
        if !(lead_ok && merge_ok) {
            return Err(bad(format!(
                "lead_mm {} and merge_mm {}: give a positive lead and a merge of 0 or more",
                settings.lead_mm, settings.merge_mm
            )));
        }
        let mut steps = Vec::new();
        for (i, line) in raw.rows.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() {
                continue;
            }
            let v: Vec<f64> = line
                .split(',')
                .map(|t| t.trim().parse::<f64>())
                .collect::<Result<_, _>>()
                .map_err(|e| bad(format!("row {}: {e} in \"{line}\"", i + 1)))?;
            if v.len() != 6 || !v.iter().all(|x| x.is_finite()) {
                return Err(bad(format!(
                    "row {}: \"{line}\" is not six finite numbers ({STEP_COLUMNS})",
                    i + 1
                )));
            }
            steps.push(Step {
                from_mm: v[0],
                to_mm: v[1],
                along_mm: v[2],
                vertical_mm: v[3],
                variance: [v[4], v[5]],
            });
        }
        Ok(StoredSteps { settings, steps })
    }
}

impl StoredMap {
    /// The map's TOML, then its certificate and its steps (when it has them).
    pub fn to_toml(&self) -> String {
        let mut text = self.map.to_toml();
        let mut table = |key: &str, value: Result<toml::Value, toml::ser::Error>| {
            let mut wrap = toml::Table::new();
            let t = value.and_then(|v| {
                wrap.insert(key.to_string(), v);
                toml::to_string(&wrap)
            });
            if !text.ends_with('\n') {
                text.push('\n');
            }
            match t {
                Ok(t) => text.push_str(&t),
                Err(e) => text.push_str(&format!("# the {key} could not be written: {e}\n")),
            }
        };
        if let Some(c) = &self.certificate {
            table(CERTIFICATE_KEY, toml::Value::try_from(c));
        }
        if let Some(s) = &self.steps {
            table(STEPS_KEY, toml::Value::try_from(s.to_raw()));
        }
        text
    }

    /// Read a map written by [`StoredMap::to_toml`] (or [`FollowerMap::to_toml`], or stored
    /// before the steps or the certificate were kept); `file` names it in errors.
    pub fn from_toml(text: &str, file: &str) -> Result<StoredMap, MapError> {
        let bad = |e: toml::de::Error| MapError::File {
            file: file.to_string(),
            problem: format!("not a follower map: {}", e.message()),
        };
        let mut table: toml::Table = toml::from_str(text).map_err(bad)?;
        let certificate = match table.remove(CERTIFICATE_KEY) {
            Some(v) => Some(v.try_into::<Certificate>().map_err(bad)?),
            None => None,
        };
        let steps = match table.remove(STEPS_KEY) {
            Some(v) => Some(StoredSteps::from_raw(
                v.try_into::<RawSteps>().map_err(bad)?,
                file,
            )?),
            None => None,
        };
        let map: FollowerMap = toml::Value::Table(table).try_into().map_err(bad)?;
        Ok(StoredMap {
            map,
            certificate,
            steps,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn steps() -> StoredSteps {
        let mut rng = crate::sim::Rng::new(3);
        let steps = (0..40)
            .map(|k| {
                let a = k as f64 * 3.75 + rng.gauss(1e-3);
                Step {
                    from_mm: a,
                    to_mm: a + 3.75 + rng.gauss(1e-3),
                    along_mm: 3.75 + rng.gauss(1e-4),
                    vertical_mm: rng.gauss(1e-4),
                    variance: [rng.gauss(1e-9).abs(), 1.0 / 3.0 * 1e-8],
                }
            })
            .collect();
        StoredSteps {
            settings: MapSettings {
                lead_mm: 5.0,
                long_degree: 2,
                merge_mm: 0.5,
            },
            steps,
        }
    }

    /// The steps come back bit for bit, with the certificate and the map; one line a step.
    #[test]
    fn the_steps_round_trip_exactly() {
        let s = steps();
        let cert = Certificate::parse(
            "position_mm,error_um,direction,uncertainty_um\n0,0,+,0.2\n200,1.5,+,0.2\n",
            "c.csv",
        )
        .unwrap();
        let map = super::super::build(&s.steps, Some(&cert), &s.settings).unwrap();
        let stored = StoredMap {
            map,
            certificate: Some(cert),
            steps: Some(s.clone()),
        };
        let text = stored.to_toml();
        assert!(
            text.contains(&format!("columns = \"{STEP_COLUMNS}\"")),
            "{text}"
        );
        let back = StoredMap::from_toml(&text, "map 1").unwrap();
        assert_eq!(back, stored);
        let bits = |v: &StoredSteps| {
            v.steps
                .iter()
                .flat_map(|s| {
                    [
                        s.from_mm,
                        s.to_mm,
                        s.along_mm,
                        s.vertical_mm,
                        s.variance[0],
                        s.variance[1],
                    ]
                })
                .map(f64::to_bits)
                .collect::<Vec<_>>()
        };
        assert_eq!(bits(back.steps.as_ref().unwrap()), bits(&s));
        // The map's own reader ignores both tables.
        assert_eq!(
            FollowerMap::from_toml(&text, "map 1").unwrap(),
            stored.map,
            "the map reads alone"
        );
        // A map stored before the steps were kept: none, and said so by `None`.
        let old = StoredMap::from_toml(&stored.map.to_toml(), "map 2").unwrap();
        assert_eq!((old.certificate, old.steps), (None, None));
    }

    #[test]
    fn a_bad_row_is_refused_naming_it() {
        let stored = StoredMap {
            map: super::super::build(&steps().steps, None, &steps().settings).unwrap(),
            certificate: None,
            steps: Some(steps()),
        };
        let text = stored.to_toml();
        let s = &steps().steps[0];
        let first = format!(
            "{},{},{},{},{},{}",
            s.from_mm, s.to_mm, s.along_mm, s.vertical_mm, s.variance[0], s.variance[1]
        );
        assert!(text.contains(&first), "{text}");
        let broken = text.replacen(&first, "1,2,x,4,5,6", 1);
        let e = StoredMap::from_toml(&broken, "map 7")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("map 7: self_calibration_steps: row 1:") && e.contains("1,2,x,4,5,6"),
            "{e}"
        );
    }
}
