//! The twin drive's CiA 402 side: the power state machine driven by the controlword, modes
//! of operation, the profile-position set-point handshake, the statusword, and the process
//! values kept up to date in the dictionary.

use super::profile::Goal;
use super::{Homing, TwinDrive};
use crate::canopen::cia402::{
    self, CW_CHANGE_IMMEDIATELY, CW_HALT, CW_NEW_SETPOINT, CW_RELATIVE, FsaCommand, HomingStatus,
    MODE_CSP, MODE_HOMING, MODE_PROFILE_POSITION, PowerState, SW_CSP_TARGET_USED,
    SW_FOLLOWING_ERROR, SW_INTERNAL_LIMIT, SW_REMOTE, SW_SETPOINT_ACK, SW_TARGET_REACHED,
    SW_VOLTAGE_ENABLED,
};
use std::time::Instant;

impl TwinDrive {
    pub(super) fn mode(&self) -> i8 {
        self.od.i8(0x6060, 0)
    }

    pub(super) fn on_mode(&mut self, now: Instant) {
        self.update(now);
        if self.homing != Homing::Idle && self.mode() != MODE_HOMING {
            self.interrupt_homing();
        }
        self.ack = false;
        let was_csp = self.csp.is_some();
        if self.mode() == MODE_CSP {
            if !was_csp {
                self.pending = None;
                self.csp_hold_here();
            }
        } else if was_csp {
            // Out of CSP: brake what motion is left; the last demand is the base of relative
            // moves.
            self.csp = None;
            if self.mover.vel != 0.0 {
                let d = self.speed(0x6084, 0).max(1e-6);
                self.mover.brake(d);
            }
        }
    }

    fn enter(&mut self, to: PowerState) {
        let from = self.fsa;
        self.fsa = to;
        match to {
            PowerState::QuickStopActive => {
                self.csp = None;
                let d = self.speed(0x6085, 0).max(1e-6);
                self.mover.brake(d);
                self.pending = None;
                if self.homing != Homing::Idle {
                    self.interrupt_homing();
                }
            }
            PowerState::OperationEnabled if from != PowerState::OperationEnabled => {
                self.csp_hold_here();
            }
            PowerState::OperationEnabled => {}
            _ if from == PowerState::OperationEnabled || from == PowerState::QuickStopActive => {
                // Power removed: the stage stops where it is (the brake holds it).
                self.csp = None;
                self.mover.vel = 0.0;
                self.mover.goal = Goal::Idle;
                self.pending = None;
                self.ack = false;
                if self.homing != Homing::Idle {
                    self.interrupt_homing();
                }
            }
            _ => {}
        }
        if from == PowerState::Fault && to == PowerState::SwitchOnDisabled {
            self.fault_code = 0;
            self.following_error = false;
            self.od.set(0x603F, 0, &[0, 0]);
            self.od.set(0x1001, 0, &[0]);
            self.emcy(0, [0; 5]);
        }
    }

    pub(super) fn on_controlword(&mut self, cw: u16, now: Instant) {
        self.update(now);
        let prev = self.last_cw;
        self.last_cw = cw;
        if let Some(cmd) = FsaCommand::decode(cw, prev)
            && let Some(next) = cia402::transition(self.fsa, cmd)
        {
            self.enter(next);
            if !self.mover.moving() {
                self.standstill();
            }
        }
        if self.fsa != PowerState::OperationEnabled {
            self.refresh_ack(cw);
            return;
        }
        let rising = |bit: u16| cw & bit != 0 && prev & bit == 0;
        let falling = |bit: u16| cw & bit == 0 && prev & bit != 0;
        if cw & CW_HALT != 0 {
            if !self.halted {
                self.halted = true;
                self.csp = None;
                let d = self.speed(0x6084, 0).max(1e-6);
                self.mover.brake(d);
                self.pending = None;
                if self.homing != Homing::Idle {
                    self.interrupt_homing();
                }
            }
        } else if self.halted {
            self.halted = false;
            if self.mode() == MODE_CSP {
                self.csp_hold_here();
            }
        }
        match self.mode() {
            MODE_PROFILE_POSITION if !self.halted && rising(CW_NEW_SETPOINT) && !self.ack => {
                self.accept_setpoint(cw);
            }
            MODE_HOMING if rising(cia402::CW_HOMING_START) && !self.halted => self.start_homing(),
            MODE_HOMING if falling(cia402::CW_HOMING_START) && self.homing != Homing::Idle => {
                self.interrupt_homing();
            }
            _ => {}
        }
        self.refresh_ack(cw);
    }

    /// Set-point acknowledge (bit 12) drops once the master has dropped bit 4 and the
    /// set-point buffer is free.
    pub(super) fn refresh_ack(&mut self, cw: u16) {
        if cw & CW_NEW_SETPOINT == 0 && self.pending.is_none() {
            self.ack = false;
        }
    }

    fn accept_setpoint(&mut self, cw: u16) {
        let t = self.od.i32(0x607A, 0);
        let mut target = if cw & CW_RELATIVE != 0 {
            self.last_target.saturating_add(t)
        } else {
            t
        };
        let (lo, hi) = (self.od.i32(0x607D, 1), self.od.i32(0x607D, 2));
        self.internal_limit = false;
        if lo < hi && !(lo..=hi).contains(&target) {
            target = target.clamp(lo, hi);
            self.internal_limit = true;
        }
        self.last_target = target;
        self.ack = true;
        let phys = self.to_mm(target) + self.zero;
        if self.mover.moving() && cw & CW_CHANGE_IMMEDIATELY == 0 {
            self.pending = Some(phys);
        } else {
            self.move_to(phys);
        }
    }

    pub(super) fn standstill(&mut self) {
        match self.fsa {
            PowerState::FaultReactionActive => self.fsa = PowerState::Fault,
            // 0x605A quick stop option: 0–4 end in switch on disabled, 5–8 stay.
            PowerState::QuickStopActive if (0..=4).contains(&(self.od.u16(0x605A, 0) as i16)) => {
                self.fsa = PowerState::SwitchOnDisabled;
            }
            _ => {}
        }
    }

    pub(super) fn statusword(&self) -> u16 {
        let mut sw = self.fsa.statusword_bits() | SW_REMOTE;
        if self.fsa != PowerState::NotReadyToSwitchOn {
            sw |= SW_VOLTAGE_ENABLED;
        }
        let still = !self.mover.moving();
        match self.mode() {
            MODE_PROFILE_POSITION => {
                if still && self.pending.is_none() {
                    sw |= SW_TARGET_REACHED;
                }
                if self.ack {
                    sw |= SW_SETPOINT_ACK;
                }
                if self.following_error {
                    sw |= SW_FOLLOWING_ERROR;
                }
            }
            MODE_CSP => {
                // Bit 10 is reserved in CSP.
                if self.csp.is_some() {
                    sw |= SW_CSP_TARGET_USED;
                }
                if self.following_error || self.csp_error > self.speed(0x6065, 0) {
                    sw |= SW_FOLLOWING_ERROR;
                }
            }
            MODE_HOMING => {
                let mut h = self.homing_status;
                if h == HomingStatus::ErrorStopped && !still {
                    h = HomingStatus::ErrorMoving;
                }
                if h == HomingStatus::Interrupted && !still {
                    h = HomingStatus::InProgress;
                }
                sw |= h.bits();
            }
            _ => {
                if still {
                    sw |= SW_TARGET_REACHED;
                }
            }
        }
        if self.internal_limit {
            sw |= SW_INTERNAL_LIMIT;
        }
        sw
    }

    /// Bring the process values in the dictionary up to date.
    pub(super) fn refresh_od(&mut self) {
        let sw = self.statusword();
        self.od.set(0x6041, 0, &sw.to_le_bytes());
        let pos = self.encoder_counts();
        self.od.set(0x6064, 0, &pos.to_le_bytes());
        let demand = match self.csp {
            Some(ip) => self.counts(ip.at(self.last_update).0),
            None => pos,
        };
        self.od.set(0x6062, 0, &demand.to_le_bytes());
        let vel = (self.mover.vel * self.cpm).round() as i32;
        self.od.set(0x606C, 0, &vel.to_le_bytes());
        let mode = self.mode();
        self.od.set(0x6061, 0, &[mode as u8]);
        self.od.set(0x603F, 0, &self.fault_code.to_le_bytes());
    }
}
