//! Pull: our own Modbus TCP server from which the CNC's PLC pulls the last approved table
//! unattended (DESIGN §6), on the `modbus::server` scaffolding.
//!
//! It serves the map's layout with the roles of push reversed: the header, the payload and
//! the commit word — here the *published sequence* — are read-only; the PLC-written handshake
//! fields (ready, heartbeat, status, error code, echoed and active sequence) form the one
//! writable acknowledgement range, where the PLC reports what it did. The PLC polls the
//! published sequence; when it differs from its active one it reads the header and payload,
//! checks the header's sequence and the CRC, applies the table and acknowledges.
//!
//! - [`PullServer::set_table`] publishes a new table atomically: the whole register bank is
//!   built aside and swapped in one step, so no read ever sees half of one table and half of
//!   another. (A table spans several reads; the PLC detects a swap between them by the
//!   header's sequence and the CRC, and reads again.)
//! - The acknowledgement the PLC writes is decoded and published on a `watch`
//!   ([`PullServer::acks`]).
//! - Reads are validated by the scaffolding (quantity 1..=125, range inside the address
//!   space); reads outside the served span get "illegal data address".
//! - Writes outside the acknowledgement range get "illegal data address" (those registers are
//!   read-only for everyone); writes into it from a peer not in `writers` get "illegal
//!   function" (that peer may read, not write); the connection is kept either way and nothing
//!   changes. Peers not in `allow` are refused on accept, before any Modbus traffic (the
//!   scaffolding's allow-list).
//! - At most `max_connections` peers at once, and a connection with no request for
//!   `idle_timeout` is closed (both logged; `plc.pull_max_connections`, `plc.pull_idle_timeout_s`).
//! - Unit ids other than the map's and 0xFF get "gateway target device failed to respond".

use super::map::{CncMap, Field, Writer};
use super::table::{Encoded, PlcTable, TableError, encode, sequence_regs};
use super::{PlcStatus, StatusCode};
use crate::modbus::server::{RegisterBank, ServerConfig, ServerError, ServerHandle};
use crate::modbus::{Exception, ReadRange, RegisterKind, WriteRange};
use std::net::{IpAddr, SocketAddr};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant};
use thiserror::Error;
use tokio::sync::watch;

/// Pull-server settings.
#[derive(Clone, Debug, PartialEq)]
pub struct PullConfig {
    /// Where to listen (502 in production; port 0 for an ephemeral port).
    pub bind: SocketAddr,
    /// Peers allowed to connect at all (`None`: everyone); others are refused on accept.
    pub allow: Option<Vec<IpAddr>>,
    /// Peers allowed to write the acknowledgement range (`None`: every connected peer). The
    /// CNC's PLC belongs here; a console or monitoring tool may read but not write.
    pub writers: Option<Vec<IpAddr>>,
    /// Connections open at once; more are closed on accept and logged.
    pub max_connections: usize,
    /// A connection with no request for this long is closed and logged (a PLC polls far
    /// more often; an idle or trickling peer would otherwise hold a place for ever).
    pub idle_timeout: Duration,
}

/// The pull server's idle timeout unless configured (`plc.pull_idle_timeout_s`).
pub const DEFAULT_PULL_IDLE_TIMEOUT: Duration = Duration::from_secs(60);

impl PullConfig {
    pub fn new(bind: SocketAddr) -> Self {
        PullConfig {
            bind,
            allow: None,
            writers: None,
            max_connections: crate::modbus::server::DEFAULT_MAX_CONNECTIONS,
            idle_timeout: DEFAULT_PULL_IDLE_TIMEOUT,
        }
    }
}

/// Why the pull server cannot start.
#[derive(Debug, Error)]
pub enum PullError {
    #[error(
        "CNC map {file}: `{key}`: {problem}; use a map whose PLC fields are holding registers in one range (plc-maps/cnc/generic.toml)"
    )]
    Layout {
        file: String,
        key: String,
        problem: String,
    },
    #[error(transparent)]
    Server(#[from] ServerError),
}

/// The acknowledgement the PLC wrote, as the service sees it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PullAck {
    pub status: PlcStatus,
    /// The peer of the last write, and when it came.
    pub peer: Option<SocketAddr>,
    pub at: Option<Instant>,
    /// Writes to the range so far.
    pub writes: u64,
}

impl PullAck {
    /// Whether the PLC reports `sequence` as accepted or rejected.
    pub fn answers(&self, sequence: u32) -> bool {
        self.status.status_sequence == sequence
            && matches!(
                self.status.status,
                StatusCode::Accepted | StatusCode::Rejected
            )
    }
}

struct Bank {
    map: CncMap,
    /// Holding registers served: 0..end.
    end: u32,
    /// The acknowledgement range: start..end.
    ack: (u16, u32),
    writers: Option<Vec<IpAddr>>,
    /// The read-only registers (header, payload, published sequence) over 0..end; swapped
    /// whole.
    image: RwLock<Arc<Vec<u16>>>,
    acks: Mutex<Vec<u16>>,
    tx: watch::Sender<PullAck>,
    writes: AtomicU64,
}

impl Bank {
    fn image(&self) -> Arc<Vec<u16>> {
        self.image
            .read()
            .map(|g| g.clone())
            .unwrap_or_else(|p| p.into_inner().clone())
    }

    fn acks(&self) -> std::sync::MutexGuard<'_, Vec<u16>> {
        self.acks.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn unit_ok(&self, unit: u8) -> Result<(), Exception> {
        if unit == self.map.unit_id || unit == 0xFF {
            Ok(())
        } else {
            Err(Exception::GatewayTargetDevice)
        }
    }

    fn status(&self, acks: &[u16]) -> PlcStatus {
        let (s, e) = self.ack;
        let get = |a: u16| -> u16 {
            if a >= s && (a as u32) < e {
                acks[(a - s) as usize]
            } else {
                0
            }
        };
        PlcStatus::decode(&self.map, &get, &|_| 0)
    }
}

impl RegisterBank for Bank {
    fn read(&self, unit: u8, kind: RegisterKind, r: ReadRange) -> Result<Vec<u16>, Exception> {
        self.unit_ok(unit)?;
        if kind != RegisterKind::Holding || r.end() > self.end {
            return Err(Exception::IllegalDataAddress);
        }
        let image = self.image();
        let acks = self.acks();
        let (s, e) = self.ack;
        Ok((r.start() as u32..r.end())
            .map(|a| {
                if a >= s as u32 && a < e {
                    acks[(a - s as u32) as usize]
                } else {
                    image[a as usize]
                }
            })
            .collect())
    }

    fn write(
        &self,
        unit: u8,
        r: WriteRange,
        values: &[u16],
        peer: SocketAddr,
    ) -> Result<(), Exception> {
        self.unit_ok(unit)?;
        // Registers outside the range are read-only for everyone; inside it, only writers
        // may write.
        let (s, e) = self.ack;
        if r.start() < s || r.end() > e {
            return Err(Exception::IllegalDataAddress);
        }
        if let Some(w) = &self.writers
            && !w.contains(&peer.ip())
        {
            tracing::warn!(%peer, "pull server: write from a peer not allowed to write");
            return Err(Exception::IllegalFunction);
        }
        let mut acks = self.acks();
        let from = (r.start() - s) as usize;
        acks[from..from + values.len()].copy_from_slice(values);
        let status = self.status(&acks);
        drop(acks);
        let writes = self.writes.fetch_add(1, Ordering::Relaxed) + 1;
        self.tx.send_replace(PullAck {
            status,
            peer: Some(peer),
            at: Some(crate::util::clock::now()),
            writes,
        });
        Ok(())
    }
}

/// The running pull server.
pub struct PullServer {
    server: ServerHandle,
    bank: Arc<Bank>,
    acks: watch::Receiver<PullAck>,
}

impl std::fmt::Debug for PullServer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PullServer")
            .field("addr", &self.server.local_addr())
            .field("map", &self.bank.map.name)
            .finish()
    }
}

/// The acknowledgement range of `map`: the span of the PLC-written fields, which must be
/// holding registers with no field written by the service inside.
pub fn ack_range(map: &CncMap) -> Result<(u16, u32), PullError> {
    let layout = |f: &Field, problem: String| PullError::Layout {
        file: map.file.clone(),
        key: format!("{}.address", f.key),
        problem,
    };
    let plc = map.handshake.plc_fields();
    if let Some(f) = plc.iter().find(|f| f.kind != RegisterKind::Holding) {
        return Err(layout(
            f,
            "is an input register; in pull mode the PLC writes its acknowledgement into our server, which needs holding registers".into(),
        ));
    }
    let s = plc.iter().map(|f| f.address as u32).min().unwrap_or(0);
    let e = plc.iter().map(|f| f.end()).max().unwrap_or(0);
    let service = map
        .header
        .fields()
        .into_iter()
        .chain([&map.handshake.commit])
        .map(|f| (f, f.address as u32, f.end()));
    for (f, a, b) in service {
        if f.writer == Writer::Service && a < e && s < b {
            return Err(layout(
                f,
                format!("lies inside the PLC's acknowledgement range {s}..{e}"),
            ));
        }
    }
    if s < map.payload.end() && (map.payload.address as u32) < e {
        return Err(PullError::Layout {
            file: map.file.clone(),
            key: "payload.address".into(),
            problem: format!("the payload lies inside the acknowledgement range {s}..{e}"),
        });
    }
    Ok((s as u16, e))
}

impl PullServer {
    /// Serve `map`'s layout with no table yet (published sequence 0).
    pub async fn start(map: CncMap, config: PullConfig) -> Result<PullServer, PullError> {
        let ack = ack_range(&map)?;
        let (_, end) = map.holding_span();
        let (tx, acks) = watch::channel(PullAck {
            status: PlcStatus {
                ready: 0,
                heartbeat: 0,
                status: StatusCode::Idle,
                error_code: 0,
                status_sequence: 0,
                active_sequence: 0,
            },
            peer: None,
            at: None,
            writes: 0,
        });
        let bank = Arc::new(Bank {
            end,
            ack,
            writers: config.writers,
            image: RwLock::new(Arc::new(vec![0; end as usize])),
            acks: Mutex::new(vec![0; (ack.1 - ack.0 as u32) as usize]),
            tx,
            writes: AtomicU64::new(0),
            map,
        });
        let server = ServerHandle::start(
            ServerConfig {
                allow: config.allow,
                max_connections: config.max_connections,
                idle_timeout: Some(config.idle_timeout),
                ..ServerConfig::new(config.bind)
            },
            bank.clone(),
        )
        .await?;
        Ok(PullServer { server, bank, acks })
    }

    /// The address it listens on.
    pub fn local_addr(&self) -> SocketAddr {
        self.server.local_addr()
    }

    /// The scaffolding's handle (counters, fault injection).
    pub fn server(&self) -> &ServerHandle {
        &self.server
    }

    pub fn map(&self) -> &CncMap {
        &self.bank.map
    }

    /// The acknowledgement range (start, end).
    pub fn ack_range(&self) -> (u16, u32) {
        self.bank.ack
    }

    /// Publish `table` as `sequence`: encode it and swap the whole bank in one step. On an
    /// encoding error nothing changes.
    pub fn set_table(&self, table: &PlcTable, sequence: u32) -> Result<Encoded, TableError> {
        let e = encode(table, &self.bank.map, sequence)?;
        let mut image = vec![0u16; self.bank.end as usize];
        for (a, v) in e.registers() {
            image[a as usize] = v;
        }
        let c = &self.bank.map.handshake.commit;
        image[c.address as usize..c.end() as usize].copy_from_slice(&e.commit);
        self.swap(image);
        Ok(e)
    }

    /// Withdraw the table: published sequence 0, header and payload zero.
    pub fn clear(&self) {
        self.swap(vec![0u16; self.bank.end as usize]);
    }

    fn swap(&self, image: Vec<u16>) {
        let mut g = self.bank.image.write().unwrap_or_else(|p| p.into_inner());
        *g = Arc::new(image);
    }

    /// The published sequence (0: none).
    pub fn published(&self) -> u32 {
        let img = self.bank.image();
        let c = &self.bank.map.handshake.commit;
        super::table::read_field(c, &|a| img.get(a as usize).copied().unwrap_or(0)) as u32
    }

    /// The PLC's acknowledgements, as they are written.
    pub fn acks(&self) -> watch::Receiver<PullAck> {
        self.acks.clone()
    }

    /// Wait until the PLC answers `sequence` (accepted or rejected), at most `timeout`.
    pub async fn wait_ack(&self, sequence: u32, timeout: Duration) -> Option<PullAck> {
        let mut rx = self.acks.clone();
        match tokio::time::timeout(timeout, rx.wait_for(|a| a.answers(sequence))).await {
            Ok(Ok(a)) => Some(*a),
            _ => None,
        }
    }
}

/// The registers a sequence takes in the commit field (for PLC-side code and tests).
pub fn published_regs(map: &CncMap, sequence: u32) -> Result<Vec<u16>, TableError> {
    sequence_regs(&map.handshake.commit, sequence)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::comp::{MachineAxis, TableKind};
    use crate::modbus::server::handle;
    use crate::plc::table::TableDirection;
    use std::borrow::Cow;
    use tokio_modbus::prelude::{Request, Response};

    fn bank(writers: Option<Vec<IpAddr>>) -> (Bank, watch::Receiver<PullAck>) {
        let map = CncMap::generic().unwrap();
        let ack = ack_range(&map).unwrap();
        let (_, end) = map.holding_span();
        let (tx, rx) = watch::channel(PullAck {
            status: PlcStatus {
                ready: 0,
                heartbeat: 0,
                status: StatusCode::Idle,
                error_code: 0,
                status_sequence: 0,
                active_sequence: 0,
            },
            peer: None,
            at: None,
            writes: 0,
        });
        let b = Bank {
            end,
            ack,
            writers,
            image: RwLock::new(Arc::new((0..end).map(|a| a as u16).collect())),
            acks: Mutex::new(vec![0; 8]),
            tx,
            writes: AtomicU64::new(0),
            map,
        };
        (b, rx)
    }

    fn plc() -> SocketAddr {
        "127.0.0.2:40000".parse().unwrap()
    }

    #[test]
    fn the_generic_ack_range_is_the_plc_fields() {
        assert_eq!(ack_range(&CncMap::generic().unwrap()).unwrap(), (0, 8));
        let codesys = CncMap::load(
            &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("plc-maps/cnc/codesys.toml"),
        )
        .unwrap();
        let e = ack_range(&codesys).unwrap_err();
        assert!(e.to_string().contains("handshake.plc_ready.address"), "{e}");
    }

    #[test]
    fn reads_compose_the_image_and_the_acks() {
        let (b, _) = bank(None);
        let r = handle(&b, 1, &Request::ReadHoldingRegisters(6, 4), plc()).unwrap();
        assert_eq!(r, Response::ReadHoldingRegisters(vec![0, 0, 8, 9]));
        assert_eq!(
            handle(&b, 1, &Request::ReadHoldingRegisters(4120, 9), plc()),
            Err(Exception::IllegalDataAddress)
        );
        assert!(handle(&b, 1, &Request::ReadHoldingRegisters(4120, 8), plc()).is_ok());
        assert_eq!(
            handle(&b, 1, &Request::ReadInputRegisters(0, 1), plc()),
            Err(Exception::IllegalDataAddress)
        );
        assert_eq!(
            handle(&b, 7, &Request::ReadHoldingRegisters(0, 1), plc()),
            Err(Exception::GatewayTargetDevice)
        );
    }

    #[test]
    fn writes_only_into_the_ack_range_from_writers() {
        let (b, rx) = bank(Some(vec!["127.0.0.2".parse().unwrap()]));
        let other: SocketAddr = "127.0.0.1:5000".parse().unwrap();
        assert_eq!(
            handle(&b, 1, &Request::WriteSingleRegister(2, 2), other),
            Err(Exception::IllegalFunction)
        );
        assert_eq!(
            handle(
                &b,
                1,
                &Request::WriteMultipleRegisters(6, Cow::Owned(vec![0, 1, 2])),
                plc()
            ),
            Err(Exception::IllegalDataAddress),
            "runs into the published sequence"
        );
        assert_eq!(
            handle(&b, 1, &Request::WriteSingleRegister(16, 1), plc()),
            Err(Exception::IllegalDataAddress)
        );
        assert_eq!(rx.borrow().writes, 0, "nothing changed");
        // status accepted (2) for sequence 5, active 5.
        handle(
            &b,
            1,
            &Request::WriteMultipleRegisters(0, Cow::Owned(vec![1, 9, 2, 0, 0, 5, 0, 5])),
            plc(),
        )
        .unwrap();
        let a = *rx.borrow();
        assert_eq!(a.writes, 1);
        assert_eq!(a.peer, Some(plc()));
        assert!(a.answers(5));
        assert_eq!(a.status.heartbeat, 9);
    }

    #[tokio::test]
    async fn set_table_swaps_the_whole_bank() {
        let map = CncMap::generic().unwrap();
        let s = PullServer::start(map.clone(), PullConfig::new("127.0.0.1:0".parse().unwrap()))
            .await
            .unwrap();
        assert_eq!(s.published(), 0);
        let t = PlcTable {
            kind: TableKind::Straightness,
            axis: MachineAxis::X,
            base_axis: MachineAxis::Y,
            direction: TableDirection::Both,
            start_mm: 0.0,
            interval_mm: 10.0,
            values_mm: vec![0.0, 0.001, -0.002],
            down_mm: None,
        };
        let e = s.set_table(&t, 42).unwrap();
        assert_eq!(s.published(), 42);
        let img = s.bank.image();
        for (a, v) in e.registers() {
            assert_eq!(img[a as usize], v);
        }
        let mut bad = t.clone();
        bad.values_mm[1] = 5.0;
        assert!(s.set_table(&bad, 43).is_err());
        assert_eq!(s.published(), 42, "unchanged after a refused table");
        s.clear();
        assert_eq!(s.published(), 0);
        assert!(s.bank.image().iter().all(|&r| r == 0));
    }
}
