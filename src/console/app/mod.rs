//! The console's state, sans-I/O: keys, snapshots and replies go in (`handle_*`, with the
//! time as an argument where it matters), [`Action`]s come out (requests to send, quit). The
//! screens draw from it and nothing else; the loop in `console::run` only carries things.
//!
//! It has no logic of its own beyond presentation: plans are checked with the library's
//! `Plan::new` only to show the targets and say early what the service would refuse.
//!
//! Split as quinn-proto splits a connection: this file holds the shared state and the inputs
//! every screen shares (link, snapshots, global keys, overlays, help texts); each screen's own
//! state and keys are in a file of their own, and the replies in `reply`.

mod align;
mod calibrate;
mod follower_level;
mod follower_map;
mod machine;
mod measure;
mod publish;
mod reply;
mod results;
#[cfg(test)]
mod tests;
mod trends;

pub use align::{AdviceView, AlignProc, StationSpot, StationView, StoredAlignment};
pub use calibrate::{CalSummary, CalibrateState, HexapodView};
pub use follower_level::parse_level_reading;
pub use follower_map::{AlignPanel, FollowerPanel, parse_mapping};
pub use machine::MachinePanel;
pub use measure::{Field, PlanForm, RunProgress};
pub use publish::PublishState;
pub use results::ResultsView;
pub use trends::{AxisTrend, FigureTrend, ForecastView, TrendPoint, TrendsView};

use super::client::{ClientError, Identity, LinkEvent, PeerRole};
use crate::run::{Plan, PlanSpec};
use crate::service::api::snapshot::Snapshot;
use crate::service::api::{FollowerAction, Request};
use crate::service::results::{AuditView, RunResult, RunSummary};
use crate::service::tables::{PublishView, StatusView, TableView};
use crossterm::event::{KeyCode, KeyEvent, KeyEventKind, KeyModifiers};
use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

/// The screens, in tab order (number keys 1–8).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Screen {
    Live,
    Align,
    Calibrate,
    Measure,
    Results,
    Publish,
    Events,
    Machine,
}

impl Screen {
    pub const ALL: [Screen; 8] = [
        Screen::Live,
        Screen::Align,
        Screen::Calibrate,
        Screen::Measure,
        Screen::Results,
        Screen::Publish,
        Screen::Events,
        Screen::Machine,
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
            Screen::Machine => "Machine",
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
    /// Accept the pending calibration; `true`: over its plausibility concerns (the override).
    Accept(bool),
    /// Start a hexapod calibration run: the plan CSV on the service's host ("" for the
    /// default plan).
    HexapodStart(String),
    /// Map the follower by the stop-and-go self-calibration.
    MapStart(crate::service::api::MappingRequest),
    /// Stop the follower mapping under way.
    MapStop,
    /// Read a level at stations along the map in use's span.
    LevelStart,
    /// Check the map in use on this set-up with a level's stations.
    LevelCheck,
    /// Stop the level stations under way.
    LevelStop,
    /// Detach the run of set-up `setup` (1-based) of machine `id` and those of the set-ups
    /// after it (`runs`, for the question).
    Detach {
        id: i64,
        setup: usize,
        runs: Vec<i64>,
    },
}

/// What a line typed into the input box is for.
#[derive(Clone, Debug, PartialEq)]
pub enum InputFor {
    /// The table's axis name, typed to confirm its publication.
    PublishAxis { table_id: i64, axis: String },
    /// The path of a pose-set CSV on the service's host.
    PosePath,
    /// The hexapod run's plan CSV on the service's host (empty: the default plan).
    HexapodPlan,
    /// Where to save the part program of the plan (on this host).
    ProgramPath,
    /// The alignment's span: "FROM TO" (mm).
    AlignSpan,
    /// What the alignment target shows where a spot is off its PSD: "PSD X Y" (mm).
    AlignTarget,
    /// The follower encoder's certificate CSV on the service's host.
    CertificatePath,
    /// The follower mapping: "FROM TO [PASSES [FRAMES]]".
    Mapping,
    /// The level's reading at the station being read (arcsec).
    LevelReading,
    /// A machine's record (TOML) on the service's host, to store the machine.
    MachineRecord,
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
    HexapodStart,
    HexapodStatus,
    HexapodStop,
    RunStart(Box<Plan>),
    RunStatus,
    RunAbort,
    Runs,
    RunResult(ResultFor),
    Audit,
    AlignRead,
    AlignTarget,
    /// The advice over this span (mm).
    AlignAdvice((f64, f64)),
    AlignStored,
    AlignClear,
    Certificate,
    MapStart,
    MapStop,
    LevelStart,
    LevelStop,
    LevelReading,
    /// The Machine screen's machine.
    Machine,
    /// Attaching this run to the next set-up.
    MachineAttach(i64),
    /// Detaching from this set-up (1-based) on.
    MachineDetach(usize),
    /// Storing a machine from its record's file.
    MachineNew,
    /// The axis's trends (the Results screen's trends view).
    Trend,
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
                | Pending::HexapodStatus
                | Pending::Machine
                | Pending::Trend
        )
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
    /// The input box shows its suggested text selected: the first character typed replaces
    /// it, Backspace clears it (until any key was pressed in the box).
    pub input_fresh: bool,
    pub message: Option<Message>,
    pub plan: PlanForm,
    pub jog_step_mm: f64,
    pub run: Option<RunProgress>,
    pub results: ResultsView,
    /// The Results screen's trends view.
    pub trends: TrendsView,
    /// The error the Measure screen's live plot shows (0..6, `Errors6` order).
    pub live_dof: usize,
    /// The service's audit log, newest first, as last fetched (the Events screen).
    pub audit: Option<Vec<AuditView>>,
    last_audit: Option<Instant>,
    pub publish: PublishState,
    pub calibrate: CalibrateState,
    /// The beam alignment on the Align screen.
    pub align: AlignProc,
    /// The follower error map on the Align screen.
    pub follower: FollowerPanel,
    /// The whole machine's commissioning plan (the Machine screen).
    pub machine: MachinePanel,
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
            input_fresh: true,
            message: None,
            plan: PlanForm {
                spec: PlanSpec::default(),
                selected: 0,
                editing: None,
                notes: None,
            },
            run: None,
            // Positioning first: the ISO 230-2 result.
            trends: TrendsView::default(),
            results: ResultsView {
                dof: 1,
                ..ResultsView::default()
            },
            live_dof: 1,
            audit: None,
            last_audit: None,
            publish: PublishState::default(),
            calibrate: CalibrateState::default(),
            align: AlignProc::default(),
            follower: FollowerPanel::default(),
            machine: MachinePanel::default(),
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
        out.extend(self.calibrate_need_hexapod());
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
            Screen::Machine => out.extend(self.machine_need()),
            Screen::Align => out.extend(self.align_need_stored()),
            _ => {}
        }
        out.extend(self.calibrate_need_hexapod());
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
            // A service that restarted may hold other tables, calibration and alignment
            // than this console last read: what the screens show from the store is read again.
            self.publish.listed = false;
            self.publish.status = None;
            self.calibrate.loaded = false;
            self.align.stored = StoredAlignment::Unknown;
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
                r.paused = rv.paused.clone();
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
        self.observe_mapping();
        self.observe_level();
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
        // The next input box opens with its suggestion selected.
        self.input_fresh = true;
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
            (_, Some(c @ '1'..='8')) => {
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
            Screen::Results if self.trends.shown => self.trends_key(key),
            Screen::Results => self.results_key(key),
            Screen::Publish => self.publish_key(key),
            Screen::Calibrate => self.calibrate_key(key),
            Screen::Machine => self.machine_key(key),
            _ => Vec::new(),
        }
    }

    fn input_key(&mut self, key: KeyEvent) -> Vec<Action> {
        let Overlay::Input(input) = &mut self.overlay else {
            return Vec::new();
        };
        let fresh = std::mem::replace(&mut self.input_fresh, false);
        if key.modifiers.contains(KeyModifiers::CONTROL) && key.code == KeyCode::Char('u') {
            input.text.clear();
            return Vec::new();
        }
        match (key.code, key_char(&key)) {
            (KeyCode::Esc, _) => {
                self.overlay = Overlay::None;
                self.say(Level::Info, "cancelled");
            }
            (KeyCode::Backspace, _) if fresh => input.text.clear(),
            (KeyCode::Backspace, _) => {
                input.text.pop();
            }
            (_, Some(c)) if fresh && !c.is_control() => {
                input.text.clear();
                input.text.push(c);
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
            InputFor::HexapodPlan => {
                self.overlay = Overlay::Confirm(Confirm::HexapodStart(text));
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
            InputFor::AlignSpan | InputFor::AlignTarget => self.align_input(&input.purpose, &text),
            InputFor::CertificatePath | InputFor::Mapping => {
                self.follower_map_input(&input.purpose, &text)
            }
            InputFor::LevelReading => self.follower_level_input(&text),
            InputFor::MachineRecord => self.machine_new(&text),
        }
    }

    /// Go to `screen` (and ask for what it shows, if it has nothing yet).
    fn show(&mut self, screen: Screen) -> Vec<Action> {
        // Publish reads the store and the PLC again each time it is opened: tables generated
        // from the command line, or published by another console, show without `r`.
        if screen == Screen::Publish && self.screen != Screen::Publish {
            self.publish.listed = false;
            self.publish.status = None;
        }
        self.screen = screen;
        let mut out = self.results_need_list();
        out.extend(self.events_need_audit());
        out.extend(self.screens_need());
        out
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
                        notes: self.plan.notes_for(&spec),
                        plan: spec,
                        dialect: None,
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
            Confirm::HexapodStart(plan) => self.hexapod_start(plan),
            c @ (Confirm::MapStart(_) | Confirm::MapStop) => self.follower_map_confirmed(c),
            c @ (Confirm::LevelStart | Confirm::LevelCheck | Confirm::LevelStop) => {
                self.follower_level_confirmed(c)
            }
            Confirm::Accept(force) => {
                self.log(
                    Level::Info,
                    if force {
                        "→ accept the calibration over its concerns"
                    } else {
                        "→ accept the calibration"
                    },
                );
                vec![self.send(Request::CalibrationAccept { force }, Pending::CalAccept)]
            }
            Confirm::Detach { id, setup, .. } => {
                self.log(
                    Level::Info,
                    format!("→ detach set-up {setup} of machine {id} and those after it"),
                );
                vec![self.send(
                    Request::MachineDetach { id, setup },
                    Pending::MachineDetach(setup),
                )]
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
}

/// The keys of a screen, for the help overlay (and its tests): (key, what it does).
pub fn screen_keys(screen: Screen) -> &'static [(&'static str, &'static str)] {
    match screen {
        Screen::Live => &[],
        Screen::Align => &[
            ("h", "home the follower"),
            ("j / k", "jog the follower − / + one step"),
            ("[ / ]", "jog step ÷10 / ×10"),
            ("z / c", "zero here (errors, stitching) / clear it"),
            ("x / r", "stop the follower / reset a fault, enable"),
            ("s", "type the alignment span (from to, mm)"),
            ("n / f", "read the spots at the near / far end"),
            ("t", "type what a PSD's target shows (no spot)"),
            ("a", "advice: the check, the screws to turn"),
            ("e", "erase the stations read (after turning)"),
            ("i / m", "follower: certificate CSV / map (asks), stop"),
            ("l / L", "level stations (asks), its reading / stop"),
            ("v", "panel: follower map / beam alignment"),
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
            ("↑ / ↓", "select a stored run (in the trends: a figure)"),
            ("Enter", "show its results"),
            ("b", "compare with it (before)"),
            ("c", "clear the comparison"),
            ("← / →", "previous / next error"),
            ("t", "the trends of the newest run's axis, and back"),
            ("r", "reload the run list (in the trends: the trends)"),
        ],
        Screen::Calibrate => &[
            (
                "h",
                "calibrate with the hexapod: plan file or default (asks)",
            ),
            ("s", "stop the hexapod run (the poses stay stored)"),
            ("u", "resume the stopped or failed hexapod run"),
            ("f", "fit a pose-set CSV on the service's host (asks)"),
            ("a", "accept the pending calibration (asks)"),
            (
                "A",
                "accept it over its plausibility concerns (the override, asks)",
            ),
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
        Screen::Machine => &[
            ("↑ / ↓", "select a set-up: its steps show"),
            (
                "p",
                "the next set-up's run into Measure's plan (start it there)",
            ),
            ("a", "attach a finished run to the next set-up (pick it)"),
            (
                "n",
                "store a new machine from its record (a TOML file on the service's host)",
            ),
            (
                "d",
                "detach the selected set-up's run and those after it (asked first)",
            ),
            ("r", "reload the machine"),
        ],
    }
}

/// The keys every screen has.
pub const GLOBAL_KEYS: &[(&str, &str)] = &[
    ("1–8", "screens"),
    ("Tab / S-Tab", "next / previous screen"),
    ("?", "this help"),
    ("Esc", "clear the message"),
    ("q", "quit (asks while a run is active)"),
    ("Ctrl-C", "quit now (a run continues in the service)"),
];
