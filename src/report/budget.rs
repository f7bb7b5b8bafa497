//! A stored run's uncertainty budget (ISO/TR 230-9), from what the run recorded when it
//! started ([`crate::evaluate::recorded`]): the follower error map it used (read back from
//! the store by id), the calibration's own term, the drift check and the temperature
//! inputs. A run stored before runs recorded them has those terms "not recorded"; the
//! follower's specification given to the report stands in for a run with no map.
//!
//! [`record_lab_run`] writes the same record for a run measured in the virtual-time lab (the
//! demo), whose budget inputs are known once it has run.

use super::source::{RunData, SourceError};
use crate::evaluate::recorded::{
    Recorded, RecordedBudget, RecordedCalibration, RecordedDrift, RecordedMap, RecordedThermal,
    Stated,
};
use crate::evaluate::uncertainty::{
    self, Budget, BudgetInputs, Component, FollowerInput, ThermalInput,
};
use crate::follower::FollowerMap;
use crate::store::{FollowerMapRecord, RunId, Store, StoreError};
use crate::units::DOF_TO_USER;

/// The spacing (mm) at which a follower map's uncertainty is taken for the budget.
const MAP_STEP_MM: f64 = 2.5;

/// ISO 1's reference temperature (°C).
const REFERENCE_C: f64 = 20.0;

/// What the report is given beside the store.
#[derive(Clone, Debug)]
pub struct Fallbacks {
    /// PSD2's sensitivities from the layout (first order), for a run that did not record its
    /// own decoupling's.
    pub psd2_sensitivity: [[f64; 2]; 6],
    /// The follower's specification (`--follower-spec-um`), for a run with no map.
    pub follower_spec: Option<FollowerInput>,
}

/// The follower term's input and, when it is not stated, why.
fn follower_term(
    store: &Store,
    recorded: &Recorded,
    reference_mm: f64,
    spec: Option<&FollowerInput>,
) -> Result<(FollowerInput, Option<String>), SourceError> {
    let fallback = |why: String| match spec {
        Some(s) => (s.clone(), None),
        None => (FollowerInput::Unstated, Some(why)),
    };
    let Some(r) = recorded.budget() else {
        return Ok(fallback(recorded.missing().unwrap_or_default()));
    };
    let why = match &r.follower_map {
        Stated::Stated(m) => match store.follower_map(m.id) {
            Ok(rec) => {
                let offset = m.encoder_offset_mm.unwrap_or(0.0);
                let at = match m.encoder_offset_mm {
                    Some(o) => format!(
                        "the follower's encoder read {:.3} mm {} than the carriage when the run started",
                        o.abs(),
                        if o < 0.0 { "less" } else { "more" }
                    ),
                    None => "the encoder taken to read the carriage's position".into(),
                };
                let words = format!(
                    "id {} \"{}\" ({}), the run's: {}; u at the point and at the zero reference, {at}",
                    rec.id,
                    rec.name,
                    rec.source,
                    rec.map.describe_sources()
                );
                let input =
                    FollowerInput::of_map(&rec.map, offset, reference_mm, MAP_STEP_MM, words);
                return Ok((input, None));
            }
            Err(StoreError::NoSuchFollowerMap(_)) => format!(
                "not stated: the run used follower map id {} \"{}\", which is no longer in the store",
                m.id, m.name
            ),
            Err(e) => return Err(e.into()),
        },
        Stated::NotStated(why) => format!("not stated: {why}"),
    };
    if spec.is_none()
        && let Some([along, vertical]) = r.follower_spec_um
    {
        return Ok((
            FollowerInput::Specification {
                positioning_mm: along * 1e-3,
                straightness_mm: vertical * 1e-3,
            },
            None,
        ));
    }
    Ok(fallback(why))
}

/// The calibration term and its words, or why it is not stated.
fn calibration(
    store: &Store,
    run: &RunData,
) -> Result<Result<([f64; 6], String), String>, SourceError> {
    if let Some(r) = run.recorded.budget() {
        return Ok(match &r.calibration {
            Stated::Stated(c) => Ok((c.internal(), recorded_calibration_words(c))),
            Stated::NotStated(why) => Err(format!("not stated: {why}")),
        });
    }
    let missing = run.recorded.missing().unwrap_or_default();
    // A run that did not record the term still names its calibration: the term follows
    // from the stored file by the same formula.
    let Some(id) = run.record.calibration else {
        return Ok(Err(missing));
    };
    let rec = match store.calibration(id) {
        Ok(r) => r,
        Err(StoreError::NoSuchCalibration(_)) => return Ok(Err(missing)),
        Err(e) => return Err(e.into()),
    };
    let term = crate::calibrate::CalibrationFile::parse(&rec.file_text, "the stored calibration")
        .map_err(|e| e.to_string())
        .and_then(|f| f.budget_term());
    Ok(match term {
        Ok(t) => Ok((
            std::array::from_fn(|k| t.u[k] / DOF_TO_USER[k]),
            format!(
                "calibration id {} (the run's; the run did not record its term, made now from the stored file): {}",
                id.0,
                t.words()
            ),
        )),
        Err(why) => Err(format!("not stated: calibration id {}: {why}", id.0)),
    })
}

fn recorded_calibration_words(c: &RecordedCalibration) -> String {
    match c.id {
        Some(id) => format!("calibration id {id}, recorded with the run: {}", c.source),
        None => format!("recorded with the run: {}", c.source),
    }
}

/// The run's budget: every term from the run's record (or the fallbacks), each source in
/// words.
pub fn run_budget(store: &Store, run: &RunData, fb: &Fallbacks) -> Result<Budget, SourceError> {
    let handovers: Vec<_> = store
        .handovers(Some(run.record.id))?
        .into_iter()
        .map(|h| h.record)
        .collect();
    let eval = &run.eval;
    let reference_mm = run
        .plan
        .as_ref()
        .map(|p| p.reference_mm)
        .or_else(|| eval.positions_mm.first().copied())
        .unwrap_or(0.0);
    let recorded = run.recorded.budget();
    let missing = run.recorded.missing();
    let mut notes: Vec<(Component, String)> = Vec::new();

    let (follower, why) = follower_term(
        store,
        &run.recorded,
        reference_mm,
        fb.follower_spec.as_ref(),
    )?;
    if let Some(w) = why {
        notes.push((Component::Bend, w.clone()));
        notes.push((Component::Follower, w));
    }

    let calibration = match calibration(store, run)? {
        Ok(c) => Some(c),
        Err(why) => {
            notes.push((Component::Calibration, why));
            None
        }
    };

    let drift_range = match recorded.map(|r| &r.drift) {
        Some(Stated::Stated(d)) => {
            let over = d
                .duration_s
                .map_or(String::new(), |s| format!(" over {s:.0} s"));
            notes.push((
                Component::Environment,
                format!("the drift check at the reference{over}, recorded with the run (range E_VE, rectangular)"),
            ));
            Some(d.internal())
        }
        Some(Stated::NotStated(why)) => {
            notes.push((Component::Environment, format!("not stated: {why}")));
            None
        }
        None => {
            notes.push((Component::Environment, missing.clone().unwrap_or_default()));
            None
        }
    };

    let thermal = match recorded.map(|r| &r.thermal) {
        Some(Stated::Stated(t)) => match eval.thermal.mean_material_c {
            Some(c) => Some(ThermalInput {
                alpha_per_k: t.alpha_um_per_m_k * 1e-6,
                u_alpha_per_k: t.u_alpha_um_per_m_k * 1e-6,
                u_temperature_k: t.u_temperature_k,
                delta_t_k: c - REFERENCE_C,
            }),
            None => {
                let why = "not stated: the run's captures carry no material temperature";
                notes.push((Component::ThermalTemperature, why.into()));
                notes.push((Component::ThermalCoefficient, why.into()));
                None
            }
        },
        Some(Stated::NotStated(why)) => {
            for c in [Component::ThermalTemperature, Component::ThermalCoefficient] {
                notes.push((c, format!("not stated: {why}")));
            }
            None
        }
        None => {
            for c in [Component::ThermalTemperature, Component::ThermalCoefficient] {
                notes.push((c, missing.clone().unwrap_or_default()));
            }
            None
        }
    };

    let inputs = BudgetInputs {
        reference_mm,
        psd2_sensitivity: recorded
            .and_then(|r| r.psd2_sensitivity)
            .unwrap_or(fb.psd2_sensitivity),
        follower,
        calibration,
        thermal,
        drift_range,
    };
    let mut budget = uncertainty::budget(
        eval,
        &uncertainty::stitched(&run.captures, &handovers),
        &inputs,
    );
    for (c, words) in notes {
        budget = budget.with_source(c, words);
    }
    Ok(budget)
}

/// Find `map` in the store (the same map stored before), or store it, in use.
fn stored_map(store: &mut Store, map: &FollowerMap) -> Result<FollowerMapRecord, StoreError> {
    let text = map.to_toml();
    if let Some(r) = store
        .follower_maps()?
        .into_iter()
        .find(|r| r.map.to_toml() == text)
    {
        return Ok(r);
    }
    let name = match &map.certificate_name {
        Some(c) => format!("the lab's follower map (self-calibration, certificate {c})"),
        None => "the lab's follower map (self-calibration)".into(),
    };
    let id = store.insert_follower_map(map, &name, true)?;
    store.follower_map(id)
}

/// Record, in stored run `run`'s configuration, the budget inputs a run measured in the
/// virtual-time lab used (`inputs`, as `sim::closed_loop::Measured::budget.inputs` holds
/// them), with the follower `map` it applied — stored in `store` (once, in use) so that the
/// report reads it back by id. The encoder's offset to the carriage is the one the lab's
/// budget used: its map grid starts at the map's first position, shifted by it.
pub fn record_lab_run(
    store: &mut Store,
    run: RunId,
    inputs: &BudgetInputs,
    map: Option<&FollowerMap>,
) -> Result<(), SourceError> {
    let user = |v: [f64; 6]| -> [f64; 6] { std::array::from_fn(|k| v[k] * DOF_TO_USER[k]) };
    let (follower_map, follower_spec_um) = match (&inputs.follower, map) {
        (FollowerInput::Map { positions_mm, .. }, Some(m)) => {
            let r = stored_map(store, m)?;
            let offset = positions_mm.first().map(|p| m.span().0 - p);
            (
                Stated::Stated(RecordedMap {
                    id: r.id,
                    name: r.name,
                    source: r.source,
                    created: crate::util::time::rfc3339(r.created_us.div_euclid(1_000_000)),
                    encoder_offset_mm: offset,
                }),
                None,
            )
        }
        (
            FollowerInput::Specification {
                positioning_mm,
                straightness_mm,
            },
            _,
        ) => (
            Stated::NotStated("no follower map: the stage's specification stands in".into()),
            Some([positioning_mm * 1e3, straightness_mm * 1e3]),
        ),
        _ => (
            Stated::NotStated("no follower map or specification given to the run".into()),
            None,
        ),
    };
    let record = RecordedBudget {
        follower_map,
        follower_spec_um,
        calibration: match &inputs.calibration {
            Some((u, source)) => Stated::Stated(RecordedCalibration {
                id: None,
                u_um_arcsec: user(*u),
                source: source.clone(),
            }),
            None => Stated::NotStated("no calibration term given to the run's budget".into()),
        },
        drift: match inputs.drift_range {
            Some(r) => Stated::Stated(RecordedDrift {
                range_um_arcsec: user(r),
                duration_s: None,
            }),
            None => Stated::NotStated("no drift check before the run".into()),
        },
        thermal: match &inputs.thermal {
            Some(t) => Stated::Stated(RecordedThermal {
                alpha_um_per_m_k: t.alpha_per_k * 1e6,
                u_alpha_um_per_m_k: t.u_alpha_per_k * 1e6,
                u_temperature_k: t.u_temperature_k,
            }),
            None => Stated::NotStated("no material temperature sensor on the axis".into()),
        },
        psd2_sensitivity: Some(inputs.psd2_sensitivity),
    };
    store.set_run_config_key(run, crate::evaluate::recorded::KEY, record.to_json())?;
    Ok(())
}
