//! The Results screen's state and keys: stored runs, the run shown, the comparison.

use super::*;

/// The Results screen: the stored runs, the run shown and the one compared with.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ResultsView {
    /// Newest first, as the service lists them.
    pub runs: Vec<RunSummary>,
    /// Whether a `runs` reply came (an empty list then means no runs).
    pub listed: bool,
    /// The highlighted run in the list.
    pub selected: usize,
    /// The run shown ("after" when comparing).
    pub shown: Option<RunResult>,
    /// The run compared with ("before").
    pub before: Option<RunResult>,
    /// The error the narrow layout charts, 0..6 in `Errors6` order (the wide one shows all six
    /// and marks this one).
    pub dof: usize,
    /// Why the last `run_result` failed.
    pub error: Option<String>,
}

impl ResultsView {
    /// The highlighted run's id.
    pub fn selected_id(&self) -> Option<i64> {
        self.runs.get(self.selected).map(|r| r.id)
    }
}

impl App {
    pub(super) fn apply_runs(&mut self, v: serde_json::Value) {
        match serde_json::from_value::<Vec<RunSummary>>(v["runs"].clone()) {
            Ok(runs) => {
                let keep = self.results.selected_id();
                let r = &mut self.results;
                r.runs = runs;
                r.listed = true;
                // Keep the highlighted run where it went; else the one shown; else the newest.
                let want = keep.or(r.shown.as_ref().map(|s| s.run.id));
                r.selected = want
                    .and_then(|id| r.runs.iter().position(|x| x.id == id))
                    .unwrap_or(0);
            }
            Err(e) => self.say(Level::Error, format!("bad run list from the service: {e}")),
        }
    }

    pub(super) fn apply_result(&mut self, to: ResultFor, v: serde_json::Value) {
        let result = match serde_json::from_value::<RunResult>(v) {
            Ok(r) => r,
            Err(e) => {
                self.say(
                    Level::Error,
                    format!("bad run result from the service: {e}"),
                );
                return;
            }
        };
        match to {
            ResultFor::Live => {
                if let Some(r) = self.run.as_mut().filter(|r| r.run_id == result.run.id) {
                    r.live = Some(result);
                }
            }
            ResultFor::Shown => {
                self.results.error = None;
                if let Some(i) = self.results.runs.iter().position(|x| x.id == result.run.id) {
                    self.results.selected = i;
                }
                self.results.shown = Some(result);
            }
            ResultFor::Before => {
                self.results.error = None;
                self.say(
                    Level::Info,
                    format!("comparing with run {} (before)", result.run.id),
                );
                self.results.before = Some(result);
            }
        }
    }

    pub(super) fn results_key(&mut self, key: KeyEvent) -> Vec<Action> {
        let n = self.results.runs.len();
        match (key.code, key_char(&key)) {
            (KeyCode::Up, _) if n > 0 => {
                self.results.selected = (self.results.selected + n - 1) % n;
            }
            (KeyCode::Down, _) if n > 0 => {
                self.results.selected = (self.results.selected + 1) % n;
            }
            (KeyCode::Left, _) => self.results.dof = (self.results.dof + 5) % 6,
            (KeyCode::Right, _) => self.results.dof = (self.results.dof + 1) % 6,
            (KeyCode::Enter, _) => match self.results.selected_id() {
                Some(id) => return vec![self.load_result(id, ResultFor::Shown)],
                None => self.say(Level::Info, "no stored runs to show"),
            },
            (_, Some('b')) => match self.results.selected_id() {
                Some(id) if self.results.shown.as_ref().is_some_and(|s| s.run.id == id) => {
                    self.say(
                        Level::Warn,
                        "pick another run to compare with (↑/↓, then b)",
                    );
                }
                Some(id) => return vec![self.load_result(id, ResultFor::Before)],
                None => self.say(Level::Info, "no stored runs to compare with"),
            },
            (_, Some('c')) if self.results.before.is_some() => {
                self.results.before = None;
                self.say(Level::Info, "comparison cleared");
            }
            (_, Some('r')) => {
                self.results.listed = false;
                return self.results_need_list();
            }
            (_, Some('t')) => {
                self.trends.shown = true;
                return vec![self.load_trend()];
            }
            _ => {}
        }
        Vec::new()
    }
}
