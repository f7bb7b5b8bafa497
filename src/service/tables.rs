//! The PLC tables task (DESIGN §6–§8): compensation tables generated from stored runs,
//! published into the CNC's PLC (push: the `plc::publish` handshake over this task's own
//! `modbus::Link`) and/or served for the PLC to pull (`plc::PullServer`), and what the PLC
//! holds read back and compared with the store. It answers the control API's `table_list`,
//! `table_generate`, `table_publish` and `table_status`, so the core never waits on a PLC.
//!
//! - Every publish attempt is recorded in the store (table, target, sequence, result, time);
//!   operator requests are written to the audit log before they are handled, as the core does.
//! - A stored table is the table as published: the run's `comp` table fitted to the CNC map's
//!   grid (`PlcTable::from_comp`), with its payload CRC-32 in the `crc` column and the
//!   measured table beside it ([`StoredTable`]). Publishing re-encodes it and refuses when the
//!   CRC differs (the configured map changed since it was generated).
//! - The pull server, when configured, serves the last table the PLC accepted (restored from
//!   the store at start).
//!
//! The decisions (stored format, the next sequence, the status verdict) are plain functions
//! with unit tests; the task only does the I/O. The protocol is `plc-maps/README.md`. The task
//! reaches its store connection through a [`StoreQueue`] of its own, so a store locked by
//! another process holds up this task's requests, never the runtime the core shares with it.

use super::api::Request;
use super::composition;
use super::control::Command;
use super::shutdown::Shutdown;
use super::stored::{Base, StoredTable};
use crate::comp::{self, AxisMapping, MachineAxis, TableSpec};
use crate::config::{PlcSettings, TableBuild};
use crate::evaluate::{EvalOptions, ReferenceLine, evaluate_captures};
use crate::modbus::Link;
use crate::plc::table::{self as ptable, RawHeader, Reject};
use crate::plc::{self, CncMap, PlcStatus, PlcTable, PublishOutcome, PullServer, StatusCode};
use crate::store::{
    AuditEntry, Publication, PublicationOutcome, PublicationRecord, RunId, RunTables, Store,
    StoreError, StoreQueue, TableEntry, TableId, TableRecord, now_us,
};
use serde::{Deserialize, Serialize};
use std::net::SocketAddr;
use std::path::Path;
use thiserror::Error;
use tokio::sync::mpsc;

/// Why the tables task could not start.
#[derive(Debug, Error)]
pub enum TablesError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("PLC pull server: {0}")]
    Pull(#[from] plc::PullError),
}

// ---------- replies ----------

/// A publication, as replies show it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PublicationView {
    pub table_id: i64,
    pub target: String,
    pub sequence: u32,
    /// "accepted", "rejected" or "failed".
    pub result: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub code: Option<i64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub text: Option<String>,
    pub unix_us: i64,
}

impl From<&PublicationRecord> for PublicationView {
    fn from(r: &PublicationRecord) -> Self {
        let p = &r.publication;
        let (result, code, text) = match &p.outcome {
            PublicationOutcome::Accepted => ("accepted", None, None),
            PublicationOutcome::Rejected { code, text } => ("rejected", *code, Some(text.clone())),
            PublicationOutcome::Failed { code, text } => ("failed", *code, Some(text.clone())),
        };
        PublicationView {
            table_id: p.table.0,
            target: p.target.clone(),
            sequence: p.sequence,
            result: result.into(),
            code,
            text,
            unix_us: p.unix_us,
        }
    }
}

/// A stored table, as `table_list` and `table_generate` show it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TableView {
    pub id: i64,
    /// ISO 230-1 name.
    pub name: String,
    pub kind: String,
    pub axis: String,
    pub base_axis: String,
    pub direction: String,
    pub points: usize,
    pub start_mm: f64,
    pub interval_mm: f64,
    /// Smallest and largest e = measured − nominal (µm).
    pub min_um: f64,
    pub max_um: f64,
    /// CRC-32 of the payload, "0x…".
    pub crc: String,
    /// The CNC map it was fitted to.
    pub map: String,
    pub source_run: Option<i64>,
    pub generated_us: i64,
    /// Its latest publication.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub last_publication: Option<PublicationView>,
    /// e per point (µm): the values as published (the + profile when bidirectional), and the
    /// − profile of a bidirectional table.
    #[serde(default)]
    pub values_um: Vec<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub down_um: Option<Vec<f64>>,
    /// "measured", or "composed: table N (sequence S, CRC …) + the residual measured by run R".
    #[serde(default)]
    pub composition: String,
}

fn table_view(r: &TableRecord, pubs: &[PublicationRecord]) -> TableView {
    let s = StoredTable::from_record(r).ok();
    let (min_um, max_um) = s.as_ref().map_or((0.0, 0.0), StoredTable::range_um);
    TableView {
        id: r.id.0,
        name: s.as_ref().map(|s| s.name.clone()).unwrap_or_default(),
        kind: r.entry.kind.clone(),
        axis: r.entry.axis.clone(),
        base_axis: s
            .as_ref()
            .map(|s| s.base_axis.to_string())
            .unwrap_or_default(),
        direction: s
            .as_ref()
            .map(|s| s.direction.clone())
            .unwrap_or_else(|| r.entry.direction.map_or("both", |d| d.sign()).into()),
        points: s.as_ref().map_or(0, |s| s.values_mm.len()),
        start_mm: s.as_ref().map_or(0.0, |s| s.start_mm),
        interval_mm: s.as_ref().map_or(0.0, |s| s.interval_mm),
        min_um,
        max_um,
        crc: format!("0x{:08X}", r.entry.crc),
        map: s.as_ref().map(|s| s.map.clone()).unwrap_or_default(),
        source_run: r.entry.source_run.map(|x| x.0),
        generated_us: r.entry.generated_us,
        last_publication: pubs
            .iter()
            .rev()
            .find(|p| p.publication.table == r.id)
            .map(PublicationView::from),
        values_um: s.as_ref().map_or_else(Vec::new, |s| um(&s.values_mm)),
        down_um: s.as_ref().and_then(|s| s.down_mm.as_deref().map(um)),
        composition: s.as_ref().map(StoredTable::composition).unwrap_or_default(),
    }
}

fn um(mm: &[f64]) -> Vec<f64> {
    mm.iter().map(|v| v * 1e3).collect()
}

/// The `table_publish` reply.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PublishView {
    pub table_id: i64,
    pub target: String,
    pub sequence: u32,
    /// "committed" (the PLC accepted and applies it), "rejected" (the PLC refused it, with
    /// `code`) or "failed" (no answer; `message` says how far it got).
    pub result: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub code: Option<u16>,
    /// The code's meaning, or the reason of the failure.
    pub message: String,
    /// The PLC's active sequence afterwards, when it said.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub active_sequence: Option<u32>,
    /// Whether the commit word went out (a failure after it: the PLC may have applied it).
    pub commit_sent: bool,
    /// Set when the publication could not be recorded in the store.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub not_recorded: Option<String>,
}

/// The PLC's own fields.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlcStatusView {
    pub ready: u16,
    pub heartbeat: u16,
    /// "idle", "busy", "accepted", "rejected" or the code.
    pub status: String,
    pub error_code: u16,
    pub status_sequence: u32,
    pub active_sequence: u32,
}

impl From<&PlcStatus> for PlcStatusView {
    fn from(s: &PlcStatus) -> Self {
        PlcStatusView {
            ready: s.ready,
            heartbeat: s.heartbeat,
            status: match s.status {
                StatusCode::Idle => "idle".into(),
                StatusCode::Busy => "busy".into(),
                StatusCode::Accepted => "accepted".into(),
                StatusCode::Rejected => "rejected".into(),
                StatusCode::Other(c) => c.to_string(),
            },
            error_code: s.error_code,
            status_sequence: s.status_sequence,
            active_sequence: s.active_sequence,
        }
    }
}

/// The PLC's staging area (header and payload), read back.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StagedView {
    pub sequence: u32,
    pub crc: String,
    pub points: u16,
    pub kind: u16,
    pub axis: u16,
    pub direction: u16,
    /// Why the PLC would refuse it (its CRC or limits), when it would.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub invalid: Option<String>,
    /// The values it holds (µm, decoded from the payload read back; the + profile when
    /// bidirectional), for a per-point diff; empty when it does not decode.
    #[serde(default)]
    pub values_um: Vec<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub down_um: Option<Vec<f64>>,
}

/// The `table_status` reply.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StatusView {
    /// Where the answer comes from: the PLC read back (push) or its acknowledgement (pull).
    pub source: String,
    pub plc: PlcStatusView,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub staged: Option<StagedView>,
    /// "matches", "differs" or "empty".
    pub verdict: String,
    /// The stored table the PLC holds, when it matches one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub table_id: Option<i64>,
    /// "matches table N" and how that was established, what differs, or "PLC empty".
    pub message: String,
    /// Every table the PLC applies, one per kind and axis (issue 15), with what is known of it.
    #[serde(default)]
    pub active: Vec<ActiveView>,
    /// Where `active` comes from, or why it is unknown.
    #[serde(default)]
    pub active_source: String,
}

/// A table the PLC applies: which stored table, its sequence and CRC, when it was published
/// and from which run, and its values (µm) for a diff against another table of its kind.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ActiveView {
    pub kind: String,
    pub axis: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub table_id: Option<i64>,
    pub sequence: u32,
    pub crc: String,
    /// True when the PLC's staging area was read back with this sequence and CRC; else known
    /// from the store's record of what the PLC accepted.
    pub read_back: bool,
    /// When the PLC accepted it (µs since the epoch), when recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub published_us: Option<i64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source_run: Option<i64>,
    #[serde(default)]
    pub composition: String,
    #[serde(default)]
    pub values_um: Vec<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub down_um: Option<Vec<f64>>,
}

/// The views of `active`, filled in from the store's tables and publications.
pub fn active_views(
    active: &RunTables,
    tables: &[TableRecord],
    pubs: &[PublicationRecord],
) -> Vec<ActiveView> {
    active
        .tables
        .iter()
        .map(|a| {
            let rec = a.table.and_then(|id| tables.iter().find(|t| t.id == id));
            let stored = rec.and_then(|r| StoredTable::from_record(r).ok());
            ActiveView {
                kind: a.kind.clone(),
                axis: a.axis.clone(),
                table_id: a.table.map(|t| t.0),
                sequence: a.sequence,
                crc: format!("0x{:08X}", a.crc),
                read_back: a.read_back,
                published_us: pubs
                    .iter()
                    .rev()
                    .find(|p| {
                        Some(p.publication.table) == a.table
                            && p.publication.sequence == a.sequence
                            && p.publication.outcome == PublicationOutcome::Accepted
                    })
                    .map(|p| p.publication.unix_us),
                source_run: rec.and_then(|r| r.entry.source_run.map(|x| x.0)),
                composition: stored
                    .as_ref()
                    .map(StoredTable::composition)
                    .unwrap_or_default(),
                values_um: stored.as_ref().map_or_else(Vec::new, |s| um(&s.values_mm)),
                down_um: stored.as_ref().and_then(|s| s.down_mm.as_deref().map(um)),
            }
        })
        .collect()
}

// ---------- decisions ----------

/// The sequence of the next publish: after every sequence the store has published and the
/// PLC's own (status and active), wrapping to 1 past the sequence field's largest value.
pub fn next_sequence(store_max: u32, plc: Option<&PlcStatus>, map: &CncMap) -> u32 {
    let (_, max) = map.header.sequence.ty.range();
    let max = max as u64;
    let known = plc.map_or(0, |s| s.status_sequence.max(s.active_sequence));
    let mut s = store_max.max(known) as u64 + 1;
    if s > max {
        s = 1;
    }
    // After a wrap, step past a sequence the PLC still reports.
    while plc.is_some_and(|p| p.status_sequence as u64 == s || p.active_sequence as u64 == s) {
        s = if s >= max { 1 } else { s + 1 };
    }
    s as u32
}

/// What the PLC holds against the store: (verdict, table, message). `staged` is the staging
/// area read back (its header, and whether the PLC's own check passes), `None` when it
/// cannot be read (pull). The staging area is the active table when its sequence is the
/// active one; then the CRC decides. Otherwise (a later publish was rejected or not
/// committed) only the active sequence can be matched against the store's publications.
pub fn verdict(
    status: &PlcStatus,
    staged: Option<(&RawHeader, Option<&Reject>)>,
    tables: &[TableRecord],
    pubs: &[PublicationRecord],
    target: &str,
) -> (&'static str, Option<TableId>, String) {
    let active = status.active_sequence;
    if active == 0 {
        return (
            "empty",
            None,
            "PLC empty: it applies no table (active sequence 0)".into(),
        );
    }
    let published = pubs
        .iter()
        .rev()
        .find(|p| {
            p.publication.target == target
                && p.publication.sequence == active
                && p.publication.outcome == PublicationOutcome::Accepted
        })
        .map(|p| p.publication.table);
    let crc_of = |id: TableId| tables.iter().find(|t| t.id == id).map(|t| t.entry.crc);
    match staged {
        Some((h, None)) if h.sequence == active => {
            if let Some(id) = published
                && crc_of(id) == Some(h.crc)
            {
                return (
                    "matches",
                    Some(id),
                    format!(
                        "matches table {id}: sequence {active}, CRC 0x{:08X} read back",
                        h.crc
                    ),
                );
            }
            if let Some(id) = published {
                return (
                    "differs",
                    Some(id),
                    format!(
                        "differs: the PLC's table (sequence {active}, CRC 0x{:08X}) is not table {id} published as sequence {active} (CRC 0x{:08X})",
                        h.crc,
                        crc_of(id).unwrap_or(0)
                    ),
                );
            }
            match tables.iter().rev().find(|t| t.entry.crc == h.crc) {
                Some(t) => (
                    "matches",
                    Some(t.id),
                    format!(
                        "matches table {} by its CRC 0x{:08X} (sequence {active} is not recorded as its publication to {target})",
                        t.id, h.crc
                    ),
                ),
                None => (
                    "differs",
                    None,
                    format!(
                        "differs: the PLC's table (sequence {active}, CRC 0x{:08X}) is none of the stored tables",
                        h.crc
                    ),
                ),
            }
        }
        Some((h, Some(r))) if h.sequence == active => (
            "differs",
            published,
            format!(
                "differs: the PLC's staging area for its active sequence {active} fails its check ({r})"
            ),
        ),
        _ => {
            let staged_note = match staged {
                Some((h, _)) => format!(
                    "; its staging area holds sequence {}, not applied, so the active table cannot be read back",
                    h.sequence
                ),
                None => String::new(),
            };
            match published {
                Some(id) => (
                    "matches",
                    Some(id),
                    format!(
                        "matches table {id} by its sequence {active} (accepted by the PLC){staged_note}"
                    ),
                ),
                None => (
                    "differs",
                    None,
                    format!(
                        "differs: the PLC applies sequence {active}, which the store has not recorded as accepted by {target}{staged_note}"
                    ),
                ),
            }
        }
    }
}

/// Build the tables of run `run_id` for `map` (nothing stored): evaluate its captures,
/// build positioning (and the straightnesses, when `build` says so) with the standard
/// mapping of the run's axis, fit each to the map's grid and check it encodes within the
/// map's limits. All or nothing: the first table that does not fit is the error.
pub fn generate(
    store: &Store,
    run_id: i64,
    residual_only: bool,
    map: &CncMap,
    build: &TableBuild,
) -> Result<Vec<(TableEntry, StoredTable)>, String> {
    // Finished, no flag open, and what the PLC applied while it ran known (issue 24).
    let during = composition::usable(store, RunId(run_id), residual_only)?;
    let rec = store.run(RunId(run_id)).map_err(|e| e.to_string())?;
    let captures = store.captures(rec.id).map_err(|e| e.to_string())?;
    let eval = evaluate_captures(&captures, &EvalOptions::default())
        .map_err(|e| format!("run {run_id} cannot be evaluated: {e}"))?;
    let axis = MachineAxis::from_letter(&rec.axis)
        .ok_or_else(|| format!("run {run_id}: axis {:?} is not X, Y or Z", rec.axis))?;
    let reference_mm = rec
        .plan
        .get("reference_mm")
        .and_then(serde_json::Value::as_f64)
        .or_else(|| eval.positions_mm.first().copied())
        .unwrap_or(0.0);
    let spec = TableSpec {
        mapping: AxisMapping::standard(axis),
        reference_mm,
        positioning: build.positioning,
        straightness_line: ReferenceLine::LeastSquares,
        functional_point_mm: None,
    };
    let set = comp::build_tables(&eval, &spec).map_err(|e| format!("run {run_id}: {e}"))?;
    let mut chosen = vec![set.positioning];
    if build.straightness {
        chosen.extend(set.straightness);
    }
    let generated_us = now_us();
    // Issue 15: what the PLC applied while the run ran; a table of a kind it applied is the
    // residual on top of that table, so it is composed with it.
    chosen
        .iter()
        .map(|c| {
            let fail = |e: String| {
                format!(
                    "run {run_id}: table {} does not fit the CNC map {}: {e}; nothing was stored",
                    c.name, map.file
                )
            };
            let active = during
                .as_ref()
                .and_then(|d| d.find(c.kind.name(), c.comp_axis.letter()));
            let (t, base) = match active {
                None => (
                    PlcTable::from_comp(c, map, build.step_mm).map_err(|e| fail(e.to_string()))?,
                    None,
                ),
                Some(a) => {
                    let cannot = |why: String| {
                        format!(
                            "run {run_id} was measured while the PLC applied {} {} sequence {} (CRC 0x{:08X}): {} cannot be composed with it ({why}); nothing was stored",
                            a.kind, a.axis, a.sequence, a.crc, c.name
                        )
                    };
                    let id = a
                        .table
                        .ok_or_else(|| cannot("that table is not in the store".into()))?;
                    let base_rec = store.table(id).map_err(|e| cannot(e.to_string()))?;
                    let base = StoredTable::from_record(&base_rec).map_err(cannot)?;
                    let t = composition::compose_stored(&base, c).map_err(cannot)?;
                    (
                        t,
                        Some(Base {
                            active: a.clone(),
                            run_id,
                        }),
                    )
                }
            };
            let enc = ptable::encode(&t, map, 1).map_err(|e| fail(e.to_string()))?;
            let mut stored = StoredTable::new(map, &t, c);
            stored.base = base;
            let entry = stored
                .entry(&t, enc.crc, Some(rec.id), generated_us)
                .map_err(|e| fail(e.to_string()))?;
            Ok((entry, stored))
        })
        .collect()
}

/// Pull only: serve `t` as `sequence` and wait for the PLC's acknowledgement.
async fn serve_for_pull(
    pull: &PullServer,
    t: &PlcTable,
    sequence: u32,
    wait: std::time::Duration,
) -> Result<PublishOutcome, plc::PublishError> {
    pull.set_table(t, sequence)?;
    match pull.wait_ack(sequence, wait).await {
        Some(a) if a.status.status == StatusCode::Accepted => Ok(PublishOutcome::Accepted {
            sequence,
            active_sequence: a.status.active_sequence,
        }),
        Some(a) => Ok(PublishOutcome::Rejected {
            sequence,
            code: ptable::RejectCode::from_code(a.status.error_code),
            active_sequence: a.status.active_sequence,
        }),
        None => Err(plc::PublishError::NoEcho {
            sequence,
            waited: wait,
            last: Some(pull.acks().borrow().status),
            link_error: None,
        }),
    }
}

// ---------- the task ----------

/// The tables task's state: the CNC map, the store connection, the PLC link, the pull server.
pub struct Tables {
    map: CncMap,
    settings: PlcSettings,
    store: StoreQueue,
    link: Option<Link>,
    pull: Option<PullServer>,
    /// Runs created from this time on get their active tables recorded (µs since the epoch).
    started_us: i64,
}

impl std::fmt::Debug for Tables {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Tables")
            .field("map", &self.map.name)
            .field("push", &self.link.as_ref().map(Link::addr))
            .field("pull", &self.pull_addr())
            .finish()
    }
}

impl Tables {
    /// Open a store connection of its own, start the link (push) and the pull server, and
    /// serve the last accepted table for pull.
    pub async fn start(
        map: CncMap,
        settings: &PlcSettings,
        store_path: &Path,
    ) -> Result<Tables, TablesError> {
        let store = Store::open(store_path)?;
        let mut map = map;
        if let Some(p) = &settings.push {
            map.unit_id = p.unit_or(map.unit_id);
        }
        let link = settings.push.as_ref().map(|p| Link::spawn(p.link.clone()));
        let pull = match &settings.pull {
            Some(cfg) => Some(PullServer::start(map.clone(), cfg.clone()).await?),
            None => None,
        };
        let (store, _) = StoreQueue::spawn(store);
        let t = Tables {
            map,
            settings: settings.clone(),
            store,
            link,
            pull,
            started_us: now_us(),
        };
        t.restore_pull().await;
        Ok(t)
    }

    /// Run `f` on this task's store connection (on the store's thread) and wait for it.
    async fn db<R, F>(&self, f: F) -> Result<R, String>
    where
        R: Send + 'static,
        F: FnOnce(&mut Store) -> Result<R, StoreError> + Send + 'static,
    {
        match self.store.call(f).await {
            Ok(r) => r.map_err(|e| e.to_string()),
            Err(e) => Err(e.to_string()),
        }
    }

    /// The tables and every publication, as stored.
    async fn tables_and_publications(
        &self,
    ) -> Result<(Vec<TableRecord>, Vec<PublicationRecord>), String> {
        self.db(|s| Ok((s.tables()?, s.publications(None)?))).await
    }

    /// Where the pull server listens.
    pub fn pull_addr(&self) -> Option<SocketAddr> {
        self.pull.as_ref().map(PullServer::local_addr)
    }

    /// Serve the table the PLC last accepted (any target) on the pull server.
    async fn restore_pull(&self) {
        let Some(pull) = &self.pull else { return };
        let last = match self.db(|s| s.publications(None)).await {
            Ok(p) => p
                .into_iter()
                .rev()
                .find(|p| p.publication.outcome == PublicationOutcome::Accepted),
            Err(e) => {
                tracing::warn!("pull server: cannot read publications: {e}");
                return;
            }
        };
        let Some(p) = last else { return };
        let id = p.publication.table;
        let r = self
            .db(move |s| s.table(id))
            .await
            .and_then(|r| StoredTable::from_record(&r))
            .and_then(|s| s.plc_table())
            .and_then(|t| {
                pull.set_table(&t, p.publication.sequence)
                    .map_err(|e| e.to_string())
            });
        match r {
            Ok(_) => tracing::info!(
                table = p.publication.table.0,
                sequence = p.publication.sequence,
                "pull server: serving the last accepted table"
            ),
            Err(e) => tracing::warn!("pull server: last accepted table not served: {e}"),
        }
    }

    fn push_target(&self) -> Option<String> {
        self.link
            .as_ref()
            .map(|l| format!("{} at {}", self.map.name, l.addr()))
    }

    fn pull_target(&self) -> Option<String> {
        self.pull_addr()
            .map(|a| format!("{} pulled from {a}", self.map.name))
    }

    /// Serve requests until shutdown; a publish in progress is finished first. Once a second,
    /// new runs get the tables active in the PLC recorded (read when the task first sees them,
    /// within a second of their start).
    pub async fn run(mut self, mut commands: mpsc::Receiver<Command>, mut shutdown: Shutdown) {
        let mut tick = tokio::time::interval(std::time::Duration::from_secs(1));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                _ = shutdown.recv() => break,
                c = commands.recv() => match c {
                    Some(c) => self.handle(c).await,
                    None => break,
                },
                _ = tick.tick() => self.record_new_runs().await,
            }
        }
    }

    /// What the PLC applies now (issue 15): read back (push) or its acknowledgement (pull),
    /// against the store's publications; "none" when no PLC is configured.
    pub async fn read_active(&mut self) -> RunTables {
        let unix_us = now_us();
        let unknown = |source: String| RunTables {
            unix_us,
            known: false,
            source,
            tables: Vec::new(),
        };
        let (tables, pubs) = match self.tables_and_publications().await {
            Ok(tp) => tp,
            Err(e) => return unknown(e),
        };
        if let (Some(link), Some(target)) = (&self.link, self.push_target()) {
            match plc::read_table(link, &self.map).await {
                Ok(rb) => {
                    let reject = rb.table.as_ref().err();
                    composition::active_tables(
                        &rb.status,
                        Some((&rb.header, reject)),
                        &tables,
                        &pubs,
                        &target,
                        unix_us,
                    )
                }
                Err(e) => unknown(format!("cannot read the PLC at {}: {e}", link.addr())),
            }
        } else if let (Some(pull), Some(target)) = (&self.pull, self.pull_target()) {
            let st = pull.acks().borrow().status;
            composition::active_tables(&st, None, &tables, &pubs, &target, unix_us)
        } else {
            RunTables {
                unix_us,
                known: true,
                source: "no PLC configured".into(),
                tables: Vec::new(),
            }
        }
    }

    /// Read what the PLC applies and record it as the tables active during run `run`.
    pub async fn record_run_tables(&mut self, run: RunId) -> Result<RunTables, String> {
        let active = self.read_active().await;
        let record = active.clone();
        self.db(move |s| s.record_run_tables(run, &record)).await?;
        tracing::info!(run = run.0, tables = %active.summary(), "tables active during the run recorded");
        Ok(active)
    }

    async fn record_new_runs(&mut self) {
        let since = self.started_us;
        let runs = match self.db(move |s| s.runs_without_tables(since)).await {
            Ok(r) => r,
            Err(e) => {
                tracing::warn!("cannot list new runs: {e}");
                return;
            }
        };
        for r in runs {
            if let Err(e) = self.record_run_tables(r).await {
                tracing::warn!(run = r.0, "tables active during the run not recorded: {e}");
            }
        }
    }

    /// Answer one table request from `who` (what the control socket's commands come to).
    pub async fn request(
        &mut self,
        request: &Request,
        who: &str,
    ) -> Result<serde_json::Value, String> {
        match request {
            Request::TableList { limit } => self.list(limit.unwrap_or(50)).await,
            Request::TableGenerate {
                run_id,
                residual_only,
            } => self.generate(*run_id, *residual_only).await,
            Request::TablePublish { table_id, confirm } => {
                self.publish(*table_id, *confirm, who).await
            }
            Request::TableStatus => self.status().await,
            _ => Err("internal: not a table request".into()),
        }
    }

    /// An audit entry for what a request did (the request itself is audited as it arrives).
    async fn audit_outcome(&mut self, who: &str, action: &str, details: serde_json::Value) {
        let entry = AuditEntry {
            unix_us: now_us(),
            who: crate::store::Actor {
                uid: None,
                user: (!who.is_empty()).then(|| who.to_string()),
                pid: None,
            },
            role: "service".into(),
            action: action.into(),
            details,
            outcome: crate::store::AuditOutcome::Done,
        };
        self.store_audit(entry).await;
    }

    async fn store_audit(&self, entry: AuditEntry) {
        if let Err(e) = self.db(move |s| s.audit(&entry)).await {
            tracing::error!("audit entry not stored: {e}");
        }
    }

    /// The request in the audit log, with what became of it.
    async fn audit(&mut self, c: &Command, r: &Result<serde_json::Value, String>) {
        let Some(mut entry) = c.audit_entry() else {
            return;
        };
        entry.outcome = match r {
            Ok(_) => crate::store::AuditOutcome::Done,
            Err(why) => crate::store::AuditOutcome::Refused(why.clone()),
        };
        self.store_audit(entry).await;
    }

    async fn handle(&mut self, c: Command) {
        let name = serde_json::to_value(&c.request)
            .ok()
            .and_then(|v| v["cmd"].as_str().map(str::to_string))
            .unwrap_or_default();
        tracing::info!(user = %c.peer.user, uid = c.peer.uid, request = %name, "control request");
        let r = match c.request.check() {
            Ok(()) => self.request(&c.request, &c.peer.user).await,
            Err(e) => Err(e),
        };
        self.audit(&c, &r).await;
        let _ = c.reply.send(r);
    }

    async fn list(&self, limit: usize) -> Result<serde_json::Value, String> {
        let (tables, pubs) = self.tables_and_publications().await?;
        let v: Vec<TableView> = tables
            .iter()
            .rev()
            .take(limit)
            .map(|t| table_view(t, &pubs))
            .collect();
        Ok(serde_json::json!({ "tables": v, "map": self.map.name }))
    }

    async fn generate(
        &mut self,
        run_id: i64,
        residual_only: bool,
    ) -> Result<serde_json::Value, String> {
        let (map, build) = (self.map.clone(), self.settings.tables);
        // Built and stored in one job: nothing else reaches this connection in between.
        let stored = match self
            .store
            .call(move |s| -> Result<Vec<TableRecord>, String> {
                let built = generate(s, run_id, residual_only, &map, &build)?;
                let mut records = Vec::new();
                for (entry, _) in &built {
                    let id = s.insert_table(entry).map_err(|e| e.to_string())?;
                    records.push(s.table(id).map_err(|e| e.to_string())?);
                }
                Ok(records)
            })
            .await
        {
            Ok(r) => r?,
            Err(e) => return Err(e.to_string()),
        };
        let views: Vec<TableView> = stored.iter().map(|rec| table_view(rec, &[])).collect();
        tracing::info!(
            run = run_id,
            tables = %views.iter().map(|v| v.id.to_string()).collect::<Vec<_>>().join(", "),
            "tables generated"
        );
        self.audit_outcome(
            "",
            "tables_generated",
            serde_json::json!({
                "run_id": run_id,
                "table_ids": views.iter().map(|v| v.id).collect::<Vec<_>>(),
                "compositions": views.iter().map(|v| v.composition.clone()).collect::<Vec<_>>(),
            }),
        )
        .await;
        Ok(serde_json::json!({ "run_id": run_id, "map": self.map.name, "tables": views }))
    }

    async fn publish(
        &mut self,
        table_id: i64,
        confirm: bool,
        who: &str,
    ) -> Result<serde_json::Value, String> {
        if !confirm {
            return Err(format!(
                "table_publish changes the compensation the machine applies: check table {table_id} (table_list) and send it again with \"confirm\": true (axiscomp table publish --table {table_id} --confirm)"
            ));
        }
        if self.link.is_none() && self.pull.is_none() {
            return Err(
                "no PLC is configured: set [plc] push = true and address, or pull = true, in the configuration"
                    .into(),
            );
        }
        let rec = self.db(move |s| s.table(TableId(table_id))).await?;
        let stored = StoredTable::from_record(&rec)?;
        let t = stored
            .plc_table()
            .map_err(|e| format!("table {table_id}: unreadable values ({e})"))?;
        let enc = ptable::encode(&t, &self.map, 1).map_err(|e| {
            format!(
                "table {table_id} cannot be encoded for the CNC map {}: {e}",
                self.map.file
            )
        })?;
        if enc.crc != rec.entry.crc {
            return Err(format!(
                "table {table_id} was fitted to the CNC map \"{}\" (CRC 0x{:08X}); the configured map {} gives CRC 0x{:08X}: generate it again (table_generate)",
                stored.map, rec.entry.crc, self.map.file, enc.crc
            ));
        }
        // Issue 24: nothing from a run whose flags are open.
        if let Some(r) = rec.entry.source_run
            && let Some(why) = self.db(move |s| s.open_flags(r)).await?
        {
            return Err(format!("table {table_id} is from run {}: {why}", r.0));
        }
        // Issue 15: never the residual alone, never on a base the PLC no longer applies.
        let during = match rec.entry.source_run {
            Some(r) => self.db(move |s| s.run_tables(r)).await?,
            None => None,
        };
        let now = self.read_active().await;
        composition::publishable(
            rec.id,
            &stored,
            rec.entry.source_run.map(|r| r.0),
            during.as_ref(),
            &now,
        )?;
        let store_max = self
            .db(|s| s.publications(None))
            .await?
            .iter()
            .map(|p| p.publication.sequence)
            .max()
            .unwrap_or(0);
        tracing::info!(table = table_id, by = who, "publishing");
        let (target, sequence, result, active) =
            if let (Some(link), Some(target)) = (self.link.clone(), self.push_target()) {
                // The PLC's sequences too, so a store that was reset never reuses one.
                let plc_now = plc::read_status(&link, &self.map).await.ok();
                let sequence = next_sequence(store_max, plc_now.as_ref(), &self.map);
                let r = plc::publish(&link, &self.map, &t, sequence, self.settings.timeouts).await;
                let active = match &r {
                    Ok(PublishOutcome::Accepted {
                        active_sequence, ..
                    })
                    | Ok(PublishOutcome::Rejected {
                        active_sequence, ..
                    }) => Some(*active_sequence),
                    Err(_) => None,
                };
                if matches!(r, Ok(PublishOutcome::Accepted { .. }))
                    && let Some(pull) = &self.pull
                    && let Err(e) = pull.set_table(&t, sequence)
                {
                    tracing::warn!("pull server: the published table not served: {e}");
                }
                (target, sequence, r, active)
            } else if let (Some(pull), Some(target)) = (&self.pull, self.pull_target()) {
                let sequence = next_sequence(store_max.max(pull.published()), None, &self.map);
                let r = serve_for_pull(pull, &t, sequence, self.settings.timeouts.echo).await;
                if !matches!(r, Ok(PublishOutcome::Accepted { .. })) {
                    // Withdraw it and serve the last accepted table again (or none), so the
                    // PLC does not pull a table that was refused or never acknowledged.
                    pull.clear();
                    self.restore_pull().await;
                }
                let active = pull.acks().borrow().status.active_sequence;
                (target, sequence, r, Some(active))
            } else {
                return Err("internal: no PLC".into());
            };
        let outcome = plc::publication_outcome(&result);
        let publication = Publication {
            table: rec.id,
            target: target.clone(),
            sequence,
            outcome,
            unix_us: now_us(),
        };
        let not_recorded = self
            .db(move |s| s.insert_publication(&publication))
            .await
            .err()
            .map(|e| {
                tracing::error!("publication not recorded: {e}");
                e.to_string()
            });
        let (res, code, message, commit_sent) = match &result {
            Ok(PublishOutcome::Accepted { .. }) => (
                "committed",
                None,
                format!("the PLC accepted sequence {sequence} and applies table {table_id}"),
                true,
            ),
            Ok(PublishOutcome::Rejected { code, .. }) => (
                "rejected",
                Some(code.code()),
                format!(
                    "the PLC rejected sequence {sequence}: {code}; it keeps its previous table"
                ),
                true,
            ),
            Err(e) => ("failed", None, e.to_string(), e.commit_sent()),
        };
        tracing::info!(table = table_id, sequence, result = res, %message, "publish done");
        // The audit log names the object (issue 15): which table, as which sequence, and what
        // came of it.
        self.audit_outcome(
            who,
            "table_published",
            serde_json::json!({
                "table_id": table_id, "kind": stored.kind, "axis": stored.axis.to_string(),
                "sequence": sequence, "crc": format!("0x{:08X}", rec.entry.crc),
                "target": target, "result": res, "composition": stored.composition(),
            }),
        )
        .await;
        let v = PublishView {
            table_id,
            target,
            sequence,
            result: res.into(),
            code,
            message,
            active_sequence: active,
            commit_sent,
            not_recorded,
        };
        serde_json::to_value(v).map_err(|e| e.to_string())
    }

    async fn status(&mut self) -> Result<serde_json::Value, String> {
        let (tables, pubs) = self.tables_and_publications().await?;
        let view = if let (Some(link), Some(target)) = (&self.link, self.push_target()) {
            let rb = plc::read_table(link, &self.map)
                .await
                .map_err(|e| format!("cannot read the PLC at {}: {e}", link.addr()))?;
            let reject = rb.table.as_ref().err();
            let (verdict, id, message) = verdict(
                &rb.status,
                Some((&rb.header, reject)),
                &tables,
                &pubs,
                &target,
            );
            let active = composition::active_tables(
                &rb.status,
                Some((&rb.header, reject)),
                &tables,
                &pubs,
                &target,
                now_us(),
            );
            StatusView {
                source: format!("read back from {target}"),
                plc: PlcStatusView::from(&rb.status),
                // A staging area never written (sequence 0) holds no table: not an invalid one.
                staged: (rb.header.sequence != 0).then(|| StagedView {
                    sequence: rb.header.sequence,
                    crc: format!("0x{:08X}", rb.header.crc),
                    points: rb.header.points,
                    kind: rb.header.kind,
                    axis: rb.header.axis,
                    direction: rb.header.direction,
                    invalid: reject.map(ToString::to_string),
                    values_um: rb
                        .table
                        .as_ref()
                        .map_or_else(|_| Vec::new(), |t| um(&t.values_mm)),
                    down_um: rb
                        .table
                        .as_ref()
                        .ok()
                        .and_then(|t| t.down_mm.as_deref().map(um)),
                }),
                verdict: verdict.into(),
                table_id: id.map(|t| t.0),
                message,
                active: active_views(&active, &tables, &pubs),
                active_source: active.source,
            }
        } else if let (Some(pull), Some(target)) = (&self.pull, self.pull_target()) {
            let st = pull.acks().borrow().status;
            let (verdict, id, message) = verdict(&st, None, &tables, &pubs, &target);
            let active = composition::active_tables(&st, None, &tables, &pubs, &target, now_us());
            StatusView {
                source: format!(
                    "the PLC's acknowledgement on {target} (published sequence {})",
                    pull.published()
                ),
                plc: PlcStatusView::from(&st),
                staged: None,
                verdict: verdict.into(),
                table_id: id.map(|t| t.0),
                message,
                active: active_views(&active, &tables, &pubs),
                active_source: active.source,
            }
        } else {
            return Err(
                "no PLC is configured: set [plc] push = true and address, or pull = true".into(),
            );
        };
        serde_json::to_value(view).map_err(|e| e.to_string())
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::plc::table::RejectCode;
    use crate::service::composition::tests::header;

    fn status(active: u32, status_sequence: u32) -> PlcStatus {
        PlcStatus {
            ready: 1,
            heartbeat: 7,
            status: StatusCode::Accepted,
            error_code: 0,
            status_sequence,
            active_sequence: active,
        }
    }

    #[test]
    fn sequences_follow_the_store_and_the_plc_and_wrap() {
        let m = CncMap::generic().unwrap();
        assert_eq!(next_sequence(0, None, &m), 1);
        assert_eq!(next_sequence(4, None, &m), 5);
        assert_eq!(next_sequence(4, Some(&status(9, 11)), &m), 12);
        assert_eq!(next_sequence(u32::MAX, None, &m), 1);
        assert_eq!(next_sequence(u32::MAX, Some(&status(1, 2)), &m), 3);
        let mut m16 = m.clone();
        for f in [
            &mut m16.header.sequence,
            &mut m16.handshake.commit,
            &mut m16.handshake.status_sequence,
            &mut m16.handshake.active_sequence,
        ] {
            f.ty = crate::modbus::codec::ValueType::U16;
        }
        assert_eq!(next_sequence(65_535, None, &m16), 1);
    }

    fn table(id: i64, crc: u32) -> TableRecord {
        TableRecord {
            id: TableId(id),
            entry: TableEntry {
                kind: "positioning".into(),
                axis: "Y".into(),
                direction: None,
                generated_us: 0,
                source_run: None,
                values: serde_json::json!({}),
                crc,
            },
        }
    }

    fn publication(table: i64, sequence: u32, outcome: PublicationOutcome) -> PublicationRecord {
        PublicationRecord {
            id: sequence as i64,
            publication: Publication {
                table: TableId(table),
                target: "plc".into(),
                sequence,
                outcome,
                unix_us: 0,
            },
        }
    }

    #[test]
    fn the_verdict_compares_the_crc_or_falls_back_to_the_sequence() {
        let tables = [table(1, 0xAAAA), table(2, 0xBBBB)];
        let pubs = [
            publication(1, 1, PublicationOutcome::Accepted),
            publication(
                2,
                2,
                PublicationOutcome::Rejected {
                    code: Some(1),
                    text: "CRC mismatch".into(),
                },
            ),
        ];
        let v = |st: &PlcStatus, h: Option<(&RawHeader, Option<&Reject>)>| {
            verdict(st, h, &tables, &pubs, "plc")
        };
        assert_eq!(v(&status(0, 0), None).0, "empty");
        // The active table read back: CRC compared.
        let (verdict, id, msg) = v(&status(1, 1), Some((&header(1, 0xAAAA), None)));
        assert_eq!((verdict, id), ("matches", Some(TableId(1))), "{msg}");
        assert!(
            msg.contains("matches table 1") && msg.contains("CRC"),
            "{msg}"
        );
        let (verdict, _, msg) = v(&status(1, 1), Some((&header(1, 0xCCCC), None)));
        assert_eq!(verdict, "differs", "{msg}");
        // Sequence 2 was rejected: the staging holds it, the PLC still applies 1.
        let (verdict, id, msg) = v(&status(1, 2), Some((&header(2, 0xBBBB), None)));
        assert_eq!((verdict, id), ("matches", Some(TableId(1))), "{msg}");
        assert!(msg.contains("by its sequence 1"), "{msg}");
        // A staging area that fails its own check for the active sequence.
        let r = Reject {
            code: RejectCode::Crc,
            detail: "x".into(),
        };
        assert_eq!(
            v(&status(1, 1), Some((&header(1, 0xAAAA), Some(&r)))).0,
            "differs"
        );
        // Unknown active sequence, but a stored table's CRC.
        let (verdict, id, _) = v(&status(7, 7), Some((&header(7, 0xBBBB), None)));
        assert_eq!((verdict, id), ("matches", Some(TableId(2))));
        // Pull: the acknowledgement only.
        assert_eq!(v(&status(1, 1), None).0, "matches");
        assert_eq!(v(&status(2, 2), None).0, "differs");
    }
}
