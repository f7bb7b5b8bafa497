//! Following in cyclic synchronous position (mode 8): follow targets feed the
//! [`DemandRamp`](crate::canopen::csp::DemandRamp) whose demand goes out at every SYNC
//! (`csp_tick`); the steps into and out of following (`csp_enter`, `csp_leave`); what a TPDO
//! means for following and "target reached" (`csp_status`); following's start and its end
//! (braking, or aborted on the actual position).

use super::{Cond, DriveError, Event, Master, Progress, Step};
use crate::canopen::cia402::{
    CW_CHANGE_IMMEDIATELY, CW_HALT, CW_NEW_SETPOINT, CW_RELATIVE, MODE_CSP, MODE_PROFILE_POSITION,
    PowerState, Statusword,
};
use crate::canopen::csp::TargetTrack;
use std::time::{Duration, Instant};

impl Master {
    pub(super) fn check_limits(&self, target_mm: f64) -> Result<(), DriveError> {
        let l = self.s.config().limits;
        if target_mm >= l.min_mm
            && target_mm <= l.max_mm
            && self.s.mm_to_counts(target_mm).is_some()
        {
            Ok(())
        } else {
            Err(DriveError::OutOfLimits {
                target_mm,
                min_mm: l.min_mm,
                max_mm: l.max_mm,
            })
        }
    }

    /// Follow targets go on feeding the ramp (which must exist).
    pub(super) fn start_following(&mut self) {
        if let (Some(r), Some(g)) = (self.ramp.as_mut(), self.follow_track.latest()) {
            r.set_goal(g);
        }
        if !self.following {
            self.following = true;
            self.status.following = true;
            tracing::info!("follower following (cyclic synchronous position)");
            self.events.push_back(Event::FollowingStarted);
        }
    }

    /// Following ends; the ramp, if any, is left as it is. An error refuses further follow
    /// targets until the next command.
    pub(super) fn end_following(&mut self, result: Result<(), DriveError>) {
        self.follow_track = TargetTrack::default();
        if !self.following {
            return;
        }
        self.following = false;
        self.status.following = false;
        match &result {
            Ok(()) => tracing::info!("follower following ended"),
            Err(e) => {
                tracing::warn!("follower following ended: {e}");
                self.follow_armed = false;
            }
        }
        self.events.push_back(Event::FollowingEnded(result));
    }

    /// End following with the demand braking to where it can stop.
    pub(super) fn brake_following(&mut self, result: Result<(), DriveError>) {
        let period = self.s.config().sync_period.as_secs_f64();
        if let Some(r) = self.ramp.as_mut() {
            let stop = r.stopping_point(period);
            r.hold_at(stop);
        }
        self.end_following(result);
    }

    /// End following at once: no more ramp, the demand is the actual position.
    pub(super) fn abort_following(&mut self, e: DriveError) {
        if self.ramp.take().is_some()
            && let Some(p) = self.status.position_counts
        {
            self.set_demand(p, self.sync.count() + 1);
        }
        self.end_following(Err(e));
    }

    /// One SYNC of following: the ramp's next demand goes into this SYNC's RPDO. `dt` is the
    /// time since the previous SYNC (the nominal period if unknown; bounded to ¼..4 periods).
    pub(super) fn csp_tick(&mut self, dt: Option<Duration>, now: Instant) {
        if self.ramp.is_none() {
            return;
        }
        let goal = if self.following {
            self.follow_goal(now)
        } else {
            None
        };
        let Some(r) = self.ramp.as_mut() else {
            return;
        };
        if let Some((g, v)) = goal {
            r.set_goal_moving(g, v);
        }
        let period = self.s.config().sync_period.as_secs_f64();
        let dt = match dt {
            Some(d) if !std::mem::take(&mut self.ramp_new) => d.as_secs_f64(),
            _ => period,
        };
        let mm = r.step(dt.clamp(period / 4.0, period * 4.0));
        if let Some(c) = self.s.mm_to_counts(mm) {
            self.set_demand(c, self.sync.count());
            self.commanded = Some(c);
            self.status.commanded_mm = Some(self.s.counts_to_mm(c));
        }
    }

    /// The follow target at `now` and its velocity (see [`TargetTrack`]), within the limits.
    fn follow_goal(&mut self, now: Instant) -> Option<(f64, f64)> {
        let c = self.s.config();
        let p = c.profile;
        let (g, v) = self
            .follow_track
            .goal(now, c.sync_period, p.velocity_mm_s, p.accel_mm_s2)?;
        Some((g.clamp(c.limits.min_mm, c.limits.max_mm), v))
    }

    /// The target position as a cyclic demand, first carried by SYNC number `sync` (no wait
    /// on the drive depends on it, unlike `set_target`).
    pub(super) fn set_demand(&mut self, t: i32, sync: u64) {
        if t != self.target {
            self.target = t;
            self.demand_since = sync;
            self.csp_demand_moved();
        }
    }

    /// A new demand: "target reached" in CSP waits for a TPDO answering a later SYNC.
    pub(super) fn csp_demand_moved(&mut self) {
        if self.status.mode == Some(MODE_CSP) {
            self.status.target_reached = false;
        }
    }

    pub(super) fn window_mm(&self) -> f64 {
        self.s.config().profile.position_window_mm
    }

    /// Cyclic synchronous position: what a TPDO means for following, and "target reached".
    pub(super) fn csp_status(&mut self, w: Statusword, pos: i32) {
        let st = w.state();
        let enabled = st == Some(PowerState::OperationEnabled);
        if !enabled {
            if self.ramp.is_some() {
                let e = match st {
                    Some(s) if s.is_fault() => self.fault(),
                    _ => DriveError::NotEnabled {
                        what: "follow",
                        state: st.map_or("an unknown state".into(), |s| s.to_string()),
                    },
                };
                self.abort_following(e);
            }
            // Enabling in CSP takes the target position at once: keep it where the stage is.
            self.set_demand(pos, self.sync.count() + 1);
        } else if w.following_error() && self.following {
            self.brake_following(Err(DriveError::FollowingError));
        }
        let err = (self.s.counts_to_mm(pos) - self.s.counts_to_mm(self.target)).abs();
        self.status.target_reached =
            enabled && err < self.window_mm() && self.tpdo_sync > self.demand_since;
    }

    /// The steps into following: let a profile move end, hold the actual position as the
    /// demand (so the switch asks for no motion), mode 8 confirmed in 0x6061, then stream.
    pub(super) fn csp_enter(&mut self, target_mm: f64, now: Instant) -> Progress {
        if let Err(e) = self.check_limits(target_mm) {
            return Progress::Fail(e);
        }
        if self.follow_track.latest().is_none() {
            self.follow_track.push(target_mm, now);
        }
        if self.ramp.is_some() {
            self.start_following();
            return Progress::Next;
        }
        let c = *self.s.config();
        let mut v = Vec::new();
        if self.status.mode == Some(MODE_PROFILE_POSITION) && !self.status.target_reached {
            let here = self.status.position_counts.unwrap_or(0);
            let dist =
                self.s.counts_to_mm(self.commanded.unwrap_or(here)) - self.s.counts_to_mm(here);
            let t = c.state_timeout + self.move_time(dist) * 2 + c.profile.move_timeout_margin;
            v.push(Step::AwaitStatus(Cond::TargetReached, t));
        }
        v.push(Step::Cw {
            set: 0,
            clear: CW_NEW_SETPOINT | CW_CHANGE_IMMEDIATELY | CW_RELATIVE | CW_HALT,
        });
        v.push(Step::HoldActual);
        v.push(Step::AwaitStatus(Cond::Applied, c.state_timeout));
        v.push(Step::EnsureMode(MODE_CSP));
        v.push(Step::CspStart);
        Progress::Replace(v)
    }

    /// The steps out of following: the demand to rest (on the last target for stop following,
    /// else where it can stop), reached, then profile position for stop following.
    pub(super) fn csp_leave(&mut self, stop_following: bool) -> Progress {
        let c = *self.s.config();
        let period = c.sync_period.as_secs_f64();
        let mut v = Vec::new();
        let to_last = if stop_following && self.following {
            self.follow_track.latest()
        } else {
            None
        };
        if let Some(r) = self.ramp.as_mut() {
            let goal = to_last.unwrap_or_else(|| r.stopping_point(period));
            r.hold_at(goal);
            let (dist, vel) = (goal - r.pos(), r.vel());
            v.push(Step::AwaitStatus(
                Cond::CspSettled,
                c.state_timeout + self.ramp_time(dist, vel),
            ));
            v.push(Step::CspEnd);
        }
        self.end_following(Ok(()));
        if stop_following && (self.status.mode == Some(MODE_CSP) || self.ramp.is_some()) {
            v.push(Step::EnsureMode(MODE_PROFILE_POSITION));
        }
        Progress::Replace(v)
    }
}
