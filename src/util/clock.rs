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
}
