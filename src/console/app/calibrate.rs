//! The Calibrate screen's state and keys: the calibration in use, the one waiting, fits.

use super::*;

/// A calibration as the service summarises it (`calibration`, `calibration_fit`).
pub use crate::service::calibration::Summary as CalSummary;

/// The Calibrate screen: the calibration in use, the one waiting, a fit under way.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CalibrateState {
    /// Whether a `calibration` reply came.
    pub loaded: bool,
    /// In use: `None` is the nominal layout.
    pub active: Option<CalSummary>,
    pub active_id: Option<i64>,
    pub pending: Option<CalSummary>,
    /// A fit runs (this console's, or the service says so).
    pub fitting: bool,
    /// The pose set this console asked to fit.
    pub fit_path: Option<String>,
    /// Why the last fit, accept or reject failed.
    pub error: Option<String>,
}

impl App {
    pub(super) fn apply_calibration(&mut self, v: &serde_json::Value) {
        let summary = |x: &serde_json::Value| -> Result<Option<CalSummary>, String> {
            if x.is_null() {
                return Ok(None);
            }
            serde_json::from_value(x.clone())
                .map(Some)
                .map_err(|e| format!("bad calibration from the service: {e}"))
        };
        let c = &mut self.calibrate;
        c.loaded = true;
        match (summary(&v["active"]), summary(&v["pending"])) {
            (Ok(active), Ok(pending)) => {
                c.active = active;
                c.pending = pending;
                c.active_id = v["active_id"].as_i64();
                // This console's fit is still under way until its reply comes.
                c.fitting = c.fitting || v["fitting"].as_bool().unwrap_or(false);
            }
            (Err(e), _) | (_, Err(e)) => c.error = Some(e),
        }
    }

    pub(super) fn calibrate_key(&mut self, key: KeyEvent) -> Vec<Action> {
        match key_char(&key) {
            Some('f') => {
                if self.calibrate.fitting {
                    self.say(Level::Warn, "a fit is under way: wait for its result");
                } else if self.may_operate("fitting a calibration") {
                    self.overlay = Overlay::Input(Input {
                        purpose: InputFor::PosePath,
                        text: self.calibrate.fit_path.clone().unwrap_or_default(),
                    });
                }
            }
            Some('a') => {
                if self.calibrate.pending.is_none() {
                    self.say(Level::Info, "no calibration is waiting: fit a pose set (f)");
                } else if self.may_operate("accepting a calibration") {
                    self.overlay = Overlay::Confirm(Confirm::Accept);
                }
            }
            Some('x') => {
                if self.calibrate.pending.is_none() {
                    self.say(Level::Info, "no calibration is waiting");
                } else if self.may_operate("rejecting a calibration") {
                    self.log(Level::Info, "→ reject the calibration");
                    return vec![self.send(Request::CalibrationReject, Pending::CalReject)];
                }
            }
            Some('r') => {
                self.calibrate.loaded = false;
                return self.screens_need();
            }
            _ => {}
        }
        Vec::new()
    }
}
