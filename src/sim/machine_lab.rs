//! The whole machine measured on the lab (issue 27): the twin's three-axis machine
//! (`sim::machine`), each set-up of the commissioning order run through the product's own path
//! on the single-axis twin that carries that axis (`closed_loop::prepare` and `measure`: the
//! head mounted by eye and aligned, the instrument's follower map re-used with a level's check,
//! the ISO 230-2 cycle), its component errors into `machine::from_head`'s table, its
//! straightness slopes into `machine::squareness` with the optical square's certificate, and
//! the 21-error model of the measured tables and squarenesses.
//!
//! The order: X with its beam aligned; Y and Z each through an optical square from X's beam
//! (C0Y, B0Z); Z again through a square from Y's beam (A0Z). On a set-up through a square the
//! technician aligns every screw but the one that would turn the beam in the square's plane:
//! the square fixes that direction (`sim::machine::hold_in_plane`). The model takes X, Y and
//! the first Z set-up's tables.

use super::InstallSpec;
use super::closed_loop::{BudgetSpec, LoopError, LoopSpec, Measured, Pass, measure, prepare};
use super::follower::FollowerSpec;
use super::follower_cal::{MapTwinError, Mapping, TwinMap, map_instrument};
use super::lab::{Lab, LabError, LabSpec, plan_span};
use super::machine::{MachineSpec, TwinMachine, TwinSquare, hold_in_plane};
use super::plant::{MountSpec, PlantSpec};
use crate::commission::fit::{MeasuredSetup, fit};
use crate::commission::plan::run_plan;
use crate::commission::record::MachineRecord;
use crate::comp::PositioningMode;
use crate::comp::mapping::{AxisMapping, MachineAxis};
use crate::evaluate::ReferenceLine;
use crate::machine::from_head::table_from_evaluation;
use crate::machine::squareness::{MeasuredSquareness, SetupSlopes, SquarePair};
use crate::machine::{ComponentTable, MachineError, MachineModel};
use crate::plc::CncMap;
use crate::run::program::CaptureMode;
use crate::run::{Dialect, Plan};
use std::time::Duration;
use thiserror::Error;

pub use crate::commission::plan::{Beam, SETUPS};
pub use crate::machine::exports::TABLE_STEP_MM;

/// Why the machine could not be measured.
#[derive(Debug, Error)]
pub enum MachineLabError {
    #[error("the instrument's follower map on its bench: {0}")]
    Bench(#[from] MapTwinError),
    #[error("{axis} ({beam}): {source}")]
    Lab {
        axis: MachineAxis,
        beam: Beam,
        #[source]
        source: LabError,
    },
    #[error("{axis} ({beam}): {source}")]
    Loop {
        axis: MachineAxis,
        beam: Beam,
        #[source]
        source: Box<LoopError>,
    },
    #[error("{axis} ({beam}): {what}")]
    Setup {
        axis: MachineAxis,
        beam: Beam,
        what: String,
    },
    #[error(transparent)]
    Machine(#[from] MachineError),
}

/// What is measured and how.
#[derive(Clone, Debug)]
pub struct MachineLabSpec {
    pub machine: MachineSpec,
    /// The twin machine's seed; its squares are drawn from it too.
    pub seed: u64,
    /// The single-axis twin's parts that are not the axis (head, mount, follower).
    pub base: PlantSpec,
    /// A target every this far (mm), each axis from 0 to its travel.
    pub target_every_mm: f64,
    /// Bidirectional runs per set-up.
    pub runs: u32,
}

impl MachineLabSpec {
    /// The set-up the README recommends on each axis: the head mounted by eye, one instrument
    /// (its follower rail's own shape the same on every axis, a 2 µm bend from each bed), a
    /// target every 20 mm, two bidirectional runs.
    pub fn standard(machine: MachineSpec, seed: u64) -> MachineLabSpec {
        MachineLabSpec {
            machine,
            seed,
            base: PlantSpec {
                install: InstallSpec {
                    offset_mm: 0.0,
                    tilt_deg: 0.0,
                    gain_error: 0.0,
                },
                mount: MountSpec::by_eye(),
                follower: FollowerSpec {
                    instrument_seed: Some(1),
                    bend_um: 2.0,
                    rail_mm: Some(1000.0),
                    ..FollowerSpec::default()
                },
                ..PlantSpec::default()
            },
            target_every_mm: 20.0,
            runs: 2,
        }
    }

    /// The machine's record as its builder would write it for the twin: the twin's chain and
    /// travels, a 150 mm tool, the squares' certificates.
    pub fn record(&self, squares: &[TwinSquare]) -> MachineRecord {
        MachineRecord {
            name: format!("twin machine, seed {}", self.seed),
            chain: self.machine.chain,
            travel_mm: self.machine.travel_mm,
            tool_mm: [0.0, 0.0, -150.0],
            target_every_mm: self.target_every_mm,
            runs: self.runs,
            squares: std::array::from_fn(|i| squares[i].certificate.clone()),
        }
    }
}

/// One set-up as measured.
#[derive(Clone, Debug)]
pub struct SetupResult {
    pub axis: MachineAxis,
    pub beam: Beam,
    /// The component errors at the measured targets.
    pub measured: ComponentTable,
    /// The model's table: every [`TABLE_STEP_MM`] from a spline through `measured`.
    pub table: ComponentTable,
    pub slopes: SetupSlopes,
    /// Machine time of the set-up: bring-up, alignment, the follower's check, the run (s).
    pub machine_s: f64,
    /// Each component error's largest difference from the truth at the measured targets (mm,
    /// rad; straightness from its reference line, the rest relative to the zero).
    pub worst_off: [f64; 6],
    /// The run as measured (its captures, evaluation and budget), to store it.
    pub plan: Plan,
    pub run: Measured,
    /// The run's first and last moment by the twin's clock (µs since the Unix epoch).
    pub times_us: [i64; 2],
    /// The follower map the run applied.
    pub map: Option<crate::follower::FollowerMap>,
}

/// A squareness as measured, with the twin's truth.
#[derive(Clone, Debug)]
pub struct SquarenessResult {
    pub measured: MeasuredSquareness,
    pub truth_rad: f64,
}

/// The whole machine as measured.
#[derive(Clone, Debug)]
pub struct MachineLabResult {
    /// The record the plan was walked with.
    pub record: MachineRecord,
    pub setups: Vec<SetupResult>,
    pub squareness: Vec<SquarenessResult>,
    pub squares: Vec<TwinSquare>,
    pub model: MachineModel,
    pub twin: TwinMachine,
}

impl MachineLabResult {
    /// Machine time of every set-up (s).
    pub fn machine_s(&self) -> f64 {
        self.setups.iter().map(|s| s.machine_s).sum()
    }
}

/// The instrument's follower map, made once on its bench (1000 mm, four passes of 1000 frames
/// a side) and re-used on every set-up.
pub fn bench_map(follower: FollowerSpec) -> Result<TwinMap, MapTwinError> {
    let mut bench = Mapping::over((0.0, 1000.0));
    bench.cal.passes = 4;
    bench.cal.average_frames = 1000;
    map_instrument(follower, 1000.0, &bench.cal, |_, _| {})
}

impl MachineLabResult {
    /// The machine in `store` as a technician leaves it after the plan: its record, each
    /// set-up's run stored as the service stores a live one (its budget's inputs and follower
    /// map with it), attached to its set-up in the plan's order (`commission::stored`, which
    /// checks each run); the machine's id.
    pub fn store(
        &self,
        store: &mut crate::store::Store,
        unix_us: i64,
    ) -> Result<i64, crate::commission::CommissionError> {
        use crate::commission::stored;
        use crate::sim::lab_store::{LabRunRecord, store_lab_run};
        // Each set-up's lab keeps its own clock. On the machine they follow one another, each
        // set-up's preparation (mount, alignment, the follower's check) before its run, the
        // last run ending at `unix_us`; the record is stored as the first preparation begins.
        let mut rel = Vec::with_capacity(self.setups.len());
        let mut t = 0i64;
        for s in &self.setups {
            let run_us = s.times_us[1] - s.times_us[0];
            t += ((s.machine_s * 1e6) as i64 - run_us).max(0);
            rel.push(t);
            t += run_us;
        }
        let base = unix_us - t;
        let id = stored::create(store, &self.record.to_toml(), "the twin's record", base)?;
        for (i, (s, start)) in self.setups.iter().zip(rel).enumerate() {
            let shift = base + start - s.times_us[0];
            let times_us = [s.times_us[0] + shift, s.times_us[1] + shift];
            let captures: Vec<_> = s
                .run
                .run
                .captures
                .iter()
                .map(|c| crate::run::Capture {
                    unix_us: c.capture.unix_us + shift,
                    ..c.capture
                })
                .collect();
            let run = store_lab_run(
                store,
                &LabRunRecord {
                    plan: &s.plan,
                    config: serde_json::json!({ "twin": "axiscomp demo --machine", "setup": i + 1 }),
                    notes: format!(
                        "demo --machine: set-up {}",
                        crate::commission::plan::title(i)
                    ),
                    captures: &captures,
                    times_us,
                    budget: Some((&s.run.budget.inputs, s.map.as_ref())),
                    tables: None,
                    calibration: None,
                },
            )?;
            stored::attach(store, id, i, run.0, times_us[1])?;
        }
        Ok(id)
    }
}

/// Measure the whole machine; `progress` hears of each set-up as it ends.
pub fn measure_machine(
    spec: &MachineLabSpec,
    progress: &mut dyn FnMut(&SetupResult),
) -> Result<MachineLabResult, MachineLabError> {
    let twin = TwinMachine::new(&spec.machine, spec.seed);
    let made = bench_map(spec.base.follower)?;
    let squares: Vec<TwinSquare> = SquarePair::ALL
        .iter()
        .map(|&p| TwinSquare::draw(p, spec.seed.wrapping_mul(10).wrapping_add(p.index() as u64)))
        .collect();
    let record = spec.record(&squares);
    let mut setups: Vec<SetupResult> = Vec::new();
    let mut beams = Vec::new();
    for (axis, beam) in SETUPS {
        let setup = |what: String| MachineLabError::Setup { axis, beam, what };
        let lab_err = |source| MachineLabError::Lab { axis, beam, source };
        let loop_err = |source| MachineLabError::Loop {
            axis,
            beam,
            source: Box::new(source),
        };
        let plant = twin.plant_spec(axis, spec.base.clone());
        let plan = Plan::new(run_plan(&record, setups.len()))
            .map_err(|e| setup(format!("the plan: {e}")))?;
        let span = plan_span(&plan);
        let mut follower = Mapping::over(span);
        follower.reuse = Some(Box::new(made.clone()));
        let loop_spec = LoopSpec {
            lab: LabSpec::standard(plant.clone(), None).map_err(lab_err)?,
            plan,
            dialect: Dialect::LinuxCnc,
            mode: CaptureMode::Stability,
            positioning: PositioningMode::Bidirectional,
            straightness_line: ReferenceLine::LeastSquares,
            map: CncMap::generic().map_err(|e| setup(format!("the CNC's map: {e}")))?,
            step_mm: Some(5.0),
            zero_window: Duration::from_secs(2),
            align_rounds: 8,
            budget: BudgetSpec::of_plant(&plant),
            follower: Some(follower),
        };
        let mut lab = Lab::new(&loop_spec.lab).map_err(lab_err)?;
        let started = lab.now();
        let map = prepare(&mut lab, &loop_spec, &mut |_| {}).map_err(loop_err)?;
        if let Beam::Through(pair, from) = beam {
            // The head's axis that lies along the pair's first axis reads the slope the
            // turned beam gives.
            let along = twin.direction(pair.axes().0);
            let hx =
                nalgebra::Vector3::from(AxisMapping::standard(axis).to_machine([1.0, 0.0, 0.0]));
            let j = if hx.dot(&along).abs() > 0.5 { 0 } else { 1 };
            let incoming = beams
                .get(from)
                .copied()
                .ok_or_else(|| setup(format!("set-up {from}'s beam is not measured yet")))?;
            let want = twin.slopes_for_beam(axis, squares[pair.index()].prism.turn(incoming))[j];
            let set = hold_in_plane(&lab.plant, span, j, want, lab.now());
            if (set - want).abs() > 1e-9 {
                return Err(setup(format!(
                    "the square's slope {want:e} could not be set on the mount ({set:e})"
                )));
            }
        }
        let u0 = lab.unix_us();
        let m = measure(&mut lab, &loop_spec, Pass::Before, &mut |_| {}).map_err(loop_err)?;
        let times_us = [u0, lab.unix_us()];
        beams.push(twin.beam_of(axis, lab.plant.true_slopes(span, lab.now())));
        let mapping = AxisMapping::standard(axis);
        let measured = table_from_evaluation(&mapping, &m.eval)?;
        // The control interpolates linearly: its table follows the axis between the targets.
        let table = measured.refined(TABLE_STEP_MM)?;
        let result = SetupResult {
            axis,
            beam,
            worst_off: twin.worst_off(&measured),
            slopes: SetupSlopes::from_evaluation(mapping, &m.eval, &m.budget)?,
            measured,
            table,
            machine_s: (lab.now() - started).as_secs_f64(),
            plan: loop_spec.plan.clone(),
            run: m,
            times_us,
            map: map.map(|t| t.map),
        };
        progress(&result);
        setups.push(result);
    }
    let truth = twin.squareness().to_array();
    let measured: [Option<MeasuredSetup>; 4] = std::array::from_fn(|i| {
        setups.get(i).map(|s| MeasuredSetup {
            table: s.table.clone(),
            slopes: s.slopes,
        })
    });
    let fitted = fit(&record, &measured)?;
    let squareness = fitted
        .squareness
        .into_iter()
        .map(|sq| SquarenessResult {
            truth_rad: truth[sq.pair.index()],
            measured: sq,
        })
        .collect();
    let model = fitted.model.ok_or_else(|| MachineLabError::Setup {
        axis: SETUPS[0].0,
        beam: SETUPS[0].1,
        what: "the model needs every set-up measured".into(),
    })?;
    Ok(MachineLabResult {
        record,
        setups,
        squareness,
        squares,
        model,
        twin,
    })
}
