//! PSD acquisition (DESIGN §6): one block read of the I/O module's registers per frame, decoded
//! through an I/O-module map (counts → volts → spot position) into a `Frame` of three spots.
//! A PSD whose SUM is below threshold has no spot: the beam is blocked or off it, and the frame
//! is never averaged in.
//!
//! - `map`: I/O-module maps (`plc-maps/io/*.toml`), raw then validated, conditioned or
//!   electrode channel modes.
//! - `decode`: registers → volts → spots (and the inverse, for the twin), pure functions.
//! - `task`: the acquisition loop over a `modbus::Link`, publishing frames on a broadcast
//!   channel and the latest on a watch, with statistics.

pub mod decode;
pub mod map;
pub mod task;

pub use decode::{DecodeError, Reading};
pub use map::{IoMap, MapError};
pub use task::{AcquireConfig, AcquireStats, Acquisition};

use crate::optics::Spot;
use nalgebra::Vector6;
use std::time::Instant;

/// One snapshot of the three PSDs, decoded from one block read.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frame {
    /// Sequence number, counting every frame of this acquisition run.
    pub seq: u64,
    /// Monotonic time the reply arrived.
    pub at: Instant,
    /// Wall-clock time of the reply, µs since the Unix epoch.
    pub unix_us: i64,
    /// Spot per PSD (mm, PSD frame); `None` when its SUM is below the threshold.
    pub spots: [Option<Spot>; 3],
    /// SUM signal per PSD (V).
    pub sums: [f64; 3],
}

impl Frame {
    /// When it was read, to order it (monotonic) and to name it (wall clock).
    pub fn stamp(&self) -> crate::util::clock::Stamp {
        crate::util::clock::Stamp {
            at: self.at,
            unix_us: self.unix_us,
        }
    }

    /// The six readings (mm) when every PSD has its spot.
    pub fn readings(&self) -> Option<Vector6<f64>> {
        let mut v = Vector6::zeros();
        for (k, s) in self.spots.iter().enumerate() {
            let s = s.as_ref()?;
            v[2 * k] = s.x;
            v[2 * k + 1] = s.y;
        }
        Some(v)
    }

    /// Whether every PSD has its spot.
    pub fn is_valid(&self) -> bool {
        self.spots.iter().all(Option::is_some)
    }
}
