//! Where the carriage is, in the follower's encoder coordinates, from PSD2's spot and the
//! follower's time-stamped positions.
//!
//! A frame's spot on PSD2 is the carriage minus the follower *at the frame's time*, so the
//! carriage is `follower(t) + x2(t)`. The follower's position is known only at its samples
//! (the drive samples its TPDO at each SYNC, and the report arrives later — on a loaded
//! machine tens of milliseconds later, with SYNCs late too). Taking "the follower now" from
//! the latest report, or extrapolating it, puts every error of that guess straight into the
//! carriage; a follower driven from that carriage then feeds its own motion back into its
//! target, and the loop oscillates. So a frame waits until the follower has a sample at or
//! after its time, and the follower is interpolated between the samples around it: the
//! follower's own motion cancels out of the carriage, whatever it does. While the follower
//! stands still (its last samples agree and its target is reached) a frame needs no wait.
//!
//! The carriage samples are fitted by a straight line over a short window (least squares):
//! the line gives the carriage's velocity, and the position moved on to the latest frame's
//! time, for a bounded time (a follower whose reports stop does not make a carriage run
//! away). Pure: time is an argument.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// The carriage is fitted over this much of its history.
pub const FIT_WINDOW: Duration = Duration::from_millis(50);
/// A frame waits at most this long for the follower's sample after it, then is dropped.
pub const MAX_WAIT: Duration = Duration::from_millis(120);
/// The fit is moved on by at most this long past its newest sample.
pub const MAX_EXTRAPOLATION: Duration = Duration::from_millis(100);
/// Follower samples kept (enough to place any frame still waiting).
const REPORTS_KEPT: Duration = Duration::from_millis(300);

/// The carriage's position and velocity (encoder coordinates).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CarriageFix {
    /// Position (mm) at the time asked for.
    pub position_mm: f64,
    /// Velocity (mm/s).
    pub velocity_mm_s: f64,
    /// Carriage samples in the fit.
    pub samples: usize,
}

/// The estimator (see the module documentation).
#[derive(Clone, Debug, Default)]
pub struct CarriageEstimator {
    /// Follower samples (time, encoder mm), in time order.
    reports: VecDeque<(Instant, f64)>,
    /// The follower stands still at its latest sample.
    still: bool,
    /// Frames waiting for a follower sample at or after their time: (time, X2 mm).
    pending: VecDeque<(Instant, f64)>,
    /// Carriage positions (time, mm), in time order.
    samples: VecDeque<(Instant, f64)>,
    /// The latest frame's time (frames out of order are ignored).
    last_frame: Option<Instant>,
}

impl CarriageEstimator {
    /// Forget everything (the follower's coordinates may jump: homing, not ready).
    pub fn clear(&mut self) {
        *self = CarriageEstimator::default();
    }

    /// A follower sample: at `at` the encoder read `mm`; `still` when it stands (its target
    /// reached).
    pub fn handle_follower(&mut self, at: Instant, mm: f64, still: bool) {
        if !mm.is_finite() {
            return;
        }
        match self.reports.back_mut() {
            Some(last) if at < last.0 => return,
            Some(last) if at == last.0 => last.1 = mm,
            _ => self.reports.push_back((at, mm)),
        }
        self.still =
            still && self.reports.len() >= 2 && self.reports[self.reports.len() - 2].1 == mm;
        while self.reports.len() > 2
            && self
                .reports
                .front()
                .is_some_and(|(t, _)| at.saturating_duration_since(*t) > REPORTS_KEPT)
        {
            self.reports.pop_front();
        }
        self.resolve();
    }

    /// A frame at `at` with PSD2's spot at `x2_mm` along the follower axis.
    pub fn handle_frame(&mut self, at: Instant, x2_mm: f64) {
        if !x2_mm.is_finite() || self.last_frame.is_some_and(|t| at <= t) {
            return;
        }
        self.last_frame = Some(at);
        self.pending.push_back((at, x2_mm));
        while self
            .pending
            .front()
            .is_some_and(|(t, _)| at.saturating_duration_since(*t) > MAX_WAIT)
        {
            self.pending.pop_front();
        }
        self.resolve();
    }

    /// The follower at `t` by its samples: interpolated between the two around it; `None`
    /// after the latest (unless it stands still) or before the earliest.
    fn follower_at(&self, t: Instant) -> Option<f64> {
        let &(t1, p1) = self.reports.back()?;
        if t >= t1 {
            return (t == t1 || self.still).then_some(p1);
        }
        let k = self.reports.partition_point(|(tr, _)| *tr <= t);
        if k == 0 {
            return None;
        }
        let (ta, pa) = self.reports[k - 1];
        let (tb, pb) = self.reports[k];
        let span = tb.saturating_duration_since(ta).as_secs_f64();
        if span <= 0.0 {
            return Some(pb);
        }
        let f = t.saturating_duration_since(ta).as_secs_f64() / span;
        Some(pa + (pb - pa) * f)
    }

    /// Turn the frames the follower's samples now cover into carriage samples.
    fn resolve(&mut self) {
        while let Some(&(t, x2)) = self.pending.front() {
            let Some(f) = self.follower_at(t) else {
                if self.reports.front().is_some_and(|(t0, _)| t < *t0) {
                    // Older than every sample: it cannot be placed.
                    self.pending.pop_front();
                    continue;
                }
                break;
            };
            self.pending.pop_front();
            self.samples.push_back((t, f + x2));
        }
        if let Some(&(newest, _)) = self.samples.back() {
            while self
                .samples
                .front()
                .is_some_and(|(t, _)| newest.saturating_duration_since(*t) > FIT_WINDOW)
            {
                self.samples.pop_front();
            }
        }
    }

    /// The carriage at `now`: the least-squares line through the samples of the last
    /// `FIT_WINDOW`, moved on to `now` (by at most `MAX_EXTRAPOLATION` past the newest
    /// sample). One sample, or samples spanning under a fifth of the window, give no
    /// velocity.
    pub fn estimate(&self, now: Instant) -> Option<CarriageFix> {
        let &(newest, last) = self.samples.back()?;
        let n = self.samples.len();
        let (t0, _) = self.samples[0];
        let span = newest.saturating_duration_since(t0);
        if n < 3 || span < FIT_WINDOW / 5 {
            return Some(CarriageFix {
                position_mm: last,
                velocity_mm_s: 0.0,
                samples: n,
            });
        }
        let ts = |t: Instant| t.saturating_duration_since(t0).as_secs_f64();
        let nf = n as f64;
        let (mut st, mut sc) = (0.0, 0.0);
        for &(t, c) in &self.samples {
            st += ts(t);
            sc += c;
        }
        let (tm, cm) = (st / nf, sc / nf);
        let (mut stt, mut stc) = (0.0, 0.0);
        for &(t, c) in &self.samples {
            let dt = ts(t) - tm;
            stt += dt * dt;
            stc += dt * (c - cm);
        }
        let v = if stt > 0.0 { stc / stt } else { 0.0 };
        let ahead = now.min(newest + MAX_EXTRAPOLATION);
        let position_mm = cm + v * (ts(ahead.max(t0)) - tm);
        Some(CarriageFix {
            position_mm,
            velocity_mm_s: v,
            samples: n,
        })
    }

    /// The newest carriage sample's time.
    pub fn newest(&self) -> Option<Instant> {
        self.samples.back().map(|(t, _)| *t)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(t0: Instant, n: f64) -> Instant {
        t0 + Duration::from_secs_f64(n / 1e3)
    }

    /// A frame is placed by the follower's samples around it, not by the latest one: the
    /// follower's motion cancels out of the carriage, even when its samples come late.
    #[test]
    fn frames_wait_for_the_follower_sample_after_them() {
        let t0 = crate::util::clock::now();
        let mut e = CarriageEstimator::default();
        // Carriage at 30 mm/s from 1 mm; the follower at 40 mm/s from 0 (catching up).
        let carriage = |t: f64| 1.0 + 0.03 * t;
        let follower = |t: f64| 0.04 * t;
        e.handle_follower(ms(t0, 0.0), follower(0.0), false);
        for k in 1..=25 {
            let t = 2.0 * k as f64;
            e.handle_frame(ms(t0, t), carriage(t) - follower(t));
        }
        // No sample after the frames yet: nothing known but nothing wrong either.
        assert_eq!(e.estimate(ms(t0, 50.0)), None);
        // The SYNC at 40 ms reported late (at 50 ms): frames up to 40 ms placed exactly.
        e.handle_follower(ms(t0, 40.0), follower(40.0), false);
        let fix = e.estimate(ms(t0, 50.0)).expect("fix");
        assert!((fix.velocity_mm_s - 30.0).abs() < 1e-6, "{fix:?}");
        assert!((fix.position_mm - carriage(50.0)).abs() < 1e-9, "{fix:?}");
        // Extrapolation is bounded.
        let far = e.estimate(ms(t0, 1000.0)).expect("fix");
        assert!((far.position_mm - carriage(40.0 + 100.0)).abs() < 1e-9);
    }

    /// A follower standing still needs no wait; frames older than every sample are dropped;
    /// late frames out of order are ignored.
    #[test]
    fn a_still_follower_places_frames_at_once() {
        let t0 = crate::util::clock::now();
        let mut e = CarriageEstimator::default();
        e.handle_frame(ms(t0, 0.0), 0.5);
        e.handle_follower(ms(t0, 5.0), 2.0, true);
        e.handle_follower(ms(t0, 10.0), 2.0, true);
        assert_eq!(
            e.estimate(ms(t0, 10.0)),
            None,
            "the frame before every sample"
        );
        for k in 0..20 {
            e.handle_frame(ms(t0, 12.0 + 2.0 * k as f64), 0.25);
        }
        e.handle_frame(ms(t0, 11.0), 9.0);
        let fix = e.estimate(ms(t0, 50.0)).expect("fix");
        assert_eq!(fix.samples, 20);
        assert!((fix.position_mm - 2.25).abs() < 1e-12 && fix.velocity_mm_s.abs() < 1e-9);
        // Moving again (target not reached): frames wait.
        e.handle_follower(ms(t0, 52.0), 2.1, false);
        e.handle_frame(ms(t0, 54.0), 0.15);
        assert_eq!(e.estimate(ms(t0, 54.0)).expect("fix").samples, 20);
        e.clear();
        assert_eq!(e.estimate(ms(t0, 54.0)), None);
    }
}
