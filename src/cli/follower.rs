//! `axiscomp follower import|map|show`: the follower's error map (`follower`), kept in the
//! store (`store::follower`). `import` reads the encoder's calibration certificate (CSV, see
//! `follower::certificate`); `map --twin` runs the stop-and-go self-calibration on the digital
//! twin's lab (`sim::follower_cal`) and combines it with a certificate; `show` prints the map
//! in use (or `--id`) and exports it as TOML or CSV. Exit codes: 2 for a bad certificate or
//! arguments, 1 for anything else.

use super::InputError;
use anyhow::{Context, Result};
use axiscomp::follower::{Certificate, FollowerMap, MapSettings};
use axiscomp::store::Store;
use clap::Subcommand;
use std::path::{Path, PathBuf};

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Import the follower encoder's calibration certificate (CSV: position_mm, error_um,
    /// direction + or -, uncertainty_um) as a map, and put it in use.
    Import(ImportArgs),
    /// Map the follower by the stop-and-go self-calibration (on the digital twin), with a
    /// certificate for the length reference, and put the map in use.
    Map(MapArgs),
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
    /// Run on the digital twin's lab (virtual time): the only place it runs from the command
    /// line.
    #[arg(long)]
    pub twin: bool,
    /// The twin's seed.
    #[arg(long, default_value_t = 2026)]
    pub seed: u64,
    /// The twin's axis length (mm; the follower's travel is the axis').
    #[arg(long, default_value_t = 1000.0)]
    pub length_mm: f64,
    /// The carriage's step between stops (mm).
    #[arg(long, default_value_t = 3.75)]
    pub step_mm: f64,
    /// Passes over the travel.
    #[arg(long, default_value_t = 4)]
    pub passes: usize,
    /// Frames averaged each side of a handover.
    #[arg(long, default_value_t = 1000)]
    pub frames: usize,
    /// The follower's screw lead (mm).
    #[arg(long, default_value_t = 5.0)]
    pub lead_mm: f64,
    /// The encoder's certificate (default: the twin's own, written beside the store).
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
    /// Write the map as TOML (every term, reads back exactly).
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
        Command::Import(a) => {
            let cert = read_certificate(&a.certificate)?;
            let map = axiscomp::follower::build(&[], Some(&cert), &MapSettings::default())?;
            let mut store = Store::open(db_path(&a.db)?)?;
            let id = store.insert_follower_map(&map, &cert.name, !a.keep_current)?;
            print_map(id, &cert.name, &map);
            if a.keep_current {
                println!("stored; not in use (the map in use is unchanged)");
            } else {
                println!("in use from the service's next start");
            }
            Ok(())
        }
        Command::Map(a) => map(a),
        Command::Show(a) => show(a),
    }
}

fn map(a: MapArgs) -> Result<()> {
    if !a.twin {
        return Err(InputError(
            "follower map runs on the digital twin only (--twin); on a machine, the service runs it \
             with the carriage under its control"
                .into(),
        )
        .into());
    }
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
    let cal = axiscomp::sim::follower_cal::CalSpec {
        from_mm: -2.0,
        to_mm: a.length_mm + 2.0,
        step_mm: a.step_mm,
        passes: a.passes,
        average_frames: a.frames,
        ..Default::default()
    };
    let settings = MapSettings {
        lead_mm: a.lead_mm,
        ..MapSettings::default()
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
    let id = store.insert_follower_map(&out.map, &name, true)?;
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
        std::fs::write(p, rec.map.to_toml()).with_context(|| format!("writing {}", p.display()))?;
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
