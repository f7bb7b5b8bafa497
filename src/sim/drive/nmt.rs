//! The twin drive's NMT slave: boot-up, the state commands, reset node and reset
//! communication, and the heartbeat producer's schedule (0x1017).

use super::od::communication_objects;
use super::profile::Goal;
use super::{Homing, TwinDrive, frame};
use crate::canopen::cia402::{HomingStatus, PowerState};
use crate::canopen::{NmtState, cob};
use std::time::{Duration, Instant};

impl TwinDrive {
    pub(super) fn boot(&mut self, now: Instant) {
        self.nmt = NmtState::PreOperational;
        self.transfer = None;
        self.rpdo_latched = None;
        self.tpdo_syncs = 0;
        self.last_tpdo = None;
        self.tx
            .push_back(frame(cob::HEARTBEAT + self.id(), &[0x00]));
        self.schedule_heartbeat(now);
    }

    pub(super) fn schedule_heartbeat(&mut self, now: Instant) {
        let ms = self.od.u16(0x1017, 0);
        self.next_heartbeat =
            (ms > 0 && self.heartbeat_on).then(|| now + Duration::from_millis(ms as u64));
    }

    fn reset_communication(&mut self, now: Instant) {
        communication_objects(
            &mut self.od,
            self.cfg.node_id,
            self.cfg.default_heartbeat_ms,
        );
        self.boot(now);
    }

    fn reset_application(&mut self) {
        self.mover.vel = 0.0;
        self.mover.goal = Goal::Idle;
        self.csp = None;
        self.demand_at = None;
        self.cycle = None;
        self.csp_error = 0.0;
        self.fsa = PowerState::SwitchOnDisabled;
        self.last_cw = 0;
        self.ack = false;
        self.pending = None;
        self.halted = false;
        self.homing = Homing::Idle;
        self.homing_status = HomingStatus::Interrupted;
        self.homed = false;
        self.following_error = false;
        self.fault_code = 0;
        self.zero = self.mover.pos;
        self.last_target = 0;
        self.od.set(0x6040, 0, &[0, 0]);
        self.od.set(0x6060, 0, &[0]);
        self.od.set(0x607A, 0, &[0; 4]);
    }

    pub(super) fn on_nmt(&mut self, data: &[u8], now: Instant) {
        if data.len() != 2 || (data[1] != 0 && data[1] != self.node.raw()) {
            return;
        }
        match data[0] {
            0x01 => self.nmt = NmtState::Operational,
            0x02 => self.nmt = NmtState::Stopped,
            0x80 => self.nmt = NmtState::PreOperational,
            0x81 => {
                self.reset_application();
                self.reset_communication(now);
            }
            0x82 => self.reset_communication(now),
            _ => {}
        }
        if self.nmt != NmtState::Operational {
            self.rpdo_latched = None;
        }
    }
}
