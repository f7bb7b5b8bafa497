//! What a run records of its uncertainty budget's inputs when the service starts it
//! ([`crate::evaluate::recorded`], under the run configuration's `budget` key): the follower
//! error map in use (store id, name, source, date, and how much more the follower's encoder
//! reads than the carriage's measured position, since the map is indexed by the encoder),
//! the calibration in use's own standard uncertainty per DOF (from its hold-out:
//! `CalibrationFile::budget_term`), PSD2's sensitivities through the decoupling in use at
//! mid-travel, and — said as not stated, with the reason — the drift check (the service runs
//! none) and the temperature inputs (the service reads no material temperature sensor).

use super::api::FollowerMapView;
use super::calibration::Calibrations;
use crate::decouple::Decoupler;
use crate::evaluate::recorded::{RecordedBudget, RecordedMap, Stated};
use crate::evaluate::uncertainty::psd2_sensitivity;
use crate::run::Plan;

/// Where the service stands when a run starts.
pub(super) struct AtStart<'a> {
    pub calibrations: &'a Calibrations,
    pub follower_map: Option<&'a FollowerMapView>,
    /// The follower's encoder (mm).
    pub encoder_mm: Option<f64>,
    /// The carriage's position as the head measures it (mm; after a zero reference).
    pub carriage_mm: Option<f64>,
    pub decoupler: &'a Decoupler,
}

/// The record for a run of `plan` started now.
pub(super) fn record(at: &AtStart, plan: &Plan) -> RecordedBudget {
    let follower_map = match at.follower_map {
        Some(m) => Stated::Stated(RecordedMap {
            id: m.id,
            name: m.name.clone(),
            source: m.source.clone(),
            created: m.created.clone(),
            encoder_offset_mm: at
                .encoder_mm
                .zip(at.carriage_mm)
                .map(|(e, c)| e - c)
                .filter(|o| o.is_finite()),
        }),
        None => Stated::NotStated(
            "no follower error map in use: the follower's own errors are in the measurement \
             (axiscomp follower import, or the service's follower mapping)"
                .into(),
        ),
    };
    let mid = (plan.spec.start_mm + plan.spec.end_mm) / 2.0;
    RecordedBudget {
        follower_map,
        follower_spec_um: None,
        calibration: at.calibrations.budget_term().clone(),
        drift: Stated::NotStated(
            "the service runs no drift check before a run (ISO 230-2's E_VE)".into(),
        ),
        thermal: Stated::NotStated("no material temperature sensor: the service reads none".into()),
        psd2_sensitivity: psd2_sensitivity(at.decoupler, mid).ok(),
    }
}
