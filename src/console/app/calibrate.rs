//! The Calibrate screen's state and keys: the calibration in use, the one waiting, fits.

use super::*;

/// A hexapod run as the service reports it (`hexapod_status`).
pub use crate::service::api::HexapodView;
/// A calibration as the service summarises it (`calibration`, `calibration_fit`).
pub use crate::service::calibration::Summary as CalSummary;

/// Polling interval of `hexapod_status` while the Calibrate screen shows.
pub const HEXAPOD_STATUS_EVERY: Duration = Duration::from_secs(1);

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
    /// The hexapod run (`hexapod_status`), when the service has answered.
    pub hexapod: Option<HexapodView>,
    /// The plan this console last started a hexapod run with ("" the default plan).
    pub hexapod_plan: String,
    pub last_hexapod_status: Option<Instant>,
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

    /// On the Calibrate screen, `hexapod_status` every `HEXAPOD_STATUS_EVERY`.
    pub(super) fn calibrate_need_hexapod(&mut self) -> Vec<Action> {
        let due = self
            .calibrate
            .last_hexapod_status
            .is_none_or(|t| self.now.saturating_duration_since(t) >= HEXAPOD_STATUS_EVERY);
        if self.screen != Screen::Calibrate
            || self.link != LinkState::Up
            || !due
            || self.waiting(&Pending::HexapodStatus)
        {
            return Vec::new();
        }
        self.calibrate.last_hexapod_status = Some(self.now);
        vec![self.send(Request::HexapodStatus, Pending::HexapodStatus)]
    }

    /// A `hexapod_status` reply: a run that has just finished brings its calibration to wait
    /// for accept or reject (the calibration is read again).
    pub(super) fn apply_hexapod_status(&mut self, v: serde_json::Value) -> Vec<Action> {
        let view: HexapodView = match serde_json::from_value(v) {
            Ok(view) => view,
            Err(e) => {
                self.calibrate.error = Some(format!("bad hexapod status from the service: {e}"));
                return Vec::new();
            }
        };
        let was = self.calibrate.hexapod.as_ref().map(|h| h.state.clone());
        let now = view.state.clone();
        let changed = was.as_deref().is_some_and(|w| w != now);
        self.calibrate.hexapod = Some(view);
        if !changed {
            return Vec::new();
        }
        let h = self.calibrate.hexapod.clone().unwrap_or_default();
        match now.as_str() {
            "done" => {
                let text = format!(
                    "hexapod run done: {} poses; the calibration waits (a accepts, x rejects)",
                    h.total
                );
                self.log(Level::Info, format!("✓ {text}"));
                self.say(Level::Info, text);
                self.calibrate.loaded = false;
                return self.screens_need();
            }
            "failed" | "stopped" => {
                let text = h.error.unwrap_or_else(|| format!("hexapod run {now}"));
                self.log(Level::Error, format!("✗ {text}"));
                self.say(Level::Error, text);
            }
            _ => {}
        }
        Vec::new()
    }

    /// Start (or resume) a hexapod run with `plan` ("" the default plan).
    pub(super) fn hexapod_start(&mut self, plan: String) -> Vec<Action> {
        let h = self.calibrate.hexapod.clone().unwrap_or_default();
        // Resuming: the same plan and run directory as the run shown.
        let resume = h.total > 0 && h.plan == plan && !h.out.is_empty();
        let request = Request::HexapodStart {
            plan: (!plan.is_empty()).then(|| plan.clone()),
            poses: (plan.is_empty() && resume).then_some(h.poses),
            out: resume.then(|| h.out.clone()),
        };
        self.calibrate.hexapod_plan = plan.clone();
        self.calibrate.error = None;
        self.log(
            Level::Info,
            if plan.is_empty() {
                "→ hexapod run with the default plan".to_string()
            } else {
                format!("→ hexapod run with the plan {plan}")
            },
        );
        vec![self.send(request, Pending::HexapodStart)]
    }

    pub(super) fn calibrate_key(&mut self, key: KeyEvent) -> Vec<Action> {
        let active = self.calibrate.hexapod.as_ref().is_some_and(|h| h.active());
        match key_char(&key) {
            Some('h') => {
                if active {
                    self.say(Level::Warn, "a hexapod run is under way: s stops it");
                } else if self.may_operate("calibrating with the hexapod") {
                    self.overlay = Overlay::Input(Input {
                        purpose: InputFor::HexapodPlan,
                        text: self.calibrate.hexapod_plan.clone(),
                    });
                }
            }
            Some('s') => {
                if !active {
                    self.say(Level::Info, "no hexapod run is moving");
                } else if self.may_operate("stopping the hexapod") {
                    self.log(Level::Info, "→ stop the hexapod run");
                    return vec![self.send(Request::HexapodStop, Pending::HexapodStop)];
                }
            }
            Some('u') => {
                let resumable = self
                    .calibrate
                    .hexapod
                    .as_ref()
                    .is_some_and(|h| matches!(h.state.as_str(), "stopped" | "failed"));
                if !resumable {
                    self.say(Level::Info, "no stopped or failed hexapod run to resume");
                } else if self.may_operate("resuming the hexapod run") {
                    let plan = self
                        .calibrate
                        .hexapod
                        .as_ref()
                        .map(|h| h.plan.clone())
                        .unwrap_or_default();
                    return self.hexapod_start(plan);
                }
            }
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
            Some(k @ ('a' | 'A')) => {
                if self.calibrate.pending.is_none() {
                    self.say(Level::Info, "no calibration is waiting: fit a pose set (f)");
                } else if self.may_operate("accepting a calibration") {
                    self.overlay = Overlay::Confirm(Confirm::Accept(k == 'A'));
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
