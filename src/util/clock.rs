//! The one clock (DESIGN §5, "Time and the disk"): everything in the service, the procedures
//! and the twin that reads the time reads it here.
//!
//! It is tokio's clock. In the service it is the monotonic clock. In a test on a paused
//! runtime (`#[tokio::test(start_paused = true)]`) it is simulated: it stands still while any
//! task is ready to run and jumps to the next timer when none is, so the service and the twin
//! in one runtime run exactly, whatever else the machine is doing, and as fast as they can.
//! Outside a runtime it is the monotonic clock. Work on other threads is not waited for
//! (`spawn_blocking` is: tokio does not advance a paused clock while a blocking task runs).
//!
//! Sans-I/O state machines never call it: they take `now` as an argument.

use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// Now.
pub fn now() -> Instant {
    tokio::time::Instant::now().into_std()
}

/// How long since `t` (zero for a `t` in the future).
pub fn since(t: Instant) -> Duration {
    now().saturating_duration_since(t)
}

/// The wall clock at [`now`]: the system's, moved by as far as a paused clock has been
/// advanced beyond the monotonic one (no move on a real clock). So wall times stamped on a
/// simulated clock are as far apart as their instants, and a step of the system clock still
/// shows.
pub fn wall() -> SystemTime {
    let (sim, real, sys) = (now(), Instant::now(), SystemTime::now());
    match sim.checked_duration_since(real) {
        Some(ahead) => sys.checked_add(ahead).unwrap_or(sys),
        None => sys
            .checked_sub(real.saturating_duration_since(sim))
            .unwrap_or(sys),
    }
}

/// [`wall`] in µs since the Unix epoch (0 before it).
pub fn unix_us() -> i64 {
    unix_us_of(wall())
}

/// A wall time in µs since the Unix epoch (0 before it).
pub fn unix_us_of(t: SystemTime) -> i64 {
    t.duration_since(UNIX_EPOCH)
        .map(|d| i64::try_from(d.as_micros()).unwrap_or(i64::MAX))
        .unwrap_or(0)
}

/// When a frame was read: by the monotonic clock, which orders frames, and by the wall clock,
/// which names them for people and the store. The wall clock can step back (an NTP
/// correction, a clock set by hand): what came before what is never judged by it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Stamp {
    pub at: Instant,
    pub unix_us: i64,
}

impl Stamp {
    /// Where this frame stands in the order frames were read.
    pub fn order(&self) -> FrameTime {
        FrameTime::Read(self.at)
    }
}

/// A place in the order frames were read: a frame of this process by its monotonic time, or
/// a time kept from before a restart (wall clock, µs), which comes before every frame of this
/// process. Times kept are ordered among themselves by the wall clock they were stored with.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum FrameTime {
    Kept(i64),
    Read(Instant),
}

impl FrameTime {
    /// `d` earlier: a kept time by as much on the wall clock; a frame's so early that the
    /// monotonic clock cannot say it (the first moments after boot) before everything.
    pub fn earlier(self, d: Duration) -> FrameTime {
        let us = i64::try_from(d.as_micros()).unwrap_or(i64::MAX);
        match self {
            FrameTime::Kept(t) => FrameTime::Kept(t.saturating_sub(us)),
            FrameTime::Read(t) => t
                .checked_sub(d)
                .map_or(FrameTime::Kept(i64::MIN), FrameTime::Read),
        }
    }
}

/// A frame read `us` µs after a fixed instant, the wall clock reading `us` too: for tests of
/// the state machines that take frames' stamps.
#[cfg(test)]
pub fn stamp_us(us: i64) -> Stamp {
    static BASE: std::sync::OnceLock<Instant> = std::sync::OnceLock::new();
    // An hour ahead of the first call, so that times a little before zero can be said.
    let base = *BASE.get_or_init(|| Instant::now() + Duration::from_secs(3600));
    let d = Duration::from_micros(us.unsigned_abs());
    let at = if us >= 0 { base + d } else { base - d };
    Stamp { at, unix_us: us }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On a paused runtime the clock moves only as the runtime advances it, and the wall
    /// clock moves with it.
    #[tokio::test(start_paused = true)]
    async fn a_paused_clock_moves_by_the_timers() {
        let (t0, w0) = (now(), unix_us());
        tokio::time::sleep(Duration::from_secs(3600)).await;
        assert_eq!(since(t0), Duration::from_secs(3600));
        let dw = unix_us() - w0;
        // The real time the test took is on top (well under a second).
        assert!((3_599_999_000..3_601_000_000).contains(&dw), "{dw} µs");
    }

    #[test]
    fn outside_a_runtime_it_is_the_monotonic_clock() {
        let a = Instant::now();
        let b = now();
        let c = Instant::now();
        assert!(a <= b && b <= c);
        assert!((unix_us() - unix_us_of(SystemTime::now())).abs() < 1_000_000);
    }

    /// Frames order by their monotonic time, whatever the wall clock did; a time kept from
    /// before a restart comes before every frame of this process.
    #[test]
    fn frames_order_by_the_monotonic_clock_and_kept_times_before_them() {
        let t = Instant::now() + Duration::from_secs(10);
        let later = Stamp {
            at: t + Duration::from_millis(2),
            unix_us: 1_000,
        };
        let earlier = Stamp {
            at: t,
            unix_us: 3_600_000_000,
        };
        assert!(
            later.order() > earlier.order(),
            "a wall clock stepped back an hour"
        );
        assert!(FrameTime::Kept(i64::MAX) < earlier.order());
        assert!(FrameTime::Kept(5) < FrameTime::Kept(6));
        assert_eq!(
            later.order().earlier(Duration::from_millis(2)),
            earlier.order()
        );
        assert_eq!(
            FrameTime::Kept(1_000).earlier(Duration::from_millis(2)),
            FrameTime::Kept(-1_000)
        );
    }
}
