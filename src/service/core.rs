//! The core task: the one place that owns the tracking machine and the live measurement. It
//! takes frames from the acquisition, follower status and events from the drive, requests from
//! the control socket, and publishes the `Snapshot`. Drive commands go out as their own small
//! tasks, so the loop never waits on the bus.

use super::Prepared;
use super::api::snapshot::{
    FollowerView, LinkView, LinksView, LiveView, PsdView, RunView, Snapshot, TrackingView,
};
use super::api::{FollowerAction, Request};
use super::control::Command;
use super::notify;
use super::pipeline::{Output, Pipeline, now_us};
use super::results;
use super::shutdown::Shutdown;
use crate::acquire::{Acquisition, Frame};
use crate::canopen::{DriveError, DriveHandle, DriveStatus, Event, PowerState};
use crate::config::CncMode;
use crate::modbus::{Exception, LinkState};
use crate::optics::layout::{Aperture, Kind};
use crate::run::program::{CaptureMode, generate_settled, makeup_steps, remaining_steps};
use crate::run::{CaptureSettings, Dialect, Plan, RunMachine, TargetKey};
use crate::store::{NewRun, RunId, RunState, Store};
use crate::track::FollowerCommand;
use std::collections::BTreeSet;
use std::path::PathBuf;
use std::time::{Duration, Instant};
use tokio::sync::{broadcast, mpsc, oneshot, watch};
use tokio::task::JoinHandle;

/// A frame older than this when the core gets to it is not decoupled (it is still tracked).
const LATE: Duration = Duration::from_millis(100);

/// Exception replies for this long raise the `io-exception` alarm.
const EXCEPTIONS_PERSIST: Duration = Duration::from_secs(1);

/// No sign of the follower drive (no heartbeat, no boot-up) this long after start raises
/// the `drive-absent` alarm.
const DRIVE_ABSENT_AFTER: Duration = Duration::from_secs(5);

/// The acceleration the run's ETA assumes (mm/s²): a machine tool's axis at measuring feed
/// is at speed within a millimetre or two, so the dwells and the feed set the time.
const ETA_ACCEL_MM_S2: f64 = 500.0;

/// The I/O link as the snapshot shows it: the state's name; the detail says why it is not up,
/// or names the last exception of the last minute while up.
fn link_view(
    state: &LinkState,
    peer: String,
    last_exception: Option<(Exception, Instant)>,
    now: Instant,
) -> LinkView {
    let detail = match state {
        LinkState::Connecting { attempt } => Some(format!("attempt {attempt}")),
        LinkState::Up { .. } => last_exception
            .map(|(x, at)| (x, now.saturating_duration_since(at)))
            .filter(|(_, ago)| *ago <= Duration::from_secs(60))
            .map(|(x, ago)| format!("last {x} {:.1} s ago", ago.as_secs_f64())),
        LinkState::Closed => None,
        s => Some(s.to_string()),
    };
    LinkView {
        state: state.name().to_string(),
        peer,
        detail,
        ..LinkView::default()
    }
}

/// The CAN link as the snapshot shows it: up while the drive's heartbeat comes; the detail
/// names the drive's NMT state and the SYNC period in use (the quiet one at rest, see
/// `DriveConfig::quiet_sync_period`); the rate is the TPDOs the drive answers with per second.
fn can_view(st: &DriveStatus, peer: String, sync: (Duration, Duration), tpdo_hz: f64) -> LinkView {
    let mut detail = Vec::new();
    if let Some(n) = st.nmt {
        detail.push(format!("NMT {}", crate::canopen::nmt::state_name(n)));
    }
    if st.sync_running {
        detail.push(if st.sync_quiet {
            format!("SYNC {} ms (quiet at rest)", sync.1.as_millis())
        } else {
            format!("SYNC {} ms", sync.0.as_millis())
        });
    }
    LinkView {
        state: if st.heartbeat_ok {
            "up".into()
        } else {
            "no heartbeat".into()
        },
        peer,
        detail: (!detail.is_empty()).then(|| detail.join(", ")),
        rate_hz: tpdo_hz,
        ..LinkView::default()
    }
}

/// Events per second from a running count, over spans of at least `span` (the last complete
/// span; 0 before the first ends). Sans-I/O: time is an argument.
#[derive(Clone, Copy, Debug)]
struct CountRate {
    span: Duration,
    since: Option<(Instant, u64)>,
    rate_hz: f64,
}

impl CountRate {
    fn new(span: Duration) -> Self {
        CountRate {
            span,
            since: None,
            rate_hz: 0.0,
        }
    }

    fn update(&mut self, now: Instant, count: u64) -> f64 {
        match self.since {
            Some((t0, c0)) if now.saturating_duration_since(t0) >= self.span => {
                let dt = now.saturating_duration_since(t0).as_secs_f64();
                self.rate_hz = count.saturating_sub(c0) as f64 / dt;
                self.since = Some((now, count));
            }
            Some((_, c0)) if count < c0 => self.since = Some((now, count)),
            Some(_) => {}
            None => self.since = Some((now, count)),
        }
        self.rate_hz
    }
}

fn power_name(s: Option<PowerState>) -> String {
    s.map(|p| p.label().to_string())
        .unwrap_or_else(|| "unknown".into())
}

pub(super) struct Core {
    pipeline: Pipeline,
    align: super::align::AlignState,
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
    zero_reply: Option<oneshot::Sender<Result<serde_json::Value, String>>>,
    zero_window: Duration,
    ready_sent: bool,
    started: Instant,
    /// The follower target the tracker wants (the follower task sends the latest).
    follow: watch::Sender<Option<f64>>,
    /// The drive refused mode 8: follow targets go as profile moves.
    csp_refused: bool,
    /// Following ended on an error: re-arm it with a profile move.
    follow_rearm: bool,
    /// A run to resume once the follower is ready.
    pending_resume: Option<PendingResume>,
    store: Store,
    follower_map: Option<super::api::FollowerMapView>,
    run: Option<ActiveRun>,
    cnc: CncMode,
    dialect: Dialect,
    capture: CaptureSettings,
    /// The acquisition's frame rate (Hz; 0: as fast as the module answers).
    rate_hz: f64,
    state_dir: PathBuf,
    /// Results of the core's own asynchronous work (talking to the CNC).
    events_tx: mpsc::UnboundedSender<CoreEvent>,
    events_rx: Option<mpsc::UnboundedReceiver<CoreEvent>>,
    last_cnc_poll: Instant,
    calibrations: super::calibration::Calibrations,
    hexapod: super::hexapod_run::HexapodRuns,
    follower_mapping: super::follower_map::FollowerMapping,
    follower_level: super::follower_level::FollowerLevel,
}

/// A make-up pass is sent for a missing capture at most this many times before the run fails.
const MAKEUP_TRIES: u32 = 3;

/// A run found unfinished in the store, resumed once the follower is ready.
#[derive(Debug)]
struct PendingResume {
    id: RunId,
    plan: Plan,
    /// The dialect the run was started with (its programs go on in it).
    dialect: Dialect,
    /// The captures stored.
    done: BTreeSet<TargetKey>,
}

/// A run being measured.
#[derive(Debug)]
struct ActiveRun {
    id: RunId,
    plan: Plan,
    dialect: Dialect,
    /// Where the last program went.
    program: String,
    /// Programs sent to the twin's CNC for this run (the twin counts programs it started).
    programs_sent: u32,
    /// The twin's program count when this run's latest program was sent.
    twin_programs_at_send: Option<u32>,
    /// Make-up programs sent so far for each capture.
    makeup_for: std::collections::BTreeMap<TargetKey, u32>,
    /// The twin's program was stopped because the run paused: once the spots are back, the
    /// rest of the cycle is sent (from the next missing capture), not a make-up pass.
    stopped_by_pause: bool,
}

/// The outcome of asynchronous work the core started.
#[derive(Debug)]
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
    /// A program was (or was not) delivered to the twin; the twin's program count after it.
    Delivered(Result<u32, String>),
    /// The twin CNC's state.
    Cnc(serde_json::Value),
    /// The follower drive was (or could not be) enabled again after its heartbeat came back.
    ReEnabled(Result<(), String>),
    /// A calibration fit ended; the reply owed to its request.
    Fitted(
        oneshot::Sender<Result<serde_json::Value, String>>,
        Box<Result<super::calibration::Pending, super::calibration::CalibrationError>>,
    ),
}

/// A task forwarding each new value of `rx` into the core's channel as `event(value)`; when
/// the sender is gone, `closed` (if the core cannot go on without it).
fn forward_watch<T: Clone + Send + Sync + 'static>(
    tx: mpsc::UnboundedSender<CoreEvent>,
    mut rx: watch::Receiver<T>,
    event: fn(T) -> CoreEvent,
    closed: Option<&'static str>,
) -> JoinHandle<()> {
    tokio::spawn(async move {
        while rx.changed().await.is_ok() {
            let v = rx.borrow_and_update().clone();
            if tx.send(event(v)).is_err() {
                return;
            }
        }
        if let Some(what) = closed {
            let _ = tx.send(CoreEvent::Closed(what));
        }
    })
}

/// Send one JSON request to the twin's control socket and read its reply.
pub(super) async fn twin_request(
    addr: std::net::SocketAddr,
    req: serde_json::Value,
) -> Result<serde_json::Value, String> {
    use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
    let s = tokio::time::timeout(Duration::from_secs(5), tokio::net::TcpStream::connect(addr))
        .await
        .map_err(|_| format!("twin CNC {addr}: no connection within 5 s"))?
        .map_err(|e| format!("twin CNC {addr}: {e}"))?;
    let (rd, mut wr) = s.into_split();
    let mut line = req.to_string();
    line.push('\n');
    wr.write_all(line.as_bytes())
        .await
        .map_err(|e| format!("twin CNC {addr}: {e}"))?;
    let mut lines = BufReader::new(rd).lines();
    let reply = tokio::time::timeout(Duration::from_secs(5), lines.next_line())
        .await
        .map_err(|_| format!("twin CNC {addr}: no reply within 5 s"))?
        .map_err(|e| format!("twin CNC {addr}: {e}"))?
        .ok_or_else(|| format!("twin CNC {addr}: closed"))?;
    let v: serde_json::Value =
        serde_json::from_str(&reply).map_err(|e| format!("twin CNC {addr}: {e}"))?;
    if v.get("ok").and_then(|o| o.as_bool()) == Some(true) {
        Ok(v)
    } else {
        Err(format!(
            "twin CNC {addr}: {}",
            v.get("error").and_then(|e| e.as_str()).unwrap_or("refused")
        ))
    }
}

impl Core {
    pub(super) fn new(
        p: &Prepared,
        acquisition: Acquisition,
        drive: DriveHandle,
        can_peer: String,
        snapshot: watch::Sender<Snapshot>,
        store: Store,
    ) -> Core {
        let (events_tx, events_rx) = mpsc::unbounded_channel();
        let s = &p.settings;
        let (follower_map, map) = super::follower::in_use(&store);
        let mut pipeline = Pipeline::new(s.tracking, p.decoupler.clone(), s.head.live_window);
        pipeline.tracker.set_map(map);
        let mut half_size_um = [0.0; 3];
        for (k, path) in p.layout.paths.iter().enumerate() {
            let el = &p.layout.elements[path.psd];
            if el.kind == Kind::Psd {
                half_size_um[k] = match el.aperture {
                    Aperture::Square { half } | Aperture::Circle { radius: half } => half * 1e3,
                };
            }
        }
        Core {
            pipeline,
            align: super::align::AlignState::new(s.align.clone()),
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
            zero_window: s.head.zero_window,
            ready_sent: false,
            started: crate::util::clock::now(),
            follow: watch::channel(None).0,
            csp_refused: false,
            follow_rearm: false,
            pending_resume: None,
            store,
            follower_map,
            run: None,
            cnc: s.cnc.mode.clone(),
            dialect: s.cnc.dialect,
            capture: s.capture,
            rate_hz: s.io.acquire.rate_hz,
            state_dir: s.service.state_dir.clone(),
            events_tx,
            events_rx: Some(events_rx),
            last_cnc_poll: crate::util::clock::now(),
            calibrations: super::calibration::Calibrations::new(
                p.layout.clone(),
                p.calibration.as_ref(),
                &s.head
                    .calibration
                    .as_ref()
                    .map(|f| f.display().to_string())
                    .unwrap_or_default(),
            ),
            hexapod: super::hexapod_run::HexapodRuns::new(
                s.hexapod.clone(),
                p.layout.clone(),
                &s.service.state_dir,
            ),
            follower_mapping: super::follower_map::FollowerMapping::new(
                super::follower_map::MappingConfig {
                    cnc: s.cnc.mode.clone(),
                    dialect: s.cnc.dialect,
                    state_dir: s.service.state_dir.clone(),
                    frame_rate_hz: s.io.acquire.rate_hz,
                    follower_velocity_mm_s: s.follower.drive.profile.velocity_mm_s,
                    follower_accel_mm_s2: s.follower.drive.profile.accel_mm_s2,
                    sync: s.follower.drive.sync_period,
                },
            ),
            follower_level: super::follower_level::FollowerLevel::new(
                super::follower_level::LevelConfig {
                    source: s.follower.level.clone(),
                    level_sd_rad: s.follower.level_sd_rad,
                    cnc: s.cnc.mode.clone(),
                    dialect: s.cnc.dialect,
                    state_dir: s.service.state_dir.clone(),
                    frame_rate_hz: s.io.acquire.rate_hz,
                    live_window: s.head.live_window,
                    sync: s.follower.drive.sync_period,
                },
            ),
        }
    }

    /// The follower mapping with what it works on (`service::follower_map`).
    fn with_mapping<R>(
        &mut self,
        f: impl FnOnce(&mut super::follower_map::FollowerMapping, super::follower_map::Ctx<'_>) -> R,
    ) -> R {
        let ctx = super::follower_map::Ctx {
            pipeline: &mut self.pipeline,
            store: &mut self.store,
            shown: &mut self.follower_map,
            zero_window: self.zero_window,
            frames_per_s: self.acquisition.stats().frames_per_s,
        };
        f(&mut self.follower_mapping, ctx)
    }

    /// The follower's level stations with what they work on (`service::follower_level`).
    fn with_level<R>(
        &mut self,
        f: impl FnOnce(&mut super::follower_level::FollowerLevel, super::follower_map::Ctx<'_>) -> R,
    ) -> R {
        let ctx = super::follower_map::Ctx {
            pipeline: &mut self.pipeline,
            store: &mut self.store,
            shown: &mut self.follower_map,
            zero_window: self.zero_window,
            frames_per_s: self.acquisition.stats().frames_per_s,
        };
        f(&mut self.follower_level, ctx)
    }

    pub(super) async fn run(
        mut self,
        commands: mpsc::Receiver<Command>,
        shutdown: Shutdown,
    ) -> Result<(), super::ServiceError> {
        let mut frames = self.acquisition.subscribe();
        let bring_up = tokio::spawn(bring_up(
            self.drive.clone(),
            self.home_on_start,
            shutdown.clone(),
        ));
        let follower = tokio::spawn(follow(
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
        self.resume_run();
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
        let status = self.drive.watch_status();
        let mut events = self.drive.events();
        let io_state = self.acquisition.link().state();
        let mut tick = tokio::time::interval(self.snapshot_period.min(Duration::from_millis(100)));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        let forward = |tx: &mpsc::UnboundedSender<CoreEvent>, e| tx.send(e).is_ok();
        vec![
            tokio::spawn({
                let tx = tx.clone();
                async move {
                    shutdown.recv().await;
                    forward(&tx, CoreEvent::Closed("shutdown"));
                }
            }),
            forward_watch(
                tx.clone(),
                status,
                |st| CoreEvent::DriveStatus(Box::new(st)),
                Some("drive status"),
            ),
            tokio::spawn({
                let tx = tx.clone();
                async move {
                    loop {
                        match events.recv().await {
                            Ok(e) => {
                                if !forward(&tx, CoreEvent::Drive(e)) {
                                    return;
                                }
                            }
                            Err(broadcast::error::RecvError::Lagged(_)) => {}
                            Err(broadcast::error::RecvError::Closed) => {
                                forward(&tx, CoreEvent::Closed("drive events"));
                                return;
                            }
                        }
                    }
                }
            }),
            forward_watch(tx.clone(), io_state, CoreEvent::IoState, None),
            tokio::spawn({
                let tx = tx.clone();
                async move {
                    while let Some(c) = commands.recv().await {
                        if !forward(&tx, CoreEvent::Command(c)) {
                            return;
                        }
                    }
                    forward(&tx, CoreEvent::Closed("control API"));
                }
            }),
            tokio::spawn({
                let tx = tx.clone();
                async move {
                    loop {
                        tick.tick().await;
                        if !forward(&tx, CoreEvent::Tick) {
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
        let late = behind > 0 || crate::util::clock::now().saturating_duration_since(f.at) > LATE;
        self.align.handle_frame(f);
        self.pipeline.handle_frame(f, late);
        self.pump();
    }

    /// Carry out what the pipeline asks.
    fn pump(&mut self) {
        while let Some(out) = self.pipeline.poll_output() {
            match out {
                // Under a hexapod calibration the follower holds still (the poses' PSD2
                // readings are taken with it where it is).
                Output::Follower(_) if self.hexapod.active() => {}
                // Only the latest target matters: the follower task skips superseded ones.
                Output::Follower(FollowerCommand::MoveTo(mm)) => {
                    self.follow.send_replace(Some(mm));
                }
                Output::Follower(FollowerCommand::Follow {
                    target_mm,
                    velocity_mm_s,
                    at,
                }) => {
                    if self.csp_refused || std::mem::take(&mut self.follow_rearm) {
                        self.follow.send_replace(Some(target_mm));
                        continue;
                    }
                    match self.drive.follow_moving(target_mm, velocity_mm_s, at) {
                        Ok(()) => {}
                        // Following ended (a stop, a fault, a drive refusing mode 8): go on
                        // in profile position; the move re-arms following.
                        Err(DriveError::FollowDisarmed) => {
                            self.follow.send_replace(Some(target_mm));
                        }
                        Err(e) => tracing::warn!("follower to {target_mm:.4} mm: {e}"),
                    }
                }
                Output::QuickStop => {
                    let drive = self.drive.clone();
                    tokio::spawn(async move {
                        let _ = drive.quick_stop().await;
                    });
                }
                Output::ReEnable => {
                    let drive = self.drive.clone();
                    let tx = self.events_tx.clone();
                    tokio::spawn(async move {
                        // Quick stop leaves the drive in switch on disabled; a drive that
                        // faulted meanwhile needs its fault reset first.
                        let r = match drive.enable().await {
                            Ok(()) => Ok(()),
                            Err(_) => match drive.fault_reset().await {
                                Ok(()) => drive.enable().await,
                                Err(e) => Err(e),
                            },
                        };
                        let _ = tx.send(CoreEvent::ReEnabled(r.map_err(|e| e.to_string())));
                    });
                }
                Output::Handover(r) => {
                    self.follower_mapping.handle_record(&r, &mut self.pipeline);
                    let run = self.run.as_ref().map(|a| a.id);
                    if let Err(e) = self.store.insert_handover(run, &r) {
                        self.pipeline
                            .alarms
                            .raise("store", format!("handover not stored: {e}"));
                    }
                }
                Output::Captured(c) => {
                    let Some(run) = self.run.as_ref() else {
                        continue;
                    };
                    match self.store.insert_capture(run.id, &c) {
                        Ok(true) => {
                            tracing::info!(
                                run = run.id.0,
                                pass = c.run,
                                target = c.target_index,
                                direction = c.direction.sign(),
                                "captured"
                            );
                            // The store takes writes again (a full disk freed, a lock gone).
                            self.pipeline.alarms.clear("store");
                        }
                        Ok(false) => {
                            tracing::info!("capture {} was already stored", TargetKey::of(&c));
                            self.pipeline.alarms.clear("store");
                        }
                        Err(e) => self.pipeline.alarms.raise(
                            "store",
                            format!("capture not stored: {e}; the run will take it again"),
                        ),
                    }
                }
                Output::Acknowledge(_) => {}
                // The pipeline keeps the alarm. With the beam off the fixed PSDs the twin's
                // CNC stops at its next stop, and the rest of the cycle follows once the beam
                // is back. PSD2 alone (the follower behind) waits for the carriage's pass. A CNC
                // the service does not drive goes on: what it missed is the make-up pass's.
                Output::RunPaused(why) => {
                    tracing::warn!("{why}");
                    if self.pipeline.beam_lost() {
                        self.stop_twin_program();
                    }
                }
                Output::RunResumed => tracing::info!("every spot is back: the run goes on"),
                Output::RunFinished => self.end_run(RunState::Finished, "all captures taken"),
                Output::RunFailed(why) => self.end_run(RunState::Failed, &why),
            }
        }
    }

    /// A drive that refuses cyclic synchronous position (an SDO abort on entering it) is
    /// followed in profile position until it reboots.
    fn note_following(&mut self, e: &Event) {
        match e {
            Event::FollowingEnded(Err(DriveError::Sdo(err))) => {
                if !self.csp_refused {
                    tracing::warn!(
                        "the follower drive refused cyclic synchronous position ({err}): \
                         following in profile position, which lags a moving carriage"
                    );
                }
                self.csp_refused = true;
            }
            // Following ended on an error (a following error, a stop): the next target
            // goes as a profile move, which re-arms following.
            Event::FollowingEnded(Err(_)) => self.follow_rearm = true,
            Event::BootUp { .. } => self.csp_refused = false,
            _ => {}
        }
    }

    fn end_run(&mut self, state: RunState, why: &str) {
        let Some(run) = self.run.take() else {
            return;
        };
        if let Err(e) = self.store.set_run_state(run.id, state) {
            self.pipeline
                .alarms
                .raise("store", format!("run {} state not stored: {e}", run.id.0));
        }
        if state == RunState::Failed {
            let _ = self.store.set_run_notes(run.id, why);
            self.pipeline
                .alarms
                .raise("run-failed", format!("run {} failed: {why}", run.id.0));
        } else {
            self.pipeline.alarms.clear("run-failed");
        }
        tracing::info!(run = run.id.0, ?state, "run ended: {why}");
    }

    /// Resume a run the store says is still running (the service stopped or crashed in it):
    /// what is stored is kept, and the CNC gets the rest of the cycle.
    fn resume_run(&mut self) {
        let runs = match self.store.runs_in_state(RunState::Running) {
            Ok(r) => r,
            Err(e) => {
                self.pipeline
                    .alarms
                    .raise("store", format!("cannot look for runs to resume: {e}"));
                return;
            }
        };
        let Some(rec) = runs.into_iter().max_by_key(|r| r.id.0) else {
            return;
        };
        let plan: Result<Plan, String> =
            serde_json::from_value(rec.plan.clone()).map_err(|e| e.to_string());
        let done = self.store.completed_keys(rec.id);
        // The run's programs go on in the dialect it was started with (the configuration
        // snapshot names it), not in the configured default.
        let dialect = rec.config["dialect"]
            .as_str()
            .and_then(Dialect::parse)
            .unwrap_or(self.dialect);
        match (plan, done) {
            (Ok(plan), Ok(done)) => {
                tracing::info!(
                    run = rec.id.0,
                    captured = done.len(),
                    ?dialect,
                    "resuming run once the follower is ready"
                );
                self.pending_resume = Some(PendingResume {
                    id: rec.id,
                    plan,
                    dialect,
                    done,
                });
            }
            (Err(e), _) => self.end_run_record(rec.id, &format!("its plan does not load: {e}")),
            (_, Err(e)) => self.end_run_record(rec.id, &format!("its captures do not load: {e}")),
        }
    }

    fn end_run_record(&mut self, id: RunId, why: &str) {
        let _ = self.store.set_run_state(id, RunState::Failed);
        let _ = self.store.set_run_notes(id, why);
        self.pipeline
            .alarms
            .raise("run-failed", format!("run {} cannot resume: {why}", id.0));
    }

    /// Resume the pending run once the follower is ready: the CNC first brings the carriage
    /// back to the follower (which held its position while the service was down), where
    /// PSD2 finds the spot again, then goes on with the rest of the cycle.
    fn try_resume(&mut self) {
        if self.pending_resume.is_none() {
            return;
        }
        let Some(fs) = self.pipeline.follower_state().filter(|f| f.ready) else {
            return;
        };
        let Some(PendingResume {
            id,
            plan,
            dialect,
            done,
        }) = self.pending_resume.take()
        else {
            return;
        };
        let mut steps = remaining_steps(&plan, &done).unwrap_or_default();
        if steps.is_empty() {
            self.end_run_record(id, "nothing left to capture, yet the run was not finished");
            return;
        }
        steps.insert(
            0,
            crate::run::Step {
                position_mm: fs.position_mm,
                target: None,
            },
        );
        let machine = RunMachine::new(plan.clone(), self.capture, false, done);
        self.start_active(id, plan, dialect);
        // Number the programs on from those the run already has: none is overwritten.
        let written = self.programs_written(id);
        if let Some(run) = self.run.as_mut() {
            run.programs_sent = written;
        }
        self.pipeline.resume_run(machine);
        self.pump();
        // The carriage comes back from wherever the CNC left it: hold the approach points
        // (see `generate_settled`).
        let hold = self.run.as_ref().map(|r| r.plan.spec.dwell_s);
        self.deliver_with(&steps, "resumed", None, hold);
    }

    fn start_active(&mut self, id: RunId, plan: Plan, dialect: Dialect) {
        self.run = Some(ActiveRun {
            id,
            plan,
            dialect,
            program: String::new(),
            programs_sent: 0,
            twin_programs_at_send: None,
            makeup_for: Default::default(),
            stopped_by_pause: false,
        });
    }

    /// The highest program number written for run `id` (0: none).
    fn programs_written(&self, id: RunId) -> u32 {
        let dir = self.state_dir.join("runs").join(id.0.to_string());
        std::fs::read_dir(dir)
            .map(|entries| {
                entries
                    .filter_map(|e| {
                        let name = e.ok()?.file_name().into_string().ok()?;
                        name.strip_prefix("program-")?
                            .split('.')
                            .next()?
                            .parse::<u32>()
                            .ok()
                    })
                    .max()
                    .unwrap_or(0)
            })
            .unwrap_or(0)
    }

    /// Start measuring `id` with `done` captures already stored, and send the CNC what is
    /// left of the cycle.
    fn begin_run(
        &mut self,
        id: RunId,
        plan: Plan,
        dialect: Dialect,
        done: BTreeSet<TargetKey>,
        note: &str,
    ) {
        let steps = remaining_steps(&plan, &done).unwrap_or_default();
        let machine = RunMachine::new(plan.clone(), self.capture, false, done);
        self.start_active(id, plan, dialect);
        self.pipeline.start_run(machine);
        self.pump();
        if !steps.is_empty() {
            self.deliver(&steps, note);
        }
    }

    /// Write or send a program for `steps` of the active run.
    fn deliver(&mut self, steps: &[crate::run::Step], note: &str) {
        self.deliver_with(steps, note, None, None);
    }

    /// Write or send a program for `steps` of the active run, dwelling `dwell_s` at each
    /// target (None: the plan's dwell) and `hold_s` at each approach point (None: not).
    fn deliver_with(
        &mut self,
        steps: &[crate::run::Step],
        note: &str,
        dwell_s: Option<f64>,
        hold_s: Option<f64>,
    ) {
        let Some(run) = self.run.as_mut() else {
            return;
        };
        let mut plan = run.plan.clone();
        if let Some(d) = dwell_s {
            plan.spec.dwell_s = d;
        }
        let text = match generate_settled(
            &plan,
            steps,
            note,
            run.dialect,
            CaptureMode::Stability,
            hold_s.unwrap_or(0.0),
        ) {
            Ok(t) => t,
            Err(e) => {
                self.pipeline
                    .alarms
                    .raise("run", format!("no program: {e}"));
                return;
            }
        };
        run.programs_sent += 1;
        let dir = self.state_dir.join("runs").join(run.id.0.to_string());
        let file = dir.join(format!(
            "program-{}.{}",
            run.programs_sent,
            run.dialect.extension()
        ));
        if let Err(e) = std::fs::create_dir_all(&dir).and_then(|()| std::fs::write(&file, &text)) {
            self.pipeline
                .alarms
                .raise("run", format!("cannot write {}: {e}", file.display()));
        }
        run.program = file.display().to_string();
        if let CncMode::Twin(addr) = self.cnc {
            let dialect = match run.dialect {
                Dialect::LinuxCnc => "linuxcnc",
                _ => "iso",
            };
            let req = serde_json::json!({"cmd": "program", "dialect": dialect, "axis": run.plan.spec.axis, "text": text});
            let tx = self.events_tx.clone();
            tokio::spawn(async move {
                let r = match twin_request(addr, req).await {
                    Ok(_) => twin_request(addr, serde_json::json!({"cmd": "cnc"}))
                        .await
                        .map(|v| v["cnc"]["programs"].as_u64().unwrap_or(0) as u32),
                    Err(e) => Err(e),
                };
                let _ = tx.send(CoreEvent::Delivered(r));
            });
        }
    }

    fn handle_core_event(&mut self, e: CoreEvent) {
        match e {
            CoreEvent::DriveStatus(st) => {
                self.pipeline.handle_drive_status(&st, crate::util::clock::now());
                self.try_resume();
                self.drive_status = *st;
                self.pump();
            }
            CoreEvent::Drive(e) => {
                self.note_following(&e);
                self.pipeline.handle_drive_event(&e, &self.can_peer);
                self.pump();
            }
            CoreEvent::IoState(st) => self.handle_io_state(&st),
            CoreEvent::Command(c) => self.handle_command(c),
            // The loop's own (the watchdog, leaving the loop).
            CoreEvent::Tick | CoreEvent::Closed(_) => {}
            CoreEvent::Delivered(Ok(n)) => {
                if let Some(run) = self.run.as_mut() {
                    run.twin_programs_at_send = Some(n);
                }
                self.pipeline.alarms.clear("cnc");
            }
            CoreEvent::Delivered(Err(e)) => self.pipeline.alarms.raise("cnc", e),
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
            CoreEvent::Fitted(reply, r) => {
                let measure = &self.pipeline.measure;
                let v = self.calibrations.fitted(*r, |d| measure.read_with(d));
                Self::reply(reply, v)
            }
            CoreEvent::Cnc(v) => {
                let done = v["cnc"]["done"].as_bool().unwrap_or(false);
                let programs = v["cnc"]["programs"].as_u64().unwrap_or(0) as u32;
                let Some(run) = self.run.as_ref() else {
                    return;
                };
                // The program this run sent has ended and captures are still missing.
                if !done || run.twin_programs_at_send != Some(programs) {
                    return;
                }
                let missing: Vec<TargetKey> = self.pipeline.run_missing().unwrap_or_default();
                if missing.is_empty() || self.pipeline.beam_lost() {
                    return;
                }
                if run.stopped_by_pause {
                    // The beam is back on the fixed PSDs: the rest of the cycle, from the
                    // carriage's stop, with the approach points held as after a restart. Where
                    // PSD2 is still without its spot (the follower stayed behind while the beam
                    // was off), the carriage's pass brings it back and the run resumes then.
                    let done: BTreeSet<TargetKey> = run
                        .plan
                        .steps()
                        .iter()
                        .filter_map(|s| s.target)
                        .filter(|k| !missing.contains(k))
                        .collect();
                    let steps = remaining_steps(&run.plan, &done).unwrap_or_default();
                    let hold = run.plan.spec.dwell_s;
                    if let Some(run) = self.run.as_mut() {
                        run.stopped_by_pause = false;
                        run.twin_programs_at_send = None;
                    }
                    tracing::info!(
                        missing = missing.len(),
                        "the spots are back: the rest of the cycle goes to the CNC"
                    );
                    self.deliver_with(&steps, "resumed", None, Some(hold));
                    return;
                }
                let tries = |k: &TargetKey| run.makeup_for.get(k).copied().unwrap_or(0);
                if missing.iter().all(|k| tries(k) >= MAKEUP_TRIES) {
                    let why = format!(
                        "{} captures still missing after {MAKEUP_TRIES} make-up passes",
                        missing.len()
                    );
                    self.pipeline.abort_run();
                    self.end_run(RunState::Failed, &why);
                    return;
                }
                let pass = missing.iter().map(tries).min().unwrap_or(0) + 1;
                // Each target approached from the plan's overrun (within the travel the plan
                // already asks of the machine; more than the target tolerance by its check),
                // dwelling twice as long as the cycle: what missed the capture the first time
                // was a dwell too short for the follower to settle.
                let steps = makeup_steps(&run.plan, &missing, run.plan.spec.overrun_mm);
                let (dwell, hold) = (2.0 * run.plan.spec.dwell_s, run.plan.spec.dwell_s);
                if let Some(run) = self.run.as_mut() {
                    for k in &missing {
                        *run.makeup_for.entry(*k).or_insert(0) += 1;
                    }
                    run.twin_programs_at_send = None;
                }
                tracing::info!(
                    missing = missing.len(),
                    pass,
                    "the program ended with captures missing: make-up pass"
                );
                self.deliver_with(&steps, &format!("make-up {pass}"), Some(dwell), Some(hold));
            }
        }
    }

    /// A run paused: stop the twin's program at its next stop (the carriage goes no further
    /// than the target it is moving to; nothing is captured while paused).
    fn stop_twin_program(&mut self) {
        let (Some(run), CncMode::Twin(addr)) = (self.run.as_mut(), &self.cnc) else {
            return;
        };
        let addr = *addr;
        run.stopped_by_pause = true;
        tokio::spawn(async move {
            if let Err(e) =
                twin_request(addr, serde_json::json!({"cmd": "cnc", "stop": true})).await
            {
                tracing::warn!("the twin's CNC was not stopped: {e}");
            }
        });
    }

    /// Start a run on request.
    fn start_run_request(
        &mut self,
        spec: crate::run::PlanSpec,
        dialect: Option<String>,
        notes: Option<String>,
        who: &str,
    ) -> Result<serde_json::Value, String> {
        if let Some(r) = &self.run {
            return Err(format!("run {} is under way: abort it first", r.id.0));
        }
        if self.hexapod.active() {
            return Err("a hexapod calibration run is under way (it moves the head): stop it with hexapod_stop or let it finish, then start the run".into());
        }
        if let Some(why) = self.follower_mapping.refusal("start the run") {
            return Err(why);
        }
        if let Some(why) = self.follower_level.refusal("start the run") {
            return Err(why);
        }
        let plan = Plan::new(spec).map_err(|e| e.to_string())?;
        if plan.spec.overrun_mm <= self.capture.target_tolerance_mm {
            return Err(format!(
                "the overrun ({} mm) must exceed capture.target_tolerance_mm ({} mm), or reversals look like targets",
                plan.spec.overrun_mm, self.capture.target_tolerance_mm
            ));
        }
        // At 0 Hz the module is read as fast as it answers: assume no less than 200 frames/s.
        let rate = if self.rate_hz > 0.0 {
            self.rate_hz
        } else {
            200.0
        };
        self.capture.check_dwell(&plan, rate)?;
        self.align.pre_run_check(
            &self.store,
            &plan.spec.axis,
            plan.travel_mm(),
            crate::store::now_us(),
        )?;
        let dialect = match dialect {
            Some(d) => Dialect::parse(&d).ok_or_else(|| {
                format!("dialect \"{d}\": use iso, siemens, heidenhain or linuxcnc")
            })?,
            None => self.dialect,
        };
        if matches!(self.cnc, CncMode::Twin(_))
            && !matches!(dialect, Dialect::Iso | Dialect::LinuxCnc)
        {
            return Err("the twin's CNC runs iso or linuxcnc programs".into());
        }
        let budget = super::run_budget::record(
            &super::run_budget::AtStart {
                calibrations: &self.calibrations,
                follower_map: self.follower_map.as_ref(),
                encoder_mm: self.drive_status.position_mm,
                carriage_mm: self.pipeline.measure.position(),
                decoupler: self.pipeline.measure.decoupler(),
            },
            &plan,
        );
        let id = self
            .store
            .create_run(&NewRun {
                axis: plan.spec.axis.clone(),
                plan: serde_json::to_value(&plan).map_err(|e| e.to_string())?,
                config: serde_json::json!({"capture": self.capture.to_json(), "dialect": dialect.name(), "budget": budget.to_json()}),
                calibration: self.calibrations.active_id(),
                notes: notes.unwrap_or_else(|| format!("started by {who}")),
            })
            .map_err(|e| e.to_string())?;
        self.store
            .set_run_state(id, RunState::Running)
            .map_err(|e| e.to_string())?;
        let expected = plan.capture_count();
        let warnings = plan.warnings();
        self.begin_run(id, plan, dialect, BTreeSet::new(), "");
        let program = self
            .run
            .as_ref()
            .map(|r| r.program.clone())
            .unwrap_or_default();
        Ok(
            serde_json::json!({"run_id": id.0, "captures_expected": expected, "program": program,
            "warnings": warnings,
            "cnc": match self.cnc { CncMode::Twin(a) => format!("sent to the twin at {a}"), CncMode::Manual => "load the program on the CNC and start it".into() }}),
        )
    }

    /// The run's state for `run_status`: while running, the plan's machine time (`plan_s`)
    /// and what is left of it (`left_s`), for the ETA.
    fn run_status(&self) -> serde_json::Value {
        match (&self.run, self.pipeline.run_progress()) {
            (Some(r), Some((done, total))) => {
                // The plan's motion and dwell for what is left (a make-up pass adds to it).
                let plan_s = r.plan.motion_time_s(ETA_ACCEL_MM_S2);
                let left_s = plan_s * total.saturating_sub(done) as f64 / total.max(1) as f64;
                serde_json::json!({
                    "run_id": r.id.0, "state": "running", "captures": done, "expected": total,
                    "missing": self.pipeline.run_missing().map(|m| m.len()).unwrap_or(0),
                    "program": r.program,
                    "paused": self.pipeline.paused(),
                    "plan_s": plan_s,
                    "left_s": left_s,
                })
            }
            _ => match self
                .store
                .list_runs()
                .ok()
                .and_then(|v| v.into_iter().max_by_key(|r| r.id.0))
            {
                Some(r) => serde_json::json!({
                    "run_id": r.id.0, "state": r.state.as_str(),
                    "captures": self.store.captures(r.id).map(|c| c.len()).unwrap_or(0),
                    "notes": r.notes,
                }),
                None => serde_json::json!({"state": "none"}),
            },
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

    fn reply(
        reply: oneshot::Sender<Result<serde_json::Value, String>>,
        r: Result<serde_json::Value, String>,
    ) {
        let _ = reply.send(r);
    }

    /// Write an operator request to the audit log (who, when, what); a store that cannot take
    /// it raises the store alarm, the request goes on.
    fn audit(&mut self, c: &Command) {
        let Some(entry) = c.audit_entry() else {
            return;
        };
        if let Err(e) = self.store.audit(&entry) {
            self.pipeline
                .alarms
                .raise("store", format!("audit entry not stored: {e}"));
        }
    }

    /// Fit a pose set off the event loop; the reply goes out when the fit ends.
    fn calibration_fit(
        &mut self,
        poses: String,
        reply: oneshot::Sender<Result<serde_json::Value, String>>,
    ) {
        if self.run.is_some() {
            return Self::reply(
                reply,
                Err("a run is under way: calibrate between runs".into()),
            );
        }
        if let Err(e) = self.calibrations.begin_fit() {
            return Self::reply(reply, Err(e));
        }
        let layout = self.calibrations.layout().clone();
        let tx = self.events_tx.clone();
        tokio::spawn(async move {
            let r = super::calibration::fit_async(PathBuf::from(poses), layout).await;
            let _ = tx.send(CoreEvent::Fitted(reply, Box::new(r)));
        });
    }

    /// Store the waiting calibration and decouple with it (judged again on the current
    /// spots; with concerns only when `force`).
    fn calibration_accept(&mut self, force: bool) -> Result<serde_json::Value, String> {
        if self.run.is_some() {
            return Err("a run is under way: its captures must keep one decoupling".into());
        }
        let measure = &self.pipeline.measure;
        let p = self
            .calibrations
            .take_for_accept(force, |d| measure.read_with(d))?;
        let text = super::calibration::file_text(&p.calibration, self.calibrations.layout());
        let id = match self.store.insert_calibration(&text) {
            Ok(id) => id,
            Err(e) => {
                self.calibrations.restore_pending(p);
                return Err(format!(
                    "the calibration was not stored (it still waits): {e}"
                ));
            }
        };
        self.pipeline.measure.set_decoupler(p.decoupler.clone());
        let decoupling = p.summary.decoupling.clone();
        let overridden = p.summary.concerns.clone();
        if overridden.is_empty() {
            tracing::info!(calibration = id.0, %decoupling, "calibration accepted");
        } else {
            tracing::warn!(
                calibration = id.0,
                %decoupling,
                concerns = %overridden.join("; "),
                "calibration accepted over its concerns (override)"
            );
        }
        self.calibrations.accepted(id, p);
        Ok(serde_json::json!({
            "calibration_id": id.0,
            "decoupling": decoupling,
            "overridden": overridden,
            "zero": "cleared: take the zero reference again",
        }))
    }

    fn handle_command(&mut self, c: Command) {
        tracing::info!(user = %c.peer.user, uid = c.peer.uid, request = ?c.request, "control request");
        self.audit(&c);
        match c.request {
            Request::Status | Request::Subscribe { .. } => Self::reply(
                c.reply,
                Err("status and subscribe are answered by the socket".into()),
            ),
            Request::TableList { .. }
            | Request::TableGenerate { .. }
            | Request::TablePublish { .. }
            | Request::TableStatus => Self::reply(
                c.reply,
                Err("internal: table requests are answered by the tables task".into()),
            ),
            Request::Nominal { mm } => {
                if mm.is_some_and(|x| !x.is_finite()) {
                    return Self::reply(
                        c.reply,
                        Err("nominal must be a finite number of mm or null".into()),
                    );
                }
                if self.pipeline.run_progress().is_some() {
                    return Self::reply(
                        c.reply,
                        Err("a run is under way: it sets the nominal".into()),
                    );
                }
                self.pipeline.measure.set_nominal(mm);
                Self::reply(c.reply, Ok(serde_json::json!({"nominal_mm": mm})));
            }
            Request::AlignRead { at_mm } => {
                let at = at_mm.or_else(|| self.pipeline.measure.position());
                let r = match at {
                    Some(at) => self.align.read(at).map(|st| super::align::station_json(&st)),
                    None => Err("where is the carriage? give at_mm (the position is measured only after a zero reference)".into()),
                };
                Self::reply(c.reply, r);
            }
            Request::AlignTarget { psd, x, y } => {
                let r = self
                    .align
                    .target(psd, x, y)
                    .map(|st| super::align::station_json(&st));
                Self::reply(c.reply, r);
            }
            Request::AlignAdvice {
                from_mm,
                to_mm,
                axis,
            } => {
                let r = self.align.advise_and_store(
                    self.calibrations.layout(),
                    axis.as_deref().unwrap_or("X"),
                    (from_mm, to_mm),
                    &mut self.store,
                );
                Self::reply(c.reply, r);
            }
            Request::FollowerMap { id } => {
                let (store, tracker) = (&mut self.store, &mut self.pipeline.tracker);
                let r = super::follower::request(store, tracker, &mut self.follower_map, id);
                Self::reply(c.reply, r);
            }
            Request::FollowerCertificate(req) => {
                let (store, tracker) = (&mut self.store, &mut self.pipeline.tracker);
                let shown = &mut self.follower_map;
                let r = super::follower::import_certificate(store, tracker, shown, req);
                Self::reply(c.reply, r);
            }
            Request::FollowerMapStart(_) if self.follower_level.active() => {
                let why = self.follower_level.refusal("map the follower");
                Self::reply(c.reply, Err(why.unwrap_or_default()));
            }
            Request::FollowerMapStart(mapping) => {
                let busy = super::follower_map::Busy {
                    run: self.run.as_ref().map(|r| r.id.0),
                    hexapod: self.hexapod.active(),
                };
                let who = c.peer.user.clone();
                let r = self.with_mapping(|m, ctx| m.start(mapping, &who, busy, ctx));
                Self::reply(c.reply, r);
            }
            Request::FollowerMapStatus => Self::reply(c.reply, Ok(self.follower_mapping.status())),
            Request::FollowerMapStop => {
                let who = c.peer.user.clone();
                let r = self.with_mapping(|m, ctx| m.stop(&who, ctx));
                Self::reply(c.reply, r);
            }
            Request::FollowerMapFinish => {
                let who = c.peer.user.clone();
                let r = self.with_mapping(|m, ctx| m.finish(&who, ctx));
                Self::reply(c.reply, r);
            }
            Request::FollowerLevelStatus => Self::reply(c.reply, Ok(self.follower_level.status())),
            req @ (Request::FollowerLevelStart(_)
            | Request::FollowerLevelReading { .. }
            | Request::FollowerLevelStop
            | Request::FollowerLevelFinish) => {
                let busy = super::follower_level::Busy {
                    run: self.run.as_ref().map(|r| r.id.0),
                    hexapod: self.hexapod.active(),
                    mapping: self.follower_mapping.active(),
                };
                let who = c.peer.user.clone();
                let r = self.with_level(|l, ctx| l.request(req, &who, busy, ctx));
                Self::reply(c.reply, r);
            }
            Request::AlignClear => {
                self.align.clear();
                Self::reply(c.reply, Ok(serde_json::json!({"stations": 0})));
            }
            Request::Strategy { strategy } => {
                self.pipeline.tracker.set_strategy(strategy);
                Self::reply(c.reply, Ok(serde_json::json!({"strategy": strategy})));
            }
            Request::ClearZero => {
                self.pipeline.measure.clear_zero();
                Self::reply(c.reply, Ok(serde_json::json!({"zeroed": false})));
            }
            Request::Zero => {
                if !self
                    .pipeline
                    .begin_zero(crate::util::clock::now(), self.zero_window)
                {
                    return Self::reply(
                        c.reply,
                        Err("the follower's position is not known yet: is the drive up?".into()),
                    );
                }
                self.zero_reply = Some(c.reply);
            }
            Request::RunStart {
                plan,
                dialect,
                notes,
            } => {
                let r = self.start_run_request(plan, dialect, notes, &c.peer.user);
                Self::reply(c.reply, r);
            }
            Request::RunStatus => Self::reply(c.reply, Ok(self.run_status())),
            Request::Runs { limit } => Self::reply(
                c.reply,
                results::runs(&self.store, limit.unwrap_or(50))
                    .map(|v| serde_json::json!({ "runs": v })),
            ),
            Request::Audit { limit } => Self::reply(
                c.reply,
                results::audit(&self.store, limit.unwrap_or(50))
                    .map(|v| serde_json::json!({ "entries": v })),
            ),
            Request::RunResult { run_id } => Self::reply(
                c.reply,
                results::run_result(&self.store, run_id)
                    .and_then(|r| serde_json::to_value(r).map_err(|e| format!("run result: {e}"))),
            ),
            Request::Calibration => {
                self.take_hexapod_fit();
                Self::reply(c.reply, Ok(self.calibrations.status()))
            }
            Request::CalibrationFit { poses } => self.calibration_fit(poses, c.reply),
            Request::CalibrationAccept { force } => {
                let r = self.calibration_accept(force);
                Self::reply(c.reply, r);
            }
            Request::CalibrationReject => Self::reply(c.reply, self.calibrations.reject()),
            Request::HexapodStart { plan, poses, out } => {
                let mapping = self
                    .follower_mapping
                    .refusal("calibrate")
                    .or_else(|| self.follower_level.refusal("calibrate"));
                let r = match (&self.run, mapping) {
                    (Some(r), _) => Err(format!(
                        "measurement run {} is under way: the hexapod would move the head under it; abort it or let it finish, then calibrate",
                        r.id.0
                    )),
                    (None, Some(why)) => Err(why),
                    (None, None) => self.hexapod.start(
                        plan,
                        poses,
                        out,
                        self.acquisition.subscribe(),
                        super::hexapod_run::ServiceBench::new(&self.cnc, self.drive.clone()),
                    ),
                };
                if r.is_ok() {
                    self.pipeline.invalidate_stitch(
                        "the hexapod moved the head: zero again before measuring",
                    );
                }
                Self::reply(c.reply, r);
            }
            Request::HexapodStatus => {
                // A run that reads "done" has its calibration waiting by the time anyone
                // asks (the tick that takes it may not have come yet).
                let status = self.hexapod.status();
                self.take_hexapod_fit();
                Self::reply(c.reply, Ok(status))
            }
            Request::HexapodStop => Self::reply(c.reply, self.hexapod.stop()),
            Request::RunAbort => {
                if self.pipeline.abort_run() {
                    let id = self.run.as_ref().map(|r| r.id.0);
                    self.end_run(RunState::Aborted, &format!("aborted by {}", c.peer.user));
                    Self::reply(c.reply, Ok(serde_json::json!({"aborted": id})));
                } else {
                    Self::reply(c.reply, Err("no run is under way".into()));
                }
            }
            Request::Follower { action, mm } => {
                let drive = self.drive.clone();
                if matches!(
                    action,
                    FollowerAction::Jog | FollowerAction::Move | FollowerAction::Home
                ) {
                    // A commanded move is not a measured handover: the stitch must be
                    // re-zeroed. Said as what it was (a jog, a move, a homing) and by whom.
                    let what = match action {
                        FollowerAction::Jog => "jogged",
                        FollowerAction::Move => "moved to a position",
                        _ => "homed",
                    };
                    self.pipeline.invalidate_stitch(&format!(
                        "the follower was {what} by {}'s request: zero again before measuring",
                        c.peer.user
                    ));
                }
                tokio::spawn(async move {
                    let r = match (action, mm) {
                        (FollowerAction::Home, _) => drive.home().await,
                        (FollowerAction::Enable, _) => drive.enable().await,
                        (FollowerAction::Disable, _) => drive.disable().await,
                        (FollowerAction::Stop, _) => drive.stop().await,
                        (FollowerAction::FaultReset, _) => match drive.fault_reset().await {
                            Ok(()) => drive.enable().await,
                            Err(e) => Err(e),
                        },
                        (FollowerAction::Jog, Some(d)) => drive.jog(d).await,
                        (FollowerAction::Move, Some(t)) => drive.move_to(t).await,
                        (FollowerAction::Jog | FollowerAction::Move, None) => {
                            let _ = c.reply.send(Err("jog and move need \"mm\"".into()));
                            return;
                        }
                    };
                    let _ = c.reply.send(
                        r.map(|()| serde_json::json!({"position_mm": drive.status().position_mm}))
                            .map_err(|e| format!("follower {action:?}: {e}")),
                    );
                });
            }
        }
    }

    /// A finished hexapod run's calibration, made pending (once).
    fn take_hexapod_fit(&mut self) {
        if let Some(p) = self.hexapod.take_finished() {
            let measure = &self.pipeline.measure;
            let _ = self.calibrations.fitted(Ok(p), |d| measure.read_with(d));
        }
    }

    fn on_tick(&mut self) {
        let now = crate::util::clock::now();
        self.take_hexapod_fit();
        self.with_mapping(|m, ctx| m.tick(now, ctx));
        self.with_level(|l, ctx| l.tick(now, ctx));
        if let Some(z) = self.pipeline.zero_ready(now)
            && let Some(reply) = self.zero_reply.take()
        {
            let r = match z {
                Some(z) => Ok(serde_json::json!({"zeroed": true, "offsets": z.to_user()})),
                None => Err("no valid frames to zero on: is the beam on all three PSDs?".into()),
            };
            let _ = reply.send(r);
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
        // In twin mode, watch the CNC so a program that ended with captures missing gets a
        // make-up pass.
        if let (Some(_), CncMode::Twin(addr)) = (&self.run, &self.cnc)
            && crate::util::clock::since(self.last_cnc_poll) >= Duration::from_secs(1)
        {
            self.last_cnc_poll = crate::util::clock::now();
            let (addr, tx) = (*addr, self.events_tx.clone());
            tokio::spawn(async move {
                if let Ok(v) = twin_request(addr, serde_json::json!({"cmd": "cnc"})).await {
                    let _ = tx.send(CoreEvent::Cnc(v));
                }
            });
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

    fn build_snapshot(&self) -> Snapshot {
        let stats = self.acquisition.stats();
        let p = &self.pipeline;
        let now = crate::util::clock::now();
        let psd = p.last_frame.map(|f| PsdView {
            seq: f.seq,
            spots_um: f.spots.map(|s| s.map(|s| [s.x * 1e3, s.y * 1e3])),
            sums_v: f.sums,
            half_size_um: self.half_size_um,
            valid: f.is_valid() && self.acquisition.is_fresh(&f, now),
            age_ms: now.saturating_duration_since(f.at).as_secs_f64() * 1e3,
            rate_hz: stats.frames_per_s,
            invalid_frames: stats.invalid_frames,
            late_frames: p.late_frames,
        });
        let live = p.measure.live().map(|l| LiveView {
            errors: l.errors.to_user(),
            sd: l.sd.to_user(),
            frames: l.frames,
            travel_mm: l.travel_mm,
            nominal_mm: l.nominal,
            position_mm: l.position_mm,
            zeroed: l.zeroed,
        });
        let st = &self.drive_status;
        let stitch = p.tracker.stitch();
        let link_stats = self.acquisition.link().stats();
        let mut io = link_view(
            &self.acquisition.link().state().borrow(),
            self.acquisition.link().addr().to_string(),
            link_stats.last_exception,
            now,
        );
        io.exceptions = link_stats.exceptions;
        io.rate_hz = stats.frames_per_s;
        io.latency_p50_us = link_stats
            .latency_p50
            .map(|d| d.as_secs_f64() * 1e6)
            .unwrap_or(0.0);
        io.latency_p99_us = link_stats
            .latency_p99
            .map(|d| d.as_secs_f64() * 1e6)
            .unwrap_or(0.0);
        io.errors = link_stats.errors;
        io.reconnects = link_stats.reconnects;
        let can = can_view(
            st,
            self.can_peer.clone(),
            self.sync_periods,
            self.tpdo_rate.rate_hz,
        );
        Snapshot {
            unix_us: now_us(),
            psd,
            live,
            follower: FollowerView {
                node_id: self.node_id,
                state: power_name(st.state),
                position_mm: st.position_mm,
                target_mm: st.commanded_mm,
                homed: st.homed,
                heartbeat_ok: st.heartbeat_ok,
                last_emcy: st.last_emcy.map(|e| e.to_string()),
            },
            tracking: TrackingView {
                strategy: format!("{:?}", stitch.strategy).to_lowercase(),
                valid: stitch.valid,
                at_rest: p.tracker.at_rest(crate::util::clock::now()),
                follower_mm: stitch.follower_mm,
                vertical_um: stitch.vertical_mm * 1e3,
                sd_um: stitch.variance.map(|v| v.sqrt() * 1e3),
                handovers: stitch.handovers,
                follower_map: self.follower_map.clone(),
            },
            links: LinksView { io, can },
            alarms: p.alarms.list().to_vec(),
            run: self.run.as_ref().map(|r| {
                let (captures, expected) = p.run_progress().unwrap_or((0, 0));
                RunView {
                    id: r.id.0,
                    axis: r.plan.spec.axis.clone(),
                    captures,
                    expected,
                    program: r.program.clone(),
                    paused: p.paused().map(str::to_string),
                }
            }),
            follower_mapping: self.follower_mapping.view(),
            follower_level: self.follower_level.view(),
        }
    }
}

/// Send the tracker's follower targets, always the latest: a set-point takes a couple of SYNC
/// periods, and targets that were superseded meanwhile are never sent.
async fn follow(
    drive: DriveHandle,
    mut targets: watch::Receiver<Option<f64>>,
    mut shutdown: Shutdown,
) {
    loop {
        tokio::select! {
            _ = shutdown.recv() => return,
            r = targets.changed() => {
                if r.is_err() {
                    return;
                }
                let target = *targets.borrow_and_update();
                if let Some(mm) = target
                    && let Err(e) = drive.set_target(mm).await
                {
                    tracing::warn!("follower to {mm:.4} mm: {e}");
                }
            }
        }
    }
}

/// Bring the drive up: configure its PDOs, start it, enable it (and home it when asked),
/// retrying while it is unreachable; again whenever it reboots.
async fn bring_up(drive: DriveHandle, home: bool, mut shutdown: Shutdown) {
    let mut events = drive.events();
    loop {
        let attempt = async {
            drive.configure().await?;
            drive.start().await?;
            drive.enable().await?;
            if home || !drive.status().homed {
                drive.home().await?;
            }
            Ok::<(), crate::canopen::DriveError>(())
        };
        let r = tokio::select! {
            _ = shutdown.recv() => return,
            r = attempt => r,
        };
        match r {
            Ok(()) => {
                tracing::info!("follower drive configured, enabled and homed");
                // Wait for a reboot, then do it again.
                loop {
                    tokio::select! {
                        _ = shutdown.recv() => return,
                        e = events.recv() => match e {
                            Ok(Event::BootUp { expected: false }) => break,
                            Ok(_) | Err(broadcast::error::RecvError::Lagged(_)) => {}
                            Err(broadcast::error::RecvError::Closed) => return,
                        },
                    }
                }
            }
            Err(e) => {
                tracing::warn!("follower drive bring-up failed: {e}; retrying in 2 s");
                tokio::select! {
                    _ = shutdown.recv() => return,
                    _ = tokio::time::sleep(Duration::from_secs(2)) => {}
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::canopen::NmtState;

    const SYNC: (Duration, Duration) = (Duration::from_millis(10), Duration::from_millis(100));

    /// A resumed run takes its plan from the store's JSON text: every target must come back
    /// bit for bit, or the captures before and after a restart carry two nominal positions of
    /// one target and the run cannot be evaluated (the fault storm's SIGKILL: 101.18033988749896
    /// against 101.18033988749895 mm; serde_json parses exactly only with float_roundtrip).
    #[test]
    fn a_plan_comes_back_from_the_stored_json_bit_for_bit() {
        let plan = Plan::new(crate::run::PlanSpec {
            axis: "X".into(),
            start_mm: 0.0,
            end_mm: 1000.0,
            targets: 11,
            runs: 5,
            overrun_mm: 2.0,
            dwell_s: 1.2,
            feed_mm_min: 6000.0,
            lead_mm: 10.0,
            reference_mm: None,
        })
        .unwrap();
        let text = serde_json::to_string(&plan).unwrap();
        let stored: serde_json::Value = serde_json::from_str(&text).unwrap();
        let back: Plan = serde_json::from_value(stored).unwrap();
        let bits = |p: &Plan| p.targets.iter().map(|t| t.to_bits()).collect::<Vec<_>>();
        assert_eq!(
            bits(&back),
            bits(&plan),
            "{:?} became {:?}",
            plan.targets,
            back.targets
        );
    }

    #[test]
    fn the_can_link_names_nmt_and_the_sync_period_in_use() {
        let mut st = DriveStatus::default();
        let v = can_view(&st, "peer".into(), SYNC, 0.0);
        assert_eq!((v.state.as_str(), v.detail), ("no heartbeat", None));
        st.heartbeat_ok = true;
        st.nmt = Some(NmtState::Operational);
        st.sync_running = true;
        let v = can_view(&st, "peer".into(), SYNC, 100.0);
        assert_eq!(v.state, "up");
        assert_eq!(v.detail.as_deref(), Some("NMT Operational, SYNC 10 ms"));
        assert_eq!(v.rate_hz, 100.0);
        st.sync_quiet = true;
        let v = can_view(&st, "peer".into(), SYNC, 10.0);
        assert_eq!(
            v.detail.as_deref(),
            Some("NMT Operational, SYNC 100 ms (quiet at rest)")
        );
    }

    #[test]
    fn the_count_rate_is_over_whole_spans() {
        let t0 = crate::util::clock::now();
        let ms = Duration::from_millis;
        let mut r = CountRate::new(Duration::from_secs(1));
        assert_eq!(r.update(t0, 50), 0.0);
        // Within the span the last rate holds.
        assert_eq!(r.update(t0 + ms(500), 100), 0.0);
        // 125 TPDOs over 1.25 s.
        assert!((r.update(t0 + ms(1250), 175) - 100.0).abs() < 1e-9);
        assert!((r.update(t0 + ms(1900), 180) - 100.0).abs() < 1e-9);
        // 10 over the next 1 s: the quiet SYNC.
        assert!((r.update(t0 + ms(2250), 185) - 10.0).abs() < 1e-9);
        // A count that restarts (a new drive handle) starts a new span instead of going negative.
        assert!((r.update(t0 + ms(2500), 3) - 10.0).abs() < 1e-9);
        assert!((r.update(t0 + ms(3500), 13) - 10.0).abs() < 1e-9);
    }
}
