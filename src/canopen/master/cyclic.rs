//! The cyclic exchange: the RPDO1 image the master sends at every SYNC (controlword and
//! target position), each TPDO1 (statusword and position actual) into the
//! [`DriveStatus`](super::DriveStatus), and the SYNC's pace (quiet at rest).

use super::{Event, Master, QUIET_AFTER, RECENT_POSITIONS};
use crate::canopen::cia402::{MODE_CSP, MODE_PROFILE_POSITION, Statusword};
use canopen_rs::NmtState;
use std::time::Instant;

impl Master {
    pub(super) fn pdo_active(&self) -> bool {
        self.status.configured && self.hb.state() == Some(NmtState::Operational)
    }

    pub(super) fn on_tpdo(&mut self, sw: u16, pos: i32, now: Instant) {
        self.tpdo_sync = self.sync.count();
        self.status.tpdo_count += 1;
        let window = self.window_mm();
        self.standstill = self
            .status
            .position_counts
            .is_some_and(|p| (self.s.counts_to_mm(pos) - self.s.counts_to_mm(p)).abs() < window);
        if !self.standstill || self.status.statusword != Some(sw) {
            // Moving, or a new state: the full SYNC rate until it settles.
            self.active_at = Some(now);
        }
        self.set_statusword(sw);
        self.status.position_at = self.last_sync_at;
        self.set_position(pos);
        if let Some(at) = self.last_sync_at {
            let h = &mut self.status.recent_positions;
            h.rotate_left(1);
            h[RECENT_POSITIONS - 1] = Some((at, self.s.counts_to_mm(pos)));
        }
        if self.status.mode == Some(MODE_CSP) {
            self.csp_status(Statusword(sw), pos);
        }
    }

    pub(super) fn set_statusword(&mut self, sw: u16) {
        let w = Statusword(sw);
        let st = w.state();
        if let Some(to) = st
            && self.status.state != Some(to)
        {
            tracing::info!(
                from = %self.status.state.map_or_else(|| "unknown".to_string(), |s| s.to_string()),
                to = %to,
                "follower drive power state"
            );
            self.events.push_back(Event::PowerState {
                from: self.status.state,
                to,
            });
        }
        self.status.statusword = Some(sw);
        self.status.state = st;
        self.status.target_reached = w.target_reached();
        let pp = self.status.mode == Some(MODE_PROFILE_POSITION);
        let csp = self.status.mode == Some(MODE_CSP);
        self.status.setpoint_ack = pp && w.setpoint_ack();
        self.status.following_error = (pp || csp) && w.following_error();
    }

    pub(super) fn set_position(&mut self, pos: i32) {
        self.status.position_counts = Some(pos);
        self.status.position_mm = Some(self.s.counts_to_mm(pos));
    }

    pub(super) fn set_cw(&mut self, cw: u16) {
        if cw != self.cw {
            self.cw = cw;
            self.cw_applied_at = self.sync.count() + 1;
        }
        self.status.controlword = self.cw;
    }

    pub(super) fn set_target(&mut self, t: i32) {
        if t != self.target {
            self.target = t;
            self.cw_applied_at = self.sync.count() + 1;
            self.demand_since = self.sync.count() + 1;
            self.csp_demand_moved();
        }
    }

    /// Whether the last TPDO reflects the current RPDO image.
    pub(super) fn fresh(&self) -> bool {
        self.status.tpdo_count > 0 && self.tpdo_sync >= self.cw_applied_at
    }

    /// SYNC at the quiet period once nothing has been under way or changed for
    /// [`QUIET_AFTER`]: in profile position (or not enabled), no command running or queued,
    /// not following. Anything else, and the first change the drive reports, brings back the
    /// full rate at once.
    pub(super) fn pace_sync(&mut self, now: Instant) {
        // Commands were counted when `run` began (with this same `now`).
        if self.following || self.ramp.is_some() || self.status.mode == Some(MODE_CSP) {
            self.active_at = Some(now);
        }
        let quiet = self
            .active_at
            .is_none_or(|t| now.saturating_duration_since(t) >= QUIET_AFTER);
        self.sync.set_quiet(quiet, now);
        self.status.sync_quiet = self.sync.is_quiet();
    }
}
