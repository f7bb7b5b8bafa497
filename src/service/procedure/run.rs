//! The measurement run in the service (`run_start`, `run_status`, `run_abort`): the ISO 230-2
//! cycle's part program to the CNC, the captures the pipeline takes stored as they come, the
//! programs after it — the rest of the cycle after a pause, make-up passes for what is
//! missing — from [`crate::run::session`] (the same logic the virtual-time lab runs), and a
//! run found unfinished in the store at start resumed once the follower is ready.
//!
//! Nothing here waits for the disk: the run is created, its captures and its end stored
//! through the store's queue. A capture the store does not take (locked past its busy
//! timeout, a full disk) is kept and stored again every second, with the `store` alarm up
//! until it is in; the run ends only once every capture is stored.

use super::{Ctx, Procedure, Reply, Who};
use crate::config::CncMode;
use crate::evaluate::recorded::RecordedBudget;
use crate::run::program::CaptureMode;
use crate::run::session::{Next, Program, Session};
use crate::run::{Capture, CaptureSettings, Dialect, Plan, PlanSpec, RunMachine, TargetKey};
use crate::service::api::snapshot::RunView;
use crate::service::api::{Request, Snapshot};
use crate::service::cnc::{CncDriver, CncNews};
use crate::service::pipeline::{Output, Pipeline};
use crate::store::{NewRun, RunId, RunState, StoreError};
use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;
use std::time::{Duration, Instant};
use tokio::sync::mpsc;

use crate::run::ETA_ACCEL_MM_S2;

/// A capture the store did not take is offered again after this long.
const RETRY_EVERY: Duration = Duration::from_secs(1);

/// A run found unfinished in the store at start, resumed once the follower is ready.
#[derive(Debug)]
pub struct Resume {
    pub id: RunId,
    pub plan: Plan,
    /// The dialect the run was started with (its programs go on in it).
    pub dialect: Dialect,
    /// The captures stored (the judge takes them as true and checks the rest against them).
    pub stored: Vec<Capture>,
    /// The programs already written for it (their numbers go on from there).
    pub programs: u32,
}

/// What the service knows that a run needs.
#[derive(Clone, Debug)]
pub struct RunConfig {
    pub capture: CaptureSettings,
    /// The acquisition's frame rate (Hz; 0: as fast as the module answers).
    pub rate_hz: f64,
    pub dialect: Dialect,
    pub cnc: CncMode,
    pub state_dir: PathBuf,
}

/// News of the run's asynchronous work.
enum News {
    /// The store created a run (or could not).
    Created(Box<Created>),
    /// A capture went to the store: stored (or already there), or not.
    Stored {
        key: TargetKey,
        result: Result<(), String>,
    },
    /// A flag or an event went to the store, or not.
    Recorded { id: u64, result: Result<(), String> },
}

/// A flagged capture or an event of the active run, for the store (kept until it is stored).
#[derive(Clone, Debug)]
enum Record {
    Flag {
        capture: Capture,
        reason: String,
        stored: bool,
        unix_us: i64,
    },
    Event {
        kind: String,
        detail: String,
        unix_us: i64,
    },
    Restate {
        capture: Capture,
        reason: String,
        unix_us: i64,
    },
}

/// A run the store created (or could not): the reply owed, the plan, its dialect.
struct Created {
    reply: Reply,
    plan: Plan,
    dialect: Dialect,
    id: Result<RunId, String>,
}

/// The state of a finished run whose flags are open (and the start of its notes).
pub const WITH_FLAGS: &str = "finished with flags";

/// A run being measured.
struct Active {
    id: RunId,
    dialect: Dialect,
    session: Session,
    cnc: CncDriver,
    /// Where the last program went.
    program: String,
    /// Captures taken and not yet stored (the store's answer awaited, or to offer again).
    unstored: BTreeMap<TargetKey, (Capture, bool)>,
    /// Flags and events not yet stored (the store's answer awaited: true), by number.
    unrecorded: BTreeMap<u64, (Record, bool)>,
    next_record: u64,
    /// When the captures the store refused are offered again.
    retry_at: Option<Instant>,
    /// The run machine has every capture: the run ends once they are stored.
    complete: bool,
    /// The program ended: what comes next is decided once every spot is back.
    ended: bool,
    /// The last program sent, and when to send it again when it could not be written or
    /// taken (a full disk).
    last: Option<Program>,
    send_again_at: Option<Instant>,
    /// When this process started the run or took it up again after a restart: its machine
    /// time so far is counted from here.
    started: Instant,
    resumed: bool,
}

/// The service's measurement run: at most one at a time.
pub struct MeasurementRun {
    cfg: RunConfig,
    active: Option<Active>,
    /// A start waits for the store to create its run.
    starting: bool,
    resume: Option<Resume>,
    tx: mpsc::Sender<News>,
    rx: mpsc::Receiver<News>,
}

impl MeasurementRun {
    pub fn new(cfg: RunConfig, resume: Option<Resume>) -> MeasurementRun {
        let (tx, rx) = mpsc::channel(64);
        MeasurementRun {
            cfg,
            active: None,
            starting: false,
            resume,
            tx,
            rx,
        }
    }

    /// `run_start`: checks on the loop; the run created by the store; then its program.
    fn start(
        &mut self,
        spec: PlanSpec,
        dialect: Option<String>,
        notes: Option<String>,
        who: &Who,
        reply: Reply,
        ctx: &mut Ctx,
    ) {
        if let Some(a) = &self.active {
            return reply.send(Err(format!("run {} is under way: abort it first", a.id.0)));
        }
        if self.starting || self.resume.is_some() {
            return reply.send(Err(
                "a run is being started (or resumed): wait for it, then abort it first".into(),
            ));
        }
        let r = self.prepare(spec, dialect, notes, who, ctx);
        let (plan, dialect, new) = match r {
            Ok(p) => p,
            Err(e) => return reply.send(Err(e)),
        };
        let tx = self.tx.clone();
        let job = ctx.store.try_call(move |s| -> Result<RunId, StoreError> {
            let id = s.create_run(&new)?;
            s.set_run_state(id, RunState::Running)?;
            Ok(id)
        });
        match job {
            Ok(done) => {
                self.starting = true;
                tokio::spawn(async move {
                    let id = match done.await {
                        Ok(r) => r.map_err(|e| e.to_string()),
                        Err(e) => Err(e.to_string()),
                    };
                    let _ = tx
                        .send(News::Created(Box::new(Created {
                            reply,
                            plan,
                            dialect,
                            id,
                        })))
                        .await;
                });
            }
            Err(e) => reply.send(Err(format!("the run was not created: {e}"))),
        }
    }

    /// Everything a start checks before the store is asked: the plan, the dwell, the beam
    /// alignment, the dialect; the run's record.
    fn prepare(
        &self,
        spec: PlanSpec,
        dialect: Option<String>,
        notes: Option<String>,
        who: &Who,
        ctx: &mut Ctx,
    ) -> Result<(Plan, Dialect, NewRun), String> {
        let capture = self.cfg.capture;
        let plan = Plan::new(spec).map_err(|e| e.to_string())?;
        if plan.spec.overrun_mm <= capture.target_tolerance_mm {
            return Err(format!(
                "the overrun ({} mm) must exceed capture.target_tolerance_mm ({} mm), or reversals look like targets",
                plan.spec.overrun_mm, capture.target_tolerance_mm
            ));
        }
        // At 0 Hz the module is read as fast as it answers: assume no less than 200 frames/s.
        let rate = if self.cfg.rate_hz > 0.0 {
            self.cfg.rate_hz
        } else {
            200.0
        };
        capture.check_dwell(&plan, rate, ctx.env.settings.tracking.rest_at_stop())?;
        let align = crate::service::align::AlignState::new(ctx.env.settings.align.clone());
        align.pre_run_check(
            ctx.cached.alignments.get(&plan.spec.axis),
            &plan.spec.axis,
            plan.travel_mm(),
            crate::store::now_us(),
        )?;
        let dialect = match dialect {
            Some(d) => Dialect::parse(&d).ok_or_else(|| {
                format!("dialect \"{d}\": use iso, siemens, heidenhain or linuxcnc")
            })?,
            None => self.cfg.dialect,
        };
        if matches!(self.cfg.cnc, CncMode::Twin(_))
            && !matches!(dialect, Dialect::Iso | Dialect::LinuxCnc)
        {
            return Err("the twin's CNC runs iso or linuxcnc programs".into());
        }
        let budget: RecordedBudget = crate::service::run_budget::record(
            &crate::service::run_budget::AtStart {
                calibrations: ctx.calibrations,
                follower_map: ctx.shown.as_ref(),
                encoder_mm: ctx.pipeline.follower_state().map(|f| f.position_mm),
                carriage_mm: ctx.pipeline.measure.position(),
                decoupler: ctx.pipeline.measure.decoupler(),
            },
            &plan,
        );
        let new = NewRun {
            axis: plan.spec.axis.clone(),
            plan: serde_json::to_value(&plan).map_err(|e| e.to_string())?,
            config: serde_json::json!({
                "capture": capture.to_json(),
                "dialect": dialect.name(),
                "budget": budget.to_json(),
            }),
            calibration: ctx.calibrations.active_id(),
            notes: notes.unwrap_or_else(|| format!("started by {}", who.user)),
        };
        Ok((plan, dialect, new))
    }

    /// Start measuring `id` with `done` captures already stored (a resumed run: `resumed_at`
    /// is where the follower holds the carriage's last position), and send the CNC its
    /// first program; `then` is answered once it is written (and sent).
    #[allow(clippy::too_many_arguments)]
    fn begin(
        &mut self,
        id: RunId,
        plan: Plan,
        dialect: Dialect,
        stored: Vec<Capture>,
        resumed_at: Option<f64>,
        programs: u32,
        then: Option<(Reply, serde_json::Value)>,
        ctx: &mut Ctx,
    ) {
        let done: BTreeSet<TargetKey> = stored.iter().map(TargetKey::of).collect();
        let machine = RunMachine::resumed(plan.clone(), self.cfg.capture, false, stored);
        let mut session = Session::new(plan);
        session.programs = programs;
        let first = session.first(&done, resumed_at);
        self.active = Some(Active {
            id,
            dialect,
            session,
            cnc: CncDriver::new(self.cfg.cnc.clone()),
            program: String::new(),
            unstored: BTreeMap::new(),
            unrecorded: BTreeMap::new(),
            next_record: 0,
            retry_at: None,
            complete: false,
            ended: false,
            last: None,
            send_again_at: None,
            started: ctx.now,
            resumed: resumed_at.is_some(),
        });
        match resumed_at {
            Some(_) => ctx.pipeline.resume_run(machine),
            None => ctx.pipeline.start_run(machine),
        }
        match (first, then) {
            (Some(p), then) => self.deliver(&p, then, ctx),
            (None, Some((reply, answer))) => reply.send(Ok(answer)),
            (None, None) => {}
        }
    }

    /// Write (and with the twin's CNC send) program `p` of the active run; `then` is answered
    /// once it is written (and sent).
    fn deliver(&mut self, p: &Program, then: Option<(Reply, serde_json::Value)>, ctx: &mut Ctx) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        let text = match p.text(a.session.plan(), a.dialect, CaptureMode::Stability) {
            Ok(t) => t,
            Err(e) => {
                let why = format!("no program: {e}");
                ctx.pipeline.alarms.raise("run", why.clone());
                if let Some((reply, _)) = then {
                    reply.send(Err(why));
                }
                return;
            }
        };
        let dir = self.cfg.state_dir.join("runs").join(a.id.0.to_string());
        let name = format!("program-{}", a.session.programs);
        let file = match a.cnc.program_file(&dir, &name, a.dialect) {
            Ok((file, _)) => file,
            Err(e) => {
                ctx.pipeline.alarms.raise("cnc", e.clone());
                if let Some((reply, _)) = then {
                    reply.send(Err(e));
                }
                return;
            }
        };
        a.send_again_at = None;
        a.last = Some(p.clone());
        a.program = file.display().to_string();
        let then = then.map(|(reply, mut answer)| {
            answer["program"] = serde_json::json!(a.program);
            (reply, answer)
        });
        let axis = a.session.plan().spec.axis.clone();
        a.cnc.deliver(file, text, a.dialect, &axis, then);
        // A follower that lost the spot waits for the carriage at the program's first target.
        if let Some(first) = p.steps.iter().find(|s| s.target.is_some())
            && ctx.pipeline.seek_carriage(first.position_mm, ctx.now)
        {
            tracing::info!(
                at_mm = first.position_mm,
                "PSD2 has no spot: the follower waits for the carriage at the program's first target"
            );
        }
    }

    /// Store a capture through the queue; its answer comes back as news.
    fn store_capture(&mut self, c: Capture, ctx: &mut Ctx) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        let (id, key, tx) = (a.id, TargetKey::of(&c), self.tx.clone());
        a.unstored.insert(key, (c, true));
        match ctx.store.try_call(move |s| s.insert_capture(id, &c)) {
            Ok(done) => {
                tokio::spawn(async move {
                    let result = match done.await {
                        Ok(Ok(_)) => Ok(()),
                        Ok(Err(e)) => Err(e.to_string()),
                        Err(e) => Err(e.to_string()),
                    };
                    let _ = tx.send(News::Stored { key, result }).await;
                });
            }
            Err(e) => self.refused(key, &e.to_string(), ctx),
        }
    }

    /// Keep `r` for the store, and offer it.
    fn record(&mut self, r: Record, ctx: &mut Ctx) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        let id = a.next_record;
        a.next_record += 1;
        a.unrecorded.insert(id, (r, true));
        self.offer_record(id, ctx);
    }

    fn offer_record(&mut self, id: u64, ctx: &mut Ctx) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        let Some((r, asked)) = a.unrecorded.get_mut(&id) else {
            return;
        };
        *asked = true;
        let (run, r, tx) = (a.id, r.clone(), self.tx.clone());
        let job = ctx.store.try_call(move |s| match r {
            Record::Flag {
                capture,
                reason,
                stored,
                unix_us,
            } => s.flag_capture(run, &capture, &reason, stored, unix_us),
            Record::Event {
                kind,
                detail,
                unix_us,
            } => s.record_run_event(run, unix_us, &kind, &detail),
            Record::Restate {
                capture,
                reason,
                unix_us,
            } => s
                .restate_capture(run, &capture, &reason, unix_us)
                .map(|_| ()),
        });
        match job {
            Ok(done) => {
                tokio::spawn(async move {
                    let result = match done.await {
                        Ok(Ok(())) => Ok(()),
                        Ok(Err(e)) => Err(e.to_string()),
                        Err(e) => Err(e.to_string()),
                    };
                    let _ = tx.send(News::Recorded { id, result }).await;
                });
            }
            Err(e) => self.record_refused(id, &e.to_string(), ctx),
        }
    }

    /// The store did not take flag or event `id`: kept, offered again in a second.
    fn record_refused(&mut self, id: u64, why: &str, ctx: &mut Ctx) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        if let Some(u) = a.unrecorded.get_mut(&id) {
            u.1 = false;
        }
        a.retry_at.get_or_insert(ctx.now + RETRY_EVERY);
        ctx.pipeline.alarms.raise(
            "store",
            format!(
                "run record not stored: {why}; {} kept, stored again every {} s",
                a.unrecorded.len(),
                RETRY_EVERY.as_secs()
            ),
        );
    }

    /// The store did not take capture `key`: kept, offered again in a second.
    fn refused(&mut self, key: TargetKey, why: &str, ctx: &mut Ctx) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        if let Some(u) = a.unstored.get_mut(&key) {
            u.1 = false;
        }
        a.retry_at.get_or_insert(ctx.now + RETRY_EVERY);
        ctx.pipeline.alarms.raise(
            "store",
            format!(
                "capture not stored: {why}; {} kept, stored again every {} s",
                a.unstored.len(),
                RETRY_EVERY.as_secs()
            ),
        );
    }

    /// End the active run in `state` (stored through the queue).
    fn end(&mut self, state: RunState, why: &str, ctx: &mut Ctx) {
        let Some(mut a) = self.active.take() else {
            return;
        };
        a.cnc.forget();
        let (id, note) = (a.id, why.to_string());
        let failed = state == RunState::Failed;
        // A run that ends with flags open says why in its notes (its state reads "finished
        // with flags" while they are open).
        let keep_note = failed || why.starts_with(WITH_FLAGS);
        let job = ctx.store.try_call(move |s| {
            s.set_run_state(id, state)?;
            if keep_note {
                s.set_run_notes(id, &note)?;
            }
            Ok::<(), StoreError>(())
        });
        if let Err(e) = job {
            ctx.pipeline
                .alarms
                .raise("store", format!("run {} state not stored: {e}", id.0));
        }
        if failed {
            ctx.pipeline
                .alarms
                .raise("run-failed", format!("run {} failed: {why}", id.0));
        } else {
            ctx.pipeline.alarms.clear("run-failed");
        }
        tracing::info!(run = id.0, state = state.as_str(), "run ended: {why}");
    }

    /// The resumed run, once the follower is ready: the CNC first brings the carriage back
    /// to the follower (which held its position while the service was down), where PSD2
    /// finds the spot again, then goes on with the rest of the cycle.
    fn try_resume(&mut self, ctx: &mut Ctx) {
        if self.resume.is_none() {
            return;
        }
        let Some(fs) = ctx.pipeline.follower_state().filter(|f| f.ready) else {
            return;
        };
        let Some(r) = self.resume.take() else {
            return;
        };
        tracing::info!(run = r.id.0, captured = r.stored.len(), "resuming the run");
        let done: BTreeSet<TargetKey> = r.stored.iter().map(TargetKey::of).collect();
        if crate::run::program::remaining_steps(&r.plan, &done).is_none() {
            let (id, why) = (
                r.id,
                "nothing left to capture, yet the run was not finished".to_string(),
            );
            self.fail_record(id, &why, ctx);
            return;
        }
        self.begin(
            r.id,
            r.plan,
            r.dialect,
            r.stored,
            Some(fs.position_mm),
            r.programs,
            None,
            ctx,
        );
    }

    /// Mark a stored run failed (one that cannot resume).
    fn fail_record(&mut self, id: RunId, why: &str, ctx: &mut Ctx) {
        let note = why.to_string();
        let _ = ctx.store.try_call(move |s| {
            s.set_run_state(id, RunState::Failed)?;
            s.set_run_notes(id, &note)
        });
        ctx.pipeline
            .alarms
            .raise("run-failed", format!("run {} cannot resume: {why}", id.0));
    }

    /// `run_status`: while running, the plan's machine time (`plan_s`), what is left of it
    /// (`left_s`), for the ETA, and the machine time so far (`machine_s`, since the run started
    /// or this process took it up again: `resumed`); else the newest stored run (read off the
    /// loop), with its machine time from its start to its end when it ended
    /// (`machine_time_s`).
    fn status(&self, reply: Reply, ctx: &mut Ctx) {
        if let (Some(a), Some((done, total))) = (&self.active, ctx.pipeline.run_progress()) {
            let plan = a.session.plan();
            let plan_s = plan.motion_time_s(ETA_ACCEL_MM_S2);
            let left_s = plan_s * total.saturating_sub(done) as f64 / total.max(1) as f64;
            let (flagged, held, unverified) = ctx.pipeline.run_judged().unwrap_or_default();
            return reply.send(Ok(serde_json::json!({
                "run_id": a.id.0, "state": "running", "captures": done, "expected": total,
                "missing": ctx.pipeline.run_missing().map(|m| m.len()).unwrap_or(0),
                "flagged": flagged,
                "held": held,
                "unverified_since": unverified,
                "program": a.program,
                "paused": ctx.pipeline.paused(),
                "plan_s": plan_s,
                "left_s": left_s,
                "machine_s": ctx.now.saturating_duration_since(a.started).as_secs_f64(),
                "resumed": a.resumed,
            })));
        }
        let store = ctx.store.clone();
        tokio::spawn(async move {
            let r = store
                .call(|s| {
                    let newest = s.list_runs()?.into_iter().max_by_key(|r| r.id.0);
                    Ok::<_, StoreError>(match newest {
                        Some(r) => {
                            let flags = s.capture_flags(r.id)?;
                            let open = flags.iter().filter(|f| f.open()).count();
                            let state = if r.state == RunState::Finished && open > 0 {
                                WITH_FLAGS
                            } else {
                                r.state.as_str()
                            };
                            let ended = matches!(
                                r.state,
                                RunState::Finished | RunState::Failed | RunState::Aborted
                            );
                            serde_json::json!({
                                "run_id": r.id.0, "state": state,
                                "captures": s.captures(r.id).map(|c| c.len()).unwrap_or(0),
                                "flagged": flags.len(),
                                "flags_open": open,
                                "notes": r.notes,
                                "machine_time_s": ended.then(|| r.machine_time_s()),
                            })
                        }
                        None => serde_json::json!({"state": "none"}),
                    })
                })
                .await;
            reply.send(match r {
                Ok(Ok(v)) => Ok(v),
                Ok(Err(e)) => Err(e.to_string()),
                Err(e) => Err(e.to_string()),
            });
        });
    }

    fn heard(&mut self, n: News, ctx: &mut Ctx) {
        match n {
            News::Created(c) => {
                let Created {
                    reply,
                    plan,
                    dialect,
                    id,
                } = *c;
                self.starting = false;
                let id = match id {
                    Ok(id) => id,
                    Err(e) => return reply.send(Err(format!("the run was not created: {e}"))),
                };
                let answer = serde_json::json!({
                    "run_id": id.0, "captures_expected": plan.capture_count(),
                    "warnings": plan.warnings(),
                    "cnc": match self.cfg.cnc {
                        CncMode::Twin(a) => format!("sent to the twin at {a}"),
                        CncMode::Manual => "load the program on the CNC and start it".into(),
                    }
                });
                self.begin(
                    id,
                    plan,
                    dialect,
                    Vec::new(),
                    None,
                    0,
                    Some((reply, answer)),
                    ctx,
                );
            }
            News::Stored { key, result } => match result {
                Ok(()) => {
                    let Some(a) = self.active.as_mut() else {
                        return;
                    };
                    if a.unstored.remove(&key).is_some() {
                        tracing::info!(run = a.id.0, capture = %key, direction = key.direction.sign(), "captured");
                    }
                    if a.unstored.values().all(|(_, asked)| *asked) {
                        // The store takes writes again (a full disk freed, a lock gone).
                        ctx.pipeline.alarms.clear("store");
                    }
                }
                Err(e) => self.refused(key, &e, ctx),
            },
            News::Recorded { id, result } => match result {
                Ok(()) => {
                    let Some(a) = self.active.as_mut() else {
                        return;
                    };
                    a.unrecorded.remove(&id);
                    if a.unstored.values().all(|(_, asked)| *asked)
                        && a.unrecorded.values().all(|(_, asked)| *asked)
                    {
                        ctx.pipeline.alarms.clear("store");
                    }
                }
                Err(e) => self.record_refused(id, &e, ctx),
            },
        }
    }
}

impl Procedure for MeasurementRun {
    fn name(&self) -> &'static str {
        "the measurement run"
    }

    fn takes(&self, req: &Request) -> bool {
        matches!(
            req,
            Request::RunStart { .. } | Request::RunStatus | Request::RunAbort
        )
    }

    fn starts(&self, req: &Request) -> bool {
        matches!(req, Request::RunStart { .. })
    }

    fn holds_machine(&self) -> bool {
        self.active.is_some() || self.starting || self.resume.is_some()
    }

    fn busy(&self, what: &str) -> String {
        match &self.active {
            Some(a) => format!(
                "measurement run {} is under way (it moves the carriage): abort it with run_abort or let it finish, then {what}",
                a.id.0
            ),
            None => format!(
                "a measurement run is being started or resumed: wait for it (run_status), then {what}"
            ),
        }
    }

    fn request(&mut self, req: Request, who: &Who, reply: Reply, ctx: &mut Ctx) {
        match req {
            Request::RunStart {
                plan,
                dialect,
                notes,
            } => self.start(plan, dialect, notes, who, reply, ctx),
            Request::RunStatus => self.status(reply, ctx),
            Request::RunAbort => {
                if ctx.pipeline.abort_run() {
                    let id = self.active.as_ref().map(|a| a.id.0);
                    if let Some(a) = self.active.as_mut() {
                        a.cnc.stop();
                    }
                    self.end(RunState::Aborted, &format!("aborted by {}", who.user), ctx);
                    reply.send(Ok(serde_json::json!({"aborted": id})));
                } else {
                    reply.send(Err("no run is under way".into()));
                }
            }
            _ => reply.send(Err("internal: not a run request".into())),
        }
    }

    fn claims(&self, out: &Output) -> bool {
        matches!(out, Output::Handover(_)) && self.active.is_some()
    }

    fn on_output(&mut self, out: &Output, ctx: &mut Ctx) {
        match out {
            Output::Handover(r) => {
                let Some(a) = self.active.as_ref() else {
                    return;
                };
                let (id, r) = (a.id, *r);
                if let Err(e) = ctx.store.try_call(move |s| s.insert_handover(Some(id), &r)) {
                    ctx.pipeline
                        .alarms
                        .raise("store", format!("handover not stored: {e}"));
                }
            }
            Output::Captured(c) => self.store_capture(*c, ctx),
            Output::Flagged {
                capture,
                reason,
                stored,
            } => {
                if let Some(a) = self.active.as_mut() {
                    // Not offered again: the flag keeps it.
                    a.unstored.remove(&TargetKey::of(capture));
                }
                self.record(
                    Record::Flag {
                        capture: *capture,
                        reason: reason.clone(),
                        stored: *stored,
                        unix_us: crate::util::clock::unix_us(),
                    },
                    ctx,
                );
            }
            Output::Restated { capture, reason } => {
                let Some(a) = self.active.as_mut() else {
                    return;
                };
                // Not stored yet: it is offered with its new u; else the store keeps both.
                if let Some((c, _)) = a.unstored.get_mut(&TargetKey::of(capture))
                    && c.unix_us == capture.unix_us
                {
                    c.u = capture.u;
                }
                self.record(
                    Record::Restate {
                        capture: *capture,
                        reason: reason.clone(),
                        unix_us: crate::util::clock::unix_us(),
                    },
                    ctx,
                );
            }
            Output::RunEvent { kind, detail } => {
                tracing::warn!(kind = %kind, "run event: {detail}");
                self.record(
                    Record::Event {
                        kind: kind.clone(),
                        detail: detail.clone(),
                        unix_us: crate::util::clock::unix_us(),
                    },
                    ctx,
                );
            }
            // The pipeline keeps the alarm. With the beam off the fixed PSDs the twin's CNC
            // stops at its next stop, and the rest of the cycle follows once the beam is
            // back. PSD2 alone (the follower behind) waits for the carriage's pass. A CNC the
            // service does not drive goes on: what it missed is the make-up pass's.
            Output::RunPaused(why) => {
                tracing::warn!("{why}");
                // Nothing is captured while paused: the program stops at its next stop and
                // the rest of the cycle follows once the spots are back (PSD2's found by
                // sending the follower to the carriage's next stop, `deliver`).
                if let Some(a) = self.active.as_mut()
                    && a.cnc.twin().is_some()
                {
                    a.cnc.stop();
                    a.session.paused();
                }
            }
            Output::RunResumed => tracing::info!("every spot is back: the run goes on"),
            Output::RunFinished => {
                if let Some(a) = self.active.as_mut() {
                    a.complete = true;
                }
            }
            Output::RunFailed(why) => self.end(RunState::Failed, why, ctx),
            _ => {}
        }
    }

    fn tick(&mut self, ctx: &mut Ctx) {
        while let Ok(n) = self.rx.try_recv() {
            self.heard(n, ctx);
        }
        self.try_resume(ctx);
        let now = ctx.now;
        let Some(a) = self.active.as_mut() else {
            return;
        };
        // Captures the store refused, offered again.
        if a.retry_at.is_some_and(|t| now >= t) {
            a.retry_at = None;
            let again: Vec<Capture> = a
                .unstored
                .values()
                .filter(|(_, asked)| !asked)
                .map(|(c, _)| *c)
                .collect();
            for c in again {
                self.store_capture(c, ctx);
            }
            let records: Vec<u64> = self
                .active
                .as_ref()
                .map(|a| {
                    a.unrecorded
                        .iter()
                        .filter(|(_, (_, asked))| !asked)
                        .map(|(id, _)| *id)
                        .collect()
                })
                .unwrap_or_default();
            for id in records {
                self.offer_record(id, ctx);
            }
        }
        let Some(a) = self.active.as_mut() else {
            return;
        };
        if a.send_again_at.is_some_and(|t| now >= t)
            && let Some(p) = a.last.clone()
        {
            a.send_again_at = None;
            self.deliver(&p, None, ctx);
        }
        let Some(a) = self.active.as_mut() else {
            return;
        };
        if a.complete && a.unstored.is_empty() && a.unrecorded.is_empty() {
            self.end(RunState::Finished, "all captures taken", ctx);
            return;
        }
        for n in a.cnc.poll(now) {
            match n {
                CncNews::Refused(e) => {
                    // Written or sent again until it goes (a full disk is freed; a twin
                    // that refuses the text keeps the alarm, and the run's timeout ends it).
                    let again = RETRY_EVERY.as_secs();
                    ctx.pipeline
                        .alarms
                        .raise("cnc", format!("{e}; sent again every {again} s"));
                    if a.last.is_some() {
                        a.send_again_at = Some(now + RETRY_EVERY);
                    }
                }
                CncNews::Taken => ctx.pipeline.alarms.clear("cnc"),
                CncNews::Ended => {
                    ctx.pipeline.alarms.clear("cnc");
                    a.ended = true;
                }
            }
        }
        // The program has ended: once every spot is back (the beam off the fixed PSDs waits),
        // the rest of the cycle or a make-up pass, or the run fails.
        let follower_down = ctx.pipeline.follower_state().is_none_or(|f| !f.ready);
        if !a.ended
            || ctx.pipeline.beam_lost()
            || (ctx.pipeline.paused().is_some() && follower_down)
        {
            return;
        }
        a.ended = false;
        let missing = ctx.pipeline.run_missing().unwrap_or_default();
        match a.session.ended(&missing) {
            Next::Program(p) => {
                tracing::info!(
                    missing = missing.len(),
                    note = %p.note,
                    "the program ended with captures missing: the next program"
                );
                self.deliver(&p, None, ctx);
            }
            Next::Nothing => {}
            Next::Fail(why) => {
                // Every capture still missing was flagged (`run::judge`) and its retakes ran
                // out: the run ends with its flags open, not failed; nothing of it reaches a
                // table until they are retaken or excluded.
                let flagged = ctx.pipeline.run_flagged().unwrap_or_default();
                let all_flagged =
                    !missing.is_empty() && missing.iter().all(|k| flagged.contains(k));
                ctx.pipeline.abort_run();
                if all_flagged {
                    self.end(RunState::Finished, &format!("{WITH_FLAGS}: {why}"), ctx);
                } else {
                    self.end(RunState::Failed, &why, ctx);
                }
            }
        }
    }

    fn show(&self, snap: &mut Snapshot, pipeline: &Pipeline) {
        let Some(a) = &self.active else {
            return;
        };
        let (captures, expected) = pipeline.run_progress().unwrap_or((0, 0));
        snap.run = Some(RunView {
            id: a.id.0,
            axis: a.session.plan().spec.axis.clone(),
            captures,
            expected,
            program: a.program.clone(),
            paused: pipeline.paused().map(str::to_string),
        });
    }
}
