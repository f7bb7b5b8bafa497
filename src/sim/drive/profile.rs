//! The twin's kinematics, pure: a point mass following a trapezoidal profile ([`Mover`],
//! also servoing onto a moving set-point and braking) and the cyclic synchronous position
//! interpolation of the internal demand ([`Interp`]).

use std::time::{Duration, Instant};

#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Goal {
    Idle,
    /// Go to `target` (mm) with at most `v` (mm/s), accelerating with `a`, braking with `d`.
    To {
        target: f64,
        v: f64,
        a: f64,
        d: f64,
    },
    /// Brake to standstill with `d`.
    Stop {
        d: f64,
    },
}

/// A point mass following a trapezoidal profile: the velocity tracks the largest speed from
/// which it can still stop within the distance to go, capped at `v`, within the acceleration
/// limits; so it accelerates, cruises and brakes to arrive at rest, from any starting
/// velocity (a target changed on the fly). The braking speed is the discrete-time one,
/// `h·(√(¼ + 2s/(h·dt)) − ½)` with `h = d·dt`, so that stepping `x += v·dt` after each
/// velocity change stops on the target rather than overshooting it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Mover {
    pub(super) pos: f64,
    pub(super) vel: f64,
    pub(super) goal: Goal,
}

impl Mover {
    /// Advance by `dt` seconds; returns true when the goal was reached in this step.
    pub(super) fn step(&mut self, dt: f64) -> bool {
        match self.goal {
            Goal::Idle => false,
            Goal::Stop { d } => {
                let dv = d * dt;
                if self.vel.abs() <= dv {
                    self.vel = 0.0;
                    self.goal = Goal::Idle;
                    return true;
                }
                self.vel -= dv * self.vel.signum();
                self.pos += self.vel * dt;
                false
            }
            Goal::To { target, v, a, d } => {
                let s = target - self.pos;
                if s.abs() < 1e-12 {
                    self.pos = target;
                    self.vel = 0.0;
                    self.goal = Goal::Idle;
                    return true;
                }
                let h = d * dt;
                let braking = h * ((0.25 + 2.0 * s.abs() / (h * dt)).sqrt() - 0.5);
                let want = s.signum() * v.min(braking);
                let speeding_up = want.abs() > self.vel.abs() && want * self.vel >= 0.0;
                let limit = if speeding_up { a } else { d } * dt;
                self.vel += (want - self.vel).clamp(-limit, limit);
                let next = self.pos + self.vel * dt;
                if (target - next) * s <= 0.0 {
                    // Crossed or reached the target in this step: arrive.
                    self.pos = target;
                    self.vel = 0.0;
                    self.goal = Goal::Idle;
                    return true;
                }
                self.pos = next;
                false
            }
        }
    }

    pub(super) fn moving(&self) -> bool {
        self.goal != Goal::Idle || self.vel != 0.0
    }

    /// Servo for `dt` seconds onto a set-point that is at `s` (mm) at the end of the step and
    /// moves at `sv` (mm/s), within `v` (mm/s) and `a` (mm/s², speeding up and braking):
    /// velocity feed-forward plus the braking speed that closes the remaining gap. Lands on
    /// the set-point when one step can, within both limits.
    pub(super) fn track(&mut self, s: f64, sv: f64, v: f64, a: f64, dt: f64) {
        self.goal = Goal::Idle;
        if dt <= 0.0 {
            return;
        }
        let h = a * dt;
        let land = (s - self.pos) / dt;
        if land.abs() <= v && (land - self.vel).abs() <= h && (land - sv).abs() <= h {
            self.pos = s;
            self.vel = if sv == 0.0 && land.abs() < 1e-12 {
                0.0
            } else {
                land
            };
            return;
        }
        let gap = s - self.pos - sv * dt;
        let braking = if h > 0.0 {
            h * ((0.25 + 2.0 * gap.abs() / (h * dt)).sqrt() - 0.5)
        } else {
            0.0
        };
        let want = (sv + gap.signum() * braking).clamp(-v, v);
        self.vel += (want - self.vel).clamp(-h, h);
        self.pos += self.vel * dt;
    }

    /// Brake with `d` (at once idle when already at rest).
    pub(super) fn brake(&mut self, d: f64) {
        self.goal = if self.vel == 0.0 {
            Goal::Idle
        } else {
            Goal::Stop { d }
        };
    }
}

/// Cyclic synchronous position: the internal position demand (physical mm), moving linearly
/// from `from` to the latest demand `to` over `span` from `start`; then, if the motion is
/// steady (this segment's velocity within a quarter of the previous one's), on at that
/// velocity for up to one more `span` (a late next demand), else holding.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Interp {
    pub(super) from: f64,
    pub(super) to: f64,
    pub(super) start: Instant,
    pub(super) span: Duration,
    /// Go on past `to` while the next demand is late.
    pub(super) steady: bool,
}

impl Interp {
    /// At rest at `pos`.
    pub(super) fn hold(pos: f64, now: Instant) -> Self {
        Interp {
            from: pos,
            to: pos,
            start: now,
            span: Duration::ZERO,
            steady: false,
        }
    }

    /// The velocity of the segment (mm/s).
    pub(super) fn vel(&self) -> f64 {
        let span = self.span.as_secs_f64();
        if span > 0.0 {
            (self.to - self.from) / span
        } else {
            0.0
        }
    }

    /// The internal demand and its velocity at `t`.
    pub(super) fn at(&self, t: Instant) -> (f64, f64) {
        let span = self.span.as_secs_f64();
        let since = t.saturating_duration_since(self.start).as_secs_f64();
        if span <= 0.0 {
            return (self.to, 0.0);
        }
        let v = self.vel();
        let go_on = if self.steady { 2.0 } else { 1.0 };
        if since <= go_on * span {
            (self.from + v * since, v)
        } else {
            (self.from + go_on * v * span, 0.0)
        }
    }

    /// When the internal demand comes to rest.
    pub(super) fn end(&self) -> Instant {
        self.start + self.span * if self.steady { 2 } else { 1 }
    }
}
