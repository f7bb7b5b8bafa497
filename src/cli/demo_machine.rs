//! `axiscomp demo --machine`: the whole machine on the twin (issue 27). The twin's vertical
//! machining centre (X 1000 × Y 600 × Z 500 mm, a cross table) measured set-up by set-up
//! through the product's path on the lab (`sim::machine_lab`): X with its beam aligned, Y and Z
//! through an optical square from X's beam, Z again through a square from Y's beam; the 21
//! errors into the model, exported for each control (Beckhoff's `ISG_CSV`, HEIDENHAIN's
//! KinematicsComp, FANUC's grid, Siemens's EEC and CEC tables; `exports`), each read back and
//! applied by the twin's CNC; judged by the twin's truth.
//!
//! `summary.json`: `{"seed", "machine": {"chain", "travel_mm", "machine_time_s", "axes":
//! [{"axis", "setup", "targets", "machine_time_s", "worst_off": {name: value}}], "squareness":
//! [{"pair", "name", "measured_arcsec", "truth_arcsec", "U_arcsec", "terms": [{"name",
//! "u_arcsec", "source"}]}], "volumetric": {"points", "tool_mm", "before_max_um",
//! "before_rms_um", "after_max_um", "after_rms_um", "model_after_max_um",
//! "model_after_rms_um"}, "exports": [{"control", "path", "carries", "after_max_um",
//! "after_rms_um"}]}}`, the volumetric "after" that of the Beckhoff file; `worst_off` in µm and arcsec
//! (straightness from its reference line, the rest relative to the zero).

use anyhow::{Context, Result};
use axiscomp::commission::{report, stored};
use axiscomp::machine::component_names;
use axiscomp::sim::Rng;
use axiscomp::sim::machine::MachineSpec;
use axiscomp::sim::machine_lab::{MachineLabSpec, measure_machine};
use axiscomp::store::Store;
use axiscomp::units::RAD_PER_ARCSEC;
use std::path::Path;

/// Random points of the volume the figures are taken at.
const POINTS: usize = 1000;

fn arcsec(rad: f64) -> f64 {
    rad / RAD_PER_ARCSEC
}

pub fn run(seed: u64, out: &Path) -> Result<()> {
    let spec = MachineLabSpec::standard(MachineSpec::vertical_mc(), seed);
    let m = &spec.machine;
    println!(
        "The twin's machine (seed {seed}): {}, X {:.0} × Y {:.0} × Z {:.0} mm. Set-ups in order: X with its beam aligned; Y and Z through an optical square from X's beam (C0Y, B0Z); Z through a square from Y's beam (A0Z). Each: the head mounted by eye and aligned, the instrument's follower map checked by a level, a target every {:.0} mm, {} bidirectional runs.",
        m.chain, m.travel_mm[0], m.travel_mm[1], m.travel_mm[2], spec.target_every_mm, spec.runs
    );
    let r = measure_machine(&spec, &mut |s| {
        let names = component_names(s.axis);
        let worst: Vec<String> = (0..6)
            .map(|k| match k {
                0..=2 => format!("{} {:.2} µm", names[k], s.worst_off[k] * 1e3),
                _ => format!("{} {:.2}″", names[k], arcsec(s.worst_off[k])),
            })
            .collect();
        println!(
            "  {} ({}): {} targets, {:.1} min of machine time; largest difference from the truth: {}",
            s.axis,
            s.beam,
            s.measured.positions_mm().len(),
            s.machine_s / 60.0,
            worst.join(", ")
        );
    })
    .context("measuring the machine")?;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    // The machine as the product keeps it: its record, each set-up's run stored and attached
    // in the plan's order; the model and the exports are the stored machine's.
    let record_path = out.join("machine.toml");
    std::fs::write(&record_path, r.record.to_toml())
        .with_context(|| format!("writing {}", record_path.display()))?;
    let db = out.join("axiscomp.db");
    super::remove_store(&db)?;
    let mut store = Store::open(&db)?;
    let id = r.store(&mut store, axiscomp::store::now_us())?;
    let state = stored::state(&store, id)?;
    let model = state
        .model()
        .map_err(|e| anyhow::anyhow!("the stored machine: {e}"))?
        .clone();
    println!(
        "Stored: machine {id} ({}) in {}, its record in {}, the four set-ups' runs ({}) attached in the plan's order; the model below is the stored machine's.",
        r.record.name,
        db.display(),
        record_path.display(),
        state.runs_words()
    );
    let truth = r.twin.squareness().to_array();
    let fitted = state
        .fit
        .as_ref()
        .map_err(|e| anyhow::anyhow!("the stored machine: {e}"))?;
    for sq in &fitted.squareness {
        println!(
            "  {}; the truth {:+.2}″",
            sq,
            arcsec(truth[sq.pair.index()])
        );
    }
    let tool = r.record.tool_mm;
    let points = r.twin.random_points(POINTS, &mut Rng::new(seed ^ 0x5eed));
    let before = r.twin.volumetric(&points, tool, None);
    let in_memory = r.twin.volumetric(&points, tool, Some(&model));
    // Each control's files, written and read back (the twin's CNC applies what the files
    // say), and the machine acceptance report that names them, from the store.
    let report_dir = out.join("report");
    let written = report::write(&store, id, &report_dir, out, axiscomp::store::now_us())?;
    let exports = written.exports;
    println!(
        "Volumetric error of the tool point ({} points, a {:.0} mm tool), by the twin's truth: {:.1} µm largest, {:.1} µm RMS before; with the stored machine's model applied exactly {:.2} µm largest, {:.2} µm RMS. Each control's files written, read back and applied by the twin's CNC:",
        before.points,
        -tool[2],
        before.max_mm * 1e3,
        before.rms_mm * 1e3,
        in_memory.max_mm * 1e3,
        in_memory.rms_mm * 1e3,
    );
    let mut applied = Vec::new();
    for e in &exports {
        let after = r.twin.volumetric(&points, tool, Some(e.applied.as_ref()));
        println!(
            "  {}: {:.2} µm largest, {:.2} µm RMS ({}; {})",
            e.control,
            after.max_mm * 1e3,
            after.rms_mm * 1e3,
            e.carries,
            e.path.display()
        );
        applied.push(after);
    }
    // The volumetric figures after are the Beckhoff file's, the first written.
    let after = *applied.first().context("no control's files were written")?;
    println!(
        "Machine time: {:.1} min for the four set-ups.",
        r.machine_s() / 60.0
    );
    let axes: Vec<serde_json::Value> = r
        .setups
        .iter()
        .map(|s| {
            let names = component_names(s.axis);
            let worst: serde_json::Map<String, serde_json::Value> = (0..6)
                .map(|k| {
                    let v = if k < 3 {
                        s.worst_off[k] * 1e3
                    } else {
                        arcsec(s.worst_off[k])
                    };
                    (names[k].clone(), serde_json::json!(v))
                })
                .collect();
            serde_json::json!({
                "axis": s.axis.to_string(),
                "setup": s.beam.to_string(),
                "targets": s.measured.positions_mm().len(),
                "machine_time_s": s.machine_s,
                "worst_off": worst,
            })
        })
        .collect();
    let squares: Vec<serde_json::Value> = fitted
        .squareness
        .iter()
        .map(|m| {
            serde_json::json!({
                "pair": m.pair.to_string(),
                "name": m.pair.name(),
                "measured_arcsec": arcsec(m.value_rad),
                "truth_arcsec": arcsec(truth[m.pair.index()]),
                "U_arcsec": arcsec(m.expanded_rad),
                "terms": m.terms.iter().map(|t| serde_json::json!({
                    "name": t.name,
                    "u_arcsec": arcsec(t.u_rad),
                    "source": t.source,
                })).collect::<Vec<_>>(),
            })
        })
        .collect();
    let summary = serde_json::json!({
        "seed": seed,
        "machine": {
            "id": id,
            "store": db.display().to_string(),
            "record": record_path.display().to_string(),
            "chain": m.chain.to_string(),
            "travel_mm": m.travel_mm,
            "machine_time_s": r.machine_s(),
            "axes": axes,
            "squareness": squares,
            "volumetric": {
                "points": before.points,
                "tool_mm": tool,
                "before_max_um": before.max_mm * 1e3,
                "before_rms_um": before.rms_mm * 1e3,
                "after_max_um": after.max_mm * 1e3,
                "after_rms_um": after.rms_mm * 1e3,
                "model_after_max_um": in_memory.max_mm * 1e3,
                "model_after_rms_um": in_memory.rms_mm * 1e3,
            },
            "exports": exports.iter().zip(&applied).map(|(e, a)| serde_json::json!({
                "control": e.control,
                "path": e.path.display().to_string(),
                "carries": e.carries,
                "after_max_um": a.max_mm * 1e3,
                "after_rms_um": a.rms_mm * 1e3,
            })).collect::<Vec<_>>(),
        },
    });
    let json = out.join("summary.json");
    std::fs::write(&json, serde_json::to_string_pretty(&summary)? + "\n")
        .with_context(|| format!("writing {}", json.display()))?;
    let report: Vec<String> = written
        .report
        .iter()
        .filter(|p| p.extension().is_some_and(|e| e != "svg"))
        .map(|p| p.display().to_string())
        .collect();
    println!(
        "The machine acceptance report, from the store: {}.",
        report.join(", ")
    );
    println!("Written: the files above and {}.", json.display());
    Ok(())
}
