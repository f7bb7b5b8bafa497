//! `axiscomp calibrate simulate|fit`.

use super::{InputError, load_layout};
use anyhow::{Context, Result};
use axiscomp::calibrate::{
    self, CalibrateOptions, CalibrationFile, PoseSample, parse_pose_csv, write_pose_csv,
};
use axiscomp::optics::Layout;
use axiscomp::sim::{Hexapod, InstallSpec, PoseWindow, Rng, TwinHead};
use axiscomp::units::{Errors6, MM_PER_UM};
use axiscomp::util::numbers;
use axiscomp::util::progress::Progress;
use clap::{Subcommand, ValueEnum};
use std::path::{Path, PathBuf};

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Generate a pose set with the digital twin: a head with random installation errors
    /// driven through random hexapod poses.
    Simulate(SimulateArgs),
    /// Fit β and offset (and the installation errors) to a pose set; print the report.
    Fit(FitArgs),
    /// Calibrate with the hexapod in the loop: drive `[hexapod]` through the pose plan, read
    /// the head through `[io]` at each pose, store as it goes (run again to resume), fit,
    /// judge on held-out poses, and write the calibration file.
    Run(RunArgs),
}

#[derive(clap::Args, Debug)]
pub struct RunArgs {
    /// The service's configuration (`[hexapod]`, `[io]`, `[head]`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// A pose plan CSV (`x_mm,y_mm,z_mm,u_deg,v_deg,w_deg[,travel_mm,follower_mm]`, every pose
    /// at one travel and follower position); default:
    /// `--poses` poses over ±100 µm, ±2 mm positioning (the follower window), ±60″.
    #[arg(long)]
    pub plan: Option<PathBuf>,
    /// Poses of the default plan (without --plan).
    #[arg(long, default_value_t = 200)]
    pub poses: usize,
    /// Where the run's files go (resumed when they exist).
    #[arg(long, default_value = "calibration-run")]
    pub out: PathBuf,
    /// Hold out every n-th pose to judge the fit.
    #[arg(long, default_value_t = 5)]
    pub holdout_every: usize,
}

#[derive(clap::Args, Debug)]
pub struct SimulateArgs {
    /// Number of poses.
    #[arg(long)]
    pub poses: usize,
    /// The head `axiscomp sim --config CONFIG` runs (its seed, installation errors, gains and
    /// noise; the layout it names): the pose set to calibrate that twin with. Without it, a
    /// head of its own is drawn from `--seed` and the `--install-*` flags.
    #[arg(long, value_name = "CONFIG", conflicts_with_all = ["install_error_mm", "install_error_deg", "gain_error", "noise_um", "layout"])]
    pub twin: Option<PathBuf>,
    /// Seed of the twin (head and poses); with `--twin`, of the poses only.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Installation offset of every element, uniform within ± (mm).
    #[arg(long, default_value_t = 0.5)]
    pub install_error_mm: f64,
    /// Installation tilt of every element, uniform within ± (degrees).
    #[arg(long, default_value_t = 0.2)]
    pub install_error_deg: f64,
    /// PSD gain error, uniform within ± (relative, e.g. 0.01 for 1 %).
    #[arg(long, default_value_t = 0.0)]
    pub gain_error: f64,
    /// PSD noise per axis (µm, standard deviation).
    #[arg(long, default_value_t = 1.0)]
    pub noise_um: f64,
    /// Bench positions along the travel (mm), comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "0")]
    pub travel_mm: Vec<f64>,
    /// Half-range of the straightness poses (µm).
    #[arg(long, default_value_t = 100.0)]
    pub window_um: f64,
    /// Half-range of the positioning poses: the follower window (mm).
    #[arg(long, default_value_t = 2.0)]
    pub window_positioning_mm: f64,
    /// Half-range of the angular poses (arcsec).
    #[arg(long, default_value_t = 60.0)]
    pub window_arcsec: f64,
    /// Layout file (default: configs/optics/reference.toml).
    #[arg(long)]
    pub layout: Option<PathBuf>,
    /// Output CSV.
    #[arg(long)]
    pub output: PathBuf,
}

#[derive(Clone, Copy, Debug, ValueEnum, PartialEq)]
pub enum FitMethod {
    /// Linear β and offset, then the installation errors by Levenberg–Marquardt.
    Model,
    /// Linear β and offset only (the paper's method with an offset).
    Linear,
}

#[derive(clap::Args, Debug)]
pub struct FitArgs {
    /// Pose-set CSV.
    #[arg(long)]
    pub input: PathBuf,
    /// Calibration file to write (TOML).
    #[arg(long)]
    pub output: PathBuf,
    /// Layout file (default: configs/optics/reference.toml).
    #[arg(long)]
    pub layout: Option<PathBuf>,
    /// The fit: the model's installation errors, or the paper's linear β.
    #[arg(long, value_enum, default_value_t = FitMethod::Model)]
    pub method: FitMethod,
    /// Hold out every n-th pose to judge the fit (0: none).
    #[arg(long, default_value_t = 5)]
    pub holdout_every: usize,
}

pub fn run(c: Command) -> Result<()> {
    match c {
        Command::Simulate(a) => simulate(a),
        Command::Fit(a) => fit(a),
        Command::Run(a) => hexapod_run(a),
    }
}

fn positive(name: &str, v: f64, zero_ok: bool) -> Result<()> {
    if v.is_finite() && (v > 0.0 || (zero_ok && v == 0.0)) {
        Ok(())
    } else {
        Err(InputError(format!(
            "{name} {v}: give a {} number",
            if zero_ok { "non-negative" } else { "positive" }
        ))
        .into())
    }
}

/// Build the twin head the way `simulate` and `demo` do.
pub fn twin_head(
    layout: &Layout,
    spec: &InstallSpec,
    noise_um: f64,
    rng: &mut Rng,
) -> Result<TwinHead> {
    Ok(TwinHead::random(layout, spec, noise_um * MM_PER_UM, rng)?)
}

/// Comment lines recording the twin's true installation errors.
pub fn truth_comments(head: &TwinHead) -> Vec<String> {
    head.install
        .to_named(&head.nominal)
        .iter()
        .map(|(name, e)| {
            format!(
                "truth {name}: offset_mm={} tilt_deg={} gain_error={}",
                numbers(&e.offset),
                numbers(&e.tilt.map(f64::to_degrees)),
                numbers(&e.gain_error)
            )
        })
        .collect()
}

fn simulate(a: SimulateArgs) -> Result<()> {
    if a.poses == 0 {
        return Err(InputError("--poses 0: give the number of poses to generate".into()).into());
    }
    positive("--install-error-mm", a.install_error_mm, true)?;
    positive("--install-error-deg", a.install_error_deg, true)?;
    positive("--gain-error", a.gain_error, true)?;
    positive("--noise-um", a.noise_um, true)?;
    positive("--window-um", a.window_um, false)?;
    positive("--window-positioning-mm", a.window_positioning_mm, false)?;
    positive("--window-arcsec", a.window_arcsec, false)?;
    for t in &a.travel_mm {
        if !t.is_finite() {
            return Err(InputError(format!("--travel-mm {t}: give finite positions in mm")).into());
        }
    }
    let rng = Rng::new(a.seed);
    let (layout, head, origin) = match &a.twin {
        Some(config) => {
            let (layout, spec) = axiscomp::sim::config::load(config)?;
            let head = axiscomp::sim::plant::Plant::draw_head(&layout, &spec.plant)?;
            let origin = format!(
                "the head of `axiscomp sim --config {}` (seed {})",
                config.display(),
                spec.plant.seed
            );
            (layout, head, origin)
        }
        None => {
            let layout = load_layout(a.layout.as_deref())?;
            let spec = InstallSpec {
                offset_mm: a.install_error_mm,
                tilt_deg: a.install_error_deg,
                gain_error: a.gain_error,
            };
            let head = twin_head(&layout, &spec, a.noise_um, &mut rng.fork(1))?;
            let origin = format!(
                "--seed {} --install-error-mm {} --install-error-deg {} --gain-error {} --noise-um {}",
                a.seed, a.install_error_mm, a.install_error_deg, a.gain_error, a.noise_um
            );
            (layout, head, origin)
        }
    };
    let window = PoseWindow {
        half_range: Errors6::from_user([
            a.window_um,
            a.window_positioning_mm * 1000.0,
            a.window_um,
            a.window_arcsec,
            a.window_arcsec,
            a.window_arcsec,
        ]),
        travels: a.travel_mm.clone(),
    };
    let poses = window.draw(a.poses, &mut rng.fork(2));
    let mut progress = Progress::new("hexapod poses", poses.len() as u64);
    let (samples, skipped) =
        Hexapod::default().acquire(&head, &poses, &mut rng.fork(3), &mut progress);
    progress.finish(&format!(
        "{} poses, {skipped} without a reading",
        samples.len()
    ));
    let mut comments = vec![format!(
        "axiscomp calibrate simulate --poses {} (poses seed {}): {origin} (layout {} {})",
        a.poses,
        a.seed,
        layout.name,
        layout.hash()
    )];
    comments.extend(truth_comments(&head));
    std::fs::write(&a.output, write_pose_csv(&samples, &comments))
        .with_context(|| format!("writing {}", a.output.display()))?;
    eprintln!("wrote {} poses to {}", samples.len(), a.output.display());
    Ok(())
}

/// Read a pose-set CSV file.
pub fn read_pose_file(path: &Path) -> Result<Vec<PoseSample>> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| InputError(format!("{}: cannot read it: {e}", path.display())))?;
    Ok(parse_pose_csv(&text, &path.display().to_string())?)
}

fn fit(a: FitArgs) -> Result<()> {
    let layout = load_layout(a.layout.as_deref())?;
    let samples = read_pose_file(&a.input)?;
    let opts = CalibrateOptions {
        holdout_every: a.holdout_every,
        model: a.method == FitMethod::Model,
        ..CalibrateOptions::default()
    };
    let mut progress = Progress::new("model fit (iterations)", opts.model_options.max_iter as u64);
    let mut last_iter = 0;
    let cal = calibrate::calibrate(&samples, &layout, &opts, &mut |it, _cost| {
        last_iter = it;
        progress.set(it as u64);
    })?;
    progress.finish(&format!("{last_iter} iterations"));
    let bound = cal.crlb(&layout)?;
    print!("{}", cal.report(Some(&bound)));
    CalibrationFile::from_calibration(&cal, &layout).save(&a.output)?;
    eprintln!("wrote {}", a.output.display());
    Ok(())
}

fn duration_text(d: std::time::Duration) -> String {
    let s = d.as_secs_f64();
    if s < 90.0 {
        format!("{s:.0} s")
    } else {
        format!("{} min {:02.0} s", (s / 60.0).floor(), s % 60.0)
    }
}

fn hexapod_run(a: RunArgs) -> Result<()> {
    use axiscomp::hexapod::plan::{PlanSpec, PosePlan};
    use axiscomp::hexapod::session::{self, SessionEvent};
    use axiscomp::units::{DOF_NAMES, DOF_TO_USER, DOF_UNITS};
    let wall = std::time::Instant::now();
    let settings = super::service::settings(a.config.as_deref())?;
    let hx = settings.hexapod.clone();
    session::driver(&hx).map_err(InputError)?;
    let plan = match &a.plan {
        Some(p) => {
            let text = std::fs::read_to_string(p)
                .map_err(|e| InputError(format!("{}: cannot read it: {e}", p.display())))?;
            PosePlan::parse(&text, &p.display().to_string())
                .map_err(|e| InputError(e.to_string()))?
        }
        None => {
            if a.poses < 20 {
                return Err(InputError(format!("--poses {}: give at least 20", a.poses)).into());
            }
            PosePlan::generate(&PlanSpec {
                poses: a.poses,
                ..PlanSpec::default()
            })
        }
    };
    // Refused before anything connects or moves.
    plan.check(&hx.workspace)
        .and_then(|()| plan.station().map(|_| ()))
        .map_err(|e| InputError(e.to_string()))?;
    let prepared = axiscomp::service::prepare(&settings).map_err(|e| InputError(e.to_string()))?;
    let layout = prepared.layout.clone();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let total = plan.poses.len();
    let step = (total / 20).max(1);
    let mut fit_progress: Option<Progress> = None;
    let mut sigint = {
        let _in_runtime = rt.enter();
        tokio::signal::unix::signal(tokio::signal::unix::SignalKind::interrupt())
            .context("installing the Ctrl-C handler")?
    };
    let out = rt.block_on(async {
        let mut map = prepared.map.clone();
        if settings.io.unit != 0 {
            map.unit_id = settings.io.unit;
        }
        let acq = axiscomp::acquire::Acquisition::spawn_paced(
            settings.io.link.clone(),
            std::sync::Arc::new(map),
            settings.io.acquire,
        );
        let mut rx = acq.subscribe();
        // Ctrl-C halts the hexapod before its next pose; what is stored stays (the procedure
        // says so, and how to resume).
        let (stop_tx, stop) = tokio::sync::watch::channel(false);
        let out_dir = a.out.display().to_string();
        tokio::spawn(async move {
            if sigint.recv().await.is_some() {
                eprintln!(
                    "Ctrl-C: halting the hexapod before its next pose; the poses taken so far \
                     stay in {out_dir} (Ctrl-C again leaves at once)"
                );
                let _ = stop_tx.send(true);
            }
            if sigint.recv().await.is_some() {
                eprintln!("Ctrl-C again: leaving now; the poses taken so far stay in {out_dir}");
                std::process::exit(130);
            }
        });
        let r = session::run(
            &hx,
            &mut rx,
            &mut axiscomp::hexapod::bench::Stay,
            &plan,
            &a.out,
            &layout,
            a.holdout_every,
            &stop,
            &mut |e| match e {
                SessionEvent::Resuming { stored, total } => eprintln!(
                    "resuming {}: {stored} of {total} poses stored",
                    a.out.display()
                ),
                SessionEvent::Connected { controller, id } => {
                    eprintln!("{controller} at {}: {id}", hx.address)
                }
                SessionEvent::Pose(p) => {
                    if p.done % step == 0 || p.done == p.total {
                        eprintln!(
                            "hexapod pose {}/{} ({:.0} %), machine time {}, ETA {}",
                            p.done,
                            p.total,
                            100.0 * p.done as f64 / p.total as f64,
                            duration_text(p.machine),
                            p.eta.map(duration_text).unwrap_or_else(|| "?".into())
                        );
                    }
                }
                SessionEvent::Fitting { iteration } => fit_progress
                    .get_or_insert_with(|| {
                        Progress::new(
                            "model fit (iterations)",
                            CalibrateOptions::default().model_options.max_iter as u64,
                        )
                    })
                    .set(iteration as u64),
            },
        )
        .await;
        acq.stop();
        r
    })?;
    if let Some(p) = fit_progress.take() {
        p.finish("done");
    }
    let j = &out.judgement;
    let bound = j.calibration.crlb(&layout)?;
    print!("{}", j.calibration.report(Some(&bound)));
    println!(
        "held out: {} poses, {} frames decoupled one by one against the reached poses ({} untraceable, left out)",
        j.holdout_poses, j.frames, j.untraceable
    );
    println!(
        "  {:<24}{}",
        "DOF",
        DOF_NAMES.map(|n| format!("{n:>9}")).join("")
    );
    let row = |label: &str, v: [f64; 6]| {
        let cells: String = (0..6)
            .map(|k| format!("{:>9.3}", v[k] * DOF_TO_USER[k]))
            .collect();
        println!("  {label:<24}{cells}");
    };
    row("hold-out RMS, 1 frame", j.holdout_rms);
    row("Cramér–Rao, 1 frame", j.crlb);
    println!(
        "  {:<24}{}",
        "ratio",
        j.ratio().map(|r| format!("{r:>9.3}")).join("")
    );
    println!("  units: {}", DOF_UNITS.join(", "));
    let report = out.report;
    println!(
        "poses: {} this run, {} resumed; machine time {}, wall time {}; {} link reconnects",
        report.taken,
        report.resumed_from,
        duration_text(report.machine),
        duration_text(wall.elapsed()),
        report.reconnects
    );
    println!(
        "wrote {} and the pose set {} (fit, accept or reject it on the console's Calibrate screen)",
        out.calibration_file.display(),
        out.pose_file.display()
    );
    Ok(())
}
