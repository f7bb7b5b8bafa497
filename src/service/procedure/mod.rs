//! The service's procedures (DESIGN §5): whatever holds the machine for a while — the
//! measurement run, the follower's mapping and level stations, the hexapod calibration run —
//! and the beam alignment's requests, each one type behind one trait that the core drives.
//!
//! The core keeps them in a list, hands each request to the procedure that takes it, shows
//! each the pipeline's outputs, the drive's events and the frames, ticks them with the time,
//! and lets each fill its part of the snapshot. It knows which one holds the machine: a
//! request that would start one while another holds it is refused by the core, in the words
//! of the one that holds it, so no procedure names another and none imports the core.
//!
//! Adding a procedure: a type in this folder implementing [`Procedure`], its requests and
//! view in `service::api`, one line in the core's list (`core::procedures`).

pub mod align;
pub mod follower_level;
pub mod follower_map;
pub mod hexapod;
pub mod run;

use super::api::{FollowerMapView, Request, Snapshot};
use super::calibration::Calibrations;
use super::pipeline::{Output, Pipeline};
use crate::acquire::Frame;
use crate::canopen::{DriveHandle, Event};
use crate::config::{CncMode, Settings};
use crate::store::{
    AlignmentRecord, AuditEntry, AuditOutcome, FollowerMapRecord, QueueError, StoreError,
    StoreQueue,
};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, oneshot};

/// Who asked.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Who {
    pub user: String,
    pub uid: u32,
}

/// The answer owed to a request: sent once, now or later. An operator's request is written
/// to the audit log with its outcome (done, or refused with the reason) when it is answered.
#[derive(Debug)]
pub struct Reply {
    tx: oneshot::Sender<Result<serde_json::Value, String>>,
    audit: Option<(AuditEntry, StoreQueue, mpsc::Sender<String>)>,
}

impl Reply {
    /// A reply to `tx`; with `audit`, the entry is stored with the outcome through `store`,
    /// and a store that cannot take it is said on `alarm`.
    pub fn new(
        tx: oneshot::Sender<Result<serde_json::Value, String>>,
        audit: Option<(AuditEntry, StoreQueue, mpsc::Sender<String>)>,
    ) -> Reply {
        Reply { tx, audit }
    }

    /// Answer.
    pub fn send(self, r: Result<serde_json::Value, String>) {
        if let Some((mut entry, store, alarm)) = self.audit {
            entry.outcome = match &r {
                Ok(_) => AuditOutcome::Done,
                Err(why) => AuditOutcome::Refused(why.clone()),
            };
            match store.try_call(move |s| s.audit(&entry)) {
                Ok(done) => {
                    tokio::spawn(async move {
                        let why = match done.await {
                            Ok(Ok(_)) => return,
                            Ok(Err(e)) => e.to_string(),
                            Err(e) => e.to_string(),
                        };
                        let _ = alarm.send(format!("audit entry not stored: {why}")).await;
                    });
                }
                Err(e) => {
                    let _ = alarm.try_send(format!("audit entry not stored: {e}"));
                }
            }
        }
        let _ = self.tx.send(r);
    }
}

/// What the store holds that the procedures look up, kept current by the service (the one
/// writer while it runs), so a lookup never waits for the disk.
#[derive(Clone, Debug, Default)]
pub struct Cached {
    /// The newest alignment of each axis.
    pub alignments: BTreeMap<String, AlignmentRecord>,
    /// The follower map in use.
    pub follower_map: Option<FollowerMapRecord>,
}

/// What the procedures need of the service's settings.
#[derive(Clone, Debug)]
pub struct Env {
    pub settings: Arc<Settings>,
    pub state_dir: PathBuf,
    pub cnc: CncMode,
}

/// What a procedure works with during one call: the core lends it.
pub struct Ctx<'a> {
    pub now: Instant,
    pub pipeline: &'a mut Pipeline,
    pub store: &'a StoreQueue,
    pub cached: &'a mut Cached,
    pub drive: &'a DriveHandle,
    pub calibrations: &'a mut Calibrations,
    /// The follower map in use, as the snapshot shows it.
    pub shown: &'a mut Option<FollowerMapView>,
    /// PSD frames per second over the last second.
    pub frames_per_s: f64,
    pub env: &'a Env,
    /// The acquisition, for a procedure that reads the frames on a task of its own.
    pub acquisition: &'a crate::acquire::Acquisition,
}

impl Ctx<'_> {
    /// The zero reference's window.
    pub fn zero_window(&self) -> Duration {
        self.env.settings.head.zero_window
    }
}

/// One of the service's procedures.
pub trait Procedure: Send {
    /// What it is, in words ("the follower mapping").
    fn name(&self) -> &'static str;

    /// Whether `req` is one of its requests.
    fn takes(&self, req: &Request) -> bool;

    /// Whether `req` would start it (the core refuses that while another holds the machine).
    fn starts(&self, _req: &Request) -> bool {
        false
    }

    /// Whether it holds the machine now (it moves the carriage, the follower or the head).
    fn holds_machine(&self) -> bool;

    /// Whether the follower must hold still while it works (the tracker's moves are not
    /// sent).
    fn holds_follower(&self) -> bool {
        false
    }

    /// Why `what` cannot be done while it holds the machine, and how to end it.
    fn busy(&self, what: &str) -> String;

    /// Its request; the reply may be kept and sent later.
    fn request(&mut self, req: Request, who: &Who, reply: Reply, ctx: &mut Ctx);

    /// A frame from the PSDs (before the pipeline has it).
    fn on_frame(&mut self, _f: &Frame) {}

    /// Whether `out` is its to keep (a handover of its run: the core does not store it).
    fn claims(&self, _out: &Output) -> bool {
        false
    }

    /// One of the pipeline's outputs (after the core has carried out its own part).
    fn on_output(&mut self, _out: &Output, _ctx: &mut Ctx) {}

    /// An event of the follower drive.
    fn on_drive_event(&mut self, _e: &Event, _ctx: &mut Ctx) {}

    /// The follower's drive is ready (homed, enabled): what waited for it may start.
    fn on_drive_ready(&mut self, _ctx: &mut Ctx) {}

    /// Each tick (10 Hz at least): its asynchronous work heard, its state advanced.
    fn tick(&mut self, ctx: &mut Ctx);

    /// Its part of the snapshot.
    fn show(&self, _snap: &mut Snapshot, _pipeline: &Pipeline) {}
}

/// A store error, or the queue's, in words.
pub fn store_words(r: Result<Result<(), StoreError>, QueueError>) -> Result<(), String> {
    match r {
        Ok(Ok(())) => Ok(()),
        Ok(Err(e)) => Err(e.to_string()),
        Err(e) => Err(e.to_string()),
    }
}
