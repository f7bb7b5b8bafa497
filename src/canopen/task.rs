//! The driver task: owns a `CanTransport`, runs the [`Master`] on the real clock, answers
//! commands from cloneable [`DriveHandle`]s, publishes [`DriveStatus`] on a watch channel and
//! the other [`Event`]s on a broadcast channel. Follow targets come on a watch channel of
//! their own (only the latest counts; a command sent after a target is applied after it). It
//! ends when every handle is dropped or the transport closes.

use super::config::{ConfigError, DriveConfig, TravelLimits};
use super::master::{Command, DriveError, DriveStatus, Event, Master, OpId, Reply};
use super::sdo::ObjAddr;
use crate::can::{CanError, CanTransport};
use canopen_rs::NmtCommand;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;
use tokio::sync::{broadcast, mpsc, oneshot, watch};
use tokio::task::JoinHandle;

type ReplyTx = oneshot::Sender<Result<Reply, DriveError>>;

/// Start the driver task for the drive in `config` on `transport`.
pub fn spawn_drive<T: CanTransport>(
    transport: T,
    config: &DriveConfig,
) -> Result<(DriveHandle, JoinHandle<Result<(), CanError>>), ConfigError> {
    let mut master = Master::new(config)?;
    // SYNC wakes the runtime together with the acquisition's ticks (util::pace).
    master.align_sync(crate::util::pace::origin());
    let (cmd_tx, cmd_rx) = mpsc::channel(64);
    let (status_tx, status_rx) = watch::channel(master.status().clone());
    let (event_tx, _) = broadcast::channel(1024);
    let (follow_tx, follow_rx) = watch::channel(None);
    let join = tokio::spawn(drive(
        master,
        transport,
        Inputs {
            commands: cmd_rx,
            follow: follow_rx,
        },
        status_tx,
        event_tx.clone(),
    ));
    let handle = DriveHandle {
        cmd: cmd_tx,
        follow: Arc::new(follow_tx),
        limits: config.limits,
        status: status_rx,
        events: event_tx,
    };
    Ok((handle, join))
}

/// A follow target: where (mm), when, and how fast it moves (mm/s) if the sender knows.
type FollowTarget = (f64, Instant, Option<f64>);

/// What the handles send the task.
struct Inputs {
    commands: mpsc::Receiver<(Command, ReplyTx)>,
    /// The latest follow target (`None`: none sent yet).
    follow: watch::Receiver<Option<FollowTarget>>,
}

/// Hand the latest follow target to the master (marks it seen).
fn apply_follow(m: &mut Master, follow: &mut watch::Receiver<Option<FollowTarget>>) {
    let target = *follow.borrow_and_update();
    if let Some((mm, at, vel)) = target
        && let Err(e) = m.follow_moving(mm, vel, at, crate::util::clock::now())
    {
        tracing::debug!("follow target {mm} mm not taken: {e}");
    }
}

async fn drive<T: CanTransport>(
    mut m: Master,
    bus: T,
    inputs: Inputs,
    status: watch::Sender<DriveStatus>,
    events: broadcast::Sender<Event>,
) -> Result<(), CanError> {
    let Inputs {
        mut commands,
        mut follow,
    } = inputs;
    let mut follow_open = true;
    let mut pending: HashMap<OpId, ReplyTx> = HashMap::new();
    // One timer for the task's life, moved only when the master's deadline changes: a fresh
    // Sleep per turn of the loop (a frame, a follow target) re-registers with tokio's timer,
    // which wakes its driver when the deadline is earlier than the one it sleeps to.
    let timer = tokio::time::sleep_until(tokio::time::Instant::now());
    tokio::pin!(timer);
    let mut armed: Option<Instant> = None;
    loop {
        while let Some(f) = m.poll_transmit() {
            match bus.send(&f).await {
                Ok(()) => {}
                Err(CanError::Closed) => return Err(CanError::Closed),
                // A frame lost on a busy bus is recovered by the protocols' own timeouts.
                Err(e) => tracing::warn!("CANopen master could not send {f}: {e}"),
            }
        }
        // The status first: a caller woken by a completion sees the status that completed it.
        status.send_if_modified(|s| {
            let changed = s != m.status();
            if changed {
                *s = m.status().clone();
            }
            changed
        });
        while let Some(ev) = m.poll_event() {
            match ev {
                Event::Completed { id, result } => {
                    if let Some(tx) = pending.remove(&id) {
                        let _ = tx.send(result);
                    }
                }
                ev => {
                    let _ = events.send(ev);
                }
            }
        }
        let deadline = m.poll_timeout();
        if deadline != armed
            && let Some(d) = deadline
        {
            timer.as_mut().reset(tokio::time::Instant::from_std(d));
        }
        armed = deadline;
        // In order of age when several are ready (this task held up on a loaded machine):
        // frames already received first (a TPDO that came before the SYNC now due answers the
        // previous one, and is stamped with its time), then the latest follow target, then
        // commands, then the clock.
        tokio::select! {
            biased;
            r = bus.recv() => match r {
                Ok(f) => m.handle_frame(&f, crate::util::clock::now()),
                Err(e @ (CanError::Lagged(_) | CanError::Malformed(_))) => {
                    tracing::warn!("CANopen master: {e}")
                }
                Err(e) => return Err(e),
            },
            r = follow.changed(), if follow_open => match r {
                Ok(()) => apply_follow(&mut m, &mut follow),
                Err(_) => follow_open = false,
            },
            c = commands.recv() => match c {
                Some((cmd, reply)) => {
                    // A target sent before this command is applied before it.
                    if follow.has_changed().unwrap_or(false) {
                        apply_follow(&mut m, &mut follow);
                    }
                    let id = m.submit(cmd, crate::util::clock::now());
                    pending.insert(id, reply);
                }
                None => return Ok(()),
            },
            () = &mut timer, if armed.is_some() => {
                armed = None;
                m.handle_timeout(crate::util::clock::now());
            }
        }
    }
}

/// Commands and status for the follower drive; clone it freely.
#[derive(Clone, Debug)]
pub struct DriveHandle {
    cmd: mpsc::Sender<(Command, ReplyTx)>,
    follow: Arc<watch::Sender<Option<FollowTarget>>>,
    limits: TravelLimits,
    status: watch::Receiver<DriveStatus>,
    events: broadcast::Sender<Event>,
}

impl DriveHandle {
    /// Run one command and wait for its result.
    pub async fn request(&self, cmd: Command) -> Result<Reply, DriveError> {
        let (tx, rx) = oneshot::channel();
        self.cmd
            .send((cmd, tx))
            .await
            .map_err(|_| DriveError::Closed)?;
        rx.await.map_err(|_| DriveError::Closed)?
    }

    async fn done(&self, cmd: Command) -> Result<(), DriveError> {
        self.request(cmd).await.map(|_| ())
    }

    /// SDO configuration in pre-operational (see `Command::Configure`).
    pub async fn configure(&self) -> Result<(), DriveError> {
        self.done(Command::Configure).await
    }
    /// NMT start and SYNC.
    pub async fn start(&self) -> Result<(), DriveError> {
        self.done(Command::Start).await
    }
    pub async fn nmt(&self, cmd: NmtCommand) -> Result<(), DriveError> {
        self.done(Command::Nmt(cmd)).await
    }
    /// To operation enabled.
    pub async fn enable(&self) -> Result<(), DriveError> {
        self.done(Command::Enable).await
    }
    /// To switch on disabled.
    pub async fn disable(&self) -> Result<(), DriveError> {
        self.done(Command::Disable).await
    }
    pub async fn home(&self) -> Result<(), DriveError> {
        self.done(Command::Home).await
    }
    /// Absolute move; returns at "target reached".
    pub async fn move_to(&self, target_mm: f64) -> Result<(), DriveError> {
        self.done(Command::MoveTo { target_mm }).await
    }
    /// Relative move; returns at "target reached".
    pub async fn jog(&self, delta_mm: f64) -> Result<(), DriveError> {
        self.done(Command::Jog { delta_mm }).await
    }
    /// New set-point, changed immediately; returns at the drive's acknowledge.
    pub async fn set_target(&self, target_mm: f64) -> Result<(), DriveError> {
        self.done(Command::SetTarget { target_mm }).await
    }
    /// Follow `target_mm` (cyclic synchronous position): the follower should be there now.
    /// Records the latest target and returns at once; call it as often as the target changes.
    /// The task switches the drive to mode 8 on the first target and from then on sends a
    /// demand ramped toward the latest target at every SYNC (see [`Master::follow`]).
    /// Problems come as [`Event::FollowingEnded`] and in [`DriveStatus::following`]. Refused
    /// at once outside the travel limits or with the link closed.
    pub fn follow(&self, target_mm: f64) -> Result<(), DriveError> {
        self.follow_at(target_mm, crate::util::clock::now())
    }
    /// As [`follow`](Self::follow), for a target worked out for time `at` (e.g. from a
    /// time-stamped measurement of the carriage).
    pub fn follow_at(&self, target_mm: f64, at: Instant) -> Result<(), DriveError> {
        self.send_follow((target_mm, at, None))
    }
    /// As [`follow_at`](Self::follow_at), for a target moving at `velocity_mm_s`: the task
    /// moves it on by that velocity to each SYNC, however late (see
    /// [`TargetTrack`](super::csp::TargetTrack)).
    pub fn follow_moving(
        &self,
        target_mm: f64,
        velocity_mm_s: f64,
        at: Instant,
    ) -> Result<(), DriveError> {
        self.send_follow((target_mm, at, Some(velocity_mm_s)))
    }
    fn send_follow(&self, target: FollowTarget) -> Result<(), DriveError> {
        let target_mm = target.0;
        let l = self.limits;
        if !(target_mm >= l.min_mm && target_mm <= l.max_mm) {
            return Err(DriveError::OutOfLimits {
                target_mm,
                min_mm: l.min_mm,
                max_mm: l.max_mm,
            });
        }
        self.follow
            .send(Some(target))
            .map_err(|_| DriveError::Closed)
    }
    /// Stop following: the demand comes to rest on the last target (one sent just before is
    /// still taken) and the drive returns to profile position; returns when it is there (at
    /// once when not following).
    pub async fn stop_following(&self) -> Result<(), DriveError> {
        self.done(Command::StopFollowing).await
    }
    pub async fn stop(&self) -> Result<(), DriveError> {
        self.done(Command::Stop).await
    }
    pub async fn quick_stop(&self) -> Result<(), DriveError> {
        self.done(Command::QuickStop).await
    }
    pub async fn fault_reset(&self) -> Result<(), DriveError> {
        self.done(Command::FaultReset).await
    }
    pub async fn sdo_read(&self, index: u16, sub: u8) -> Result<Vec<u8>, DriveError> {
        match self
            .request(Command::SdoRead(ObjAddr::new(index, sub)))
            .await?
        {
            Reply::Data(d) => Ok(d),
            Reply::Done => Ok(Vec::new()),
        }
    }
    pub async fn sdo_write(&self, index: u16, sub: u8, data: Vec<u8>) -> Result<(), DriveError> {
        self.done(Command::SdoWrite(ObjAddr::new(index, sub), data))
            .await
    }

    /// The latest status.
    pub fn status(&self) -> DriveStatus {
        self.status.borrow().clone()
    }
    /// A watch of the status (updated at least at every TPDO, i.e. at SYNC rate).
    pub fn watch_status(&self) -> watch::Receiver<DriveStatus> {
        self.status.clone()
    }
    /// Events from now on (boot-up, NMT, heartbeat lost/resumed, EMCY, power state).
    pub fn events(&self) -> broadcast::Receiver<Event> {
        self.events.subscribe()
    }
}
