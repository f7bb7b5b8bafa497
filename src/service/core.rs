//! The core task: the one place that owns the tracking machine and the live measurement. It
//! takes frames from the acquisition, follower status and events from the drive, requests from
//! the control socket, and publishes the `Snapshot`. Drive commands go out as their own small
//! tasks, so the loop never waits on the bus.

use super::Prepared;
use super::control::{Command, FollowerAction, Request};
use super::notify;
use super::pipeline::{Output, Pipeline, now_us};
use super::shutdown::Shutdown;
use super::snapshot::{
    FollowerView, LinkView, LinksView, LiveView, PsdView, Snapshot, TrackingView,
};
use crate::acquire::{Acquisition, Frame};
use crate::canopen::{DriveHandle, DriveStatus, Event, PowerState};
use crate::modbus::{Link, LinkState};
use crate::optics::layout::{Aperture, Kind};
use std::time::{Duration, Instant};
use tokio::sync::{broadcast, mpsc, oneshot, watch};

/// A frame older than this when the core gets to it is not decoupled (it is still tracked).
const LATE: Duration = Duration::from_millis(100);

fn link_view(state: &LinkState, peer: String) -> LinkView {
    let (state, detail) = match state {
        LinkState::Up { .. } => ("up".to_string(), None),
        LinkState::Connecting { attempt } => {
            ("connecting".to_string(), Some(format!("attempt {attempt}")))
        }
        LinkState::Down { error, .. } => ("down".to_string(), Some(error.to_string())),
        LinkState::Closed => ("closed".to_string(), None),
    };
    LinkView {
        state,
        peer,
        detail,
        ..LinkView::default()
    }
}

fn power_name(s: Option<PowerState>) -> String {
    s.map(|p| format!("{p:?}"))
        .unwrap_or_else(|| "unknown".into())
}

pub(super) struct Core {
    pipeline: Pipeline,
    link: Link,
    acquisition: Acquisition,
    drive: DriveHandle,
    drive_status: DriveStatus,
    can_peer: String,
    node_id: u8,
    snapshot: watch::Sender<Snapshot>,
    snapshot_period: Duration,
    half_size_um: [f64; 3],
    home_on_start: bool,
    watchdog: bool,
    /// The reply owed to a zero request, answered once the window has refilled.
    zero_reply: Option<oneshot::Sender<Result<serde_json::Value, String>>>,
    live_window: Duration,
    ready_sent: bool,
    started: Instant,
    /// The follower target the tracker wants (the follower task sends the latest).
    follow: watch::Sender<Option<f64>>,
}

impl Core {
    pub(super) fn new(
        p: &Prepared,
        link: Link,
        acquisition: Acquisition,
        drive: DriveHandle,
        can_peer: String,
        snapshot: watch::Sender<Snapshot>,
    ) -> Core {
        let s = &p.settings;
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
            pipeline: Pipeline::new(s.tracking, p.decoupler.clone(), s.head.live_window),
            link,
            acquisition,
            drive_status: drive.status(),
            drive,
            can_peer,
            node_id: s.follower.drive.node_id,
            snapshot,
            snapshot_period: s.service.snapshot_period,
            half_size_um,
            home_on_start: s.follower.home_on_start,
            watchdog: s.service.watchdog,
            zero_reply: None,
            live_window: s.head.live_window,
            ready_sent: false,
            started: Instant::now(),
            follow: watch::channel(None).0,
        }
    }

    pub(super) async fn run(
        mut self,
        mut commands: mpsc::Receiver<Command>,
        mut shutdown: Shutdown,
    ) -> Result<(), super::ServiceError> {
        let mut frames = self.acquisition.subscribe();
        let mut status = self.drive.watch_status();
        let mut events = self.drive.events();
        let mut io_state = self.link.state();
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
        let mut tick = tokio::time::interval(self.snapshot_period.min(Duration::from_millis(100)));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        let watchdog = notify::watchdog_period().filter(|_| self.watchdog);
        let mut last_watchdog = Instant::now();
        loop {
            tokio::select! {
                _ = shutdown.recv() => break,
                f = frames.recv() => match f {
                    Ok(f) => self.handle_frame(&f),
                    Err(broadcast::error::RecvError::Lagged(n)) => {
                        tracing::warn!("core fell behind the acquisition by {n} frames");
                    }
                    Err(broadcast::error::RecvError::Closed) => break,
                },
                r = status.changed() => {
                    if r.is_err() { break; }
                    let st = status.borrow_and_update().clone();
                    self.pipeline.handle_drive_status(&st, Instant::now());
                    self.drive_status = st;
                    self.pump();
                }
                e = events.recv() => match e {
                    Ok(e) => {
                        self.pipeline.handle_drive_event(&e, &self.can_peer);
                        self.pump();
                    }
                    Err(broadcast::error::RecvError::Lagged(_)) => {}
                    Err(broadcast::error::RecvError::Closed) => break,
                },
                r = io_state.changed() => {
                    if r.is_ok() {
                        let st = *io_state.borrow_and_update();
                        self.handle_io_state(&st);
                    }
                }
                c = commands.recv() => match c {
                    Some(c) => self.handle_command(c),
                    None => break,
                },
                _ = tick.tick() => {
                    self.on_tick();
                    if let Some(period) = watchdog
                        && last_watchdog.elapsed() >= period
                    {
                        notify::watchdog();
                        last_watchdog = Instant::now();
                    }
                }
            }
        }
        bring_up.abort();
        follower.abort();
        // Leave the follower at rest.
        let _ = tokio::time::timeout(Duration::from_secs(1), self.drive.stop()).await;
        Ok(())
    }

    fn handle_frame(&mut self, f: &Frame) {
        // The pipeline judges a frame at its own time (when the module answered); a frame the
        // core reaches late is tracked but not decoupled, so the core catches up.
        let late = Instant::now().saturating_duration_since(f.at) > LATE;
        self.pipeline.handle_frame(f, late);
        self.pump();
    }

    /// Carry out what the pipeline asks.
    fn pump(&mut self) {
        while let Some(out) = self.pipeline.poll_output() {
            match out {
                // Only the latest target matters: the follower task skips superseded ones.
                Output::Follow(mm) => {
                    self.follow.send_replace(Some(mm));
                }
                Output::QuickStop => {
                    let drive = self.drive.clone();
                    tokio::spawn(async move {
                        let _ = drive.quick_stop().await;
                    });
                }
                Output::Handover(_) => {}
                Output::Captured(c) => tracing::info!(?c.run, c.target_index, "captured"),
                Output::Acknowledge(_) | Output::RunFinished | Output::RunFailed(_) => {}
            }
        }
    }

    fn handle_io_state(&mut self, st: &LinkState) {
        match st {
            LinkState::Up { .. } => self.pipeline.alarms.clear("io-link-down"),
            LinkState::Down { error, .. } => self.pipeline.alarms.raise(
                "io-link-down",
                format!(
                    "PSD I/O module {} unreachable: {error}; reconnecting",
                    self.link.addr()
                ),
            ),
            _ => {}
        }
    }

    fn reply(
        reply: oneshot::Sender<Result<serde_json::Value, String>>,
        r: Result<serde_json::Value, String>,
    ) {
        let _ = reply.send(r);
    }

    fn handle_command(&mut self, c: Command) {
        tracing::info!(user = %c.peer.user, uid = c.peer.uid, request = ?c.request, "control request");
        match c.request {
            Request::Status | Request::Subscribe { .. } => Self::reply(
                c.reply,
                Err("status and subscribe are answered by the socket".into()),
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
            Request::Strategy { strategy } => {
                self.pipeline.tracker.set_strategy(strategy);
                Self::reply(c.reply, Ok(serde_json::json!({"strategy": strategy})));
            }
            Request::ClearZero => {
                self.pipeline.measure.clear_zero();
                Self::reply(c.reply, Ok(serde_json::json!({"zeroed": false})));
            }
            Request::Zero => {
                if !self.pipeline.begin_zero(Instant::now(), self.live_window) {
                    return Self::reply(
                        c.reply,
                        Err("the follower's position is not known yet: is the drive up?".into()),
                    );
                }
                self.zero_reply = Some(c.reply);
            }
            Request::Follower { action, mm } => {
                let drive = self.drive.clone();
                if matches!(
                    action,
                    FollowerAction::Jog | FollowerAction::Move | FollowerAction::Home
                ) {
                    // A manual move is not a measured handover: the stitch must be re-zeroed.
                    self.pipeline.invalidate_stitch(
                        "the follower was moved by hand: zero again before measuring",
                    );
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

    fn on_tick(&mut self) {
        let now = Instant::now();
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
            let io_up = self.link.state().borrow().is_up();
            let drive_up = self.drive_status.state == Some(PowerState::OperationEnabled);
            if (io_up && drive_up) || self.started.elapsed() > Duration::from_secs(30) {
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
        let snap = self.build_snapshot();
        self.snapshot.send_replace(snap);
    }

    fn build_snapshot(&self) -> Snapshot {
        let stats = self.acquisition.stats();
        let p = &self.pipeline;
        let psd = p.last_frame.map(|f| PsdView {
            seq: f.seq,
            spots_um: f.spots.map(|s| s.map(|s| [s.x * 1e3, s.y * 1e3])),
            sums_v: f.sums,
            half_size_um: self.half_size_um,
            valid: f.is_valid(),
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
        let link_stats = self.link.stats();
        let mut io = link_view(&self.link.state().borrow(), self.link.addr().to_string());
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
        let can = LinkView {
            state: if st.heartbeat_ok {
                "up".into()
            } else {
                "no heartbeat".into()
            },
            peer: self.can_peer.clone(),
            detail: st.nmt.map(|n| format!("NMT {n:?}")),
            rate_hz: 0.0,
            ..LinkView::default()
        };
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
                at_rest: p.tracker.at_rest(Instant::now()),
                follower_mm: stitch.follower_mm,
                vertical_um: stitch.vertical_mm * 1e3,
                sd_um: stitch.variance.map(|v| v.sqrt() * 1e3),
                handovers: stitch.handovers,
            },
            links: LinksView { io, can },
            alarms: p.alarms.list().to_vec(),
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
