//! The stage's motion over time on the twin drive: profile moves toward a target, homing
//! (search, final approach, the zero set at the switch), the cyclic synchronous position
//! demand taken from each RPDO, and the update that advances it all and reports the position
//! to the plant.

use super::profile::{Goal, Interp};
use super::{Homing, TwinDrive};
use crate::canopen::cia402::{HomingStatus, MODE_CSP, PowerState};
use std::time::{Duration, Instant};

impl TwinDrive {
    /// Cyclic synchronous position: 0x607A is the new demand (when the drive follows), reached
    /// by the internal demand one cycle later.
    pub(super) fn take_demand(&mut self, now: Instant) {
        self.update(now);
        if let Some(prev) = self.demand_at.replace(now) {
            let iv = now.saturating_duration_since(prev);
            if iv <= Duration::from_secs(1) {
                self.cycle = Some(match self.cycle {
                    Some(c) => (c * 3 + iv) / 4,
                    None => iv,
                });
            }
        }
        let Some(ip) = self.csp else {
            return;
        };
        let mut t = self.od.i32(0x607A, 0);
        let (lo, hi) = (self.od.i32(0x607D, 1), self.od.i32(0x607D, 2));
        self.internal_limit = false;
        if lo < hi && !(lo..=hi).contains(&t) {
            t = t.clamp(lo, hi);
            self.internal_limit = true;
        }
        self.last_target = t;
        let mut next = Interp {
            from: ip.at(now).0,
            to: self.to_mm(t) + self.zero,
            start: now,
            span: self.cycle.unwrap_or(Duration::ZERO),
            steady: false,
        };
        let (v, before) = (next.vel(), ip.vel());
        next.steady = v != 0.0 && (v - before).abs() <= 0.25 * v.abs();
        self.csp = Some(next);
    }

    /// Follow demands from where the stage is, if mode 8, operation enabled and no halt.
    pub(super) fn csp_hold_here(&mut self) {
        let follows =
            self.mode() == MODE_CSP && self.fsa == PowerState::OperationEnabled && !self.halted;
        self.csp = follows.then(|| Interp::hold(self.mover.pos, self.last_update));
        if follows {
            self.mover.goal = Goal::Idle;
        }
    }

    /// Whether CSP motion is still under way (the internal demand moving or not yet reached).
    pub(super) fn csp_busy(&self) -> bool {
        self.csp.is_some_and(|ip| {
            (ip.from != ip.to && self.last_update < ip.end())
                || self.mover.pos != ip.at(ip.end()).0
                || self.mover.vel != 0.0
        })
    }

    pub(super) fn move_to(&mut self, phys: f64) {
        let v = self.speed(0x6081, 0);
        let a = self.speed(0x6083, 0).max(1e-6);
        let d = self.speed(0x6084, 0).max(1e-6);
        self.mover.goal = Goal::To {
            target: phys,
            v,
            a,
            d,
        };
    }

    pub(super) fn start_homing(&mut self) {
        let method = self.od.i8(0x6098, 0);
        let offset = self.to_mm(self.od.i32(0x607C, 0));
        match method {
            35 | 37 => {
                self.zero = self.mover.pos - offset;
                self.finish_homing();
            }
            1..=34 => {
                let (fast, slow) = (self.speed(0x6099, 1), self.speed(0x6099, 2));
                if fast <= 0.0 || slow <= 0.0 {
                    self.homing_status = HomingStatus::ErrorStopped;
                    return;
                }
                self.homing_status = HomingStatus::InProgress;
                let here = self.mover.pos;
                let approach = self.cfg.homing_approach_mm.max(0.0);
                let a = self.speed(0x609A, 0).max(1e-6);
                if here.abs() > approach {
                    self.homing = Homing::Search;
                    self.mover.goal = Goal::To {
                        target: here.signum() * approach,
                        v: fast,
                        a,
                        d: a,
                    };
                } else {
                    self.homing = Homing::Approach;
                    self.mover.goal = Goal::To {
                        target: 0.0,
                        v: slow,
                        a,
                        d: a,
                    };
                }
            }
            _ => self.homing_status = HomingStatus::ErrorStopped,
        }
    }

    fn finish_homing(&mut self) {
        self.homing = Homing::Idle;
        self.homing_status = HomingStatus::Completed;
        self.homed = true;
        self.last_target = self.encoder_counts();
    }

    pub(super) fn interrupt_homing(&mut self) {
        self.homing = Homing::Idle;
        self.homing_status = HomingStatus::Interrupted;
        if self.mover.goal != Goal::Idle {
            let d = self.speed(0x609A, 0).max(1e-6);
            self.mover.brake(d);
        }
    }

    /// A reached goal: next homing phase, buffered set-point, or the end of a stop.
    fn arrived(&mut self) {
        match self.homing {
            Homing::Search => {
                self.homing = Homing::Approach;
                let a = self.speed(0x609A, 0).max(1e-6);
                self.mover.goal = Goal::To {
                    target: 0.0,
                    v: self.speed(0x6099, 2),
                    a,
                    d: a,
                };
                return;
            }
            Homing::Approach => {
                let offset = self.to_mm(self.od.i32(0x607C, 0));
                // The switch is at physical 0: there the encoder reads the home offset.
                self.zero = -offset;
                self.finish_homing();
                return;
            }
            Homing::Idle => {}
        }
        if let Some(p) = self.pending.take() {
            self.move_to(p);
            let cw = self.last_cw;
            self.refresh_ack(cw);
        }
    }

    /// Advance the motion to `now` in steps of at most 1 ms.
    pub(super) fn update(&mut self, now: Instant) {
        let mut t = self.last_update;
        const STEP: Duration = Duration::from_millis(1);
        let (v, a) = (self.speed(0x607F, 0), self.speed(0x60C5, 0));
        while t < now {
            let dt = (now - t).min(STEP);
            t += dt;
            if let Some(ip) = self.csp {
                let (s, sv) = ip.at(t);
                self.mover.track(s, sv, v, a, dt.as_secs_f64());
            } else if self.mover.step(dt.as_secs_f64()) {
                self.arrived();
            }
        }
        self.last_update = self.last_update.max(now);
        self.csp_error = self
            .csp
            .map_or(0.0, |ip| (ip.at(self.last_update).0 - self.mover.pos).abs());
        if !self.mover.moving() {
            self.standstill();
        }
        self.report_position();
    }

    pub(super) fn report_position(&mut self) {
        let p = self.mover.pos;
        if self.reported != Some(p) {
            self.reported = Some(p);
            (self.on_position)(p);
        }
    }
}
