//! The whole loop on the twin: measure the axis, compensate it through the PLC, measure again.
//!
//! 1. The ISO 230-2 cycle in the virtual-time [`Lab`] (the service's pipeline and run machine,
//!    the CANopen master and twin drive, the CNC running the generated part program).
//! 2. Evaluation (ISO 230-2 positioning, ISO 230-1 straightness) and the compensation tables
//!    ([`build_tables`]): positioning and both straightnesses.
//! 3. Each table fitted to the PLC's grid and published over Modbus TCP on loopback into the
//!    twin's PLC ([`TwinPlc`]) with the handshake of [`crate::plc::publish`]. The PLC validates
//!    it (CRC, limits) and applies it to the plant: the commanded position corrected by the
//!    interpolated table, as a controller does.
//! 4. The same cycle again on the compensated axis, and the figures before and after.
//!
//! Time is simulated in the measuring steps (a 1000 mm cycle takes seconds, not minutes);
//! publishing is real Modbus TCP traffic on a small Tokio runtime of its own.

use super::lab::{AlignRound, Lab, LabError, LabRun, LabSpec, Progress, plan_span};
use super::plc::{TwinPlc, TwinPlcConfig, TwinPlcError};
use crate::comp::{
    AxisMapping, CompError, CompTable, MachineAxis, PositioningMode, TableSet, TableSpec,
    build_tables,
};
use crate::evaluate::{AxisEvaluation, EvalError, EvalOptions, ReferenceLine, evaluate_captures};
use crate::modbus::link::{Link, LinkConfig};
use crate::plc::map::CncMap;
use crate::plc::publish::{PublishError, PublishOutcome, Timeouts, publish};
use crate::plc::table::{PlcTable, TableError};
use crate::run::program::CaptureMode;
use crate::run::{Dialect, Plan};
use std::time::Duration;
use thiserror::Error;

/// Why the loop stopped.
#[derive(Debug, Error)]
pub enum LoopError {
    #[error("{pass} run: {source}")]
    Lab {
        pass: Pass,
        #[source]
        source: LabError,
    },
    #[error("{pass} run: evaluation: {source}")]
    Evaluate {
        pass: Pass,
        #[source]
        source: EvalError,
    },
    #[error("compensation tables: {0}")]
    Tables(#[from] CompError),
    #[error("{table} table for the PLC: {source}")]
    PlcTable {
        table: String,
        #[source]
        source: TableError,
    },
    #[error("the twin's PLC: {0}")]
    Plc(#[from] TwinPlcError),
    #[error("publishing the {table} table: {source}")]
    Publish {
        table: String,
        #[source]
        source: PublishError,
    },
    #[error("the PLC rejected the {table} table: {detail}")]
    Rejected { table: String, detail: String },
    #[error("the plan's axis {0:?} is not X, Y or Z")]
    Axis(String),
    #[error("a Tokio runtime for publishing: {0}")]
    Runtime(std::io::Error),
}

/// Which measuring run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pass {
    /// The axis as it is.
    Before,
    /// The axis with the published tables active (the verification run).
    After,
}

impl std::fmt::Display for Pass {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Pass::Before => "measuring",
            Pass::After => "verification",
        })
    }
}

/// What the loop is doing, for whoever shows progress.
#[derive(Clone, Debug, PartialEq)]
pub enum Step {
    /// A round of beam alignment over the plan's travel (before the first pass).
    Aligning(Box<AlignRound>),
    /// Follower up and homed, the zero reference taken, for a pass.
    Ready(Pass),
    /// About once per simulated second during a run.
    Running(Pass, Progress),
    /// A run's captures are in.
    Measured(Pass, usize),
    /// A table went into the PLC.
    Published {
        table: String,
        sequence: u32,
        points: usize,
    },
}

/// What to do.
#[derive(Clone, Debug)]
pub struct LoopSpec {
    pub lab: LabSpec,
    pub plan: Plan,
    pub dialect: Dialect,
    pub mode: CaptureMode,
    pub positioning: PositioningMode,
    pub straightness_line: ReferenceLine,
    /// The PLC's register map (its table format and limits).
    pub map: CncMap,
    /// The PLC table spacing (mm); `None`: the measured targets' mean spacing.
    pub step_mm: Option<f64>,
    /// Averaging window of the zero reference.
    pub zero_window: Duration,
    /// Align the head over the plan's travel before the first pass, in at most this many
    /// rounds (0: do not; the pre-run check still runs).
    pub align_rounds: usize,
}

/// One measuring run and its evaluation.
#[derive(Clone, Debug)]
pub struct Measured {
    pub run: LabRun,
    pub eval: AxisEvaluation,
    pub figures: Figures,
}

/// A table as published.
#[derive(Clone, Debug)]
pub struct Published {
    pub name: String,
    pub table: PlcTable,
    pub sequence: u32,
}

/// The whole loop's outcome.
#[derive(Clone, Debug)]
pub struct LoopResult {
    pub before: Measured,
    pub tables: TableSet,
    pub published: Vec<Published>,
    pub after: Measured,
    /// How the head was mounted at the start and after the alignment (the twin's truth).
    pub mount: [crate::align::Mount; 2],
}

/// The figures the loop is judged by (mm and rad, the crate's internal units).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Figures {
    /// ISO 230-2 systematic positioning error E (bidirectional, else the one direction's)
    /// and mean bidirectional positioning error M (NaN when undefined).
    pub e: f64,
    pub m: f64,
    /// Accuracy A, repeatability R, reversal B (when defined).
    pub a: Option<f64>,
    pub r: Option<f64>,
    pub b: Option<f64>,
    /// ISO 230-1 straightness deviation of the mean profiles, horizontal (dx) and vertical
    /// (dz), against the reference line the tables use.
    pub straightness_x: f64,
    pub straightness_z: f64,
    /// Largest − smallest of the mean angular profiles: pitch, yaw, roll.
    pub pitch: f64,
    pub yaw: f64,
    pub roll: f64,
}

impl Figures {
    /// From an evaluation, the straightness against `line`.
    pub fn of(eval: &AxisEvaluation, line: ReferenceLine) -> Figures {
        let a = &eval.positioning.axis;
        let first = |v: [Option<f64>; 3]| v.into_iter().flatten().next().unwrap_or(f64::NAN);
        Figures {
            e: first([a.e, a.e_up, a.e_down]),
            m: a.m.unwrap_or(f64::NAN),
            a: a.a,
            r: a.r,
            b: a.b,
            straightness_x: eval.straightness_x.mean.line(line).straightness,
            straightness_z: eval.straightness_z.mean.line(line).straightness,
            pitch: eval.pitch.mean,
            yaw: eval.yaw.mean,
            roll: eval.roll.mean,
        }
    }
}

/// Run the loop. `step` hears of each stage as it happens.
pub fn run(spec: &LoopSpec, mut step: impl FnMut(Step)) -> Result<LoopResult, LoopError> {
    let axis = &spec.plan.spec.axis;
    let mapping = AxisMapping::standard(
        MachineAxis::from_letter(axis).ok_or_else(|| LoopError::Axis(axis.clone()))?,
    );
    let mut lab = Lab::new(&spec.lab).map_err(|source| LoopError::Lab {
        pass: Pass::Before,
        source,
    })?;
    let mount_at_start = lab.plant.mount();
    let before = measure(&mut lab, spec, Pass::Before, &mut step)?;
    let mount_aligned = lab.plant.mount();
    let tables = build_tables(
        &before.eval,
        &TableSpec {
            mapping,
            reference_mm: spec.plan.reference_mm,
            positioning: spec.positioning,
            straightness_line: spec.straightness_line,
            functional_point_mm: None,
        },
    )?;
    let published = publish_all(&lab, spec, &tables, &mut step)?;
    let after = measure(&mut lab, spec, Pass::After, &mut step)?;
    Ok(LoopResult {
        before,
        tables,
        published,
        after,
        mount: [mount_at_start, mount_aligned],
    })
}

/// Bring up (the first time), move to the reference, zero, run the cycle, evaluate.
fn measure(
    lab: &mut Lab,
    spec: &LoopSpec,
    pass: Pass,
    step: &mut impl FnMut(Step),
) -> Result<Measured, LoopError> {
    let lab_err = |source| LoopError::Lab { pass, source };
    if pass == Pass::Before {
        lab.bring_up().map_err(lab_err)?;
        if spec.align_rounds > 0 {
            lab.align(plan_span(&spec.plan), spec.align_rounds, |r| {
                step(Step::Aligning(Box::new(r.clone())))
            })
            .map_err(lab_err)?;
        }
    }
    // Before the zero: the check may traverse the travel.
    lab.pre_run_check(&spec.plan).map_err(lab_err)?;
    let reference = spec.plan.reference_mm;
    lab.move_carriage(reference).map_err(lab_err)?;
    lab.zero(reference, spec.zero_window).map_err(lab_err)?;
    step(Step::Ready(pass));
    let run = lab
        .measure(&spec.plan, spec.dialect, spec.mode, |p| {
            step(Step::Running(pass, p))
        })
        .map_err(lab_err)?;
    step(Step::Measured(pass, run.captures.len()));
    let captures: Vec<_> = run.captures.iter().map(|c| c.capture).collect();
    let eval = evaluate_captures(&captures, &EvalOptions::default())
        .map_err(|source| LoopError::Evaluate { pass, source })?;
    let figures = Figures::of(&eval, spec.straightness_line);
    Ok(Measured { run, eval, figures })
}

/// The tables of `set` that go to the PLC, with their names.
fn plc_tables(set: &TableSet) -> Vec<(String, &CompTable)> {
    std::iter::once(&set.positioning)
        .chain(&set.straightness)
        .map(|t| (t.name.clone(), t))
        .collect()
}

/// Publish every table into a twin PLC serving `lab`'s plant, sequence 1, 2, …
fn publish_all(
    lab: &Lab,
    spec: &LoopSpec,
    set: &TableSet,
    step: &mut impl FnMut(Step),
) -> Result<Vec<Published>, LoopError> {
    let mut tables = Vec::new();
    for (name, t) in plc_tables(set) {
        let table = PlcTable::from_comp(t, &spec.map, spec.step_mm).map_err(|source| {
            LoopError::PlcTable {
                table: name.clone(),
                source,
            }
        })?;
        tables.push((name, table));
    }
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(LoopError::Runtime)?;
    let plant = lab.plant.clone();
    let map = spec.map.clone();
    rt.block_on(async move {
        let plc = TwinPlc::start(plant, map.clone(), TwinPlcConfig::default()).await?;
        let link = Link::spawn(LinkConfig::new(plc.local_addr()));
        // The production timeouts; polled often, the twin answers at once.
        let timeouts = Timeouts {
            poll: Duration::from_millis(5),
            ..Timeouts::default()
        };
        let mut out = Vec::new();
        for (k, (name, table)) in tables.into_iter().enumerate() {
            let sequence = k as u32 + 1;
            match publish(&link, &map, &table, sequence, timeouts).await {
                Ok(PublishOutcome::Accepted { .. }) => {}
                Ok(other) => {
                    return Err(LoopError::Rejected {
                        table: name,
                        detail: format!("{other:?}"),
                    });
                }
                Err(source) => {
                    return Err(LoopError::Publish {
                        table: name,
                        source,
                    });
                }
            }
            step(Step::Published {
                table: name.clone(),
                sequence,
                points: table.values_mm.len(),
            });
            out.push(Published {
                name,
                table,
                sequence,
            });
        }
        Ok(out)
    })
}
