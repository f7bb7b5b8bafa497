//! Fault injection on the twin drive: a drive fault with its EMCY, the heartbeat off and on,
//! refused and slow SDO replies.

use super::{Homing, SdoRefusal, TwinDrive};
use crate::canopen::cia402::{HomingStatus, PowerState};
use std::time::{Duration, Instant};

impl TwinDrive {
    /// Raise a drive fault with EMCY `code`: fault reaction (quick-stop ramp), then fault.
    /// Code 0x8611 also sets the following-error bit.
    pub fn inject_fault(&mut self, code: u16, manufacturer: [u8; 5], now: Instant) {
        self.update(now);
        self.fault_code = code;
        self.following_error = code == 0x8611;
        let class = match code >> 8 {
            0x21..=0x23 => 0x02,
            0x30..=0x33 => 0x04,
            0x40..=0x44 => 0x08,
            0x81 => 0x10,
            0x50..=0x8F => 0x20,
            _ => 0x80,
        };
        self.od.set(0x1001, 0, &[0x01 | class]);
        self.od.set(0x603F, 0, &code.to_le_bytes());
        self.pending = None;
        self.ack = false;
        if self.homing != Homing::Idle {
            self.homing = Homing::Idle;
            self.homing_status = HomingStatus::ErrorStopped;
        }
        self.fsa = PowerState::FaultReactionActive;
        self.csp = None;
        let d = self.speed(0x6085, 0).max(1e-6);
        self.mover.brake(d);
        self.emcy(code, manufacturer);
        self.update(now);
    }

    /// Stop or resume the heartbeat producer.
    pub fn set_heartbeat(&mut self, on: bool, now: Instant) {
        self.heartbeat_on = on;
        self.schedule_heartbeat(now);
    }

    /// Refuse SDO requests (`None`: serve them again).
    pub fn refuse_sdo(&mut self, refusal: Option<SdoRefusal>) {
        self.refusal = refusal;
    }

    /// Delay every SDO response by `delay`.
    pub fn set_sdo_delay(&mut self, delay: Duration) {
        self.sdo_delay = delay;
    }
}
