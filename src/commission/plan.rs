//! The commissioning plan (issue 27): the set-ups of a machine in the order the technician
//! takes them, what each asks at the machine, the run each needs, and where the machine stands
//! from the runs attached so far.
//!
//! The order is the laser systems' (an XM-60's optical square, a CARTO volumetric test): X with
//! its beam aligned; Y and Z each through an optical square from X's beam (C0Y, B0Z); Z again
//! through a square from Y's beam (A0Z). On a set-up through a square the technician aligns
//! every screw but the one that would turn the beam in the square's plane: the square fixes that
//! direction. The model takes X, Y and the first Z set-up's tables; the second Z set-up gives A0Z
//! alone.

use super::record::MachineRecord;
use crate::comp::mapping::MachineAxis;
use crate::machine::squareness::SquarePair;
use crate::run::PlanSpec;

/// How a set-up's beam comes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Beam {
    /// Aligned to its axis by the technician.
    Aligned,
    /// Another set-up's beam (its index in [`SETUPS`]) turned by an optical square.
    Through(SquarePair, usize),
}

impl std::fmt::Display for Beam {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Beam::Aligned => f.write_str("beam aligned"),
            Beam::Through(pair, _) => write!(f, "through the optical square for {pair}"),
        }
    }
}

/// The commissioning order of the set-ups.
pub const SETUPS: [(MachineAxis, Beam); 4] = [
    (MachineAxis::X, Beam::Aligned),
    (MachineAxis::Y, Beam::Through(SquarePair::XY, 0)),
    (MachineAxis::Z, Beam::Through(SquarePair::ZX, 0)),
    (MachineAxis::Z, Beam::Through(SquarePair::YZ, 1)),
];

/// Set-up `index` of [`SETUPS`] (the last for an index beyond it: callers check the range
/// where it comes in, `refuse_attach`, the API's `check`).
pub fn setup_at(index: usize) -> (MachineAxis, Beam) {
    SETUPS[index.min(SETUPS.len() - 1)]
}

/// How many set-ups of [`SETUPS`] feed the model's tables (X, Y, the first Z).
pub const MODEL_SETUPS: usize = 3;

/// A set-up's run: each axis from 0 to its travel. The dwell leaves the follower its rest and
/// the capture its frames at 500 Hz (the service refuses less than 1.45 s there); the lead
/// spreads the targets off the screw's period (ISO 230-2).
pub fn run_plan(record: &MachineRecord, setup: usize) -> PlanSpec {
    let (axis, _) = setup_at(setup);
    let len = record.travel_mm[axis.index()];
    PlanSpec {
        axis: axis.to_string(),
        start_mm: 0.0,
        end_mm: len,
        targets: (len / record.target_every_mm).round() as usize + 1,
        runs: record.runs,
        overrun_mm: 2.0,
        dwell_s: 2.0,
        feed_mm_min: 6000.0,
        lead_mm: 10.0,
        reference_mm: None,
    }
}

/// A set-up's title: "2 of 4: Y through the optical square for XY".
pub fn title(setup: usize) -> String {
    let (axis, beam) = setup_at(setup);
    format!("{} of {}: {axis} {beam}", setup + 1, SETUPS.len())
}

/// The notes a run started for `setup` of machine `machine` carries (`run_start`'s notes), so
/// that it is attached nowhere else: "machine 2, set-up 3 of 4: Z through the optical square
/// for ZX".
pub fn run_notes(machine: i64, setup: usize) -> String {
    format!("machine {machine}, set-up {}", title(setup))
}

/// The set-up (0-based) a run's notes name ("set-up K of 4"), when they name one.
pub fn setup_named(notes: &str) -> Option<usize> {
    let at = notes.find("set-up ")? + "set-up ".len();
    let rest = &notes[at..];
    let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
    let after = &rest[digits.len()..];
    let k: usize = digits.parse().ok()?;
    (after.starts_with(&format!(" of {}", SETUPS.len())) && (1..=SETUPS.len()).contains(&k))
        .then(|| k - 1)
}

/// What the technician does at the machine for `setup`, step by step, in words.
pub fn steps(record: &MachineRecord, setup: usize) -> Vec<String> {
    let (axis, beam) = setup_at(setup);
    let plan = run_plan(record, setup);
    let mut out = Vec::new();
    match beam {
        Beam::Aligned => {
            out.push(format!(
                "Set the laser and the head's fixed part on the bed along {axis}, the moving part on the spindle; move {axis} to 0."
            ));
            out.push(format!(
                "Align the beam over {axis}'s travel (the alignment procedure: every screw, until the spot stays put end to end)."
            ));
        }
        Beam::Through(pair, from) => {
            let (first, _) = SETUPS[from];
            let c = &record.squares[pair.index()];
            out.push(format!(
                "Leave the laser as set up for {first} (set-up {}). Set the optical square {} (certificate: {:+.2}″ ± {:.2}″) in the beam so that it turns it along {axis}.",
                from + 1,
                c.id,
                c.deviation_rad / crate::units::RAD_PER_ARCSEC,
                c.u_rad / crate::units::RAD_PER_ARCSEC
            ));
            out.push(format!(
                "Mount the head on {axis}; align every screw but the one that turns the beam in the {pair} plane: the square fixes that direction, and {} comes from it.",
                pair.name()
            ));
        }
    }
    out.push(
        "Check the follower's map with the level (follower level), as on every set-up.".into(),
    );
    out.push(format!(
        "Run {} bidirectional run{} over 0–{:.0} mm, {} targets (a target every {:.0} mm), and attach the finished run to this set-up.",
        plan.runs,
        if plan.runs == 1 { "" } else { "s" },
        plan.end_mm,
        plan.targets,
        record.target_every_mm
    ));
    out
}

/// Where a set-up stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SetupState {
    /// Measured by stored run `run_id`.
    Measured { run_id: i64 },
    /// The next to take: every set-up before it is measured.
    Next,
    /// Waits for the set-ups before it.
    Waiting,
}

impl SetupState {
    pub fn words(&self) -> String {
        match self {
            SetupState::Measured { run_id } => format!("measured by run {run_id}"),
            SetupState::Next => "next".into(),
            SetupState::Waiting => "waiting".into(),
        }
    }
}

/// Each set-up's state from the runs attached to it (`attached[i]` for `SETUPS[i]`). The
/// plan is walked in order: the first set-up without a run is next.
pub fn states(attached: &[Option<i64>; 4]) -> [SetupState; 4] {
    let next = attached.iter().position(Option::is_none);
    std::array::from_fn(|i| match attached[i] {
        Some(run_id) => SetupState::Measured { run_id },
        None if Some(i) == next => SetupState::Next,
        None => SetupState::Waiting,
    })
}

/// Why `setup` may not take a run now, or `None`: set-ups are taken in order (a square's
/// set-up needs its beam's, and the plan walks the technician through them so).
pub fn refuse_attach(attached: &[Option<i64>; 4], setup: usize) -> Option<String> {
    if setup >= SETUPS.len() {
        return Some(format!(
            "there is no set-up {}: the plan has {} (1 to {})",
            setup + 1,
            SETUPS.len(),
            SETUPS.len()
        ));
    }
    if let Some(run_id) = attached[setup] {
        return Some(format!(
            "set-up {} is already measured by run {run_id}: detach it first to measure it again",
            setup + 1
        ));
    }
    match states(attached).iter().position(|s| *s == SetupState::Next) {
        Some(next) if next < setup => Some(format!(
            "set-up {} comes first ({}): the plan takes the set-ups in order",
            next + 1,
            title(next)
        )),
        _ => None,
    }
}
