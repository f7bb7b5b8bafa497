//! The acquisition loop: one block read per frame through the [`Link`], decoded by the map,
//! timestamped on arrival, published on a `broadcast` channel (every frame) and a `watch`
//! (the latest), with statistics.
//!
//! At `rate_hz > 0` reads start on a fixed schedule (missed ticks are skipped, never
//! bunched); at `rate_hz = 0` the next read starts as soon as the previous reply is in.
//! [`Acquisition::spawn_paced`] reads at a fixed rate through a [`PacedReader`] instead of a
//! [`Link`]: one wake-up per frame instead of two, each frame published one period after its
//! reply arrived (and stamped with that arrival).
//! [`Acquisition::spawn_pipelined`] reads unthrottled through a [`PipelinedReader`] instead:
//! several requests in flight, so the module answers the next read while this one is decoded
//! and published, and nothing is allocated per frame.
//! While the link is down the loop waits for it instead of spinning. Frames with a PSD below
//! its SUM threshold are published marked invalid (that spot `None`) and counted; consumers
//! must not average them in.

use super::Frame;
use super::decode::{self, DecodeError};
use super::map::IoMap;
use crate::modbus::link::{LinkConfig, LinkError, LinkState, Window};
use crate::modbus::{Link, Monitor, PacedReader, PipelinedReader};
use crate::util::pace::Pacer;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use tokio::sync::{broadcast, watch};
use tokio::task::JoinHandle;

/// A frame is stale, never shown or used as valid, once older than this or
/// [`STALE_PERIODS`] frame periods, whichever is longer ([`AcquireConfig::stale_after`]).
pub const STALE_AFTER: Duration = Duration::from_millis(100);
/// Frame periods after which a frame is stale, at low frame rates.
pub const STALE_PERIODS: u32 = 5;

/// Acquisition settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AcquireConfig {
    /// Frames per second; 0 reads as fast as the link answers (default 200).
    pub rate_hz: f64,
    /// Frames a slow subscriber may fall behind before it loses some (default 4096).
    pub capacity: usize,
    /// Frames in the statistics window (default 1024).
    pub window: usize,
    /// Block reads in flight when unthrottled through [`Acquisition::spawn_pipelined`]
    /// (default [`DEFAULT_DEPTH`](crate::modbus::pipelined::DEFAULT_DEPTH), 1: one at a time,
    /// as every module takes; more for a module that answers requests queued behind another).
    pub pipeline: usize,
}

impl AcquireConfig {
    /// The age at which the latest frame is stale: [`STALE_AFTER`] (100 ms), or
    /// [`STALE_PERIODS`] (5) periods at `rate_hz` when that is longer. At 500 Hz: 100 ms, 50
    /// frames; at 10 Hz: 500 ms.
    pub fn stale_after(&self) -> Duration {
        if self.rate_hz > 0.0 && self.rate_hz.is_finite() {
            STALE_AFTER.max(Duration::from_secs_f64(
                f64::from(STALE_PERIODS) / self.rate_hz,
            ))
        } else {
            STALE_AFTER
        }
    }
}

impl Default for AcquireConfig {
    fn default() -> Self {
        AcquireConfig {
            rate_hz: 200.0,
            capacity: 4096,
            window: 1024,
            pipeline: crate::modbus::pipelined::DEFAULT_DEPTH,
        }
    }
}

/// Acquisition statistics (a snapshot).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AcquireStats {
    /// Frames published.
    pub frames: u64,
    /// Of which invalid (a PSD without its spot).
    pub invalid_frames: u64,
    /// Reads that failed (link errors) and blocks that did not decode.
    pub read_errors: u64,
    pub decode_errors: u64,
    /// The last error, if any.
    pub last_error: Option<AcquireError>,
    /// Frames per second over the last second.
    pub frames_per_s: f64,
    /// Request-to-reply time per frame over the window.
    pub latency_p50: Option<Duration>,
    pub latency_p99: Option<Duration>,
    /// The link's state.
    pub link: LinkState,
}

/// What went wrong with one read.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum AcquireError {
    #[error("read failed: {0}")]
    Link(#[from] LinkError),
    #[error("block did not decode: {0}")]
    Decode(#[from] DecodeError),
}

struct Counters {
    frames: u64,
    invalid: u64,
    read_errors: u64,
    decode_errors: u64,
    last_error: Option<AcquireError>,
    window: Window,
}

/// A running acquisition. Dropping it (or [`stop`](Self::stop)) ends the loop.
pub struct Acquisition {
    frames: broadcast::Sender<Frame>,
    latest: watch::Receiver<Option<Frame>>,
    counters: Arc<Mutex<Counters>>,
    link: Monitor,
    stale_after: Duration,
    task: JoinHandle<()>,
}

impl Drop for Acquisition {
    fn drop(&mut self) {
        self.task.abort();
    }
}

fn lock(c: &Mutex<Counters>) -> std::sync::MutexGuard<'_, Counters> {
    c.lock().unwrap_or_else(|p| p.into_inner())
}

fn unix_us(now: SystemTime) -> i64 {
    match now.duration_since(UNIX_EPOCH) {
        Ok(d) => d.as_micros() as i64,
        Err(e) => -(e.duration().as_micros() as i64),
    }
}

impl Acquisition {
    /// Start reading `map`'s block through `link` (on the current Tokio runtime).
    pub fn spawn(link: Link, map: Arc<IoMap>, config: AcquireConfig) -> Acquisition {
        let monitor = link.monitor();
        Self::start(monitor, config, |out| {
            tokio::spawn(run(link, map, config, out))
        })
    }

    /// Start reading `map`'s block from the device in `link` at `config.rate_hz` (which must
    /// be above zero) through a [`PacedReader`] of its own.
    pub fn spawn_paced(link: LinkConfig, map: Arc<IoMap>, config: AcquireConfig) -> Acquisition {
        let (reader, monitor) = PacedReader::new(link, map.kind, map.unit_id, map.block);
        Self::start(monitor, config, |out| {
            tokio::spawn(run_paced(reader, map, config, out))
        })
    }

    /// Start reading `map`'s block from the device in `link` as fast as it answers, with
    /// `config.pipeline` reads in flight, through a [`PipelinedReader`] of its own
    /// (`config.rate_hz` is not used).
    pub fn spawn_pipelined(
        link: LinkConfig,
        map: Arc<IoMap>,
        config: AcquireConfig,
    ) -> Acquisition {
        let (reader, monitor) =
            PipelinedReader::new(link, map.kind, map.unit_id, map.block, config.pipeline);
        Self::start(monitor, config, |out| {
            tokio::spawn(run_pipelined(reader, map, config, out))
        })
    }

    fn start(
        link: Monitor,
        config: AcquireConfig,
        spawn: impl FnOnce(Outputs) -> JoinHandle<()>,
    ) -> Acquisition {
        let (frames, _) = broadcast::channel(config.capacity.max(1));
        let (latest_tx, latest) = watch::channel(None);
        let counters = Arc::new(Mutex::new(Counters {
            frames: 0,
            invalid: 0,
            read_errors: 0,
            decode_errors: 0,
            last_error: None,
            window: Window::new(config.window),
        }));
        let task = spawn(Outputs {
            frames: frames.clone(),
            latest: latest_tx,
            counters: counters.clone(),
            seq: 0,
            last_stamp: None,
        });
        Acquisition {
            frames,
            latest,
            counters,
            link,
            stale_after: config.stale_after(),
            task,
        }
    }

    /// The link's address, state and statistics.
    pub fn link(&self) -> &Monitor {
        &self.link
    }

    /// The age at which a frame is stale ([`AcquireConfig::stale_after`]).
    pub fn stale_after(&self) -> Duration {
        self.stale_after
    }

    /// Whether `frame` is still fresh at `now` (not older than [`stale_after`](Self::stale_after)).
    pub fn is_fresh(&self, frame: &Frame, now: Instant) -> bool {
        now.saturating_duration_since(frame.at) <= self.stale_after
    }

    /// Every frame from now on.
    pub fn subscribe(&self) -> broadcast::Receiver<Frame> {
        self.frames.subscribe()
    }

    /// The latest frame.
    pub fn latest(&self) -> watch::Receiver<Option<Frame>> {
        self.latest.clone()
    }

    /// A statistics snapshot.
    pub fn stats(&self) -> AcquireStats {
        let c = lock(&self.counters);
        AcquireStats {
            frames: c.frames,
            invalid_frames: c.invalid,
            read_errors: c.read_errors,
            decode_errors: c.decode_errors,
            last_error: c.last_error,
            frames_per_s: c.window.rate_hz(crate::util::clock::now()),
            latency_p50: c.window.quantile(0.5),
            latency_p99: c.window.quantile(0.99),
            link: *self.link.state().borrow(),
        }
    }

    /// End the loop.
    pub fn stop(self) {
        drop(self);
    }
}

/// Where frames and counts go.
struct Outputs {
    frames: broadcast::Sender<Frame>,
    latest: watch::Sender<Option<Frame>>,
    counters: Arc<Mutex<Counters>>,
    seq: u64,
    /// The last reply time and its wall-clock time: replies read together (pipelined) share
    /// one instant and get one wall time, so `unix_us` never steps back between them.
    last_stamp: Option<(Instant, i64)>,
}

impl Outputs {
    /// Decode and publish one reply (sent at `sent`, arrived at `at`); the error if it does
    /// not decode.
    fn publish(
        &mut self,
        map: &IoMap,
        block: &[u16],
        sent: Instant,
        at: Instant,
    ) -> Result<(), AcquireError> {
        let wall = match self.last_stamp {
            Some((last, us)) if last == at => us,
            _ => unix_us(
                crate::util::clock::wall()
                    - crate::util::clock::now().saturating_duration_since(at),
            ),
        };
        self.last_stamp = Some((at, wall));
        let frame = decode::frame(map, block, self.seq, at, wall)?;
        self.seq += 1;
        {
            let mut c = lock(&self.counters);
            c.frames += 1;
            if !frame.is_valid() {
                c.invalid += 1;
            }
            c.window.push(at, at.saturating_duration_since(sent));
        }
        self.latest.send_replace(Some(frame));
        // No subscriber is not an error: the watch still has the frame.
        let _ = self.frames.send(frame);
        Ok(())
    }

    fn count(&self, error: AcquireError) {
        let mut c = lock(&self.counters);
        match error {
            AcquireError::Link(_) => c.read_errors += 1,
            AcquireError::Decode(_) => c.decode_errors += 1,
        }
        c.last_error = Some(error);
    }
}

async fn run(link: Link, map: Arc<IoMap>, config: AcquireConfig, mut out: Outputs) {
    let mut ticker = (config.rate_hz > 0.0 && config.rate_hz.is_finite())
        .then(|| Pacer::new(Duration::from_secs_f64(1.0 / config.rate_hz)));
    let mut state = link.state();
    loop {
        if let Some(t) = ticker.as_mut() {
            t.tick().await;
        }
        let sent = crate::util::clock::now();
        let error = match link.read(map.kind, map.unit_id, map.block).await {
            Ok(block) => match out.publish(&map, &block, sent, crate::util::clock::now()) {
                Ok(()) => continue,
                Err(e) => e,
            },
            Err(e) => AcquireError::Link(e),
        };
        out.count(error);
        match error {
            AcquireError::Link(LinkError::Closed) => return,
            AcquireError::Link(e) if !e.drops_connection() && !link_down(&e) => {
                // The device answered (an exception) or the map does not fit it: retry at
                // the configured rate, or after a short pause when unthrottled.
                if ticker.is_none() {
                    tokio::time::sleep(Duration::from_millis(10)).await;
                }
            }
            AcquireError::Link(_) => {
                // Wait for the link to come back rather than spinning on errors.
                let _ = tokio::time::timeout(
                    Duration::from_secs(1),
                    state.wait_for(|s| s.is_connected() || *s == LinkState::Closed),
                )
                .await;
            }
            AcquireError::Decode(_) => {
                if ticker.is_none() {
                    tokio::time::sleep(Duration::from_millis(10)).await;
                }
            }
        }
    }
}

/// The paced loop: the reader's own backoff paces reconnects, exceptions and undecodable
/// blocks are retried at the next tick.
async fn run_paced(
    mut reader: PacedReader,
    map: Arc<IoMap>,
    config: AcquireConfig,
    mut out: Outputs,
) {
    let rate = if config.rate_hz > 0.0 && config.rate_hz.is_finite() {
        config.rate_hz
    } else {
        AcquireConfig::default().rate_hz
    };
    let mut ticker = Pacer::new(Duration::from_secs_f64(1.0 / rate));
    loop {
        ticker.tick().await;
        let error = match reader.tick().await {
            None => continue,
            Some(Ok(reply)) => match out.publish(&map, &reply.registers, reply.sent, reply.at) {
                Ok(()) => continue,
                Err(e) => e,
            },
            Some(Err(e)) => AcquireError::Link(e),
        };
        out.count(error);
    }
}

/// The pipelined loop: the reader's own backoff paces reconnects; after an exception or an
/// undecodable block the next read waits a little (the module answers at once, again).
async fn run_pipelined(
    mut reader: PipelinedReader,
    map: Arc<IoMap>,
    _config: AcquireConfig,
    mut out: Outputs,
) {
    loop {
        let error = match reader.next().await {
            Ok(b) => match out.publish(&map, b.registers, b.sent, b.at) {
                Ok(()) => continue,
                Err(e) => e,
            },
            Err(e) => AcquireError::Link(e),
        };
        out.count(error);
        match error {
            AcquireError::Link(e) if e.drops_connection() || link_down(&e) => {}
            _ => tokio::time::sleep(Duration::from_millis(10)).await,
        }
    }
}

fn link_down(e: &LinkError) -> bool {
    matches!(e, LinkError::Disconnected | LinkError::Connect(_))
}
