//! The console's state, sans-I/O: keys, snapshots and replies go in (`handle_*`, with the
//! time as an argument where it matters), [`Action`]s come out (requests to send, quit). The
//! screens draw from it and nothing else; the loop in `console::run` only carries things.
//!
//! It has no logic of its own beyond presentation: plans are checked with the library's
//! `Plan::new` only to show the targets and say early what the service would refuse.

use super::client::{ClientError, Identity, LinkEvent, PeerRole};
use crate::run::{Plan, PlanSpec};
use crate::service::control::{FollowerAction, Request};
use crate::service::results::{AuditView, RunResult, RunSummary};
use crate::service::snapshot::Snapshot;
use crate::service::tables::{PublishView, StatusView, TableView};
use crossterm::event::{KeyCode, KeyEvent, KeyEventKind, KeyModifiers};
use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

/// The screens, in tab order (number keys 1–7).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Screen {
    Live,
    Align,
    Calibrate,
    Measure,
    Results,
    Publish,
    Events,
}

impl Screen {
    pub const ALL: [Screen; 7] = [
        Screen::Live,
        Screen::Align,
        Screen::Calibrate,
        Screen::Measure,
        Screen::Results,
        Screen::Publish,
        Screen::Events,
    ];

    pub fn title(self) -> &'static str {
        match self {
            Screen::Live => "Live",
            Screen::Align => "Align",
            Screen::Calibrate => "Calibrate",
            Screen::Measure => "Measure",
            Screen::Results => "Results",
            Screen::Publish => "Publish",
            Screen::Events => "Events",
        }
    }

    pub fn index(self) -> usize {
        Screen::ALL.iter().position(|s| *s == self).unwrap_or(0)
    }

    fn step(self, by: isize) -> Screen {
        let n = Screen::ALL.len() as isize;
        Screen::ALL[((self.index() as isize + by).rem_euclid(n)) as usize]
    }
}

/// What the loop must do.
#[derive(Clone, Debug, PartialEq)]
pub enum Action {
    /// Send a request; its reply comes back through `handle_reply` with the same id.
    Send {
        id: u64,
        request: Request,
    },
    Quit,
    /// Write `text` to `path` (on this host); the outcome comes back through `handle_saved`.
    Save {
        path: String,
        text: String,
    },
}

/// The snapshot stream's state.
#[derive(Clone, Debug, PartialEq)]
pub enum LinkState {
    Connecting,
    Up,
    Down { error: String, retry_in: Duration },
}

/// What this console may do, as far as it knows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Access {
    /// The service has not said (an older service): learnt from the first refusal.
    Unknown,
    Viewer,
    Operator,
}

/// A question the operator must answer with y or n.
#[derive(Clone, Debug, PartialEq)]
pub enum Confirm {
    Quit,
    StartRun(PlanSpec),
    AbortRun(Option<i64>),
    /// Fit the pose set at this path on the service's host.
    Fit(String),
    /// Accept the pending calibration.
    Accept,
}

/// What a line typed into the input box is for.
#[derive(Clone, Debug, PartialEq)]
pub enum InputFor {
    /// The table's axis name, typed to confirm its publication.
    PublishAxis { table_id: i64, axis: String },
    /// The path of a pose-set CSV on the service's host.
    PosePath,
    /// Where to save the part program of the plan (on this host).
    ProgramPath,
}

/// A line being typed (Enter takes it, Esc drops it).
#[derive(Clone, Debug, PartialEq)]
pub struct Input {
    pub purpose: InputFor,
    pub text: String,
}

/// Longest line the input box takes.
pub const INPUT_MAX: usize = 200;

#[derive(Clone, Debug, PartialEq)]
pub enum Overlay {
    None,
    Help,
    Confirm(Confirm),
    Input(Input),
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Level {
    Info,
    Warn,
    Error,
}

/// A line in the status bar.
#[derive(Clone, Debug, PartialEq)]
pub struct Message {
    pub text: String,
    pub level: Level,
    pub at: Instant,
}

/// How long a status-bar message stays.
pub const MESSAGE_FOR: Duration = Duration::from_secs(8);

/// One entry of this session's request log (the Events screen).
#[derive(Clone, Debug, PartialEq)]
pub struct LogLine {
    /// The service's clock at the time (the last snapshot's), µs since the epoch; 0 if none.
    pub unix_us: i64,
    pub level: Level,
    pub text: String,
}

/// Most log lines kept.
pub const LOG_LINES: usize = 200;

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
    /// The plan, when this console started the run (for the per-target view).
    pub plan: Option<Plan>,
    /// The captures so far as the service evaluates them (`run_result` of this run), for the
    /// live plot.
    pub live: Option<RunResult>,
    first_seen: Instant,
    first_captures: usize,
    last_change: Instant,
    now: Instant,
}

impl RunProgress {
    fn new(run_id: i64, captures: usize, now: Instant) -> Self {
        RunProgress {
            run_id,
            state: "running".into(),
            captures,
            expected: None,
            missing: None,
            program: None,
            notes: None,
            plan: None,
            live: None,
            first_seen: now,
            first_captures: captures,
            last_change: now,
            now,
        }
    }

    fn observe(&mut self, captures: usize, now: Instant) {
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

    /// Time left at the pace of the captures seen so far; `None` before two captures were
    /// seen to come in, or when the run is not running.
    pub fn eta(&self) -> Option<Duration> {
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

/// The Publish screen: the stored tables, what the PLC holds, generation and publication.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PublishState {
    /// Newest first, as `table_list` gives them.
    pub tables: Vec<TableView>,
    /// The CNC map the service fits tables to.
    pub map: Option<String>,
    /// Whether a `table_list` reply came.
    pub listed: bool,
    pub selected: usize,
    /// The last `table_status`, or why it failed.
    pub status: Option<Result<StatusView, String>>,
    /// Picking the run to generate tables from: the index into [`PublishState::runs`].
    pub picking: Option<usize>,
    /// Tables being generated from this run.
    pub generating: Option<i64>,
    /// The table being published (until the reply).
    pub publishing: Option<i64>,
    /// The last publication's outcome (the service's reply), or why it failed.
    pub outcome: Option<Result<PublishView, String>>,
}

impl PublishState {
    pub fn selected_table(&self) -> Option<&TableView> {
        self.tables.get(self.selected)
    }
    /// The finished runs tables can be generated from.
    pub fn runs(results: &ResultsView) -> Vec<&RunSummary> {
        results
            .runs
            .iter()
            .filter(|r| r.state == "finished")
            .collect()
    }
}

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

/// What a sent request was, to handle its reply.
#[derive(Clone, Debug, PartialEq)]
enum Pending {
    Tables,
    TableStatus,
    Generate(i64),
    Publish(i64),
    Calibration,
    Fit,
    CalAccept,
    CalReject,
    RunStart(Box<Plan>),
    RunStatus,
    RunAbort,
    Runs,
    RunResult(ResultFor),
    Audit,
    Other(String),
}

/// Where a `run_result` reply goes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ResultFor {
    /// The Results screen's run ("after").
    Shown,
    /// The Results screen's comparison run ("before").
    Before,
    /// The live plot of the run under way (Measure).
    Live,
}

impl Pending {
    /// Polls and reads: their failures are not the operator's doing and do not make a viewer.
    fn is_read(&self) -> bool {
        matches!(
            self,
            Pending::RunStatus
                | Pending::Runs
                | Pending::RunResult(_)
                | Pending::Audit
                | Pending::Tables
                | Pending::TableStatus
                | Pending::Calibration
        )
    }
}

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

/// Console options the app needs.
#[derive(Clone, Debug, PartialEq)]
pub struct AppOptions {
    /// Where the service is (shown while connecting).
    pub socket: String,
    /// Follower jog step (mm).
    pub jog_step_mm: f64,
    /// Draw colours (false under `NO_COLOR`).
    pub color: bool,
}

/// Polling interval of `run_status` while the Measure screen shows.
pub const RUN_STATUS_EVERY: Duration = Duration::from_secs(2);

/// Polling interval of `audit` while the Events screen shows.
pub const AUDIT_EVERY: Duration = Duration::from_secs(2);

/// Audit entries fetched.
pub const AUDIT_LINES: u32 = 50;

/// A snapshot older than this is shown as stale.
pub const STALE_AFTER: Duration = Duration::from_secs(3);

/// The whole console state.
#[derive(Clone, Debug)]
pub struct App {
    pub opts: AppOptions,
    pub screen: Screen,
    pub link: LinkState,
    pub access: Access,
    pub user: Option<String>,
    pub snapshot: Option<Snapshot>,
    pub last_snapshot: Option<Instant>,
    pub overlay: Overlay,
    pub message: Option<Message>,
    pub plan: PlanForm,
    pub jog_step_mm: f64,
    pub run: Option<RunProgress>,
    pub results: ResultsView,
    /// The error the Measure screen's live plot shows (0..6, `Errors6` order).
    pub live_dof: usize,
    /// The service's audit log, newest first, as last fetched (the Events screen).
    pub audit: Option<Vec<AuditView>>,
    last_audit: Option<Instant>,
    pub publish: PublishState,
    pub calibrate: CalibrateState,
    /// Where the part program was last saved, or why not.
    pub saved: Option<Result<String, String>>,
    pub log: VecDeque<LogLine>,
    pub now: Instant,
    next_id: u64,
    pending: BTreeMap<u64, Pending>,
    last_run_status: Option<Instant>,
}

fn key_char(k: &KeyEvent) -> Option<char> {
    match k.code {
        KeyCode::Char(c) if !k.modifiers.contains(KeyModifiers::CONTROL) => Some(c),
        _ => None,
    }
}

impl App {
    pub fn new(opts: AppOptions, now: Instant) -> App {
        App {
            jog_step_mm: opts.jog_step_mm,
            opts,
            screen: Screen::Live,
            link: LinkState::Connecting,
            access: Access::Unknown,
            user: None,
            snapshot: None,
            last_snapshot: None,
            overlay: Overlay::None,
            message: None,
            plan: PlanForm {
                spec: PlanSpec::default(),
                selected: 0,
                editing: None,
            },
            run: None,
            // Positioning first: the ISO 230-2 result.
            results: ResultsView {
                dof: 1,
                ..ResultsView::default()
            },
            live_dof: 1,
            audit: None,
            last_audit: None,
            publish: PublishState::default(),
            calibrate: CalibrateState::default(),
            saved: None,
            log: VecDeque::new(),
            now,
            next_id: 1,
            pending: BTreeMap::new(),
            last_run_status: None,
        }
    }

    pub fn read_only(&self) -> bool {
        self.access == Access::Viewer
    }

    /// Whether the last snapshot is too old to trust (or there is none).
    pub fn stale(&self) -> bool {
        self.last_snapshot
            .is_none_or(|t| self.now.saturating_duration_since(t) > STALE_AFTER)
    }

    /// A run is under way (as far as the service last said).
    pub fn run_active(&self) -> bool {
        self.snapshot.as_ref().is_some_and(|s| s.run.is_some())
            || self.run.as_ref().is_some_and(RunProgress::running)
    }

    fn say(&mut self, level: Level, text: impl Into<String>) {
        let text = text.into();
        self.message = Some(Message {
            text: text.clone(),
            level,
            at: self.now,
        });
    }

    fn log(&mut self, level: Level, text: impl Into<String>) {
        let unix_us = self.snapshot.as_ref().map(|s| s.unix_us).unwrap_or(0);
        self.log.push_front(LogLine {
            unix_us,
            level,
            text: text.into(),
        });
        self.log.truncate(LOG_LINES);
    }

    fn send(&mut self, request: Request, pending: Pending) -> Action {
        let id = self.next_id;
        self.next_id += 1;
        if let Pending::Other(what) = &pending {
            self.log(Level::Info, format!("→ {what}"));
        }
        self.pending.insert(id, pending);
        Action::Send { id, request }
    }

    /// Whether an operator request may go; says why not in read-only mode.
    fn may_operate(&mut self, what: &str) -> bool {
        if self.read_only() {
            self.say(
                Level::Warn,
                format!("read-only (viewer): {what} needs the operator role"),
            );
            false
        } else {
            true
        }
    }

    // ---------- inputs ----------

    /// Time passes: messages expire, `run_status` is polled while the Measure screen shows.
    pub fn tick(&mut self, now: Instant) -> Vec<Action> {
        self.now = now;
        if let Some(r) = self.run.as_mut() {
            r.now = now;
        }
        if self
            .message
            .as_ref()
            .is_some_and(|m| now.saturating_duration_since(m.at) > MESSAGE_FOR)
        {
            self.message = None;
        }
        if self.link != LinkState::Up {
            return Vec::new();
        }
        let mut out = Vec::new();
        let due = self
            .last_run_status
            .is_none_or(|t| now.saturating_duration_since(t) >= RUN_STATUS_EVERY);
        if self.screen == Screen::Measure && due && !self.waiting(&Pending::RunStatus) {
            self.last_run_status = Some(now);
            out.push(self.send(Request::RunStatus, Pending::RunStatus));
            // The live plot: the captures of the run under way (or just ended) so far.
            if let Some(id) = self.run.as_ref().map(|r| r.run_id)
                && !self.waiting(&Pending::RunResult(ResultFor::Live))
            {
                out.push(self.send(
                    Request::RunResult { run_id: Some(id) },
                    Pending::RunResult(ResultFor::Live),
                ));
            }
        }
        out.extend(self.results_need_list());
        out.extend(self.events_need_audit());
        out.extend(self.screens_need());
        out
    }

    /// Publish and Calibrate: what they show, once (until `r` asks again or a change
    /// makes it old).
    fn screens_need(&mut self) -> Vec<Action> {
        let mut out = Vec::new();
        if self.link != LinkState::Up {
            return out;
        }
        match self.screen {
            Screen::Publish => {
                if !self.publish.listed && !self.waiting(&Pending::Tables) {
                    out.push(self.send(Request::TableList { limit: None }, Pending::Tables));
                }
                if self.publish.status.is_none() && !self.waiting(&Pending::TableStatus) {
                    out.push(self.send(Request::TableStatus, Pending::TableStatus));
                }
            }
            Screen::Calibrate if !self.calibrate.loaded && !self.waiting(&Pending::Calibration) => {
                out.push(self.send(Request::Calibration, Pending::Calibration));
            }
            _ => {}
        }
        out
    }

    /// The tables and what the PLC holds, again.
    fn reload_publish(&mut self) -> Vec<Action> {
        self.publish.listed = false;
        self.publish.status = None;
        self.screens_need()
    }

    /// On the Events screen, the audit log every `AUDIT_EVERY`.
    fn events_need_audit(&mut self) -> Vec<Action> {
        let due = self
            .last_audit
            .is_none_or(|t| self.now.saturating_duration_since(t) >= AUDIT_EVERY);
        if self.screen == Screen::Events
            && self.link == LinkState::Up
            && due
            && !self.waiting(&Pending::Audit)
        {
            self.last_audit = Some(self.now);
            return vec![self.send(
                Request::Audit {
                    limit: Some(AUDIT_LINES),
                },
                Pending::Audit,
            )];
        }
        Vec::new()
    }

    fn waiting(&self, p: &Pending) -> bool {
        self.pending.values().any(|q| q == p)
    }

    /// On the Results screen, the run list once (until `r` asks again).
    fn results_need_list(&mut self) -> Vec<Action> {
        if self.screen == Screen::Results
            && self.link == LinkState::Up
            && !self.results.listed
            && !self.waiting(&Pending::Runs)
        {
            return vec![self.send(Request::Runs { limit: None }, Pending::Runs)];
        }
        Vec::new()
    }

    fn load_result(&mut self, id: i64, to: ResultFor) -> Action {
        self.send(
            Request::RunResult { run_id: Some(id) },
            Pending::RunResult(to),
        )
    }

    /// Anything the client reports.
    pub fn handle_link_event(&mut self, ev: LinkEvent, now: Instant) -> Vec<Action> {
        match ev {
            LinkEvent::Connected(id) => self.handle_connected(id, now),
            LinkEvent::Snapshot(s) => return self.handle_snapshot(*s, now),
            LinkEvent::Down { error, retry_in } => self.handle_down(&error, retry_in, now),
            LinkEvent::Reply { id, result } => return self.handle_reply(id, result, now),
        }
        Vec::new()
    }

    pub fn handle_connected(&mut self, id: Identity, now: Instant) {
        self.now = now;
        let was_down = !matches!(self.link, LinkState::Up);
        self.link = LinkState::Up;
        self.user = id.user;
        match id.role {
            Some(PeerRole::Viewer) => {
                if self.access != Access::Viewer {
                    self.say(
                        Level::Warn,
                        "read-only (viewer): operator keys are disabled",
                    );
                }
                self.access = Access::Viewer;
            }
            Some(PeerRole::Operator) => self.access = Access::Operator,
            None => {}
        }
        if was_down {
            self.log(Level::Info, "connected to the service");
        }
    }

    pub fn handle_down(&mut self, error: &ClientError, retry_in: Duration, now: Instant) {
        self.now = now;
        if self.link == LinkState::Up {
            self.log(Level::Warn, format!("lost the service: {error}"));
        }
        self.link = LinkState::Down {
            error: error.to_string(),
            retry_in,
        };
    }

    /// A snapshot from the stream.
    pub fn handle_snapshot(&mut self, s: Snapshot, now: Instant) -> Vec<Action> {
        self.now = now;
        self.last_snapshot = Some(now);
        let mut out = Vec::new();
        match &s.run {
            Some(rv) => {
                let r = match self.run.as_mut() {
                    Some(r) if r.run_id == rv.id => r,
                    _ => self.run.insert(RunProgress::new(rv.id, rv.captures, now)),
                };
                r.state = "running".into();
                r.observe(rv.captures, now);
                r.expected = Some(rv.expected);
                r.program = Some(rv.program.clone());
            }
            None => {
                // The run ended: ask how.
                if self.run.as_ref().is_some_and(RunProgress::running)
                    && !self.waiting(&Pending::RunStatus)
                {
                    self.last_run_status = Some(now);
                    out.push(self.send(Request::RunStatus, Pending::RunStatus));
                }
            }
        }
        self.snapshot = Some(s);
        out
    }

    /// The reply to request `id`; it may ask for more (the result of a run that finished).
    pub fn handle_reply(
        &mut self,
        id: u64,
        result: Result<serde_json::Value, ClientError>,
        now: Instant,
    ) -> Vec<Action> {
        self.now = now;
        let Some(pending) = self.pending.remove(&id) else {
            return Vec::new();
        };
        let v = match result {
            Ok(v) => v,
            Err(e) => {
                if e.is_role_refusal() {
                    match pending {
                        Pending::Publish(_) => self.publish.publishing = None,
                        Pending::Generate(_) => self.publish.generating = None,
                        Pending::Fit => self.calibrate.fitting = false,
                        _ => {}
                    }
                    self.access = Access::Viewer;
                    self.say(Level::Warn, format!("read-only (viewer): {e}"));
                    self.log(Level::Error, format!("✗ {e}"));
                } else {
                    match pending {
                        Pending::RunStatus | Pending::RunResult(ResultFor::Live) => {}
                        Pending::RunResult(_) => {
                            self.results.error = Some(e.to_string());
                            self.say(Level::Error, e.to_string());
                        }
                        Pending::Tables => {
                            self.publish.listed = true;
                            self.say(Level::Error, format!("table list: {e}"));
                        }
                        Pending::TableStatus => self.publish.status = Some(Err(e.to_string())),
                        Pending::Publish(table_id) => {
                            self.publish.publishing = None;
                            self.publish.outcome = Some(Err(e.to_string()));
                            self.log(Level::Error, format!("✗ publish table {table_id}: {e}"));
                            self.say(Level::Error, format!("publish failed: {e}"));
                            return self.reload_publish();
                        }
                        Pending::Generate(run) => {
                            self.publish.generating = None;
                            self.log(Level::Error, format!("✗ generate from run {run}: {e}"));
                            self.say(Level::Error, e.to_string());
                        }
                        Pending::Calibration => {
                            self.calibrate.loaded = true;
                            self.calibrate.error = Some(e.to_string());
                        }
                        Pending::Fit | Pending::CalAccept | Pending::CalReject => {
                            if pending == Pending::Fit {
                                self.calibrate.fitting = false;
                            }
                            self.calibrate.error = Some(e.to_string());
                            self.log(Level::Error, format!("✗ {e}"));
                            self.say(Level::Error, e.to_string());
                        }
                        _ => {
                            self.say(Level::Error, e.to_string());
                            self.log(Level::Error, format!("✗ {e}"));
                        }
                    }
                }
                return Vec::new();
            }
        };
        if self.access == Access::Unknown && !pending.is_read() {
            // An operator request went through.
            self.access = Access::Operator;
        }
        match pending {
            Pending::Tables => {
                match serde_json::from_value::<Vec<TableView>>(v["tables"].clone()) {
                    Ok(tables) => {
                        let keep = self.publish.selected_table().map(|t| t.id);
                        let p = &mut self.publish;
                        p.tables = tables;
                        p.map = v["map"].as_str().map(str::to_string);
                        p.selected = keep
                            .and_then(|id| p.tables.iter().position(|t| t.id == id))
                            .unwrap_or(0);
                    }
                    Err(e) => self.say(Level::Error, format!("bad table list: {e}")),
                }
                self.publish.listed = true;
            }
            Pending::TableStatus => {
                self.publish.status = Some(
                    serde_json::from_value::<StatusView>(v)
                        .map_err(|e| format!("bad table status from the service: {e}")),
                );
            }
            Pending::Generate(run) => {
                self.publish.generating = None;
                let ids: Vec<String> = v["tables"]
                    .as_array()
                    .map(|a| {
                        a.iter()
                            .map(|t| {
                                format!(
                                    "{} {}",
                                    t["id"].as_i64().unwrap_or(0),
                                    t["name"].as_str().unwrap_or("?")
                                )
                            })
                            .collect()
                    })
                    .unwrap_or_default();
                let text = format!("run {run}: tables {} generated", ids.join(", "));
                self.log(Level::Info, format!("✓ {text}"));
                self.say(Level::Info, text);
                // The newest first: select the first generated.
                self.publish.selected = 0;
                return self.reload_publish();
            }
            Pending::Publish(table_id) => {
                self.publish.publishing = None;
                let outcome = serde_json::from_value::<PublishView>(v)
                    .map_err(|e| format!("bad publish reply from the service: {e}"));
                let (level, text) = match &outcome {
                    Ok(p) if p.result == "committed" => (
                        Level::Info,
                        format!("table {table_id} committed as sequence {}", p.sequence),
                    ),
                    Ok(p) => (
                        Level::Error,
                        format!("table {table_id} {}: {}", p.result, p.message),
                    ),
                    Err(e) => (Level::Error, e.clone()),
                };
                self.log(
                    level,
                    format!("{} {text}", if level == Level::Info { "✓" } else { "✗" }),
                );
                self.say(level, text);
                self.publish.outcome = Some(outcome);
                return self.reload_publish();
            }
            Pending::Calibration => self.apply_calibration(&v),
            Pending::Fit => {
                self.calibrate.fitting = false;
                self.calibrate.error = None;
                match serde_json::from_value::<CalSummary>(v["pending"].clone()) {
                    Ok(c) => {
                        let text = format!(
                            "fitted {} poses ({}): judge it, then a accepts or x rejects",
                            c.poses, c.decoupling
                        );
                        self.log(Level::Info, format!("✓ {text}"));
                        self.say(Level::Info, text);
                        self.calibrate.pending = Some(c);
                    }
                    Err(e) => self.say(Level::Error, format!("bad fit reply: {e}")),
                }
            }
            Pending::CalAccept => {
                let text = format!(
                    "calibration {} in use ({}); the zero was cleared: take it again (screen 2, z)",
                    v["calibration_id"].as_i64().unwrap_or(0),
                    v["decoupling"].as_str().unwrap_or("?")
                );
                self.log(Level::Info, format!("✓ {text}"));
                self.say(Level::Info, text);
                self.calibrate.loaded = false;
                return self.screens_need();
            }
            Pending::CalReject => {
                self.calibrate.pending = None;
                self.log(Level::Info, "✓ calibration rejected");
                self.say(Level::Info, "calibration rejected");
                self.calibrate.loaded = false;
                return self.screens_need();
            }
            Pending::RunStart(plan) => {
                let run_id = v["run_id"].as_i64().unwrap_or(0);
                let expected = v["captures_expected"].as_u64().map(|n| n as usize);
                let mut r = RunProgress::new(run_id, 0, now);
                r.expected = expected;
                r.program = v["program"].as_str().map(str::to_string);
                r.plan = Some(*plan);
                self.run = Some(r);
                let cnc = v["cnc"].as_str().unwrap_or("");
                let text = format!(
                    "run {run_id} started: {} captures; {cnc}",
                    expected.map(|e| e.to_string()).unwrap_or("?".into())
                );
                self.log(Level::Info, format!("✓ {text}"));
                self.say(Level::Info, text);
            }
            Pending::RunStatus => return self.apply_run_status(&v, now),
            Pending::Runs => self.apply_runs(v),
            Pending::Audit => {
                match serde_json::from_value::<Vec<AuditView>>(v["entries"].clone()) {
                    Ok(entries) => self.audit = Some(entries),
                    Err(e) => {
                        self.say(Level::Error, format!("bad audit log from the service: {e}"))
                    }
                }
            }
            Pending::RunResult(to) => self.apply_result(to, v),
            Pending::RunAbort => {
                let text = match v["aborted"].as_i64() {
                    Some(id) => format!("run {id} aborted (its captures stay stored)"),
                    None => "run aborted".into(),
                };
                if let Some(r) = self.run.as_mut() {
                    r.state = "aborted".into();
                }
                self.results.listed = false;
                self.log(Level::Info, format!("✓ {text}"));
                self.say(Level::Info, text);
            }
            Pending::Other(what) => {
                let detail = if v.is_null() {
                    String::new()
                } else {
                    format!(": {v}")
                };
                let text = format!("{what} done{detail}");
                self.log(Level::Info, format!("✓ {text}"));
                self.say(Level::Info, text);
            }
        }
        Vec::new()
    }

    fn apply_calibration(&mut self, v: &serde_json::Value) {
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

    /// The outcome of an [`Action::Save`].
    pub fn handle_saved(&mut self, path: &str, result: Result<(), String>) {
        match result {
            Ok(()) => {
                self.log(Level::Info, format!("✓ part program saved to {path}"));
                self.say(Level::Info, format!("part program saved to {path}"));
                self.saved = Some(Ok(path.to_string()));
            }
            Err(e) => {
                let text = format!("part program not saved to {path}: {e}");
                self.log(Level::Error, format!("✗ {text}"));
                self.say(Level::Error, text.clone());
                self.saved = Some(Err(text));
            }
        }
    }

    fn apply_runs(&mut self, v: serde_json::Value) {
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

    fn apply_result(&mut self, to: ResultFor, v: serde_json::Value) {
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

    fn apply_run_status(&mut self, v: &serde_json::Value, now: Instant) -> Vec<Action> {
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

    /// A key press.
    pub fn handle_key(&mut self, key: KeyEvent) -> Vec<Action> {
        if key.kind == KeyEventKind::Release {
            return Vec::new();
        }
        if key.modifiers.contains(KeyModifiers::CONTROL) && key.code == KeyCode::Char('c') {
            return vec![Action::Quit];
        }
        match &self.overlay {
            Overlay::Confirm(c) => {
                let c = c.clone();
                return self.confirm_key(c, key);
            }
            Overlay::Help => {
                self.overlay = Overlay::None;
                return Vec::new();
            }
            Overlay::Input(_) => return self.input_key(key),
            Overlay::None => {}
        }
        if self.screen == Screen::Measure && self.plan.editing.is_some() {
            self.edit_key(key);
            return Vec::new();
        }
        match (key.code, key_char(&key)) {
            (_, Some('?')) => {
                self.overlay = Overlay::Help;
                return Vec::new();
            }
            (_, Some('q')) => {
                if self.run_active() {
                    self.overlay = Overlay::Confirm(Confirm::Quit);
                    return Vec::new();
                }
                return vec![Action::Quit];
            }
            (_, Some(c @ '1'..='7')) => {
                return self.show(Screen::ALL[(c as u8 - b'1') as usize]);
            }
            (KeyCode::Tab, _) => return self.show(self.screen.step(1)),
            (KeyCode::BackTab, _) => return self.show(self.screen.step(-1)),
            (KeyCode::Esc, _) => {
                self.message = None;
                return Vec::new();
            }
            _ => {}
        }
        match self.screen {
            Screen::Align => self.align_key(key),
            Screen::Measure => self.measure_key(key),
            Screen::Results => self.results_key(key),
            Screen::Publish => self.publish_key(key),
            Screen::Calibrate => self.calibrate_key(key),
            _ => Vec::new(),
        }
    }

    fn input_key(&mut self, key: KeyEvent) -> Vec<Action> {
        let Overlay::Input(input) = &mut self.overlay else {
            return Vec::new();
        };
        match (key.code, key_char(&key)) {
            (KeyCode::Esc, _) => {
                self.overlay = Overlay::None;
                self.say(Level::Info, "cancelled");
            }
            (KeyCode::Backspace, _) => {
                input.text.pop();
            }
            (KeyCode::Enter, _) => {
                let input = input.clone();
                return self.input_done(input);
            }
            (_, Some(c)) if !c.is_control() && input.text.chars().count() < INPUT_MAX => {
                input.text.push(c);
            }
            _ => {}
        }
        Vec::new()
    }

    fn input_done(&mut self, input: Input) -> Vec<Action> {
        let text = input.text.trim().to_string();
        match input.purpose {
            InputFor::PublishAxis { table_id, axis } => {
                if !text.eq_ignore_ascii_case(&axis) {
                    self.say(
                        Level::Warn,
                        format!("type the axis name \"{axis}\" to publish (Esc cancels)"),
                    );
                    return Vec::new();
                }
                self.overlay = Overlay::None;
                self.publish.publishing = Some(table_id);
                self.publish.outcome = None;
                self.log(
                    Level::Info,
                    format!("→ publish table {table_id} (axis {axis})"),
                );
                vec![self.send(
                    Request::TablePublish {
                        table_id,
                        confirm: true,
                    },
                    Pending::Publish(table_id),
                )]
            }
            InputFor::PosePath => {
                if text.is_empty() {
                    self.say(
                        Level::Warn,
                        "type the path of a pose-set CSV on the service's host",
                    );
                    return Vec::new();
                }
                self.overlay = Overlay::Confirm(Confirm::Fit(text));
                Vec::new()
            }
            InputFor::ProgramPath => {
                if text.is_empty() {
                    self.say(Level::Warn, "type a file name for the part program");
                    return Vec::new();
                }
                self.overlay = Overlay::None;
                match self.program_text() {
                    Ok(program) => vec![Action::Save {
                        path: text,
                        text: program,
                    }],
                    Err(e) => {
                        self.say(Level::Error, e);
                        Vec::new()
                    }
                }
            }
        }
    }

    /// The part program of the plan in the form: generated here by the library's
    /// `run::program::generate` (pure presentation of the plan), ISO dialect, dwell captures —
    /// what the service sends with its default `[cnc]` settings.
    pub fn program_text(&self) -> Result<String, String> {
        use crate::run::program::{CaptureMode, Dialect, generate};
        let plan = self.plan.checked()?;
        generate(&plan, Dialect::Iso, CaptureMode::Stability).map_err(|e| e.to_string())
    }

    fn publish_key(&mut self, key: KeyEvent) -> Vec<Action> {
        if let Some(i) = self.publish.picking {
            let runs: Vec<i64> = PublishState::runs(&self.results)
                .iter()
                .map(|r| r.id)
                .collect();
            let n = runs.len();
            match key.code {
                KeyCode::Up if n > 0 => self.publish.picking = Some((i + n - 1) % n),
                KeyCode::Down if n > 0 => self.publish.picking = Some((i + 1) % n),
                KeyCode::Esc => self.publish.picking = None,
                KeyCode::Enter => {
                    let Some(&run) = runs.get(i) else {
                        self.say(Level::Info, "no finished run to generate tables from");
                        return Vec::new();
                    };
                    self.publish.picking = None;
                    if !self.may_operate("generating tables") {
                        return Vec::new();
                    }
                    self.publish.generating = Some(run);
                    self.log(Level::Info, format!("→ generate tables from run {run}"));
                    return vec![self.send(
                        Request::TableGenerate { run_id: run },
                        Pending::Generate(run),
                    )];
                }
                _ => {}
            }
            return Vec::new();
        }
        let n = self.publish.tables.len();
        match (key.code, key_char(&key)) {
            (KeyCode::Up, _) if n > 0 => {
                self.publish.selected = (self.publish.selected + n - 1) % n
            }
            (KeyCode::Down, _) if n > 0 => self.publish.selected = (self.publish.selected + 1) % n,
            (_, Some('r')) => return self.reload_publish(),
            (_, Some('g')) if self.may_operate("generating tables") => {
                self.publish.picking = Some(0);
                self.results.listed = false;
                if !self.waiting(&Pending::Runs) {
                    return vec![self.send(Request::Runs { limit: None }, Pending::Runs)];
                }
            }
            (_, Some('p')) => {
                if self.publish.publishing.is_some() {
                    self.say(
                        Level::Warn,
                        "a publication is under way: wait for its outcome",
                    );
                } else if let Some(t) = self.publish.selected_table() {
                    let (table_id, axis) = (t.id, t.axis.clone());
                    if self.may_operate("publishing a table") {
                        self.overlay = Overlay::Input(Input {
                            purpose: InputFor::PublishAxis { table_id, axis },
                            text: String::new(),
                        });
                    }
                } else {
                    self.say(Level::Info, "no stored table: generate one from a run (g)");
                }
            }
            _ => {}
        }
        Vec::new()
    }

    fn calibrate_key(&mut self, key: KeyEvent) -> Vec<Action> {
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

    /// Go to `screen` (and ask for what it shows, if it has nothing yet).
    fn show(&mut self, screen: Screen) -> Vec<Action> {
        self.screen = screen;
        let mut out = self.results_need_list();
        out.extend(self.events_need_audit());
        out.extend(self.screens_need());
        out
    }

    fn results_key(&mut self, key: KeyEvent) -> Vec<Action> {
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
            _ => {}
        }
        Vec::new()
    }

    fn confirm_key(&mut self, c: Confirm, key: KeyEvent) -> Vec<Action> {
        let yes = matches!(key_char(&key), Some('y' | 'Y')) || key.code == KeyCode::Enter;
        let no = matches!(key_char(&key), Some('n' | 'N')) || key.code == KeyCode::Esc;
        if no {
            self.overlay = Overlay::None;
            self.say(Level::Info, "cancelled");
            return Vec::new();
        }
        if !yes {
            return Vec::new();
        }
        self.overlay = Overlay::None;
        match c {
            Confirm::Quit => vec![Action::Quit],
            Confirm::StartRun(spec) => match Plan::new(spec.clone()) {
                Ok(plan) => {
                    let request = Request::RunStart {
                        plan: spec,
                        dialect: None,
                        notes: None,
                    };
                    self.log(
                        Level::Info,
                        format!(
                            "→ start run: axis {} {}–{} mm, {} targets, {} runs",
                            plan.spec.axis,
                            plan.spec.start_mm,
                            plan.spec.end_mm,
                            plan.targets.len(),
                            plan.spec.runs
                        ),
                    );
                    vec![self.send(request, Pending::RunStart(Box::new(plan)))]
                }
                Err(e) => {
                    self.say(Level::Error, e.to_string());
                    Vec::new()
                }
            },
            Confirm::Fit(path) => {
                self.calibrate.fitting = true;
                self.calibrate.error = None;
                self.calibrate.fit_path = Some(path.clone());
                self.log(Level::Info, format!("→ fit the pose set {path}"));
                vec![self.send(Request::CalibrationFit { poses: path }, Pending::Fit)]
            }
            Confirm::Accept => {
                self.log(Level::Info, "→ accept the calibration");
                vec![self.send(Request::CalibrationAccept, Pending::CalAccept)]
            }
            Confirm::AbortRun(id) => {
                self.log(
                    Level::Info,
                    format!(
                        "→ abort run {}",
                        id.map(|i| i.to_string()).unwrap_or_default()
                    ),
                );
                vec![self.send(Request::RunAbort, Pending::RunAbort)]
            }
        }
    }

    fn follower(&mut self, action: FollowerAction, mm: Option<f64>, what: String) -> Vec<Action> {
        if !self.may_operate(&what) {
            return Vec::new();
        }
        vec![self.send(Request::Follower { action, mm }, Pending::Other(what))]
    }

    fn align_key(&mut self, key: KeyEvent) -> Vec<Action> {
        let step = self.jog_step_mm;
        match key_char(&key) {
            Some('h') => self.follower(FollowerAction::Home, None, "home the follower".into()),
            Some('j') => self.follower(
                FollowerAction::Jog,
                Some(-step),
                format!("jog the follower -{step} mm"),
            ),
            Some('k') => self.follower(
                FollowerAction::Jog,
                Some(step),
                format!("jog the follower +{step} mm"),
            ),
            Some('x') => self.follower(FollowerAction::Stop, None, "stop the follower".into()),
            Some('r') => self.follower(
                FollowerAction::FaultReset,
                None,
                "reset the follower's fault".into(),
            ),
            Some('z') => {
                if !self.may_operate("zero") {
                    return Vec::new();
                }
                vec![self.send(Request::Zero, Pending::Other("zero here".into()))]
            }
            Some('c') => {
                if !self.may_operate("clear zero") {
                    return Vec::new();
                }
                vec![self.send(Request::ClearZero, Pending::Other("clear the zero".into()))]
            }
            Some('+' | ']') => {
                self.jog_step_mm = (step * 10.0).min(10.0);
                self.say(Level::Info, format!("jog step {} mm", self.jog_step_mm));
                Vec::new()
            }
            Some('-' | '[') => {
                self.jog_step_mm = (step / 10.0).max(0.001);
                self.say(Level::Info, format!("jog step {} mm", self.jog_step_mm));
                Vec::new()
            }
            _ => Vec::new(),
        }
    }

    fn measure_key(&mut self, key: KeyEvent) -> Vec<Action> {
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

    fn edit_key(&mut self, key: KeyEvent) {
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

/// The keys of a screen, for the help overlay (and its tests): (key, what it does).
pub fn screen_keys(screen: Screen) -> &'static [(&'static str, &'static str)] {
    match screen {
        Screen::Live => &[],
        Screen::Align => &[
            ("h", "home the follower"),
            ("j / k", "jog the follower − / + one step"),
            ("[ / ]", "jog step ÷10 / ×10"),
            ("z", "zero here (errors and stitching)"),
            ("c", "clear the zero"),
            ("x", "stop the follower"),
            ("r", "reset a drive fault and enable"),
        ],
        Screen::Measure => &[
            ("↑ / ↓", "select a plan field"),
            ("Enter", "edit it (Enter keeps, Esc drops)"),
            ("← / →", "step it down / up"),
            ("s", "start the run (asks first)"),
            ("a", "abort the run (asks first)"),
            ("r", "refresh the run status"),
            ("e", "plot the next error"),
            ("w", "write the plan's part program to a file"),
        ],
        Screen::Results => &[
            ("↑ / ↓", "select a stored run"),
            ("Enter", "show its results"),
            ("b", "compare with it (before)"),
            ("c", "clear the comparison"),
            ("← / →", "previous / next error"),
            ("r", "reload the run list"),
        ],
        Screen::Calibrate => &[
            ("f", "fit a pose-set CSV on the service's host (asks)"),
            ("a", "accept the pending calibration (asks)"),
            ("x", "reject the pending calibration"),
            ("r", "reload"),
        ],
        Screen::Publish => &[
            ("↑ / ↓", "select a stored table"),
            ("g", "generate tables from a finished run"),
            ("p", "publish it to the PLC (type the axis name)"),
            ("r", "reload the tables and the PLC's status"),
        ],
        Screen::Events => &[],
    }
}

/// The keys every screen has.
pub const GLOBAL_KEYS: &[(&str, &str)] = &[
    ("1–7", "screens"),
    ("Tab / S-Tab", "next / previous screen"),
    ("?", "this help"),
    ("Esc", "clear the message"),
    ("q", "quit (asks while a run is active)"),
    ("Ctrl-C", "quit now (a run continues in the service)"),
];

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::snapshot::RunView;

    fn key(c: KeyCode) -> KeyEvent {
        KeyEvent::new(c, KeyModifiers::NONE)
    }
    fn ch(c: char) -> KeyEvent {
        key(KeyCode::Char(c))
    }
    fn app() -> (App, Instant) {
        let t0 = Instant::now();
        let mut a = App::new(
            AppOptions {
                socket: "/run/axiscomp/control.sock".into(),
                jog_step_mm: 0.1,
                color: false,
            },
            t0,
        );
        a.handle_connected(
            Identity {
                user: Some("op".into()),
                role: Some(PeerRole::Operator),
            },
            t0,
        );
        (a, t0)
    }

    #[test]
    fn tabs_by_number_tab_and_backtab() {
        let (mut a, _) = app();
        a.handle_key(ch('4'));
        assert_eq!(a.screen, Screen::Measure);
        a.handle_key(key(KeyCode::Tab));
        assert_eq!(a.screen, Screen::Results);
        a.handle_key(key(KeyCode::BackTab));
        a.handle_key(key(KeyCode::BackTab));
        assert_eq!(a.screen, Screen::Calibrate);
        a.handle_key(ch('1'));
        a.handle_key(key(KeyCode::BackTab));
        assert_eq!(a.screen, Screen::Events);
    }

    #[test]
    fn quit_asks_while_a_run_is_active() {
        let (mut a, t0) = app();
        assert_eq!(a.handle_key(ch('q')), vec![Action::Quit]);
        a.handle_snapshot(
            Snapshot {
                run: Some(RunView {
                    id: 3,
                    axis: "X".into(),
                    captures: 1,
                    expected: 20,
                    program: "twin".into(),
                }),
                ..Snapshot::default()
            },
            t0,
        );
        assert!(a.handle_key(ch('q')).is_empty());
        assert_eq!(a.overlay, Overlay::Confirm(Confirm::Quit));
        assert!(a.handle_key(ch('n')).is_empty());
        assert_eq!(a.overlay, Overlay::None);
        a.handle_key(ch('q'));
        assert_eq!(a.handle_key(ch('y')), vec![Action::Quit]);
    }

    #[test]
    fn align_keys_send_follower_requests_with_the_step() {
        let (mut a, _) = app();
        a.handle_key(ch('2'));
        let out = a.handle_key(ch('k'));
        assert!(matches!(
            &out[..],
            [Action::Send { request: Request::Follower { action: FollowerAction::Jog, mm: Some(m) }, .. }] if (*m - 0.1).abs() < 1e-12
        ));
        a.handle_key(ch(']'));
        let out = a.handle_key(ch('j'));
        assert!(matches!(
            &out[..],
            [Action::Send { request: Request::Follower { mm: Some(m), .. }, .. }] if (*m + 1.0).abs() < 1e-12
        ));
        assert!(matches!(
            &a.handle_key(ch('z'))[..],
            [Action::Send {
                request: Request::Zero,
                ..
            }]
        ));
    }

    #[test]
    fn viewer_keys_are_refused_locally_and_a_refusal_makes_a_viewer() {
        let (mut a, t0) = app();
        a.access = Access::Unknown;
        a.handle_key(ch('2'));
        let Action::Send { id, .. } = a.handle_key(ch('h')).remove(0) else {
            panic!()
        };
        a.handle_reply(
            id,
            Err(ClientError::Refused(
                "user ana (uid 1001) may not follower: it needs the operator role (operator_group group)".into(),
            )),
            t0,
        );
        assert!(a.read_only());
        assert!(a.handle_key(ch('h')).is_empty());
        assert!(
            a.message
                .as_ref()
                .unwrap()
                .text
                .starts_with("read-only (viewer)")
        );
        a.handle_key(ch('4'));
        assert!(a.handle_key(ch('s')).is_empty());
        assert_eq!(a.overlay, Overlay::None);
    }

    #[test]
    fn plan_editing_with_arrows_enter_and_typing() {
        let (mut a, _) = app();
        a.handle_key(ch('4'));
        a.handle_key(key(KeyCode::Down)); // start
        a.handle_key(key(KeyCode::Down)); // end
        a.handle_key(key(KeyCode::Enter));
        for _ in 0..6 {
            a.handle_key(key(KeyCode::Backspace));
        }
        for c in "20".chars() {
            a.handle_key(ch(c));
        }
        // Digits go to the field while editing, not to the tabs.
        assert_eq!(a.screen, Screen::Measure);
        a.handle_key(key(KeyCode::Enter));
        assert_eq!(a.plan.spec.end_mm, 20.0);
        a.handle_key(key(KeyCode::Up));
        a.handle_key(key(KeyCode::Up));
        a.handle_key(key(KeyCode::Right));
        assert_eq!(a.plan.spec.axis, "Y");
        // A bad number is refused with a reason and the value kept.
        a.handle_key(key(KeyCode::Down));
        a.handle_key(key(KeyCode::Enter));
        a.handle_key(ch('x'));
        a.handle_key(key(KeyCode::Enter));
        assert!(a.message.as_ref().unwrap().text.contains("not a number"));
        a.handle_key(key(KeyCode::Esc));
        assert_eq!(a.plan.editing, None);
        assert_eq!(a.plan.spec.start_mm, 0.0);
    }

    #[test]
    fn start_confirms_then_sends_the_plan_and_progress_gives_an_eta() {
        let (mut a, t0) = app();
        a.handle_key(ch('4'));
        a.plan.spec.end_mm = 20.0;
        a.plan.spec.targets = 5;
        a.plan.spec.runs = 2;
        assert!(a.handle_key(ch('s')).is_empty());
        assert!(matches!(a.overlay, Overlay::Confirm(Confirm::StartRun(_))));
        let out = a.handle_key(ch('y'));
        let [
            Action::Send {
                id,
                request: Request::RunStart { plan, .. },
            },
        ] = &out[..]
        else {
            panic!("{out:?}")
        };
        assert_eq!(plan.end_mm, 20.0);
        a.handle_reply(
            *id,
            Ok(serde_json::json!({"run_id": 4, "captures_expected": 20, "program": "p.nc", "cnc": "sent to the twin"})),
            t0,
        );
        let r = a.run.as_ref().unwrap();
        assert_eq!((r.run_id, r.expected), (4, Some(20)));
        assert!(r.plan.is_some());
        assert_eq!(r.eta(), None);
        let view = |captures| Snapshot {
            run: Some(RunView {
                id: 4,
                axis: "X".into(),
                captures,
                expected: 20,
                program: "p.nc".into(),
            }),
            ..Snapshot::default()
        };
        a.handle_snapshot(view(0), t0);
        a.handle_snapshot(view(5), t0 + Duration::from_secs(10));
        // Off the Measure screen, nothing polls run_status.
        a.handle_key(ch('1'));
        a.tick(t0 + Duration::from_secs(12));
        // 2 s per capture, 15 to go, 2 s since the last: 28 s.
        assert_eq!(a.run.as_ref().unwrap().eta(), Some(Duration::from_secs(28)));
        // The run ends: the console asks how.
        let out = a.handle_snapshot(Snapshot::default(), t0 + Duration::from_secs(50));
        let [
            Action::Send {
                id,
                request: Request::RunStatus,
            },
        ] = &out[..]
        else {
            panic!("{out:?}")
        };
        a.handle_reply(
            *id,
            Ok(serde_json::json!({"run_id": 4, "state": "complete", "captures": 20})),
            t0 + Duration::from_secs(50),
        );
        let r = a.run.as_ref().unwrap();
        assert_eq!((r.state.as_str(), r.captures), ("complete", 20));
        assert!(!a.run_active());
    }

    #[test]
    fn publish_sends_confirm_only_after_the_axis_name_is_typed() {
        let (mut a, t0) = app();
        let out = a.handle_key(ch('6'));
        assert_eq!(out.len(), 2, "{out:?}");
        let Action::Send { id, .. } = &out[0] else {
            panic!()
        };
        a.handle_reply(
            *id,
            Ok(serde_json::json!({"map": "m", "tables": [{"id": 7, "name": "EXX", "kind": "positioning",
                "axis": "X", "base_axis": "X", "direction": "both", "points": 2, "start_mm": 0.0,
                "interval_mm": 10.0, "min_um": 0.0, "max_um": 1.0, "crc": "0x1", "map": "m",
                "source_run": 2, "generated_us": 0, "values_um": [0.0, 1.0]}]})),
            t0,
        );
        assert!(a.handle_key(ch('p')).is_empty());
        // A wrong name is refused; typing goes to the box, not to the tabs.
        for c in ['Y', '1'] {
            assert!(a.handle_key(ch(c)).is_empty());
        }
        assert!(a.handle_key(key(KeyCode::Enter)).is_empty());
        assert_eq!(a.screen, Screen::Publish);
        assert!(a.message.as_ref().unwrap().text.contains("\"X\""));
        a.handle_key(key(KeyCode::Backspace));
        a.handle_key(key(KeyCode::Backspace));
        a.handle_key(ch('x'));
        let out = a.handle_key(key(KeyCode::Enter));
        let [Action::Send { id, request }] = &out[..] else {
            panic!("{out:?}")
        };
        assert_eq!(
            request,
            &Request::TablePublish {
                table_id: 7,
                confirm: true
            }
        );
        assert_eq!(a.publish.publishing, Some(7));
        let out = a.handle_reply(
            *id,
            Ok(serde_json::json!({"table_id": 7, "target": "plc", "sequence": 4, "result": "rejected",
                "code": 3, "message": "the PLC rejected sequence 4: limits", "commit_sent": true})),
            t0,
        );
        assert_eq!(a.publish.publishing, None);
        assert!(matches!(&a.publish.outcome, Some(Ok(p)) if p.code == Some(3)));
        // The list again (the status once its outstanding request is answered).
        assert!(
            matches!(
                &out[..],
                [Action::Send {
                    request: Request::TableList { .. },
                    ..
                }]
            ),
            "{out:?}"
        );
    }

    #[test]
    fn calibrate_fit_asks_then_accept_asks_and_a_viewer_cannot() {
        let (mut a, t0) = app();
        let out = a.handle_key(ch('3'));
        assert!(matches!(
            &out[..],
            [Action::Send {
                request: Request::Calibration,
                ..
            }]
        ));
        a.handle_key(ch('f'));
        for c in "/tmp/p.csv".chars() {
            a.handle_key(ch(c));
        }
        assert!(a.handle_key(key(KeyCode::Enter)).is_empty());
        assert_eq!(
            a.overlay,
            Overlay::Confirm(Confirm::Fit("/tmp/p.csv".into()))
        );
        let out = a.handle_key(ch('y'));
        let [Action::Send { id, request }] = &out[..] else {
            panic!("{out:?}")
        };
        assert_eq!(
            request,
            &Request::CalibrationFit {
                poses: "/tmp/p.csv".into()
            }
        );
        assert!(a.calibrate.fitting);
        a.handle_reply(
            *id,
            Ok(
                serde_json::json!({"pending": {"source": "/tmp/p.csv", "poses": 60, "rank": 7,
                "condition_number": 5.0, "decoupling": "model"}}),
            ),
            t0,
        );
        assert!(!a.calibrate.fitting);
        assert_eq!(a.calibrate.pending.as_ref().map(|p| p.poses), Some(60));
        assert!(a.handle_key(ch('a')).is_empty());
        let out = a.handle_key(ch('y'));
        assert!(matches!(
            &out[..],
            [Action::Send {
                request: Request::CalibrationAccept,
                ..
            }]
        ));
        a.access = Access::Viewer;
        assert!(a.handle_key(ch('f')).is_empty());
        assert_eq!(a.overlay, Overlay::None);
    }

    #[test]
    fn w_saves_the_plans_program_to_the_typed_path() {
        let (mut a, _) = app();
        a.handle_key(ch('4'));
        a.plan.spec.end_mm = 20.0;
        a.plan.spec.targets = 5;
        a.plan.spec.runs = 2;
        assert!(a.handle_key(ch('w')).is_empty());
        for _ in 0..20 {
            a.handle_key(key(KeyCode::Backspace));
        }
        for c in "/tmp/x.nc".chars() {
            a.handle_key(ch(c));
        }
        let out = a.handle_key(key(KeyCode::Enter));
        let [Action::Save { path, text }] = &out[..] else {
            panic!("{out:?}")
        };
        assert_eq!(path, "/tmp/x.nc");
        assert_eq!(text, &a.program_text().unwrap());
        assert!(text.contains("20"), "{text}");
        a.handle_saved(path, Err("Permission denied".into()));
        assert!(
            a.message
                .as_ref()
                .unwrap()
                .text
                .contains("Permission denied")
        );
    }

    #[test]
    fn run_status_is_polled_only_on_the_measure_screen() {
        let (mut a, t0) = app();
        assert!(a.tick(t0).is_empty());
        a.handle_key(ch('4'));
        assert_eq!(a.tick(t0).len(), 1);
        // Not again while one is outstanding, nor before the interval.
        assert!(a.tick(t0 + Duration::from_secs(5)).is_empty());
    }
}
