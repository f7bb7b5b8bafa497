//! The twin's PLC (DESIGN §9): the PLC side of axiscomp's table protocol (plc-maps/README.md)
//! for any map in `plc-maps/cnc/`, applying accepted tables to the twin's axis.
//!
//! As a Modbus TCP server (push), on our server scaffolding:
//! - its own fields (ready, a heartbeat that counts up every `heartbeat_period`, status, error
//!   code, echoed and active sequence) in the registers the map gives them, holding or input;
//! - the header, payload and commit word writable; writes anywhere else, and reads outside the
//!   map's registers, get "illegal data address"; other unit ids than the map's and 0xFF
//!   "gateway target device failed to respond";
//! - a new nonzero commit value makes it validate the staged table (`plc::table::validate`:
//!   header sequence = commit, point count, unit, CRC, limits) and either apply it — converted
//!   to `sim::plant::Profile`s and handed to `Plant::set_compensation` — and echo "accepted"
//!   with the sequence, or echo "rejected" with the protocol's code and keep its active table.
//!
//! Applying: the table's values are `e = measured − nominal` in machine axes; the controller
//! adds the correction `−e` to the commanded position. Machine axis → head axis through an
//! `AxisMapping` (the configured one, default `AxisMapping::standard(base axis)`):
//! positioning tables (acting on the axis under test) go to head y (`dy`), straightness
//! tables to head x or z (`dx`/`dz`), whichever the acting axis is, with the mapping's sign.
//! Positions are the carriage's nominal travel (the twin's CNC commands machine positions of
//! the axis under test directly). A "both" table corrects both directions; a bidirectional
//! one gives the plant a separate − profile. This PLC keeps one table per head axis; it
//! refuses Abbe tables and one-direction (+ or − only) tables with code 6 (unsupported).
//!
//! Fault injection: reject the next commit (with a code), ignore the next commit (no echo),
//! corrupt a staged payload register when the next commit arrives (before validation: a CRC
//! mismatch), go silent after N more writes (the write is not applied and not answered; the
//! server stops, closing connections, and comes back after a set time), not ready, a frozen
//! heartbeat, slow replies (the server's delay).
//!
//! As a pull client ([`spawn_pull_client`]): it polls the service's pull server for the
//! published sequence, reads and validates a new table exactly as above, applies it and
//! writes its acknowledgement and heartbeat into the server's acknowledgement range.

use super::plant::{Compensation, Plant, Profile};
use crate::comp::{AxisMapping, TableKind};
use crate::modbus::server::{RegisterBank, ServerConfig, ServerError, ServerHandle};
use crate::modbus::{Exception, Link, LinkError, ReadRange, RegisterKind, WriteRange};
use crate::plc::map::{CncMap, Field};
use crate::plc::table::{self, MAX_CHUNK, PlcTable, Reject, RejectCode, TableDirection};
use crate::plc::{Image, PlcStatus, StatusCode};
use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;

/// Twin PLC settings.
#[derive(Clone, Debug, PartialEq)]
pub struct TwinPlcConfig {
    /// Where to listen (default 127.0.0.1:0, an ephemeral port).
    pub bind: SocketAddr,
    /// Peers allowed to connect (default everyone).
    pub allow: Option<Vec<IpAddr>>,
    /// The heartbeat counts up once per period (default 20 ms).
    pub heartbeat_period: Duration,
    /// The head ↔ machine mapping (default: the standard one for each table's base axis).
    pub mapping: Option<AxisMapping>,
    /// Time from the commit to the echo, the status busy meanwhile (default 0: at once).
    pub apply_delay: Duration,
}

impl Default for TwinPlcConfig {
    fn default() -> Self {
        TwinPlcConfig {
            bind: SocketAddr::new(IpAddr::V4(Ipv4Addr::LOCALHOST), 0),
            allow: None,
            heartbeat_period: Duration::from_millis(20),
            mapping: None,
            apply_delay: Duration::ZERO,
        }
    }
}

/// What the PLC did with one commit.
#[derive(Clone, Debug, PartialEq)]
pub enum CommitResult {
    Accepted,
    Rejected(Reject),
    /// Ignored (fault injection: no echo).
    Ignored,
}

/// One commit the PLC saw.
#[derive(Clone, Debug, PartialEq)]
pub struct CommitRecord {
    pub sequence: u32,
    pub result: CommitResult,
    pub at: Instant,
}

/// The tables the twin's axis applies, one per head axis (x, y, z), and the plant.
struct Axis {
    plant: Arc<Plant>,
    mapping: Option<AxisMapping>,
    active: [Option<(u32, PlcTable)>; 3],
}

impl Axis {
    /// Which head axis `t` acts on and with which sign, or why this PLC refuses it.
    fn slot(&self, t: &PlcTable) -> Result<(usize, f64), Reject> {
        let unsupported = |detail: String| Reject {
            code: RejectCode::Unsupported,
            detail,
        };
        let mapping = self
            .mapping
            .unwrap_or_else(|| AxisMapping::standard(t.base_axis));
        if mapping.axis() != t.base_axis {
            return Err(unsupported(format!(
                "base axis {} is not the twin's axis {}",
                t.base_axis,
                mapping.axis()
            )));
        }
        if !matches!(
            t.direction,
            TableDirection::Both | TableDirection::Bidirectional
        ) {
            return Err(unsupported(format!(
                "tables of {} are not handled (one direction only)",
                t.direction.words()
            )));
        }
        let head = mapping.head_axes();
        let k = head
            .iter()
            .position(|h| h.axis == t.axis)
            .ok_or_else(|| unsupported(format!("axis {} is not one of the head's axes", t.axis)))?;
        match (t.kind, k) {
            (TableKind::Positioning, 1) | (TableKind::Straightness, 0 | 2) => {
                Ok((k, head[k].sign()))
            }
            (kind, _) => Err(unsupported(format!(
                "a {} table acting on {} is not handled",
                kind.name(),
                t.axis
            ))),
        }
    }

    fn apply(&mut self, sequence: u32, t: PlcTable) -> Result<(), Reject> {
        let (k, _) = self.slot(&t)?;
        self.active[k] = Some((sequence, t));
        self.push();
        Ok(())
    }

    /// Hand the active tables to the plant as corrections `−e`, in the head frame.
    fn push(&self) {
        let profile = |k: usize| -> Option<Profile> {
            let (_, t) = self.active[k].as_ref()?;
            let (_, sign) = self.slot(t).ok()?;
            let c = |v: &[f64]| -> Vec<f64> { v.iter().map(|e| -sign * e).collect() };
            Some(Profile {
                positions_mm: t.positions(),
                up_mm: c(&t.values_mm),
                down_mm: t.down_mm.as_deref().map(c),
            })
        };
        self.plant.set_compensation(Compensation {
            dx: profile(0),
            dy: profile(1),
            dz: profile(2),
        });
    }
}

#[derive(Debug, Default)]
struct Faults {
    reject_next: Option<u16>,
    ignore_next: bool,
    corrupt_next: Option<usize>,
    /// Writes still served before going silent, and for how long.
    silent_after: Option<(u64, Duration)>,
}

struct State {
    holding: Vec<u16>,
    input: Vec<u16>,
    status: PlcStatus,
    frozen_heartbeat: Option<u16>,
    last_commit: u32,
    faults: Faults,
    writes: u64,
    commits: Vec<CommitRecord>,
    axis: Axis,
}

struct Shared {
    map: CncMap,
    unit: u8,
    t0: Instant,
    period: Duration,
    apply_delay: Duration,
    /// Registers the service may write: (start, end) spans of the holding table.
    writable: Vec<(u32, u32)>,
    silent: AtomicBool,
    down: mpsc::UnboundedSender<Duration>,
    state: Mutex<State>,
}

fn put(holding: &mut [u16], input: &mut [u16], kind: RegisterKind, a: u16, regs: &[u16]) {
    let t = match kind {
        RegisterKind::Holding => holding,
        RegisterKind::Input => input,
    };
    let s = a as usize;
    if let Some(slot) = t.get_mut(s..s + regs.len()) {
        slot.copy_from_slice(regs);
    }
}

impl Shared {
    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn heartbeat(&self, st: &State) -> u16 {
        st.frozen_heartbeat.unwrap_or_else(|| {
            let n = crate::util::clock::since(self.t0).as_nanos() / self.period.as_nanos().max(1);
            n as u16
        })
    }

    /// Write the status fields into the register images.
    fn publish_status(&self, st: &mut State) {
        st.status.heartbeat = self.heartbeat(st);
        let State {
            holding,
            input,
            status,
            ..
        } = st;
        for (kind, a, regs) in status.encode(&self.map) {
            put(holding, input, kind, a, &regs);
        }
    }

    /// Validate the staged table for commit `seq` and apply it or reject it.
    fn process_commit(&self, st: &mut State, seq: u32) {
        let at = crate::util::clock::now();
        if let Some(k) = st.faults.corrupt_next.take() {
            let a = self.map.payload.address as usize + k;
            if let Some(r) = st.holding.get_mut(a) {
                *r ^= 0x0001;
            }
        }
        let result = {
            let holding = &st.holding;
            let get = |a: u16| holding.get(a as usize).copied().unwrap_or(0);
            let header = table::decode_header(&self.map, &get);
            let counts =
                table::decode_payload(&self.map, table::payload_len(&self.map, &header), &get);
            table::validate(&self.map, &header, &counts, Some(seq))
        };
        let result = match (st.faults.reject_next.take(), result) {
            (Some(code), _) => Err(Reject {
                code: RejectCode::from_code(code),
                detail: "refused by the PLC program (fault injection)".into(),
            }),
            (None, Ok(t)) => st.axis.apply(seq, t),
            (None, Err(r)) => Err(r),
        };
        match &result {
            Ok(()) => {
                st.status.status = StatusCode::Accepted;
                st.status.error_code = 0;
                st.status.active_sequence = seq;
                tracing::info!(sequence = seq, "twin PLC: table accepted");
            }
            Err(r) => {
                st.status.status = StatusCode::Rejected;
                st.status.error_code = r.code.code();
                tracing::info!(sequence = seq, reason = %r, "twin PLC: table rejected");
            }
        }
        st.status.status_sequence = seq;
        st.commits.push(CommitRecord {
            sequence: seq,
            result: match result {
                Ok(()) => CommitResult::Accepted,
                Err(r) => CommitResult::Rejected(r),
            },
            at,
        });
        self.publish_status(st);
    }

    fn writable(&self, r: WriteRange) -> bool {
        self.writable
            .iter()
            .any(|&(s, e)| r.start() as u32 >= s && r.end() <= e)
    }
}

struct Bank(Arc<Shared>);

impl RegisterBank for Bank {
    fn read(&self, unit: u8, kind: RegisterKind, r: ReadRange) -> Result<Vec<u16>, Exception> {
        let sh = &self.0;
        if unit != sh.unit && unit != 0xFF {
            return Err(Exception::GatewayTargetDevice);
        }
        let mut st = sh.lock();
        sh.publish_status(&mut st);
        let t = match kind {
            RegisterKind::Holding => &st.holding,
            RegisterKind::Input => &st.input,
        };
        t.get(r.start() as usize..r.end() as usize)
            .map(<[u16]>::to_vec)
            .ok_or(Exception::IllegalDataAddress)
    }

    fn write(
        &self,
        unit: u8,
        r: WriteRange,
        values: &[u16],
        _peer: SocketAddr,
    ) -> Result<(), Exception> {
        let sh = &self.0;
        if unit != sh.unit && unit != 0xFF {
            return Err(Exception::GatewayTargetDevice);
        }
        if !sh.writable(r) {
            return Err(Exception::IllegalDataAddress);
        }
        let mut st = sh.lock();
        if let Some((left, down)) = st.faults.silent_after {
            if left == 0 {
                st.faults.silent_after = None;
                drop(st);
                // Not applied, not answered: the server stops and comes back after `down`.
                sh.silent.store(true, Ordering::SeqCst);
                let _ = sh.down.send(down);
                return Err(Exception::ServerDeviceFailure);
            }
            st.faults.silent_after = Some((left - 1, down));
        }
        let s = r.start() as usize;
        if let Some(slot) = st.holding.get_mut(s..s + values.len()) {
            slot.copy_from_slice(values);
        }
        st.writes += 1;
        let c = &sh.map.handshake.commit;
        if (r.start() as u32) < c.end() && (c.address as u32) < r.end() {
            let holding = &st.holding;
            let seq =
                table::read_field(c, &|a| holding.get(a as usize).copied().unwrap_or(0)) as u32;
            if seq != 0 && seq != st.last_commit {
                st.last_commit = seq;
                if std::mem::take(&mut st.faults.ignore_next) {
                    st.commits.push(CommitRecord {
                        sequence: seq,
                        result: CommitResult::Ignored,
                        at: crate::util::clock::now(),
                    });
                } else if sh.apply_delay.is_zero() {
                    sh.process_commit(&mut st, seq);
                } else {
                    st.status.status = StatusCode::Busy;
                    sh.publish_status(&mut st);
                    let (sh2, delay) = (sh.clone(), sh.apply_delay);
                    tokio::spawn(async move {
                        tokio::time::sleep(delay).await;
                        let mut st = sh2.lock();
                        sh2.process_commit(&mut st, seq);
                    });
                }
            }
        }
        Ok(())
    }

    fn responsive(&self) -> bool {
        !self.0.silent.load(Ordering::SeqCst)
    }
}

/// Why the twin PLC could not start.
#[derive(Debug, thiserror::Error)]
pub enum TwinPlcError {
    #[error(transparent)]
    Map(#[from] crate::plc::MapError),
    #[error(transparent)]
    Server(#[from] ServerError),
}

/// The running twin PLC.
pub struct TwinPlc {
    server: ServerHandle,
    shared: Arc<Shared>,
    restarter: JoinHandle<()>,
}

impl Drop for TwinPlc {
    fn drop(&mut self) {
        self.restarter.abort();
    }
}

fn sizes(map: &CncMap) -> (usize, usize) {
    let mut holding = map.payload.end() as usize;
    let mut input = 0usize;
    for f in map
        .handshake
        .plc_fields()
        .into_iter()
        .chain([&map.handshake.commit])
        .chain(map.header.fields())
    {
        match f.kind {
            RegisterKind::Holding => holding = holding.max(f.end() as usize),
            RegisterKind::Input => input = input.max(f.end() as usize),
        }
    }
    (holding, input)
}

/// A field's value as the PLC holds it, from its own register table.
fn field_value(st: &State, f: &Field) -> f64 {
    let regs = match f.kind {
        RegisterKind::Holding => &st.holding,
        RegisterKind::Input => &st.input,
    };
    crate::plc::table::read_field(f, &|a| regs.get(a as usize).copied().unwrap_or(0))
}

fn writable(map: &CncMap) -> Vec<(u32, u32)> {
    let mut v: Vec<(u32, u32)> = map
        .header
        .fields()
        .into_iter()
        .chain([&map.handshake.commit])
        .chain(
            map.check
                .iter()
                .flat_map(|c| c.fields().into_iter().skip(1)),
        )
        .filter(|f| f.kind == RegisterKind::Holding)
        .map(|f: &Field| (f.address as u32, f.end()))
        .collect();
    v.push((map.payload.address as u32, map.payload.end()));
    v.sort();
    // Merge touching spans, so a write across neighbouring fields is one span.
    let mut out: Vec<(u32, u32)> = Vec::new();
    for (s, e) in v {
        match out.last_mut() {
            Some((_, le)) if *le >= s => *le = (*le).max(e),
            _ => out.push((s, e)),
        }
    }
    out
}

impl TwinPlc {
    /// Serve `map` for `plant` (on the current Tokio runtime): ready, idle, no table.
    pub async fn start(
        plant: Arc<Plant>,
        map: CncMap,
        config: TwinPlcConfig,
    ) -> Result<TwinPlc, TwinPlcError> {
        let (holding, input) = sizes(&map);
        let (down_tx, mut down_rx) = mpsc::unbounded_channel();
        let shared = Arc::new(Shared {
            unit: map.unit_id,
            writable: writable(&map),
            t0: crate::util::clock::now(),
            period: config.heartbeat_period,
            apply_delay: config.apply_delay,
            silent: AtomicBool::new(false),
            down: down_tx,
            state: Mutex::new(State {
                holding: vec![0; holding],
                input: vec![0; input],
                status: PlcStatus {
                    ready: 1,
                    heartbeat: 0,
                    status: StatusCode::Idle,
                    error_code: 0,
                    status_sequence: 0,
                    active_sequence: 0,
                },
                frozen_heartbeat: None,
                last_commit: 0,
                faults: Faults::default(),
                writes: 0,
                commits: Vec::new(),
                axis: Axis {
                    plant,
                    mapping: config.mapping,
                    active: [None, None, None],
                },
            }),
            map,
        });
        {
            let mut st = shared.lock();
            shared.publish_status(&mut st);
        }
        let server = ServerHandle::start(
            ServerConfig {
                allow: config.allow,
                ..ServerConfig::new(config.bind)
            },
            Arc::new(Bank(shared.clone())),
        )
        .await?;
        let (srv, sh) = (server.clone(), shared.clone());
        let restarter = tokio::spawn(async move {
            while let Some(down) = down_rx.recv().await {
                srv.stop().await;
                tracing::info!(down = %crate::util::time::span(down), "twin PLC: off (fault injection)");
                tokio::time::sleep(down).await;
                sh.silent.store(false, Ordering::SeqCst);
                if let Err(e) = srv.restart().await {
                    tracing::warn!(error = %e, "twin PLC: cannot listen again");
                }
            }
        });
        Ok(TwinPlc {
            server,
            shared,
            restarter,
        })
    }

    /// Serve the generic map on an ephemeral loopback port.
    pub async fn generic(plant: Arc<Plant>) -> Result<TwinPlc, TwinPlcError> {
        let map = CncMap::generic()?;
        TwinPlc::start(plant, map, TwinPlcConfig::default()).await
    }

    pub fn local_addr(&self) -> SocketAddr {
        self.server.local_addr()
    }

    /// The server, for its counters and fault injection (delays, exceptions, stop/restart).
    pub fn server(&self) -> &ServerHandle {
        &self.server
    }

    pub fn map(&self) -> &CncMap {
        &self.shared.map
    }

    /// The PLC's own fields now.
    pub fn status(&self) -> PlcStatus {
        let mut st = self.shared.lock();
        self.shared.publish_status(&mut st);
        st.status
    }

    /// The active tables (sequence, table) per head axis x, y, z.
    pub fn active_tables(&self) -> [Option<(u32, PlcTable)>; 3] {
        self.shared.lock().axis.active.clone()
    }

    /// Every commit seen so far, oldest first.
    pub fn commits(&self) -> Vec<CommitRecord> {
        self.shared.lock().commits.clone()
    }

    /// Write requests applied so far.
    pub fn writes(&self) -> u64 {
        self.shared.lock().writes
    }

    /// The CNC asks for a check in a break: the next request number written into
    /// `check.request` (1 after the type's largest); `None` when the map has no check fields.
    pub fn request_check(&self) -> Option<u32> {
        let c = self.shared.map.check.as_ref()?;
        let mut st = self.shared.lock();
        let st = &mut *st;
        let now = field_value(st, &c.request);
        let (_, max) = c.request.ty.range();
        let next = if now + 1.0 > max { 1 } else { now as u32 + 1 };
        let regs = crate::plc::table::sequence_regs(&c.request, next).ok()?;
        put(
            &mut st.holding,
            &mut st.input,
            c.request.kind,
            c.request.address,
            &regs,
        );
        Some(next)
    }

    /// The check fields as the PLC holds them: request, answered, state, result, run.
    pub fn check_fields(&self) -> Option<[u32; 5]> {
        let c = self.shared.map.check.as_ref()?;
        let st = self.shared.lock();
        let f = c.fields();
        Some(std::array::from_fn(|k| field_value(&st, f[k]) as u32))
    }

    /// A copy of the holding registers (the staging area included).
    pub fn holding(&self) -> Vec<u16> {
        self.shared.lock().holding.clone()
    }

    /// A copy of the input registers.
    pub fn input(&self) -> Vec<u16> {
        self.shared.lock().input.clone()
    }

    /// Fault: reject the next commit with `code` (e.g. 256 for a site-specific refusal).
    pub fn reject_next(&self, code: u16) {
        self.shared.lock().faults.reject_next = Some(code);
    }

    /// Fault: ignore the next commit (never echo it).
    pub fn ignore_next_commit(&self) {
        self.shared.lock().faults.ignore_next = true;
    }

    /// Fault: when the next commit arrives, flip a bit of payload register `k` (counted from
    /// the payload's start) before validating: a CRC mismatch.
    pub fn corrupt_next_commit(&self, k: usize) {
        self.shared.lock().faults.corrupt_next = Some(k);
    }

    /// Fault: serve `n` more writes, then go silent (the next write is neither applied nor
    /// answered), stop listening, and come back after `down`.
    pub fn go_silent_after_writes(&self, n: u64, down: Duration) {
        self.shared.lock().faults.silent_after = Some((n, down));
    }

    /// Set `plc_ready`.
    pub fn set_ready(&self, ready: bool) {
        let mut st = self.shared.lock();
        st.status.ready = ready as u16;
        self.shared.publish_status(&mut st);
    }

    /// Freeze the heartbeat at its current value (`true`) or let it count again.
    pub fn freeze_heartbeat(&self, frozen: bool) {
        let mut st = self.shared.lock();
        st.frozen_heartbeat = if frozen {
            Some(self.shared.heartbeat(&st))
        } else {
            None
        };
        self.shared.publish_status(&mut st);
    }
}

// ---------- pull client ----------

/// Settings of the twin PLC as a pull client.
#[derive(Clone, Debug, PartialEq)]
pub struct PullClientConfig {
    /// Polling period (default 20 ms).
    pub period: Duration,
    pub mapping: Option<AxisMapping>,
}

impl Default for PullClientConfig {
    fn default() -> Self {
        PullClientConfig {
            period: Duration::from_millis(20),
            mapping: None,
        }
    }
}

/// What the pull client has done.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PullClientState {
    pub status: Option<PlcStatus>,
    pub commits: Vec<CommitRecord>,
    pub last_error: Option<LinkError>,
}

/// A running pull client; aborted on drop.
pub struct PullClient {
    task: JoinHandle<()>,
    state: Arc<Mutex<PullClientState>>,
}

impl Drop for PullClient {
    fn drop(&mut self) {
        self.task.abort();
    }
}

impl PullClient {
    pub fn state(&self) -> PullClientState {
        self.state.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }
}

async fn read_span(
    link: &Link,
    map: &CncMap,
    img: &mut Image,
    start: u32,
    end: u32,
) -> Result<(), LinkError> {
    let mut s = start;
    while s < end {
        let n = (end - s).min(MAX_CHUNK as u32);
        let r = ReadRange::new(s as u16, n as u16).map_err(LinkError::Address)?;
        let v = link.read(RegisterKind::Holding, map.unit_id, r).await?;
        img.put(RegisterKind::Holding, s as u16, &v);
        s += n;
    }
    Ok(())
}

/// Play the PLC pulling from the service's pull server behind `link` (see the module docs).
pub fn spawn_pull_client(
    link: Link,
    map: CncMap,
    plant: Arc<Plant>,
    config: PullClientConfig,
) -> PullClient {
    let state = Arc::new(Mutex::new(PullClientState::default()));
    let st2 = state.clone();
    let task = tokio::spawn(async move {
        let mut axis = Axis {
            plant,
            mapping: config.mapping,
            active: [None, None, None],
        };
        let mut status = PlcStatus {
            ready: 1,
            heartbeat: 0,
            status: StatusCode::Idle,
            error_code: 0,
            status_sequence: 0,
            active_sequence: 0,
        };
        let mut done: u32 = 0;
        loop {
            // A commit is recorded before its acknowledgement goes out, so whoever sees the
            // acknowledgement also sees the record.
            let record = |rec: CommitRecord, status: PlcStatus| {
                let mut s = st2.lock().unwrap_or_else(|p| p.into_inner());
                s.status = Some(status);
                s.commits.push(rec);
            };
            let r = pull_once(&link, &map, &mut axis, &mut status, &mut done, record).await;
            {
                let mut s = st2.lock().unwrap_or_else(|p| p.into_inner());
                s.status = Some(status);
                if let Err(e) = r {
                    s.last_error = Some(e);
                }
            }
            tokio::time::sleep(config.period).await;
        }
    });
    PullClient { task, state }
}

async fn pull_once(
    link: &Link,
    map: &CncMap,
    axis: &mut Axis,
    status: &mut PlcStatus,
    done: &mut u32,
    record: impl FnOnce(CommitRecord, PlcStatus),
) -> Result<(), LinkError> {
    status.heartbeat = status.heartbeat.wrapping_add(1);
    let c = &map.handshake.commit;
    let mut img = Image::default();
    read_span(link, map, &mut img, c.address as u32, c.end()).await?;
    let published = table::read_field(c, &|a| img.get(RegisterKind::Holding, a)) as u32;
    if published != 0 && published != *done {
        let h = &map.header;
        let lo = h
            .fields()
            .iter()
            .map(|f| f.address as u32)
            .min()
            .unwrap_or(0);
        let hi = h.fields().iter().map(|f| f.end()).max().unwrap_or(0);
        read_span(link, map, &mut img, lo, hi).await?;
        let get = |a: u16| img.get(RegisterKind::Holding, a);
        let header = table::decode_header(map, &get);
        let n = table::payload_len(map, &header);
        let p = map.payload.address as u32;
        read_span(
            link,
            map,
            &mut img,
            p,
            p + (n * map.payload.ty.words() as usize) as u32,
        )
        .await?;
        let get = |a: u16| img.get(RegisterKind::Holding, a);
        let counts = table::decode_payload(map, n, &get);
        let result = match table::validate(map, &header, &counts, Some(published)) {
            // The table changed between reads: read it again next time.
            Err(r) if r.code == RejectCode::Sequence => return Ok(()),
            Ok(t) => axis.apply(published, t),
            Err(r) => Err(r),
        };
        *done = published;
        status.status_sequence = published;
        match &result {
            Ok(()) => {
                status.status = StatusCode::Accepted;
                status.error_code = 0;
                status.active_sequence = published;
            }
            Err(r) => {
                status.status = StatusCode::Rejected;
                status.error_code = r.code.code();
            }
        }
        record(
            CommitRecord {
                sequence: published,
                result: match result {
                    Ok(()) => CommitResult::Accepted,
                    Err(r) => CommitResult::Rejected(r),
                },
                at: crate::util::clock::now(),
            },
            *status,
        );
    }
    // The acknowledgement and heartbeat, as runs of contiguous fields.
    let mut runs: Vec<(u16, Vec<u16>)> = Vec::new();
    let mut fields = status.encode(map);
    fields.sort_by_key(|f| f.1);
    for (_, a, regs) in fields {
        match runs.last_mut() {
            Some((s, v)) if *s as usize + v.len() == a as usize => v.extend(regs),
            _ => runs.push((a, regs)),
        }
    }
    for (a, v) in runs {
        link.write_multiple_registers(map.unit_id, a, &v).await?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::comp::MachineAxis::*;
    use crate::optics::Layout;
    use crate::sim::plant::PlantSpec;

    fn plant() -> Arc<Plant> {
        Arc::new(
            Plant::new(
                &Layout::reference(),
                &PlantSpec::default(),
                crate::util::clock::now(),
            )
            .unwrap(),
        )
    }

    fn t(
        kind: TableKind,
        axis: crate::comp::MachineAxis,
        base: crate::comp::MachineAxis,
    ) -> PlcTable {
        PlcTable {
            kind,
            axis,
            base_axis: base,
            direction: TableDirection::Both,
            start_mm: 0.0,
            interval_mm: 100.0,
            values_mm: vec![0.0, 0.002, -0.004],
            down_mm: None,
        }
    }

    #[test]
    fn tables_go_to_the_head_axis_they_act_on_with_the_mappings_sign() {
        let p = plant();
        let mut a = Axis {
            plant: p.clone(),
            mapping: None,
            active: [None, None, None],
        };
        // X axis, standard mapping: head x = −Y, y = +X, z = +Z.
        a.apply(1, t(TableKind::Positioning, X, X)).unwrap();
        a.apply(2, t(TableKind::Straightness, Y, X)).unwrap();
        a.apply(3, t(TableKind::Straightness, Z, X)).unwrap();
        let c = p.compensation();
        assert_eq!(c.dy.unwrap().up_mm, [0.0, -0.002, 0.004], "correction −e");
        assert_eq!(c.dx.unwrap().up_mm, [0.0, 0.002, -0.004], "head x = −Y: +e");
        assert_eq!(c.dz.unwrap().up_mm, [0.0, -0.002, 0.004]);
        for (kind, axis, base) in [
            (TableKind::Abbe, Y, X),
            (TableKind::Positioning, Y, X),
            (TableKind::Straightness, X, X),
        ] {
            let e = a.apply(9, t(kind, axis, base)).unwrap_err();
            assert_eq!(e.code, RejectCode::Unsupported, "{kind:?} {axis}");
        }
        let mut one = t(TableKind::Positioning, X, X);
        one.direction = TableDirection::Positive;
        assert_eq!(a.apply(9, one).unwrap_err().code, RejectCode::Unsupported);
        a.mapping = Some(AxisMapping::standard(Y));
        assert_eq!(
            a.apply(9, t(TableKind::Positioning, X, X))
                .unwrap_err()
                .code,
            RejectCode::Unsupported
        );
    }

    #[test]
    fn writable_spans_and_sizes_per_map() {
        let g = CncMap::generic().unwrap();
        // The commit; the check's answer (11..16) beside the header (16..30); the payload.
        assert_eq!(writable(&g), [(8, 10), (11, 30), (32, 4128)]);
        assert_eq!(sizes(&g), (4128, 0));
        let c = CncMap::load(
            &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("plc-maps/cnc/codesys.toml"),
        )
        .unwrap();
        assert_eq!(writable(&c), [(0, 4016)]);
        assert_eq!(sizes(&c), (4016, 8));
    }
}
