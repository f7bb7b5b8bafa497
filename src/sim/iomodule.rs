//! The twin's I/O module (DESIGN §9): a Modbus TCP server, on our server scaffolding, that
//! answers each read of its map's block with the plant sampled at that instant, digitised as
//! raw counts the way a module following the map would present them (`acquire::decode::encode`:
//! rounding, saturation, status bits clear, unused registers 0).
//!
//! It serves `plc-maps/io/generic.toml` by default and any other valid map (the real products'
//! maps included), in either channel mode. It answers the map's unit id and 0xFF (the value
//! the Modbus TCP implementation guide recommends for a directly addressed device); other unit
//! ids get "gateway target device failed to respond", reads of the other register table or
//! outside the block "illegal data address". It records what it served (the truth), so tests
//! compare what was measured with what was there. Fault injection is the server's: stop and
//! come back, delayed replies, exceptions.

use super::plant::{Plant, PsdSample};
use crate::acquire::decode::{self, Reading};
use crate::acquire::map::{IoMap, MapError};
use crate::modbus::server::{RegisterBank, ServerConfig, ServerError, ServerHandle};
use crate::modbus::{Exception, ReadRange, RegisterKind};
use std::collections::VecDeque;
use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// What the PSDs deliver: the plant, or a fixed sample for tests and interop checks.
pub trait PsdSource: Send + Sync + 'static {
    fn sample(&self, now: Instant) -> PsdSample;
}

impl PsdSource for Plant {
    fn sample(&self, now: Instant) -> PsdSample {
        Plant::sample(self, now)
    }
}

/// A sample that changes only when told to.
#[derive(Debug)]
pub struct FixedSource(Mutex<PsdSample>);

impl FixedSource {
    pub fn new(sample: PsdSample) -> Self {
        FixedSource(Mutex::new(sample))
    }
    pub fn set(&self, sample: PsdSample) {
        *self.0.lock().unwrap_or_else(|p| p.into_inner()) = sample;
    }
}

impl PsdSource for FixedSource {
    fn sample(&self, _now: Instant) -> PsdSample {
        *self.0.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// One read the module served: its index (from 0), when, and what the PSDs delivered.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Served {
    pub index: u64,
    pub at: Instant,
    pub sample: PsdSample,
}

/// I/O-module settings.
#[derive(Clone, Debug, PartialEq)]
pub struct IoModuleConfig {
    /// Where to listen (default 127.0.0.1:0, an ephemeral port; a real module uses 502).
    pub bind: SocketAddr,
    /// Peers allowed to connect (default everyone).
    pub allow: Option<Vec<IpAddr>>,
    /// Served reads kept in the history (default 4096).
    pub history: usize,
}

impl Default for IoModuleConfig {
    fn default() -> Self {
        IoModuleConfig {
            bind: SocketAddr::new(IpAddr::V4(Ipv4Addr::LOCALHOST), 0),
            allow: None,
            history: 4096,
        }
    }
}

/// Why the module could not start.
#[derive(Debug, thiserror::Error)]
pub enum IoModuleError {
    #[error(transparent)]
    Map(#[from] MapError),
    #[error(transparent)]
    Server(#[from] ServerError),
}

struct Bank {
    source: Arc<dyn PsdSource>,
    map: Arc<IoMap>,
    history: Mutex<VecDeque<Served>>,
    capacity: usize,
    count: AtomicU64,
}

impl RegisterBank for Bank {
    fn read(&self, unit: u8, kind: RegisterKind, range: ReadRange) -> Result<Vec<u16>, Exception> {
        if unit != self.map.unit_id && unit != 0xFF {
            return Err(Exception::GatewayTargetDevice);
        }
        if kind != self.map.kind || !self.map.block.contains(&range) {
            return Err(Exception::IllegalDataAddress);
        }
        let at = crate::util::clock::now();
        let sample = self.source.sample(at);
        let reading = Reading {
            spots: sample.spots,
            sums: sample.sums,
        };
        let block = decode::encode(&self.map, &reading).map_err(|e| {
            tracing::warn!(error = %e, "twin I/O module cannot encode the sample");
            Exception::ServerDeviceFailure
        })?;
        let index = self.count.fetch_add(1, Ordering::Relaxed);
        {
            let mut h = self.history.lock().unwrap_or_else(|p| p.into_inner());
            if h.len() == self.capacity {
                h.pop_front();
            }
            h.push_back(Served { index, at, sample });
        }
        let from = (range.start() - self.map.block.start()) as usize;
        Ok(block[from..from + range.count() as usize].to_vec())
    }
}

/// The running I/O module.
pub struct IoModule {
    server: ServerHandle,
    bank: Arc<Bank>,
}

impl IoModule {
    /// Serve `source` through `map` (on the current Tokio runtime).
    pub async fn start(
        source: Arc<dyn PsdSource>,
        map: IoMap,
        config: IoModuleConfig,
    ) -> Result<IoModule, IoModuleError> {
        let bank = Arc::new(Bank {
            source,
            map: Arc::new(map),
            history: Mutex::new(VecDeque::new()),
            capacity: config.history.max(1),
            count: AtomicU64::new(0),
        });
        let server = ServerHandle::start(
            ServerConfig {
                allow: config.allow,
                ..ServerConfig::new(config.bind)
            },
            bank.clone(),
        )
        .await?;
        Ok(IoModule { server, bank })
    }

    /// Serve the plant through the generic map on an ephemeral loopback port.
    pub async fn generic(plant: Arc<Plant>) -> Result<IoModule, IoModuleError> {
        IoModule::start(plant, IoMap::generic()?, IoModuleConfig::default()).await
    }

    /// The address it listens on.
    pub fn local_addr(&self) -> SocketAddr {
        self.server.local_addr()
    }

    /// The server, for fault injection (stop/restart, delays, exceptions) and counters.
    pub fn server(&self) -> &ServerHandle {
        &self.server
    }

    /// The map it serves.
    pub fn map(&self) -> &IoMap {
        &self.bank.map
    }

    /// Reads served so far.
    pub fn served_count(&self) -> u64 {
        self.bank.count.load(Ordering::Relaxed)
    }

    /// The most recent served reads (oldest first), up to the history size.
    pub fn served(&self) -> Vec<Served> {
        let h = self.bank.history.lock().unwrap_or_else(|p| p.into_inner());
        h.iter().copied().collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::Spot;

    fn sample() -> PsdSample {
        PsdSample {
            spots: [
                Some(Spot { x: 1.0, y: -2.0 }),
                None,
                Some(Spot { x: 0.25, y: 4.0 }),
            ],
            sums: [5.0, 0.02, 4.5],
        }
    }

    fn bank(map: IoMap) -> Bank {
        Bank {
            source: Arc::new(FixedSource::new(sample())),
            map: Arc::new(map),
            history: Mutex::new(VecDeque::new()),
            capacity: 2,
            count: AtomicU64::new(0),
        }
    }

    #[test]
    fn serves_the_generic_encoding_and_records_it() {
        let b = bank(IoMap::generic().unwrap());
        let all = b
            .read(1, RegisterKind::Input, ReadRange::new(0, 9).unwrap())
            .unwrap();
        // 1.0 V = 3276.7 → 3277 counts; -2.0 V → -6553 (0xE667); 5 V → 16384 (16383.5
        // rounds up); PSD2 centred with 0.02 V = 65.5 → 66 counts.
        assert_eq!(&all[..6], &[3277, 0xE667, 16384, 0, 0, 66]);
        let part = b
            .read(0xFF, RegisterKind::Input, ReadRange::new(3, 3).unwrap())
            .unwrap();
        assert_eq!(part, all[3..6]);
        assert_eq!(
            b.read(2, RegisterKind::Input, ReadRange::new(0, 9).unwrap()),
            Err(Exception::GatewayTargetDevice)
        );
        assert_eq!(
            b.read(1, RegisterKind::Holding, ReadRange::new(0, 9).unwrap()),
            Err(Exception::IllegalDataAddress)
        );
        assert_eq!(
            b.read(1, RegisterKind::Input, ReadRange::new(5, 5).unwrap()),
            Err(Exception::IllegalDataAddress)
        );
        let h = b.history.lock().unwrap();
        assert_eq!(h.len(), 2, "bounded history");
        assert_eq!((h[0].index, h[1].index), (0, 1));
        assert_eq!(h[1].sample, sample());
    }
}
