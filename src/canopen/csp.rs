//! Following in cyclic synchronous position (CSP, mode 8), the master's side: [`TargetTrack`]
//! turns the tracker's time-stamped follow targets into a goal and its velocity at each SYNC,
//! and [`DemandRamp`] moves the position demand toward that goal within a velocity and an
//! acceleration limit, so that a jump in the target never asks the drive for an impossible
//! step.
//!
//! Scope: pure values (positions in mm, velocities in mm/s, time as an argument), no I/O.
//! The law is time-optimal tracking with feed-forward: the target's own velocity is estimated
//! from its change between steps, and the demand closes the remaining gap along the discrete
//! braking curve of the acceleration limit, so it lands on a target moving at constant speed
//! with no lag and stops on a static one without overshoot. An optional lead aims at where the
//! target will be that much later (its estimated velocity times the lead), to make up for a
//! drive that reaches each demand only at the next SYNC. A target that stops more abruptly
//! than the limit allows is overshot and returned to; the limits are never exceeded. Travel
//! bounds are walls the demand brakes for in the same way.

use std::time::{Duration, Instant};

/// The follow targets as the tracker sends them, each for a moment (`at`): at a SYNC, where
/// the target is then and how fast it moves.
///
/// The velocity comes from targets about a SYNC period apart (at least a quarter period, so
/// that close samples do not make a noisy estimate). It is used, and the latest target moved
/// on by it to the SYNC's time, only while it is plausible: it changed by no more than twice
/// the acceleration limit allows in the time between the estimates (a jump of the target is a
/// jump, not a velocity), and the tracker is still sending (the latest target is at most two
/// SYNC periods old: a late target is moved on, one that stopped coming is not). Otherwise the
/// target is taken as standing where it was last put.
///
/// A target pushed with its velocity (`push_moving`: the caller measured it, e.g. the carriage
/// the follower follows) needs no estimate: it is moved on by that velocity to the SYNC's
/// time, however late the SYNC or the target (a loaded machine delays both by tens of
/// milliseconds; taking a late moving target as standing would pull the demand back), for at
/// most [`EXTRAPOLATE_PERIODS`] SYNC periods; it then stands where that took it.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TargetTrack {
    latest: Option<(f64, Instant)>,
    /// The latest target's velocity (mm/s) as the caller gave it.
    given_vel: Option<f64>,
    /// The target the velocity was last estimated from.
    reference: Option<(f64, Instant)>,
    vel: f64,
    /// The velocity is believed.
    plausible: bool,
}

/// A target pushed with its velocity is moved on by it for at most this many SYNC periods.
pub const EXTRAPOLATE_PERIODS: u32 = 10;

impl TargetTrack {
    /// A target for time `at` (a target older than the latest is ignored).
    pub fn push(&mut self, mm: f64, at: Instant) {
        if self.latest.is_some_and(|(_, prev)| at < prev) {
            return;
        }
        self.latest = Some((mm, at));
        self.given_vel = None;
    }

    /// A target for time `at` moving at `vel` (mm/s; a non-finite velocity is none).
    pub fn push_moving(&mut self, mm: f64, vel: f64, at: Instant) {
        if self.latest.is_some_and(|(_, prev)| at < prev) {
            return;
        }
        self.latest = Some((mm, at));
        self.given_vel = vel.is_finite().then_some(vel);
    }

    /// The latest target.
    pub fn latest(&self) -> Option<f64> {
        self.latest.map(|(mm, _)| mm)
    }

    /// At a SYNC at `now`: the target then and its velocity (see the type), with `period` the
    /// SYNC period, `vmax` and `amax` the limits.
    pub fn goal(
        &mut self,
        now: Instant,
        period: Duration,
        vmax: f64,
        amax: f64,
    ) -> Option<(f64, f64)> {
        let (mm, at) = self.latest?;
        if let Some(v) = self.given_vel {
            let v = v.clamp(-vmax, vmax);
            self.reference = Some((mm, at));
            self.vel = v;
            self.plausible = true;
            let age = now.saturating_duration_since(at);
            let horizon = period * EXTRAPOLATE_PERIODS;
            return Some(if age > horizon {
                (mm + v * horizon.as_secs_f64(), 0.0)
            } else {
                (mm + v * age.as_secs_f64(), v)
            });
        }
        match self.reference {
            Some((pmm, pat)) if at > pat => {
                let dt = (at - pat).as_secs_f64();
                if dt >= period.as_secs_f64() / 4.0 {
                    let v = ((mm - pmm) / dt).clamp(-vmax, vmax);
                    self.plausible = (v - self.vel).abs() <= 2.0 * amax * dt;
                    self.vel = v;
                    self.reference = Some((mm, at));
                }
            }
            Some(_) => {}
            None => self.reference = Some((mm, at)),
        }
        let age = now.saturating_duration_since(at);
        if !self.plausible || age > period * 2 {
            return Some((mm, 0.0));
        }
        Some((mm + self.vel * age.as_secs_f64(), self.vel))
    }
}

/// The demand generator (see the module documentation).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DemandRamp {
    pos: f64,
    vel: f64,
    goal: f64,
    /// The goal at the previous step: the target's velocity is estimated from it.
    prev_goal: f64,
    /// The target's velocity when the caller knows it (else estimated from the goal's change).
    goal_vel: Option<f64>,
    vmax: f64,
    amax: f64,
    lo: f64,
    hi: f64,
    /// Aim this far ahead (s) along the target's estimated velocity.
    lead: f64,
}

/// The largest speed for this step from which braking at `h` per step (`h = a·dt`, stepping
/// `x += v·dt` after each velocity change) covers no more than `s`: the steps are `v`,
/// `v − h`, … down to a last one of at most `h`, which lands. With `q` whole decrements the
/// distance is `dt·(q+1)·(r + q·h/2)` for `v = q·h + r`, `0 ≤ r ≤ h`; `q` is the largest
/// whole number with `dt·h·q(q+1)/2 ≤ s`.
fn braking_speed(s: f64, h: f64, dt: f64) -> f64 {
    if !(s > 0.0 && h > 0.0 && dt > 0.0) {
        return 0.0;
    }
    if s.is_infinite() {
        return f64::INFINITY;
    }
    let n = (0.25 + 2.0 * s / (h * dt)).sqrt() - 0.5;
    let mut q = n.floor().max(0.0);
    if dt * h * q * (q + 1.0) / 2.0 > s && q > 0.0 {
        q -= 1.0;
    }
    let r = (s / (dt * (q + 1.0)) - q * h / 2.0).clamp(0.0, h);
    q * h + r
}

impl DemandRamp {
    /// At rest at `pos`, with limits `vmax` (mm/s) and `amax` (mm/s²), inside `lo..=hi` (mm).
    /// Non-finite or negative limits are taken as 0 (the demand then stays where it is); a NaN
    /// bound as no bound.
    pub fn new(pos: f64, vmax: f64, amax: f64, lo: f64, hi: f64) -> Self {
        let clean = |v: f64| if v.is_finite() && v > 0.0 { v } else { 0.0 };
        let lo = if lo.is_nan() { f64::NEG_INFINITY } else { lo };
        let hi = if hi.is_nan() { f64::INFINITY } else { hi };
        let (lo, hi) = if lo <= hi { (lo, hi) } else { (hi, lo) };
        DemandRamp {
            pos,
            vel: 0.0,
            goal: pos,
            prev_goal: pos,
            goal_vel: None,
            vmax: clean(vmax),
            amax: clean(amax),
            lo,
            hi,
            lead: 0.0,
        }
    }

    /// Aim `lead` seconds ahead of the target along its estimated velocity (0: none;
    /// negative or non-finite values are taken as 0).
    pub fn with_lead(mut self, lead: f64) -> Self {
        self.lead = if lead.is_finite() && lead > 0.0 {
            lead
        } else {
            0.0
        };
        self
    }

    /// The current demand (mm).
    pub fn pos(&self) -> f64 {
        self.pos
    }

    /// The demand's velocity over the last step (mm/s).
    pub fn vel(&self) -> f64 {
        self.vel
    }

    pub fn goal(&self) -> f64 {
        self.goal
    }

    /// A new target, clamped to the bounds; its change since the last step is taken as the
    /// target's velocity.
    pub fn set_goal(&mut self, goal: f64) {
        if goal.is_finite() {
            self.goal = goal.clamp(self.lo, self.hi);
            self.goal_vel = None;
        }
    }

    /// A new target moving at `vel` (mm/s), as the caller measured it.
    pub fn set_goal_moving(&mut self, goal: f64, vel: f64) {
        self.set_goal(goal);
        if goal.is_finite() && vel.is_finite() {
            self.goal_vel = Some(vel);
        }
    }

    /// A target to stop at: no velocity is inferred from the jump to it.
    pub fn hold_at(&mut self, goal: f64) {
        self.set_goal(goal);
        self.prev_goal = self.goal;
    }

    /// Where the demand can come to rest braking at the acceleration limit (one step of
    /// margin, so braking there never needs more than the limit), within the bounds.
    pub fn stopping_point(&self, dt: f64) -> f64 {
        if self.amax <= 0.0 {
            return self.pos;
        }
        if self.vel == 0.0 {
            return self.pos;
        }
        let d = self.vel * self.vel / (2.0 * self.amax) + self.vel.abs() * dt.max(0.0);
        (self.pos + d.copysign(self.vel)).clamp(self.lo, self.hi)
    }

    /// At rest on its goal.
    pub fn at_rest(&self) -> bool {
        self.vel == 0.0 && self.pos == self.goal
    }

    /// Advance by `dt` seconds (the time since the previous SYNC); returns the new demand.
    pub fn step(&mut self, dt: f64) -> f64 {
        if !(dt.is_finite() && dt > 0.0) {
            return self.pos;
        }
        let (vmax, dv) = (self.vmax, self.amax * dt);
        let vt = self
            .goal_vel
            .unwrap_or((self.goal - self.prev_goal) / dt)
            .clamp(-vmax, vmax);
        self.prev_goal = self.goal;
        let goal = (self.goal + vt * self.lead).clamp(self.lo, self.hi);
        // Land on the goal in this step if that keeps both limits and the next step can go on
        // at the target's velocity.
        let vs = (goal - self.pos) / dt;
        let tol = dv * 1e-9 + 1e-12;
        if vs.abs() <= vmax + tol
            && (vs - self.vel).abs() <= dv + tol
            && (vs - vt).abs() <= dv + tol
        {
            self.vel = vs;
            self.pos = goal;
            if self.vel.abs() < 1e-12 && vt == 0.0 {
                self.vel = 0.0;
            }
            return self.pos;
        }
        // Close the gap relative to the moving target along the braking curve.
        let gap = goal - self.pos - vt * dt;
        let want = vt + gap.signum() * braking_speed(gap.abs(), dv, dt);
        // The bounds are walls to brake for.
        let up = braking_speed(self.hi - self.pos, dv, dt);
        let down = braking_speed(self.pos - self.lo, dv, dt);
        let want = want.clamp(-vmax, vmax).clamp(-down, up);
        self.vel += (want - self.vel).clamp(-dv, dv);
        self.pos = (self.pos + self.vel * dt).clamp(self.lo, self.hi);
        self.pos
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DT: f64 = 0.01;

    fn ramp(pos: f64) -> DemandRamp {
        DemandRamp::new(pos, 100.0, 1000.0, -1000.0, 1000.0)
    }

    /// Velocity and acceleration between successive demands stay within the limits.
    fn check_limits(traj: &[f64], vmax: f64, amax: f64, dt: f64) {
        let v: Vec<f64> = traj.windows(2).map(|w| (w[1] - w[0]) / dt).collect();
        for (k, x) in v.iter().enumerate() {
            assert!(x.abs() <= vmax + 1e-9, "step {k}: {x} mm/s");
        }
        for (k, w) in v.windows(2).enumerate() {
            let a = (w[1] - w[0]) / dt;
            assert!(a.abs() <= amax * (1.0 + 1e-9) + 1e-9, "step {k}: {a} mm/s²");
        }
    }

    /// A jump of the target from rest: the demand accelerates at a·dt per step, so after k
    /// steps it is at a·dt²·k(k+1)/2 (independent closed form), cruises at vmax and stops on
    /// the target without overshoot.
    #[test]
    fn step_target_accelerates_cruises_and_stops() {
        let mut r = ramp(0.0);
        r.set_goal(50.0);
        let mut traj = vec![0.0];
        for k in 1..=5 {
            let p = r.step(DT);
            let want = 1000.0 * DT * DT * (k * (k + 1)) as f64 / 2.0;
            assert!((p - want).abs() < 1e-9, "step {k}: {p} vs {want}");
            traj.push(p);
        }
        for _ in 0..200 {
            traj.push(r.step(DT));
        }
        check_limits(&traj, 100.0, 1000.0, DT);
        assert!(traj.iter().all(|p| *p <= 50.0), "no overshoot");
        assert!(r.at_rest() && r.pos() == 50.0, "{r:?}");
        // Cruise at vmax in the middle: 50 mm at 100 mm/s with 0.1 s ramps.
        let vmid = (traj[30] - traj[29]) / DT;
        assert!((vmid - 100.0).abs() < 1e-6, "{vmid}");
    }

    /// A target moving at constant speed is matched exactly once caught up (feed-forward).
    #[test]
    fn moving_target_is_tracked_without_lag() {
        let mut r = ramp(0.0);
        let mut traj = vec![0.0];
        let mut err = vec![];
        for k in 1..=200 {
            let g = 50.0 * k as f64 * DT;
            r.set_goal(g);
            traj.push(r.step(DT));
            err.push((g - r.pos()).abs());
        }
        check_limits(&traj, 100.0, 1000.0, DT);
        // Caught up within 0.2 s, then on the target every step.
        assert!(err[20..].iter().all(|e| *e < 1e-9), "{:?}", &err[..30]);
        // The target stops dead: the demand overshoots by about v²/2a and returns.
        let end = r.goal();
        for _ in 0..100 {
            traj.push(r.step(DT));
        }
        check_limits(&traj, 100.0, 1000.0, DT);
        let peak = traj.iter().cloned().fold(f64::MIN, f64::max);
        assert!(peak - end < 50.0 * 50.0 / 2000.0 + 0.1, "{peak}");
        assert!(r.at_rest() && r.pos() == end);
    }

    /// With a lead of one step the demand runs that far ahead of a steadily moving target
    /// (v·dt), and comes back to rest on it when it stops.
    #[test]
    fn lead_runs_ahead_of_a_moving_target() {
        let mut r = ramp(0.0).with_lead(DT);
        let mut traj = vec![0.0];
        let mut ahead = vec![];
        for k in 1..=100 {
            let g = 40.0 * k as f64 * DT;
            r.set_goal(g);
            traj.push(r.step(DT));
            ahead.push(r.pos() - g);
        }
        assert!(
            ahead[30..].iter().all(|a| (a - 40.0 * DT).abs() < 1e-9),
            "{:?}",
            &ahead[..40]
        );
        let end = r.goal();
        for _ in 0..100 {
            traj.push(r.step(DT));
        }
        check_limits(&traj, 100.0, 1000.0, DT);
        assert!(r.at_rest() && r.pos() == end);
    }

    /// A target velocity given by the caller replaces the estimate: a goal that jitters
    /// around a steady motion is followed smoothly when its velocity is known.
    #[test]
    fn known_target_velocity() {
        let mut r = ramp(0.0);
        for k in 1..=100 {
            r.set_goal_moving(30.0 * k as f64 * DT, 30.0);
            r.step(DT);
        }
        assert!((r.vel() - 30.0).abs() < 1e-9 && (r.pos() - 30.0).abs() < 1e-9);
        // A stale goal (jittered 2 ms back) with its known velocity: the demand keeps the
        // velocity rather than braking for the jitter.
        r.set_goal_moving(30.0 + 30.0 * (DT - 0.002), 30.0);
        r.step(DT);
        assert!((r.vel() - 30.0).abs() <= 1000.0 * DT + 1e-9);
    }

    /// Targets at 500 Hz moving at 40 mm/s, read at 100 Hz SYNCs 1 ms after the latest: the
    /// velocity once two estimates agree, the target moved on to the SYNC; a jump gives no
    /// velocity for that SYNC; a tracker gone quiet for two SYNC periods leaves the target
    /// standing.
    #[test]
    fn target_track_velocity_jumps_and_quiet() {
        let t0 = crate::util::clock::now();
        let ms = |n: u64| t0 + Duration::from_millis(n);
        let period = Duration::from_millis(10);
        let mut tr = TargetTrack::default();
        let mut goals = vec![];
        for k in 0..=40u64 {
            tr.push(40.0 * k as f64 * 0.002, ms(2 * k));
            if k % 5 == 0 {
                goals.push(tr.goal(ms(2 * k + 1), period, 100.0, 1000.0).unwrap());
            }
        }
        // The first estimate jumps from 0 to 40 mm/s (more than 2·a·dt = 20 mm/s): no
        // velocity; from the next one on, 40 mm/s and the target 1 ms on.
        assert_eq!(goals[0], (0.0, 0.0));
        assert_eq!(goals[1], (0.4, 0.0));
        for (j, &(g, v)) in goals.iter().enumerate().skip(2) {
            let at = (10 * j) as f64 * 0.001;
            assert!((v - 40.0).abs() < 1e-9, "{j}: {v}");
            assert!((g - 40.0 * (at + 0.001)).abs() < 1e-9, "{j}: {g}");
        }
        // A jump of 5 mm: taken as standing at the new place.
        tr.push(8.0 + 5.0, ms(85));
        assert_eq!(tr.goal(ms(91), period, 100.0, 1000.0), Some((13.0, 0.0)));
        // Steady again at 40 mm/s, then quiet: after two periods (20 ms) no extrapolation.
        for k in 0..10u64 {
            tr.push(13.0 + 40.0 * k as f64 * 0.002, ms(92 + 2 * k));
            tr.goal(ms(92 + 2 * k + 1), period, 100.0, 1000.0);
        }
        let last = 13.0 + 40.0 * 9.0 * 0.002;
        let (g, v) = tr.goal(ms(121), period, 100.0, 1000.0).unwrap();
        assert!((v - 40.0).abs() < 1e-9 && (g - (last + 0.44)).abs() < 1e-9);
        assert_eq!(tr.goal(ms(131), period, 100.0, 1000.0), Some((last, 0.0)));
        assert_eq!(tr.latest(), Some(last));
        // Older targets than the latest are ignored.
        tr.push(0.0, ms(50));
        assert_eq!(tr.latest(), Some(last));
    }

    /// A target with its velocity: moved on by it to each SYNC however late (a SYNC 40 ms
    /// after the target still finds it moving), up to the horizon, where it stands; jumps
    /// need no plausibility; a target without velocity goes back to the estimate.
    #[test]
    fn target_track_with_given_velocity() {
        let t0 = crate::util::clock::now();
        let ms = |n: u64| t0 + Duration::from_millis(n);
        let period = Duration::from_millis(10);
        let mut tr = TargetTrack::default();
        tr.push_moving(2.0, 50.0, ms(0));
        let (g, v) = tr.goal(ms(40), period, 100.0, 1000.0).unwrap();
        assert!((g - 4.0).abs() < 1e-9 && v == 50.0, "{g} {v}");
        let (g, v) = tr.goal(ms(300), period, 100.0, 1000.0).unwrap();
        assert!((g - 7.0).abs() < 1e-9 && v == 0.0, "{g} {v}");
        // Clamped to vmax; an older target is ignored.
        tr.push_moving(10.0, 500.0, ms(400));
        tr.push_moving(0.0, 0.0, ms(390));
        let (g, v) = tr.goal(ms(410), period, 100.0, 1000.0).unwrap();
        assert!((g - 11.0).abs() < 1e-9 && v == 100.0, "{g} {v}");
        tr.push_moving(10.0, f64::NAN, ms(420));
        tr.push(10.0, ms(430));
        assert_eq!(
            tr.goal(ms(431), period, 100.0, 1000.0).map(|x| x.1),
            Some(0.0)
        );
    }

    /// Braking to the stopping point from speed needs no more than the limit.
    #[test]
    fn hold_at_the_stopping_point() {
        let mut r = ramp(0.0);
        r.set_goal(500.0);
        let mut traj = vec![0.0];
        for _ in 0..30 {
            traj.push(r.step(DT));
        }
        let stop = r.stopping_point(DT);
        r.hold_at(stop);
        for _ in 0..100 {
            traj.push(r.step(DT));
        }
        check_limits(&traj, 100.0, 1000.0, DT);
        assert!(
            traj.windows(2).all(|w| w[1] >= w[0]),
            "monotonic: no return {:?}",
            &traj[28..]
        );
        assert!(r.at_rest() && r.pos() == stop);
    }

    /// Bounds are braked for, never crossed; goals outside are clamped.
    #[test]
    fn bounds_are_walls() {
        let mut r = DemandRamp::new(0.0, 100.0, 1000.0, -5.0, 10.0);
        let mut traj = vec![0.0];
        // A target running past the bound at 80 mm/s.
        for k in 1..=100 {
            r.set_goal(80.0 * k as f64 * DT);
            traj.push(r.step(DT));
        }
        check_limits(&traj, 100.0, 1000.0, DT);
        assert!(traj.iter().all(|p| *p <= 10.0));
        assert_eq!(r.pos(), 10.0);
        r.set_goal(-100.0);
        assert_eq!(r.goal(), -5.0);
        r.set_goal(f64::NAN);
        assert_eq!(r.goal(), -5.0);
        // Zero time or bad limits leave the demand where it is.
        assert_eq!(r.step(0.0), 10.0);
        let mut z = DemandRamp::new(1.0, f64::NAN, 1000.0, -5.0, 10.0);
        z.set_goal(3.0);
        assert_eq!(z.step(DT), 1.0);
    }
}
