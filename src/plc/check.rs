//! The check handshake (issue 30; `plc-maps/README.md` §5): the PLC asks for a short check of
//! the axis in a break by writing a new nonzero value into `check.request`; the service
//! answers in `check.answered` (the request it answers), `check.state` (busy, done, refused),
//! `check.result` (what the check found, or why it was refused) and `check.run` (the stored
//! run). The answer's fields are written in that reverse order, `answered` last, so a PLC that
//! sees its request answered reads a state and result that belong to it.
//!
//! A request is new when it is nonzero and not the one answered: a restarted service reads
//! what it answered back from the PLC and never runs a request twice. A request found answered
//! busy with no check in hand is one a restarted service had under way; the driver looks for
//! its run. A new request while a check runs waits for it to end (the PLC should wait for
//! done or refused before it asks again).
//!
//! Sans-I/O: the driver (`service::checks`) reads the fields when [`CheckHandshake::poll_timeout`]
//! is due, hands them to [`CheckHandshake::handle_read`], starts what it is told to, reports
//! how the check went, and writes what [`CheckHandshake::poll_write`] gives until it goes.

use super::Image;
use super::map::{CheckFields, Field};
use super::table::{TableError, field_regs, read_field};
use std::time::{Duration, Instant};

/// What the service says of a request (`check.state`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CheckState {
    /// Nothing asked yet.
    Idle,
    /// The check runs: the PLC keeps the axis free for it.
    Busy,
    /// The check ended; `check.result` says how.
    Done,
    /// The check was not run; `check.result` says why.
    Refused,
}

impl CheckState {
    pub fn code(self) -> u16 {
        match self {
            CheckState::Idle => 0,
            CheckState::Busy => 1,
            CheckState::Done => 2,
            CheckState::Refused => 3,
        }
    }

    pub fn from_code(c: u16) -> Option<CheckState> {
        [
            CheckState::Idle,
            CheckState::Busy,
            CheckState::Done,
            CheckState::Refused,
        ]
        .into_iter()
        .find(|s| s.code() == c)
    }

    pub fn words(self) -> &'static str {
        match self {
            CheckState::Idle => "idle",
            CheckState::Busy => "busy",
            CheckState::Done => "done",
            CheckState::Refused => "refused",
        }
    }
}

/// What a check found, or why it was not run or did not count (`check.result`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CheckResult {
    /// Nothing yet (busy).
    None,
    /// Stored and trended: every figure within its control limits and its tolerance.
    InControl,
    /// Stored and trended: too few checks under these tables for control limits yet.
    Learning,
    /// Stored and trended: a figure beyond its control limits that a compensation table
    /// reaches (a drift alarm: compose a table from the check; `axiscomp trend` names it).
    Drift,
    /// Stored and trended: a figure beyond its control limits that no table reaches (a
    /// reversal or repeatability growing, an angle, the beam's alignment): a maintenance alarm.
    Maintenance,
    /// Stored and trended: a figure beyond its tolerance (`[acceptance]`).
    Tolerance,
    /// Refused: no full run of the axis in the store to take the check's targets from.
    NoPlan,
    /// Refused by the service (the machine held by another procedure, the travel not aligned,
    /// …): the reason is in the audit log.
    NotStarted,
    /// Ended with flagged captures open: it counts once they are retaken or excluded.
    Flags,
    /// Failed or aborted (`axiscomp run status` says why).
    Failed,
    /// The service restarted and the check's run was no longer under way.
    Interrupted,
}

impl CheckResult {
    const ALL: [CheckResult; 11] = [
        CheckResult::None,
        CheckResult::InControl,
        CheckResult::Learning,
        CheckResult::Drift,
        CheckResult::Tolerance,
        CheckResult::Maintenance,
        CheckResult::NoPlan,
        CheckResult::NotStarted,
        CheckResult::Flags,
        CheckResult::Failed,
        CheckResult::Interrupted,
    ];

    pub fn code(self) -> u16 {
        match self {
            CheckResult::None => 0,
            CheckResult::InControl => 1,
            CheckResult::Learning => 2,
            CheckResult::Drift => 3,
            CheckResult::Tolerance => 4,
            CheckResult::Maintenance => 5,
            CheckResult::NoPlan => 16,
            CheckResult::NotStarted => 17,
            CheckResult::Flags => 18,
            CheckResult::Failed => 19,
            CheckResult::Interrupted => 20,
        }
    }

    pub fn from_code(c: u16) -> Option<CheckResult> {
        CheckResult::ALL.into_iter().find(|r| r.code() == c)
    }

    /// The state a request ends in with this result.
    pub fn state(self) -> CheckState {
        match self {
            CheckResult::None => CheckState::Busy,
            CheckResult::NoPlan | CheckResult::NotStarted => CheckState::Refused,
            _ => CheckState::Done,
        }
    }

    pub fn words(self) -> &'static str {
        match self {
            CheckResult::None => "none yet",
            CheckResult::InControl => "in control: every figure within its limits",
            CheckResult::Learning => "stored: too few checks for control limits yet",
            CheckResult::Drift => "drift within a table's reach: compose a table from the check",
            CheckResult::Maintenance => "maintenance alarm: a drift no table reaches",
            CheckResult::Tolerance => "a figure beyond its tolerance",
            CheckResult::NoPlan => {
                "refused: no full run of the axis to take the check's targets from"
            }
            CheckResult::NotStarted => "refused by the service: the reason is in the audit log",
            CheckResult::Flags => "ended with flagged captures open: retake or exclude them",
            CheckResult::Failed => "failed or aborted",
            CheckResult::Interrupted => "interrupted: the service restarted",
        }
    }
}

/// The check fields as read from the PLC.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Polled {
    pub request: u32,
    pub answered: u32,
    pub state: u16,
}

impl Polled {
    /// The fields the PLC's request is judged by, each from its own register table.
    pub fn reads(f: &CheckFields) -> [&Field; 3] {
        [&f.request, &f.answered, &f.state]
    }

    /// The fields from a register image read over [`Polled::reads`].
    pub fn read(f: &CheckFields, img: &Image) -> Polled {
        let get = |field: &Field| read_field(field, &|a| img.get(field.kind, a));
        Polled {
            request: get(&f.request) as u32,
            answered: get(&f.answered) as u32,
            state: get(&f.state) as u16,
        }
    }
}

/// An answer to write.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Answer {
    pub request: u32,
    pub state: CheckState,
    pub result: CheckResult,
    /// The stored run (0: none).
    pub run: u32,
}

impl Answer {
    /// The writes, in order (run, result, state, then answered): each field's address and
    /// registers. A run id beyond a u16 `run` field is written 0 (unknown).
    pub fn writes(&self, f: &CheckFields) -> Result<Vec<(u16, Vec<u16>)>, TableError> {
        let w = |field: &Field, v: f64| field_regs(field, v).map(|r| (field.address, r));
        let run = f64::from(self.run);
        Ok(vec![
            w(&f.run, if run > f.run.ty.range().1 { 0.0 } else { run })?,
            w(&f.result, f64::from(self.result.code()))?,
            w(&f.state, f64::from(self.state.code()))?,
            w(&f.answered, f64::from(self.request))?,
        ])
    }
}

/// What the driver is to do after a read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Next {
    /// Nothing new.
    Nothing,
    /// Start a check for this request (its busy answer is queued).
    Start(u32),
    /// This request was answered busy before the service restarted: find its run, and
    /// [`CheckHandshake::started`] or [`CheckHandshake::ended`] it.
    Resume(u32),
}

/// The handshake.
#[derive(Clone, Debug)]
pub struct CheckHandshake {
    every: Duration,
    next_read: Instant,
    /// The request in hand, and its run once started.
    current: Option<(u32, u32)>,
    unwritten: Option<Answer>,
}

impl CheckHandshake {
    /// A handshake that reads the PLC's fields every `every`, the first time at `now`.
    pub fn new(now: Instant, every: Duration) -> CheckHandshake {
        CheckHandshake {
            every,
            next_read: now,
            current: None,
            unwritten: None,
        }
    }

    /// When the fields are to be read next.
    pub fn poll_timeout(&self) -> Instant {
        self.next_read
    }

    /// The request in hand and its run (0 before it started).
    pub fn current(&self) -> Option<(u32, u32)> {
        self.current
    }

    /// The fields as read at `now`.
    pub fn handle_read(&mut self, now: Instant, p: Polled) -> Next {
        self.next_read = now + self.every;
        if self.current.is_some() || p.request == 0 {
            return Next::Nothing;
        }
        if p.request != p.answered {
            self.current = Some((p.request, 0));
            self.unwritten = Some(Answer {
                request: p.request,
                state: CheckState::Busy,
                result: CheckResult::None,
                run: 0,
            });
            return Next::Start(p.request);
        }
        if p.state == CheckState::Busy.code() {
            self.current = Some((p.request, 0));
            return Next::Resume(p.request);
        }
        Next::Nothing
    }

    /// A read that failed at `now` (the link down): read again after the period.
    pub fn read_failed(&mut self, now: Instant) {
        self.next_read = now + self.every;
    }

    /// The check for `request` runs as stored run `run`.
    pub fn started(&mut self, request: u32, run: u32) {
        if self.current.map(|c| c.0) == Some(request) {
            self.current = Some((request, run));
            self.unwritten = Some(Answer {
                request,
                state: CheckState::Busy,
                result: CheckResult::None,
                run,
            });
        }
    }

    /// The check for `request` ended (or was refused) with `result`.
    pub fn ended(&mut self, request: u32, result: CheckResult) {
        let Some((r, run)) = self.current else {
            return;
        };
        if r != request {
            return;
        }
        self.current = None;
        self.unwritten = Some(Answer {
            request,
            state: result.state(),
            result,
            run,
        });
    }

    /// The answer to write now, if any; handed back by [`CheckHandshake::write_failed`] when
    /// it did not go.
    pub fn poll_write(&mut self) -> Option<Answer> {
        self.unwritten.take()
    }

    /// `a` could not be written: it is offered again, unless a newer answer came since.
    pub fn write_failed(&mut self, a: Answer) {
        if self.unwritten.is_none() {
            self.unwritten = Some(a);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::modbus::RegisterKind;
    use crate::plc::CncMap;

    fn generic() -> CheckFields {
        CncMap::generic()
            .expect("the generic map")
            .check
            .expect("the generic map has the check fields")
    }

    fn polled(request: u32, answered: u32, state: CheckState) -> Polled {
        Polled {
            request,
            answered,
            state: state.code(),
        }
    }

    #[test]
    fn a_new_request_is_answered_busy_then_done_answered_last() {
        let t0 = Instant::now();
        let mut h = CheckHandshake::new(t0, Duration::from_secs(1));
        assert_eq!(h.poll_timeout(), t0);
        assert_eq!(
            h.handle_read(t0, polled(0, 0, CheckState::Idle)),
            Next::Nothing
        );
        assert_eq!(h.poll_timeout(), t0 + Duration::from_secs(1));
        let t1 = t0 + Duration::from_secs(1);
        assert_eq!(
            h.handle_read(t1, polled(7, 0, CheckState::Idle)),
            Next::Start(7)
        );
        let busy = h.poll_write().expect("busy is answered at once");
        assert_eq!(
            (busy.request, busy.state, busy.run),
            (7, CheckState::Busy, 0)
        );
        // While it runs, the same request (or a new one) starts nothing.
        assert_eq!(
            h.handle_read(t1, polled(7, 7, CheckState::Busy)),
            Next::Nothing
        );
        assert_eq!(
            h.handle_read(t1, polled(8, 7, CheckState::Busy)),
            Next::Nothing
        );
        h.started(7, 42);
        assert_eq!(h.poll_write().map(|a| a.run), Some(42));
        h.ended(7, CheckResult::Drift);
        let done = h.poll_write().expect("the end is answered");
        assert_eq!(
            (done.state, done.result, done.run),
            (CheckState::Done, CheckResult::Drift, 42)
        );
        // The registers of the generic map (plc-maps/cnc/generic.toml: request 10, answered
        // 11, state 12, result 13, run 14-15 big-endian), written with answered last.
        let w = done.writes(&generic()).expect("fits");
        assert_eq!(
            w,
            vec![
                (14, vec![0, 42]),
                (13, vec![3]),
                (12, vec![2]),
                (11, vec![7])
            ]
        );
        // The PLC's image after the writes reads the request answered, done.
        let mut img = Image::default();
        img.put(RegisterKind::Holding, 10, &[7]);
        for (a, regs) in &w {
            img.put(RegisterKind::Holding, *a, regs);
        }
        let p = Polled::read(&generic(), &img);
        assert_eq!(p, polled(7, 7, CheckState::Done));
        assert_eq!(h.handle_read(t1, p), Next::Nothing);
        // The next request after it is new.
        assert_eq!(
            h.handle_read(t1, polled(8, 7, CheckState::Done)),
            Next::Start(8)
        );
    }

    #[test]
    fn a_refusal_ends_the_request_refused_and_a_failed_write_is_offered_again() {
        let t0 = Instant::now();
        let mut h = CheckHandshake::new(t0, Duration::from_secs(1));
        assert_eq!(
            h.handle_read(t0, polled(3, 2, CheckState::Done)),
            Next::Start(3)
        );
        let busy = h.poll_write().expect("busy");
        h.ended(3, CheckResult::NoPlan);
        let refused = h.poll_write().expect("refused");
        assert_eq!(refused.state, CheckState::Refused);
        assert_eq!(refused.result.code(), 16);
        // The busy answer failing after the refusal was queued does not replace it.
        h.write_failed(refused);
        h.write_failed(busy);
        assert_eq!(h.poll_write(), Some(refused));
        assert_eq!(h.poll_write(), None);
    }

    #[test]
    fn a_request_answered_busy_before_a_restart_is_resumed_not_started_again() {
        let t0 = Instant::now();
        let mut h = CheckHandshake::new(t0, Duration::from_secs(1));
        assert_eq!(
            h.handle_read(t0, polled(5, 5, CheckState::Busy)),
            Next::Resume(5)
        );
        assert_eq!(
            h.poll_write(),
            None,
            "nothing is written before the run is found"
        );
        h.ended(5, CheckResult::Interrupted);
        let a = h.poll_write().expect("answered");
        assert_eq!((a.state, a.result.code()), (CheckState::Done, 20));
        // Answered done: nothing more.
        assert_eq!(
            h.handle_read(t0, polled(5, 5, CheckState::Done)),
            Next::Nothing
        );
    }

    #[test]
    fn every_code_reads_back_and_results_end_in_their_state() {
        for r in CheckResult::ALL {
            assert_eq!(CheckResult::from_code(r.code()), Some(r));
        }
        for s in [
            CheckState::Idle,
            CheckState::Busy,
            CheckState::Done,
            CheckState::Refused,
        ] {
            assert_eq!(CheckState::from_code(s.code()), Some(s));
        }
        assert_eq!(CheckResult::NotStarted.state(), CheckState::Refused);
        assert_eq!(CheckResult::Flags.state(), CheckState::Done);
        assert_eq!(CheckResult::from_code(6), None);
    }
}
