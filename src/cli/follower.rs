//! `axiscomp follower import|map|level|show`: the follower's error map (`follower`), kept in the
//! store (`store::follower`). `import` reads the encoder's calibration certificate (CSV, see
//! `follower::certificate`) and hands it to the running service, which stores and applies it
//! at once (with no service running, or `--db`, it goes into the store directly); `map` starts
//! the stop-and-go self-calibration on the running service (`service::follower_map`: its part
//! program on the CNC) and follows it to the map, or `--status`, `--stop`, `--finish` it;
//! `map --twin` runs it on the digital twin's lab instead (`sim::follower_cal`); `level` reads a
//! level at stations and refits the map (`cli::follower_level`); `show` prints
//! the map in use (or `--id`) and exports it as TOML or CSV. Exit codes: 2 for a bad
//! certificate, arguments or a refused request, 1 for anything else.

use super::InputError;
use super::client::{Leave, duration_words, follow, refused, runtime, socket_path};
use anyhow::{Context, Result};
use axiscomp::follower::{Certificate, FollowerMap};
use axiscomp::service::api::Request;
use axiscomp::service::control::{Client, ClientError};
use axiscomp::store::Store;
use clap::Subcommand;
use std::path::{Path, PathBuf};

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Import the follower encoder's calibration certificate (CSV: position_mm, error_um,
    /// direction + or -, uncertainty_um) as a map, and put it in use: through the running
    /// service (applied at once), else into the store.
    Import(ImportArgs),
    /// Map the follower by the stop-and-go self-calibration on the running service (its part
    /// program on the CNC; or --twin: on the digital twin's lab), with the certificate for the
    /// length reference, and put the map in use.
    Map(MapArgs),
    /// Read a level at stations along the follower's map on the running service, and refit
    /// the map in use with them (its self-calibration's steps + the stations): start, or
    /// --status, --stop, --finish, or --reading ARCSEC (a level read by hand).
    Level(super::follower_level::LevelArgs),
    /// The map in use (or --id), every stored map, and exports.
    Show(ShowArgs),
}

#[derive(clap::Args, Debug)]
pub struct DbArgs {
    /// The store (default: axiscomp.db in the configured state directory).
    #[arg(long)]
    pub db: Option<PathBuf>,
    /// The service's configuration, for the state directory (default: /etc/axiscomp/axiscomp.toml).
    #[arg(long)]
    pub config: Option<PathBuf>,
}

#[derive(clap::Args, Debug)]
pub struct ImportArgs {
    #[command(flatten)]
    pub db: DbArgs,
    /// The running service's control socket (default: from the configuration); not used with
    /// --db.
    #[arg(long)]
    pub socket: Option<PathBuf>,
    /// The certificate (CSV).
    pub certificate: PathBuf,
    /// Store it without putting it in use.
    #[arg(long)]
    pub keep_current: bool,
}

#[derive(clap::Args, Debug)]
pub struct MapArgs {
    #[command(flatten)]
    pub db: DbArgs,
    /// The running service's control socket (default: from the configuration).
    #[arg(long)]
    pub socket: Option<PathBuf>,
    /// Run on the digital twin's lab (virtual time) instead of the running service.
    #[arg(long, conflicts_with_all = ["status", "stop", "finish", "detach"])]
    pub twin: bool,
    /// Where the running service's mapping is (stops, steps, time left), then exit.
    #[arg(long, conflicts_with_all = ["stop", "finish"])]
    pub status: bool,
    /// Stop the running service's mapping: nothing is stored.
    #[arg(long, conflicts_with = "finish")]
    pub stop: bool,
    /// Build the map now from the steps so far (with a CNC the service does not drive, the
    /// mapping ends by itself once every planned stop was seen).
    #[arg(long)]
    pub finish: bool,
    /// Start the mapping and return at once (follow it with --status).
    #[arg(long)]
    pub detach: bool,
    /// The span's near end on the service (mm; default: the axis' last alignment).
    #[arg(long, allow_negative_numbers = true)]
    pub from_mm: Option<f64>,
    /// The span's far end on the service (mm; default: the axis' last alignment).
    #[arg(long, allow_negative_numbers = true)]
    pub to_mm: Option<f64>,
    /// The machine axis on the service: its alignment, the program's axis letter (default X).
    #[arg(long)]
    pub axis: Option<String>,
    /// The twin's seed.
    #[arg(long, default_value_t = 2026)]
    pub seed: u64,
    /// The twin's axis length (mm; the follower's travel is the axis').
    #[arg(long, default_value_t = 1000.0)]
    pub length_mm: f64,
    /// The carriage's step between stops (mm; default 3.75).
    #[arg(long)]
    pub step_mm: Option<f64>,
    /// Passes over the travel (default 4).
    #[arg(long)]
    pub passes: Option<usize>,
    /// Frames averaged each side of a handover (default 1000).
    #[arg(long)]
    pub frames: Option<usize>,
    /// The follower's screw lead (mm; default 5).
    #[arg(long)]
    pub lead_mm: Option<f64>,
    /// A back-and-forth probe every this many stops of a pass (default 13; 0: none).
    #[arg(long)]
    pub probe_every: Option<usize>,
    /// The carriage's feed on the service (mm/min; default 2000).
    #[arg(long)]
    pub feed_mm_min: Option<f64>,
    /// The program's dialect on the service: iso, siemens, heidenhain or linuxcnc (default:
    /// the configuration's).
    #[arg(long)]
    pub dialect: Option<String>,
    /// The encoder's certificate (default: on the twin its own, written beside the store; on
    /// the service the one kept with the map in use; a file the service can read).
    #[arg(long)]
    pub certificate: Option<PathBuf>,
}

#[derive(clap::Args, Debug)]
pub struct ShowArgs {
    #[command(flatten)]
    pub db: DbArgs,
    /// A stored map instead of the one in use.
    #[arg(long)]
    pub id: Option<i64>,
    /// Write the map as TOML (every term and the certificate it was built from; reads back
    /// exactly).
    #[arg(long)]
    pub toml: Option<PathBuf>,
    /// Write the map as CSV every --step-mm.
    #[arg(long)]
    pub csv: Option<PathBuf>,
    /// The CSV's spacing (mm).
    #[arg(long, default_value_t = 1.0)]
    pub step_mm: f64,
}

fn db_path(a: &DbArgs) -> Result<PathBuf> {
    Ok(match &a.db {
        Some(p) => p.clone(),
        None => super::service::settings(a.config.as_deref())?
            .service
            .state_dir
            .join("axiscomp.db"),
    })
}

fn read_certificate(path: &Path) -> Result<Certificate> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading the certificate {}", path.display()))?;
    Certificate::parse(&text, &path.display().to_string())
        .map_err(|e| InputError(e.to_string()).into())
}

fn print_map(id: i64, name: &str, map: &FollowerMap) {
    println!("follower map {id} ({name}):");
    for l in map.summary() {
        println!("  {l}");
    }
}

pub fn run(c: Command) -> Result<()> {
    match c {
        Command::Import(a) => import(a),
        Command::Map(a) if a.twin => map_twin(a),
        Command::Map(a) => map_on_service(a),
        Command::Level(a) => super::follower_level::run(a),
        Command::Show(a) => show(a),
    }
}

fn import(a: ImportArgs) -> Result<()> {
    let text = std::fs::read_to_string(&a.certificate)
        .with_context(|| format!("reading the certificate {}", a.certificate.display()))?;
    let name = a.certificate.display().to_string();
    let cert = Certificate::parse(&text, &name).map_err(|e| InputError(e.to_string()))?;
    if a.db.db.is_none() {
        let socket = socket_path(a.socket.as_deref(), a.db.config.as_deref())?;
        let req = Request::FollowerCertificate(axiscomp::service::api::CertificateImport {
            csv: Some(text),
            name: Some(name),
            keep_current: a.keep_current,
            ..Default::default()
        });
        let sent = runtime()?.block_on(async {
            let mut c = Client::connect(&socket).await?;
            c.request(&req).await.map(Some)
        });
        match sent {
            Ok(Some(v)) => {
                let id = v["id"].as_i64().unwrap_or(0);
                println!(
                    "follower map {id} ({}):",
                    v["name"].as_str().unwrap_or_default()
                );
                for l in v["summary"].as_array().into_iter().flatten() {
                    println!("  {}", l.as_str().unwrap_or_default());
                }
                if let Some(j) = v["joined_with"].as_i64() {
                    println!("joined with the self-calibration of map {j} (the map in use)");
                }
                println!(
                    "stored by the running service ({}); {}",
                    socket.display(),
                    v["zero"].as_str().unwrap_or_default()
                );
                return Ok(());
            }
            Ok(None) => {}
            // No service there: the store directly.
            Err(ClientError::Connect { .. }) => println!(
                "no service answers at {}: the certificate goes into the store directly",
                socket.display()
            ),
            Err(e) => return Err(refused(e)),
        }
    }
    let path = db_path(&a.db)?;
    let mut store = Store::open(&path)?;
    let (stored, name, joined) =
        axiscomp::service::follower::certificate_map(&store, &cert).map_err(anyhow::Error::msg)?;
    let id = store.insert_stored_follower_map(&stored, &name, !a.keep_current)?;
    print_map(id, &name, &stored.map);
    if let Some(j) = joined {
        println!("joined with the self-calibration of map {j} (the map in use)");
    }
    if a.keep_current {
        println!(
            "stored in {}; not in use (the map in use is unchanged)",
            path.display()
        );
    } else {
        println!(
            "stored in {}; in use from the service's next start",
            path.display()
        );
    }
    Ok(())
}

/// The mapping's progress on one line.
fn progress_line(v: &serde_json::Value) -> String {
    let n = |k: &str| v[k].as_u64().unwrap_or(0);
    let t = |k: &str| duration_words(v[k].as_f64().unwrap_or(0.0));
    format!(
        "{}: stop {} of {}, {} steps kept, {} skipped; {} of machine time, {} left",
        v["state"].as_str().unwrap_or("?"),
        n("stops_done"),
        n("stops_planned"),
        n("steps_kept"),
        n("skipped"),
        t("elapsed_s"),
        t("left_s")
    )
}

/// The mapping's state as `follower_map_status` gives it.
fn print_status(v: &serde_json::Value) {
    let state = v["state"].as_str().unwrap_or("?");
    let refused = &v["last_refused"];
    if state == "idle" {
        match (refused["reason"].as_str(), refused["unix_us"].as_i64()) {
            (Some(why), Some(t)) => println!(
                "no follower mapping since the service started; the last start, at {}, was refused: {why}",
                axiscomp::store::iso_utc(t)
                    .replace('T', " ")
                    .replace('Z', " UTC")
            ),
            _ => println!("no follower mapping since the service started"),
        }
        return;
    }
    println!("follower mapping {}", progress_line(v));
    println!(
        "  axis {} {:.1} to {:.1} mm by {} mm, {} passes, {} frames a side; started {} by {}",
        v["axis"].as_str().unwrap_or_default(),
        v["from_mm"].as_f64().unwrap_or(f64::NAN),
        v["to_mm"].as_f64().unwrap_or(f64::NAN),
        v["step_mm"].as_f64().unwrap_or(f64::NAN),
        v["passes"].as_u64().unwrap_or(0),
        v["frames"].as_u64().unwrap_or(0),
        v["started"].as_str().unwrap_or_default(),
        v["started_by"].as_str().unwrap_or_default()
    );
    for (k, what) in [
        ("dwell", ""),
        ("program", "program: "),
        ("cnc", "CNC: "),
        ("certificate", "certificate: "),
    ] {
        if let Some(t) = v[k].as_str().filter(|t| !t.is_empty()) {
            println!("  {what}{t}");
        }
    }
    if let Some(n) = v["out_of_plan"].as_u64().filter(|n| *n > 0) {
        println!(
            "  {n} steps were not the plan's moves: is the CNC running this mapping's program?"
        );
    }
    if let Some(e) = v["error"].as_str() {
        println!("  {e}");
    }
    if let Some(id) = v["map_id"].as_i64() {
        println!("  follower map {id}, in use:");
        for l in v["summary"].as_array().into_iter().flatten() {
            println!("    {}", l.as_str().unwrap_or_default());
        }
    }
}

/// How a finished mapping ends the command: done is success, anything else an error.
fn outcome(v: &serde_json::Value) -> Result<()> {
    match v["state"].as_str() {
        Some("done") => Ok(()),
        Some(s) => Err(anyhow::anyhow!(
            "the follower mapping {s}: {}",
            v["error"].as_str().unwrap_or("no map was stored")
        )),
        None => Err(anyhow::anyhow!("the service's reply has no state: {v}")),
    }
}

fn map_on_service(a: MapArgs) -> Result<()> {
    let socket = socket_path(a.socket.as_deref(), a.db.config.as_deref())?;
    let certificate = match &a.certificate {
        Some(p) => Some(
            std::fs::canonicalize(p)
                .with_context(|| format!("the certificate {}", p.display()))?
                .display()
                .to_string(),
        ),
        None => None,
    };
    let req = axiscomp::service::api::MappingRequest {
        from_mm: a.from_mm,
        to_mm: a.to_mm,
        step_mm: a.step_mm,
        passes: a.passes,
        frames: a.frames,
        lead_mm: a.lead_mm,
        probe_every: a.probe_every,
        feed_mm_min: a.feed_mm_min,
        axis: a.axis.clone(),
        dialect: a.dialect.clone(),
        certificate,
    };
    runtime()?.block_on(async move {
        let mut c = Client::connect(&socket).await?;
        if a.status {
            let v = c.request(&Request::FollowerMapStatus).await?;
            super::stdout_closes_quietly();
            print_status(&v);
            return Ok(());
        }
        if a.stop || a.finish {
            let r = if a.stop {
                Request::FollowerMapStop
            } else {
                Request::FollowerMapFinish
            };
            let v = c.request(&r).await.map_err(refused)?;
            print_status(&v);
            return if a.stop { Ok(()) } else { outcome(&v) };
        }
        let mut leave = Leave::listen(
            "the follower mapping goes on in the service; follow it with: axiscomp follower map \
             --status; stop it with: axiscomp follower map --stop"
                .into(),
        )?;
        let v = c
            .request(&Request::FollowerMapStart(req))
            .await
            .map_err(refused)?;
        print_status(&v);
        if a.detach {
            println!("follow it with: axiscomp follower map --status");
            return Ok(());
        }
        let running = |v: &serde_json::Value| {
            matches!(
                v["state"].as_str(),
                Some("approaching" | "mapping" | "finishing")
            )
        };
        let v = follow(
            &mut c,
            &Request::FollowerMapStatus,
            progress_line,
            running,
            &mut leave,
        )
        .await?;
        print_status(&v);
        outcome(&v)
    })
}

fn map_twin(a: MapArgs) -> Result<()> {
    if !(a.length_mm >= 20.0 && a.length_mm <= 2000.0) {
        return Err(InputError(format!("--length-mm {}: give 20 to 2000 mm", a.length_mm)).into());
    }
    let db = db_path(&a.db)?;
    let certificate = a.certificate.as_deref().map(read_certificate).transpose()?;
    let mut plant = axiscomp::sim::plant::PlantSpec {
        seed: a.seed,
        ..Default::default()
    };
    plant.axis.length_mm = a.length_mm;
    plant.install.offset_mm = 0.0;
    plant.install.tilt_deg = 0.0;
    let d = axiscomp::sim::follower_cal::CalSpec::default();
    let cal = axiscomp::sim::follower_cal::CalSpec {
        from_mm: -2.0,
        to_mm: a.length_mm + 2.0,
        step_mm: a.step_mm.unwrap_or(d.step_mm),
        passes: a.passes.unwrap_or(d.passes),
        average_frames: a.frames.unwrap_or(d.average_frames),
        probe_every: a.probe_every.unwrap_or(d.probe_every),
    };
    let settings = axiscomp::follower::MapSettings {
        lead_mm: a
            .lead_mm
            .unwrap_or(axiscomp::follower::MapSettings::default().lead_mm),
        ..Default::default()
    };
    let level = Some(axiscomp::sim::follower_cal::LevelSpec::default());
    let out = axiscomp::sim::follower_cal::map_twin(
        plant,
        &cal,
        certificate,
        &settings,
        level,
        |i, n| eprint!("\rstop {i} of {n}"),
    )
    .map_err(|e| match e {
        axiscomp::sim::follower_cal::MapTwinError::Lab(axiscomp::sim::lab::LabError::Setup(s)) => {
            anyhow::Error::from(InputError(s.to_string()))
        }
        e => e.into(),
    })?;
    eprintln!();
    let name = match (&out.certificate_text, &a.certificate) {
        (Some(text), _) => {
            let path = db.with_file_name("twin-certificate.csv");
            std::fs::write(&path, text)
                .with_context(|| format!("writing the twin's certificate {}", path.display()))?;
            println!("the twin's certificate: {}", path.display());
            format!(
                "self-calibration on the twin (seed {}) + {}",
                a.seed,
                path.display()
            )
        }
        (None, Some(p)) => format!(
            "self-calibration on the twin (seed {}) + {}",
            a.seed,
            p.display()
        ),
        (None, None) => format!("self-calibration on the twin (seed {})", a.seed),
    };
    let mut store = Store::open(&db)?;
    let stored = axiscomp::follower::StoredMap {
        map: out.map.clone(),
        certificate: Some(out.certificate.clone()),
        steps: Some(axiscomp::follower::StoredSteps {
            settings,
            steps: out.run.steps.clone(),
        }),
    };
    let id = store.insert_stored_follower_map(&stored, &name, true)?;
    print_map(id, &name, &out.map);
    println!(
        "{} steps in {:.1} min of machine time; in use from the service's next start",
        out.run.steps.len(),
        out.run.machine_time.as_secs_f64() / 60.0
    );
    Ok(())
}

fn show(a: ShowArgs) -> Result<()> {
    let path = db_path(&a.db)?;
    if !path.exists() {
        return Err(InputError(format!(
            "{}: no store there; give --db or --config",
            path.display()
        ))
        .into());
    }
    let store = Store::open_read_only(&path)?;
    let rec = match a.id {
        Some(id) => Some(store.follower_map(id)?),
        None => store.follower_map_in_use()?,
    };
    for m in store.follower_maps()? {
        println!(
            "{}{:>4}  {}  {:<16}  {}",
            if m.in_use { "*" } else { " " },
            m.id,
            axiscomp::util::time::rfc3339(m.created_us.div_euclid(1_000_000)),
            m.source,
            m.name
        );
    }
    let Some(rec) = rec else {
        println!("no follower map in use: tracking takes the follower's encoder as it reads");
        return Ok(());
    };
    print_map(rec.id, &rec.name, &rec.map);
    if let Some(p) = &a.toml {
        let text = axiscomp::follower::StoredMap {
            map: rec.map.clone(),
            certificate: rec.certificate.clone(),
            steps: rec.steps.clone(),
        }
        .to_toml();
        std::fs::write(p, text).with_context(|| format!("writing {}", p.display()))?;
        println!("written: {}", p.display());
    }
    if let Some(p) = &a.csv {
        if a.step_mm.is_nan() || a.step_mm <= 0.0 {
            return Err(
                InputError(format!("--step-mm {}: give a positive step", a.step_mm)).into(),
            );
        }
        std::fs::write(p, rec.map.to_csv(a.step_mm))
            .with_context(|| format!("writing {}", p.display()))?;
        println!("written: {}", p.display());
    }
    Ok(())
}
