//! The machine acceptance report (issue 27): a stored machine as its builder signs it — the
//! record and the runs that measured it, every set-up's ISO 230-2 positioning and ISO 230-1
//! figures with their expanded uncertainties, the 21 component errors, the squarenesses with
//! their budgets, the tool point's error over the volume before compensation (figures and a map
//! at three heights) and what each control's files leave of it, then the signatures.
//!
//! A `report::doc::Document`, so the HTML, Markdown and PDF renderers of the axis report place
//! it. The volumetric figures are the model's: what a control's compensation leaves of the
//! model's error, not a measurement after it — the report says so, and a verification run
//! measures the truth.

use super::plan::{self, MODEL_SETUPS};
use super::stored::{CommissionError, MachineState, SetupRun};
use crate::machine::exports::{self, Export};
use crate::machine::squareness::SquarePair;
use crate::machine::volume::{self, PlaneMap};
use crate::machine::{MachineModel, Squareness, component_names};
use crate::report::doc::{Block, Column, Document, Table};
use crate::report::text::{fixed, when};
use crate::report::{Format, write_acceptance};
use crate::store::Store;
use crate::units::RAD_PER_ARCSEC;
use std::path::{Path, PathBuf};

/// A number at `decimals` with a true minus sign.
fn num(v: f64, decimals: usize) -> String {
    fixed(v, decimals).replace('-', "−")
}

fn um(mm: f64) -> String {
    num(mm * 1e3, 2)
}

fn opt_um(mm: Option<f64>) -> String {
    mm.map_or_else(|| "–".into(), um)
}

fn arcsec(rad: f64) -> String {
    num(rad / RAD_PER_ARCSEC, 2)
}

/// What [`write`] wrote.
pub struct Written {
    /// The report's files: `acceptance.html`, `acceptance.md` and its charts, `acceptance.pdf`.
    pub report: Vec<PathBuf>,
    /// Each control's files, as read back.
    pub exports: Vec<Export>,
}

/// Machine `id`'s report written into `dir`: every control's files into `controls` first (each
/// read back; the report names them and states what they leave of the model's error), then
/// `acceptance.html`, `acceptance.md` (its charts beside it) and `acceptance.pdf`.
pub fn write(
    store: &Store,
    id: i64,
    dir: &Path,
    controls: &Path,
    generated_us: i64,
) -> Result<Written, CommissionError> {
    // Each set-up's run is read and evaluated once: for the fit and for the report.
    let (state, runs) = super::stored::state_with_runs(store, id)?;
    let model = state.model().map_err(CommissionError::NoModel)?;
    let machine_err = |source| CommissionError::Machine {
        machine: id,
        source,
    };
    std::fs::create_dir_all(controls).map_err(|e| {
        machine_err(crate::machine::MachineError::Io {
            path: controls.display().to_string(),
            problem: e.to_string(),
        })
    })?;
    let title = format!("axiscomp machine {id} ({})", state.record.name);
    let exports = exports::write_and_read_back(model, controls, &title, state.record.tool_mm)
        .map_err(machine_err)?;
    let doc = document(&MachineReport {
        state: &state,
        runs: &runs,
        exports: &exports,
        generated_us,
    })
    .map_err(CommissionError::NoModel)?;
    let report = write_acceptance(dir, &doc, &Format::ALL, generated_us)?;
    Ok(Written { report, exports })
}

/// What the report is made of.
pub struct MachineReport<'a> {
    pub state: &'a MachineState,
    /// The attached set-ups' runs, in the plan's order (`stored::state_with_runs`).
    pub runs: &'a [SetupRun],
    /// Each control's files as written for this model and read back, when they were.
    pub exports: &'a [Export],
    /// When the report is made (µs since the Unix epoch).
    pub generated_us: i64,
}

/// The document, or why there is none: a report needs the 21-error model.
pub fn document(r: &MachineReport) -> Result<Document, String> {
    let state = r.state;
    let model = state.model()?;
    let rec = &state.record;
    let mut doc = Document {
        title: format!("Machine acceptance report — {}", rec.name),
        subtitle: format!(
            "Machine {} ({}), the 21 geometric errors of ISO 230-1 from runs {}; made {}",
            state.id,
            rec.chain,
            state.runs_words(),
            when(r.generated_us)
        ),
        blocks: Vec::new(),
    };
    let b = &mut doc.blocks;
    identification(r, b);
    axes(r, b);
    components(model, b);
    squareness(state, b);
    volumetric(r, model, b);
    doc.sign_and_number(
        "The figures above were measured and evaluated as stated. The volumetric figures after \
         compensation are the model's; the machine's own are measured by a verification run \
         with the compensation active.",
    );
    Ok(doc)
}

fn identification(r: &MachineReport, b: &mut Vec<Block>) {
    let rec = &r.state.record;
    b.push(Block::Heading("The machine".into()));
    let t = rec.travel_mm;
    let tool = rec.tool_mm;
    let mut fields = vec![
        ("Machine".to_string(), rec.name.clone()),
        ("Kinematic chain".into(), rec.chain.to_string()),
        (
            "Travels".into(),
            format!("X {:.0} mm, Y {:.0} mm, Z {:.0} mm", t[0], t[1], t[2]),
        ),
        (
            "Tool offset".into(),
            format!(
                "({}, {}, {}) mm",
                num(tool[0], 1),
                num(tool[1], 1),
                num(tool[2], 1)
            ),
        ),
        (
            "Plan".into(),
            format!(
                "a target every {:.0} mm, {} bidirectional runs per set-up",
                rec.target_every_mm, rec.runs
            ),
        ),
        ("Record stored".into(), when(r.state.created_us)),
        (
            "Software".into(),
            format!("axiscomp {}", env!("CARGO_PKG_VERSION")),
        ),
    ];
    for pair in SquarePair::ALL {
        let sq = &rec.squares[pair.index()];
        fields.push((
            format!("Optical square for {pair}"),
            format!(
                "{}: deviation {}″, u {}″ (its certificate)",
                sq.id,
                arcsec(sq.deviation_rad),
                arcsec(sq.u_rad)
            ),
        ));
    }
    b.push(Block::Fields(fields));
    let rows = r
        .runs
        .iter()
        .map(|s| {
            let setup = s.setup;
            let rec = &s.data.record;
            vec![
                plan::title(setup),
                s.run.to_string(),
                when(rec.created_us),
                rec.notes.clone(),
            ]
        })
        .collect();
    b.push(Block::Subheading(
        "Set-ups and the runs that measured them".into(),
    ));
    b.push(Block::Table(Table {
        columns: vec![
            Column::text("Set-up"),
            Column::number("Run"),
            Column::text("Measured"),
            Column::text("Notes"),
        ],
        rows,
        note: Some(format!(
            "The model takes each axis's six errors from set-ups 1 to {MODEL_SETUPS}; each \
             squareness from the two set-ups that share its square's beam."
        )),
    }));
}

/// The largest expanded uncertainty of one error of a run's points, and k.
fn largest_u(s: &SetupRun, dof: usize) -> (f64, f64) {
    (s.budget.largest(dof).2, s.budget.k)
}

fn axes(r: &MachineReport, b: &mut Vec<Block>) {
    b.push(Block::Heading(
        "Each set-up's axis (ISO 230-2, ISO 230-1)".into(),
    ));
    b.push(Block::Paragraph(
        "Positioning figures bidirectional, in µm; straightness by the least-squares line, in \
         the head's two cross directions; angular errors as the range of the mean angle over the \
         travel, in arcsec. U: the largest expanded uncertainty of a mean point (ISO/TR 230-9)."
            .into(),
    ));
    let mut rows = Vec::new();
    let mut urows = Vec::new();
    let mut k = 2.0;
    for s in r.runs {
        let setup = s.setup;
        let (axis, _) = plan::setup_at(setup);
        let e = &s.data.eval;
        let a = &e.positioning.axis;
        let ls = |st: &crate::evaluate::iso230_1::DirectionalStraightness| {
            um(st
                .mean
                .line(crate::evaluate::iso230_1::ReferenceLine::LeastSquares)
                .straightness)
        };
        rows.push(vec![
            format!("{} ({axis})", setup + 1),
            opt_um(a.e),
            opt_um(a.m),
            opt_um(a.a),
            opt_um(a.r),
            opt_um(a.b),
            ls(&e.straightness_x),
            ls(&e.straightness_z),
            arcsec(e.pitch.mean),
            arcsec(e.yaw.mean),
            arcsec(e.roll.mean),
        ]);
        let mut u = vec![format!("{} ({axis})", setup + 1)];
        for dof in 0..6 {
            let (big, kk) = largest_u(s, dof);
            k = kk;
            u.push(if dof < 3 { um(big) } else { arcsec(big) });
        }
        urows.push(u);
    }
    b.push(Block::Table(Table {
        columns: vec![
            Column::text("Set-up"),
            Column::number("E (µm)"),
            Column::number("M (µm)"),
            Column::number("A (µm)"),
            Column::number("R (µm)"),
            Column::number("B (µm)"),
            Column::number("Str. x (µm)"),
            Column::number("Str. z (µm)"),
            Column::number("Pitch (″)"),
            Column::number("Yaw (″)"),
            Column::number("Roll (″)"),
        ],
        rows,
        note: Some(
            "E systematic deviation, M mean deviation, A accuracy, R repeatability, B reversal \
             (ISO 230-2). Str. x and z: the straightness in the head's x and z."
                .into(),
        ),
    }));
    b.push(Block::Subheading(
        "The budget: each error's largest U".into(),
    ));
    b.push(Block::Table(Table {
        columns: vec![
            Column::text("Set-up"),
            Column::number("dx (µm)"),
            Column::number("dy (µm)"),
            Column::number("dz (µm)"),
            Column::number("pitch (″)"),
            Column::number("roll (″)"),
            Column::number("yaw (″)"),
        ],
        rows: urows,
        note: Some(format!(
            "Expanded uncertainty U (k = {}) of a mean point, the largest over the travel; each \
             run's own report lists its terms point by point.",
            fixed(k, 1).trim_end_matches(".0")
        )),
    }));
}

fn components(model: &MachineModel, b: &mut Vec<Block>) {
    b.push(Block::Heading("The 21 geometric errors (ISO 230-1)".into()));
    let mut rows = Vec::new();
    for t in model.tables() {
        let names = component_names(t.axis());
        for (k, name) in names.iter().enumerate() {
            let (lo, hi) = t
                .values()
                .iter()
                .map(|v| v[k])
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
                    (a.min(x), b.max(x))
                });
            let (range, unit) = if k < 3 {
                (um(hi - lo), "µm")
            } else {
                (arcsec(hi - lo), "″")
            };
            rows.push(vec![name.clone(), t.axis().to_string(), range, unit.into()]);
        }
    }
    let sq = model.squareness.to_array();
    for (name, v) in Squareness::NAMES.iter().zip(sq) {
        rows.push(vec![(*name).into(), "–".into(), arcsec(v), "″".into()]);
    }
    b.push(Block::Table(Table {
        columns: vec![
            Column::text("Error"),
            Column::text("Axis"),
            Column::number("Range / value"),
            Column::text("Unit"),
        ],
        rows,
        note: Some(
            "A component error's range (max − min) over its axis's travel, in the machine's \
             frame; a squareness's value."
                .into(),
        ),
    }));
}

fn squareness(state: &MachineState, b: &mut Vec<Block>) {
    b.push(Block::Heading(
        "Squareness through the optical square".into(),
    ));
    let Ok(fit) = &state.fit else {
        return;
    };
    let rows = fit
        .squareness
        .iter()
        .map(|q| {
            vec![
                q.pair.name().to_string(),
                q.pair.to_string(),
                arcsec(q.value_rad),
                arcsec(q.u_rad),
                arcsec(q.expanded_rad),
                state.record.squares[q.pair.index()].id.clone(),
            ]
        })
        .collect();
    b.push(Block::Table(Table {
        columns: vec![
            Column::text("Error"),
            Column::text("Axes"),
            Column::number("Value (″)"),
            Column::number("u (″)"),
            Column::number("U, k = 2 (″)"),
            Column::text("Square"),
        ],
        rows,
        note: Some(
            "Each from the straightness slopes of two set-ups against one beam, the second turned \
             by the square, and the square's certified deviation."
                .into(),
        ),
    }));
    for q in &fit.squareness {
        b.push(Block::Subheading(format!(
            "The budget of {} ({})",
            q.pair.name(),
            q.pair
        )));
        b.push(Block::Table(Table {
            columns: vec![
                Column::text("Term"),
                Column::number("u (″)"),
                Column::text("Source"),
            ],
            rows: q
                .terms
                .iter()
                .map(|t| vec![t.name.clone(), arcsec(t.u_rad), t.source.clone()])
                .collect(),
            note: None,
        }));
    }
}

/// A map in µm: a row per Y, a column per X.
fn map_table(m: &PlaneMap) -> Table {
    let mut columns = vec![Column::text("Y / X (mm)")];
    columns.extend(m.x_mm.iter().map(|x| Column::number(&format!("{x:.0}"))));
    let rows = m
        .y_mm
        .iter()
        .zip(&m.error_mm)
        .map(|(y, row)| {
            let mut cells = vec![format!("{y:.0}")];
            cells.extend(row.iter().map(|e| num(e * 1e3, 1)));
            cells
        })
        .collect();
    Table {
        columns,
        rows,
        note: None,
    }
}

fn volumetric(r: &MachineReport, model: &MachineModel, b: &mut Vec<Block>) {
    let rec = &r.state.record;
    let (t, tool) = (rec.travel_mm, rec.tool_mm);
    b.push(Block::Heading(
        "The tool point's error over the volume".into(),
    ));
    let before = volume::survey(model, None, t, tool);
    b.push(Block::Paragraph(format!(
        "The length of the tool point's error, predicted by the 21-error model at the {} corners \
         of a regular grid over the travels ({} per axis, ends included), with the tool offset \
         ({}, {}, {}) mm.",
        before.points,
        volume::SIDE,
        num(tool[0], 1),
        num(tool[1], 1),
        num(tool[2], 1)
    )));
    let mut rows = vec![vec![
        "uncompensated".to_string(),
        num(before.max_mm * 1e3, 2),
        num(before.rms_mm * 1e3, 2),
        format!(
            "({:.0}, {:.0}, {:.0})",
            before.at_mm[0], before.at_mm[1], before.at_mm[2]
        ),
        "–".into(),
    ]];
    let mut files = Vec::new();
    for e in r.exports {
        let after = volume::survey(model, Some(e.applied.as_ref()), t, tool);
        let short = e.control.split_whitespace().next().unwrap_or(e.control);
        rows.push(vec![
            format!("after {short}"),
            num(after.max_mm * 1e3, 2),
            num(after.rms_mm * 1e3, 2),
            format!(
                "({:.0}, {:.0}, {:.0})",
                after.at_mm[0], after.at_mm[1], after.at_mm[2]
            ),
        ]);
        let name = e
            .path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        files.push((e.control.to_string(), format!("{name}: {}", e.carries)));
    }
    b.push(Block::Table(Table {
        columns: vec![
            Column::text("Compensation"),
            Column::number("Largest (µm)"),
            Column::number("RMS (µm)"),
            Column::text("Largest at X, Y, Z (mm)"),
        ],
        rows,
        note: Some(if r.exports.is_empty() {
            "No control's files were written with this report (axiscomp machine report writes \
             them beside it)."
                .into()
        } else {
            "After: what each control's files, read back as the control loads them, leave of \
             the model's error. The model's own uncertainty (section 2's U, section 4's) is not \
             in these figures."
                .into()
        }),
    }));
    if !files.is_empty() {
        b.push(Block::Subheading("The controls' files".into()));
        b.push(Block::Fields(files));
    }
    for z in [0.0, t[2] / 2.0, t[2]] {
        b.push(Block::Subheading(format!(
            "Map at Z = {z:.0} mm, uncompensated (µm)"
        )));
        b.push(Block::Table(map_table(&volume::plane_map(
            model, None, t, tool, z, 6, 5,
        ))));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_map_table_has_a_row_per_y_and_a_column_per_x_in_micrometres() {
        let m = PlaneMap {
            z_mm: 0.0,
            x_mm: vec![0.0, 500.0, 1000.0],
            y_mm: vec![0.0, 600.0],
            error_mm: vec![vec![0.001, 0.0125, -0.0], vec![0.02, 0.0, 0.00349]],
        };
        let t = map_table(&m);
        assert_eq!(t.columns.len(), 4);
        assert_eq!(t.columns[2].title, "500");
        assert_eq!(t.rows[0], vec!["0", "1.0", "12.5", "0.0"]);
        assert_eq!(t.rows[1], vec!["600", "20.0", "0.0", "3.5"]);
    }
}
