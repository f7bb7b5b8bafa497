//! Fault injection around any transport (smoltcp `phy::FaultInjector` style), for the
//! reliability tests: lost frames (heartbeat loss), added latency, and a cut link.
//!
//! [`Faulty`] wraps a [`CanTransport`] and applies, separately to the frames it sends (tx)
//! and to the frames it receives (rx), a [`Faults`] setting: drop with a probability, drop
//! every n-th frame, and delay. A [`FaultControl`] handle (cloneable, shared with the
//! wrapper) changes the settings at run time, cuts and restores the link, and reads counters.
//!
//! Semantics:
//! - Drops are decided by a seeded random stream of the wrapper's own (xorshift64*, one per
//!   direction; the formula is at `Xorshift`), so a seed gives the same losses on every run
//!   and build. `drop_every = n` drops frames n, 2n, 3n… of that direction, counted over
//!   frames that reach the decision (link up); then `drop_probability` applies.
//! - Link down: frames sent are discarded (`send` still returns `Ok`, as a cut cable gives no
//!   error to a tunnel), frames arriving are read from the inner transport and discarded, and
//!   delayed frames still in flight when they fall due are discarded too.
//! - Delay: a received frame is returned no earlier than `delay` after this wrapper read it
//!   from the inner transport (frames are read only while a `recv` is pending, so time spent
//!   in the inner transport's buffer before that is not counted). A sent frame is handed to
//!   the inner transport `delay` after `send` by a forwarding task, and `send` returns at once;
//!   order is kept in both directions. Errors of delayed sends are logged only.
//! - `recv` stays cancel-safe: frames read from the inner transport are queued before any
//!   wait, and the inner `recv` is itself cancel-safe.
//! - Timing uses `tokio::time`, so tests can run it on a paused clock.

use super::{CanError, CanFrame, CanTransport};
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex as StdMutex, OnceLock};
use std::time::Duration;
use tokio::sync::{Mutex, mpsc};
use tokio::time::Instant;

/// Faults applied to one direction.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Faults {
    /// Probability in [0, 1] that a frame is dropped.
    pub drop_probability: f64,
    /// Drop every n-th frame (0: never).
    pub drop_every: u64,
    /// Added latency.
    pub delay: Duration,
}

impl Faults {
    /// No faults.
    pub const NONE: Faults = Faults {
        drop_probability: 0.0,
        drop_every: 0,
        delay: Duration::ZERO,
    };
}

/// Counters of a [`Faulty`] transport.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FaultStats {
    /// Frames handed on to the inner transport.
    pub tx_passed: u64,
    /// Frames sent and dropped (faults or link down).
    pub tx_dropped: u64,
    /// Frames received and returned.
    pub rx_passed: u64,
    /// Frames received and dropped (faults or link down).
    pub rx_dropped: u64,
}

/// The drops' random stream, carried here as smoltcp's fault injector carries its
/// xorshift32: xorshift64* (Marsaglia's xorshift, Vigna's multiplier). The stream of
/// direction `stream` starts at `x = (seed ^ stream << 32) · 0x9E37_79B9_7F4A_7C15` (1 if that
/// is 0); each draw steps `x ^= x >> 12; x ^= x << 25; x ^= x >> 27` and is the top 53 bits
/// of `x · 0x2545_F491_4F6C_DD1D` as a fraction in [0, 1).
#[derive(Clone, Debug)]
struct Xorshift(u64);

impl Xorshift {
    fn new(seed: u64, stream: u64) -> Self {
        Xorshift(((seed ^ (stream << 32)).wrapping_mul(0x9E37_79B9_7F4A_7C15)).max(1))
    }

    /// Uniform in [0, 1).
    fn unit(&mut self) -> f64 {
        let x = &mut self.0;
        *x ^= *x >> 12;
        *x ^= *x << 25;
        *x ^= *x >> 27;
        (x.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Per-direction drop decision (sans-I/O).
#[derive(Debug)]
struct Dropper {
    faults: Faults,
    rng: Xorshift,
    seen: u64,
}

impl Dropper {
    fn new(rng: Xorshift) -> Self {
        Dropper {
            faults: Faults::NONE,
            rng,
            seen: 0,
        }
    }

    /// Whether the next frame is dropped. One random draw per frame whenever a probability
    /// is set, whatever `drop_every` decides, so the stream of draws is predictable.
    fn drops(&mut self) -> bool {
        self.seen += 1;
        let every = self.faults.drop_every > 0 && self.seen.is_multiple_of(self.faults.drop_every);
        let p = self.faults.drop_probability;
        let random = p > 0.0 && self.rng.unit() < p;
        every || random
    }
}

#[derive(Debug)]
struct Shared {
    link_up: AtomicBool,
    tx: StdMutex<Dropper>,
    rx: StdMutex<Dropper>,
    tx_passed: AtomicU64,
    tx_dropped: AtomicU64,
    rx_passed: AtomicU64,
    rx_dropped: AtomicU64,
}

fn lock<T>(m: &StdMutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl Shared {
    fn up(&self) -> bool {
        self.link_up.load(Ordering::Acquire)
    }
    fn count(c: &AtomicU64) {
        c.fetch_add(1, Ordering::Relaxed);
    }
}

/// Stream numbers of the two directions' random streams (see the module's semantics).
pub const TX_STREAM: u64 = 1;
/// See [`TX_STREAM`].
pub const RX_STREAM: u64 = 2;

/// The handle that steers a [`Faulty`] transport from a test.
#[derive(Clone, Debug)]
pub struct FaultControl(Arc<Shared>);

impl FaultControl {
    /// Cut the link: nothing passes either way until [`FaultControl::restore`].
    pub fn cut(&self) {
        self.0.link_up.store(false, Ordering::Release);
    }
    /// Restore the link.
    pub fn restore(&self) {
        self.0.link_up.store(true, Ordering::Release);
    }
    /// Whether the link is up.
    pub fn is_up(&self) -> bool {
        self.0.up()
    }
    /// Faults for frames sent from now on.
    pub fn set_tx(&self, f: Faults) {
        lock(&self.0.tx).faults = f;
    }
    /// Faults for frames received from now on.
    pub fn set_rx(&self, f: Faults) {
        lock(&self.0.rx).faults = f;
    }
    /// Current tx faults.
    pub fn tx(&self) -> Faults {
        lock(&self.0.tx).faults
    }
    /// Current rx faults.
    pub fn rx(&self) -> Faults {
        lock(&self.0.rx).faults
    }
    /// Counters so far.
    pub fn stats(&self) -> FaultStats {
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        FaultStats {
            tx_passed: g(&self.0.tx_passed),
            tx_dropped: g(&self.0.tx_dropped),
            rx_passed: g(&self.0.rx_passed),
            rx_dropped: g(&self.0.rx_dropped),
        }
    }
}

/// A transport with injected faults; see the module docs.
#[derive(Debug)]
pub struct Faulty<T> {
    inner: Arc<T>,
    shared: Arc<Shared>,
    /// Received frames waiting for their delay, with their due time.
    rx_queue: Mutex<VecDeque<(Instant, CanFrame)>>,
    /// The forwarding task's queue for delayed sends, started on first use.
    tx_queue: OnceLock<mpsc::UnboundedSender<(Instant, CanFrame)>>,
}

impl<T: CanTransport> Faulty<T> {
    /// Wrap `inner` with no faults yet and the link up; `seed` fixes the random drops.
    pub fn new(inner: T, seed: u64) -> Self {
        Faulty {
            inner: Arc::new(inner),
            shared: Arc::new(Shared {
                link_up: AtomicBool::new(true),
                tx: StdMutex::new(Dropper::new(Xorshift::new(seed, TX_STREAM))),
                rx: StdMutex::new(Dropper::new(Xorshift::new(seed, RX_STREAM))),
                tx_passed: AtomicU64::new(0),
                tx_dropped: AtomicU64::new(0),
                rx_passed: AtomicU64::new(0),
                rx_dropped: AtomicU64::new(0),
            }),
            rx_queue: Mutex::new(VecDeque::new()),
            tx_queue: OnceLock::new(),
        }
    }

    /// Wrap with the given faults.
    pub fn with_faults(inner: T, seed: u64, tx: Faults, rx: Faults) -> Self {
        let f = Faulty::new(inner, seed);
        f.control().set_tx(tx);
        f.control().set_rx(rx);
        f
    }

    /// A handle to steer this transport.
    pub fn control(&self) -> FaultControl {
        FaultControl(self.shared.clone())
    }

    /// The wrapped transport.
    pub fn inner(&self) -> &T {
        &self.inner
    }

    /// Whether a frame in this direction passes (link up and not dropped), counted.
    fn admit(&self, tx: bool) -> bool {
        let s = &*self.shared;
        let (dropper, passed, dropped) = if tx {
            (&s.tx, &s.tx_passed, &s.tx_dropped)
        } else {
            (&s.rx, &s.rx_passed, &s.rx_dropped)
        };
        let pass = s.up() && !lock(dropper).drops();
        Shared::count(if pass { passed } else { dropped });
        pass
    }

    fn forwarder(&self) -> &mpsc::UnboundedSender<(Instant, CanFrame)> {
        self.tx_queue.get_or_init(|| {
            let (tx, mut rx) = mpsc::unbounded_channel::<(Instant, CanFrame)>();
            let inner = self.inner.clone();
            let shared = self.shared.clone();
            tokio::spawn(async move {
                while let Some((due, frame)) = rx.recv().await {
                    tokio::time::sleep_until(due).await;
                    if !shared.up() {
                        recount_as_dropped(&shared.tx_passed, &shared.tx_dropped);
                        continue;
                    }
                    if let Err(e) = inner.send(&frame).await {
                        tracing::warn!("delayed send of {frame} failed: {e}");
                    }
                }
            });
            tx
        })
    }
}

/// A frame admitted earlier was lost in flight (link cut during its delay): move its count.
fn recount_as_dropped(passed: &AtomicU64, dropped: &AtomicU64) {
    passed.fetch_sub(1, Ordering::Relaxed);
    dropped.fetch_add(1, Ordering::Relaxed);
}

impl<T: CanTransport> CanTransport for Faulty<T> {
    async fn send(&self, frame: &CanFrame) -> Result<(), CanError> {
        if !self.admit(true) {
            return Ok(());
        }
        let delay = lock(&self.shared.tx).faults.delay;
        if delay.is_zero() {
            return self.inner.send(frame).await;
        }
        self.forwarder()
            .send((Instant::now() + delay, *frame))
            .map_err(|_| CanError::Closed)
    }

    async fn recv(&self) -> Result<CanFrame, CanError> {
        let mut queue = self.rx_queue.lock().await;
        loop {
            if let Some(&(due, frame)) = queue.front() {
                if Instant::now() >= due {
                    queue.pop_front();
                    if self.shared.up() {
                        return Ok(frame);
                    }
                    recount_as_dropped(&self.shared.rx_passed, &self.shared.rx_dropped);
                    continue;
                }
                tokio::select! {
                    _ = tokio::time::sleep_until(due) => {}
                    r = self.inner.recv() => {
                        let f = r?;
                        if self.admit(false) {
                            let delay = lock(&self.shared.rx).faults.delay;
                            queue.push_back((Instant::now() + delay, f));
                        }
                    }
                }
            } else {
                let f = self.inner.recv().await?;
                if self.admit(false) {
                    let delay = lock(&self.shared.rx).faults.delay;
                    if delay.is_zero() {
                        return Ok(f);
                    }
                    queue.push_back((Instant::now() + delay, f));
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dropper(f: Faults, seed: u64) -> Dropper {
        let mut d = Dropper::new(Xorshift::new(seed, 0));
        d.faults = f;
        d
    }

    /// The stream is the documented one (values from an independent Python of the formula).
    #[test]
    fn the_random_stream_is_the_documented_xorshift64_star() {
        let mut r = Xorshift::new(2024, RX_STREAM);
        let got: Vec<f64> = (0..4).map(|_| r.unit()).collect();
        assert_eq!(
            got,
            [
                0.7415143008375686,
                0.2530152719881609,
                0.14178793876460116,
                0.9113456998088905
            ]
        );
        // Seed 0 of stream 0 would be xorshift's fixed point 0: it starts at 1 instead.
        let mut zero = Xorshift::new(0, 0);
        assert_eq!(zero.unit(), 0.28083505005035947);
    }

    #[test]
    fn drop_every_n_drops_the_nth_frames() {
        let mut d = dropper(
            Faults {
                drop_every: 3,
                ..Faults::NONE
            },
            1,
        );
        let pattern: Vec<bool> = (0..9).map(|_| d.drops()).collect();
        assert_eq!(
            pattern,
            [false, false, true, false, false, true, false, false, true]
        );
    }

    #[test]
    fn random_drops_follow_the_seeded_stream() {
        let p = 0.25;
        let mut d = dropper(
            Faults {
                drop_probability: p,
                ..Faults::NONE
            },
            77,
        );
        let mut reference = Xorshift::new(77, 0);
        let got: Vec<bool> = (0..1000).map(|_| d.drops()).collect();
        let want: Vec<bool> = (0..1000).map(|_| reference.unit() < p).collect();
        assert_eq!(got, want);
        let n = got.iter().filter(|&&x| x).count();
        // binomial(1000, 0.25): mean 250, sd 13.7; the seed is fixed, this guards the rate
        assert!((200..300).contains(&n), "{n} drops");
        let mut all = dropper(
            Faults {
                drop_probability: 1.0,
                ..Faults::NONE
            },
            3,
        );
        assert!((0..100).all(|_| all.drops()));
        let mut none = dropper(Faults::NONE, 3);
        assert!((0..100).all(|_| !none.drops()));
    }
}
