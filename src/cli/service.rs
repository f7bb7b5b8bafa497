//! `axiscomp serve|status|check|sim`: the service, its status, the offline check, the twin.

use super::InputError;
use anyhow::{Context, Result};
use axiscomp::config::{self, Layers, Resource};
use axiscomp::service::api::snapshot::Snapshot;
use axiscomp::service::control::Client;
use axiscomp::service::shutdown::{self, Trigger};
use axiscomp::service::{self, ServiceError};
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug)]
pub struct ServeArgs {
    /// Configuration file (layered over /etc/axiscomp/axiscomp.toml and the defaults).
    #[arg(long)]
    pub config: Option<PathBuf>,
}

#[derive(clap::Args, Debug)]
pub struct StatusArgs {
    /// The control socket (default: from the configuration).
    #[arg(long)]
    pub socket: Option<PathBuf>,
    /// The service's configuration (default: /etc/axiscomp/axiscomp.toml), for the socket.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Print the snapshot as JSON.
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct SimArgs {
    /// The twin's configuration (see configs/sim.toml).
    #[arg(long)]
    pub config: PathBuf,
}

pub(crate) fn init_logs() {
    use tracing_subscriber::EnvFilter;
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    // Under systemd, journald stamps the time itself and shows no colours.
    let journald = std::env::var_os("JOURNAL_STREAM").is_some();
    let b = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(!journald && std::io::IsTerminal::is_terminal(&std::io::stderr()));
    let _ = if journald {
        b.without_time().try_init()
    } else {
        b.try_init()
    };
}

/// The layered configuration with `--config FILE` (for other subcommands too).
pub fn settings(file: Option<&Path>) -> Result<config::Settings> {
    load_settings(file)
}

fn load_settings(file: Option<&Path>) -> Result<config::Settings> {
    config::load(&Layers::standard(file)).map_err(|e| InputError(e.to_string()).into())
}

fn service_error(e: ServiceError) -> anyhow::Error {
    if e.is_input() {
        InputError(e.to_string()).into()
    } else {
        e.into()
    }
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")
}

/// The service's runtime: one thread. Its work per frame is small (microseconds); what costs
/// at 500 frames/s is waking tasks, and on one thread that is a function call, not an OS
/// context switch between workers.
fn service_runtime() -> Result<tokio::runtime::Runtime> {
    // The pacing grid starts just before the runtime's clock: tokio rounds a deadline up to
    // its next millisecond tick, so grid points just before its ticks fire at once rather
    // than up to a millisecond late (which at 2 ms made every tenth frame or so miss its tick).
    axiscomp::util::pace::origin();
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")
}

/// SIGTERM or SIGINT fires the shutdown.
fn on_signals(trigger: Trigger) -> Result<()> {
    use tokio::signal::unix::{SignalKind, signal};
    let mut term = signal(SignalKind::terminate()).context("installing the SIGTERM handler")?;
    let mut int = signal(SignalKind::interrupt()).context("installing the SIGINT handler")?;
    tokio::spawn(async move {
        tokio::select! {
            _ = term.recv() => tracing::info!("SIGTERM: shutting down"),
            _ = int.recv() => tracing::info!("SIGINT: shutting down"),
        }
        service::notify::stopping();
        trigger.trigger();
    });
    Ok(())
}

pub fn serve(a: ServeArgs) -> Result<()> {
    init_logs();
    let settings = load_settings(a.config.as_deref())?;
    let prepared = service::prepare(&settings).map_err(service_error)?;
    service_runtime()?.block_on(async move {
        let (trigger, listener) = shutdown::channel();
        on_signals(trigger)?;
        service::run(prepared, listener)
            .await
            .map_err(service_error)
    })
}

fn resource(r: &Resource) -> String {
    match r {
        Resource::Builtin(n) => format!("built-in {n}"),
        Resource::File(p) => p.display().to_string(),
    }
}

pub fn check(a: ServeArgs) -> Result<()> {
    use axiscomp::config::kind::{self, FileKind};
    if let Some(path) = a.config.as_deref() {
        let text = std::fs::read_to_string(path)
            .map_err(|e| InputError(format!("{}: cannot read it: {e}", path.display())))?;
        let k = kind::detect(&text).unwrap_or(FileKind::Service);
        println!("{}: {}", path.display(), k.describe());
        if k != FileKind::Service {
            return check_other(path, &text, k);
        }
    }
    let settings = load_settings(a.config.as_deref())?;
    let p = service::prepare(&settings).map_err(service_error)?;
    println!("configuration: {}", settings.sources.join(" + "));
    println!(
        "layout: {} ({}), {} elements",
        resource(&settings.head.layout),
        p.layout.hash(),
        p.layout.elements.len()
    );
    match (&settings.head.calibration, &p.calibration) {
        (Some(path), Some(c)) => println!(
            "calibration: {} ({} poses, {}, made {})",
            path.display(),
            c.poses,
            if c.model.is_some() {
                "model-based"
            } else {
                "linear β"
            },
            c.created
        ),
        _ => println!("calibration: none (the layout's own model)"),
    }
    println!(
        "I/O module: {} unit {} via map {} ({} {} registers from {})",
        settings.io.link.addr,
        if settings.io.unit == 0 {
            p.map.unit_id
        } else {
            settings.io.unit
        },
        resource(&settings.io.map),
        p.map.block.count(),
        p.map.kind,
        p.map.block.start()
    );
    println!(
        "CAN: {}, follower node {}",
        settings.can, settings.follower.drive.node_id
    );
    let m = &p.cnc_map;
    let pl = &settings.plc;
    println!(
        "CNC map: {} ({}, {}, unit {}, up to {} points, |value| ≤ {} µm, step ≤ {} µm)",
        resource(&pl.map),
        m.name,
        m.file,
        m.unit_id,
        m.limits.max_points,
        m.limits.max_abs_mm * 1e3,
        m.limits.max_step_mm * 1e3
    );
    match &pl.push {
        Some(push) => println!(
            "PLC push: {} unit {}",
            push.link.addr,
            push.unit_or(m.unit_id)
        ),
        None => println!("PLC push: off"),
    }
    // The check the CNC asks for is read from the PLC: it needs push.
    match (&m.check, &pl.push) {
        (Some(c), Some(_)) => println!(
            "PLC check requests: read every second (check.request at {}, answered at {})",
            m.doc(&c.request),
            m.doc(&c.answered)
        ),
        (Some(_), None) => println!(
            "PLC check requests: not read: the map has [check] but push is off, so the CNC's requests go unanswered; set [plc] push = true and its address"
        ),
        (None, _) => println!("PLC check requests: none (the map has no [check] section)"),
    }
    match &pl.pull {
        Some(pull) => println!(
            "PLC pull server: {} (allow {}, writers {})",
            pull.bind,
            pull.allow
                .as_ref()
                .map_or("everyone".into(), |a| addresses(a)),
            pull.writers
                .as_ref()
                .map_or("every connected peer".into(), |a| addresses(a))
        ),
        None => println!("PLC pull server: off"),
    }
    let dialect = settings.cnc.dialect.name();
    match settings.cnc.mode {
        axiscomp::config::CncMode::Manual => println!(
            "CNC: manual: each run's part program ({dialect}) is written to the state directory for the operator to load"
        ),
        axiscomp::config::CncMode::Twin(a) => {
            println!("CNC: the twin at {a} runs each part program ({dialect})")
        }
    }
    println!("control socket: {}", settings.service.socket.display());
    println!("ok");
    Ok(())
}

/// `check` of a file that is not the service's configuration: read it with its own reader.
fn check_other(path: &Path, text: &str, k: axiscomp::config::kind::FileKind) -> Result<()> {
    use axiscomp::config::kind::FileKind;
    let label = path.display().to_string();
    match k {
        FileKind::Service => unreachable!("the service's configuration is checked by check"),
        FileKind::Twin => {
            let (layout, spec) = axiscomp::sim::config::parse(text, &label)?;
            println!(
                "twin: seed {}, axis {:.0} mm, layout {} ({}), I/O module on {}",
                spec.plant.seed,
                spec.plant.axis.length_mm,
                layout.name,
                layout.hash(),
                spec.io_bind
            );
        }
        FileKind::IoMap => {
            let m = axiscomp::acquire::map::IoMap::parse(text, &label)?;
            println!(
                "I/O map: {}, unit {}, {} registers from {}",
                m.name,
                m.unit_id,
                m.block.count(),
                m.block.start()
            );
        }
        FileKind::CncMap => {
            let m = axiscomp::plc::map::CncMap::parse(text, &label)?;
            println!(
                "CNC map: {}, unit {}, up to {} points",
                m.name, m.unit_id, m.limits.max_points
            );
        }
        FileKind::Layout => {
            let l = axiscomp::optics::Layout::parse(text, &label)?;
            println!(
                "layout: {} ({}), {} elements",
                l.name,
                l.hash(),
                l.elements.len()
            );
        }
        FileKind::Calibration => {
            let c = axiscomp::calibrate::CalibrationFile::parse(text, &label)?;
            println!(
                "calibration: {} poses, made {}",
                c.meta.poses, c.meta.created
            );
        }
    }
    println!("ok");
    Ok(())
}

fn print_snapshot(s: &Snapshot) {
    println!(
        "links: I/O {} ({}; {:.0} frames/s, p99 {:.0} µs), CAN {} ({}; {:.0} TPDO/s{})",
        s.links.io.state,
        s.links.io.peer,
        s.links.io.rate_hz,
        s.links.io.latency_p99_us,
        s.links.can.state,
        s.links.can.peer,
        s.links.can.rate_hz,
        s.links
            .can
            .detail
            .as_ref()
            .map(|d| format!(", {d}"))
            .unwrap_or_default()
    );
    match &s.psd {
        Some(p) => {
            for (k, spot) in p.spots_um.iter().enumerate() {
                match spot {
                    Some([x, y]) => println!(
                        "PSD{}: X {x:>9.1} µm  Y {y:>9.1} µm  SUM {:.2} V",
                        k + 1,
                        p.sums_v[k]
                    ),
                    None => println!("PSD{}: no spot (SUM {:.2} V)", k + 1, p.sums_v[k]),
                }
            }
        }
        None => println!("PSDs: no frame yet"),
    }
    let f = &s.follower;
    println!(
        "follower (node {}): {}, position {}, homed {}, heartbeat {}{}",
        f.node_id,
        f.state,
        f.position_mm
            .map(|p| format!("{p:.4} mm"))
            .unwrap_or_else(|| "?".into()),
        f.homed,
        if f.heartbeat_ok { "ok" } else { "LOST" },
        f.last_emcy
            .as_ref()
            .map(|e| format!(", last EMCY {e}"))
            .unwrap_or_default()
    );
    let t = &s.tracking;
    println!(
        "tracking: {} {}, PSD2 at {:.4} mm (±{:.2} µm), {} handovers{}",
        t.strategy,
        if t.valid { "valid" } else { "NOT referenced" },
        t.follower_mm,
        t.sd_um[0],
        t.handovers,
        if t.at_rest { ", at rest" } else { "" }
    );
    match &s.live {
        Some(l) => {
            let names = ["dx", "dy", "dz", "ex", "ey", "ez"];
            let units = ["µm", "µm", "µm", "″", "″", "″"];
            println!(
                "errors ({} frames, travel {:.3} mm, nominal {}{}):",
                l.frames,
                l.travel_mm,
                l.nominal_mm
                    .map(|n| format!("{n:.3} mm"))
                    .unwrap_or_else(|| "not set".into()),
                if l.zeroed { ", zeroed" } else { "" }
            );
            for k in 0..6 {
                println!(
                    "  {} {:>10.3} ± {:.3} {}",
                    names[k], l.errors[k], l.sd[k], units[k]
                );
            }
        }
        None => println!("errors: none yet"),
    }
    for a in s.alarms.iter().filter(|a| a.active) {
        println!("ALARM {}: {}", a.code, a.text);
    }
}

pub fn status(a: StatusArgs) -> Result<()> {
    let socket = match a.socket {
        Some(s) => s,
        None => load_settings(a.config.as_deref())?.service.socket,
    };
    let snap = runtime()?.block_on(async {
        let mut c = Client::connect(&socket).await?;
        c.status().await
    })?;
    super::stdout_closes_quietly();
    if a.json {
        println!("{}", serde_json::to_string_pretty(&snap)?);
    } else {
        print_snapshot(&snap);
    }
    Ok(())
}

pub fn sim(a: SimArgs) -> Result<()> {
    init_logs();
    let (layout, spec, plc) = axiscomp::sim::config::load_all(&a.config)?;
    runtime()?.block_on(async move {
        let twin = axiscomp::sim::twin::Twin::start(&layout, spec).await?;
        // The twin's PLC applies accepted tables to the same plant.
        let plc = match plc {
            Some(p) => Some(
                axiscomp::sim::plc::TwinPlc::start(
                    twin.plant.clone(),
                    p.map,
                    axiscomp::sim::plc::TwinPlcConfig {
                        bind: p.bind,
                        ..Default::default()
                    },
                )
                .await
                .map(std::sync::Arc::new)
                .with_context(|| format!("the twin's PLC on {}", p.bind))?,
            ),
            None => None,
        };
        if let Some(p) = &plc {
            twin.attach_plc(p.clone());
        }
        println!(
            "twin up: I/O module on {}, control on {}{}",
            twin.io.local_addr(),
            twin.control_addr()
                .map(|a| a.to_string())
                .unwrap_or_default(),
            plc.as_ref()
                .map(|p| format!(", PLC on {} ({})", p.local_addr(), p.map().name))
                .unwrap_or_default()
        );
        let hexapod = start_twin_hexapod(&a.config, &twin).await?;
        let (trigger, mut listener) = shutdown::channel();
        on_signals(trigger)?;
        listener.recv().await;
        drop(hexapod);
        drop(plc);
        drop(twin);
        Ok(())
    })
}

/// The twin's hexapod controller (`[hexapod]` of the twin's config; by default GCS on
/// 127.0.0.1:50000 and XPS on 127.0.0.1:5001). A port already taken (another twin, a real
/// controller's simulator) is a warning: the rest of the twin runs without it.
async fn start_twin_hexapod(
    config: &std::path::Path,
    twin: &axiscomp::sim::twin::Twin,
) -> Result<Option<axiscomp::sim::hexapod_servers::HexapodServers>> {
    use axiscomp::sim::hexapod_servers::{spec_from_config, start};
    let text =
        std::fs::read_to_string(config).with_context(|| format!("reading {}", config.display()))?;
    let spec = spec_from_config(&text, &config.display().to_string()).map_err(super::InputError)?;
    match start(spec, twin.plant.hexapod.clone()).await {
        Ok(s) => {
            let at = |a: Option<std::net::SocketAddr>| {
                a.map(|a| a.to_string()).unwrap_or_else(|| "off".into())
            };
            println!(
                "twin hexapod: PI GCS on {}, Newport XPS on {}",
                at(s.gcs),
                at(s.xps)
            );
            Ok(Some(s))
        }
        Err(e) => {
            tracing::warn!("{e}: the twin runs without its hexapod");
            eprintln!("warning: {e}: the twin runs without its hexapod");
            Ok(None)
        }
    }
}

/// Addresses for reading: "192.0.2.1, 127.0.0.1".
fn addresses(a: &[std::net::IpAddr]) -> String {
    let all: Vec<String> = a.iter().map(ToString::to_string).collect();
    all.join(", ")
}
