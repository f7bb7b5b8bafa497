//! Planning: a [`Command`](super::Command) as its program of `Step`s, and a move's concrete
//! steps once the drive's state is known (`expand_move`); the time bounds the waits get and
//! the profile, homing and limit parameters configure writes.

use super::{Command, Cond, DriveError, Master, Motion, Progress, ReadUse, Step};
use crate::canopen::cia402::{
    self, CW_CHANGE_IMMEDIATELY, CW_COMMAND_MASK, CW_FAULT_RESET, CW_HALT, CW_NEW_SETPOINT,
    CW_RELATIVE, FsaCommand, MODE_HOMING, MODE_PROFILE_POSITION, PowerState,
};
use crate::canopen::pdo::{self, SdoWrite};
use crate::canopen::sdo::ObjAddr;
use canopen_rs::{NmtCommand, NmtState};
use std::collections::VecDeque;
use std::time::Duration;

impl Master {
    /// A command as steps.
    pub(super) fn plan(&self, cmd: &Command) -> VecDeque<Step> {
        let c = self.s.config();
        let mut v = Vec::new();
        match cmd {
            Command::Configure => return self.plan_configure(c.reset_communication),
            Command::Start => {
                v.push(Step::RequireConfigured);
                v.push(Step::Nmt(NmtCommand::StartRemoteNode));
                v.push(Step::AwaitNmt(NmtState::Operational));
                v.push(Step::SyncOn);
                v.push(Step::AwaitTpdo);
            }
            Command::Nmt(n) => {
                v.push(Step::Nmt(*n));
                match n {
                    NmtCommand::StartRemoteNode => {
                        v.push(Step::AwaitNmt(NmtState::Operational));
                        if self.status.configured {
                            v.push(Step::SyncOn);
                        }
                    }
                    NmtCommand::StopRemoteNode => v.push(Step::AwaitNmt(NmtState::Stopped)),
                    NmtCommand::EnterPreOperational => {
                        v.push(Step::AwaitNmt(NmtState::PreOperational))
                    }
                    NmtCommand::ResetNode | NmtCommand::ResetCommunication => {
                        v.push(Step::AwaitBootUp);
                        v.push(Step::Settle(c.boot_settle));
                    }
                }
            }
            Command::Enable => {
                v.push(Step::RequirePdo);
                v.push(Step::Power(PowerState::OperationEnabled));
            }
            Command::Disable => {
                v.push(Step::RequirePdo);
                v.push(Step::Power(PowerState::SwitchOnDisabled));
            }
            Command::Home => {
                let h = c.homing;
                v.push(Step::RequirePdo);
                v.push(Step::RequireEnabled);
                v.push(Step::CspLeave {
                    stop_following: false,
                });
                v.push(Step::EnsureMode(MODE_HOMING));
                // Bit 4 low first so that setting it is a rising edge.
                v.push(Step::Cw {
                    set: 0,
                    clear: CW_NEW_SETPOINT | CW_HALT,
                });
                v.push(Step::AwaitStatus(Cond::Applied, c.state_timeout));
                v.push(Step::Cw {
                    set: cia402::CW_HOMING_START,
                    clear: 0,
                });
                v.push(Step::AwaitStatus(Cond::HomingDone, h.timeout));
                v.push(Step::Cw {
                    set: 0,
                    clear: cia402::CW_HOMING_START,
                });
                v.push(Step::AwaitStatus(Cond::Applied, c.state_timeout));
                v.push(Step::MarkHomed);
            }
            Command::MoveTo { target_mm } => self.plan_move(&mut v, Motion::Absolute(*target_mm)),
            Command::Jog { delta_mm } => self.plan_move(&mut v, Motion::Relative(*delta_mm)),
            Command::SetTarget { target_mm } => self.plan_move(&mut v, Motion::Track(*target_mm)),
            Command::Follow { target_mm } => {
                v.push(Step::RequirePdo);
                v.push(Step::RequireEnabled);
                v.push(Step::RequireHomed);
                v.push(Step::CspEnter(*target_mm));
            }
            Command::StopFollowing => v.push(Step::CspLeave {
                stop_following: true,
            }),
            Command::Stop => {
                v.push(Step::RequirePdo);
                v.push(Step::Cw {
                    set: CW_HALT,
                    clear: CW_NEW_SETPOINT,
                });
                v.push(Step::AwaitStatus(
                    Cond::Stopped,
                    c.state_timeout + self.stop_time(c.profile.decel_mm_s2),
                ));
            }
            Command::QuickStop => {
                v.push(Step::RequirePdo);
                v.push(Step::Cw {
                    set: FsaCommand::QuickStop.bits(),
                    clear: CW_COMMAND_MASK | CW_NEW_SETPOINT,
                });
                v.push(Step::AwaitStatus(
                    Cond::QuickStopped,
                    c.state_timeout + self.stop_time(c.profile.quick_stop_decel_mm_s2),
                ));
            }
            Command::FaultReset => {
                v.push(Step::RequirePdo);
                v.push(Step::Cw {
                    set: FsaCommand::DisableVoltage.bits(),
                    clear: CW_COMMAND_MASK | CW_NEW_SETPOINT,
                });
                v.push(Step::AwaitStatus(Cond::Applied, c.state_timeout));
                v.push(Step::Cw {
                    set: CW_FAULT_RESET,
                    clear: 0,
                });
                v.push(Step::AwaitStatus(Cond::NotFault, c.state_timeout));
                v.push(Step::Cw {
                    set: 0,
                    clear: CW_FAULT_RESET,
                });
                v.push(Step::AwaitStatus(Cond::Applied, c.state_timeout));
            }
            Command::SdoRead(obj) => v.push(Step::Read(*obj, ReadUse::Reply)),
            Command::SdoWrite(obj, data) => v.push(Step::Write(SdoWrite::bytes(
                obj.index,
                obj.sub,
                data.clone(),
            ))),
        }
        v.into()
    }

    pub(super) fn plan_configure(&self, reset: bool) -> VecDeque<Step> {
        let mut v = vec![Step::SyncOff, Step::SetConfigured(false)];
        if reset {
            v.push(Step::Nmt(NmtCommand::ResetCommunication));
            v.push(Step::AwaitBootUp);
            // A power-on boot-up still in flight may have been taken for the reset's.
            v.push(Step::Settle(self.s.config().boot_settle));
        }
        v.push(Step::Nmt(NmtCommand::EnterPreOperational));
        v.push(Step::Read(ObjAddr::new(0x1000, 0), ReadUse::DeviceType));
        v.push(Step::Write(SdoWrite::u16(0x1017, 0, self.s.heartbeat_ms())));
        for w in pdo::follower_pdo_sequence(self.s.node()) {
            v.push(Step::Write(w));
        }
        for w in self.parameter_writes() {
            v.push(Step::Write(w));
        }
        v.push(Step::Read(ObjAddr::new(0x6041, 0), ReadUse::Statusword));
        v.push(Step::Read(ObjAddr::new(0x6064, 0), ReadUse::Position));
        v.push(Step::Read(ObjAddr::new(0x6061, 0), ReadUse::Mode));
        v.push(Step::AwaitNmt(NmtState::PreOperational));
        v.push(Step::SetConfigured(true));
        v.into()
    }

    fn plan_move(&self, v: &mut Vec<Step>, m: Motion) {
        v.push(Step::RequirePdo);
        v.push(Step::RequireEnabled);
        v.push(Step::RequireHomed);
        v.push(Step::CspLeave {
            stop_following: false,
        });
        v.push(Step::EnsureMode(MODE_PROFILE_POSITION));
        v.push(Step::Plan(m));
    }

    /// Time to stop from profile velocity at `decel`.
    fn stop_time(&self, decel: f64) -> Duration {
        Duration::from_secs_f64(self.s.config().profile.velocity_mm_s / decel)
    }

    /// How long a profile move over `dist_mm` takes (trapezoid or triangle).
    pub(super) fn move_time(&self, dist_mm: f64) -> Duration {
        let p = self.s.config().profile;
        let (v, a, d) = (p.velocity_mm_s, p.accel_mm_s2, p.decel_mm_s2);
        let dist = dist_mm.abs();
        let ramps = v * v / (2.0 * a) + v * v / (2.0 * d);
        let t = if dist >= ramps {
            dist / v + v / (2.0 * a) + v / (2.0 * d)
        } else {
            let vp = (2.0 * dist * a * d / (a + d)).sqrt();
            vp / a + vp / d
        };
        Duration::from_secs_f64(t.min(1e6))
    }

    /// A generous bound on the ramp coming to rest over `dist_mm` from `vel` (mm/s).
    pub(super) fn ramp_time(&self, dist_mm: f64, vel: f64) -> Duration {
        let p = self.s.config().profile;
        let (v, a) = (p.velocity_mm_s, p.accel_mm_s2);
        let t = dist_mm.abs() / v + 2.0 * v / a + vel.abs() / a;
        Duration::from_secs_f64((2.0 * t).min(1e6))
    }

    fn parameter_writes(&self) -> Vec<SdoWrite> {
        let c = self.s.config();
        let s = &self.s;
        let u = |v: f64| s.unsigned_counts(v).unwrap_or(u32::MAX);
        let i = |v: f64| s.mm_to_counts(v).unwrap_or(0);
        let mut w = vec![
            SdoWrite::u32(0x6081, 0, u(c.profile.velocity_mm_s)),
            SdoWrite::u32(0x6083, 0, u(c.profile.accel_mm_s2)),
            SdoWrite::u32(0x6084, 0, u(c.profile.decel_mm_s2)),
            SdoWrite::u32(0x6085, 0, u(c.profile.quick_stop_decel_mm_s2)).optional(),
            SdoWrite::u32(0x6067, 0, u(c.profile.position_window_mm)).optional(),
            SdoWrite::u32(0x6065, 0, u(c.profile.following_error_window_mm)).optional(),
            SdoWrite::i8(0x6098, 0, c.homing.method),
            SdoWrite::u32(0x6099, 1, u(c.homing.switch_speed_mm_s)),
            SdoWrite::u32(0x6099, 2, u(c.homing.zero_speed_mm_s)),
            SdoWrite::u32(0x609A, 0, u(c.homing.accel_mm_s2)).optional(),
            SdoWrite::i32(0x607C, 0, i(c.homing.offset_mm)).optional(),
        ];
        if c.limits.write_to_drive {
            w.push(SdoWrite::i32(0x607D, 1, i(c.limits.min_mm)).optional());
            w.push(SdoWrite::i32(0x607D, 2, i(c.limits.max_mm)).optional());
        }
        w
    }

    /// Turn a move into its concrete steps, now that the current state is known.
    pub(super) fn expand_move(&mut self, m: Motion) -> Progress {
        let c = *self.s.config();
        let base = self.commanded.or(self.status.position_counts).unwrap_or(0);
        let here = self.status.position_counts.unwrap_or(base);
        let (target_mm, relative, immediate) = match m {
            Motion::Absolute(t) => (t, false, c.profile.change_immediately),
            Motion::Track(t) => (t, false, true),
            Motion::Relative(d) => (self.s.counts_to_mm(base) + d, true, false),
        };
        let l = c.limits;
        if !(target_mm >= l.min_mm && target_mm <= l.max_mm) {
            return Progress::Fail(DriveError::OutOfLimits {
                target_mm,
                min_mm: l.min_mm,
                max_mm: l.max_mm,
            });
        }
        let Some(abs) = self.s.mm_to_counts(target_mm) else {
            return Progress::Fail(DriveError::OutOfLimits {
                target_mm,
                min_mm: l.min_mm,
                max_mm: l.max_mm,
            });
        };
        let value = if relative { abs - base } else { abs };
        let mut set = CW_NEW_SETPOINT;
        let mut clear = CW_HALT | CW_RELATIVE | CW_CHANGE_IMMEDIATELY;
        if relative {
            set |= CW_RELATIVE;
            clear &= !CW_RELATIVE;
        }
        if immediate {
            set |= CW_CHANGE_IMMEDIATELY;
            clear &= !CW_CHANGE_IMMEDIATELY;
        }
        let dist = self.s.counts_to_mm(abs) - self.s.counts_to_mm(here);
        let mut steps = vec![
            Step::AwaitStatus(Cond::AckClear, c.state_timeout),
            Step::Target(value),
            Step::Cw { set, clear },
            Step::AwaitStatus(Cond::AckSet, c.state_timeout),
            Step::Cw {
                set: 0,
                clear: CW_NEW_SETPOINT,
            },
            Step::Commanded(abs),
        ];
        if !matches!(m, Motion::Track(_)) {
            let t = self.move_time(dist) * 2 + c.profile.move_timeout_margin;
            steps.push(Step::AwaitStatus(Cond::TargetReached, t));
        }
        Progress::Replace(steps)
    }
}
