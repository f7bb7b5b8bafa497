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
//! Each run is judged twice: by the head (its ISO figures, and the uncertainty budget of every
//! point, [`crate::evaluate::uncertainty`]) and by the twin's truth at the same captures
//! ([`Measured::points`], [`Measured::truth_figures`]): the truth relative to the truth at the
//! zero reference, straightness relative to its own least-squares line, as the head reads them.
//!
//! Time is simulated in the measuring steps (a 1000 mm cycle takes seconds, not minutes);
//! publishing is real Modbus TCP traffic on a small Tokio runtime of its own.

use super::follower_cal::{Mapping, TwinMap, map_on_lab};
use super::lab::{AlignRound, Lab, LabError, LabRun, LabSpec, Progress, plan_span};
use super::machine_time::MachineTime;
use super::plant::{PlantSpec, Truth};
use super::plc::{TwinPlc, TwinPlcConfig, TwinPlcError};
use crate::comp::{
    AxisMapping, CompError, CompTable, MachineAxis, PositioningMode, TableSet, TableSpec,
    build_tables,
};
use crate::evaluate::uncertainty::{
    Budget, BudgetInputs, FollowerInput, ThermalInput, budget, psd2_sensitivity, stitched,
};
use crate::evaluate::{AxisEvaluation, EvalError, EvalOptions, ReferenceLine, evaluate_captures};
use crate::modbus::link::{Link, LinkConfig};
use crate::plc::map::CncMap;
use crate::plc::publish::{PublishError, PublishOutcome, Timeouts, publish};
use crate::plc::table::{PlcTable, TableError};
use crate::run::program::CaptureMode;
use crate::run::{Capture, Dialect, Direction, Plan};
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
    #[error("the uncertainty budget: PSD2's sensitivities: {0}")]
    Sensitivity(crate::decouple::DecoupleError),
    #[error("the drift check: the head gave no live reading at the reference")]
    Drift,
    #[error("mapping the follower: {0}")]
    Mapping(#[from] super::follower_cal::MapTwinError),
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
    /// Mapping the follower (before the first pass): stop `stop` of `stops`.
    Mapping { stop: usize, stops: usize },
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
    /// What the uncertainty budget is told beside the captures.
    pub budget: BudgetSpec,
    /// Map the follower after the alignment, before the first pass, and apply the map in
    /// tracking (`None`: the follower's own errors stay in the measurement; the budget
    /// states them from `budget.follower`). With a map the budget states the map's
    /// uncertainty instead.
    pub follower: Option<Mapping>,
}

/// The budget's inputs that are not in the captures.
#[derive(Clone, Debug, PartialEq)]
pub struct BudgetSpec {
    /// What is known of the follower's own errors (its specification until a map exists).
    pub follower: FollowerInput,
    /// Per DOF standard uncertainty of the calibration (internal units) and its source.
    pub calibration: Option<([f64; 6], String)>,
    pub thermal: Option<ThermalInput>,
    /// Before each pass, after the zero: the head reads the carriage at rest at the reference
    /// for this long (ISO 230-2's drift check; its range per DOF is E_VE).
    pub drift_check: Option<Duration>,
}

impl BudgetSpec {
    /// The twin's follower stated by its specification (`[twin.follower]`: ±positioning,
    /// ±vertical straightness), nothing else.
    pub fn of_plant(plant: &PlantSpec) -> BudgetSpec {
        BudgetSpec {
            follower: FollowerInput::Specification {
                // The bound of the along-axis error: the long-wavelength shape, the
                // screw-periodic term and half the reversal (each direction's share).
                positioning_mm: (plant.follower.positioning_um
                    + plant.follower.periodic_um
                    + 0.5 * plant.follower.reversal_um)
                    * 1e-3,
                straightness_mm: plant.follower.straightness_um * 1e-3,
            },
            calibration: None,
            thermal: None,
            drift_check: None,
        }
    }
}

/// One measuring run and its evaluation.
#[derive(Clone, Debug)]
pub struct Measured {
    pub run: LabRun,
    pub eval: AxisEvaluation,
    pub figures: Figures,
    /// The uncertainty budget of every point.
    pub budget: Budget,
    /// The twin's truth when the zero reference was taken.
    pub zero_truth: Truth,
    /// The drift check's range per DOF (internal units), when one was done.
    pub drift_range: Option<[f64; 6]>,
}

/// One DOF at one target and direction: the head's mean over the runs, the truth's mean over
/// the same captures, and the stated expanded uncertainty (internal units).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TruePoint {
    pub dof: usize,
    pub target_index: u32,
    pub target_mm: f64,
    pub direction: Direction,
    pub measured: f64,
    pub truth: f64,
    /// Expanded, k = 2.
    pub expanded: f64,
}

impl TruePoint {
    /// The truth lies within the stated U of the measured value.
    pub fn covered(&self) -> bool {
        (self.measured - self.truth).abs() <= self.expanded
    }
}

impl Measured {
    /// The captures with the truth's errors in place of the head's, relative to the truth at
    /// the zero reference (as the head's are relative to its zero).
    pub fn truth_captures(&self) -> Vec<Capture> {
        let z = self.zero_truth.errors.to_vector();
        self.run
            .captures
            .iter()
            .map(|c| Capture {
                errors: crate::units::Errors6::from_vector(&(c.truth.errors.to_vector() - z)),
                ..c.capture
            })
            .collect()
    }

    /// The figures of the truth at this run's captures.
    pub fn truth_figures(&self, line: ReferenceLine) -> Result<Figures, EvalError> {
        let eval = evaluate_captures(&self.truth_captures(), &EvalOptions::default())?;
        Ok(Figures::of(&eval, line))
    }

    /// Every DOF at every target and direction, measured against the truth. Straightness
    /// (dx, dz) is relative to the least-squares line of its bidirectional mean profile, the
    /// head's and the truth's each to its own (the line is the beam's alignment, ISO 230-1);
    /// the other DOFs relative to the zero reference.
    pub fn points(&self) -> Result<Vec<TruePoint>, EvalError> {
        let truth = evaluate_captures(&self.truth_captures(), &EvalOptions::default())?;
        let mut out = Vec::new();
        for k in 0..6 {
            let line = |e: &AxisEvaluation| -> (f64, f64) {
                let s = match k {
                    0 => &e.straightness_x,
                    2 => &e.straightness_z,
                    _ => return (0.0, 0.0),
                };
                let l = s.mean.line(ReferenceLine::LeastSquares);
                (l.slope, l.intercept_mm)
            };
            let (lm, lt) = (line(&self.eval), line(&truth));
            for d in [Direction::Up, Direction::Down] {
                let (Some(m), Some(t)) = (
                    self.eval.profiles[k].direction(d),
                    truth.profiles[k].direction(d),
                ) else {
                    continue;
                };
                for (i, &ti) in self.eval.target_indices.iter().enumerate() {
                    let p = self.eval.positions_mm[i];
                    let expanded = self
                        .budget
                        .point(k, ti, Some(d))
                        .map_or(f64::NAN, |b| b.expanded);
                    out.push(TruePoint {
                        dof: k,
                        target_index: ti,
                        target_mm: p,
                        direction: d,
                        measured: m[i] - (lm.0 * p + lm.1),
                        truth: t[i] - (lt.0 * p + lt.1),
                        expanded,
                    });
                }
            }
        }
        Ok(out)
    }
}

/// A table as published.
#[derive(Clone, Debug)]
pub struct Published {
    pub name: String,
    pub table: PlcTable,
    pub sequence: u32,
    /// Its payload's CRC as the PLC checked it.
    pub crc: u32,
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
    /// The follower's map, when the loop made one, with its machine time.
    pub follower: Option<TwinMap>,
    /// How long each phase kept the machine.
    pub machine_time: MachineTime,
    /// When each pass (before, after) started and ended on the lab's clock (µs since the
    /// Unix epoch, as its captures are dated): the runs' times in a store.
    pub passes_unix_us: [[i64; 2]; 2],
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
    let mut lab = Lab::new(&spec.lab).map_err(|source| LoopError::Lab {
        pass: Pass::Before,
        source,
    })?;
    let mount_at_start = lab.plant.mount();
    let mut machine_time = MachineTime::default();
    let follower = prepare_timed(&mut lab, spec, &mut step, &mut machine_time)?;
    let (t, u0) = (lab.now(), lab.unix_us());
    let before = measure(&mut lab, spec, Pass::Before, &mut step)?;
    machine_time.before = lab.now() - t;
    let before_us = [u0, lab.unix_us()];
    let mount_aligned = lab.plant.mount();
    let tables = tables_of(spec, &before.eval)?;
    // Real Modbus TCP on loopback: the wall clock.
    let wall = std::time::Instant::now();
    let published = publish_all(&lab, spec, &tables, 1, &mut step)?;
    machine_time.publish = wall.elapsed();
    let (t, u0) = (lab.now(), lab.unix_us());
    let after = measure(&mut lab, spec, Pass::After, &mut step)?;
    machine_time.after = lab.now() - t;
    let after_us = [u0, lab.unix_us()];
    Ok(LoopResult {
        before,
        tables,
        published,
        after,
        mount: [mount_at_start, mount_aligned],
        follower,
        machine_time,
        passes_unix_us: [before_us, after_us],
    })
}

/// Before the first pass: bring the lab up, align the head over the plan's travel (when
/// asked for), and map the follower (when asked for: the map is then in use in tracking).
pub fn prepare(
    lab: &mut Lab,
    spec: &LoopSpec,
    step: &mut impl FnMut(Step),
) -> Result<Option<TwinMap>, LoopError> {
    prepare_timed(lab, spec, step, &mut MachineTime::default())
}

/// [`prepare`], each phase's machine time into `times`.
fn prepare_timed(
    lab: &mut Lab,
    spec: &LoopSpec,
    step: &mut impl FnMut(Step),
    times: &mut MachineTime,
) -> Result<Option<TwinMap>, LoopError> {
    let lab_err = |source| LoopError::Lab {
        pass: Pass::Before,
        source,
    };
    let t = lab.now();
    lab.bring_up().map_err(lab_err)?;
    times.bring_up = lab.now() - t;
    if spec.align_rounds > 0 {
        let t = lab.now();
        let rounds = lab
            .align(plan_span(&spec.plan), spec.align_rounds, |r| {
                step(Step::Aligning(Box::new(r.clone())))
            })
            .map_err(lab_err)?;
        times.align = lab.now() - t;
        // The last round passed; the technician turned the screws after each before it.
        times.align_turns = rounds.len().saturating_sub(1);
    }
    let Some(m) = &spec.follower else {
        return Ok(None);
    };
    let t = lab.now();
    let mapped = map_on_lab(
        lab,
        m,
        &spec.lab.decoupler,
        spec.lab.live_window,
        |stop, stops| step(Step::Mapping { stop, stops }),
    )?;
    times.follower_map = lab.now() - t;
    times.map_reused = m.reuse.is_some();
    Ok(Some(mapped))
}

/// Move to the reference, zero (and the drift check when asked for), run the cycle,
/// evaluate, and make the uncertainty budget. One pass of [`run`] (after [`prepare`]), for
/// tests that need a measured run judged by the truth without the compensation. With a
/// follower map in use in the lab's tracker, the budget states the map's uncertainty.
pub fn measure(
    lab: &mut Lab,
    spec: &LoopSpec,
    pass: Pass,
    step: &mut impl FnMut(Step),
) -> Result<Measured, LoopError> {
    let lab_err = |source| LoopError::Lab { pass, source };
    // Before the zero: the check may traverse the travel.
    lab.pre_run_check(&spec.plan).map_err(lab_err)?;
    let reference = spec.plan.reference_mm;
    lab.move_carriage(reference).map_err(lab_err)?;
    lab.zero(reference, spec.zero_window).map_err(lab_err)?;
    let zero_truth = lab.truth();
    // Where the follower's encoder stands with the carriage at the reference.
    let encoder_offset = lab
        .drive_status()
        .position_mm
        .map_or(0.0, |e| e - reference);
    let drift_range = match spec.budget.drift_check {
        Some(d) => Some(drift_check(lab, reference, d).map_err(|e| match e {
            Some(source) => lab_err(source),
            None => LoopError::Drift,
        })?),
        None => None,
    };
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
    let b = &spec.budget;
    let mid = (spec.plan.spec.start_mm + spec.plan.spec.end_mm) / 2.0;
    let inputs = BudgetInputs {
        reference_mm: reference,
        psd2_sensitivity: psd2_sensitivity(&spec.lab.decoupler, mid)
            .map_err(LoopError::Sensitivity)?,
        follower: match lab.pipeline.tracker.map::<crate::follower::FollowerMap>() {
            Some(m) => {
                FollowerInput::of_map(m, encoder_offset, reference, 2.5, m.describe_sources())
            }
            None => b.follower.clone(),
        },
        calibration: b.calibration.clone(),
        thermal: b.thermal,
        drift_range,
    };
    let budget = budget(&eval, &stitched(&captures, &run.handovers), &inputs);
    Ok(Measured {
        run,
        eval,
        figures,
        budget,
        zero_truth,
        drift_range,
    })
}

/// ISO 230-2's drift check: the head reads the carriage at rest at `reference` for `d`; the
/// range of each DOF's live reading (sampled once a second) is E_VE. `Err(None)`: no reading.
fn drift_check(lab: &mut Lab, reference: f64, d: Duration) -> Result<[f64; 6], Option<LabError>> {
    lab.pipeline.measure.set_nominal(Some(reference));
    let mut lo = [f64::INFINITY; 6];
    let mut hi = [f64::NEG_INFINITY; 6];
    let seconds = d.as_secs().max(1);
    let mut result = Ok(());
    for _ in 0..seconds {
        if let Err(e) = lab.advance(Duration::from_secs(1)) {
            result = Err(Some(e));
            break;
        }
        if let Some(live) = lab.pipeline.measure.live() {
            for (k, v) in live.errors.to_array().into_iter().enumerate() {
                lo[k] = lo[k].min(v);
                hi[k] = hi[k].max(v);
            }
        }
    }
    lab.pipeline.measure.set_nominal(None);
    result?;
    if !lo[0].is_finite() {
        return Err(None);
    }
    Ok(std::array::from_fn(|k| hi[k] - lo[k]))
}

/// The tables of `set` that go to the PLC, with their names.
fn plc_tables(set: &TableSet) -> Vec<(String, &CompTable)> {
    std::iter::once(&set.positioning)
        .chain(&set.straightness)
        .map(|t| (t.name.clone(), t))
        .collect()
}

/// The tables of a measured run (positioning per `spec.positioning`, both straightnesses
/// against `spec.straightness_line`), zero at the plan's reference.
pub fn tables_of(spec: &LoopSpec, eval: &AxisEvaluation) -> Result<TableSet, LoopError> {
    let axis = &spec.plan.spec.axis;
    let mapping = AxisMapping::standard(
        MachineAxis::from_letter(axis).ok_or_else(|| LoopError::Axis(axis.clone()))?,
    );
    Ok(build_tables(
        eval,
        &TableSpec {
            mapping,
            reference_mm: spec.plan.reference_mm,
            positioning: spec.positioning,
            straightness_line: spec.straightness_line,
            functional_point_mm: None,
        },
    )?)
}

/// Publish every table of `set` into a twin PLC serving `lab`'s plant (a PLC of its own:
/// its tables replace every one in force), sequence `first`, `first + 1`, …
pub fn publish_all(
    lab: &Lab,
    spec: &LoopSpec,
    set: &TableSet,
    first: u32,
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
            let sequence = first + k as u32;
            match publish(&link, &map, &table, sequence, timeouts).await {
                Ok(PublishOutcome::Accepted { .. }) => {}
                Ok(other) => {
                    return Err(LoopError::Rejected {
                        table: name,
                        detail: match other {
                            PublishOutcome::Rejected {
                                code,
                                active_sequence,
                                ..
                            } => format!(
                                "refused with {code}; the PLC keeps sequence {active_sequence}"
                            ),
                            PublishOutcome::Accepted { .. } => "accepted".into(),
                        },
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
            // The CRC the PLC checked, as the publication encoded it (the same map and
            // sequence give the same payload).
            let crc = crate::plc::table::encode(&table, &map, sequence)
                .map(|e| e.crc)
                .map_err(|source| LoopError::PlcTable {
                    table: name.clone(),
                    source,
                })?;
            out.push(Published {
                name,
                table,
                sequence,
                crc,
            });
        }
        Ok(out)
    })
}
