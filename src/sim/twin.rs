//! The assembled digital twin: the plant, its I/O module on Modbus TCP, the follower's CiA 402
//! drive on a CAN transport, and a control socket for what a test (or an operator at the twin)
//! would do to the plant: move the carriage, read the truth, inject faults.
//!
//! Control protocol: TCP, newline-delimited JSON, one reply line per request:
//! - `{"cmd":"move","mm":100.0}` → `{"ok":true,"duration_s":2.1}`
//! - `{"cmd":"wait"}` → waits until the carriage is at rest
//! - `{"cmd":"truth"}` → `{"ok":true,"truth":{...}}` (user units);
//!   `{"cmd":"truth","mm":500.0,"direction":"+"}` → `{"ok":true,"errors":[dx,dy,dz,ex,ey,ez]}`
//!   (µm, arcsec): the axis' errors at that position approached that way, now (what a capture
//!   taken there at rest is judged by)
//! - `{"cmd":"rests"}` → `{"ok":true,"rests":[{"from_unix_us","to_unix_us","mm","direction"}]}`:
//!   the carriage's last rests (nominal mm, the direction of the move that ended there, the
//!   twin's wall clock), what each capture was really taken at
//! - `{"cmd":"block","psd":2,"on":true}` (PSD 1..3)
//! - `{"cmd":"io","action":"stop"|"restart"}`, `{"cmd":"io","delay_ms":50}` (a hung module:
//!   a delay longer than the client waits), `{"cmd":"io","exception":6}` (every request answered
//!   with that exception code; 0 to stop)
//! - `{"cmd":"drive","fault":34321}`, `{"cmd":"drive","heartbeat":false}`
//! - `{"cmd":"program","dialect":"linuxcnc","axis":"X","text":"..."}`: run a part program on
//!   the twin's CNC (replacing one that runs); `{"cmd":"cnc"}` → its state;
//!   `{"cmd":"cnc","stop":true}` stops the running program at its next stop (the move in
//!   progress ends; `stopped` says so once it has)
//! - `{"cmd":"mount"}` → how the head is mounted (`yaw_urad`, `pitch_urad`, `x_mm`, `z_mm`);
//!   `{"cmd":"turn","screw":"yaw","turns":1.25}` turns a mount screw (clockwise positive) as a
//!   technician does; `{"cmd":"knock","yaw_urad":3000}` (any of the four) knocks the head
//! - `{"cmd":"plc"}` → the twin PLC's status, its active table per head axis (sequence, the
//!   points) and every commit it saw; with any of `"reject_next":256`, `"ignore_next":true`,
//!   `"corrupt_next":3` (payload register), `"silent_after":2` with `"down_ms":1500`,
//!   `"ready":false`, `"freeze_heartbeat":true` it injects that fault first (DESIGN §6's
//!   table protocol faults; only once `axiscomp sim` has started its PLC);
//!   `"request_check":true` is the CNC asking for a check in a break (the next number into
//!   the map's `check.request`), and `"check"` in the reply holds the check fields
//! - `{"cmd":"target"}` → what the alignment target in front of each PSD shows (mm, to 0.5 mm;
//!   `null` where no beam reaches it)
//! - `{"cmd":"age","positioning_um":6,"backlash_um":3,"thermal_um":5}` ages the axis while the
//!   twin runs (issue 15: years of wear for a maintenance re-measurement; `sim::axis::Wear`):
//!   the fields given replace the wear in force, the others keep theirs (each 0..=100 µm);
//!   `{"cmd":"age"}` → the wear in force
//! - `{"cmd":"level"}` → the twin's electronic level on the carriage, a simulated instrument:
//!   `{"ok":true,"level":{"roll_arcsec":…,"sd_arcsec":…,"instrument":"…"}}`, the axis' true
//!   roll where the carriage is plus `PlantSpec::level_sd_rad` of noise (1 µrad by default) a
//!   reading, as a precision level reads roll against gravity (the service's follower level
//!   stations with `[follower] level = "twin"`)

use super::SimError;
use super::axis::Wear;
use super::drive::{TwinDriveConfig, TwinDriveHandle, spawn_twin_drive};
use super::iomodule::{IoModule, IoModuleConfig};
use super::plant::{Plant, PlantSpec, Truth};
use crate::acquire::IoMap;
use crate::can::cannelloni::Cannelloni;
use crate::can::memory::MemoryBus;
use crate::can::pycan::PyCanMulticast;
use crate::can::{CanError, CanTransport};
use crate::optics::Layout;
use crate::run::Dialect;
use serde::{Deserialize, Serialize};
use std::net::{Ipv4Addr, SocketAddr};
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::{TcpListener, TcpStream};
use tokio::task::JoinHandle;

/// How the twin's drive reaches the bus.
#[derive(Clone, Debug)]
pub enum TwinCan {
    /// A cannelloni UDP gateway: the twin listens on `local` and sends to `remote`.
    Cannelloni {
        local: SocketAddr,
        remote: SocketAddr,
    },
    /// python-can's udp_multicast bus.
    PyCan {
        group: Ipv4Addr,
        port: u16,
        iface: Ipv4Addr,
    },
    /// An in-process bus (the service must be in the same process).
    Memory(MemoryBus),
}

/// Everything the twin is built from.
#[derive(Clone, Debug)]
pub struct TwinSpec {
    pub plant: PlantSpec,
    pub io_bind: SocketAddr,
    pub io_map: IoMap,
    pub can: TwinCan,
    pub drive: TwinDriveConfig,
    /// Where the control socket listens (None: no socket).
    pub control: Option<SocketAddr>,
}

/// The twin CNC's state, shared with whoever plays its PLC side.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct CncState {
    pub running: bool,
    pub done: bool,
    /// Programs started so far.
    pub programs: u32,
    /// Handshake outputs of the CNC.
    pub code: u32,
    pub at_target: bool,
    /// The PLC's "captured" input to the CNC.
    pub captured: bool,
    /// The program time of the last completed program (s).
    pub last_program_s: Option<f64>,
    /// Stop the running program at its next stop (as the service asks when a run pauses).
    pub stop_requested: bool,
    /// Whether the last program ended by such a stop.
    pub stopped: bool,
}

/// The running twin.
pub struct Twin {
    pub plant: Arc<Plant>,
    pub io: IoModule,
    pub drive: TwinDriveHandle,
    pub cnc: Arc<std::sync::Mutex<CncState>>,
    cnc_task: Arc<std::sync::Mutex<Option<JoinHandle<()>>>>,
    drive_task: JoinHandle<Result<(), CanError>>,
    control: Option<(SocketAddr, JoinHandle<()>)>,
    plc: Arc<std::sync::Mutex<Option<Arc<super::plc::TwinPlc>>>>,
}

impl Drop for Twin {
    fn drop(&mut self) {
        self.drive_task.abort();
        if let Some(t) = self
            .cnc_task
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .take()
        {
            t.abort();
        }
        if let Some((_, t)) = &self.control {
            t.abort();
        }
    }
}

/// The truth in user units, as the control socket reports it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TruthView {
    pub travel_mm: f64,
    pub moving: bool,
    /// dx, dy, dz (µm), ex, ey, ez (arcsec).
    pub errors: [f64; 6],
    pub follower_encoder_mm: f64,
    pub follower_true_mm: f64,
    pub follower_vertical_um: f64,
}

impl From<Truth> for TruthView {
    fn from(t: Truth) -> Self {
        TruthView {
            travel_mm: t.travel,
            moving: t.moving,
            errors: t.errors.to_user(),
            follower_encoder_mm: t.follower_encoder,
            follower_true_mm: t.follower_true,
            follower_vertical_um: t.follower_vertical * 1e3,
        }
    }
}

fn spawn_drive_on<T: CanTransport>(
    transport: T,
    cfg: TwinDriveConfig,
    plant: Arc<Plant>,
) -> Result<(TwinDriveHandle, JoinHandle<Result<(), CanError>>), SimError> {
    spawn_twin_drive(transport, cfg, move |mm| plant.set_follower_encoder(mm))
}

impl Twin {
    /// Build and start the twin (inside a tokio runtime).
    pub async fn start(layout: &Layout, spec: TwinSpec) -> Result<Twin, SimError> {
        let plant = Arc::new(Plant::new(layout, &spec.plant, crate::util::clock::now())?);
        let io = IoModule::start(
            plant.clone(),
            spec.io_map.clone(),
            IoModuleConfig {
                bind: spec.io_bind,
                ..IoModuleConfig::default()
            },
        )
        .await
        .map_err(|e| SimError::Input(format!("twin I/O module: {e}")))?;
        let can_err = |e: CanError| SimError::Input(format!("twin CAN transport: {e}"));
        let (drive, drive_task) = match &spec.can {
            TwinCan::Cannelloni { local, remote } => spawn_drive_on(
                Cannelloni::open(*local, *remote).await.map_err(can_err)?,
                spec.drive,
                plant.clone(),
            )?,
            TwinCan::PyCan { group, port, iface } => spawn_drive_on(
                PyCanMulticast::open(*group, *port, *iface)
                    .await
                    .map_err(can_err)?,
                spec.drive,
                plant.clone(),
            )?,
            TwinCan::Memory(bus) => spawn_drive_on(bus.port(), spec.drive, plant.clone())?,
        };
        let mut twin = Twin {
            plant,
            io,
            drive,
            cnc: Arc::new(std::sync::Mutex::new(CncState::default())),
            cnc_task: Arc::new(std::sync::Mutex::new(None)),
            drive_task,
            control: None,
            plc: Arc::default(),
        };
        if let Some(bind) = spec.control {
            let listener = TcpListener::bind(bind)
                .await
                .map_err(|e| SimError::Input(format!("twin control socket {bind}: {e}")))?;
            let addr = listener
                .local_addr()
                .map_err(|e| SimError::Input(format!("twin control socket: {e}")))?;
            let ctx = Ctx {
                plant: twin.plant.clone(),
                drive: twin.drive.clone(),
                io: twin.io.server().clone(),
                cnc: twin.cnc.clone(),
                cnc_task: twin.cnc_task.clone(),
                plc: twin.plc.clone(),
                level_rng: Arc::new(std::sync::Mutex::new(
                    super::Rng::new(spec.plant.seed).fork(LEVEL_FORK),
                )),
            };
            let task = tokio::spawn(serve_control(listener, ctx));
            twin.control = Some((addr, task));
        }
        Ok(twin)
    }

    /// The control socket's address.
    pub fn control_addr(&self) -> Option<SocketAddr> {
        self.control.as_ref().map(|(a, _)| *a)
    }

    /// Put the twin's PLC (started on the same plant) under the control socket's `plc` command.
    pub fn attach_plc(&self, plc: Arc<super::plc::TwinPlc>) {
        *self.plc.lock().unwrap_or_else(|p| p.into_inner()) = Some(plc);
    }

    /// Run a part program on the twin's CNC, replacing one that runs.
    pub fn run_program(&self, text: &str, dialect: Dialect, axis: &str) -> Result<(), String> {
        start_program(&self.plant, &self.cnc, &self.cnc_task, text, dialect, axis)
    }

    /// Move the carriage to `mm` and wait until it is at rest.
    pub async fn move_and_wait(&self, mm: f64) {
        self.plant.move_carriage(mm, crate::util::clock::now());
        let end = self.plant.carriage_move_end();
        tokio::time::sleep_until(tokio::time::Instant::from_std(end)).await;
    }
}

#[derive(Clone)]
struct Ctx {
    plant: Arc<Plant>,
    drive: TwinDriveHandle,
    io: crate::modbus::ServerHandle,
    cnc: Arc<std::sync::Mutex<CncState>>,
    cnc_task: Arc<std::sync::Mutex<Option<JoinHandle<()>>>>,
    plc: Arc<std::sync::Mutex<Option<Arc<super::plc::TwinPlc>>>>,
    /// The twin level's noise (`level`).
    level_rng: Arc<std::sync::Mutex<super::Rng>>,
}

/// Parse `text` and run it on a fresh CNC task (aborting the one that runs).
fn start_program(
    plant: &Arc<Plant>,
    cnc: &Arc<std::sync::Mutex<CncState>>,
    task: &Arc<std::sync::Mutex<Option<JoinHandle<()>>>>,
    text: &str,
    dialect: Dialect,
    axis: &str,
) -> Result<(), String> {
    let ops = super::cnc::parse(text, dialect, axis).map_err(|e| e.to_string())?;
    let mut slot = task.lock().unwrap_or_else(|p| p.into_inner());
    if let Some(old) = slot.take() {
        old.abort();
    }
    {
        let mut st = cnc.lock().unwrap_or_else(|p| p.into_inner());
        st.running = true;
        st.done = false;
        st.programs += 1;
        st.at_target = false;
        st.stop_requested = false;
        st.stopped = false;
    }
    let (plant, cnc) = (plant.clone(), cnc.clone());
    *slot = Some(tokio::spawn(async move {
        let mut m = super::cnc::Cnc::new(ops);
        loop {
            let (captured, stop) = cnc
                .lock()
                .map(|s| (s.captured, s.stop_requested))
                .unwrap_or((false, false));
            if stop {
                m.stop_at_next_stop();
            }
            m.step(crate::util::clock::now(), &plant, captured);
            {
                let mut st = cnc.lock().unwrap_or_else(|p| p.into_inner());
                st.code = m.handshake.code;
                st.at_target = m.handshake.at_target;
                if m.is_done() {
                    st.running = false;
                    st.done = true;
                    st.stopped = st.stop_requested;
                    st.last_program_s = match (m.started, m.finished) {
                        (Some(a), Some(b)) => Some((b - a).as_secs_f64()),
                        _ => None,
                    };
                    return;
                }
            }
            // Wake at the next event, or soon while waiting for the PLC.
            let next = m
                .next_wake()
                .map(|w| w.min(crate::util::clock::now() + Duration::from_millis(5)))
                .unwrap_or(crate::util::clock::now() + Duration::from_millis(5));
            tokio::time::sleep_until(tokio::time::Instant::from_std(next)).await;
        }
    }));
    Ok(())
}

async fn serve_control(listener: TcpListener, ctx: Ctx) {
    loop {
        match listener.accept().await {
            Ok((s, _)) => {
                tokio::spawn(control_connection(s, ctx.clone()));
            }
            Err(e) => {
                tracing::warn!("twin control accept: {e}");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    }
}

async fn control_connection(s: TcpStream, ctx: Ctx) {
    let (rd, mut wr) = s.into_split();
    let mut lines = BufReader::new(rd).lines();
    while let Ok(Some(line)) = lines.next_line().await {
        let reply = match serde_json::from_str::<serde_json::Value>(&line) {
            Ok(v) => handle(&ctx, &v)
                .await
                .unwrap_or_else(|e| serde_json::json!({"ok": false, "error": e})),
            Err(e) => serde_json::json!({"ok": false, "error": format!("not JSON: {e}")}),
        };
        let mut text = reply.to_string();
        text.push('\n');
        if wr.write_all(text.as_bytes()).await.is_err() {
            return;
        }
    }
}

async fn handle(ctx: &Ctx, v: &serde_json::Value) -> Result<serde_json::Value, String> {
    let cmd = v.get("cmd").and_then(|c| c.as_str()).ok_or("no \"cmd\"")?;
    let num = |k: &str| v.get(k).and_then(|x| x.as_f64());
    match cmd {
        "move" => {
            let mm = num("mm").ok_or("move needs \"mm\"")?;
            let now = crate::util::clock::now();
            ctx.plant.move_carriage(mm, now);
            let d = ctx.plant.carriage_move_end().saturating_duration_since(now);
            Ok(serde_json::json!({"ok": true, "duration_s": d.as_secs_f64()}))
        }
        "wait" => {
            let end = ctx.plant.carriage_move_end();
            tokio::time::sleep_until(tokio::time::Instant::from_std(end)).await;
            Ok(serde_json::json!({"ok": true}))
        }
        "truth" => {
            let now = crate::util::clock::now();
            let Some(mm) = num("mm") else {
                let t = TruthView::from(ctx.plant.truth(now));
                return Ok(serde_json::json!({"ok": true, "truth": t}));
            };
            let dir = match v.get("direction").and_then(|d| d.as_str()) {
                Some("+") => super::axis::Direction::Up,
                Some("-") => super::axis::Direction::Down,
                _ => return Err("truth at \"mm\" needs \"direction\": \"+\" or \"-\"".into()),
            };
            if !mm.is_finite() {
                return Err(format!("truth at {mm} mm: give a finite position"));
            }
            let e = ctx.plant.errors_at(mm, dir, now);
            Ok(serde_json::json!({"ok": true, "errors": e.to_user()}))
        }
        "rests" => {
            // Wall-clock times (the twin's own clock, never a service's stepped one) of each
            // rest, from the monotonic instants the plant keeps.
            let now = crate::util::clock::now();
            let wall_us = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_micros() as i64);
            let unix_us = |t: std::time::Instant| {
                wall_us - now.saturating_duration_since(t).as_micros() as i64
            };
            let rests: Vec<_> = ctx
                .plant
                .rests(now)
                .iter()
                .map(|r| {
                    serde_json::json!({
                        "from_unix_us": unix_us(r.from),
                        "to_unix_us": unix_us(r.to),
                        "mm": r.mm,
                        "direction": match r.direction {
                            super::axis::Direction::Up => "+",
                            super::axis::Direction::Down => "-",
                        },
                    })
                })
                .collect();
            Ok(serde_json::json!({"ok": true, "rests": rests}))
        }
        "block" => {
            let psd = num("psd").ok_or("block needs \"psd\" (1..3)")? as usize;
            if !(1..=3).contains(&psd) {
                return Err(format!("psd {psd}: use 1, 2 or 3"));
            }
            let on = v.get("on").and_then(|x| x.as_bool()).unwrap_or(true);
            ctx.plant.set_blocked(psd - 1, on);
            Ok(serde_json::json!({"ok": true}))
        }
        "io" => {
            if let Some(ms) = num("delay_ms") {
                let delay = crate::util::range::Range::new(0.0, 60_000.0, "ms")
                    .duration(ms, 1e-3)
                    .map_err(|p| format!("io \"delay_ms\": {p}"))?;
                ctx.io.set_delay(delay);
            }
            if let Some(code) = num("exception") {
                if !(0.0..=255.0).contains(&code) {
                    return Err(format!(
                        "exception {code}: use a code 1..255, or 0 for none"
                    ));
                }
                let code = code as u8;
                ctx.io
                    .set_exception((code != 0).then(|| crate::modbus::Exception::from_code(code)));
            }
            match v.get("action").and_then(|a| a.as_str()) {
                Some("stop") => ctx.io.stop().await,
                Some("restart") => ctx.io.restart().await.map_err(|e| e.to_string())?,
                Some(other) => return Err(format!("io action \"{other}\": use stop or restart")),
                None => {}
            }
            Ok(serde_json::json!({"ok": true}))
        }
        "drive" => {
            if let Some(code) = num("fault") {
                ctx.drive.inject_fault(code as u16, [0; 5]);
            }
            if let Some(on) = v.get("heartbeat").and_then(|x| x.as_bool()) {
                ctx.drive.set_heartbeat(on);
            }
            Ok(serde_json::json!({"ok": true}))
        }
        "program" => {
            let text = v
                .get("text")
                .and_then(|t| t.as_str())
                .ok_or("program needs \"text\"")?;
            let dialect = v
                .get("dialect")
                .and_then(|d| d.as_str())
                .and_then(Dialect::parse)
                .ok_or("program needs \"dialect\": iso or linuxcnc")?;
            let axis = v.get("axis").and_then(|a| a.as_str()).unwrap_or("X");
            start_program(&ctx.plant, &ctx.cnc, &ctx.cnc_task, text, dialect, axis)?;
            Ok(serde_json::json!({"ok": true}))
        }
        "cnc" => {
            if v.get("stop").and_then(|x| x.as_bool()) == Some(true) {
                let mut st = ctx.cnc.lock().unwrap_or_else(|p| p.into_inner());
                if st.running {
                    st.stop_requested = true;
                }
            }
            let st = ctx.cnc.lock().map(|s| s.clone()).unwrap_or_default();
            Ok(serde_json::json!({"ok": true, "cnc": st}))
        }
        "mount" => {
            let m = ctx.plant.mount();
            Ok(serde_json::json!({"ok": true, "mount": {
                "yaw_urad": m.yaw * 1e6, "pitch_urad": m.pitch * 1e6, "x_mm": m.x, "z_mm": m.z,
            }}))
        }
        "turn" => {
            let name = v
                .get("screw")
                .and_then(|x| x.as_str())
                .ok_or("turn needs \"screw\": yaw, pitch, x or z")?;
            let screw = crate::align::Screw::parse(name)
                .ok_or_else(|| format!("screw \"{name}\": use yaw, pitch, x or z"))?;
            let turns = num("turns").ok_or("turn needs \"turns\" (clockwise positive)")?;
            if !turns.is_finite() || turns.abs() > 20.0 {
                return Err(format!("{turns} turns: at most 20 either way"));
            }
            ctx.plant.turn_screw(screw, turns);
            Ok(serde_json::json!({"ok": true}))
        }
        "knock" => {
            let by = crate::align::Mount {
                yaw: num("yaw_urad").unwrap_or(0.0) * 1e-6,
                pitch: num("pitch_urad").unwrap_or(0.0) * 1e-6,
                x: num("x_mm").unwrap_or(0.0),
                z: num("z_mm").unwrap_or(0.0),
            };
            ctx.plant.knock(by);
            Ok(serde_json::json!({"ok": true}))
        }
        "plc" => {
            let plc = ctx.plc.lock().unwrap_or_else(|p| p.into_inner()).clone();
            plc_command(plc.as_deref().ok_or("the twin runs no PLC")?, v)
        }
        "target" => {
            let t = ctx.plant.target_readings(crate::util::clock::now());
            let view: Vec<serde_json::Value> = t
                .iter()
                .map(|s| match s {
                    Some(s) => serde_json::json!({"x": s.x, "y": s.y}),
                    None => serde_json::Value::Null,
                })
                .collect();
            Ok(serde_json::json!({"ok": true, "targets": view}))
        }
        "age" => {
            let wear = wear_from(v, ctx.plant.axis.wear())?;
            ctx.plant.axis.set_wear(wear);
            Ok(serde_json::json!({"ok": true, "wear": {
                "positioning_um": wear.positioning_um,
                "backlash_um": wear.backlash_um,
                "thermal_um": wear.thermal_um,
            }}))
        }
        "level" => {
            let sd = ctx.plant.spec.level_sd_rad;
            let noise = ctx.level_rng.lock().map(|mut r| r.gauss(sd)).unwrap_or(0.0);
            let roll = ctx.plant.truth(crate::util::clock::now()).errors.ey + noise;
            let arcsec = |rad: f64| rad / crate::units::RAD_PER_ARCSEC;
            Ok(serde_json::json!({"ok": true, "level": {
                "roll_arcsec": arcsec(roll),
                "sd_arcsec": arcsec(sd),
                "instrument": format!(
                    "the twin's electronic level (a simulated instrument: the axis' true roll plus {:.1} µrad of noise a reading)",
                    sd * 1e6
                ),
            }}))
        }
        other => Err(format!(
            "unknown cmd \"{other}\": use move, wait, truth, block, io, drive, program, cnc, mount, turn, knock, plc, target, age or level"
        )),
    }
}

/// The stream of the twin level's noise (`Rng::fork` of the plant's seed).
const LEVEL_FORK: u64 = 18;

/// Largest wear (µm) the `age` command takes for each term: years of use add a few µm to tens
/// of µm; more is a broken axis, not an aged one (and most likely a typing error).
pub const WEAR_MAX_UM: f64 = 100.0;

/// The `age` command's wear: `now` with the fields `v` gives replaced, each a number of µm in
/// 0..=[`WEAR_MAX_UM`]; an error names the field and what it takes.
pub fn wear_from(v: &serde_json::Value, now: Wear) -> Result<Wear, String> {
    let field = |k: &str, cur: f64| -> Result<f64, String> {
        let Some(x) = v.get(k) else { return Ok(cur) };
        let um = x
            .as_f64()
            .ok_or_else(|| format!("age \"{k}\" is {x}: give a number of µm"))?;
        if !um.is_finite() || !(0.0..=WEAR_MAX_UM).contains(&um) {
            return Err(format!(
                "age \"{k}\" is {um} µm: give 0 to {WEAR_MAX_UM:.0} µm"
            ));
        }
        Ok(um)
    };
    Ok(Wear {
        positioning_um: field("positioning_um", now.positioning_um)?,
        backlash_um: field("backlash_um", now.backlash_um)?,
        thermal_um: field("thermal_um", now.thermal_um)?,
    })
}

/// The control socket's `plc` command: inject the faults named in `v`, then report.
fn plc_command(
    plc: &super::plc::TwinPlc,
    v: &serde_json::Value,
) -> Result<serde_json::Value, String> {
    use super::plc::CommitResult;
    let num = |k: &str| v.get(k).and_then(|x| x.as_f64());
    let flag = |k: &str| v.get(k).and_then(|x| x.as_bool());
    if let Some(code) = num("reject_next") {
        plc.reject_next(code as u16);
    }
    if flag("ignore_next") == Some(true) {
        plc.ignore_next_commit();
    }
    if let Some(k) = num("corrupt_next") {
        plc.corrupt_next_commit(k as usize);
    }
    if let Some(n) = num("silent_after") {
        let down = crate::util::range::Range::new(0.0, 600_000.0, "ms")
            .duration(num("down_ms").unwrap_or(1000.0), 1e-3)
            .map_err(|p| format!("plc \"down_ms\": {p}"))?;
        plc.go_silent_after_writes(n as u64, down);
    }
    if let Some(ready) = flag("ready") {
        plc.set_ready(ready);
    }
    if let Some(frozen) = flag("freeze_heartbeat") {
        plc.freeze_heartbeat(frozen);
    }
    let requested = if flag("request_check") == Some(true) {
        Some(
            plc.request_check()
                .ok_or("the twin PLC's map has no [check] fields")?,
        )
    } else {
        None
    };
    let check = plc
        .check_fields()
        .map(|[request, answered, state, result, run]| {
            serde_json::json!({"request": request, "answered": answered, "state": state,
            "result": result, "run": run, "requested": requested})
        });
    let st = plc.status();
    let active: Vec<serde_json::Value> = plc
        .active_tables()
        .iter()
        .map(|a| match a {
            // The payload's CRC-32 as the protocol carries it (the store's `crc` column).
            Some((seq, t)) => serde_json::json!({
                "sequence": seq, "start_mm": t.start_mm, "interval_mm": t.interval_mm,
                "points": t.values_mm.len(),
                "crc": crate::plc::table::encode(t, plc.map(), *seq)
                    .map(|e| format!("0x{:08X}", e.crc))
                    .unwrap_or_else(|e| e.to_string()),
            }),
            None => serde_json::Value::Null,
        })
        .collect();
    let commits: Vec<serde_json::Value> = plc
        .commits()
        .iter()
        .map(|c| {
            let result = match &c.result {
                CommitResult::Accepted => "accepted".to_string(),
                CommitResult::Rejected(r) => format!("rejected: {r}"),
                CommitResult::Ignored => "ignored".to_string(),
            };
            serde_json::json!({"sequence": c.sequence, "result": result})
        })
        .collect();
    Ok(serde_json::json!({"ok": true, "plc": {
        "ready": st.ready, "active_sequence": st.active_sequence,
        "status_sequence": st.status_sequence, "error_code": st.error_code,
        "active": active, "commits": commits, "check": check,
    }}))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn age_replaces_the_fields_given_and_names_a_bad_one() {
        let now = Wear {
            positioning_um: 1.0,
            backlash_um: 2.0,
            thermal_um: 3.0,
        };
        let v = serde_json::json!({"cmd": "age", "positioning_um": 6, "thermal_um": 5.5});
        assert_eq!(
            wear_from(&v, now),
            Ok(Wear {
                positioning_um: 6.0,
                backlash_um: 2.0,
                thermal_um: 5.5,
            })
        );
        assert_eq!(wear_from(&serde_json::json!({"cmd": "age"}), now), Ok(now));
        assert_eq!(
            wear_from(&serde_json::json!({"backlash_um": -1}), now),
            Err("age \"backlash_um\" is -1 µm: give 0 to 100 µm".to_string())
        );
        assert_eq!(
            wear_from(&serde_json::json!({"thermal_um": 250.0}), now),
            Err("age \"thermal_um\" is 250 µm: give 0 to 100 µm".to_string())
        );
        assert_eq!(
            wear_from(&serde_json::json!({"positioning_um": "6"}), now),
            Err("age \"positioning_um\" is \"6\": give a number of µm".to_string())
        );
    }
}
