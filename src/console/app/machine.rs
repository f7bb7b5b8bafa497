//! The Machine screen's state and keys (issue 27): a stored machine's commissioning plan set-up
//! by set-up, what the technician does on the one selected (the next, unless another is
//! chosen), the run that measured each, the squarenesses so far and the model's prediction.
//! `p` puts the next set-up's run into the Measure screen's plan, to start there; `a` picks a
//! finished run of the next set-up's axis and attaches it; the service checks it
//! (`commission::stored`) and the plan moves on. `d` detaches the selected set-up's run and
//! those after it (asked first): a set-up measured again takes its place in the plan. `n`
//! stores a new machine from its record, a TOML file on the service's host, and shows its plan.

use super::*;
use crate::service::api::machine::{MachineView, SetupView};

/// The Machine screen.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MachinePanel {
    /// The machine shown (the newest stored, or the one asked for), as the service last said.
    pub view: Option<MachineView>,
    /// Why the last `machine` request failed (no machine stored, say).
    pub error: Option<String>,
    /// Whether a `machine` reply came since the last change.
    pub loaded: bool,
    /// The set-up whose steps show (0-based).
    pub selected: usize,
    /// Picking the run for the next set-up: the index into [`MachinePanel::runs`].
    pub picking: Option<usize>,
    /// A run being attached (until the reply).
    pub attaching: Option<i64>,
}

impl MachinePanel {
    /// The next set-up to measure.
    pub fn next(&self) -> Option<&SetupView> {
        self.view
            .as_ref()
            .and_then(|v| v.setups.iter().find(|s| s.state == "next"))
    }

    /// The finished runs that may stand for the next set-up: its axis, not attached already.
    pub fn runs<'a>(&self, results: &'a ResultsView) -> Vec<&'a RunSummary> {
        let Some((next, view)) = self.next().zip(self.view.as_ref()) else {
            return Vec::new();
        };
        results
            .runs
            .iter()
            .filter(|r| r.state == "finished" && r.axis.eq_ignore_ascii_case(&next.axis))
            .filter(|r| !view.setups.iter().any(|s| s.run_id == Some(r.id)))
            .collect()
    }
}

impl App {
    pub(super) fn machine_key(&mut self, key: KeyEvent) -> Vec<Action> {
        if let Some(i) = self.machine.picking {
            let runs: Vec<i64> = self
                .machine
                .runs(&self.results)
                .iter()
                .map(|r| r.id)
                .collect();
            let n = runs.len();
            match key.code {
                KeyCode::Up if n > 0 => self.machine.picking = Some((i + n - 1) % n),
                KeyCode::Down if n > 0 => self.machine.picking = Some((i + 1) % n),
                KeyCode::Esc => self.machine.picking = None,
                KeyCode::Enter => {
                    let target = self
                        .machine
                        .view
                        .as_ref()
                        .map(|v| v.id)
                        .zip(self.machine.next().map(|s| s.number));
                    let (Some(&run), Some((id, setup))) = (runs.get(i), target) else {
                        self.say(
                            Level::Info,
                            "no finished run of the set-up's axis: measure it first (Measure, 4)",
                        );
                        return Vec::new();
                    };
                    self.machine.picking = None;
                    if !self.may_operate("attaching a run") {
                        return Vec::new();
                    }
                    self.machine.attaching = Some(run);
                    self.log(
                        Level::Info,
                        format!("→ attach run {run} to set-up {setup} of machine {id}"),
                    );
                    return vec![self.send(
                        Request::MachineAttach {
                            id,
                            setup,
                            run_id: run,
                        },
                        Pending::MachineAttach(run),
                    )];
                }
                _ => {}
            }
            return Vec::new();
        }
        let n = self.machine.view.as_ref().map_or(0, |v| v.setups.len());
        match (key.code, key_char(&key)) {
            (KeyCode::Up, _) if n > 0 => {
                self.machine.selected = (self.machine.selected + n - 1) % n
            }
            (KeyCode::Down, _) if n > 0 => self.machine.selected = (self.machine.selected + 1) % n,
            (_, Some('r')) => {
                self.machine.loaded = false;
                return self.screens_need();
            }
            (_, Some('p')) => match self
                .machine
                .next()
                .map(|s| (s.plan.clone(), s.title.clone(), s.run_notes.clone()))
            {
                Some((plan, title, notes)) => {
                    // The set-up's run into the Measure screen's form, to check and start (s),
                    // its notes naming the set-up.
                    self.plan.notes = Some((plan.axis.clone(), notes));
                    self.plan.spec = plan;
                    self.plan.selected = 0;
                    self.say(
                        Level::Info,
                        format!("the plan of set-up {title}: check it and start it with s"),
                    );
                    return self.show(Screen::Measure);
                }
                None => self.say(Level::Info, "no set-up is waiting for its run"),
            },
            (_, Some('d')) => self.ask_detach(),
            // (A viewer is told so by `may_operate`.)
            (_, Some('n')) if self.may_operate("storing a machine") => {
                self.overlay = Overlay::Input(Input {
                    purpose: InputFor::MachineRecord,
                    text: String::new(),
                });
            }
            (_, Some('a')) => {
                if self.machine.attaching.is_some() {
                    self.say(Level::Warn, "a run is being attached: wait for the answer");
                } else if self.machine.next().is_none() {
                    self.say(
                        Level::Info,
                        if self.machine.view.is_some() {
                            "every set-up is measured: export the controls' files (axiscomp machine export)"
                        } else {
                            "no machine stored: store its record with n (or axiscomp machine new FILE)"
                        },
                    );
                } else if self.may_operate("attaching a run") {
                    self.machine.picking = Some(0);
                    self.results.listed = false;
                    if !self.waiting(&Pending::Runs) {
                        return vec![self.send(Request::Runs { limit: None }, Pending::Runs)];
                    }
                }
            }
            _ => {}
        }
        Vec::new()
    }

    /// Store a machine from the record typed (a path on the service's host).
    pub(super) fn machine_new(&mut self, path: &str) -> Vec<Action> {
        if path.is_empty() {
            self.say(
                Level::Warn,
                "type the path of the machine's record (TOML) on the service's host",
            );
            return Vec::new();
        }
        self.overlay = Overlay::None;
        self.log(Level::Info, format!("→ store a machine from {path}"));
        vec![self.send(
            Request::MachineNew {
                record: String::new(),
                path: Some(path.to_string()),
                origin: None,
            },
            Pending::MachineNew,
        )]
    }

    /// Ask before detaching the selected set-up's run and those after it.
    fn ask_detach(&mut self) {
        let Some(v) = self.machine.view.as_ref() else {
            self.say(Level::Info, "no machine stored");
            return;
        };
        let Some(sel) = v.setups.get(self.machine.selected) else {
            return;
        };
        let runs: Vec<i64> = v
            .setups
            .iter()
            .filter(|s| s.number >= sel.number)
            .filter_map(|s| s.run_id)
            .collect();
        if sel.run_id.is_none() {
            self.say(
                Level::Info,
                format!("set-up {} has no run to detach", sel.title),
            );
            return;
        }
        let (id, setup) = (v.id, sel.number);
        if self.may_operate("detaching a run") {
            self.overlay = Overlay::Confirm(Confirm::Detach { id, setup, runs });
        }
    }

    /// What the Machine screen shows, once (until `r`, or an attachment, makes it old).
    pub(super) fn machine_need(&mut self) -> Vec<Action> {
        if self.machine.loaded || self.waiting(&Pending::Machine) {
            return Vec::new();
        }
        let id = self.machine.view.as_ref().map(|v| v.id);
        vec![self.send(Request::Machine { id }, Pending::Machine)]
    }

    /// A reply to a Machine screen's request.
    pub(super) fn machine_reply(
        &mut self,
        pending: &Pending,
        result: Result<serde_json::Value, String>,
    ) -> Vec<Action> {
        match (pending, result) {
            (Pending::Machine, Ok(v)) => {
                self.machine.loaded = true;
                match serde_json::from_value::<MachineView>(v) {
                    Ok(view) => {
                        // The steps shown follow the plan: the next set-up, once it moves on.
                        let moved = self.machine.next().map(|s| s.number)
                            != view
                                .setups
                                .iter()
                                .find(|s| s.state == "next")
                                .map(|s| s.number);
                        if moved || self.machine.view.is_none() {
                            self.machine.selected = view
                                .setups
                                .iter()
                                .position(|s| s.state == "next")
                                .unwrap_or(view.setups.len().saturating_sub(1));
                        }
                        self.machine.view = Some(view);
                        self.machine.error = None;
                    }
                    Err(e) => self.machine.error = Some(format!("bad machine view: {e}")),
                }
            }
            (Pending::Machine, Err(e)) => {
                self.machine.loaded = true;
                self.machine.error = Some(e);
            }
            (Pending::MachineAttach(run), Ok(_)) => {
                self.machine.attaching = None;
                self.log(Level::Info, format!("✓ run {run} attached"));
                self.say(
                    Level::Info,
                    format!("run {run} attached: the plan moves on"),
                );
                self.machine.loaded = false;
                return self.machine_need();
            }
            (Pending::MachineNew, Ok(v)) => {
                // The new machine's plan, from its first set-up.
                self.machine.view = None;
                let out = self.machine_reply(&Pending::Machine, Ok(v));
                if let Some(v) = &self.machine.view {
                    let text = format!(
                        "machine {} ({}) stored: its plan starts with set-up 1",
                        v.id, v.name
                    );
                    self.log(Level::Info, format!("✓ {text}"));
                    self.say(Level::Info, text);
                }
                return out;
            }
            (Pending::MachineNew, Err(e)) => {
                self.log(Level::Error, format!("✗ store a machine: {e}"));
                self.say(Level::Error, e);
            }
            (Pending::MachineDetach(setup), Ok(_)) => {
                self.log(Level::Info, format!("✓ detached from set-up {setup} on"));
                self.say(
                    Level::Info,
                    format!("detached from set-up {setup} on: measure it again and attach its run"),
                );
                self.machine.loaded = false;
                return self.machine_need();
            }
            (Pending::MachineDetach(setup), Err(e)) => {
                self.log(Level::Error, format!("✗ detach set-up {setup}: {e}"));
                self.say(Level::Error, e);
            }
            (Pending::MachineAttach(run), Err(e)) => {
                self.machine.attaching = None;
                self.log(Level::Error, format!("✗ attach run {run}: {e}"));
                self.say(Level::Error, e);
            }
            _ => {}
        }
        Vec::new()
    }
}
