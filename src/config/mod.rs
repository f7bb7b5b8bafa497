//! Configuration in two stages (DESIGN §8, ripgrep's flags): `RawConfig` is what the layers say —
//! built-in defaults, `/etc/axiscomp/axiscomp.toml`, `--config FILE`, then
//! `AXISCOMP__SECTION__KEY` environment variables, merged by the `config` crate — and `Settings`
//! is the validated result. Every error names the key and where its value came from (the file,
//! "the environment" or the built-in defaults) and says what to do.
//!
//! Each file is also parsed on its own first, so an unknown key or a wrong type is reported
//! with that file's name and line.

use serde::{Deserialize, Serialize};
use std::net::{Ipv4Addr, SocketAddr};
use std::path::{Path, PathBuf};
use std::time::Duration;
use thiserror::Error;

use crate::acquire::AcquireConfig;
use crate::canopen::{DriveConfig, HomingConfig, ProfileConfig, Scaling, TravelLimits};
use crate::modbus::LinkConfig;
use crate::run::{CaptureSettings, Dialect};
use crate::track::{Strategy, TrackSettings};
use crate::util::range::{self, POSITION_MM, Range};

pub mod kind;
pub mod reference;

/// The built-in defaults (the lowest layer).
pub const DEFAULTS: &str = include_str!("defaults.toml");
/// The system-wide file, read when it exists.
pub const ETC_PATH: &str = "/etc/axiscomp/axiscomp.toml";
/// Environment variable prefix; `AXISCOMP__IO__RATE_HZ=250` sets `io.rate_hz`.
pub const ENV_PREFIX: &str = "AXISCOMP";
/// Snapshots a second for subscribers (`service.snapshot_hz`, a `subscribe` request's `hz`).
pub const SNAPSHOT_HZ: Range = Range::new(0.1, 100.0, "Hz");

/// A configuration error: where, which key, what is wrong and what to do.
#[derive(Debug, Error, Clone, PartialEq)]
#[error("config {origin}: {}{problem}", if key.is_empty() { String::new() } else { format!("{key}: ") })]
pub struct ConfigError {
    /// The file (with line when known), "the environment" or "built-in defaults".
    pub origin: String,
    /// The key, dotted (`io.rate_hz`), or empty when the whole file is wrong.
    pub key: String,
    pub problem: String,
}

/// `[service]`
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawService {
    pub socket: String,
    pub state_dir: String,
    pub operator_group: String,
    pub viewer_group: String,
    pub snapshot_hz: f64,
    pub watchdog: bool,
    pub max_connections: u64,
}

/// `[head]`
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawHead {
    pub layout: String,
    pub calibration: String,
    pub noise_um: f64,
    pub live_window_ms: u64,
    pub zero_window_ms: u64,
    /// The head's serial number (for reports).
    pub serial: String,
}

/// `[io]`
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawIo {
    pub address: String,
    pub unit: i64,
    pub map: String,
    pub rate_hz: f64,
    pub timeout_ms: u64,
    pub reconnect_min_ms: u64,
    pub reconnect_max_ms: u64,
    /// Block reads in flight at rate_hz = 0 (1..=16).
    pub pipeline: i64,
}

/// `[can]`
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawCan {
    pub transport: String,
    pub interface: String,
    pub local: String,
    pub remote: String,
    pub group: String,
    pub port: i64,
    pub iface: String,
}

/// `[follower]`
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawFollower {
    pub node_id: i64,
    pub heartbeat_ms: u64,
    pub heartbeat_timeout_ms: u64,
    pub sdo_timeout_ms: u64,
    pub sync_ms: u64,
    pub quiet_sync_ms: u64,
    pub feed_mm: f64,
    pub shaft_revolutions: u32,
    pub encoder_increments: u32,
    pub motor_revolutions: u32,
    pub gear_ratio: f64,
    pub homing_method: i64,
    pub homing_switch_speed_mm_s: f64,
    pub homing_zero_speed_mm_s: f64,
    pub homing_accel_mm_s2: f64,
    pub homing_offset_mm: f64,
    pub homing_timeout_ms: u64,
    pub velocity_mm_s: f64,
    pub accel_mm_s2: f64,
    pub decel_mm_s2: f64,
    pub quick_stop_decel_mm_s2: f64,
    pub position_window_um: f64,
    pub following_error_window_mm: f64,
    pub min_mm: f64,
    pub max_mm: f64,
    pub home_on_start: bool,
    pub level: String,
    pub level_sd_arcsec: f64,
}

/// `[tracking]`
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawTracking {
    pub strategy: String,
    pub handover_mm: f64,
    pub edge_mm: f64,
    pub anticipate_ms: u64,
    pub rest_tolerance_um: f64,
    pub rest_ms: u64,
    pub average_frames: u64,
    pub settle_ms: u64,
    pub follow_band_mm: f64,
    pub follow_interval_ms: u64,
    pub lead_ms: u64,
    pub lost_after_ms: u64,
    pub encoder_sd_um: f64,
    pub encoder_sd_um_per_m: f64,
    pub mapped_sd_um: f64,
    pub mapped_vertical_sd_um: f64,
    pub vertical_sd_um: f64,
    pub vertical_sd_um_per_m: f64,
    pub move_timeout_ms: u64,
    pub approach_um: f64,
}

/// `[cnc]`
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawCnc {
    pub mode: String,
    pub twin: String,
    pub dialect: String,
}

/// `[capture]`
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawCapture {
    pub rest_tolerance_um: f64,
    pub settle_ms: u64,
    pub target_tolerance_mm: f64,
    pub frames: u64,
    pub timeout_s: u64,
    pub repeatability_um: f64,
    pub repeatability_arcsec: f64,
    pub judge: bool,
}

/// `[align]`
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawAlign {
    pub margin_mm: f64,
    pub max_angle_urad: f64,
    pub check_before_run: bool,
    pub valid_for_h: f64,
}

/// `[plc]`
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawPlc {
    pub map: String,
    pub push: bool,
    pub address: String,
    pub unit: i64,
    pub timeout_ms: u64,
    pub reconnect_min_ms: u64,
    pub reconnect_max_ms: u64,
    pub ready_timeout_ms: u64,
    pub heartbeat_timeout_ms: u64,
    pub poll_ms: u64,
    pub echo_timeout_ms: u64,
    pub pull: bool,
    pub pull_bind: String,
    pub pull_allow: Vec<String>,
    pub pull_writers: Vec<String>,
    pub pull_max_connections: u64,
    pub pull_idle_timeout_s: u64,
    pub positioning: String,
    pub straightness: bool,
    pub step_mm: f64,
}

/// What the layers say (first stage).
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RawConfig {
    pub service: RawService,
    pub head: RawHead,
    pub io: RawIo,
    pub can: RawCan,
    pub follower: RawFollower,
    pub tracking: RawTracking,
    pub cnc: RawCnc,
    pub capture: RawCapture,
    pub align: RawAlign,
    pub plc: RawPlc,
    pub hexapod: crate::hexapod::config::RawHexapod,
    /// `[comp.<controller>]`: the controllers' settings for `axiscomp export`.
    pub comp: crate::comp::settings::RawComp,
    /// `[machine]` and `[acceptance]`: the acceptance report's machine and tolerances.
    pub machine: crate::report::settings::RawMachine,
    pub acceptance: crate::report::settings::RawAcceptance,
}

/// Where a file, map or layout comes from: a path, or the copy built into the binary.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Resource {
    Builtin(String),
    File(PathBuf),
}

/// `[service]`, validated.
#[derive(Clone, Debug, PartialEq)]
pub struct ServiceSettings {
    pub socket: PathBuf,
    pub state_dir: PathBuf,
    pub operator_group: String,
    pub viewer_group: String,
    pub snapshot_period: Duration,
    pub watchdog: bool,
    /// Control connections open at once; more are refused (with an error line) and logged.
    pub max_connections: usize,
}

/// `[head]`, validated.
#[derive(Clone, Debug, PartialEq)]
pub struct HeadSettings {
    pub layout: Resource,
    pub calibration: Option<PathBuf>,
    pub noise_mm: f64,
    pub live_window: Duration,
    /// A zero reference averages this long (every frame of it, not the live window).
    pub zero_window: Duration,
    /// The head's serial number; empty when not configured.
    pub serial: String,
}

/// `[io]`, validated.
#[derive(Clone, Debug, PartialEq)]
pub struct IoSettings {
    /// The Modbus link to the module.
    pub link: LinkConfig,
    /// The unit id overriding the map's; 0 keeps the map's.
    pub unit: u8,
    pub map: Resource,
    /// Frames per second (0: as fast as the module answers) and buffering.
    pub acquire: AcquireConfig,
}

/// `[can]`, validated: which transport.
#[derive(Clone, Debug, PartialEq)]
pub enum CanSettings {
    SocketCan {
        interface: String,
    },
    Cannelloni {
        local: SocketAddr,
        remote: SocketAddr,
    },
    PyCan {
        group: Ipv4Addr,
        port: u16,
        iface: Ipv4Addr,
    },
}

impl std::fmt::Display for CanSettings {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            CanSettings::SocketCan { interface } => write!(f, "SocketCAN on {interface}"),
            CanSettings::Cannelloni { local, remote } => {
                write!(f, "cannelloni over UDP from {local} to {remote}")
            }
            CanSettings::PyCan { group, port, iface } => write!(
                f,
                "python-can's UDP multicast, group {group} port {port} on {iface}"
            ),
        }
    }
}

/// `[follower]`, validated.
#[derive(Clone, Debug, PartialEq)]
pub struct FollowerSettings {
    /// The CiA 402 drive, checked by `DriveConfig::validate`.
    pub drive: DriveConfig,
    pub home_on_start: bool,
    /// Where the level read at the follower's level stations comes from.
    pub level: LevelSource,
    /// One level reading's stated standard deviation (rad).
    pub level_sd_rad: f64,
}

/// Where the level read beside the head's roll at the follower's level stations comes from
/// (`service::follower_level`).
#[derive(Clone, Debug, PartialEq)]
pub enum LevelSource {
    /// The operator reads the level and types each reading (console or API).
    Manual,
    /// The digital twin's level, asked on its control socket.
    Twin(SocketAddr),
}

/// How a run's part program reaches the CNC.
#[derive(Clone, Debug, PartialEq)]
pub enum CncMode {
    /// Written to the state directory for the operator.
    Manual,
    /// Sent to the digital twin's control socket.
    Twin(SocketAddr),
}

/// `[cnc]`, validated.
#[derive(Clone, Debug, PartialEq)]
pub struct CncSettings {
    pub mode: CncMode,
    pub dialect: Dialect,
}

/// `[plc]` push: the PLC's Modbus TCP server the service writes tables into (and reads back
/// for `table status`).
#[derive(Clone, Debug, PartialEq)]
pub struct PlcPush {
    pub link: LinkConfig,
    /// The unit id overriding the map's; 0 keeps the map's.
    pub unit: u8,
}

impl PlcPush {
    /// The unit id to address: this one, or the map's `map_unit` when it is 0.
    pub fn unit_or(&self, map_unit: u8) -> u8 {
        if self.unit != 0 { self.unit } else { map_unit }
    }
}

/// Which compensation tables `table generate` builds from a run.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TableBuild {
    /// Positioning: one profile with backlash (published as two profiles) or one per
    /// direction.
    pub positioning: crate::comp::PositioningMode,
    /// Also the two straightness (cross-axis) tables.
    pub straightness: bool,
    /// Grid spacing of the published tables (mm); `None`: the measured targets' mean spacing.
    pub step_mm: Option<f64>,
}

/// `[plc]`, validated (DESIGN §6): the CNC map, push and/or pull, publish timeouts.
#[derive(Clone, Debug, PartialEq)]
pub struct PlcSettings {
    /// The CNC map (`plc-maps/cnc/`), or the built-in generic one.
    pub map: Resource,
    /// Push tables into the PLC (`None`: push off).
    pub push: Option<PlcPush>,
    /// Serve the last published table for the PLC to pull (`None`: no pull server).
    pub pull: Option<crate::plc::PullConfig>,
    /// Publish handshake timeouts (push), and the acknowledgement wait (pull: `echo`).
    pub timeouts: crate::plc::Timeouts,
    pub tables: TableBuild,
}

/// `[align]`, validated.
#[derive(Clone, Debug, PartialEq)]
pub struct AlignConfig {
    /// The check's margin and beam-angle limit (the mount's geometry is the reference one).
    pub settings: crate::align::AlignSettings,
    /// Refuse `run_start` unless a passed alignment of the axis covers the plan's travel.
    pub check_before_run: bool,
    /// How long a stored alignment stands for the pre-run check.
    pub valid_for: Duration,
}

/// The validated configuration.
#[derive(Clone, Debug, PartialEq)]
pub struct Settings {
    pub service: ServiceSettings,
    pub head: HeadSettings,
    pub io: IoSettings,
    pub can: CanSettings,
    pub follower: FollowerSettings,
    pub tracking: TrackSettings,
    pub cnc: CncSettings,
    pub capture: CaptureSettings,
    /// `[align]`: the beam alignment's check and the pre-run check.
    pub align: AlignConfig,
    pub plc: PlcSettings,
    /// `[hexapod]`: the calibration hexapod (`hexapod::config`).
    pub hexapod: crate::hexapod::config::HexapodSettings,
    pub comp: crate::comp::settings::CompSettings,
    /// `[machine]`: the machine under test (for acceptance reports).
    pub machine: crate::report::settings::MachineSettings,
    /// `[acceptance]`: the tolerances acceptance reports judge against.
    pub acceptance: crate::report::settings::AcceptanceSettings,
    /// The files that were read, in layer order (for `check` and the logs).
    pub sources: Vec<String>,
}

/// Which layers to read.
#[derive(Clone, Debug, Default)]
pub struct Layers {
    /// The system-wide file; read when present (`None`: skip it).
    pub etc: Option<PathBuf>,
    /// `--config FILE`: must exist.
    pub file: Option<PathBuf>,
    /// Environment variables (name, value); only `AXISCOMP__…` ones are used.
    pub env: Vec<(String, String)>,
}

impl Layers {
    /// The usual layers: `/etc/axiscomp/axiscomp.toml`, `--config`, the process environment.
    pub fn standard(file: Option<&Path>) -> Self {
        Layers {
            etc: Some(PathBuf::from(ETC_PATH)),
            file: file.map(Path::to_path_buf),
            env: std::env::vars()
                .filter(|(k, _)| k.starts_with(&format!("{ENV_PREFIX}__")))
                .collect(),
        }
    }
}

/// Check one file alone: TOML syntax, known keys, value types.
fn check_file(path: &Path, text: &str) -> Result<(), ConfigError> {
    toml::from_str::<RawConfig>(text)
        .map(|_| ())
        .map_err(|e| ConfigError {
            origin: path.display().to_string(),
            key: String::new(),
            problem: format!(
                "{}; see configs/axiscomp.toml for every key",
                crate::util::toml_error_line(text, &e)
            ),
        })
}

/// Read the layers, merge and validate.
pub fn load(layers: &Layers) -> Result<Settings, ConfigError> {
    use config::{Config, Environment, File, FileFormat};
    let mut builder = Config::builder().add_source(File::from_str(DEFAULTS, FileFormat::Toml));
    let mut sources = vec!["built-in defaults".to_string()];
    let read = |p: &Path| -> Result<String, ConfigError> {
        std::fs::read_to_string(p).map_err(|e| ConfigError {
            origin: p.display().to_string(),
            key: String::new(),
            problem: format!("cannot read it: {e}"),
        })
    };
    if let Some(etc) = &layers.etc
        && etc.exists()
    {
        let text = read(etc)?;
        check_file(etc, &text)?;
        builder = builder.add_source(File::from(etc.as_path()).format(FileFormat::Toml));
        sources.push(etc.display().to_string());
    }
    if let Some(f) = &layers.file {
        let text = read(f)?;
        check_file(f, &text)?;
        builder = builder.add_source(File::from(f.as_path()).format(FileFormat::Toml));
        sources.push(f.display().to_string());
    }
    let env: std::collections::HashMap<String, String> = layers
        .env
        .iter()
        .filter(|(k, _)| k.starts_with(&format!("{ENV_PREFIX}__")))
        .cloned()
        .collect();
    if !env.is_empty() {
        sources.push("the environment".into());
    }
    builder = builder.add_source(
        Environment::with_prefix(ENV_PREFIX)
            .prefix_separator("__")
            .separator("__")
            .try_parsing(true)
            .source(Some(env)),
    );
    let cfg = builder.build().map_err(|e| ConfigError {
        origin: "configuration".into(),
        key: String::new(),
        problem: e.to_string(),
    })?;
    let raw: RawConfig = cfg.clone().try_deserialize().map_err(|e| ConfigError {
        origin: if sources.len() > 1 {
            sources[1..].join(" + ")
        } else {
            "built-in defaults".into()
        },
        key: String::new(),
        problem: format!("{e}; environment variables are AXISCOMP__SECTION__KEY"),
    })?;
    // `get_table` keeps each value's origin (deserialising a single value drops it).
    let origin = |key: &str| -> String {
        let (section, name) = key.rsplit_once('.').unwrap_or(("", key));
        cfg.get_table(section)
            .ok()
            .and_then(|t| t.get(name).and_then(|v| v.origin().map(str::to_string)))
            .unwrap_or_else(|| DEFAULTS_ORIGIN.into())
    };
    validate(&raw, &origin, sources)
}

/// The origin of a key no layer set.
const DEFAULTS_ORIGIN: &str = "built-in defaults";

/// The other `[follower]` key of a relation checked by `DriveConfig::validate`.
fn follower_related(key: &str) -> Option<&'static str> {
    match key {
        "follower.heartbeat_timeout_ms" => Some("follower.heartbeat_ms"),
        "follower.heartbeat_ms" => Some("follower.heartbeat_timeout_ms"),
        "follower.quiet_sync_ms" => Some("follower.sync_ms"),
        "follower.min_mm" => Some("follower.max_mm"),
        "follower.max_mm" => Some("follower.min_mm"),
        _ => None,
    }
}

/// The `[follower]` key behind an error of `DriveConfig::validate`.
fn follower_key(e: &crate::canopen::ConfigError) -> String {
    let inner = match e {
        crate::canopen::ConfigError::Invalid { key, .. } => *key,
        crate::canopen::ConfigError::NodeId(_) => "node_id",
    };
    let name = match inner {
        "heartbeat_period" => "heartbeat_ms".to_string(),
        "heartbeat_timeout" => "heartbeat_timeout_ms".to_string(),
        "sdo_timeout" => "sdo_timeout_ms".to_string(),
        "sync_period" => "sync_ms".to_string(),
        "quiet_sync_period" => "quiet_sync_ms".to_string(),
        "homing.timeout" => "homing_timeout_ms".to_string(),
        "profile.position_window_mm" => "position_window_um".to_string(),
        "limits" | "limits.min_mm" => "min_mm".to_string(),
        "limits.max_mm" => "max_mm".to_string(),
        k => {
            if let Some(rest) = k.strip_prefix("scaling.") {
                rest.to_string()
            } else if let Some(rest) = k.strip_prefix("homing.") {
                format!("homing_{rest}")
            } else if let Some(rest) = k.strip_prefix("profile.") {
                rest.to_string()
            } else {
                k.to_string()
            }
        }
    };
    format!("follower.{name}")
}

struct V<'a> {
    origin: &'a dyn Fn(&str) -> String,
    /// The section the keys given are in (`tracking`: `rest_ms` is `tracking.rest_ms`);
    /// empty: keys are given whole.
    section: &'static str,
}

impl V<'_> {
    fn err(&self, key: &str, problem: impl Into<String>) -> ConfigError {
        let key = match self.section {
            "" => key.to_string(),
            section => format!("{section}.{key}"),
        };
        ConfigError {
            origin: (self.origin)(&key),
            key,
            problem: problem.into(),
        }
    }

    /// The same checks with keys given within `section`.
    fn section(&self, section: &'static str) -> V<'_> {
        V {
            origin: self.origin,
            section,
        }
    }

    /// An error of `key` against `other` (a relation between two keys): it names the file
    /// that set one of them, so when `key` is at its built-in default and `other` was set
    /// in a file, the error is that file's, at `other`.
    fn err_with(&self, key: &str, other: &str, problem: impl Into<String>) -> ConfigError {
        let problem = problem.into();
        let (mine, theirs) = ((self.origin)(key), (self.origin)(other));
        if mine == DEFAULTS_ORIGIN && theirs != DEFAULTS_ORIGIN {
            ConfigError {
                origin: theirs,
                key: other.into(),
                problem: format!("{problem} (with {key} at its built-in default)"),
            }
        } else {
            ConfigError {
                origin: mine,
                key: key.into(),
                problem,
            }
        }
    }

    /// A range check's result (`util::range`), its problem named with `key`.
    fn checked<T>(&self, key: &str, r: Result<T, String>) -> Result<T, ConfigError> {
        r.map_err(|p| self.err(key, p))
    }

    /// `v` within `r`.
    fn range(&self, key: &str, v: f64, r: Range) -> Result<f64, ConfigError> {
        self.checked(key, r.check(v))
    }

    fn ms(&self, key: &str, v: u64, min: u64, max: u64) -> Result<Duration, ConfigError> {
        if v < min {
            return Err(self.err(key, format!("{v} ms is too short: give at least {min} ms")));
        }
        self.checked(
            key,
            range::int(v, min, max, "ms").map(Duration::from_millis),
        )
    }

    fn addr(&self, key: &str, s: &str) -> Result<SocketAddr, ConfigError> {
        s.parse().map_err(|_| {
            self.err(
                key,
                format!("\"{s}\" is not an address: write IP:port, e.g. \"192.168.1.20:502\""),
            )
        })
    }

    fn resource(&self, key: &str, s: &str, builtins: &[&str]) -> Result<Resource, ConfigError> {
        if let Some(name) = s
            .strip_prefix("builtin:")
            .or((s == "builtin").then_some(""))
        {
            let name = if name.is_empty() { builtins[0] } else { name };
            if builtins.contains(&name) {
                return Ok(Resource::Builtin(name.to_string()));
            }
            return Err(self.err(
                key,
                format!(
                    "no built-in \"{name}\": the built-ins are {}",
                    builtins.join(", ")
                ),
            ));
        }
        if s.is_empty() {
            return Err(self.err(key, "empty: give a file path or \"builtin\""));
        }
        Ok(Resource::File(PathBuf::from(s)))
    }
}

fn validate(
    raw: &RawConfig,
    origin: &dyn Fn(&str) -> String,
    sources: Vec<String>,
) -> Result<Settings, ConfigError> {
    let v = V {
        origin,
        section: "",
    };
    let s = &raw.service;
    if s.socket.is_empty() {
        return Err(v.err("service.socket", "empty: give the control socket's path"));
    }
    let service = ServiceSettings {
        socket: PathBuf::from(&s.socket),
        state_dir: PathBuf::from(&s.state_dir),
        operator_group: s.operator_group.clone(),
        viewer_group: s.viewer_group.clone(),
        snapshot_period: v.checked("service.snapshot_hz", SNAPSHOT_HZ.period(s.snapshot_hz))?,
        watchdog: s.watchdog,
        max_connections: match s.max_connections {
            1..=10_000 => s.max_connections as usize,
            n => {
                return Err(v.err(
                    "service.max_connections",
                    format!("{n} is out of range: use 1 to 10000 (default 64)"),
                ));
            }
        },
    };
    let h = &raw.head;
    let head = HeadSettings {
        layout: v.resource("head.layout", &h.layout, &["reference"])?,
        calibration: (!h.calibration.is_empty()).then(|| PathBuf::from(&h.calibration)),
        noise_mm: v.range("head.noise_um", h.noise_um, Range::new(0.001, 1000.0, "µm"))? * 1e-3,
        live_window: v.ms("head.live_window_ms", h.live_window_ms, 10, 60_000)?,
        zero_window: v.ms("head.zero_window_ms", h.zero_window_ms, 10, 600_000)?,
        serial: h.serial.trim().to_string(),
    };
    let i = &raw.io;
    let unit = u8::try_from(i.unit).map_err(|_| {
        v.err(
            "io.unit",
            format!("{} is not a Modbus unit id (0 to 255)", i.unit),
        )
    })?;
    let rate = v.range(
        "io.rate_hz",
        i.rate_hz,
        Range::new(1.0, 10_000.0, "Hz").or_zero("as fast as the module answers"),
    )?;
    let (rmin, rmax) = (
        v.ms("io.reconnect_min_ms", i.reconnect_min_ms, 1, 600_000)?,
        v.ms("io.reconnect_max_ms", i.reconnect_max_ms, 1, 600_000)?,
    );
    if rmax < rmin {
        return Err(v.err(
            "io.reconnect_max_ms",
            format!(
                "{} ms is below io.reconnect_min_ms ({} ms)",
                i.reconnect_max_ms, i.reconnect_min_ms
            ),
        ));
    }
    let address = v.addr("io.address", &i.address)?;
    let mut link = LinkConfig::new(address);
    link.timeout = v.ms("io.timeout_ms", i.timeout_ms, 1, 60_000)?;
    link.backoff_min = rmin;
    link.backoff_max = rmax;
    let io = IoSettings {
        link,
        unit,
        map: v.resource("io.map", &i.map, &["generic"])?,
        acquire: AcquireConfig {
            rate_hz: rate,
            pipeline: io_pipeline(&v, i.pipeline)?,
            ..AcquireConfig::default()
        },
    };
    let c = &raw.can;
    let can = match c.transport.as_str() {
        "socketcan" => {
            if c.interface.is_empty() || c.interface.len() > 15 {
                return Err(v.err(
                    "can.interface",
                    format!(
                        "\"{}\" is not an interface name (1 to 15 characters, e.g. can0)",
                        c.interface
                    ),
                ));
            }
            CanSettings::SocketCan {
                interface: c.interface.clone(),
            }
        }
        "cannelloni" => CanSettings::Cannelloni {
            local: v.addr("can.local", &c.local)?,
            remote: v.addr("can.remote", &c.remote)?,
        },
        "pycan" => CanSettings::PyCan {
            group: c.group.parse().map_err(|_| {
                v.err(
                    "can.group",
                    format!("\"{}\" is not an IPv4 multicast group", c.group),
                )
            })?,
            port: u16::try_from(c.port)
                .map_err(|_| v.err("can.port", format!("{} is not a UDP port", c.port)))?,
            iface: c.iface.parse().map_err(|_| {
                v.err(
                    "can.iface",
                    format!("\"{}\" is not an IPv4 interface address", c.iface),
                )
            })?,
        },
        other => {
            return Err(v.err(
                "can.transport",
                format!("\"{other}\" is unknown: use socketcan, cannelloni or pycan"),
            ));
        }
    };
    if let CanSettings::PyCan { group, .. } = &can
        && !group.is_multicast()
    {
        return Err(v.err(
            "can.group",
            format!("{group} is not a multicast address (224.0.0.0/4)"),
        ));
    }
    let f = &raw.follower;
    let node_id = u8::try_from(f.node_id)
        .ok()
        .filter(|n| (1..=127).contains(n))
        .ok_or_else(|| {
            v.err(
                "follower.node_id",
                format!("{} is not a CANopen node id (1 to 127)", f.node_id),
            )
        })?;
    let homing_method = i8::try_from(f.homing_method).map_err(|_| {
        v.err(
            "follower.homing_method",
            format!(
                "{} is not a CiA 402 homing method (-128 to 127)",
                f.homing_method
            ),
        )
    })?;
    let speed = Range::new(0.001, 1000.0, "mm/s");
    let accel = Range::new(0.01, 1e6, "mm/s²");
    let window = Range::new(0.001, 1000.0, "mm");
    // One key a line, whole (for grep), though rustfmt would split the longer ones.
    #[rustfmt::skip]
    let homing = [
        ("follower.homing_switch_speed_mm_s", f.homing_switch_speed_mm_s, speed),
        ("follower.homing_zero_speed_mm_s", f.homing_zero_speed_mm_s, speed),
        ("follower.homing_accel_mm_s2", f.homing_accel_mm_s2, accel),
        ("follower.homing_offset_mm", f.homing_offset_mm, POSITION_MM),
    ];
    #[rustfmt::skip]
    let drive = [
        ("follower.feed_mm", f.feed_mm, Range::new(0.01, 1000.0, "mm")),
        ("follower.gear_ratio", f.gear_ratio, Range::new(0.001, 1000.0, "")),
        ("follower.velocity_mm_s", f.velocity_mm_s, speed),
        ("follower.accel_mm_s2", f.accel_mm_s2, accel),
        ("follower.decel_mm_s2", f.decel_mm_s2, accel),
        ("follower.quick_stop_decel_mm_s2", f.quick_stop_decel_mm_s2, accel),
        ("follower.position_window_um", f.position_window_um, Range::new(0.01, 10_000.0, "µm")),
        ("follower.following_error_window_mm", f.following_error_window_mm, window),
        ("follower.min_mm", f.min_mm, POSITION_MM),
        ("follower.max_mm", f.max_mm, POSITION_MM),
    ];
    for (key, x, r) in drive.into_iter().chain(homing) {
        v.range(key, x, r)?;
    }
    if !(f.min_mm.is_finite() && f.max_mm.is_finite() && f.min_mm < f.max_mm) {
        return Err(v.err(
            "follower.max_mm",
            format!(
                "the limits {} .. {} mm must be finite with min below max",
                f.min_mm, f.max_mm
            ),
        ));
    }
    let fv = v.section("follower");
    let drive = DriveConfig {
        node_id,
        // 0x1017 and 0x1016 hold u16 milliseconds.
        heartbeat_period: fv.ms("heartbeat_ms", f.heartbeat_ms, 1, 65_535)?,
        heartbeat_timeout: fv.ms("heartbeat_timeout_ms", f.heartbeat_timeout_ms, 1, 65_535)?,
        sdo_timeout: fv.ms("sdo_timeout_ms", f.sdo_timeout_ms, 1, 60_000)?,
        sync_period: fv.ms("sync_ms", f.sync_ms, 1, 1000)?,
        quiet_sync_period: fv.ms("quiet_sync_ms", f.quiet_sync_ms, 1, 60_000)?,
        scaling: Scaling {
            feed_mm: f.feed_mm,
            shaft_revolutions: f.shaft_revolutions,
            encoder_increments: f.encoder_increments,
            motor_revolutions: f.motor_revolutions,
            gear_ratio: f.gear_ratio,
        },
        homing: HomingConfig {
            method: homing_method,
            switch_speed_mm_s: f.homing_switch_speed_mm_s,
            zero_speed_mm_s: f.homing_zero_speed_mm_s,
            accel_mm_s2: f.homing_accel_mm_s2,
            offset_mm: f.homing_offset_mm,
            timeout: fv.ms("homing_timeout_ms", f.homing_timeout_ms, 1, 3_600_000)?,
        },
        profile: ProfileConfig {
            velocity_mm_s: f.velocity_mm_s,
            accel_mm_s2: f.accel_mm_s2,
            decel_mm_s2: f.decel_mm_s2,
            quick_stop_decel_mm_s2: f.quick_stop_decel_mm_s2,
            position_window_mm: f.position_window_um * 1e-3,
            following_error_window_mm: f.following_error_window_mm,
            ..ProfileConfig::default()
        },
        limits: TravelLimits {
            min_mm: f.min_mm,
            max_mm: f.max_mm,
            write_to_drive: true,
        },
        ..DriveConfig::default()
    };
    if let Err(e) = drive.validate() {
        let key = follower_key(&e);
        return Err(match follower_related(&key) {
            Some(other) => v.err_with(&key, other, e.to_string()),
            None => v.err(&key, e.to_string()),
        });
    }
    let level_sd = Range::new(0.001, 60.0, "arcsec");
    let follower = FollowerSettings {
        drive,
        home_on_start: f.home_on_start,
        level: match f.level.as_str() {
            "manual" => LevelSource::Manual,
            "twin" => LevelSource::Twin(v.addr("cnc.twin", &raw.cnc.twin)?),
            other => {
                return Err(v.err(
                    "follower.level",
                    format!("\"{other}\" is unknown: use manual or twin"),
                ));
            }
        },
        level_sd_rad: fv.range("level_sd_arcsec", f.level_sd_arcsec, level_sd)?
            * crate::units::RAD_PER_ARCSEC,
    };
    let t = &raw.tracking;
    let strategy = match t.strategy.as_str() {
        "overlap" => Strategy::Overlap,
        "encoder" => Strategy::Encoder,
        other => {
            return Err(v.err(
                "tracking.strategy",
                format!("\"{other}\" is unknown: use overlap or encoder"),
            ));
        }
    };
    let spot_mm = Range::new(0.01, 50.0, "mm");
    let handover_mm = v.range("tracking.handover_mm", t.handover_mm, spot_mm)?;
    let edge_mm = v.range("tracking.edge_mm", t.edge_mm, spot_mm)?;
    if edge_mm <= handover_mm {
        return Err(v.err_with(
            "tracking.edge_mm",
            "tracking.handover_mm",
            format!("{edge_mm} mm must exceed tracking.handover_mm ({handover_mm} mm)"),
        ));
    }
    if t.average_frames < 2 {
        return Err(v.err(
            "tracking.average_frames",
            format!("{} is too few: give at least 2", t.average_frames),
        ));
    }
    v.checked(
        "tracking.average_frames",
        range::int(t.average_frames, 2, MAX_FRAMES, ""),
    )?;
    let (tolerance_um, sd_um, sd_um_per_m) = (
        Range::new(0.01, 1000.0, "µm"),
        Range::new(0.0, 1000.0, "µm"),
        Range::new(0.0, 1000.0, "µm/m"),
    );
    let band = Range::new(0.001, 50.0, "mm");
    let tv = v.section("tracking");
    let tracking = TrackSettings {
        strategy,
        handover_mm,
        edge_mm,
        anticipate: tv.ms("anticipate_ms", t.anticipate_ms, 0, 10_000)?,
        rest_tolerance_mm: tv.range("rest_tolerance_um", t.rest_tolerance_um, tolerance_um)? * 1e-3,
        rest_time: tv.ms("rest_ms", t.rest_ms, 1, 60_000)?,
        average_frames: t.average_frames as usize,
        settle: tv.ms("settle_ms", t.settle_ms, 0, 60_000)?,
        follow_band_mm: tv.range("follow_band_mm", t.follow_band_mm, band)?,
        follow_interval: tv.ms("follow_interval_ms", t.follow_interval_ms, 1, 10_000)?,
        lead: tv.ms("lead_ms", t.lead_ms, 0, 10_000)?,
        lost_after: tv.ms("lost_after_ms", t.lost_after_ms, 1, 60_000)?,
        encoder_sd_mm: tv.range("encoder_sd_um", t.encoder_sd_um, sd_um)? * 1e-3,
        encoder_sd_per_mm: tv.range("encoder_sd_um_per_m", t.encoder_sd_um_per_m, sd_um_per_m)?
            * 1e-6,
        mapped_sd_mm: tv.range("mapped_sd_um", t.mapped_sd_um, sd_um)? * 1e-3,
        mapped_vertical_sd_mm: tv.range("mapped_vertical_sd_um", t.mapped_vertical_sd_um, sd_um)?
            * 1e-3,
        vertical_sd_mm: tv.range("vertical_sd_um", t.vertical_sd_um, sd_um)? * 1e-3,
        vertical_sd_per_mm: tv.range(
            "vertical_sd_um_per_m",
            t.vertical_sd_um_per_m,
            sd_um_per_m,
        )? * 1e-6,
        move_timeout: tv.ms("move_timeout_ms", t.move_timeout_ms, 1, 600_000)?,
        approach_mm: approach_mm(&v, t.approach_um)?,
    };
    let c = &raw.cnc;
    let cnc = CncSettings {
        mode: match c.mode.as_str() {
            "manual" => CncMode::Manual,
            "twin" => CncMode::Twin(v.addr("cnc.twin", &c.twin)?),
            other => {
                return Err(v.err(
                    "cnc.mode",
                    format!("\"{other}\" is unknown: use manual or twin"),
                ));
            }
        },
        dialect: Dialect::parse(&c.dialect).ok_or_else(|| {
            v.err(
                "cnc.dialect",
                format!(
                    "\"{}\" is unknown: use iso, siemens, heidenhain or linuxcnc",
                    c.dialect
                ),
            )
        })?,
    };
    let k = &raw.capture;
    if k.frames < 2 {
        return Err(v.err(
            "capture.frames",
            format!("{} is too few: give at least 2", k.frames),
        ));
    }
    let (cv, target_mm) = (v.section("capture"), Range::new(0.001, 100.0, "mm"));
    let capture = CaptureSettings {
        rest_tolerance_mm: cv.range("rest_tolerance_um", k.rest_tolerance_um, tolerance_um)? * 1e-3,
        settle: cv.ms("settle_ms", k.settle_ms, 1, 60_000)?,
        target_tolerance_mm: cv.range("target_tolerance_mm", k.target_tolerance_mm, target_mm)?,
        frames: v.checked(
            "capture.frames",
            range::int(k.frames, 2, MAX_FRAMES, "").map(|n| n as usize),
        )?,
        timeout: v.checked(
            "capture.timeout_s",
            range::int(k.timeout_s, 1, 86_400, "s").map(Duration::from_secs),
        )?,
        repeatability: crate::run::Repeatability {
            linear_mm: cv.range(
                "repeatability_um",
                k.repeatability_um,
                Range::new(0.01, 1000.0, "µm"),
            )? * 1e-3,
            angular_rad: cv
                .range(
                    "repeatability_arcsec",
                    k.repeatability_arcsec,
                    Range::new(0.01, 1000.0, "arcsec"),
                )?
                .to_radians()
                / 3600.0,
        },
        judge: k.judge,
    };
    let (a, angle) = (&raw.align, Range::new(1.0, 10_000.0, "µrad"));
    let align = AlignConfig {
        settings: crate::align::AlignSettings {
            margin_mm: v.range("align.margin_mm", a.margin_mm, Range::new(0.01, 10.0, "mm"))?,
            max_angle_rad: v.range("align.max_angle_urad", a.max_angle_urad, angle)? * 1e-6,
            ..Default::default()
        },
        check_before_run: a.check_before_run,
        // From a few minutes (re-align before every run) to a year.
        valid_for: v.checked(
            "align.valid_for_h",
            Range::new(0.1, 8760.0, "h").duration(a.valid_for_h, 3600.0),
        )?,
    };
    let plc = plc_settings(&v, &raw.plc)?;
    let hexapod = crate::hexapod::config::validate(&raw.hexapod)
        .map_err(|e| v.err(&e.dotted_key(), e.problem))?;
    let comp = crate::comp::settings::validate(&raw.comp).map_err(|(k, p)| v.err(&k, p))?;
    let (machine, acceptance) = crate::report::settings::validate(&raw.machine, &raw.acceptance)
        .map_err(|(k, p)| v.err(&k, p))?;
    Ok(Settings {
        service,
        head,
        io,
        can,
        follower,
        tracking,
        cnc,
        capture,
        align,
        plc,
        hexapod,
        comp,
        machine,
        acceptance,
        sources,
    })
}

/// `tracking.approach_um`: the follower's final approach from below (mm): 0 (none), or 5 to
/// 100 µm (more than the stage's reversal switch and a drive's overshoot on a short move, less
/// than a spot's rest tolerance could hide).
fn approach_mm(v: &V, um: f64) -> Result<f64, ConfigError> {
    let r = Range::new(5.0, 100.0, "µm").or_zero("no approach");
    Ok(v.range("tracking.approach_um", um, r)? * 1e-3)
}

/// Frames averaged at once (`tracking.average_frames`, `capture.frames`): 2 at least, and at
/// most a million (100 s at the highest frame rate).
const MAX_FRAMES: u64 = 1_000_000;

/// `io.pipeline`: block reads in flight when unthrottled (modbus::pipelined).
fn io_pipeline(v: &V, n: i64) -> Result<usize, ConfigError> {
    let max = crate::modbus::pipelined::MAX_DEPTH as i64;
    if (1..=max).contains(&n) {
        Ok(n as usize)
    } else {
        Err(v.err(
            "io.pipeline",
            format!("{n} is out of range: use 1 to {max} (1 for a module that takes one request at a time)"),
        ))
    }
}

fn plc_settings(v: &V, p: &RawPlc) -> Result<PlcSettings, ConfigError> {
    let map = v.resource("plc.map", &p.map, &["generic"])?;
    let push = if p.push {
        let unit = u8::try_from(p.unit).map_err(|_| {
            v.err(
                "plc.unit",
                format!("{} is not a Modbus unit id (0 to 255)", p.unit),
            )
        })?;
        let (rmin, rmax) = (
            v.ms("plc.reconnect_min_ms", p.reconnect_min_ms, 1, 600_000)?,
            v.ms("plc.reconnect_max_ms", p.reconnect_max_ms, 1, 600_000)?,
        );
        if rmax < rmin {
            return Err(v.err(
                "plc.reconnect_max_ms",
                format!(
                    "{} ms is below plc.reconnect_min_ms ({} ms)",
                    p.reconnect_max_ms, p.reconnect_min_ms
                ),
            ));
        }
        let mut link = LinkConfig::new(v.addr("plc.address", &p.address)?);
        link.timeout = v.ms("plc.timeout_ms", p.timeout_ms, 1, 60_000)?;
        link.backoff_min = rmin;
        link.backoff_max = rmax;
        Some(PlcPush { link, unit })
    } else {
        None
    };
    let ips = |key: &str, list: &[String]| -> Result<Option<Vec<std::net::IpAddr>>, ConfigError> {
        if list.is_empty() {
            return Ok(None);
        }
        list.iter()
            .map(|s| {
                s.parse().map_err(|_| {
                    v.err(
                        key,
                        format!(
                            "\"{s}\" is not an IP address: list addresses like \"192.168.10.5\""
                        ),
                    )
                })
            })
            .collect::<Result<Vec<_>, _>>()
            .map(Some)
    };
    let pull = if p.pull {
        Some(crate::plc::PullConfig {
            bind: v.addr("plc.pull_bind", &p.pull_bind)?,
            allow: ips("plc.pull_allow", &p.pull_allow)?,
            writers: ips("plc.pull_writers", &p.pull_writers)?,
            max_connections: match p.pull_max_connections {
                1..=1000 => p.pull_max_connections as usize,
                n => {
                    return Err(v.err(
                        "plc.pull_max_connections",
                        format!("{n} is out of range: use 1 to 1000 (default 32)"),
                    ));
                }
            },
            idle_timeout: match p.pull_idle_timeout_s {
                1..=3600 => Duration::from_secs(p.pull_idle_timeout_s),
                n => {
                    return Err(v.err(
                        "plc.pull_idle_timeout_s",
                        format!(
                            "{n} s is out of range: use 1 to 3600 s (default 60), longer than the PLC's poll period"
                        ),
                    ));
                }
            },
        })
    } else {
        None
    };
    let timeouts = crate::plc::Timeouts {
        ready: v.ms("plc.ready_timeout_ms", p.ready_timeout_ms, 1, 600_000)?,
        heartbeat: v.ms(
            "plc.heartbeat_timeout_ms",
            p.heartbeat_timeout_ms,
            1,
            600_000,
        )?,
        poll: v.ms("plc.poll_ms", p.poll_ms, 1, 60_000)?,
        echo: v.ms("plc.echo_timeout_ms", p.echo_timeout_ms, 1, 600_000)?,
    };
    if timeouts.heartbeat > timeouts.ready {
        return Err(v.err_with(
            "plc.heartbeat_timeout_ms",
            "plc.ready_timeout_ms",
            format!(
                "{} ms exceeds plc.ready_timeout_ms ({} ms): the heartbeat must be seen to change before the ready wait ends",
                p.heartbeat_timeout_ms, p.ready_timeout_ms
            ),
        ));
    }
    let positioning = match p.positioning.as_str() {
        "unidirectional" => crate::comp::PositioningMode::Unidirectional,
        "bidirectional" => crate::comp::PositioningMode::Bidirectional,
        other => {
            return Err(v.err(
                "plc.positioning",
                format!("\"{other}\" is unknown: use unidirectional or bidirectional"),
            ));
        }
    };
    let step_mm = Some(v.range(
        "plc.step_mm",
        p.step_mm,
        Range::new(0.01, 10_000.0, "mm").or_zero("the targets' mean spacing"),
    )?)
    .filter(|s| *s > 0.0);
    Ok(PlcSettings {
        map,
        push,
        pull,
        timeouts,
        tables: TableBuild {
            positioning,
            straightness: p.straightness,
            step_mm,
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn load_text(text: &str, env: &[(&str, &str)]) -> Result<Settings, ConfigError> {
        let dir = std::env::temp_dir().join(format!("axiscomp-cfg-{}", std::process::id()));
        let _ = std::fs::create_dir_all(&dir);
        // A file per call: tests run in parallel (a name by text length collided).
        static N: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let path = dir.join(format!("t{n}.toml"));
        std::fs::write(&path, text).unwrap();
        let r = load(&Layers {
            etc: None,
            file: Some(path.clone()),
            env: env
                .iter()
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect(),
        });
        let _ = std::fs::remove_file(&path);
        r
    }

    #[test]
    fn defaults_are_valid() {
        let s = load(&Layers::default()).unwrap();
        assert_eq!(s.io.acquire.rate_hz, 500.0);
        assert_eq!(s.follower.drive.node_id, 1);
        assert!((s.follower.drive.scaling.counts_per_mm() - 26214.4).abs() < 1e-9);
        assert_eq!(s.tracking.strategy, Strategy::Overlap);
        assert_eq!(s.head.layout, Resource::Builtin("reference".into()));
    }

    #[test]
    fn shipped_example_is_valid() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/axiscomp.toml");
        let s = load(&Layers {
            etc: None,
            file: Some(path),
            env: vec![],
        })
        .unwrap();
        assert_eq!(s.io.link.addr, "192.168.10.20:502".parse().unwrap());
        assert!(matches!(s.can, CanSettings::SocketCan { .. }));
        // Every key of the built-in defaults appears in the example.
        let defaults: toml::Table = toml::from_str(DEFAULTS).unwrap();
        let example: toml::Table = toml::from_str(
            &std::fs::read_to_string(
                Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/axiscomp.toml"),
            )
            .unwrap(),
        )
        .unwrap();
        for (section, keys) in &defaults {
            for key in keys.as_table().unwrap().keys() {
                assert!(
                    example[section].as_table().unwrap().contains_key(key),
                    "configs/axiscomp.toml lacks {section}.{key}"
                );
            }
        }
    }

    #[test]
    fn plc_section_is_validated_with_its_keys() {
        let s = load(&Layers::default()).unwrap();
        assert_eq!(s.plc.map, Resource::Builtin("generic".into()));
        assert!(s.plc.push.is_none() && s.plc.pull.is_none());
        assert_eq!(s.plc.timeouts, crate::plc::Timeouts::default());
        let s = load_text(
            "[plc]\npush = true\naddress = \"10.0.0.9:502\"\nunit = 3\npull = true\n\
             pull_bind = \"0.0.0.0:1502\"\npull_allow = [\"10.0.0.9\", \"10.0.0.10\"]\n\
             step_mm = 5.0\npositioning = \"bidirectional\"\nmap = \"plc-maps/cnc/codesys.toml\"\n",
            &[],
        )
        .unwrap();
        let push = s.plc.push.unwrap();
        assert_eq!((push.link.addr.port(), push.unit), (502, 3));
        let pull = s.plc.pull.unwrap();
        assert_eq!(pull.allow.unwrap().len(), 2);
        assert_eq!(pull.writers, None);
        assert_eq!(
            (pull.max_connections, pull.idle_timeout),
            (32, Duration::from_secs(60))
        );
        let limits = load_text(
            "[plc]\npull = true\npull_max_connections = 4\npull_idle_timeout_s = 5\n",
            &[],
        )
        .unwrap()
        .plc
        .pull
        .unwrap();
        assert_eq!(
            (limits.max_connections, limits.idle_timeout),
            (4, Duration::from_secs(5))
        );
        assert_eq!(s.plc.tables.step_mm, Some(5.0));
        assert_eq!(
            s.plc.map,
            Resource::File("plc-maps/cnc/codesys.toml".into())
        );
        for (text, key) in [
            ("push = true\naddress = \"plc\"", "plc.address"),
            ("push = true\nunit = 300", "plc.unit"),
            (
                "pull = true\npull_allow = [\"plc.local\"]",
                "plc.pull_allow",
            ),
            (
                "pull = true\npull_max_connections = 0",
                "plc.pull_max_connections",
            ),
            (
                "pull = true\npull_max_connections = 1001",
                "plc.pull_max_connections",
            ),
            (
                "pull = true\npull_idle_timeout_s = 0",
                "plc.pull_idle_timeout_s",
            ),
            (
                "pull = true\npull_idle_timeout_s = 3601",
                "plc.pull_idle_timeout_s",
            ),
            ("positioning = \"both\"", "plc.positioning"),
            ("heartbeat_timeout_ms = 9000", "plc.heartbeat_timeout_ms"),
            ("step_mm = -1.0", "plc.step_mm"),
            ("map = \"builtin:siemens\"", "plc.map"),
        ] {
            let e = load_text(&format!("[plc]\n{text}\n"), &[]).unwrap_err();
            assert_eq!(e.key, key, "{e}");
            assert!(e.origin.ends_with(".toml"), "{e}");
        }
        // A push address is only needed when pushing.
        assert!(load_text("[plc]\naddress = \"plc\"\n", &[]).is_ok());
        let e = load_text("[plc]\npush_to = true\n", &[]).unwrap_err();
        assert!(e.to_string().contains("push_to"), "{e}");
    }

    /// `hexapod::config`'s own error comes out as every other: the key and the file.
    #[test]
    fn hexapod_errors_name_the_key_and_the_file() {
        let e = load_text("[hexapod]\ndriver = \"hxp\"\n", &[]).unwrap_err();
        assert_eq!(e.key, "hexapod.driver", "{e}");
        assert!(e.origin.ends_with(".toml"), "{e}");
        assert!(
            e.to_string().contains(
                "hexapod.driver: \"hxp\": use \"pi-gcs\" (PI C-887), \"newport-xps\" (Newport HXP) or \"none\""
            ),
            "{e}"
        );
        let e = load_text("[hexapod]\npivot_mm = [0.0, 1.0]\n", &[]).unwrap_err();
        assert_eq!(e.key, "hexapod.pivot_mm", "{e}");
        assert!(e.origin.ends_with(".toml"), "{e}");
    }

    #[test]
    fn layers_override_in_order() {
        let s = load_text(
            "[io]\nrate_hz = 250.0\naddress = \"10.0.0.5:502\"\n",
            &[
                ("AXISCOMP__IO__RATE_HZ", "100"),
                ("AXISCOMP__CAN__TRANSPORT", "cannelloni"),
            ],
        )
        .unwrap();
        assert_eq!(s.io.acquire.rate_hz, 100.0);
        assert_eq!(s.io.link.addr, "10.0.0.5:502".parse().unwrap());
        assert!(matches!(s.can, CanSettings::Cannelloni { .. }));
    }

    #[test]
    fn io_pipeline_defaults_to_one_and_is_bounded() {
        assert_eq!(load_text("", &[]).unwrap().io.acquire.pipeline, 1);
        assert_eq!(
            load_text("[io]\npipeline = 4\n", &[])
                .unwrap()
                .io
                .acquire
                .pipeline,
            4
        );
        for bad in ["0", "17", "-1"] {
            let e = load_text(&format!("[io]\npipeline = {bad}\n"), &[]).unwrap_err();
            assert_eq!(e.key, "io.pipeline");
            assert!(e.origin.ends_with(".toml"), "{e}");
            assert!(
                e.to_string()
                    .contains(&format!("{bad} is out of range: use 1 to 16")),
                "{e}"
            );
        }
    }

    #[test]
    fn errors_name_key_and_file() {
        let e = load_text("[io]\nrate_hz = -5.0\n", &[]).unwrap_err();
        assert_eq!(e.key, "io.rate_hz");
        assert!(e.origin.ends_with(".toml"), "{e}");
        assert!(
            e.to_string().ends_with(
                "io.rate_hz: -5 Hz is out of range: use 0 (as fast as the module answers) or 1 to 10000 Hz"
            ),
            "{e}"
        );

        let e = load_text(
            "[io]\nrate_hz = 5.0\n",
            &[("AXISCOMP__FOLLOWER__NODE_ID", "200")],
        )
        .unwrap_err();
        assert_eq!(e.key, "follower.node_id");
        assert_eq!(e.origin, "the environment");

        // A relation broken by the file against a default names the file's key (found by
        // tests/it/fuzz.rs: heartbeat_ms = 350 blamed the built-in heartbeat_timeout_ms).
        let e = load_text("[follower]\nheartbeat_ms = 350\n", &[]).unwrap_err();
        assert_eq!(e.key, "follower.heartbeat_ms", "{e}");
        assert!(e.origin.ends_with(".toml"), "{e}");
        assert!(
            e.problem
                .ends_with("(with follower.heartbeat_timeout_ms at its built-in default)"),
            "{e}"
        );
        let e = load_text("[tracking]\nhandover_mm = 4.0\n", &[]).unwrap_err();
        assert_eq!(e.key, "tracking.handover_mm", "{e}");
        assert!(e.origin.ends_with(".toml"), "{e}");
        let e = load_text("[plc]\nready_timeout_ms = 100\n", &[]).unwrap_err();
        assert_eq!(e.key, "plc.ready_timeout_ms", "{e}");
        // Both set in the file: the key checked is named.
        let e = load_text(
            "[follower]\nheartbeat_ms = 350\nheartbeat_timeout_ms = 300\n",
            &[],
        )
        .unwrap_err();
        assert_eq!(e.key, "follower.heartbeat_timeout_ms", "{e}");

        let e = load_text("[io]\nratehz = 5.0\n", &[]).unwrap_err();
        assert!(
            e.to_string().contains("line 2") && e.to_string().contains("ratehz"),
            "{e}"
        );

        let e = load_text("[io]\nrate_hz = \"fast\"\n", &[]).unwrap_err();
        assert!(e.to_string().contains("line 2"), "{e}");

        let e = load_text("[can]\ntransport = \"usb\"\n", &[]).unwrap_err();
        assert!(
            e.to_string().contains("can.transport")
                && e.to_string().contains("socketcan, cannelloni or pycan"),
            "{e}"
        );

        let e = load_text("[follower]\nfeed_mm = 0.0\n", &[]).unwrap_err();
        assert_eq!(e.key, "follower.feed_mm", "{e}");
        let e = load_text("[follower]\nheartbeat_timeout_ms = 50\n", &[]).unwrap_err();
        assert_eq!(e.key, "follower.heartbeat_timeout_ms", "{e}");
        let e = load_text("[follower]\nquiet_sync_ms = 25\n", &[]).unwrap_err();
        assert_eq!(e.key, "follower.quiet_sync_ms", "{e}");
        assert!(e.to_string().contains("multiple of the SYNC period"), "{e}");

        let e = load_text("[io]\naddress = \"plc\"\n", &[]).unwrap_err();
        assert!(
            e.to_string().contains("io.address") && e.to_string().contains("IP:port"),
            "{e}"
        );
    }
}
