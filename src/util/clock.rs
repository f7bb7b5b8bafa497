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

/// Wall times that never step back, for ordering what the service measures (issue 24): a
/// knock found at a return to the zero reaches back to every capture since the last return
/// that agreed by their times, and a wall clock stepped back by an hour between the two put
/// the captures before it: three captures read through a 13 µrad turn were kept. Each stamp
/// is the wall clock's, or, where that stepped back, the last stamp plus the monotonic time
/// since; it runs on from there until the wall clock catches up. A step forward is followed.
/// `floor` keeps stamps after what a service before a restart stamped. Sans-I/O.
#[derive(Clone, Copy, Debug, Default)]
pub struct SteadyWall {
    last: Option<(Instant, i64)>,
    floor_us: i64,
}

impl SteadyWall {
    /// No stamp from now on at or before `us` (what was stamped before a restart).
    pub fn floor(&mut self, us: i64) {
        self.floor_us = self.floor_us.max(us);
    }

    /// The stamp of an event at monotonic `at` that the wall clock put at `wall_us`.
    pub fn stamp(&mut self, at: Instant, wall_us: i64) -> i64 {
        let steady = self.last.map(|(t, us)| {
            let dt = i64::try_from(at.saturating_duration_since(t).as_micros()).unwrap_or(i64::MAX);
            us.saturating_add(dt)
        });
        let floor = if self.floor_us > 0 {
            self.floor_us.saturating_add(1)
        } else {
            i64::MIN
        };
        let us = wall_us.max(steady.unwrap_or(i64::MIN)).max(floor);
        self.last = Some((at, us));
        us
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn steady_wall_times_never_step_back_and_follow_a_step_forward() {
        let t0 = Instant::now();
        let at = |ms: u64| t0 + Duration::from_millis(ms);
        let mut w = SteadyWall::default();
        let base = 1_700_000_000_000_000_i64;
        assert_eq!(w.stamp(at(0), base), base);
        assert_eq!(w.stamp(at(2), base + 2_000), base + 2_000);
        // The wall clock steps back an hour: the stamps run on by the monotonic clock.
        let back = base - 3_600_000_000;
        assert_eq!(w.stamp(at(4), back + 4_000), base + 4_000);
        assert_eq!(w.stamp(at(6), back + 6_000), base + 6_000);
        // Two events at one instant share a stamp.
        assert_eq!(w.stamp(at(6), back + 6_000), base + 6_000);
        // Forward by an hour: followed.
        let fwd = base + 3_600_000_000;
        assert_eq!(w.stamp(at(8), fwd), fwd);
        // After a restart, nothing at or before what the last service stamped.
        let mut w = SteadyWall::default();
        w.floor(fwd);
        assert_eq!(w.stamp(at(10), back), fwd + 1);
        assert_eq!(w.stamp(at(12), back + 2_000), fwd + 2_001);
    }

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
