//! The core task: the one place that owns the measurement pipeline (tracking, stitching,
//! live decoupling, alarms) and drives the procedures. It takes frames from the acquisition,
//! the drive's status and events, the operator's requests, and publishes the `Snapshot`.
//!
//! It never waits: drive commands, the store's work (through its queue) and the twin's CNC
//! run as small tasks whose results come back as events; what the procedures look up in the
//! store is kept in a cache the service keeps current. A request goes to the procedure that
//! takes it; one that would start a procedure while another holds the machine is refused in
//! the words of the one that holds it.

mod drive;
mod requests;
mod view;

use super::Prepared;
use super::api::{FollowerMapView, Request, Snapshot};
use super::calibration::Calibrations;
use super::control::Command;
use super::notify;
use super::pipeline::{Output, Pipeline};
use super::procedure::{Cached, Ctx, Env, Procedure, Reply, Who};
use super::shutdown::Shutdown;
use crate::acquire::{Acquisition, Frame};
use crate::canopen::{DriveHandle, DriveStatus, Event, PowerState};
use crate::modbus::LinkState;
use crate::optics::layout::{Aperture, Kind};
use crate::store::StoreQueue;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::{broadcast, mpsc, watch};
use tokio::task::JoinHandle;
use view::CountRate;

/// A frame older than this when the core gets to it is not decoupled (it is still tracked).
const LATE: Duration = Duration::from_millis(100);

/// Exception replies for this long raise the `io-exception` alarm.
const EXCEPTIONS_PERSIST: Duration = Duration::from_secs(1);

/// No sign of the follower drive (no heartbeat, no boot-up) this long after start raises
/// the `drive-absent` alarm.
const DRIVE_ABSENT_AFTER: Duration = Duration::from_secs(5);

/// Events waiting for the core at most (its inputs' tasks wait beyond this).
const EVENTS: usize = 256;

/// A continuation: work the core started, finished; run on the core.
type Then = Box<dyn FnOnce(&mut Core) + Send>;

/// What comes to the core other than frames.
enum CoreEvent {
    /// The drive's status changed.
    DriveStatus(Box<DriveStatus>),
    /// An event of the drive.
    Drive(Event),
    /// The I/O module link's state changed.
    IoState(LinkState),
    /// An operator's request from the control API.
    Command(Command),
    /// Time for a snapshot (and the watchdog).
    Tick,
    /// An input the core cannot go on without has ended.
    Closed(&'static str),
    /// The follower drive was (or could not be) enabled again after its heartbeat came back.
    ReEnabled(Result<(), String>),
    /// Work the core started has finished: carry on.
    Then(Then),
}

/// What the service read before the loop starts (the store is not read on the loop).
pub(super) struct Startup {
    pub cached: Cached,
    pub resume: Option<super::procedure::run::Resume>,
    /// The zero reference in force when the service stopped.
    pub reference: Option<super::measure::ReferenceState>,
}

pub(super) struct Core {
    pipeline: Pipeline,
    acquisition: Acquisition,
    drive: DriveHandle,
    drive_status: DriveStatus,
    can_peer: String,
    node_id: u8,
    /// The follower's SYNC period and its quiet period (for the snapshot).
    sync_periods: (Duration, Duration),
    /// TPDOs per second, from `DriveStatus::tpdo_count` at the snapshot ticks.
    tpdo_rate: CountRate,
    snapshot: watch::Sender<Snapshot>,
    snapshot_period: Duration,
    half_size_um: [f64; 3],
    home_on_start: bool,
    watchdog: bool,
    /// The reply owed to a zero request, answered once the window has refilled.
    zero_reply: Option<Reply>,
    ready_sent: bool,
    started: Instant,
    /// The follower target the tracker wants (the follower task sends the latest).
    follow: watch::Sender<Option<f64>>,
    /// The drive refused mode 8: follow targets go as profile moves.
    csp_refused: bool,
    /// Following ended on an error: re-arm it with a profile move.
    follow_rearm: bool,
    store: StoreQueue,
    cached: Cached,
    /// The follower map in use, as the snapshot shows it.
    follower_map: Option<FollowerMapView>,
    calibrations: Calibrations,
    procedures: Vec<Box<dyn Procedure>>,
    env: Env,
    events_tx: mpsc::Sender<CoreEvent>,
    events_rx: Option<mpsc::Receiver<CoreEvent>>,
    /// What cannot be stored in passing (audit entries), said as the `store` alarm.
    store_alarm_tx: mpsc::Sender<String>,
    store_alarm_rx: mpsc::Receiver<String>,
    /// The zero reference changes offered to the store so far, and the newest one it did not
    /// keep (a full disk), offered again at `reference_retry_at` until it is or a newer one
    /// replaces it: a restart must not take back a reference without the turn of the head
    /// found since (issue 24: a knock found while the disk was full was lost).
    reference_offers: u64,
    reference_unkept: Option<Unkept>,
}

/// A zero reference change the store did not keep: offer number `offer`, offered again at
/// `again_at`.
struct Unkept {
    offer: u64,
    state: Option<super::measure::ReferenceState>,
    again_at: Instant,
}

impl Core {
    pub(super) fn new(
        p: &Prepared,
        acquisition: Acquisition,
        drive: DriveHandle,
        can_peer: String,
        snapshot: watch::Sender<Snapshot>,
        store: StoreQueue,
        startup: Startup,
    ) -> Core {
        let (events_tx, events_rx) = mpsc::channel(EVENTS);
        let (store_alarm_tx, store_alarm_rx) = mpsc::channel(16);
        let s = &p.settings;
        let mut pipeline = Pipeline::new(s.tracking, p.decoupler.clone(), s.head.live_window);
        if let Some(r) = &startup.reference {
            match pipeline.restore_reference(r) {
                Ok(()) => tracing::info!(
                    turns = r.turn_rad != [0.0; 2],
                    "the zero reference in force before the restart is taken back; it is checked at the carriage's next return to the zero"
                ),
                Err(e) => tracing::warn!(
                    "the zero reference kept before the restart is not one ({e}): zero again"
                ),
            }
        }
        let shown = startup.cached.follower_map.as_ref().map(|r| {
            tracing::info!(id = r.id, name = %r.name, "follower map in use");
            pipeline.tracker.set_map(Some(Arc::new(r.map.clone())));
            super::follower::view(r)
        });
        let mut half_size_um = [0.0; 3];
        for (k, path) in p.layout.paths.iter().enumerate() {
            let el = &p.layout.elements[path.psd];
            if el.kind == Kind::Psd {
                half_size_um[k] = match el.aperture {
                    Aperture::Square { half } | Aperture::Circle { radius: half } => half * 1e3,
                };
            }
        }
        let env = Env {
            settings: Arc::new(s.clone()),
            state_dir: s.service.state_dir.clone(),
            cnc: s.cnc.mode.clone(),
        };
        let calibrations = Calibrations::new(
            p.layout.clone(),
            p.calibration.as_ref(),
            &s.head
                .calibration
                .as_ref()
                .map(|f| f.display().to_string())
                .unwrap_or_default(),
        );
        pipeline
            .measure
            .set_calibration_u(calibrations.budget_term());
        Core {
            procedures: procedures(p, startup.resume),
            pipeline,
            acquisition,
            drive_status: drive.status(),
            drive,
            can_peer,
            node_id: s.follower.drive.node_id,
            sync_periods: (
                s.follower.drive.sync_period,
                s.follower.drive.quiet_sync_period,
            ),
            tpdo_rate: CountRate::new(Duration::from_secs(1)),
            snapshot,
            snapshot_period: s.service.snapshot_period,
            half_size_um,
            home_on_start: s.follower.home_on_start,
            watchdog: s.service.watchdog,
            zero_reply: None,
            ready_sent: false,
            started: crate::util::clock::now(),
            follow: watch::channel(None).0,
            csp_refused: false,
            follow_rearm: false,
            store,
            cached: startup.cached,
            follower_map: shown,
            calibrations,
            env,
            events_tx,
            events_rx: Some(events_rx),
            store_alarm_tx,
            store_alarm_rx,
            reference_offers: 0,
            reference_unkept: None,
        }
    }

    /// Lend the procedures what they work with, and call `f` with procedure `i`.
    fn with_procedure<R>(
        &mut self,
        i: usize,
        f: impl FnOnce(&mut dyn Procedure, &mut Ctx) -> R,
    ) -> R {
        let frames_per_s = self.acquisition.stats().frames_per_s;
        let mut ctx = Ctx {
            now: crate::util::clock::now(),
            pipeline: &mut self.pipeline,
            store: &self.store,
            cached: &mut self.cached,
            drive: &self.drive,
            calibrations: &mut self.calibrations,
            shown: &mut self.follower_map,
            frames_per_s,
            env: &self.env,
            acquisition: &self.acquisition,
        };
        f(self.procedures[i].as_mut(), &mut ctx)
    }

    /// Each procedure in turn.
    fn for_each_procedure(&mut self, mut f: impl FnMut(&mut dyn Procedure, &mut Ctx)) {
        for i in 0..self.procedures.len() {
            self.with_procedure(i, &mut f);
        }
    }

    /// The procedure that holds the machine, if one does.
    fn holder(&self) -> Option<&dyn Procedure> {
        self.procedures
            .iter()
            .find(|p| p.holds_machine())
            .map(|p| p.as_ref())
    }

    /// Once `fut` is done, run `then` with its output on the core.
    fn later<T: Send + 'static>(
        &self,
        fut: impl std::future::Future<Output = T> + Send + 'static,
        then: impl FnOnce(&mut Core, T) + Send + 'static,
    ) {
        let tx = self.events_tx.clone();
        tokio::spawn(async move {
            let v = fut.await;
            let _ = tx
                .send(CoreEvent::Then(Box::new(move |core| then(core, v))))
                .await;
        });
    }

    pub(super) async fn run(
        mut self,
        commands: mpsc::Receiver<Command>,
        shutdown: Shutdown,
    ) -> Result<(), super::ServiceError> {
        let mut frames = self.acquisition.subscribe();
        let bring_up = tokio::spawn(drive::bring_up(
            self.drive.clone(),
            self.home_on_start,
            shutdown.clone(),
        ));
        let follower = tokio::spawn(drive::follow(
            self.drive.clone(),
            self.follow.subscribe(),
            shutdown.clone(),
        ));
        let inputs = self.forward_inputs(commands, shutdown.clone());
        let watchdog = notify::watchdog_period().filter(|_| self.watchdog);
        let mut last_watchdog = crate::util::clock::now();
        let mut core_events = self
            .events_rx
            .take()
            .ok_or(super::ServiceError::Internal("core events"))?;
        // Behind the acquisition: give the other tasks a turn after each frame. Working off a
        // backlog must not hold up the tasks that share the core's worker thread (the CANopen
        // task's SYNC above all), which tokio's cooperative budget alone lets it do for 128
        // frames.
        let mut behind = false;
        loop {
            if std::mem::take(&mut behind) {
                tokio::task::yield_now().await;
            }
            // Two inputs: everything but the frames comes through the core's own channel
            // (`forward_inputs`), the shutdown too.
            let e = tokio::select! {
                biased;
                Some(e) = core_events.recv() => e,
                f = frames.recv() => {
                    match f {
                        Ok(f) => {
                            let waiting = frames.len();
                            behind = waiting > 0;
                            self.handle_frame(&f, waiting);
                        }
                        Err(broadcast::error::RecvError::Lagged(n)) => {
                            tracing::warn!("core fell behind the acquisition by {n} frames");
                        }
                        Err(broadcast::error::RecvError::Closed) => break,
                    }
                    continue;
                }
            };
            match e {
                CoreEvent::Tick => {
                    self.on_tick();
                    if let Some(period) = watchdog
                        && crate::util::clock::since(last_watchdog) >= period
                    {
                        notify::watchdog();
                        last_watchdog = crate::util::clock::now();
                    }
                }
                CoreEvent::Closed(what) => {
                    tracing::debug!("core input closed: {what}");
                    break;
                }
                e => self.handle_core_event(e),
            }
        }
        for t in inputs {
            t.abort();
        }
        bring_up.abort();
        follower.abort();
        // Leave the follower at rest.
        let _ = tokio::time::timeout(Duration::from_secs(1), self.drive.stop()).await;
        Ok(())
    }

    /// Tasks that forward the core's inputs other than frames (the shutdown, drive status and
    /// events, the I/O link's state, operator commands, the snapshot tick) into its event
    /// channel, in the order they come. Waiting on each input in the core's own select would
    /// register and drop a waker for every one of them at every frame.
    fn forward_inputs(
        &self,
        mut commands: mpsc::Receiver<Command>,
        mut shutdown: Shutdown,
    ) -> Vec<JoinHandle<()>> {
        let tx = &self.events_tx;
        let mut status = self.drive.watch_status();
        let mut events = self.drive.events();
        let mut io_state = self.acquisition.link().state();
        let mut tick = tokio::time::interval(self.snapshot_period.min(Duration::from_millis(100)));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        vec![
            tokio::spawn({
                let tx = tx.clone();
                async move {
                    shutdown.recv().await;
                    let _ = tx.send(CoreEvent::Closed("shutdown")).await;
                }
            }),
            tokio::spawn({
                let tx = tx.clone();
                async move {
                    while status.changed().await.is_ok() {
                        let st = status.borrow_and_update().clone();
                        if tx.send(CoreEvent::DriveStatus(Box::new(st))).await.is_err() {
                            return;
                        }
                    }
                    let _ = tx.send(CoreEvent::Closed("drive status")).await;
                }
            }),
            tokio::spawn({
                let tx = tx.clone();
                async move {
                    loop {
                        match events.recv().await {
                            Ok(e) => {
                                if tx.send(CoreEvent::Drive(e)).await.is_err() {
                                    return;
                                }
                            }
                            Err(broadcast::error::RecvError::Lagged(_)) => {}
                            Err(broadcast::error::RecvError::Closed) => {
                                let _ = tx.send(CoreEvent::Closed("drive events")).await;
                                return;
                            }
                        }
                    }
                }
            }),
            tokio::spawn({
                let tx = tx.clone();
                async move {
                    while io_state.changed().await.is_ok() {
                        let st = *io_state.borrow_and_update();
                        if tx.send(CoreEvent::IoState(st)).await.is_err() {
                            return;
                        }
                    }
                }
            }),
            tokio::spawn({
                let tx = tx.clone();
                async move {
                    while let Some(c) = commands.recv().await {
                        if tx.send(CoreEvent::Command(c)).await.is_err() {
                            return;
                        }
                    }
                    let _ = tx.send(CoreEvent::Closed("control API")).await;
                }
            }),
            tokio::spawn({
                let tx = tx.clone();
                async move {
                    loop {
                        tick.tick().await;
                        if tx.send(CoreEvent::Tick).await.is_err() {
                            return;
                        }
                    }
                }
            }),
        ]
    }

    /// A frame, with `behind` newer frames already waiting.
    fn handle_frame(&mut self, f: &Frame, behind: usize) {
        // The pipeline judges a frame at its own time (when the module answered); a frame the
        // core reaches late, or with newer ones waiting, is tracked but not decoupled, so the
        // core catches up at once (tracking is cheap, decoupling is not: β is recomputed as
        // the carriage moves).
        let late = behind > 0 || crate::util::clock::since(f.at) > LATE;
        for p in &mut self.procedures {
            p.on_frame(f);
        }
        let held = self.procedures.iter().any(|p| p.holds_follower());
        self.pipeline.tracker.hold(held);
        self.pipeline.handle_frame(f, late);
        self.pump();
    }

    /// Carry out what the pipeline asks, then show it to the procedures.
    fn pump(&mut self) {
        if let Some(state) = self.pipeline.measure.take_reference_change() {
            self.keep_reference(state);
        }
        while let Some(out) = self.pipeline.poll_output() {
            let still = self.procedures.iter().any(|p| p.holds_follower());
            match &out {
                Output::Follower(_) if still => {}
                Output::Follower(cmd) => self.follower_output(*cmd),
                Output::QuickStop => self.quick_stop(),
                Output::ReEnable => self.re_enable(),
                Output::Handover(r) if !self.procedures.iter().any(|p| p.claims(&out)) => {
                    let r = *r;
                    if let Err(e) = self.store.try_call(move |s| s.insert_handover(None, &r)) {
                        self.pipeline
                            .alarms
                            .raise("store", format!("handover not stored: {e}"));
                    }
                }
                _ => {}
            }
            self.for_each_procedure(|p, ctx| p.on_output(&out, ctx));
        }
    }

    /// Give the store the zero reference now in force (queued: the loop does not wait); one
    /// that cannot be queued raises the store alarm, and a restart would zero again.
    fn keep_reference(&mut self, state: Option<super::measure::ReferenceState>) {
        self.reference_offers += 1;
        let offer = self.reference_offers;
        let name = super::measure::decoupler_name(self.pipeline.measure.decoupler());
        let value = state.as_ref().and_then(|s| serde_json::to_value(s).ok());
        let now = crate::util::clock::unix_us();
        match self
            .store
            .try_call(move |s| s.record_reference(now, &name, value.as_ref()))
        {
            Ok(done) => self.later(done, move |core, r| {
                let r = r
                    .map_err(|e| e.to_string())
                    .and_then(|r| r.map_err(|e| e.to_string()));
                match r {
                    Ok(()) => {
                        // Kept: this offer or a later one covers any that failed. With none
                        // failed on record, the newest offer kept clears the alarm too: an
                        // older offer's failure answered after this one was made (so not
                        // offered again) left the store alarm up for five minutes in the
                        // storm once the disk had room again.
                        let newest = offer == core.reference_offers;
                        if core
                            .reference_unkept
                            .as_ref()
                            .map_or(newest, |u| u.offer <= offer)
                        {
                            let was_unkept = core.reference_unkept.take().is_some();
                            // The store takes writes again: its alarm goes (else it stayed
                            // raised until a capture was stored, past the storm's minute
                            // when the judge held every capture).
                            core.pipeline.alarms.clear("store");
                            if was_unkept {
                                tracing::info!("the zero reference is kept for a restart again");
                            }
                        }
                    }
                    Err(e) => core.reference_not_kept(offer, state, e),
                }
            }),
            Err(e) => self.reference_not_kept(offer, state, e.to_string()),
        }
    }

    /// The store did not keep offer `offer`: said, and offered again in a second unless a
    /// newer one was offered since.
    fn reference_not_kept(
        &mut self,
        offer: u64,
        state: Option<super::measure::ReferenceState>,
        e: String,
    ) {
        self.pipeline.alarms.raise(
            "store",
            format!(
                "the zero reference is not kept for a restart yet ({e}): offered again every 1 s"
            ),
        );
        if offer == self.reference_offers {
            self.reference_unkept = Some(Unkept {
                offer,
                state,
                again_at: crate::util::clock::now() + Duration::from_secs(1),
            });
        }
    }

    fn handle_core_event(&mut self, e: CoreEvent) {
        match e {
            CoreEvent::DriveStatus(st) => {
                let ready_before = self.pipeline.follower_state().is_some_and(|f| f.ready);
                self.pipeline
                    .handle_drive_status(&st, crate::util::clock::now());
                self.drive_status = *st;
                self.pump();
                if !ready_before && self.pipeline.follower_state().is_some_and(|f| f.ready) {
                    self.for_each_procedure(|p, ctx| p.on_drive_ready(ctx));
                    self.pump();
                }
            }
            CoreEvent::Drive(e) => {
                self.note_following(&e);
                self.pipeline.handle_drive_event(&e, &self.can_peer);
                self.for_each_procedure(|p, ctx| p.on_drive_event(&e, ctx));
                self.pump();
            }
            CoreEvent::IoState(st) => self.handle_io_state(&st),
            CoreEvent::Command(c) => self.handle_command(c),
            // The loop's own (the watchdog, leaving the loop).
            CoreEvent::Tick | CoreEvent::Closed(_) => {}
            CoreEvent::ReEnabled(r) => match r {
                Ok(()) => {
                    tracing::info!("follower drive enabled again: its heartbeat came back");
                    self.pipeline.alarms.clear("follower-disabled");
                }
                Err(e) => self.pipeline.alarms.raise(
                    "follower-disabled",
                    format!(
                        "the follower drive's heartbeat came back but it could not be enabled again ({e}): enable it on screen 2 or with axiscomp's follower enable request"
                    ),
                ),
            },
            CoreEvent::Then(then) => {
                then(self);
                self.pump();
            }
        }
    }

    /// The I/O link's state (on each change and at each tick): `io-link-down` from a failure
    /// until the module answers; `io-exception` once it has answered only with exceptions
    /// for [`EXCEPTIONS_PERSIST`].
    fn handle_io_state(&mut self, st: &LinkState) {
        let addr = self.acquisition.link().addr();
        let alarms = &mut self.pipeline.alarms;
        match st {
            LinkState::Up { .. } => {
                alarms.clear("io-link-down");
                alarms.clear("io-exception");
            }
            LinkState::Refusing { .. } => {
                alarms.clear("io-link-down");
                if let Some((x, d)) = st.refusing_for(crate::util::clock::now())
                    && d >= EXCEPTIONS_PERSIST
                {
                    alarms.raise(
                        "io-exception",
                        format!("PSD I/O module {addr} answers every read with {x}: check the I/O map's unit id, register kind and block against the module"),
                    );
                }
            }
            LinkState::Down { error, .. } => {
                alarms.clear("io-exception");
                alarms.raise(
                    "io-link-down",
                    format!("PSD I/O module {addr} unreachable: {error}; reconnecting"),
                );
            }
            _ => {}
        }
    }

    /// An operator's request: to the procedure that takes it (refused while another holds
    /// the machine, if it would start it), or the core's own.
    fn handle_command(&mut self, c: Command) {
        let name = serde_json::to_value(&c.request)
            .ok()
            .and_then(|v| v["cmd"].as_str().map(str::to_string))
            .unwrap_or_default();
        // What changes the machine or the store is said; what only reads (a console polling
        // the run's status twice a second) is not, or it buries the rest of the log.
        let audit = c.audit_entry();
        if audit.is_some() {
            tracing::info!(user = %c.peer.user, uid = c.peer.uid, request = %name, "control request");
        } else {
            tracing::debug!(user = %c.peer.user, uid = c.peer.uid, request = %name, "control request");
        }
        let audit = audit.map(|e| (e, self.store.clone(), self.store_alarm_tx.clone()));
        let reply = Reply::new(c.reply, audit);
        if let Err(e) = c.request.check() {
            return reply.send(Err(e));
        }
        let who = Who {
            user: c.peer.user.clone(),
            uid: c.peer.uid,
        };
        let Some(i) = self.procedures.iter().position(|p| p.takes(&c.request)) else {
            return self.own_request(c.request, &who, reply);
        };
        if self.procedures[i].starts(&c.request)
            && let Some(h) = self
                .procedures
                .iter()
                .enumerate()
                .find(|(k, p)| *k != i && p.holds_machine())
                .map(|(_, p)| p)
        {
            let what = match &c.request {
                Request::RunStart { .. } => "start the run",
                Request::FollowerMapStart(_) => "map the follower",
                Request::FollowerLevelStart(_) => "read the level's stations",
                Request::HexapodStart { .. } => "calibrate",
                _ => "start it",
            };
            return reply.send(Err(h.busy(what)));
        }
        self.with_procedure(i, |p, ctx| p.request(c.request, &who, reply, ctx));
        self.pump();
    }

    fn on_tick(&mut self) {
        let now = crate::util::clock::now();
        while let Ok(why) = self.store_alarm_rx.try_recv() {
            self.pipeline.alarms.raise("store", why);
        }
        self.for_each_procedure(|p, ctx| p.tick(ctx));
        self.pump();
        if let Some(u) = self.reference_unkept.take_if(|u| now >= u.again_at) {
            self.keep_reference(u.state);
        }
        if let Some(z) = self.pipeline.zero_ready(now)
            && let Some(reply) = self.zero_reply.take()
        {
            reply.send(match z {
                Some(z) => Ok(serde_json::json!({"zeroed": true, "offsets": z.to_user()})),
                None => Err("no valid frames to zero on: is the beam on all three PSDs?".into()),
            });
        }
        if !self.ready_sent {
            let io_up = self.acquisition.link().state().borrow().is_up();
            let drive_up = self.drive_status.state == Some(PowerState::OperationEnabled);
            if (io_up && drive_up)
                || crate::util::clock::since(self.started) > Duration::from_secs(30)
            {
                let status = format!(
                    "measuring: I/O module {}, follower drive {}",
                    if io_up { "up" } else { "DOWN" },
                    if drive_up { "enabled" } else { "NOT ready" }
                );
                notify::ready(&status);
                tracing::info!("{status}");
                self.ready_sent = true;
            }
        }
        let io = *self.acquisition.link().state().borrow();
        self.handle_io_state(&io);
        let st = &self.drive_status;
        if st.nmt.is_some() || st.heartbeat_ok {
            self.pipeline.alarms.clear("drive-absent");
        } else if now.saturating_duration_since(self.started) >= DRIVE_ABSENT_AFTER {
            self.pipeline.alarms.raise(
                "drive-absent",
                format!(
                    "no heartbeat or boot-up from the follower drive (node {}, {}) since the service started: check its power, the CAN wiring and [follower] node_id",
                    self.node_id, self.can_peer
                ),
            );
        }
        self.tpdo_rate.update(now, self.drive_status.tpdo_count);
        let snap = self.build_snapshot();
        self.snapshot.send_replace(snap);
    }
}

/// The service's procedures: one line each.
fn procedures(
    p: &Prepared,
    resume: Option<super::procedure::run::Resume>,
) -> Vec<Box<dyn Procedure>> {
    use super::procedure::{align, follower_level, follower_map, hexapod, run};
    let s = &p.settings;
    vec![
        Box::new(run::MeasurementRun::new(
            run::RunConfig {
                capture: s.capture,
                rate_hz: s.io.acquire.rate_hz,
                dialect: s.cnc.dialect,
                cnc: s.cnc.mode.clone(),
                state_dir: s.service.state_dir.clone(),
            },
            resume,
        )),
        Box::new(follower_map::FollowerMapping::new(
            follower_map::MappingConfig {
                cnc: s.cnc.mode.clone(),
                dialect: s.cnc.dialect,
                state_dir: s.service.state_dir.clone(),
                frame_rate_hz: s.io.acquire.rate_hz,
                follower_velocity_mm_s: s.follower.drive.profile.velocity_mm_s,
                follower_accel_mm_s2: s.follower.drive.profile.accel_mm_s2,
                sync: s.follower.drive.sync_period,
            },
        )),
        Box::new(follower_level::FollowerLevel::new(
            follower_level::LevelConfig {
                source: s.follower.level.clone(),
                level_sd_rad: s.follower.level_sd_rad,
                cnc: s.cnc.mode.clone(),
                dialect: s.cnc.dialect,
                state_dir: s.service.state_dir.clone(),
                frame_rate_hz: s.io.acquire.rate_hz,
                live_window: s.head.live_window,
                sync: s.follower.drive.sync_period,
            },
        )),
        Box::new(hexapod::HexapodRuns::new(
            s.hexapod.clone(),
            p.layout.clone(),
            &s.service.state_dir,
        )),
        Box::new(align::Alignment::new(
            crate::service::align::AlignState::new(s.align.clone()),
        )),
    ]
}
