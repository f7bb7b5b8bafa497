//! The whole machine (issue 27): the twin's three-axis machines, their 21 errors as a model,
//! the Beckhoff volumetric file written to disk, read back and applied by the twin's CNC.
//! The tables here are the twin's truth sampled every 5 mm (a perfect measurement): what is
//! held is the model, the file and the compensation, not yet the measurement.

use crate::helpers::TempDir;
use axiscomp::comp::PositioningMode;
use axiscomp::comp::mapping::{AxisMapping, MachineAxis};
use axiscomp::evaluate::ReferenceLine;
use axiscomp::machine::from_head::table_from_evaluation;
use axiscomp::machine::{ComponentTable, Grid, MachineModel, Volumetric, component_names, isg_csv};
use axiscomp::plc::CncMap;
use axiscomp::run::Dialect;
use axiscomp::run::program::CaptureMode;
use axiscomp::sim::closed_loop::{BudgetSpec, LoopSpec, Pass, measure, prepare};
use axiscomp::sim::follower::FollowerSpec;
use axiscomp::sim::follower_cal::{Mapping, map_instrument};
use axiscomp::sim::lab::{Lab, LabSpec, plan_span};
use axiscomp::sim::machine::{MachineSpec, TwinMachine};
use axiscomp::sim::plant::{MountSpec, PlantSpec};
use axiscomp::sim::{InstallSpec, Rng};
use axiscomp::units::RAD_PER_ARCSEC;
use std::time::Duration;

fn norm(e: [f64; 3]) -> f64 {
    e.iter().map(|v| v * v).sum::<f64>().sqrt()
}

/// Max and RMS (µm) of the tool point's error over `points` with `tool`, uncompensated or
/// compensated by `model`.
fn volumetric(
    twin: &TwinMachine,
    points: &[[f64; 3]],
    tool: [f64; 3],
    model: Option<&dyn Volumetric>,
) -> (f64, f64) {
    let e: Vec<f64> = points
        .iter()
        .map(|&p| {
            norm(match model {
                Some(m) => twin.error_compensated(p, tool, m),
                None => twin.error(p, tool),
            })
        })
        .collect();
    let max = e.iter().fold(0.0f64, |a, &b| a.max(b));
    let rms = (e.iter().map(|v| v * v).sum::<f64>() / e.len() as f64).sqrt();
    (max * 1e3, rms * 1e3)
}

#[test]
fn the_beckhoff_file_applied_by_the_twin_s_cnc_cuts_the_volumetric_error_to_a_tenth() {
    let dir = TempDir::new("machine");
    for spec in [MachineSpec::vertical_mc(), MachineSpec::gantry()] {
        for seed in 11..=15u64 {
            let twin = TwinMachine::new(&spec, seed);
            let truth = twin.truth_model(5.0).expect("model");
            let path = dir.write(
                &format!("vol-{seed}.csv"),
                &isg_csv::write(
                    truth.tables(),
                    truth.squareness,
                    &format!("twin seed {seed}"),
                ),
            );
            let file = isg_csv::read(&path).expect("read back");
            let loaded = MachineModel::new(
                spec.chain,
                file.tables,
                file.squareness.expect("squareness in the file"),
            )
            .expect("model from the file");
            let points = twin.random_points(1000, &mut Rng::new(seed * 7));
            let tool = [0.0, 0.0, -150.0];
            let before = volumetric(&twin, &points, tool, None);
            let after = volumetric(&twin, &points, tool, Some(&loaded));
            let in_memory = volumetric(&twin, &points, tool, Some(&truth));
            eprintln!(
                "{} seed {seed}: before max {:.1} µm, RMS {:.1} µm; after (file) max {:.3} µm, RMS {:.3} µm; after (model) max {:.3} µm",
                spec.chain, before.0, before.1, after.0, after.1, in_memory.0
            );
            assert!(before.0 > 30.0, "seed {seed}: before {:.1} µm", before.0);
            assert!(
                after.0 <= 0.1 * before.0,
                "seed {seed}: {after:?} after, {before:?} before"
            );
            assert!(after.1 <= 1.5, "seed {seed}: after RMS {:.3} µm", after.1);
            // The file's rounding (0.1 nm, 1e-10 rad) changes nothing a control could see.
            assert!((after.0 - in_memory.0).abs() < 1e-3 && (after.1 - in_memory.1).abs() < 1e-3);
            // The same model onto a 20 mm grid over the volume, as FANUC's 3-D compensation
            // takes it, with the same tool: between the corners the grid is linear where the
            // errors are not (max after at 50 mm 3.8-15.5 µm; at 10 mm 0.18-0.91 µm).
            let t = spec.travel_mm;
            let grid = Grid::of_model(&loaded, [0.0; 3], t, [20.0; 3], tool).expect("grid");
            let gridded = volumetric(&twin, &points, tool, Some(&grid));
            eprintln!(
                "    grid {:?} corners: after max {:.3} µm, RMS {:.3} µm",
                grid.counts(),
                gridded.0,
                gridded.1
            );
            assert!(
                gridded.0 <= 0.1 * before.0 && gridded.1 <= 1.5,
                "{gridded:?}"
            );
        }
    }
}

/// The worst |measured − truth| of each of `table`'s six errors at its targets: positioning
/// and angles relative to the truth at the zero (0 mm), each straightness after the line
/// through what is left (the truth over these targets keeps a small line of its own).
fn worst_off(twin: &TwinMachine, table: &ComponentTable) -> [f64; 6] {
    let axis = table.axis();
    let p = table.positions_mm();
    let at0 = twin.component_errors(axis, 0.0);
    std::array::from_fn(|k| {
        let straight = k < 3 && k != axis.index();
        let d: Vec<f64> = p
            .iter()
            .zip(table.values())
            .map(|(&q, m)| {
                let t = twin.component_errors(axis, q)[k];
                m[k] - if straight { t } else { t - at0[k] }
            })
            .collect();
        let n = p.len() as f64;
        let (mx, md) = (p.iter().sum::<f64>() / n, d.iter().sum::<f64>() / n);
        let slope = if straight {
            p.iter()
                .zip(&d)
                .map(|(x, v)| (x - mx) * (v - md))
                .sum::<f64>()
                / p.iter().map(|x| (x - mx).powi(2)).sum::<f64>()
        } else {
            0.0
        };
        p.iter()
            .zip(&d)
            .map(|(x, v)| {
                if straight {
                    v - md - slope * (x - mx)
                } else {
                    *v
                }
            })
            .fold(0.0f64, |a, v| a.max(v.abs()))
    })
}

/// Each axis of the twin's vertical machining centre measured by the product's path on the
/// lab (the head mounted by eye and aligned, the instrument's follower map made once on its
/// bench and re-used with a level's check, a target every ~20 mm, two bidirectional runs),
/// put on the machine by the standard mounting, straightness from its reference line: each
/// of the 18 component errors against the machine's truth within issue 14's limits, then the
/// model with the true squarenesses (the optical square is not built) compensating the
/// twin's CNC, judged by its truth at 1000 points with a 150 mm tool.
#[test]
#[ignore = "three whole axes on the lab: run optimised by .ci/run"]
fn three_axes_measured_by_the_head_compensate_the_machine() {
    let _machine = crate::helpers::heavy();
    let spec = MachineSpec::vertical_mc();
    let twin = TwinMachine::new(&spec, 31);
    let base = PlantSpec {
        install: InstallSpec {
            offset_mm: 0.0,
            tilt_deg: 0.0,
            gain_error: 0.0,
        },
        mount: MountSpec::by_eye(),
        // One instrument on every axis: its rail's own shape is the same on each.
        follower: FollowerSpec {
            instrument_seed: Some(1),
            bend_um: 2.0,
            rail_mm: Some(1000.0),
            ..FollowerSpec::default()
        },
        ..PlantSpec::default()
    };
    let mut bench = Mapping::over((0.0, 1000.0));
    bench.cal.passes = 4;
    bench.cal.average_frames = 1000;
    let made = map_instrument(base.follower, 1000.0, &bench.cal, |_, _| {}).expect("bench map");
    let mut tables = Vec::new();
    let mut machine_s = 0.0;
    for axis in MachineAxis::ALL {
        let len = spec.travel_mm[axis.index()];
        let plant = twin.plant_spec(axis, base.clone());
        let targets = (len / 20.0).round() as usize + 1;
        let plan = crate::lab::plan(len, targets, 2, 6000.0);
        let mut follower = Mapping::over(plan_span(&plan));
        follower.reuse = Some(Box::new(made.clone()));
        let loop_spec = LoopSpec {
            lab: LabSpec::standard(plant.clone(), None).expect("lab spec"),
            plan,
            dialect: Dialect::LinuxCnc,
            mode: CaptureMode::Stability,
            positioning: PositioningMode::Bidirectional,
            straightness_line: ReferenceLine::LeastSquares,
            map: CncMap::generic().expect("map"),
            step_mm: Some(5.0),
            zero_window: Duration::from_secs(2),
            align_rounds: 8,
            budget: BudgetSpec::of_plant(&plant),
            follower: Some(follower),
        };
        let mut lab = Lab::new(&loop_spec.lab).expect("lab");
        let started = lab.now();
        prepare(&mut lab, &loop_spec, &mut |_| {}).expect("prepare");
        let m = measure(&mut lab, &loop_spec, Pass::Before, &mut |_| {}).expect("measure");
        machine_s += (lab.now() - started).as_secs_f64();
        let table = table_from_evaluation(&AxisMapping::standard(axis), &m.eval).expect("table");
        let worst = worst_off(&twin, &table);
        let names = component_names(axis);
        let user: Vec<String> = (0..6)
            .map(|k| match k {
                0..=2 => format!("{} {:.2} µm", names[k], worst[k] * 1e3),
                _ => format!("{} {:.2}″", names[k], worst[k] / RAD_PER_ARCSEC),
            })
            .collect();
        eprintln!(
            "{axis}: {} targets, {:.1} min of machine time; worst |measured − truth|: {}",
            table.positions_mm().len(),
            (lab.now() - started).as_secs_f64() / 60.0,
            user.join(", ")
        );
        // Issue 14's limits: 1 µm positioning, 0.5 µm straightness, 0.5″ roll, 0.3″ pitch
        // and yaw.
        for k in 0..6 {
            let limit = match k {
                k if k == axis.index() => 1e-3,
                0..=2 => 0.5e-3,
                k if k - 3 == axis.index() => 0.5 * RAD_PER_ARCSEC,
                _ => 0.3 * RAD_PER_ARCSEC,
            };
            assert!(
                worst[k] <= limit,
                "{}: {:e} beyond {limit:e}",
                names[k],
                worst[k]
            );
        }
        tables.push(table);
    }
    let model = MachineModel::new(spec.chain, tables, twin.squareness()).expect("model");
    let points = twin.random_points(1000, &mut Rng::new(31));
    let tool = [0.0, 0.0, -150.0];
    let before = volumetric(&twin, &points, tool, None);
    let after = volumetric(&twin, &points, tool, Some(&model));
    eprintln!(
        "{}: {:.0} min of machine time for the three axes; volumetric before max {:.1} µm, RMS {:.1} µm; after max {:.2} µm, RMS {:.2} µm",
        spec.chain,
        machine_s / 60.0,
        before.0,
        before.1,
        after.0,
        after.1
    );
    assert!(
        after.0 <= 0.1 * before.0 && after.1 <= 1.5,
        "{after:?} after, {before:?} before"
    );
}
