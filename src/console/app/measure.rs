//! The Measure screen's state and keys: the plan form, the run's progress with its ETA.

use super::*;

/// A plan field on the Measure screen.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Field {
    Axis,
    Start,
    End,
    Targets,
    Runs,
    Overrun,
    Dwell,
    Feed,
    Lead,
}

impl Field {
    pub const ALL: [Field; 9] = [
        Field::Axis,
        Field::Start,
        Field::End,
        Field::Targets,
        Field::Runs,
        Field::Overrun,
        Field::Dwell,
        Field::Feed,
        Field::Lead,
    ];

    pub fn label(self) -> &'static str {
        match self {
            Field::Axis => "axis",
            Field::Start => "start",
            Field::End => "end",
            Field::Targets => "targets",
            Field::Runs => "runs",
            Field::Overrun => "overrun",
            Field::Dwell => "dwell",
            Field::Feed => "feed",
            Field::Lead => "screw lead",
        }
    }

    pub fn unit(self) -> &'static str {
        match self {
            Field::Axis | Field::Targets => "",
            Field::Runs => "",
            Field::Start | Field::End | Field::Overrun | Field::Lead => "mm",
            Field::Dwell => "s",
            Field::Feed => "mm/min",
        }
    }

    /// The value as the form shows it.
    pub fn get(self, s: &PlanSpec) -> String {
        match self {
            Field::Axis => s.axis.clone(),
            Field::Start => format!("{}", s.start_mm),
            Field::End => format!("{}", s.end_mm),
            Field::Targets => s.targets.to_string(),
            Field::Runs => s.runs.to_string(),
            Field::Overrun => format!("{}", s.overrun_mm),
            Field::Dwell => format!("{}", s.dwell_s),
            Field::Feed => format!("{}", s.feed_mm_min),
            Field::Lead => format!("{}", s.lead_mm),
        }
    }

    /// Set from typed text; the error says what is accepted.
    pub fn set(self, s: &mut PlanSpec, text: &str) -> Result<(), String> {
        let t = text.trim();
        let num = || -> Result<f64, String> {
            t.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| format!("{}: \"{t}\" is not a number", self.label()))
        };
        let count = || -> Result<u32, String> {
            t.parse::<u32>()
                .map_err(|_| format!("{}: \"{t}\" is not a whole number", self.label()))
        };
        match self {
            Field::Axis => {
                let a = t.to_ascii_uppercase();
                if !["X", "Y", "Z"].contains(&a.as_str()) {
                    return Err(format!("axis: \"{t}\": use X, Y or Z"));
                }
                s.axis = a;
            }
            Field::Start => s.start_mm = num()?,
            Field::End => s.end_mm = num()?,
            Field::Targets => s.targets = count()? as usize,
            Field::Runs => s.runs = count()?,
            Field::Overrun => s.overrun_mm = num()?,
            Field::Dwell => s.dwell_s = num()?,
            Field::Feed => s.feed_mm_min = num()?,
            Field::Lead => s.lead_mm = num()?,
        }
        Ok(())
    }

    /// Left/Right: the next axis, or one step down/up.
    fn nudge(self, s: &mut PlanSpec, up: bool) {
        let sign = if up { 1.0 } else { -1.0 };
        let step_count = |v: u32| {
            if up {
                v.saturating_add(1)
            } else {
                v.saturating_sub(1)
            }
        };
        match self {
            Field::Axis => {
                let order = ["X", "Y", "Z"];
                let i = order.iter().position(|a| *a == s.axis).unwrap_or(0);
                let j = if up { (i + 1) % 3 } else { (i + 2) % 3 };
                s.axis = order[j].into();
            }
            Field::Start => s.start_mm += 10.0 * sign,
            Field::End => s.end_mm += 10.0 * sign,
            Field::Targets => s.targets = step_count(s.targets as u32) as usize,
            Field::Runs => s.runs = step_count(s.runs),
            Field::Overrun => s.overrun_mm = (s.overrun_mm + sign).max(0.0),
            Field::Dwell => s.dwell_s = (s.dwell_s + 0.5 * sign).max(0.0),
            Field::Feed => s.feed_mm_min = (s.feed_mm_min + 500.0 * sign).max(500.0),
            Field::Lead => s.lead_mm = (s.lead_mm + sign).max(0.0),
        }
    }
}

/// The plan being edited on the Measure screen.
#[derive(Clone, Debug, PartialEq)]
pub struct PlanForm {
    pub spec: PlanSpec,
    pub selected: usize,
    /// The text being typed into the selected field.
    pub editing: Option<String>,
    /// The notes a run of this plan is started with, and the axis they are for: a machine's
    /// set-up (the Machine screen's `p`) names itself so that its run is attached nowhere else.
    pub notes: Option<(String, String)>,
}

impl PlanForm {
    /// The notes to start the plan with: the set-up's while the plan is still on its axis.
    pub fn notes_for(&self, spec: &PlanSpec) -> Option<String> {
        self.notes
            .as_ref()
            .filter(|(axis, _)| *axis == spec.axis)
            .map(|(_, n)| n.clone())
    }
}

impl PlanForm {
    pub fn field(&self) -> Field {
        Field::ALL[self.selected.min(Field::ALL.len() - 1)]
    }
    /// The plan as the service would take it, or why not.
    pub fn checked(&self) -> Result<Plan, String> {
        Plan::new(self.spec.clone()).map_err(|e| e.to_string())
    }
}

/// A run's progress as the snapshots and `run_status` replies show it.
#[derive(Clone, Debug, PartialEq)]
pub struct RunProgress {
    pub run_id: i64,
    /// "running", "complete", "aborted", "failed", … as the service says.
    pub state: String,
    pub captures: usize,
    pub expected: Option<usize>,
    pub missing: Option<usize>,
    pub program: Option<String>,
    pub notes: Option<String>,
    /// Why the run is paused, while it is (the service's snapshot).
    pub paused: Option<String>,
    /// The plan, when this console started the run (for the per-target view).
    pub plan: Option<Plan>,
    /// The captures so far as the service evaluates them (`run_result` of this run), for the
    /// live plot.
    pub live: Option<RunResult>,
    /// The plan's machine time left (s) as the service said it, and when.
    pub left_s: Option<f64>,
    left_at: Option<Instant>,
    /// The run's machine time as the service said it (s: so far while it runs, since it
    /// started or the service took it up again; from its start to its end once it ended),
    /// and when.
    pub machine_s: Option<f64>,
    machine_at: Option<Instant>,
    first_seen: Instant,
    first_captures: usize,
    last_change: Instant,
    pub(super) now: Instant,
}

impl RunProgress {
    pub(super) fn new(run_id: i64, captures: usize, now: Instant) -> Self {
        RunProgress {
            run_id,
            state: "running".into(),
            captures,
            expected: None,
            missing: None,
            left_s: None,
            left_at: None,
            machine_s: None,
            machine_at: None,
            program: None,
            notes: None,
            paused: None,
            plan: None,
            live: None,
            first_seen: now,
            first_captures: captures,
            last_change: now,
            now,
        }
    }

    pub(super) fn observe(&mut self, captures: usize, now: Instant) {
        if captures != self.captures {
            self.last_change = now;
        }
        self.captures = captures;
        self.now = now;
    }

    pub fn running(&self) -> bool {
        self.state == "running"
    }

    /// Done fraction, 0..=1.
    pub fn fraction(&self) -> f64 {
        match self.expected {
            Some(e) if e > 0 => (self.captures as f64 / e as f64).clamp(0.0, 1.0),
            _ => 0.0,
        }
    }

    /// Time since this console first saw the run.
    pub fn watched(&self) -> Duration {
        self.now.saturating_duration_since(self.first_seen)
    }

    /// The run's machine time: while it runs, what the service last said and the time since;
    /// once it ended, from its start to its end; `None` when the service did not say.
    pub fn machine_time(&self) -> Option<Duration> {
        let said = Duration::from_secs_f64(self.machine_s?.max(0.0));
        Some(match (self.running(), self.machine_at) {
            (true, Some(at)) => said + self.now.saturating_duration_since(at),
            _ => said,
        })
    }

    /// Time left: the plan's motion and dwell for the captures still to come (from the
    /// service), else at the pace of the captures seen so far; `None` before two captures
    /// were seen to come in, or when the run is not running.
    pub fn eta(&self) -> Option<Duration> {
        if !self.running() {
            return None;
        }
        // The plan's motion and dwell for what is left, as the service last said, less the
        // time since it said so.
        if let (Some(left), Some(at)) = (self.left_s, self.left_at) {
            return Some(
                Duration::from_secs_f64(left.max(0.0))
                    .saturating_sub(self.now.saturating_duration_since(at)),
            );
        }
        let expected = self.expected?;
        let seen = self.captures.checked_sub(self.first_captures)?;
        if !self.running() || seen == 0 {
            return None;
        }
        let per = self
            .last_change
            .saturating_duration_since(self.first_seen)
            .div_f64(seen as f64);
        let left = per.mul_f64(expected.saturating_sub(self.captures) as f64);
        Some(left.saturating_sub(self.now.saturating_duration_since(self.last_change)))
    }
}

impl App {
    pub(super) fn apply_run_status(&mut self, v: &serde_json::Value, now: Instant) -> Vec<Action> {
        let Some(run_id) = v["run_id"].as_i64() else {
            return Vec::new(); // {"state":"none"}: no run yet
        };
        let was_running = self
            .run
            .as_ref()
            .is_some_and(|r| r.run_id == run_id && r.running());
        let captures = v["captures"].as_u64().unwrap_or(0) as usize;
        let r = match self.run.as_mut() {
            Some(r) if r.run_id == run_id => r,
            _ => self.run.insert(RunProgress::new(run_id, captures, now)),
        };
        r.observe(captures, now);
        if let Some(s) = v["state"].as_str() {
            r.state = s.to_string();
        }
        if let Some(e) = v["expected"].as_u64() {
            r.expected = Some(e as usize);
        }
        r.missing = v["missing"].as_u64().map(|m| m as usize);
        r.left_s = v["left_s"].as_f64();
        r.left_at = r.left_s.map(|_| now);
        r.machine_s = v["machine_s"]
            .as_f64()
            .or_else(|| v["machine_time_s"].as_f64());
        r.machine_at = r.machine_s.map(|_| now);
        if let Some(p) = v["program"].as_str() {
            r.program = Some(p.to_string());
        }
        if let Some(n) = v["notes"].as_str() {
            r.notes = Some(n.to_string());
        }
        let state = r.state.clone();
        if !was_running || state == "running" {
            return Vec::new();
        }
        // The run this console watched has ended: its result for the Results screen and the
        // live plot, and the run list again.
        self.log(Level::Info, format!("run {run_id} {state}"));
        self.results.listed = false;
        let mut out = vec![self.load_result(run_id, ResultFor::Live)];
        if state == "finished" {
            self.say(
                Level::Info,
                format!("run {run_id} finished: its results are on screen 5"),
            );
            out.push(self.load_result(run_id, ResultFor::Shown));
        }
        out.extend(self.results_need_list());
        out
    }

    /// The part program of the plan in the form: generated here by the library's
    /// `run::program::generate` (pure presentation of the plan), ISO dialect, dwell captures —
    /// what the service sends with its default `[cnc]` settings.
    pub fn program_text(&self) -> Result<String, String> {
        use crate::run::program::{CaptureMode, Dialect, generate};
        let plan = self.plan.checked()?;
        generate(&plan, Dialect::Iso, CaptureMode::Stability).map_err(|e| e.to_string())
    }

    pub(super) fn measure_key(&mut self, key: KeyEvent) -> Vec<Action> {
        let n = Field::ALL.len();
        match (key.code, key_char(&key)) {
            (KeyCode::Up, _) => self.plan.selected = (self.plan.selected + n - 1) % n,
            (KeyCode::Down, _) => self.plan.selected = (self.plan.selected + 1) % n,
            (KeyCode::Left, _) => self.plan.field().nudge(&mut self.plan.spec, false),
            (KeyCode::Right, _) => self.plan.field().nudge(&mut self.plan.spec, true),
            (KeyCode::Enter, _) => {
                self.plan.editing = Some(self.plan.field().get(&self.plan.spec));
            }
            (_, Some('s')) => {
                if self.run_active() {
                    self.say(Level::Warn, "a run is under way: abort it first (a)");
                } else if self.may_operate("starting a run") {
                    match self.plan.checked() {
                        Ok(_) => {
                            self.overlay =
                                Overlay::Confirm(Confirm::StartRun(self.plan.spec.clone()))
                        }
                        Err(e) => self.say(Level::Error, e),
                    }
                }
            }
            (_, Some('a')) => {
                if !self.run_active() {
                    self.say(Level::Info, "no run is under way");
                } else if self.may_operate("aborting the run") {
                    let id = self
                        .snapshot
                        .as_ref()
                        .and_then(|s| s.run.as_ref().map(|r| r.id))
                        .or(self.run.as_ref().map(|r| r.run_id));
                    self.overlay = Overlay::Confirm(Confirm::AbortRun(id));
                }
            }
            (_, Some('r')) => {
                self.last_run_status = Some(self.now);
                return vec![self.send(Request::RunStatus, Pending::RunStatus)];
            }
            (_, Some('e')) => self.live_dof = (self.live_dof + 1) % 6,
            (_, Some('w')) => match self.plan.checked() {
                Ok(p) => {
                    let text = match &self.saved {
                        Some(Ok(path)) => path.clone(),
                        _ => format!("axiscomp-{}.nc", p.spec.axis.to_ascii_lowercase()),
                    };
                    self.overlay = Overlay::Input(Input {
                        purpose: InputFor::ProgramPath,
                        text,
                    });
                }
                Err(e) => self.say(Level::Error, e),
            },
            _ => {}
        }
        Vec::new()
    }

    pub(super) fn edit_key(&mut self, key: KeyEvent) {
        let Some(buf) = self.plan.editing.as_mut() else {
            return;
        };
        match (key.code, key_char(&key)) {
            (KeyCode::Esc, _) => self.plan.editing = None,
            (KeyCode::Backspace, _) => {
                buf.pop();
            }
            (KeyCode::Enter, _) => {
                let text = buf.clone();
                let field = self.plan.field();
                match field.set(&mut self.plan.spec, &text) {
                    Ok(()) => {
                        self.plan.editing = None;
                        if let Err(e) = self.plan.checked() {
                            self.say(Level::Warn, e);
                        }
                    }
                    Err(e) => self.say(Level::Error, e),
                }
            }
            (_, Some(c)) if (c.is_ascii_alphanumeric() || ".-+".contains(c)) && buf.len() < 16 => {
                buf.push(c);
            }
            _ => {}
        }
    }
}
