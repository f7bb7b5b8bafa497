//! The live service (DESIGN §5, §8): the I/O-module link and acquisition, the follower drive,
//! the core task (tracking, stitching, live decoupling, alarms), the tables task (compensation
//! tables to the CNC's PLC, `tables`), the control socket, systemd notification — wired around
//! a `Snapshot` on a watch channel. `run(settings, shutdown)` is the whole service; `prepare`
//! loads and checks everything it reads (also `axiscomp check`).

pub mod align;
pub mod api;
pub mod calibration;
pub mod checks;
pub mod cnc;
pub mod composition;
pub mod control;
mod core;
pub mod follower;
pub mod machine;
pub mod measure;
pub mod notify;
pub mod peer;
pub mod pipeline;
pub mod procedure;
pub mod results;
mod run_budget;
pub mod shutdown;
pub mod stored;
pub mod tables;
pub mod trends;

use crate::acquire::{Acquisition, IoMap, MapError};
use crate::calibrate::{CalError, Calibration, CalibrationFile};
use crate::can::CanError;
use crate::can::cannelloni::Cannelloni;
use crate::can::pycan::PyCanMulticast;
use crate::can::socketcan::SocketCan;
use crate::canopen::{DriveHandle, spawn_drive};
use crate::config::{CanSettings, Resource, Settings};
use crate::decouple::{Decoupler, Method, SolveOptions, Source};
use crate::optics::{Layout, LayoutError};
use api::Snapshot;
use shutdown::Shutdown;
use thiserror::Error;
use tokio::sync::{mpsc, watch};

/// Why the service could not start or had to stop.
#[derive(Debug, Error)]
pub enum ServiceError {
    #[error(transparent)]
    Layout(#[from] LayoutError),
    #[error(transparent)]
    Calibration(#[from] CalError),
    #[error(transparent)]
    Map(#[from] MapError),
    #[error("CAN transport {what}: {source}")]
    Can { what: String, source: CanError },
    #[error("follower drive settings: {0}")]
    Drive(#[from] crate::canopen::ConfigError),
    #[error(transparent)]
    Control(#[from] control::ControlError),
    #[error("decoupling: {0}")]
    Decouple(#[from] crate::decouple::DecoupleError),
    #[error(transparent)]
    Store(#[from] crate::store::StoreError),
    #[error(transparent)]
    CncMap(#[from] crate::plc::MapError),
    #[error("[plc] pull = true: {0}")]
    PullLayout(crate::plc::PullError),
    #[error(transparent)]
    Tables(#[from] tables::TablesError),
    #[error("state directory {path}: {source}; create it or set service.state_dir")]
    StateDir {
        path: String,
        source: std::io::Error,
    },
    #[error("internal: {0}")]
    Internal(&'static str),
    #[error("the service's core task ended abnormally: {0}")]
    CoreTask(String),
}

impl ServiceError {
    /// Whether the cause is input the user must fix (a file or setting), not the field.
    pub fn is_input(&self) -> bool {
        matches!(
            self,
            ServiceError::Layout(_)
                | ServiceError::Map(_)
                | ServiceError::CncMap(_)
                | ServiceError::PullLayout(_)
                | ServiceError::Drive(_)
                | ServiceError::Calibration(
                    CalError::File { .. } | CalError::Input(_) | CalError::Csv(_)
                )
        )
    }
}

/// Everything the service reads from files, loaded and checked.
#[derive(Clone, Debug)]
pub struct Prepared {
    pub settings: Settings,
    pub layout: Layout,
    pub calibration: Option<Calibration>,
    pub map: IoMap,
    pub decoupler: Decoupler,
    /// The CNC map of `[plc]` (`plc-maps/cnc/`).
    pub cnc_map: crate::plc::CncMap,
}

/// Load and check the layout, the calibration, the I/O map, the CNC map and the drive settings.
pub fn prepare(settings: &Settings) -> Result<Prepared, ServiceError> {
    let layout = match &settings.head.layout {
        Resource::Builtin(_) => Layout::reference(),
        Resource::File(p) => Layout::load(p)?,
    };
    let map = match &settings.io.map {
        Resource::Builtin(_) => IoMap::generic()?,
        Resource::File(p) => IoMap::load(p)?,
    };
    settings.follower.drive.validate()?;
    let cnc_map = match &settings.plc.map {
        Resource::Builtin(_) => crate::plc::CncMap::generic()?,
        Resource::File(p) => crate::plc::CncMap::load(p)?,
    };
    if settings.plc.pull.is_some() {
        crate::plc::serve::ack_range(&cnc_map).map_err(ServiceError::PullLayout)?;
    }
    let calibration = match &settings.head.calibration {
        Some(p) => Some(CalibrationFile::load(p, &layout)?),
        None => None,
    };
    let decoupler = match &calibration {
        Some(c) => c.decoupler(&layout)?,
        None => Decoupler {
            source: Source::Simulated(layout.clone()),
            method: Method::Nonlinear,
            sigma_mm: [settings.head.noise_mm; 6],
            options: SolveOptions::default(),
        },
    };
    Ok(Prepared {
        settings: settings.clone(),
        layout,
        calibration,
        map,
        decoupler,
        cnc_map,
    })
}

/// Start the drive's master on the configured transport.
async fn start_drive(
    p: &Prepared,
) -> Result<
    (
        DriveHandle,
        tokio::task::JoinHandle<Result<(), CanError>>,
        String,
    ),
    ServiceError,
> {
    let cfg = &p.settings.follower.drive;
    let can_err = |what: String| move |source| ServiceError::Can { what, source };
    Ok(match &p.settings.can {
        CanSettings::SocketCan { interface } => {
            let t = SocketCan::open(interface).map_err(can_err(interface.clone()))?;
            let (h, j) = spawn_drive(t, cfg)?;
            (h, j, interface.clone())
        }
        CanSettings::Cannelloni { local, remote } => {
            let what = format!("cannelloni {local} → {remote}");
            let t = Cannelloni::open(*local, *remote)
                .await
                .map_err(can_err(what.clone()))?;
            let (h, j) = spawn_drive(t, cfg)?;
            (h, j, what)
        }
        CanSettings::PyCan { group, port, iface } => {
            let what = format!("python-can udp_multicast {group}:{port} on {iface}");
            let t = PyCanMulticast::open(*group, *port, *iface)
                .await
                .map_err(can_err(what.clone()))?;
            let (h, j) = spawn_drive(t, cfg)?;
            (h, j, what)
        }
    })
}

/// Run the service until `shutdown` fires. Returns when every task has stopped.
pub async fn run(p: Prepared, shutdown: Shutdown) -> Result<(), ServiceError> {
    let s = &p.settings;
    tracing::info!(sources = %s.sources.join(", "), "axiscomp service starting");
    let listener = control::bind(&s.service.socket)?;
    let mut map = p.map.clone();
    if s.io.unit != 0 {
        map.unit_id = s.io.unit;
    }
    let map = std::sync::Arc::new(map);
    // Paced reads cost one wake-up per frame (modbus::paced); unthrottled ones keep
    // io.pipeline reads in flight (modbus::pipelined).
    let acquisition = if s.io.acquire.rate_hz > 0.0 {
        Acquisition::spawn_paced(s.io.link.clone(), map, s.io.acquire)
    } else {
        Acquisition::spawn_pipelined(s.io.link.clone(), map, s.io.acquire)
    };
    std::fs::create_dir_all(&s.service.state_dir).map_err(|source| ServiceError::StateDir {
        path: s.service.state_dir.display().to_string(),
        source,
    })?;
    let store_path = s.service.state_dir.join("axiscomp.db");
    let store = crate::store::Store::open(&store_path)?;
    // What the loop looks up in the store, read before it starts.
    let startup = startup(&store, &s.service.state_dir, s.cnc.dialect, &p.decoupler);
    let (store, store_task) = crate::store::StoreQueue::spawn(store);
    // Opened after the core's store, which created and migrated the file.
    let tables = tables::Tables::start(p.cnc_map.clone(), &s.plc, &store_path).await?;
    let (drive, drive_task, can_peer) = start_drive(&p).await?;
    let (snap_tx, snap_rx) = watch::channel(Snapshot::default());
    let (cmd_tx, mut cmd_rx) = mpsc::channel::<control::Command>(32);
    // Table requests go to the tables task (a publish waits on the PLC), the rest to the core.
    let (core_tx, core_rx) = mpsc::channel(32);
    let (tables_tx, tables_rx) = mpsc::channel(8);
    let router = tokio::spawn(async move {
        while let Some(c) = cmd_rx.recv().await {
            let to = if c.request.is_table() {
                tables_tx.send(c).await
            } else {
                core_tx.send(c).await
            };
            if to.is_err() {
                break;
            }
        }
    });
    let tables_task = tokio::spawn(tables.run(tables_rx, shutdown.clone()));
    // The check the CNC asks for in a break (`[check]` in the CNC map, with push: the service
    // reads the PLC's request).
    let checks_task = match (&p.cnc_map.check, &s.plc.push) {
        (Some(fields), Some(push)) => {
            let checks = checks::Checks {
                fields: fields.clone(),
                unit: push.unit_or(p.cnc_map.unit_id),
                push: push.clone(),
                requests: cmd_tx.clone(),
                store_path: store_path.clone(),
                acceptance: s.acceptance.clone(),
            };
            Some(tokio::spawn(checks.run(shutdown.clone())))
        }
        _ => None,
    };
    let policy = peer::RolePolicy::from_names(&s.service.operator_group, &s.service.viewer_group);
    control::open_to_roles(&s.service.socket, &policy)?;
    let control = tokio::spawn(control::serve(
        listener,
        policy,
        snap_rx,
        cmd_tx,
        s.service.snapshot_period,
        s.service.max_connections,
        shutdown.clone(),
    ));
    let core = core::Core::new(&p, acquisition, drive, can_peer, snap_tx, store, startup);
    // A task of its own rather than the runtime's root future: waking the root future from a
    // task (every frame) costs the current-thread runtime an eventfd write and an extra poll.
    let result = match tokio::spawn(core.run(core_rx, shutdown)).await {
        Ok(r) => r,
        Err(e) => Err(ServiceError::CoreTask(e.to_string())),
    };
    notify::stopping();
    drive_task.abort();
    if let Some(t) = checks_task {
        t.abort();
    }
    let _ = control.await;
    router.abort();
    // A publish in progress ends within its own timeouts.
    if tokio::time::timeout(std::time::Duration::from_secs(30), tables_task)
        .await
        .is_err()
    {
        tracing::warn!("the tables task did not stop within 30 s");
    }
    let _ = std::fs::remove_file(&s.service.socket);
    // What the store was given is written before the service says it stopped.
    if tokio::time::timeout(std::time::Duration::from_secs(30), store_task)
        .await
        .is_err()
    {
        tracing::warn!("the store did not finish its queue within 30 s");
    }
    tracing::info!("axiscomp service stopped");
    result
}

/// What the core looks up in the store (the newest alignment of each axis, the follower map
/// in use) and a run the store says is still running (the service stopped or crashed in it):
/// read once, before the loop starts.
fn startup(
    store: &crate::store::Store,
    state_dir: &std::path::Path,
    configured: crate::run::Dialect,
    decoupler: &crate::decouple::Decoupler,
) -> core::Startup {
    use crate::store::RunState;
    let mut cached = procedure::Cached::default();
    match store.aligned_axes() {
        Ok(axes) => {
            for axis in axes {
                if let Ok(Some(rec)) = store.latest_alignment(&axis) {
                    cached.alignments.insert(axis, rec);
                }
            }
        }
        Err(e) => tracing::warn!("the alignments could not be read: {e}"),
    }
    match store.follower_map_in_use() {
        Ok(m) => cached.follower_map = m,
        Err(e) => {
            tracing::warn!("the follower map in use could not be read: {e}; tracking without")
        }
    }
    let resume = match store.runs_in_state(RunState::Running) {
        Ok(runs) => runs.into_iter().max_by_key(|r| r.id.0).and_then(|rec| {
            let plan: Result<crate::run::Plan, String> =
                serde_json::from_value(rec.plan.clone()).map_err(|e| e.to_string());
            let done = store.captures(rec.id).map_err(|e| e.to_string());
            // The run's programs go on in the dialect it was started with (the configuration
            // snapshot names it), not in the configured default.
            let dialect = rec.config["dialect"]
                .as_str()
                .and_then(crate::run::Dialect::parse)
                .unwrap_or(configured);
            match (plan, done) {
                (Ok(plan), Ok(done)) => {
                    tracing::info!(
                        run = rec.id.0,
                        captured = done.len(),
                        "resuming run once the follower is ready"
                    );
                    Some(procedure::run::Resume {
                        id: rec.id,
                        plan,
                        dialect,
                        stored: done,
                        programs: programs_written(state_dir, rec.id),
                    })
                }
                (Err(e), _) | (_, Err(e)) => {
                    let why = format!("it cannot resume: its plan or captures do not load: {e}");
                    tracing::warn!(run = rec.id.0, "{why}");
                    None
                }
            }
        }),
        Err(e) => {
            tracing::warn!("cannot look for runs to resume: {e}");
            None
        }
    };
    let reference = kept_reference(store, decoupler);
    core::Startup {
        cached,
        resume,
        reference,
    }
}

/// The zero reference in force when the service stopped, if it is in the terms of the
/// decoupling it starts with.
fn kept_reference(
    store: &crate::store::Store,
    decoupler: &crate::decouple::Decoupler,
) -> Option<measure::ReferenceState> {
    let kept = match store.latest_reference() {
        Ok(k) => k?,
        Err(e) => {
            tracing::warn!(
                "the zero reference kept before the restart could not be read: {e}; zero again"
            );
            return None;
        }
    };
    let text = kept.state_json?;
    let when = crate::store::iso_utc(kept.unix_us);
    if kept.decoupler != measure::decoupler_name(decoupler) {
        tracing::warn!(
            "the zero reference of {when} was taken with another calibration than the one in use: not taken back; zero again"
        );
        return None;
    }
    match serde_json::from_str(&text) {
        Ok(state) => Some(state),
        Err(e) => {
            tracing::warn!(
                "the zero reference of {when} does not load ({e}): not taken back; zero again"
            );
            None
        }
    }
}

/// The highest program number written for run `id` (0: none).
fn programs_written(state_dir: &std::path::Path, id: crate::store::RunId) -> u32 {
    let dir = state_dir.join("runs").join(id.0.to_string());
    std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .filter_map(|e| {
                    let name = e.ok()?.file_name().into_string().ok()?;
                    name.strip_prefix("program-")?
                        .split('.')
                        .next()?
                        .parse::<u32>()
                        .ok()
                })
                .max()
                .unwrap_or(0)
        })
        .unwrap_or(0)
}
