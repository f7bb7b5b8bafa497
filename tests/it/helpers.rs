//! Helpers shared by the integration tests.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};

/// The binary under test.
pub fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_axiscomp"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"));
    c
}

/// Run the binary with `args`, feeding `stdin`.
pub fn run(args: &[&str], stdin: &str) -> Output {
    let mut child = bin()
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn axiscomp");
    // The binary may refuse its arguments and exit before reading its input: a broken pipe
    // here is its answer, not a test failure.
    if let Err(e) = child
        .stdin
        .take()
        .expect("stdin")
        .write_all(stdin.as_bytes())
        && e.kind() != std::io::ErrorKind::BrokenPipe
    {
        panic!("write stdin: {e}");
    }
    child.wait_with_output().expect("wait axiscomp")
}

/// Standard output as text.
pub fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// Standard error as text.
pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A fresh directory under the target's temporary folder, removed on drop.
pub struct TempDir(PathBuf);

impl TempDir {
    pub fn new(name: &str) -> Self {
        static N: AtomicUsize = AtomicUsize::new(0);
        let p = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!(
            "{name}-{}-{}",
            std::process::id(),
            N.fetch_add(1, Ordering::Relaxed)
        ));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).expect("create temp dir");
        TempDir(p)
    }
    pub fn path(&self, file: &str) -> PathBuf {
        self.0.join(file)
    }
    pub fn write(&self, file: &str, text: &str) -> PathBuf {
        let p = self.path(file);
        std::fs::write(&p, text).expect("write temp file");
        p
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// The reference layout file's text.
pub fn reference_layout_text() -> String {
    std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/optics/reference.toml"),
    )
    .expect("read reference layout")
}

/// Generous bound on anything a CAN test waits for, so a broken test fails instead of
/// hanging; never a timing assertion (the VM runs about 14× slower than the host).
pub const CAN_WAIT: std::time::Duration = std::time::Duration::from_secs(60);

/// Await `fut`, failing the test with `what` if it takes longer than [`CAN_WAIT`].
pub async fn within<T>(what: &str, fut: impl std::future::Future<Output = T>) -> T {
    match tokio::time::timeout(CAN_WAIT, fut).await {
        Ok(v) => v,
        Err(_) => panic!("timed out after {CAN_WAIT:?}: {what}"),
    }
}

/// A UDP port number nobody on this host holds right now (the kernel's pick for an ephemeral
/// bind), so tests running in parallel — here or in another checkout — use distinct ports.
pub fn unused_udp_port() -> u16 {
    std::net::UdpSocket::bind("127.0.0.1:0")
        .and_then(|s| s.local_addr())
        .expect("bind an ephemeral UDP port")
        .port()
}

/// The CANopen master and the twin drive on one in-memory bus, with a plant whose follower
/// encoder the twin moves.
pub struct DriveRig {
    pub master: axiscomp::canopen::DriveHandle,
    pub twin: axiscomp::sim::TwinDriveHandle,
    pub plant: std::sync::Arc<axiscomp::sim::plant::Plant>,
    pub counts_per_mm: f64,
    /// When the twin last set the plant's follower encoder, and to what.
    encoder_set: std::sync::Arc<std::sync::Mutex<(std::time::Instant, f64)>>,
    tasks: Vec<tokio::task::JoinHandle<Result<(), axiscomp::can::CanError>>>,
}

impl DriveRig {
    /// Start both tasks (inside a tokio runtime).
    pub fn start(
        cfg: axiscomp::canopen::DriveConfig,
        twin: axiscomp::sim::TwinDriveConfig,
    ) -> DriveRig {
        use axiscomp::sim::plant::{Plant, PlantSpec};
        let bus = axiscomp::can::memory::MemoryBus::default();
        let plant = std::sync::Arc::new(
            Plant::new(
                &axiscomp::optics::Layout::reference(),
                &PlantSpec::default(),
                axiscomp::util::clock::now(),
            )
            .expect("plant"),
        );
        let p = plant.clone();
        let encoder_set = std::sync::Arc::new(std::sync::Mutex::new((
            axiscomp::util::clock::now(),
            f64::NAN,
        )));
        let set = encoder_set.clone();
        // The master listens before the twin boots, as on a real bus powered up together.
        let (master, mt) = axiscomp::canopen::spawn_drive(bus.port(), &cfg).expect("master");
        let (twin, tt) = axiscomp::sim::spawn_twin_drive(bus.port(), twin, move |mm| {
            p.set_follower_encoder(mm);
            if let Ok(mut s) = set.lock() {
                *s = (axiscomp::util::clock::now(), mm);
            }
        })
        .expect("twin drive");
        DriveRig {
            master,
            twin,
            plant,
            counts_per_mm: cfg.validate().expect("config").counts_per_mm(),
            encoder_set,
            tasks: vec![mt, tt],
        }
    }

    /// When the twin last set the plant's follower encoder, and to what.
    pub fn encoder_set(&self) -> (std::time::Instant, f64) {
        *self.encoder_set.lock().expect("encoder log")
    }
}

impl Drop for DriveRig {
    fn drop(&mut self) {
        for t in &self.tasks {
            t.abort();
        }
    }
}

/// Await `fut`, failing the test with `what` if it takes longer than `secs` (generous bounds
/// only: they catch hangs, they do not measure anything).
pub async fn within_s<T>(secs: u64, what: &str, fut: impl std::future::Future<Output = T>) -> T {
    match tokio::time::timeout(std::time::Duration::from_secs(secs), fut).await {
        Ok(v) => v,
        Err(_) => panic!("{what}: not done within {secs} s"),
    }
}

/// Wait for the first event matching `pick`.
pub async fn event<T>(
    rx: &mut tokio::sync::broadcast::Receiver<axiscomp::canopen::Event>,
    mut pick: impl FnMut(&axiscomp::canopen::Event) -> Option<T>,
) -> T {
    loop {
        match rx.recv().await {
            Ok(e) => {
                if let Some(v) = pick(&e) {
                    return v;
                }
            }
            Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => continue,
            Err(e) => panic!("event stream ended: {e}"),
        }
    }
}

// ---------- Modbus / acquisition helpers ----------

use axiscomp::modbus::{Link, LinkConfig};
use axiscomp::optics::Layout;
use axiscomp::sim::iomodule::IoModule;
use axiscomp::sim::plant::{Plant, PlantSpec};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// The twin's plant with the default spec and the reference layout.
pub fn plant() -> Arc<Plant> {
    Arc::new(
        Plant::new(
            &Layout::reference(),
            &PlantSpec::default(),
            axiscomp::util::clock::now(),
        )
        .expect("default plant"),
    )
}

/// The twin's I/O module serving `plant` through the generic map on a loopback port.
pub async fn twin(plant: Arc<Plant>) -> IoModule {
    IoModule::generic(plant)
        .await
        .expect("start the twin's I/O module")
}

/// Link settings with test-friendly timings (300 ms call timeout, backoff 50..400 ms).
pub fn link_config(addr: SocketAddr) -> LinkConfig {
    LinkConfig {
        timeout: Duration::from_millis(300),
        backoff_max: Duration::from_millis(400),
        ..LinkConfig::new(addr)
    }
}

/// A link with [`link_config`]'s timings.
pub fn link(addr: SocketAddr) -> Link {
    Link::spawn(link_config(addr))
}

/// Send one raw Modbus TCP request (`pdu` after the MBAP header) and return the reply's PDU;
/// checks the reply header echoes the transaction and unit ids.
pub async fn raw_request(stream: &mut TcpStream, tid: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
    let mut req = Vec::with_capacity(7 + pdu.len());
    req.extend_from_slice(&tid.to_be_bytes());
    req.extend_from_slice(&[0, 0]);
    req.extend_from_slice(&((pdu.len() + 1) as u16).to_be_bytes());
    req.push(unit);
    req.extend_from_slice(pdu);
    let io = async {
        stream.write_all(&req).await?;
        let mut hdr = [0u8; 7];
        stream.read_exact(&mut hdr).await?;
        let len = u16::from_be_bytes([hdr[4], hdr[5]]) as usize;
        let mut body = vec![0u8; len.saturating_sub(1)];
        stream.read_exact(&mut body).await?;
        Ok::<_, std::io::Error>((hdr, body))
    };
    let (hdr, body) = tokio::time::timeout(Duration::from_secs(5), io)
        .await
        .expect("reply within 5 s")
        .expect("reply read");
    assert_eq!(u16::from_be_bytes([hdr[0], hdr[1]]), tid, "transaction id");
    assert_eq!(hdr[6], unit, "unit id");
    body
}

/// A free loopback TCP port (bound and released).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("free port")
        .port()
}

// ---------- The service against the twin, in one process, over loopback ----------

/// `AXISCOMP_TEST_LOG=axiscomp::track=debug` shows the service's logs in a failing test.
pub fn init_test_log() {
    if let Ok(filter) = tracing_subscriber::EnvFilter::try_from_env("AXISCOMP_TEST_LOG") {
        let _ = tracing_subscriber::fmt()
            .with_env_filter(filter)
            .with_test_writer()
            .try_init();
    }
}

/// Options for a `ServiceRig`.
pub struct RigOptions {
    /// Extra TOML appended to the service configuration (e.g. a `[tracking]` section).
    pub service_toml: String,
    pub plant: PlantSpec,
    /// Give the twin a control socket and let the service send it part programs
    /// (`[cnc] mode = "twin"`), so runs execute on the twin's CNC.
    pub twin_cnc: bool,
    /// Start the twin's PLC (generic map) on the twin's plant and let the service push tables
    /// to it (`[plc] push = true`; then `service_toml` must not have a `[plc]` section).
    pub twin_plc: bool,
    /// The body of the `[io]` section instead of the twin's I/O module at 500 Hz (a test's
    /// own Modbus peer).
    pub io_toml: Option<String>,
    /// The `[follower]` section's body (e.g. another node id, for an absent drive).
    pub follower_toml: Option<String>,
    /// Wait in `ServiceRig::start` until the follower is homed and the stitch referenced.
    pub wait_ready: bool,
}

impl Default for RigOptions {
    fn default() -> Self {
        RigOptions {
            service_toml: String::new(),
            plant: PlantSpec {
                seed: 10,
                install: axiscomp::sim::InstallSpec {
                    offset_mm: 0.0,
                    tilt_deg: 0.0,
                    gain_error: 0.0,
                },
                ..PlantSpec::default()
            },
            twin_cnc: false,
            twin_plc: false,
            io_toml: None,
            follower_toml: None,
            wait_ready: true,
        }
    }
}

/// Start the twin for `opts` and write the service's configuration against it into `dir`:
/// the twin, the configuration file and the control socket's path.
pub async fn twin_and_config(
    opts: RigOptions,
    dir: &TempDir,
) -> (
    axiscomp::sim::twin::Twin,
    Option<axiscomp::sim::plc::TwinPlc>,
    PathBuf,
    PathBuf,
) {
    use axiscomp::sim::drive::TwinDriveConfig;
    use axiscomp::sim::twin::{Twin, TwinCan, TwinSpec};
    init_test_log();
    let (svc_port, twin_port) = (unused_udp_port(), unused_udp_port());
    let twin = Twin::start(
        &Layout::reference(),
        TwinSpec {
            plant: opts.plant,
            io_bind: "127.0.0.1:0".parse().expect("addr"),
            io_map: axiscomp::acquire::IoMap::generic().expect("generic map"),
            can: TwinCan::Cannelloni {
                local: format!("127.0.0.1:{twin_port}").parse().expect("addr"),
                remote: format!("127.0.0.1:{svc_port}").parse().expect("addr"),
            },
            drive: TwinDriveConfig {
                start_mm: 2.0,
                ..TwinDriveConfig::default()
            },
            control: opts.twin_cnc.then(|| "127.0.0.1:0".parse().expect("addr")),
        },
    )
    .await
    .expect("twin");
    let cnc = match twin.control_addr() {
        Some(a) => format!("[cnc]\nmode = \"twin\"\ntwin = \"{a}\"\n\n"),
        None => String::new(),
    };
    let plc = if opts.twin_plc {
        Some(
            axiscomp::sim::plc::TwinPlc::start(
                twin.plant.clone(),
                axiscomp::plc::CncMap::generic().expect("generic CNC map"),
                Default::default(),
            )
            .await
            .expect("the twin's PLC"),
        )
    } else {
        None
    };
    let plc_toml = match &plc {
        Some(p) => format!(
            "[plc]\npush = true\naddress = \"{}\"\ntimeout_ms = 300\npoll_ms = 10\n\n",
            p.local_addr()
        ),
        None => String::new(),
    };
    let socket = dir.path("control.sock");
    let io = opts
        .io_toml
        .unwrap_or_else(|| format!("address = \"{}\"\nrate_hz = 500.0\n", twin.io.local_addr()));
    let follower = opts
        .follower_toml
        .map(|f| format!("[follower]\n{f}\n"))
        .unwrap_or_default();
    let config = dir.write(
        "axiscomp.toml",
        &format!(
            "[service]\nsocket = \"{}\"\nstate_dir = \"{}\"\nsnapshot_hz = 20.0\n\n\
             [io]\n{io}\n\
             [can]\ntransport = \"cannelloni\"\nlocal = \"127.0.0.1:{svc_port}\"\nremote = \"127.0.0.1:{twin_port}\"\n\n{follower}{cnc}{plc_toml}{}",
            socket.display(),
            dir.path("state").display(),
            opts.service_toml
        ),
    );
    (twin, plc, config, socket)
}

/// The twin and the service on loopback: Modbus TCP on an ephemeral port, CANopen over a
/// cannelloni UDP pair, the control API on a Unix socket in a temporary directory.
static MACHINE: tokio::sync::RwLock<()> = tokio::sync::RwLock::const_new(());

/// A live service against the twin runs in real time (SYNC, frames, handovers): it takes the
/// machine to itself, so on a 2-core machine no other live rig and no CPU-heavy lab run
/// shares it. Light tests still run alongside.
pub async fn exclusive() -> tokio::sync::RwLockWriteGuard<'static, ()> {
    MACHINE.write().await
}

/// A CPU-heavy test on a simulated clock (not inside a runtime): many may run together, never
/// beside a live rig.
pub fn heavy() -> tokio::sync::RwLockReadGuard<'static, ()> {
    MACHINE.blocking_read()
}

/// A rig whose service drives the twin's hexapod (its platform under the twin's head) over PI
/// GCS on a free port, quick moves: `hexapod_toml` is added to the service's `[hexapod]`.
pub async fn hexapod_rig(
    mut opts: RigOptions,
    hexapod_toml: &str,
) -> (ServiceRig, axiscomp::sim::hexapod_servers::HexapodServers) {
    use axiscomp::sim::hexapod_servers::{TwinHexapodSpec, start};
    let port = free_port();
    opts.service_toml.push_str(&format!(
        "\n[hexapod]\ndriver = \"pi-gcs\"\naddress = \"127.0.0.1:{port}\"\n{hexapod_toml}"
    ));
    let rig = ServiceRig::start(opts).await;
    let servers = start(
        TwinHexapodSpec {
            gcs: Some(SocketAddr::from(([127, 0, 0, 1], port))),
            xps: None,
            workspace: axiscomp::hexapod::Workspace::symmetric([10.0, 10.0, 5.0, 7.0, 7.0, 7.0]),
            speed_mm_s: 50.0,
            speed_deg_s: 10.0,
            ..TwinHexapodSpec::default()
        },
        rig.twin.plant.hexapod.clone(),
    )
    .await
    .expect("twin hexapod");
    (rig, servers)
}

pub struct ServiceRig {
    pub twin: axiscomp::sim::twin::Twin,
    /// The twin's PLC (`RigOptions::twin_plc`).
    pub plc: Option<axiscomp::sim::plc::TwinPlc>,
    pub socket: std::path::PathBuf,
    /// The service's store (the file the service opened; WAL, so a test may open it too).
    pub store: std::path::PathBuf,
    trigger: Option<axiscomp::service::shutdown::Trigger>,
    service: Option<tokio::task::JoinHandle<Result<(), axiscomp::service::ServiceError>>>,
    _dir: TempDir,
    /// Dropped last: the machine is this rig's until it is gone.
    _exclusive: tokio::sync::RwLockWriteGuard<'static, ()>,
}

impl ServiceRig {
    /// Start the twin and the service, and wait until the follower is homed and the stitch
    /// referenced.
    pub async fn start(opts: RigOptions) -> ServiceRig {
        init_test_log();
        let exclusive = exclusive().await;
        let dir = TempDir::new("service");
        let wait_ready = opts.wait_ready;
        let (twin, plc, config, socket) = twin_and_config(opts, &dir).await;
        let settings = axiscomp::config::load(&axiscomp::config::Layers {
            etc: None,
            file: Some(config.clone()),
            env: vec![],
        })
        .expect("service config");
        let prepared = axiscomp::service::prepare(&settings).expect("prepare");
        let (trigger, shutdown) = axiscomp::service::shutdown::channel();
        let service = tokio::spawn(axiscomp::service::run(prepared, shutdown));
        let rig = ServiceRig {
            twin,
            plc,
            store: dir.path("state").join("axiscomp.db"),
            socket,
            trigger: Some(trigger),
            service: Some(service),
            _dir: dir,
            _exclusive: exclusive,
        };
        if wait_ready {
            rig.wait_for(
                60,
                "the follower homed, the stitch referenced, the spot at rest",
                |s| s.follower.homed && s.tracking.valid && s.tracking.at_rest && s.live.is_some(),
            )
            .await;
        }
        rig
    }

    /// A control client.
    pub async fn client(&self) -> axiscomp::service::control::Client {
        for _ in 0..100 {
            if let Ok(c) = axiscomp::service::control::Client::connect(&self.socket).await {
                return c;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        panic!("cannot connect to {}", self.socket.display());
    }

    /// The current snapshot.
    pub async fn snapshot(&self) -> axiscomp::service::api::snapshot::Snapshot {
        self.client().await.status().await.expect("status")
    }

    /// Send a request and return its result.
    pub async fn request(
        &self,
        r: axiscomp::service::api::Request,
    ) -> Result<serde_json::Value, axiscomp::service::control::ClientError> {
        self.client().await.request(&r).await
    }

    /// Poll snapshots (every 50 ms) until `pred` holds; fail after `secs` seconds.
    pub async fn wait_for(
        &self,
        secs: u64,
        what: &str,
        mut pred: impl FnMut(&axiscomp::service::api::snapshot::Snapshot) -> bool,
    ) -> axiscomp::service::api::snapshot::Snapshot {
        let end = axiscomp::util::clock::now() + Duration::from_secs(secs);
        let mut c = self.client().await;
        loop {
            let s = c.status().await.expect("status");
            if pred(&s) {
                return s;
            }
            if axiscomp::util::clock::now() > end {
                panic!("waited {secs} s for {what}; last snapshot:\n{s:#?}");
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    /// Stop the service and wait for it.
    pub async fn stop(mut self) {
        if let Some(t) = self.trigger.take() {
            t.trigger();
        }
        if let Some(s) = self.service.take() {
            let r = tokio::time::timeout(Duration::from_secs(10), s)
                .await
                .expect("service stops within 10 s");
            r.expect("service task").expect("service result");
        }
    }
}

impl Drop for ServiceRig {
    fn drop(&mut self) {
        if let Some(t) = self.trigger.take() {
            t.trigger();
        }
    }
}

// ---------- PLC helpers ----------

/// A CNC map from `plc-maps/cnc/`.
pub fn cnc_map(file: &str) -> axiscomp::plc::CncMap {
    axiscomp::plc::CncMap::load(
        &Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("plc-maps/cnc")
            .join(file),
    )
    .expect("shipped CNC map")
}

/// Every shipped CNC map's file name.
pub fn cnc_map_files() -> Vec<String> {
    let mut v: Vec<String> =
        std::fs::read_dir(Path::new(env!("CARGO_MANIFEST_DIR")).join("plc-maps/cnc"))
            .expect("plc-maps/cnc")
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".toml"))
            .collect();
    v.sort();
    v
}

/// The twin's PLC serving `map` for a fresh default plant, on a loopback port.
pub async fn twin_plc(map: axiscomp::plc::CncMap) -> (axiscomp::sim::plc::TwinPlc, Arc<Plant>) {
    let p = plant();
    let t = axiscomp::sim::plc::TwinPlc::start(p.clone(), map, Default::default())
        .await
        .expect("start the twin PLC");
    (t, p)
}

/// Publish timeouts for tests: short, but generous against a loaded machine.
pub fn plc_timeouts() -> axiscomp::plc::Timeouts {
    axiscomp::plc::Timeouts {
        ready: Duration::from_secs(5),
        heartbeat: Duration::from_secs(2),
        poll: Duration::from_millis(10),
        echo: Duration::from_secs(2),
    }
}

/// A positioning table for machine axis Y from `values_um` (e, µm), `interval_mm` apart from 0.
pub fn plc_table(values_um: &[f64], interval_mm: f64) -> axiscomp::plc::PlcTable {
    use axiscomp::comp::{MachineAxis, TableKind};
    axiscomp::plc::PlcTable {
        kind: TableKind::Positioning,
        axis: MachineAxis::Y,
        base_axis: MachineAxis::Y,
        direction: axiscomp::plc::TableDirection::Both,
        start_mm: 0.0,
        interval_mm,
        values_mm: values_um.iter().map(|v| v * 1e-3).collect(),
        down_mm: None,
    }
}

/// The short plan the console fixture, the key-driven test and the crash test run: X 0–8 mm,
/// 5 targets, 2 runs, dwell 1.5 s, 3000 mm/min.
pub fn short_plan() -> axiscomp::run::PlanSpec {
    axiscomp::run::PlanSpec {
        axis: "X".into(),
        start_mm: 0.0,
        end_mm: 8.0,
        targets: 5,
        runs: 2,
        overrun_mm: 1.0,
        dwell_s: 1.5,
        feed_mm_min: 3000.0,
        lead_mm: 0.0,
        reference_mm: None,
    }
}

/// One round of the beam alignment over `span` (mm) through the service's control API at
/// `socket`, as a technician does before a run: the carriage to each end (the follower brought
/// to it where PSD2 lost the spot on the way), a station read at rest, the advice stored for
/// axis X; back at 0 mm, the zero taken again. The twin's head in these rigs is mounted square,
/// so the first round passes.
pub async fn align_service(socket: &Path, twin: &axiscomp::sim::twin::Twin, span: (f64, f64)) {
    use axiscomp::service::api::{FollowerAction, Request};
    use axiscomp::service::control::Client;
    use std::time::Duration;
    let mut c = Client::connect(socket).await.expect("the control socket");
    // Wait for a spot on every PSD with the carriage at rest; the follower brought to the
    // carriage when PSD2 has none after a while.
    async fn at_rest(c: &mut Client, twin: &axiscomp::sim::twin::Twin, at: f64) {
        let mut moved = false;
        let start = axiscomp::util::clock::now();
        loop {
            let s = c.request(&Request::Status).await.expect("status");
            let spots = s["psd"]["spots_um"]
                .as_array()
                .is_some_and(|a| a.len() == 3 && a.iter().all(|v| !v.is_null()));
            if spots && s["tracking"]["at_rest"] == true {
                tokio::time::sleep(Duration::from_millis(600)).await;
                return;
            }
            if !moved && axiscomp::util::clock::since(start) > Duration::from_secs(4) {
                moved = true;
                c.request(&Request::Follower {
                    action: FollowerAction::Move,
                    mm: Some(at),
                })
                .await
                .expect("follower move");
            }
            assert!(
                axiscomp::util::clock::since(start) < Duration::from_secs(40),
                "no spot on every PSD at {at} mm: {s}; truth {:?}",
                twin.plant.truth(axiscomp::util::clock::now())
            );
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }
    c.request(&Request::AlignClear).await.expect("align clear");
    for at in [span.0, span.1] {
        twin.move_and_wait(at).await;
        at_rest(&mut c, twin, at).await;
        c.request(&Request::AlignRead { at_mm: Some(at) })
            .await
            .expect("align read");
    }
    let advice = c
        .request(&Request::AlignAdvice {
            from_mm: span.0,
            to_mm: span.1,
            axis: Some("X".into()),
        })
        .await
        .expect("align advice");
    assert_eq!(
        advice["passed"], true,
        "a square-mounted head failed: {advice}"
    );
    // The stored alignment of the axis is this advice, with its id, span and time.
    let stored = c
        .request(&Request::AlignStored {
            axis: Some("X".into()),
        })
        .await
        .expect("align stored");
    assert_eq!(
        (
            &stored["alignment_id"],
            &stored["passed"],
            &stored["check"],
            stored["from_mm"].as_f64(),
            stored["to_mm"].as_f64()
        ),
        (
            &advice["alignment_id"],
            &advice["passed"],
            &advice["check"],
            Some(span.0),
            Some(span.1)
        ),
        "{stored}"
    );
    assert!(
        stored["unix_us"].as_i64().is_some_and(|t| t > 0),
        "{stored}"
    );
    let other = c
        .request(&Request::AlignStored {
            axis: Some("Q".into()),
        })
        .await
        .expect("align stored for an axis never aligned");
    assert!(other.is_null(), "{other}");
    twin.move_and_wait(0.0).await;
    at_rest(&mut c, twin, 0.0).await;
    c.request(&Request::Zero).await.expect("zero");
}

/// Record, as the service does when a run starts, that the PLC applied no table while run
/// `run` ran (a run stored by a test, not measured by the service, has no such record, and
/// tables from it are refused).
pub fn record_no_tables(store: &mut axiscomp::store::Store, run: axiscomp::store::RunId) {
    store
        .record_run_tables(
            run,
            &axiscomp::store::RunTables {
                unix_us: axiscomp::store::now_us(),
                known: true,
                source: "no PLC configured (a test's run)".into(),
                tables: Vec::new(),
            },
        )
        .expect("record the tables active during the run");
}

/// A finished run of axis X stored as the service would: 5 targets 100 mm apart (0 to 400 mm),
/// 2 bidirectional runs, each capture's positioning deviation `dy_um(target, run, direction)`
/// with 0.1 µm (and 0.1″) stated as its u; the PLC's active tables `tables` recorded at its
/// start (none when `None`).
pub fn store_synthetic_run(
    store: &mut axiscomp::store::Store,
    tables: Option<&axiscomp::store::RunTables>,
    mut dy_um: impl FnMut(u32, u32, axiscomp::run::Direction) -> f64,
) -> axiscomp::store::RunId {
    use axiscomp::Errors6;
    use axiscomp::evaluate::axis::synthetic_capture;
    use axiscomp::run::Direction;
    use axiscomp::store::{NewRun, RunState};
    let run = store
        .create_run(&NewRun {
            axis: "X".into(),
            plan: serde_json::json!({}),
            config: serde_json::json!({}),
            calibration: None,
            notes: String::new(),
        })
        .expect("a run");
    store
        .set_run_state(run, RunState::Running)
        .expect("running");
    match tables {
        Some(t) => store.record_run_tables(run, t).expect("its tables"),
        None => record_no_tables(store, run),
    }
    for t in 0..5u32 {
        for r in 1..=2u32 {
            for d in [Direction::Up, Direction::Down] {
                let c = synthetic_capture(
                    t,
                    100.0 * f64::from(t),
                    r,
                    d,
                    Errors6::from_user([0.0, dy_um(t, r, d), 0.0, 0.0, 0.0, 0.0]),
                    Errors6::from_user([0.1; 6]),
                );
                store.insert_capture(run, &c).expect("a capture");
            }
        }
    }
    store
        .set_run_state(run, RunState::Finished)
        .expect("finished");
    run
}
