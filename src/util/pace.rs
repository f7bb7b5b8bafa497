//! A fixed-rate pacer for polling loops that costs one wake-up per period.
//!
//! `tokio::time::Interval` re-arms its timer when it is next polled. If no other timer is due
//! sooner, the runtime's time driver has to be woken to shorten its sleep (an eventfd write
//! and an extra `epoll_wait` on every tick: at 500 Hz a visible share of the service's CPU).
//! The pacer keeps the following deadline armed one period ahead on a second timer, so
//! re-arming a fired timer never moves the driver's next wake-up earlier. Missed ticks are
//! skipped, never bunched, as with `MissedTickBehavior::Skip`.
//!
//! Every pacer ticks on the process-wide grid `origin() + n·period`, and the CANopen SYNC
//! producer is aligned to the same origin: when one period is a multiple of the other (2 ms
//! acquisition, 10 ms SYNC), their deadlines coincide and the runtime wakes once for both.

use std::pin::Pin;
use std::sync::OnceLock;
use std::time::Duration;
use tokio::time::{Instant, Sleep, sleep_until};

/// The process-wide origin of the pacing grids (the first call's time). Call it just before
/// building the runtime whose timers pace on it: tokio's timer rounds deadlines up to whole
/// milliseconds from its start, and a grid that starts just before that keeps its points just
/// before the timer's ticks (fired on time) instead of up to a millisecond after them.
pub fn origin() -> std::time::Instant {
    static ORIGIN: OnceLock<std::time::Instant> = OnceLock::new();
    *ORIGIN.get_or_init(std::time::Instant::now)
}

/// The first point of the grid `origin + n·period` at or after `now` (`now` itself when it
/// is before `origin`).
pub fn grid_point_at_or_after(
    origin: std::time::Instant,
    now: std::time::Instant,
    period: Duration,
) -> std::time::Instant {
    let Some(since) = now.checked_duration_since(origin) else {
        return now;
    };
    let p = period.as_nanos().max(1);
    let n = since.as_nanos().div_ceil(p);
    match u32::try_from(n) {
        Ok(n) => origin + period * n,
        // Beyond u32 periods since the origin: stay off the grid rather than overflow.
        Err(_) => now,
    }
}

/// Ticks at `start`, `start + period`, … on two alternating timers.
pub struct Pacer {
    period: Duration,
    /// `timers[next]` is armed for `due`, the other one for `due + period`.
    timers: [Pin<Box<Sleep>>; 2],
    next: usize,
    due: Instant,
}

impl Pacer {
    /// A pacer whose first tick is the first point of its grid from now on (within a
    /// period). `period` must be non-zero.
    pub fn new(period: Duration) -> Pacer {
        let period = period.max(Duration::from_micros(1));
        let now = Instant::from_std(grid_point_at_or_after(
            origin(),
            Instant::now().into_std(),
            period,
        ));
        Pacer {
            period,
            timers: [
                Box::pin(sleep_until(now)),
                Box::pin(sleep_until(now + period)),
            ],
            next: 0,
            due: now,
        }
    }

    /// Wait for the next tick; returns its scheduled time.
    pub async fn tick(&mut self) -> Instant {
        self.timers[self.next].as_mut().await;
        let fired = self.due;
        match next_due(fired, Instant::now(), self.period) {
            Next::OnTime(following) => {
                // The other timer already waits for `following`; this one takes the tick
                // after it, later than anything the driver is already waiting for.
                self.timers[self.next]
                    .as_mut()
                    .reset(following + self.period);
                self.next = 1 - self.next;
                self.due = following;
            }
            Next::Realign(due) => {
                self.timers[0].as_mut().reset(due);
                self.timers[1].as_mut().reset(due + self.period);
                self.next = 0;
                self.due = due;
            }
        }
        fired
    }
}

/// What follows a tick scheduled at `fired` and seen at `now`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Next {
    /// The next tick on the grid, not yet due.
    OnTime(Instant),
    /// Late by a period or more: the missed ticks are skipped, this is the first grid
    /// point after `now`.
    Realign(Instant),
}

fn next_due(fired: Instant, now: Instant, period: Duration) -> Next {
    let following = fired + period;
    if now < following {
        return Next::OnTime(following);
    }
    let missed = (now - fired).as_nanos() / period.as_nanos().max(1);
    Next::Realign(fired + period * u32::try_from(missed + 1).unwrap_or(u32::MAX))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_grid_is_kept_and_missed_ticks_are_skipped() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let p = ms(2);
        // Seen within the period: the next grid point.
        assert_eq!(next_due(t0, t0, p), Next::OnTime(t0 + ms(2)));
        assert_eq!(next_due(t0, t0 + ms(1), p), Next::OnTime(t0 + ms(2)));
        // Seen exactly at the next point: that one is missed too (it is due now, so it
        // would fire at once, bunched).
        assert_eq!(next_due(t0, t0 + ms(2), p), Next::Realign(t0 + ms(4)));
        // 5 ms late: 2 and 4 skipped, 6 is the first after now.
        assert_eq!(next_due(t0, t0 + ms(5), p), Next::Realign(t0 + ms(6)));
    }

    #[test]
    fn grid_points_are_multiples_of_the_period_from_the_origin() {
        let o = crate::util::clock::now();
        let ms = Duration::from_millis;
        assert_eq!(grid_point_at_or_after(o, o, ms(2)), o);
        assert_eq!(grid_point_at_or_after(o, o + ms(3), ms(2)), o + ms(4));
        assert_eq!(grid_point_at_or_after(o, o + ms(4), ms(2)), o + ms(4));
        assert_eq!(
            grid_point_at_or_after(o, o + Duration::from_nanos(10_000_001), ms(10)),
            o + ms(20)
        );
        // Before the origin: no grid yet.
        let before = crate::util::clock::now();
        let later = before + ms(5);
        assert_eq!(grid_point_at_or_after(later, before, ms(2)), before);
    }

    #[tokio::test]
    async fn ticks_on_the_grid() {
        let p = Duration::from_millis(3);
        let mut pacer = Pacer::new(p);
        let t0 = pacer.tick().await;
        for k in 1..4u32 {
            let at = pacer.tick().await;
            // Scheduled times are exact multiples unless the test thread was late by a
            // whole period (then the grid still holds), on the process-wide grid.
            assert_eq!((at - t0).as_nanos() % p.as_nanos(), 0, "tick {k}");
            assert_eq!(
                (at.into_std() - origin()).as_nanos() % p.as_nanos(),
                0,
                "tick {k}"
            );
            assert!(Instant::now() >= at);
        }
    }
}
