//! Push: publishing a table into the PLC (DESIGN §6), as a sans-I/O machine in quinn-proto's
//! shape — inputs `handle_reply(now, id, reply)` and `handle_timeout(now)`, outputs
//! `poll_transmit(now)` (the Modbus requests to make, one at a time), `poll_timeout()` and
//! `poll_event()` — plus [`publish`], a thin async driver over our `modbus::Link`.
//!
//! The steps, each gated on the one before:
//! 1. wait until the PLC is ready (`plc_ready` = 1, `status` not busy) and alive (its heartbeat
//!    changed), polling its fields every `poll`; link errors are tolerated here until the
//!    `ready` deadline (the link may be reconnecting), a heartbeat that does not change within
//!    `heartbeat` fails at once;
//! 2. write the header and payload in chunks of at most 120 registers;
//! 3. read every chunk back and compare;
//! 4. write the commit word with the new sequence — only after the read-back matched;
//! 5. poll until the PLC echoes the sequence in `status_sequence` with accepted or rejected,
//!    up to `echo`.
//!
//! Any link error while writing or reading back ends the publish before the commit word: the
//! PLC's active table is untouched (it applies nothing until a commit). Nothing is sent after
//! the machine is done — no retry, no second commit; the caller publishes again with a new
//! sequence.

use super::map::CncMap;
use super::table::{Encoded, MAX_CHUNK, PlcTable, RejectCode, TableError};
use super::{Image, PlcStatus, StatusCode, status_reads};
use crate::modbus::codec::ReadRange;
use crate::modbus::link::ReplyFault;
use crate::modbus::{Link, LinkError, RegisterKind};
use std::collections::VecDeque;
use std::time::{Duration, Instant};
use thiserror::Error;

/// How long each step may take.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Timeouts {
    /// Until the PLC is ready and alive (default 5 s).
    pub ready: Duration,
    /// The heartbeat must change within this (default 2 s).
    pub heartbeat: Duration,
    /// Between status polls (default 50 ms).
    pub poll: Duration,
    /// Until the PLC echoes the sequence after the commit (default 5 s).
    pub echo: Duration,
}

impl Default for Timeouts {
    fn default() -> Self {
        Timeouts {
            ready: Duration::from_secs(5),
            heartbeat: Duration::from_secs(2),
            poll: Duration::from_millis(50),
            echo: Duration::from_secs(5),
        }
    }
}

/// A Modbus request the machine wants made.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Request {
    /// Read `range` of `kind` (function 3 or 4).
    Read {
        kind: RegisterKind,
        range: ReadRange,
    },
    /// Write holding registers from `start` (function 16, 1..=120 registers).
    Write { start: u16, values: Vec<u16> },
}

/// A request to make, with the id its reply is handed back under.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Transmit {
    pub id: u64,
    pub unit: u8,
    pub request: Request,
}

/// The reply to a [`Transmit`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Reply {
    Registers(Vec<u16>),
    Written,
}

/// Where the publish is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    WaitReady,
    Write,
    ReadBack,
    Commit,
    WaitEcho,
}

/// What the PLC made of a committed table.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PublishOutcome {
    /// Echoed as accepted: the table is active.
    Accepted { sequence: u32, active_sequence: u32 },
    /// Echoed as rejected with `code`: the PLC kept its previous table (`active_sequence`).
    Rejected {
        sequence: u32,
        code: RejectCode,
        active_sequence: u32,
    },
}

/// Why a publish failed (no answer from the PLC about this table).
#[derive(Clone, Debug, Error, PartialEq)]
pub enum PublishError {
    #[error("the table cannot be encoded for this PLC: {0}")]
    Table(#[from] TableError),
    #[error(
        "sequence {sequence} is already known to the PLC (its status is for {status_sequence}, its active table is {active_sequence}): publish with a new sequence; nothing was written"
    )]
    SequenceInUse {
        sequence: u32,
        status_sequence: u32,
        active_sequence: u32,
    },
    #[error("the PLC was not ready within {:.1} s: {why}; nothing was written", waited.as_secs_f64())]
    NotReady {
        waited: Duration,
        why: String,
        last: Option<PlcStatus>,
    },
    #[error(
        "the PLC's heartbeat stayed at {heartbeat} for {:.1} s: its program is not running; nothing was written", waited.as_secs_f64()
    )]
    NotAlive { heartbeat: u16, waited: Duration },
    #[error("{step}: {error}; {}", if *.commit_sent {
        "the commit word was sent: the PLC may have applied the table, read its active sequence"
    } else {
        "the commit word was not written: the PLC's active table is unchanged"
    })]
    Link {
        step: String,
        error: LinkError,
        commit_sent: bool,
    },
    #[error(
        "read-back mismatch at register {address} ({doc}, {key}): wrote 0x{wrote:04X}, read 0x{read:04X}; the commit word was not written: the PLC's active table is unchanged"
    )]
    ReadBack {
        address: u16,
        doc: String,
        key: String,
        wrote: u16,
        read: u16,
    },
    #[error(
        "no echo of sequence {sequence} within {:.1} s after the commit ({}); the PLC may still apply it: read its active sequence before publishing again",
        waited.as_secs_f64(),
        match last { Some(s) => s.to_string(), None => "its status could not be read".into() }
    )]
    NoEcho {
        sequence: u32,
        waited: Duration,
        last: Option<PlcStatus>,
        link_error: Option<LinkError>,
    },
}

impl PublishError {
    /// Whether the commit word went out (so the PLC may have applied the table).
    pub fn commit_sent(&self) -> bool {
        match self {
            PublishError::Link { commit_sent, .. } => *commit_sent,
            PublishError::NoEcho { .. } => true,
            _ => false,
        }
    }
}

/// What the machine reports.
#[derive(Clone, Debug, PartialEq)]
pub enum Event {
    /// A step started.
    Phase(Phase),
    /// Registers written so far, of the total.
    Written { registers: usize, total: usize },
    /// The end.
    Done(Result<PublishOutcome, PublishError>),
}

#[derive(Clone, Copy, Debug)]
enum Pending {
    Status(usize),
    Write(usize),
    ReadBack(usize),
    Commit,
}

#[derive(Debug, Default)]
struct Poll {
    /// The next read of the poll in progress, if one is.
    next: Option<usize>,
    image: Image,
}

#[derive(Debug)]
enum State {
    WaitReady {
        first_heartbeat: Option<(u16, Instant)>,
        alive: bool,
        next_poll: Instant,
        poll: Poll,
    },
    Write(usize),
    ReadBack(usize),
    Commit,
    WaitEcho {
        since: Instant,
        next_poll: Instant,
        poll: Poll,
    },
    Done,
}

/// The push handshake for one table (see the module docs).
#[derive(Debug)]
pub struct Publisher {
    map: CncMap,
    encoded: Encoded,
    chunks: Vec<(u16, Vec<u16>)>,
    reads: Vec<(RegisterKind, ReadRange)>,
    timeouts: Timeouts,
    started: Instant,
    state: State,
    next_id: u64,
    inflight: Option<(u64, Pending)>,
    events: VecDeque<Event>,
    written: usize,
    total: usize,
    last_status: Option<PlcStatus>,
    last_link_error: Option<LinkError>,
}

impl Publisher {
    /// Publish `encoded` (from `table::encode` with this `map`), starting at `now`.
    pub fn new(map: &CncMap, encoded: Encoded, timeouts: Timeouts, now: Instant) -> Publisher {
        let chunks = encoded.chunks(MAX_CHUNK);
        let total = chunks.iter().map(|c| c.1.len()).sum();
        let mut events = VecDeque::new();
        events.push_back(Event::Phase(Phase::WaitReady));
        Publisher {
            map: map.clone(),
            encoded,
            chunks,
            reads: status_reads(map),
            timeouts,
            started: now,
            state: State::WaitReady {
                first_heartbeat: None,
                alive: false,
                next_poll: now,
                poll: Poll::default(),
            },
            next_id: 0,
            inflight: None,
            events,
            written: 0,
            total,
            last_status: None,
            last_link_error: None,
        }
    }

    /// Encode `table` and start publishing it.
    pub fn for_table(
        map: &CncMap,
        table: &PlcTable,
        sequence: u32,
        timeouts: Timeouts,
        now: Instant,
    ) -> Result<Publisher, TableError> {
        let e = super::table::encode(table, map, sequence)?;
        Ok(Publisher::new(map, e, timeouts, now))
    }

    /// The sequence being published.
    pub fn sequence(&self) -> u32 {
        self.encoded.sequence
    }

    /// The encoded table.
    pub fn encoded(&self) -> &Encoded {
        &self.encoded
    }

    /// Whether the machine is done (its last event is, or was, `Done`).
    pub fn is_done(&self) -> bool {
        matches!(self.state, State::Done)
    }

    /// The next event.
    pub fn poll_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    fn send(&mut self, pending: Pending, request: Request) -> Transmit {
        let id = self.next_id;
        self.next_id += 1;
        self.inflight = Some((id, pending));
        Transmit {
            id,
            unit: self.map.unit_id,
            request,
        }
    }

    /// The next request to make, if one is due at `now` (one at a time: none while a reply
    /// is outstanding).
    pub fn poll_transmit(&mut self, now: Instant) -> Option<Transmit> {
        if self.inflight.is_some() {
            return None;
        }
        let (pending, request) = match &mut self.state {
            State::Done => return None,
            State::WaitReady {
                next_poll, poll, ..
            }
            | State::WaitEcho {
                next_poll, poll, ..
            } => {
                let k = match poll.next {
                    Some(k) => k,
                    None if now >= *next_poll => {
                        *poll = Poll {
                            next: Some(0),
                            image: Image::default(),
                        };
                        0
                    }
                    None => return None,
                };
                let (kind, range) = self.reads.get(k).copied()?;
                (Pending::Status(k), Request::Read { kind, range })
            }
            State::Write(k) => {
                let (start, values) = self.chunks.get(*k)?.clone();
                (Pending::Write(*k), Request::Write { start, values })
            }
            State::ReadBack(k) => {
                let (start, values) = self.chunks.get(*k)?;
                // Chunks hold 1..=120 registers inside the address space.
                let range = ReadRange::new(*start, values.len() as u16).ok()?;
                (
                    Pending::ReadBack(*k),
                    Request::Read {
                        kind: RegisterKind::Holding,
                        range,
                    },
                )
            }
            State::Commit => (
                Pending::Commit,
                Request::Write {
                    start: self.map.handshake.commit.address,
                    values: self.encoded.commit.clone(),
                },
            ),
        };
        Some(self.send(pending, request))
    }

    /// When `handle_timeout` must be called next (none while a request is outstanding or a
    /// request is due).
    pub fn poll_timeout(&self) -> Option<Instant> {
        if self.inflight.is_some() {
            return None;
        }
        match &self.state {
            State::WaitReady {
                first_heartbeat,
                alive,
                next_poll,
                poll,
            } if poll.next.is_none() => {
                let mut t = (*next_poll).min(self.started + self.timeouts.ready);
                if let (Some((_, t0)), false) = (first_heartbeat, alive) {
                    t = t.min(*t0 + self.timeouts.heartbeat);
                }
                Some(t)
            }
            State::WaitEcho {
                since,
                next_poll,
                poll,
            } if poll.next.is_none() => Some((*next_poll).min(*since + self.timeouts.echo)),
            _ => None,
        }
    }

    /// Time passed: check the deadlines.
    pub fn handle_timeout(&mut self, now: Instant) {
        self.check_deadlines(now);
    }

    fn finish(&mut self, r: Result<PublishOutcome, PublishError>) {
        self.state = State::Done;
        self.inflight = None;
        self.events.push_back(Event::Done(r));
    }

    fn fail(&mut self, e: PublishError) {
        self.finish(Err(e));
    }

    fn enter(&mut self, state: State, phase: Phase) {
        self.state = state;
        self.events.push_back(Event::Phase(phase));
    }

    fn check_deadlines(&mut self, now: Instant) {
        match &self.state {
            State::WaitReady {
                first_heartbeat,
                alive,
                ..
            } => {
                if let (Some((hb, t0)), false) = (*first_heartbeat, *alive) {
                    let waited = now.saturating_duration_since(t0);
                    if waited >= self.timeouts.heartbeat {
                        return self.fail(PublishError::NotAlive {
                            heartbeat: hb,
                            waited,
                        });
                    }
                }
                let waited = now.saturating_duration_since(self.started);
                if waited >= self.timeouts.ready {
                    let why = match (self.last_status, self.last_link_error) {
                        (Some(s), _) if !s.is_ready() => format!("plc_ready is {}", s.ready),
                        (Some(s), _) if s.status == StatusCode::Busy => "its status is busy".into(),
                        (Some(_), _) => "its heartbeat has not changed yet".into(),
                        (None, Some(e)) => format!("its status could not be read: {e}"),
                        (None, None) => "no status read yet".into(),
                    };
                    let last = self.last_status;
                    self.fail(PublishError::NotReady { waited, why, last });
                }
            }
            State::WaitEcho { since, .. } => {
                let waited = now.saturating_duration_since(*since);
                if waited >= self.timeouts.echo {
                    let (last, link_error) = (self.last_status, self.last_link_error);
                    self.fail(PublishError::NoEcho {
                        sequence: self.encoded.sequence,
                        waited,
                        last,
                        link_error,
                    });
                }
            }
            _ => {}
        }
    }

    fn doc_span(&self, start: u16, n: usize) -> String {
        format!(
            "registers {start}..{} ({}..)",
            start as usize + n,
            self.map.doc_holding(start)
        )
    }

    /// The reply to request `id`, at `now`. Replies to anything but the outstanding request
    /// (e.g. late ones after the machine is done) are ignored.
    pub fn handle_reply(&mut self, now: Instant, id: u64, reply: Result<Reply, LinkError>) {
        let pending = match self.inflight {
            Some((i, p)) if i == id => p,
            _ => return,
        };
        self.inflight = None;
        match pending {
            Pending::Status(k) => match reply {
                Ok(Reply::Registers(v)) => {
                    let (kind, range) = self.reads[k];
                    let poll = match &mut self.state {
                        State::WaitReady { poll, .. } | State::WaitEcho { poll, .. } => poll,
                        _ => return,
                    };
                    poll.image.put(kind, range.start(), &v);
                    if k + 1 < self.reads.len() {
                        poll.next = Some(k + 1);
                    } else {
                        poll.next = None;
                        let st = poll.image.status(&self.map);
                        self.on_status(now, st);
                    }
                }
                other => {
                    let e = match other {
                        Err(e) => e,
                        Ok(_) => LinkError::InvalidReply(ReplyFault::Function),
                    };
                    // Tolerated while waiting (the link may be reconnecting): poll again.
                    self.last_link_error = Some(e);
                    if let State::WaitReady {
                        next_poll, poll, ..
                    }
                    | State::WaitEcho {
                        next_poll, poll, ..
                    } = &mut self.state
                    {
                        poll.next = None;
                        *next_poll = now + self.timeouts.poll;
                    }
                    self.check_deadlines(now);
                }
            },
            Pending::Write(k) => match reply {
                Ok(Reply::Written) => {
                    self.written += self.chunks[k].1.len();
                    self.events.push_back(Event::Written {
                        registers: self.written,
                        total: self.total,
                    });
                    if k + 1 < self.chunks.len() {
                        self.state = State::Write(k + 1);
                    } else {
                        self.enter(State::ReadBack(0), Phase::ReadBack);
                    }
                }
                other => {
                    let (start, values) = &self.chunks[k];
                    let step = format!("writing {}", self.doc_span(*start, values.len()));
                    self.link_failure(step, other, false);
                }
            },
            Pending::ReadBack(k) => match reply {
                Ok(Reply::Registers(v)) => {
                    let (start, wrote) = &self.chunks[k];
                    let diff = wrote
                        .iter()
                        .zip(v.iter().chain(std::iter::repeat(&0)))
                        .position(|(w, r)| w != r);
                    if let Some(i) = diff.or((v.len() != wrote.len()).then_some(v.len())) {
                        let address = start + i as u16;
                        let e = PublishError::ReadBack {
                            address,
                            doc: self.map.doc_holding(address),
                            key: self.encoded.key_at(address),
                            wrote: wrote.get(i).copied().unwrap_or(0),
                            read: v.get(i).copied().unwrap_or(0),
                        };
                        return self.fail(e);
                    }
                    if k + 1 < self.chunks.len() {
                        self.state = State::ReadBack(k + 1);
                    } else {
                        self.enter(State::Commit, Phase::Commit);
                    }
                }
                other => {
                    let (start, values) = &self.chunks[k];
                    let step = format!("reading back {}", self.doc_span(*start, values.len()));
                    self.link_failure(step, other, false);
                }
            },
            Pending::Commit => match reply {
                Ok(Reply::Written) => {
                    self.last_link_error = None;
                    self.enter(
                        State::WaitEcho {
                            since: now,
                            next_poll: now,
                            poll: Poll::default(),
                        },
                        Phase::WaitEcho,
                    );
                }
                other => {
                    let f = &self.map.handshake.commit;
                    let step = format!(
                        "writing the commit word at {} ({})",
                        f.address,
                        self.map.doc(f)
                    );
                    // The request went out: whether the PLC took it is unknown.
                    self.link_failure(step, other, true);
                }
            },
        }
    }

    fn link_failure(&mut self, step: String, reply: Result<Reply, LinkError>, commit_sent: bool) {
        let error = match reply {
            Err(e) => e,
            Ok(_) => LinkError::InvalidReply(ReplyFault::Function),
        };
        self.fail(PublishError::Link {
            step,
            error,
            commit_sent,
        });
    }

    fn on_status(&mut self, now: Instant, st: PlcStatus) {
        let first = self.last_status.is_none();
        self.last_status = Some(st);
        let seq = self.encoded.sequence;
        let poll_every = self.timeouts.poll;
        match &mut self.state {
            State::WaitReady {
                first_heartbeat,
                alive,
                next_poll,
                ..
            } => {
                if first && (st.status_sequence == seq || st.active_sequence == seq) {
                    return self.fail(PublishError::SequenceInUse {
                        sequence: seq,
                        status_sequence: st.status_sequence,
                        active_sequence: st.active_sequence,
                    });
                }
                match first_heartbeat {
                    None => *first_heartbeat = Some((st.heartbeat, now)),
                    Some((hb, _)) if *hb != st.heartbeat => *alive = true,
                    Some(_) => {}
                }
                if *alive && st.is_ready() && st.status != StatusCode::Busy {
                    self.events.push_back(Event::Phase(Phase::Write));
                    self.state = State::Write(0);
                    return;
                }
                *next_poll = now + poll_every;
            }
            State::WaitEcho { next_poll, .. } => {
                if st.status_sequence == seq {
                    match st.status {
                        StatusCode::Accepted => {
                            return self.finish(Ok(PublishOutcome::Accepted {
                                sequence: seq,
                                active_sequence: st.active_sequence,
                            }));
                        }
                        StatusCode::Rejected => {
                            return self.finish(Ok(PublishOutcome::Rejected {
                                sequence: seq,
                                code: RejectCode::from_code(st.error_code),
                                active_sequence: st.active_sequence,
                            }));
                        }
                        _ => {}
                    }
                }
                *next_poll = now + poll_every;
            }
            _ => return,
        }
        self.check_deadlines(now);
    }
}

/// Publish `table` with `sequence` into the PLC behind `link` per `map` (see the module docs).
/// `Ok` when the PLC answered (accepted or rejected with its code); `Err` when it did not,
/// saying how far the publish got and whether the commit word went out.
pub async fn publish(
    link: &Link,
    map: &CncMap,
    table: &PlcTable,
    sequence: u32,
    timeouts: Timeouts,
) -> Result<PublishOutcome, PublishError> {
    publish_with(link, map, table, sequence, timeouts, |_| {}).await
}

/// [`publish`], reporting each event (phases, progress) to `on_event` as it happens.
pub async fn publish_with(
    link: &Link,
    map: &CncMap,
    table: &PlcTable,
    sequence: u32,
    timeouts: Timeouts,
    mut on_event: impl FnMut(&Event),
) -> Result<PublishOutcome, PublishError> {
    let mut m = Publisher::for_table(map, table, sequence, timeouts, crate::util::clock::now())?;
    loop {
        while let Some(ev) = m.poll_event() {
            on_event(&ev);
            if let Event::Done(r) = ev {
                return r;
            }
        }
        if let Some(tx) = m.poll_transmit(crate::util::clock::now()) {
            let reply = match tx.request {
                Request::Read { kind, range } => {
                    link.read(kind, tx.unit, range).await.map(Reply::Registers)
                }
                Request::Write { start, values } => link
                    .write_multiple_registers(tx.unit, start, &values)
                    .await
                    .map(|_| Reply::Written),
            };
            m.handle_reply(crate::util::clock::now(), tx.id, reply);
            continue;
        }
        // Waiting: sleep to the machine's next deadline (a due poll is sent above).
        let at = m
            .poll_timeout()
            .unwrap_or_else(|| crate::util::clock::now() + timeouts.poll);
        tokio::time::sleep_until(tokio::time::Instant::from_std(at)).await;
        m.handle_timeout(crate::util::clock::now());
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::comp::{MachineAxis, TableKind};
    use crate::plc::table::{self, TableDirection};

    const MS: Duration = Duration::from_millis(1);

    fn map() -> CncMap {
        CncMap::generic().unwrap()
    }

    fn table(n: usize) -> PlcTable {
        PlcTable {
            kind: TableKind::Positioning,
            axis: MachineAxis::Y,
            base_axis: MachineAxis::Y,
            direction: TableDirection::Both,
            start_mm: 0.0,
            interval_mm: 4.0,
            values_mm: (0..n).map(|k| (k as f64 * 0.1).sin() * 0.02).collect(),
            down_mm: None,
        }
    }

    /// A PLC in memory following the generic map: holding registers only.
    struct FakePlc {
        regs: Vec<u16>,
        map: CncMap,
        /// What it does with a commit: Some(Ok(())) accept, Some(Err(code)) reject, None mute.
        on_commit: Option<Result<(), u16>>,
        heartbeat_step: u16,
        corrupt: Option<u16>,
    }

    impl FakePlc {
        fn new() -> FakePlc {
            let map = map();
            let mut p = FakePlc {
                regs: vec![0; 4200],
                map,
                on_commit: Some(Ok(())),
                heartbeat_step: 1,
                corrupt: None,
            };
            p.set_status(PlcStatus {
                ready: 1,
                heartbeat: 100,
                status: StatusCode::Idle,
                error_code: 0,
                status_sequence: 4,
                active_sequence: 4,
            });
            p
        }
        fn status(&self) -> PlcStatus {
            PlcStatus::decode(&self.map, &|a| self.regs[a as usize], &|_| 0)
        }
        fn set_status(&mut self, st: PlcStatus) {
            for (_, a, r) in st.encode(&self.map) {
                self.regs[a as usize..a as usize + r.len()].copy_from_slice(&r);
            }
        }
        fn answer(&mut self, tx: &Transmit) -> Result<Reply, LinkError> {
            match &tx.request {
                Request::Read { range, .. } => {
                    let v = self.regs[range.start() as usize..range.end() as usize].to_vec();
                    // Each status poll sees a newer heartbeat.
                    if range.start() == 0 {
                        let mut st = self.status();
                        st.heartbeat = st.heartbeat.wrapping_add(self.heartbeat_step);
                        self.set_status(st);
                    }
                    Ok(Reply::Registers(v))
                }
                Request::Write { start, values } => {
                    let s = *start as usize;
                    self.regs[s..s + values.len()].copy_from_slice(values);
                    if let Some(a) = self.corrupt
                        && (s..s + values.len()).contains(&(a as usize))
                    {
                        self.regs[a as usize] ^= 0x0100;
                    }
                    if *start == 8 {
                        let seq = (values[0] as u32) << 16 | values[1] as u32;
                        let mut st = self.status();
                        match self.on_commit {
                            Some(Ok(())) => {
                                st.status = StatusCode::Accepted;
                                st.status_sequence = seq;
                                st.active_sequence = seq;
                                st.error_code = 0;
                            }
                            Some(Err(code)) => {
                                st.status = StatusCode::Rejected;
                                st.status_sequence = seq;
                                st.error_code = code;
                            }
                            None => {}
                        }
                        self.set_status(st);
                    }
                    Ok(Reply::Written)
                }
            }
        }
    }

    /// Run the machine against `plc` on a virtual clock; `fail` may replace the reply to
    /// request k. Returns the requests made and the outcome.
    fn run(
        plc: &mut FakePlc,
        m: &mut Publisher,
        t0: Instant,
        rtt: Duration,
        mut fail: impl FnMut(u64, &Transmit) -> Option<Result<Reply, LinkError>>,
    ) -> (Vec<Request>, Result<PublishOutcome, PublishError>, Instant) {
        let mut now = t0;
        let mut log = Vec::new();
        for _ in 0..100_000 {
            while let Some(ev) = m.poll_event() {
                if let Event::Done(r) = ev {
                    // Nothing is sent after the end.
                    assert_eq!(m.poll_transmit(now + Duration::from_secs(60)), None);
                    assert_eq!(m.poll_timeout(), None);
                    return (log, r, now);
                }
            }
            if let Some(tx) = m.poll_transmit(now) {
                log.push(tx.request.clone());
                now += rtt;
                let reply = fail(tx.id, &tx).unwrap_or_else(|| plc.answer(&tx));
                m.handle_reply(now, tx.id, reply);
                continue;
            }
            let t = m.poll_timeout().expect("a waiting machine has a deadline");
            assert!(t >= now, "deadlines never lie in the past");
            now = t;
            m.handle_timeout(now);
        }
        panic!("the machine did not finish");
    }

    fn read(kind: RegisterKind, start: u16, count: u16) -> Request {
        Request::Read {
            kind,
            range: ReadRange::new(start, count).unwrap(),
        }
    }

    fn writes_to(log: &[Request], address: u16) -> usize {
        log.iter()
            .filter(|r| matches!(r, Request::Write { start, .. } if *start == address))
            .count()
    }

    #[test]
    fn happy_path_exact_requests() {
        let map = map();
        let t0 = crate::util::clock::now();
        let t = table(256);
        let e = table::encode(&t, &map, 5).unwrap();
        let mut m = Publisher::new(&map, e.clone(), Timeouts::default(), t0);
        let mut plc = FakePlc::new();
        let (log, r, _) = run(&mut plc, &mut m, t0, MS, |_, _| None);
        assert_eq!(
            r,
            Ok(PublishOutcome::Accepted {
                sequence: 5,
                active_sequence: 5
            })
        );
        let status = read(RegisterKind::Holding, 0, 8);
        let mut want = vec![status.clone(), status.clone()];
        let chunks = [
            (16u16, 14u16),
            (32, 120),
            (152, 120),
            (272, 120),
            (392, 120),
            (512, 32),
        ];
        let regs = e.registers();
        for (s, n) in chunks {
            want.push(Request::Write {
                start: s,
                values: (s..s + n).map(|a| regs[&a]).collect(),
            });
        }
        for (s, n) in chunks {
            want.push(read(RegisterKind::Holding, s, n));
        }
        want.push(Request::Write {
            start: 8,
            values: vec![0, 5],
        });
        want.push(status);
        assert_eq!(log, want);
        for r in &log {
            if let Request::Write { values, .. } = r {
                assert!(values.len() <= 120);
            }
        }
        // The PLC holds exactly the encoding.
        for (a, v) in regs {
            assert_eq!(plc.regs[a as usize], v, "register {a}");
        }
    }

    #[test]
    fn read_back_mismatch_never_commits() {
        let map = map();
        let t0 = crate::util::clock::now();
        let mut m = Publisher::for_table(&map, &table(256), 6, Timeouts::default(), t0).unwrap();
        let mut plc = FakePlc::new();
        plc.corrupt = Some(300);
        let (log, r, _) = run(&mut plc, &mut m, t0, MS, |_, _| None);
        let e = r.unwrap_err();
        let PublishError::ReadBack {
            address, doc, key, ..
        } = &e
        else {
            panic!("{e}")
        };
        assert_eq!(
            (*address, doc.as_str(), key.as_str()),
            (300, "40301", "payload[134]")
        );
        assert!(!e.commit_sent());
        assert_eq!(writes_to(&log, 8), 0, "no commit word");
        assert_eq!(plc.status().active_sequence, 4);
    }

    #[test]
    fn a_rejection_is_reported_with_its_code() {
        let map = map();
        let t0 = crate::util::clock::now();
        let mut m = Publisher::for_table(&map, &table(10), 7, Timeouts::default(), t0).unwrap();
        let mut plc = FakePlc::new();
        plc.on_commit = Some(Err(1));
        let (log, r, _) = run(&mut plc, &mut m, t0, MS, |_, _| None);
        assert_eq!(
            r,
            Ok(PublishOutcome::Rejected {
                sequence: 7,
                code: RejectCode::Crc,
                active_sequence: 4
            })
        );
        assert_eq!(writes_to(&log, 8), 1);
    }

    #[test]
    fn no_echo_times_out_and_nothing_follows() {
        let map = map();
        let t0 = crate::util::clock::now();
        let to = Timeouts::default();
        let mut m = Publisher::for_table(&map, &table(10), 8, to, t0).unwrap();
        let mut plc = FakePlc::new();
        plc.on_commit = None;
        let (log, r, end) = run(&mut plc, &mut m, t0, MS, |_, _| None);
        let e = r.unwrap_err();
        assert!(matches!(e, PublishError::NoEcho { sequence: 8, .. }), "{e}");
        assert!(e.commit_sent());
        assert_eq!(writes_to(&log, 8), 1, "one commit, never a second");
        let commit_at = log
            .iter()
            .rposition(|r| matches!(r, Request::Write { start: 8, .. }));
        let after = &log[commit_at.unwrap() + 1..];
        assert!(after.iter().all(|r| matches!(r, Request::Read { .. })));
        // Polled every 50 ms for the 5 s echo timeout (each poll taking 1 ms here).
        assert!(after.len() >= 90 && after.len() <= 101, "{}", after.len());
        assert!(end >= t0 + to.echo);
    }

    #[test]
    fn a_link_drop_mid_write_never_commits() {
        let map = map();
        let t0 = crate::util::clock::now();
        let mut m = Publisher::for_table(&map, &table(256), 9, Timeouts::default(), t0).unwrap();
        let mut plc = FakePlc::new();
        let (log, r, _) = run(&mut plc, &mut m, t0, MS, |_, tx| match &tx.request {
            Request::Write { start: 272, .. } => {
                Some(Err(LinkError::Io(std::io::ErrorKind::ConnectionReset)))
            }
            _ => None,
        });
        let e = r.unwrap_err();
        let PublishError::Link {
            step,
            error,
            commit_sent,
        } = &e
        else {
            panic!("{e}")
        };
        assert_eq!(*error, LinkError::Io(std::io::ErrorKind::ConnectionReset));
        assert!(!commit_sent);
        assert!(step.contains("registers 272..392 (40273..)"), "{step}");
        assert_eq!(writes_to(&log, 8), 0);
        assert!(matches!(
            log.last(),
            Some(Request::Write { start: 272, .. })
        ));
        assert!(e.to_string().contains("active table is unchanged"), "{e}");
    }

    #[test]
    fn a_frozen_heartbeat_fails_before_writing() {
        let map = map();
        let t0 = crate::util::clock::now();
        let to = Timeouts::default();
        let mut m = Publisher::for_table(&map, &table(10), 10, to, t0).unwrap();
        let mut plc = FakePlc::new();
        plc.heartbeat_step = 0;
        let (log, r, end) = run(&mut plc, &mut m, t0, MS, |_, _| None);
        assert_eq!(
            r,
            Err(PublishError::NotAlive {
                heartbeat: 100,
                waited: to.heartbeat
            })
        );
        assert!(log.iter().all(|r| matches!(r, Request::Read { .. })));
        assert_eq!(end, t0 + MS + to.heartbeat);
    }

    #[test]
    fn not_ready_and_link_errors_while_waiting() {
        let map = map();
        let t0 = crate::util::clock::now();
        let to = Timeouts::default();
        let mut m = Publisher::for_table(&map, &table(10), 11, to, t0).unwrap();
        let mut plc = FakePlc::new();
        let mut st = plc.status();
        st.ready = 0;
        plc.set_status(st);
        let (log, r, _) = run(&mut plc, &mut m, t0, MS, |_, _| None);
        let e = r.unwrap_err();
        assert!(
            matches!(&e, PublishError::NotReady { why, .. } if why == "plc_ready is 0"),
            "{e}"
        );
        assert_eq!(writes_to(&log, 16), 0);

        // The link down for the first polls, then up: the publish goes through.
        let mut m = Publisher::for_table(&map, &table(10), 12, to, t0).unwrap();
        let mut plc = FakePlc::new();
        let (_, r, _) = run(&mut plc, &mut m, t0, MS, |id, _| {
            (id < 3).then_some(Err(LinkError::Disconnected))
        });
        assert!(matches!(
            r,
            Ok(PublishOutcome::Accepted { sequence: 12, .. })
        ));
    }

    #[test]
    fn a_sequence_the_plc_knows_is_refused() {
        let map = map();
        let t0 = crate::util::clock::now();
        let mut m = Publisher::for_table(&map, &table(10), 4, Timeouts::default(), t0).unwrap();
        let mut plc = FakePlc::new();
        let (log, r, _) = run(&mut plc, &mut m, t0, MS, |_, _| None);
        assert!(matches!(
            r,
            Err(PublishError::SequenceInUse { sequence: 4, .. })
        ));
        assert_eq!(log.len(), 1);
    }

    #[test]
    fn late_replies_are_ignored() {
        let map = map();
        let t0 = crate::util::clock::now();
        let mut m = Publisher::for_table(&map, &table(10), 13, Timeouts::default(), t0).unwrap();
        let tx = m.poll_transmit(t0).unwrap();
        assert_eq!(m.poll_transmit(t0), None, "one request at a time");
        m.handle_reply(t0, tx.id + 7, Ok(Reply::Written));
        assert!(m.poll_transmit(t0).is_none(), "still waiting for {}", tx.id);
    }
}
