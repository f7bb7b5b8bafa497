//! The command engine: a command's program runs one `Step` at a time (`start_step`, then
//! `poll_step` until it is done, fails or times out), SDO results and reads put to their
//! use, the power and statusword waits, and a command's end (`finish`, `complete`; a
//! cancelled command's SDO transfer aborted).

use super::{Cond, DriveError, Event, FOLLOW, Master, Op, OpId, Progress, ReadUse, Reply, Step};
use crate::canopen::cia402::{
    self, CW_FAULT_RESET, CW_NEW_SETPOINT, HomingStatus, MODE_CSP, NextStep, PowerState, Statusword,
};
use crate::canopen::csp::{DemandRamp, TargetTrack};
use crate::canopen::nmt::command_frame;
use crate::canopen::pdo::SdoWrite;
use crate::canopen::sdo::{AbortCode, ObjAddr, SdoError, SdoOutcome, value};
use canopen_rs::NmtCommand;
use std::time::Instant;

impl Master {
    /// Report a command's end; a failed `Follow` ends following before it started.
    pub(super) fn complete(
        &mut self,
        id: OpId,
        name: &'static str,
        result: Result<Reply, DriveError>,
    ) {
        if name == FOLLOW
            && let Err(e) = &result
        {
            self.follow_track = TargetTrack::default();
            if self.follow_entry == Some(id) {
                tracing::warn!("the follower could not start following: {e}");
                self.follow_armed = false;
                self.events.push_back(Event::FollowingEnded(Err(e.clone())));
            }
        }
        if self.follow_entry == Some(id) {
            self.follow_entry = None;
        }
        self.events.push_back(Event::Completed { id, result });
    }

    pub(super) fn cancel_sdo_of(&mut self, op: &Op) {
        let in_sdo = op.started
            && matches!(
                op.steps.front(),
                Some(Step::Write(_) | Step::Read(..) | Step::AwaitMode(_))
            );
        if in_sdo && self.sdo.cancel(AbortCode::GENERAL) {
            // The cancelled transfer's own outcome is of no interest any more.
            while self.sdo.poll_outcome().is_some() {}
            while let Some(f) = self.sdo.poll_transmit() {
                self.tx.push_back(f);
            }
        }
        self.sdo_result = None;
    }

    pub(super) fn finish(&mut self, op: Op, result: Result<(), DriveError>) {
        let result = match result {
            Ok(()) => Ok(op.reply.map_or(Reply::Done, Reply::Data)),
            Err(e) => {
                tracing::warn!(op = op.name, "{e}");
                // Never leave a set-point, homing start or fault reset request standing.
                self.set_cw(self.cw & !(CW_NEW_SETPOINT | CW_FAULT_RESET));
                Err(e)
            }
        };
        self.status.busy = None;
        self.status.busy_since = None;
        self.complete(op.id, op.name, result);
    }

    pub(super) fn run(&mut self, now: Instant) {
        // A command under way (or one that ends in this call) counts as activity.
        if self.op.is_some() || !self.queue.is_empty() {
            self.active_at = Some(now);
        }
        loop {
            if self.op.is_none() {
                let Some((id, cmd)) = self.queue.pop_front() else {
                    break;
                };
                self.status.busy = Some(cmd.name());
                self.status.busy_since = Some(now);
                let steps = self.plan(&cmd);
                self.op = Some(Op {
                    id,
                    name: cmd.name(),
                    steps,
                    started: false,
                    deadline: None,
                    after_sync: 0,
                    boot_mark: 0,
                    seen_progress: false,
                    restarts: 0,
                    reply: None,
                });
            }
            let Some(mut op) = self.op.take() else {
                break;
            };
            let Some(step) = op.steps.front().cloned() else {
                self.finish(op, Ok(()));
                continue;
            };
            let progress = if op.started {
                self.poll_step(&mut op, &step, now)
            } else {
                op.started = true;
                self.start_step(&mut op, &step, now)
            };
            match progress {
                Progress::Next | Progress::Replace(_) => {
                    op.steps.pop_front();
                    if let Progress::Replace(steps) = progress {
                        for s in steps.into_iter().rev() {
                            op.steps.push_front(s);
                        }
                    }
                    op.started = false;
                    op.deadline = None;
                    self.op = Some(op);
                }
                Progress::Wait => {
                    if op.deadline.is_some_and(|d| now >= d) {
                        let err = self.timeout_error(&step);
                        self.cancel_sdo_of(&op);
                        self.finish(op, Err(err));
                        continue;
                    }
                    self.op = Some(op);
                    break;
                }
                Progress::Fail(e) => self.finish(op, Err(e)),
            }
        }
        self.pace_sync(now);
        self.status.sync_running = self.sync.is_running();
    }

    fn timeout_error(&self, step: &Step) -> DriveError {
        let c = self.s.config();
        match step {
            Step::AwaitBootUp => DriveError::Timeout {
                what: "boot-up after reset",
                after: c.boot_timeout,
            },
            Step::AwaitNmt(_) => DriveError::Timeout {
                what: "heartbeat with the requested NMT state",
                after: self.nmt_timeout(),
            },
            Step::AwaitMode(_) => DriveError::Timeout {
                what: "modes of operation display (0x6061)",
                after: c.state_timeout,
            },
            Step::AwaitTpdo => DriveError::Timeout {
                what: "TPDO1 after SYNC",
                after: c.state_timeout,
            },
            Step::Power(_) => DriveError::Timeout {
                what: "power state transition",
                after: c.state_timeout,
            },
            Step::AwaitStatus(cond, after) => DriveError::Timeout {
                what: cond.what(),
                after: *after,
            },
            _ => DriveError::Timeout {
                what: "drive response",
                after: c.state_timeout,
            },
        }
    }

    fn start_sdo(&mut self, r: Result<(), SdoError>) -> Progress {
        self.collect_sdo();
        match r {
            Ok(()) => Progress::Wait,
            Err(e) => Progress::Fail(e.into()),
        }
    }

    fn start_step(&mut self, op: &mut Op, step: &Step, now: Instant) -> Progress {
        let c = *self.s.config();
        match step {
            Step::SetConfigured(b) => {
                if !b {
                    self.forget_configuration();
                }
                self.status.configured = *b;
                Progress::Next
            }
            Step::RequireConfigured => {
                if self.status.configured {
                    Progress::Next
                } else {
                    Progress::Fail(DriveError::NotConfigured { what: op.name })
                }
            }
            Step::RequirePdo => {
                if self.pdo_active() && self.sync.is_running() {
                    Progress::Next
                } else {
                    Progress::Fail(DriveError::NotOperational { what: op.name })
                }
            }
            Step::RequireEnabled => match self.status.state {
                Some(PowerState::OperationEnabled) => Progress::Next,
                Some(st) if st.is_fault() => Progress::Fail(self.fault()),
                st => Progress::Fail(DriveError::NotEnabled {
                    what: op.name,
                    state: st.map_or("an unknown state".into(), |s| s.to_string()),
                }),
            },
            Step::RequireHomed => {
                if c.require_homing && !self.status.homed {
                    Progress::Fail(DriveError::NotHomed)
                } else {
                    Progress::Next
                }
            }
            Step::Nmt(n) => {
                if !matches!(n, NmtCommand::StartRemoteNode) {
                    self.abort_following(DriveError::Interrupted { by: "NMT command" });
                }
                op.boot_mark = self.boot_count;
                if matches!(n, NmtCommand::ResetNode | NmtCommand::ResetCommunication) {
                    self.forget_configuration();
                }
                if !matches!(n, NmtCommand::StartRemoteNode) {
                    self.sync.stop();
                }
                self.tx.push_back(command_frame(*n, self.s.node()));
                Progress::Next
            }
            Step::AwaitBootUp => {
                op.deadline = Some(now + c.boot_timeout);
                self.poll_step(op, step, now)
            }
            Step::AwaitNmt(_) => {
                op.deadline = Some(now + self.nmt_timeout());
                self.poll_step(op, step, now)
            }
            Step::Settle(d) => {
                op.deadline = Some(now + *d);
                self.poll_step(op, step, now)
            }
            Step::Write(w) => {
                let r = self.sdo.download(w.obj, w.data.clone(), now);
                self.start_sdo(r)
            }
            Step::Read(obj, _) => {
                let r = self.sdo.upload(*obj, now);
                self.start_sdo(r)
            }
            Step::EnsureMode(m) => {
                if self.status.mode == Some(*m) {
                    return Progress::Next;
                }
                self.status.mode = None;
                Progress::Replace(vec![
                    Step::Write(SdoWrite::i8(0x6060, 0, *m)),
                    Step::AwaitMode(*m),
                ])
            }
            Step::AwaitMode(_) => {
                op.deadline = Some(now + c.state_timeout);
                let r = self.sdo.upload(ObjAddr::new(0x6061, 0), now);
                self.start_sdo(r)
            }
            Step::SyncOn => {
                self.sync.start(now);
                Progress::Next
            }
            Step::SyncOff => {
                self.sync.stop();
                Progress::Next
            }
            Step::AwaitTpdo => {
                op.after_sync = self.sync.count() + 1;
                op.deadline = Some(now + c.state_timeout);
                Progress::Wait
            }
            Step::Power(_) => {
                op.deadline = Some(now + c.state_timeout);
                self.poll_step(op, step, now)
            }
            Step::Cw { set, clear } => {
                self.set_cw((self.cw & !clear) | set);
                Progress::Next
            }
            Step::Target(t) => {
                self.set_target(*t);
                Progress::Next
            }
            Step::Commanded(t) => {
                self.commanded = Some(*t);
                self.status.commanded_mm = Some(self.s.counts_to_mm(*t));
                Progress::Next
            }
            Step::Plan(m) => self.expand_move(*m),
            Step::AwaitStatus(_, after) => {
                op.deadline = Some(now + *after);
                self.poll_step(op, step, now)
            }
            Step::MarkHomed => {
                self.status.homed = true;
                if let Some(p) = self.status.position_counts {
                    self.commanded = Some(p);
                    self.status.commanded_mm = Some(self.s.counts_to_mm(p));
                    self.set_target(p);
                }
                Progress::Next
            }
            Step::CspEnter(t) => self.csp_enter(*t, now),
            Step::HoldActual => {
                if let Some(p) = self.status.position_counts {
                    self.set_target(p);
                }
                Progress::Next
            }
            Step::CspStart => {
                let (p, l) = (c.profile, c.limits);
                let start = self.s.counts_to_mm(self.target);
                let lead = c.csp_lead_periods * c.sync_period.as_secs_f64();
                let mut r =
                    DemandRamp::new(start, p.velocity_mm_s, p.accel_mm_s2, l.min_mm, l.max_mm)
                        .with_lead(lead);
                if let Some(g) = self.follow_track.latest() {
                    r.hold_at(g);
                }
                self.ramp = Some(r);
                self.ramp_new = true;
                self.commanded = Some(self.target);
                self.status.commanded_mm = Some(start);
                self.start_following();
                Progress::Next
            }
            Step::CspLeave { stop_following } => self.csp_leave(*stop_following),
            Step::CspEnd => {
                self.ramp = None;
                self.commanded = Some(self.target);
                self.status.commanded_mm = Some(self.s.counts_to_mm(self.target));
                Progress::Next
            }
        }
    }

    pub(super) fn fault(&self) -> DriveError {
        DriveError::Fault {
            emcy: self.status.last_emcy,
        }
    }

    fn poll_step(&mut self, op: &mut Op, step: &Step, now: Instant) -> Progress {
        match step {
            Step::AwaitBootUp => {
                if self.boot_count > op.boot_mark {
                    Progress::Next
                } else {
                    Progress::Wait
                }
            }
            Step::Settle(_) => {
                if op.deadline.is_none_or(|d| now >= d) {
                    Progress::Next
                } else {
                    Progress::Wait
                }
            }
            Step::AwaitNmt(want) => {
                if self.hb.state() == Some(*want) && self.hb.is_alive() {
                    Progress::Next
                } else {
                    Progress::Wait
                }
            }
            Step::Write(w) => match self.sdo_result.take() {
                None => Progress::Wait,
                Some(Ok(_)) => Progress::Next,
                Some(Err(e)) if w.optional && e.is_missing_object() => {
                    tracing::debug!("optional object {} absent on the drive", w.obj);
                    Progress::Next
                }
                Some(Err(e)) => Progress::Fail(e.into()),
            },
            Step::Read(obj, use_) => match self.sdo_result.take() {
                None => Progress::Wait,
                Some(Err(e)) => Progress::Fail(e.into()),
                Some(Ok(o)) => self.use_read(op, *obj, *use_, uploaded(o)),
            },
            Step::AwaitMode(m) => match self.sdo_result.take() {
                None => Progress::Wait,
                Some(Err(e)) => Progress::Fail(e.into()),
                Some(Ok(o)) => match value::i8(&uploaded(o)) {
                    Some(got) if got == *m => {
                        self.status.mode = Some(got);
                        Progress::Next
                    }
                    Some(_) => {
                        let r = self.sdo.upload(ObjAddr::new(0x6061, 0), now);
                        self.start_sdo(r)
                    }
                    None => Progress::Fail(DriveError::BadLength {
                        obj: ObjAddr::new(0x6061, 0),
                        len: 0,
                        want: 1,
                    }),
                },
            },
            Step::AwaitTpdo => {
                if self.status.tpdo_count > 0 && self.tpdo_sync >= op.after_sync {
                    Progress::Next
                } else {
                    Progress::Wait
                }
            }
            Step::Power(to) => self.poll_power(op, *to, now),
            Step::AwaitStatus(cond, _) => self.poll_status(op, *cond),
            _ => Progress::Next,
        }
    }

    fn use_read(&mut self, op: &mut Op, obj: ObjAddr, use_: ReadUse, data: Vec<u8>) -> Progress {
        let bad = |want: usize| {
            Progress::Fail(DriveError::BadLength {
                obj,
                len: data.len(),
                want,
            })
        };
        match use_ {
            ReadUse::DeviceType => match value::u32(&data) {
                Some(t) if t & 0xFFFF == 0x0192 => Progress::Next,
                Some(t) => Progress::Fail(DriveError::NotADrive(t)),
                None => bad(4),
            },
            ReadUse::Statusword => match value::u16(&data) {
                Some(sw) => {
                    self.set_statusword(sw);
                    Progress::Next
                }
                None => bad(2),
            },
            ReadUse::Position => match value::i32(&data) {
                Some(p) => {
                    self.set_position(p);
                    self.status.position_at = None;
                    self.set_target(p);
                    self.commanded = None;
                    self.status.commanded_mm = None;
                    Progress::Next
                }
                None => bad(4),
            },
            ReadUse::Mode => match value::i8(&data) {
                Some(m) => {
                    self.status.mode = Some(m);
                    Progress::Next
                }
                None => bad(1),
            },
            ReadUse::Reply => {
                op.reply = Some(data);
                Progress::Next
            }
        }
    }

    fn poll_power(&mut self, op: &mut Op, to: PowerState, now: Instant) -> Progress {
        if !self.fresh() {
            return Progress::Wait;
        }
        let Some(from) = self.status.state else {
            return Progress::Wait;
        };
        match cia402::next_step(from, to) {
            NextStep::Done => Progress::Next,
            NextStep::Wait => Progress::Wait,
            NextStep::Send(cmd) => {
                let cw = cmd.apply_to(self.cw) & !(CW_NEW_SETPOINT | CW_FAULT_RESET);
                if cw != self.cw {
                    self.set_cw(cw);
                    op.deadline = Some(now + self.s.config().state_timeout);
                }
                Progress::Wait
            }
            NextStep::Blocked if from.is_fault() => Progress::Fail(self.fault()),
            NextStep::Blocked => Progress::Fail(DriveError::NoPath { from, to }),
        }
    }

    fn poll_status(&mut self, op: &mut Op, cond: Cond) -> Progress {
        if !self.fresh() {
            return Progress::Wait;
        }
        let Some(sw) = self.status.statusword.map(Statusword) else {
            return Progress::Wait;
        };
        let st = sw.state();
        match cond {
            Cond::Applied => return Progress::Next,
            Cond::NotFault => {
                return match st {
                    Some(s) if !s.is_fault() => Progress::Next,
                    _ => Progress::Wait,
                };
            }
            _ => {}
        }
        if st.is_some_and(PowerState::is_fault) {
            return Progress::Fail(self.fault());
        }
        let enabled = st == Some(PowerState::OperationEnabled);
        let not_enabled = || DriveError::NotEnabled {
            what: op.name,
            state: st.map_or("an unknown state".into(), |s| s.to_string()),
        };
        match cond {
            Cond::Applied | Cond::NotFault => Progress::Next,
            Cond::AckSet | Cond::AckClear | Cond::TargetReached | Cond::CspSettled if !enabled => {
                Progress::Fail(not_enabled())
            }
            Cond::CspSettled if sw.following_error() => Progress::Fail(DriveError::FollowingError),
            // Reached and still (not passing through the window), before a mode switch.
            Cond::CspSettled => yes(self.ramp.is_none_or(|r| r.at_rest())
                && self.status.target_reached
                && self.standstill
                && self.tpdo_sync > self.demand_since),
            Cond::AckSet if sw.following_error() => Progress::Fail(DriveError::FollowingError),
            Cond::AckSet => yes(sw.setpoint_ack()),
            Cond::AckClear => yes(!sw.setpoint_ack()),
            Cond::TargetReached if sw.following_error() => {
                Progress::Fail(DriveError::FollowingError)
            }
            Cond::TargetReached => yes(sw.target_reached()),
            Cond::HomingDone => {
                if !enabled {
                    return Progress::Fail(not_enabled());
                }
                match sw.homing() {
                    HomingStatus::Completed => Progress::Next,
                    HomingStatus::InProgress | HomingStatus::AttainedNotReached => {
                        op.seen_progress = true;
                        Progress::Wait
                    }
                    HomingStatus::Interrupted if !op.seen_progress => Progress::Wait,
                    h => Progress::Fail(DriveError::Homing(h)),
                }
            }
            Cond::Stopped => yes(self.still(sw) || !enabled),
            Cond::QuickStopped => yes(st == Some(PowerState::SwitchOnDisabled)
                || (st == Some(PowerState::QuickStopActive) && self.still(sw))
                || !matches!(
                    st,
                    Some(PowerState::QuickStopActive | PowerState::OperationEnabled)
                )),
        }
    }

    /// At standstill: bit 10 (target reached, profile position and homing), or in cyclic
    /// synchronous position (where bit 10 is reserved) a position that stayed within the
    /// position window between the last two TPDOs.
    fn still(&self, sw: Statusword) -> bool {
        if self.status.mode == Some(MODE_CSP) {
            self.standstill
        } else {
            sw.target_reached()
        }
    }
}

/// The bytes of an upload (none for a download, which a read step never starts).
fn uploaded(o: SdoOutcome) -> Vec<u8> {
    match o {
        SdoOutcome::Uploaded { data, .. } => data,
        SdoOutcome::Downloaded { .. } => Vec::new(),
    }
}

fn yes(b: bool) -> Progress {
    if b { Progress::Next } else { Progress::Wait }
}
