//! `axiscomp demo`: the whole loop on the built-in digital twin.
//!
//! 1. Calibrate: the twin's head, with installation errors, on the simulated hexapod; judged on
//!    independent hold-out poses against the Cramér–Rao bound.
//! 2. Align and measure: the head mounted on the twin's axis as a technician first mounts it
//!    (by eye, within 0.3° and 2 mm), aligned by following the advice `axiscomp align` gives
//!    from the spots at both ends of the travel; then the ISO 230-2 cycle (the service's
//!    pipeline and run machine, CANopen follower, the CNC running the generated program) on a
//!    simulated clock.
//! 3. Tables: positioning (bidirectional) and both straightnesses, published over Modbus TCP
//!    into the twin's PLC, which applies them to the axis.
//! 4. Verify: the same cycle on the compensated axis; the ISO figures before and after for
//!    every error, and the report (HTML, Markdown, plots, tables, the store) in `--out`.

use super::load_layout;
use anyhow::{Context, Result};
use axiscomp::comp::{PositioningMode, neutral};
use axiscomp::evaluate::{EvalOptions, ReferenceLine, evaluate_captures};
use axiscomp::plc::CncMap;
use axiscomp::report::runs::{run_report, series};
use axiscomp::report::{Comparison, Dof, RunMeta, write_run_report};
use axiscomp::run::program::CaptureMode;
use axiscomp::run::{Capture, Dialect, Direction, Plan, PlanSpec};
use axiscomp::sim::InstallSpec;
use axiscomp::sim::axis::AxisSpec;
use axiscomp::sim::closed_loop::{self, Figures, LoopResult, LoopSpec, Pass, Step};
use axiscomp::sim::lab::LabSpec;
use axiscomp::sim::plant::{MountSpec, Plant, PlantSpec};
use axiscomp::sim::study::{StudyResult, StudySpec, study_head};
use axiscomp::store::{NewRun, RunId, RunState, Store};
use axiscomp::units::{DOF_NAMES, DOF_TO_USER, DOF_UNITS};
use axiscomp::util::progress::Progress;
use std::path::{Path, PathBuf};
use std::time::Duration;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Seed of the twin.
    #[arg(long, default_value_t = 2026)]
    pub seed: u64,
    /// Calibration poses.
    #[arg(long, default_value_t = 200)]
    pub poses: usize,
    /// Independent hold-out poses.
    #[arg(long, default_value_t = 1000)]
    pub holdout: usize,
    /// Bench positions of the hexapod along the travel (mm), comma-separated (default: the
    /// axis' start, middle and end).
    #[arg(long, value_delimiter = ',')]
    pub bench_mm: Vec<f64>,
    /// Length of the twin's axis (mm); the cycle measures all of it.
    #[arg(long, default_value_t = 1000.0)]
    pub length_mm: f64,
    /// ISO 230-2 targets.
    #[arg(long, default_value_t = 11)]
    pub targets: usize,
    /// Bidirectional runs.
    #[arg(long, default_value_t = 5)]
    pub runs: u32,
    /// Feed between targets (mm/min).
    #[arg(long, default_value_t = 6000.0)]
    pub feed_mm_min: f64,
    /// Dwell at each target (s).
    #[arg(long, default_value_t = 2.0)]
    pub dwell_s: f64,
    /// Spacing of the tables in the PLC (mm).
    #[arg(long, default_value_t = 5.0)]
    pub step_mm: f64,
    /// Where the report goes.
    #[arg(long, default_value = "demo-out")]
    pub out: PathBuf,
}

pub fn run(a: Args) -> Result<()> {
    let layout = load_layout(None)?;
    let bench = if a.bench_mm.is_empty() {
        vec![0.0, a.length_mm / 2.0, a.length_mm]
    } else {
        a.bench_mm.clone()
    };
    let plant = PlantSpec {
        seed: a.seed,
        axis: AxisSpec {
            length_mm: a.length_mm,
            ..AxisSpec::default()
        },
        install: InstallSpec {
            gain_error: 0.01,
            ..InstallSpec::default()
        },
        mount: MountSpec::by_eye(),
        ..PlantSpec::default()
    };
    let study = StudySpec {
        seed: a.seed,
        install: plant.install,
        noise_mm: plant.noise_mm,
        poses: a.poses,
        holdout: a.holdout,
        holdout_travel: (0.0, a.length_mm),
        window: axiscomp::sim::PoseWindow {
            travels: bench,
            ..axiscomp::sim::PoseWindow::default()
        },
        ..StudySpec::default()
    };
    println!("axiscomp demo: the digital twin, seed {}", a.seed);
    println!("\n== 1. calibrate the head");
    let head = Plant::draw_head(&layout, &plant)?;
    println!(
        "head: layout {} with installation errors within ±{} mm / ±{}° per element, PSD gains ±{} %, noise σ = {} µm",
        layout.name,
        plant.install.offset_mm,
        plant.install.tilt_deg,
        plant.install.gain_error * 100.0,
        plant.noise_mm * 1000.0
    );
    let w = study.window.half_range.to_user();
    println!(
        "calibration: {} hexapod poses at bench positions {:?} mm (±{} µm straightness, ±{} mm positioning, ±{}″)",
        study.poses,
        study.window.travels,
        w[0],
        w[1] / 1000.0,
        w[3]
    );
    let r = study_head(head, &layout, &study, true)?;
    print!("\n{}", r.calibration.report(None));
    print_holdout(&r, &study);
    let decoupler = r.calibration.decoupler(&layout)?;

    let a_spec = plant.axis;
    println!("\n== 2. measure the axis (ISO 230-2)");
    println!(
        "axis X, {} mm: true positioning error ±{} µm with a {} µm ball-screw periodic term (lead {} mm) and {} µm backlash; straightness ±{} µm; pitch/yaw ±{}″, roll ±{}″",
        a_spec.length_mm,
        a_spec.positioning_um,
        a_spec.periodic_um,
        a_spec.lead_mm,
        a_spec.backlash_um,
        a_spec.straightness_um,
        a_spec.pitch_yaw_arcsec,
        a_spec.roll_arcsec
    );
    let plan = Plan::new(PlanSpec {
        axis: "X".into(),
        start_mm: 0.0,
        end_mm: a.length_mm,
        targets: a.targets,
        runs: a.runs,
        overrun_mm: 2.0,
        dwell_s: a.dwell_s,
        feed_mm_min: a.feed_mm_min,
        lead_mm: a_spec.lead_mm,
        reference_mm: None,
    })?;
    let targets: Vec<String> = plan.targets.iter().map(|t| format!("{t:.3}")).collect();
    println!(
        "plan: {} targets (mm) {}; {} bidirectional runs, {} s dwell, stability capture; {} captures",
        plan.targets.len(),
        targets.join(" "),
        plan.spec.runs,
        plan.spec.dwell_s,
        plan.capture_count()
    );
    let spec = LoopSpec {
        lab: LabSpec::standard(plant.clone(), Some(decoupler))?,
        plan,
        dialect: Dialect::LinuxCnc,
        mode: CaptureMode::Stability,
        positioning: PositioningMode::Bidirectional,
        straightness_line: ReferenceLine::LeastSquares,
        map: CncMap::generic()?,
        step_mm: Some(a.step_mm),
        zero_window: Duration::from_millis(500),
        align_rounds: 8,
    };
    let span = axiscomp::sim::lab::plan_span(&spec.plan);
    println!(
        "head mounted by eye (within ±{}° and ±{} mm of the axis); alignment from the spots at {:.0} and {:.0} mm, a spot at least {:.1} mm inside its PSD's edge",
        plant.mount.angle_deg, plant.mount.offset_mm, span.0, span.1, 1.0
    );
    let mut rounds = 0;
    let expected = spec.plan.capture_count() as u64;
    let mut bar: Option<Progress> = None;
    let wall = std::time::Instant::now();
    let result = closed_loop::run(&spec, |s| match s {
        Step::Aligning(r) => {
            rounds += 1;
            print_round(rounds, &r);
        }
        Step::Ready(pass) => {
            if pass == Pass::After {
                println!("\n== 4. verify: the same cycle on the compensated axis");
            }
            bar = Some(Progress::new(&format!("{pass} run, captures"), expected));
        }
        Step::Running(_, p) => {
            if let Some(b) = bar.as_mut() {
                b.set(p.captures as u64);
            }
        }
        Step::Measured(pass, n) => {
            if let Some(b) = bar.take() {
                b.finish(&format!("{n} captures"));
            }
            if pass == Pass::Before {
                println!(
                    "\n== 3. tables into the PLC (the twin's, generic map, Modbus TCP on loopback)"
                );
            }
        }
        Step::Published {
            table,
            sequence,
            points,
        } => {
            println!("published {table}: {points} points, sequence {sequence}, accepted and active")
        }
    })?;
    print_mount(&result);
    println!(
        "\n{} + {} captures in {:.0} s of machine time ({:.1} s here)",
        result.before.run.captures.len(),
        result.after.run.captures.len(),
        (result.before.run.duration + result.after.run.duration).as_secs_f64(),
        wall.elapsed().as_secs_f64()
    );

    println!("\n== 5. before and after");
    let truth = truth_figures(&result)?;
    print_figures(&result, &truth);
    let files = write_out(&a.out, &spec, &result, &truth)?;
    println!("\nreport: {} ({} files)", a.out.display(), files);
    println!(
        "  {}/after/report.html, the verification run against the first; {}/axiscomp.db: both runs (axiscomp report --db … --run 1|2)",
        a.out.display(),
        a.out.display()
    );
    Ok(())
}

/// One round of alignment as the technician reads it.
fn print_round(n: usize, r: &axiscomp::sim::lab::AlignRound) {
    let a = &r.advice;
    let state = if a.now.passed() {
        format!("check passed: {}", a.now)
    } else {
        a.now.to_string()
    };
    let angle = a
        .misalignment_urad
        .map(|[y, p]| format!("beam to travel yaw {y:+.0} µrad, pitch {p:+.0} µrad; "))
        .unwrap_or_default();
    println!("align round {n}: {angle}{state}");
    if !a.now.passed() {
        let turns: Vec<String> = a.turns.iter().map(ToString::to_string).collect();
        println!("  the technician: {}", turns.join(", "));
    }
}

/// The mount before and after the alignment, from the twin's truth.
fn print_mount(r: &LoopResult) {
    let words = |m: &axiscomp::align::Mount| {
        format!(
            "yaw {:+.0} µrad, pitch {:+.0} µrad, x {:+.3} mm, z {:+.3} mm",
            m.yaw * 1e6,
            m.pitch * 1e6,
            m.x,
            m.z
        )
    };
    println!(
        "\nthe twin's mount: before alignment {}; after {}",
        words(&r.mount[0]),
        words(&r.mount[1])
    );
}

fn print_holdout(r: &StudyResult, spec: &StudySpec) {
    println!(
        "\nhold-out: {} independent poses at random travel {}–{} mm; RMS of decoupled − true:",
        r.holdout_poses, spec.holdout_travel.0, spec.holdout_travel.1
    );
    let cols = [
        ("simulated β", &r.simulated_no_offset),
        ("sim β+zero", &r.simulated_zero_ref),
        ("linear cal", &r.linear),
    ];
    print!("{:<4}{:<7}", "DOF", "unit");
    for (name, _) in cols {
        print!("{name:>12}");
    }
    println!("{:>12}{:>12}{:>9}", "model cal", "CR bound", "ratio");
    for k in 0..6 {
        let s = DOF_TO_USER[k];
        print!("{:<4}{:<7}", DOF_NAMES[k], DOF_UNITS[k]);
        for (_, v) in cols {
            print!("{:>12.3}", v.to_array()[k] * s);
        }
        let bound = r.crlb.to_array()[k] * s;
        match &r.model {
            Some(m) => {
                let m = m.to_array()[k] * s;
                println!("{m:>12.3}{bound:>12.3}{:>9.3}", m / bound);
            }
            None => println!("{:>12}{bound:>12.3}", "-"),
        }
    }
    println!(
        "\nsimulated β: the nominal layout's β at D = 0, no offset (the paper's form); sim β+zero: with a zero\n\
         reference read at home; linear cal: calibrated β and offset (fixed over travel); model cal: the\n\
         calibrated installation errors with Gauss–Newton on the model at each travel; ratio = model / bound."
    );
}

/// The same figures computed from the twin's truth at the verification run's captures.
fn truth_figures(r: &LoopResult) -> Result<Figures> {
    let truths: Vec<Capture> = r
        .after
        .run
        .captures
        .iter()
        .map(|c| Capture {
            errors: c.truth.errors,
            ..c.capture
        })
        .collect();
    let eval = evaluate_captures(&truths, &EvalOptions::default())
        .context("evaluating the twin's truth")?;
    Ok(Figures::of(&eval, ReferenceLine::LeastSquares))
}

/// (name, unit, before, after, truth after, compensated) rows in user units.
fn rows(r: &LoopResult, truth: &Figures) -> Vec<(String, &'static str, f64, f64, f64, bool)> {
    let (b, a, t) = (&r.before.figures, &r.after.figures, truth);
    let um = 1000.0;
    let arcsec = DOF_TO_USER[3];
    let opt = |v: Option<f64>| v.unwrap_or(f64::NAN);
    vec![
        (
            "dy positioning E".into(),
            "µm",
            b.e * um,
            a.e * um,
            t.e * um,
            true,
        ),
        (
            "dy positioning M".into(),
            "µm",
            b.m * um,
            a.m * um,
            t.m * um,
            true,
        ),
        (
            "dy positioning A".into(),
            "µm",
            opt(b.a) * um,
            opt(a.a) * um,
            opt(t.a) * um,
            true,
        ),
        (
            "dy repeatability R".into(),
            "µm",
            opt(b.r) * um,
            opt(a.r) * um,
            opt(t.r) * um,
            true,
        ),
        (
            "dy reversal B".into(),
            "µm",
            opt(b.b) * um,
            opt(a.b) * um,
            opt(t.b) * um,
            true,
        ),
        (
            "dx straightness (LS)".into(),
            "µm",
            b.straightness_x * um,
            a.straightness_x * um,
            t.straightness_x * um,
            true,
        ),
        (
            "dz straightness (LS)".into(),
            "µm",
            b.straightness_z * um,
            a.straightness_z * um,
            t.straightness_z * um,
            true,
        ),
        (
            "ex pitch max − min".into(),
            "″",
            b.pitch * arcsec,
            a.pitch * arcsec,
            t.pitch * arcsec,
            false,
        ),
        (
            "ey roll max − min".into(),
            "″",
            b.roll * arcsec,
            a.roll * arcsec,
            t.roll * arcsec,
            false,
        ),
        (
            "ez yaw max − min".into(),
            "″",
            b.yaw * arcsec,
            a.yaw * arcsec,
            t.yaw * arcsec,
            false,
        ),
    ]
}

fn print_figures(r: &LoopResult, truth: &Figures) {
    println!(
        "{:<24}{:>6}{:>10}{:>10}{:>8}{:>13}",
        "figure", "unit", "before", "after", "ratio", "truth after"
    );
    for (name, unit, b, a, t, comp) in rows(r, truth) {
        let ratio = if comp && b.abs() > 0.0 {
            format!("{:.1} %", 100.0 * a / b)
        } else {
            "-".into()
        };
        println!("{name:<24}{unit:>6}{b:>10.2}{a:>10.2}{ratio:>8}{t:>13.2}");
    }
    println!(
        "\nafter: measured on the compensated axis by the same head and cycle; truth after: the same figures\n\
         from the twin's true errors at those captures (the difference is the head's own error: the follower\n\
         stage's errors between handovers, in the stated stitching uncertainty). Bidirectional R includes the\n\
         reversal at each target, so the backlash table shrinks it too. The angular errors are measured, not\n\
         compensated (no Abbe tables without a functional point): no ratio."
    );
}

/// The report directory: a run report per pass (the second compared with the first), the
/// tables, the part program, a summary, and the store with both runs.
fn write_out(dir: &Path, spec: &LoopSpec, r: &LoopResult, truth: &Figures) -> Result<usize> {
    std::fs::create_dir_all(dir)
        .with_context(|| format!("creating {}; choose another --out", dir.display()))?;
    let mut files = 0;
    let db = dir.join("axiscomp.db");
    for suffix in ["", "-wal", "-shm"] {
        let p = PathBuf::from(format!("{}{suffix}", db.display()));
        if p.exists() {
            std::fs::remove_file(&p)
                .with_context(|| format!("replacing {}; remove it by hand", p.display()))?;
        }
    }
    let mut store = Store::open(&db)?;
    files += 1;
    let before_caps: Vec<Capture> = r.before.run.captures.iter().map(|c| c.capture).collect();
    let after_caps: Vec<Capture> = r.after.run.captures.iter().map(|c| c.capture).collect();
    let mut ids = Vec::new();
    for (pass, caps) in [("before", &before_caps), ("after", &after_caps)] {
        let id = store_run(&mut store, spec, pass, caps)?;
        ids.push(id);
        let rec = store.run(id)?;
        let eval = if pass == "before" {
            &r.before.eval
        } else {
            &r.after.eval
        };
        let mut report = run_report(RunMeta::from_record(&rec), caps, eval);
        if pass == "after" {
            report.comparisons = comparisons(&before_caps, &after_caps);
        }
        files += write_run_report(&dir.join(pass), &report)?.len();
    }
    let tables = dir.join("tables");
    std::fs::create_dir_all(&tables).with_context(|| format!("creating {}", tables.display()))?;
    for t in std::iter::once(&r.tables.positioning).chain(&r.tables.straightness) {
        write(&tables.join(format!("{}.csv", t.name)), &neutral::csv(t))?;
        files += 1;
    }
    let mut plc = String::from(
        "# The tables as the PLC holds them (generic map), µm\nname,sequence,position_mm,up_um,down_um\n",
    );
    for p in &r.published {
        for (k, x) in p.table.positions().iter().enumerate() {
            let down = p.table.down_mm.as_ref().map(|d| d[k] * 1000.0);
            plc.push_str(&format!(
                "{},{},{x:.4},{:.4},{}\n",
                p.name,
                p.sequence,
                p.table.values_mm[k] * 1000.0,
                down.map(|d| format!("{d:.4}")).unwrap_or_default()
            ));
        }
    }
    write(&tables.join("plc.csv"), &plc)?;
    write(&dir.join("program.ngc"), &r.before.run.program)?;
    write(&dir.join("summary.md"), &summary(r, truth, &ids))?;
    Ok(files + 3)
}

fn store_run(store: &mut Store, spec: &LoopSpec, pass: &str, caps: &[Capture]) -> Result<RunId> {
    let id = store.create_run(&NewRun {
        axis: spec.plan.spec.axis.clone(),
        plan: serde_json::to_value(&spec.plan)?,
        config: serde_json::json!({ "twin": "axiscomp demo", "pass": pass }),
        calibration: None,
        notes: match pass {
            "before" => "demo: the axis as it is".into(),
            _ => "demo: verification with the tables active in the PLC".into(),
        },
    })?;
    store.set_run_state(id, RunState::Running)?;
    for c in caps {
        store.insert_capture(id, c)?;
    }
    store.set_run_state(id, RunState::Finished)?;
    Ok(id)
}

fn comparisons(before: &[Capture], after: &[Capture]) -> Vec<Comparison> {
    [Dof::Dx, Dof::Dy, Dof::Dz]
        .into_iter()
        .map(|dof| {
            let s = |caps: &[Capture]| -> Vec<_> {
                [Direction::Up, Direction::Down]
                    .into_iter()
                    .filter_map(|d| series(caps, dof.index(), d))
                    .collect()
            };
            Comparison {
                dof,
                before_label: "before compensation".into(),
                before: s(before),
                after_label: "with the tables active".into(),
                after: s(after),
            }
        })
        .collect()
}

fn summary(r: &LoopResult, truth: &Figures, ids: &[RunId]) -> String {
    let mut s = String::from("# axiscomp demo: before and after compensation\n\n");
    s.push_str(&format!(
        "Runs {} (before) and {} (after) in `axiscomp.db`; reports in `before/` and `after/`.\n\n",
        ids.first().map(|i| i.0).unwrap_or(0),
        ids.get(1).map(|i| i.0).unwrap_or(0)
    ));
    s.push_str(
        "| figure | unit | before | after | ratio | truth after |\n|---|---|---:|---:|---:|---:|\n",
    );
    for (name, unit, b, a, t, comp) in rows(r, truth) {
        let ratio = if comp && b.abs() > 0.0 {
            format!("{:.1} %", 100.0 * a / b)
        } else {
            "–".into()
        };
        s.push_str(&format!(
            "| {name} | {unit} | {b:.2} | {a:.2} | {ratio} | {t:.2} |\n"
        ));
    }
    s.push_str("\nTables published (sequence, points):\n\n");
    for p in &r.published {
        s.push_str(&format!(
            "- {}: sequence {}, {} points from {} mm every {} mm\n",
            p.name,
            p.sequence,
            p.table.values_mm.len(),
            p.table.start_mm,
            p.table.interval_mm
        ));
    }
    s
}

fn write(path: &Path, text: &str) -> Result<()> {
    std::fs::write(path, text).with_context(|| {
        format!(
            "writing {}; check that the directory is writable",
            path.display()
        )
    })
}
