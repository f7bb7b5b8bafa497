//! The acceptance report's content: from a run's data (and optionally a second run to compare
//! with), the configuration's machine and tolerances, a `Document` with every figure formatted
//! at its precision and with its unit. Lengths in µm to 0.01 µm, angles in arcsec to 0.01″,
//! positions in mm to 0.001 mm; uncertainties say whether they are standard (u) or expanded
//! (U, with k).

use super::doc::{Block, Chart, ChartBand, ChartLine, Column, Document, Table};
use super::settings::{AcceptanceSettings, MachineSettings};
use super::source::{ActiveTables, FollowerMapInfo, RunData};
use super::text::{fixed, when};
use super::{Dof, text::arrow};
use crate::evaluate::iso230_1::{DirectionalStraightness, ReferenceLine, fit_line};
use crate::evaluate::recorded::{Recorded, Stated};
use crate::evaluate::uncertainty::{Budget, COMPONENTS, Component};
use crate::run::Direction;

/// Everything the report is made from.
pub struct Acceptance<'a> {
    pub machine: &'a MachineSettings,
    /// The head's serial number ("" when not configured).
    pub head_serial: &'a str,
    pub tolerances: &'a AcceptanceSettings,
    pub follower_map: Option<&'a FollowerMapInfo>,
    /// The run reported.
    pub run: &'a RunData,
    /// A run to compare it with (before/after).
    pub compare: Option<&'a RunData>,
    /// The operator named on the command line, over the one the audit log gives.
    pub operator: Option<&'a str>,
    /// When the report is made (µs since the Unix epoch).
    pub generated_us: i64,
}

const NOT_CONFIGURED: &str = "not configured";

fn or_not_configured(s: &str, key: &str) -> String {
    if s.is_empty() {
        format!("{NOT_CONFIGURED} ({key})")
    } else {
        s.to_string()
    }
}

/// A DOF's value (internal units) in its user unit at report precision, without the unit.
fn val(dof: Dof, internal: f64) -> String {
    fixed(dof.to_user(internal), 2).replace('-', "−")
}

fn opt(dof: Dof, v: Option<f64>) -> String {
    v.map_or_else(|| "–".into(), |v| val(dof, v))
}

/// A position in mm.
fn mm(v: f64) -> String {
    fixed(v, 3).replace('-', "−")
}

/// The expanded uncertainty (k) of one DOF: the largest over its points.
fn expanded(run: &RunData, dof: Dof) -> (f64, f64) {
    match &run.budget {
        Some(b) => (b.largest(dof.index()).2, b.k),
        None => (
            run.eval.profiles[dof.index()]
                .u_mean
                .iter()
                .copied()
                .fold(0.0, f64::max),
            2.0,
        ),
    }
}

/// The largest combined standard uncertainty of one DOF, when a budget was made.
fn standard(run: &RunData, dof: Dof) -> Option<f64> {
    run.budget.as_ref().map(|b| b.largest(dof.index()).1)
}

fn k_text(k: f64) -> String {
    fixed(k, 1).trim_end_matches(".0").to_string()
}

/// The document.
pub fn document(a: &Acceptance) -> Document {
    let r = a.run;
    let machine = if a.machine.name.is_empty() {
        "machine (name not configured)".to_string()
    } else {
        a.machine.name.clone()
    };
    let mut doc = Document {
        title: format!("Acceptance report — {machine}, axis {}", r.record.axis),
        subtitle: format!(
            "Run {} measured {}; ISO 230-2 positioning and ISO 230-1 geometric errors",
            r.record.id.0,
            when(r.record.created_us)
        ),
        blocks: Vec::new(),
    };
    let b = &mut doc.blocks;
    identification(a, b);
    instrument(a, b);
    plan(r, b);
    positioning(r, b);
    straightness(r, b);
    angular(r, b);
    environment(a, b);
    tables(r, b);
    verdicts(a, b);
    if let Some(c) = a.compare {
        comparison(c, r, b);
    }
    uncertainty(r, b);
    doc.sign_and_number(signing(a));
    doc
}

/// What signing accepts: the axis against the stated tolerances, or (with none configured,
/// when the report gives no verdict) the figures as measured.
fn signing(a: &Acceptance) -> &'static str {
    if a.tolerances.tolerances.is_empty() {
        "The figures above were measured and evaluated as stated; no tolerances were \
         configured, so signing accepts the figures as measured, not a verdict."
    } else {
        "The figures above were measured and evaluated as stated; signing accepts the axis \
         against the tolerances in section 9."
    }
}

fn identification(a: &Acceptance, b: &mut Vec<Block>) {
    let r = &a.run.record;
    let operator = a
        .operator
        .map(str::to_string)
        .or_else(|| a.run.operator.clone())
        .unwrap_or_else(|| "not recorded (give --operator)".into());
    b.push(Block::Heading("Machine and run".into()));
    let mut rows = vec![
        (
            "Machine".into(),
            or_not_configured(&a.machine.name, "machine.name"),
        ),
        (
            "Serial number".into(),
            or_not_configured(&a.machine.serial, "machine.serial"),
        ),
        (
            "Customer".into(),
            or_not_configured(&a.machine.customer, "machine.customer"),
        ),
        ("Axis".into(), r.axis.clone()),
        ("Run".into(), format!("{} ({})", r.id.0, r.state)),
        (
            "Measured".into(),
            format!(
                "{} to {} ({:.1} min of machine time)",
                when(r.created_us),
                when(r.updated_us),
                r.machine_time_s() / 60.0
            ),
        ),
        ("Operator".into(), operator),
    ];
    if !r.notes.is_empty() {
        rows.push(("Notes".into(), r.notes.clone()));
    }
    rows.push(("Report made".into(), when(a.generated_us)));
    b.push(Block::Fields(rows));
}

fn instrument(a: &Acceptance, b: &mut Vec<Block>) {
    b.push(Block::Heading("Instrument".into()));
    let mut rows = vec![(
        "Head".into(),
        format!(
            "six-DOF geometric-optics head, serial {}",
            or_not_configured(a.head_serial, "head.serial")
        ),
    )];
    let recorded = a.run.recorded.budget();
    let recorded_cal = recorded.and_then(|r| r.calibration.value());
    match &a.run.calibration {
        Some(c) => {
            let s = &c.summary;
            rows.push((
                "Calibration".into(),
                format!(
                    "id {}, made {}, stored {}; {} poses, rank {}, condition number {}",
                    c.id.0,
                    s.file_created,
                    when(c.created_us),
                    s.poses,
                    s.rank,
                    fixed(s.condition_number, 1)
                ),
            ));
            let res: Vec<String> = s.residual_rms_um.iter().map(|v| fixed(*v, 2)).collect();
            rows.push((
                "Fit residual RMS".into(),
                format!("{} µm (X1, Y1, X2, Y2, X3, Y3)", res.join(", ")),
            ));
        }
        None => rows.push((
            "Calibration".into(),
            match recorded_cal {
                Some(_) => {
                    "not in the store; the run recorded its term for the uncertainty budget".into()
                }
                None => "none: decoupled with the layout's own model".into(),
            },
        )),
    }
    rows.push(("Follower map".into(), follower_map_text(a)));
    rows.push((
        "Budget inputs".into(),
        match &a.run.recorded {
            Recorded::Yes(_) => "recorded with the run when it started (follower map, \
                                 calibration term, drift check, temperature inputs)"
                .into(),
            other => other.missing().unwrap_or_default(),
        },
    ));
    b.push(Block::Fields(rows));
}

/// A stored map's RFC 3339 date as the report shows dates.
fn rfc_when(created: &str) -> String {
    created.replace('T', " ").replace('Z', " UTC")
}

/// The follower map the run used (as it recorded it), against the one in use now.
fn follower_map_text(a: &Acceptance) -> String {
    let now = a.follower_map;
    let now_text = |m: &FollowerMapInfo| {
        format!(
            "id {} \"{}\" ({}), made {}",
            m.id,
            m.name,
            m.source,
            when(m.created_us)
        )
    };
    match a.run.recorded.budget().map(|r| &r.follower_map) {
        Some(Stated::Stated(m)) => {
            let used = format!(
                "id {} \"{}\" ({}), made {}; in use when the run started",
                m.id,
                m.name,
                m.source,
                rfc_when(&m.created)
            );
            match now {
                Some(n) if n.id == m.id => format!("{used}, and still in use"),
                Some(n) => format!("{used}; the map in use now differs: {}", now_text(n)),
                None => format!("{used}; no map is in use now"),
            }
        }
        Some(Stated::NotStated(why)) => {
            let none = format!("none in use when the run started ({why})");
            match now {
                Some(n) => format!("{none}; in use now: {}", now_text(n)),
                None => none,
            }
        }
        None => {
            let not = "not recorded with the run (stored before runs recorded it)";
            match now {
                Some(m) if m.created_us <= a.run.record.created_us => format!(
                    "{not}; the map in use now, {}, existed when the run was made",
                    now_text(m)
                ),
                Some(m) => format!(
                    "{not}; the map in use now (id {}) was made {}, after the run",
                    m.id,
                    when(m.created_us)
                ),
                None => format!("{not}; none in use now"),
            }
        }
    }
}

fn plan(r: &RunData, b: &mut Vec<Block>) {
    b.push(Block::Heading("Test plan".into()));
    let positions: Vec<f64> = match &r.plan {
        Some(p) => {
            let s = &p.spec;
            b.push(Block::Fields(vec![
                (
                    "Travel".into(),
                    format!("{} to {} mm", mm(s.start_mm), mm(s.end_mm)),
                ),
                (
                    "Targets".into(),
                    format!(
                        "{} ({})",
                        s.targets,
                        if s.lead_mm > 0.0 {
                            format!(
                                "non-uniform spacing for a {} mm lead, ISO 230-2",
                                fixed(s.lead_mm, 1)
                            )
                        } else {
                            "uniform spacing".into()
                        }
                    ),
                ),
                (
                    "Runs".into(),
                    format!("{} bidirectional (ISO 230-2 asks for 5)", s.runs),
                ),
                ("Overrun".into(), format!("{} mm", fixed(s.overrun_mm, 1))),
                (
                    "Feed, dwell".into(),
                    format!(
                        "{} mm/min, {} s at each target",
                        fixed(s.feed_mm_min, 0),
                        fixed(s.dwell_s, 1)
                    ),
                ),
                (
                    "Reference point".into(),
                    format!("{} mm (tables are zero there)", mm(p.reference_mm)),
                ),
            ]));
            p.targets.clone()
        }
        None => {
            b.push(Block::Paragraph(
                "The stored plan could not be read; the targets below are those of the captures."
                    .into(),
            ));
            r.eval.positions_mm.clone()
        }
    };
    let rows = positions
        .iter()
        .enumerate()
        .map(|(i, p)| {
            vec![
                (i + 1).to_string(),
                mm(*p),
                if i == 0 {
                    "–".into()
                } else {
                    mm(p - positions[i - 1])
                },
            ]
        })
        .collect();
    b.push(Block::Table(Table {
        columns: vec![
            Column::number("Target"),
            Column::number("Position (mm)"),
            Column::number("Spacing (mm)"),
        ],
        rows,
        note: None,
    }));
}

fn positioning(r: &RunData, b: &mut Vec<Block>) {
    let dof = Dof::Dy;
    let p = &r.eval.positioning;
    let a = &p.axis;
    let (u_big, k) = expanded(r, dof);
    b.push(Block::Heading("Positioning (ISO 230-2)".into()));
    b.push(Block::Paragraph(format!(
        "Deviation x = measured − target position; {} runs{}. ISO 230-2 figures in µm, per \
         approach direction (↑: approaching in the increasing direction, ↓: in the decreasing \
         one) and bidirectional.",
        p.runs.len(),
        if r.eval.thermal.applied {
            ", normalised to 20 °C (section 7)"
        } else {
            ""
        }
    )));
    let row = |name: &str, up: Option<f64>, down: Option<f64>, bi: Option<f64>| {
        vec![name.to_string(), opt(dof, up), opt(dof, down), opt(dof, bi)]
    };
    b.push(Block::Table(Table {
        columns: vec![
            Column::text("Figure"),
            Column::number("↑ (µm)"),
            Column::number("↓ (µm)"),
            Column::number("Bidirectional (µm)"),
        ],
        rows: vec![
            row("A  accuracy", a.a_up, a.a_down, a.a),
            row("E  systematic deviation", a.e_up, a.e_down, a.e),
            row("R  repeatability", a.r_up, a.r_down, a.r),
            row("M  mean deviation", None, None, a.m),
            row("B  reversal value", None, None, a.b),
            row("B̄  mean reversal value", None, None, a.b_mean),
        ],
        note: Some(format!(
            "Expanded uncertainty of a target's mean deviation U = {} µm at most (k = {}, about \
             95 %); a figure made of two means (E, M, B) carries up to 1.41·U.",
            val(dof, u_big),
            k_text(k)
        )),
    }));
    b.push(Block::Subheading("Per target".into()));
    let rows = p
        .targets
        .iter()
        .map(|t| {
            let u = match &r.budget {
                Some(bu) => bu.point(dof.index(), t.index, None).map(|p| p.expanded),
                None => r.eval.profiles[dof.index()]
                    .u_mean
                    .get(t.index as usize)
                    .copied(),
            };
            vec![
                (t.index + 1).to_string(),
                mm(t.position_mm),
                opt(dof, t.x_up),
                opt(dof, t.x_down),
                opt(dof, t.x_mean),
                opt(dof, t.b),
                opt(dof, t.s_up),
                opt(dof, t.s_down),
                opt(dof, t.r),
                opt(dof, u),
            ]
        })
        .collect();
    b.push(Block::Table(Table {
        columns: vec![
            Column::number("No."),
            Column::number("Target (mm)"),
            Column::number("Mean ↑"),
            Column::number("Mean ↓"),
            Column::number("Mean"),
            Column::number("B"),
            Column::number("s↑"),
            Column::number("s↓"),
            Column::number("R"),
            Column::number(&format!("U (k = {})", k_text(k))),
        ],
        rows,
        note: Some(
            "All in µm. Mean: the mean deviation over the runs (bidirectional: of both \
             directions); B: reversal value; s: standard deviation of the runs (the machine's \
             scatter); R: repeatability at the target; U: expanded uncertainty of the \
             bidirectional mean (instrument and scatter)."
                .into(),
        ),
    }));
    let (mut lines, mut bands) = (Vec::new(), Vec::new());
    for (d, colour) in [(Direction::Up, 0), (Direction::Down, 1)] {
        let pts: Vec<(f64, f64, f64)> = p
            .targets
            .iter()
            .filter_map(|t| {
                let (x, s) = match d {
                    Direction::Up => (t.x_up?, t.s_up.unwrap_or(0.0)),
                    Direction::Down => (t.x_down?, t.s_down.unwrap_or(0.0)),
                };
                Some((t.position_mm, dof.to_user(x), dof.to_user(s)))
            })
            .collect();
        if pts.is_empty() {
            continue;
        }
        let name = arrow(d);
        lines.push(ChartLine {
            label: format!("mean {name} ± 2s"),
            colour,
            dashed: false,
            markers: true,
            points: pts.iter().map(|&(x, y, _)| (x, y)).collect(),
        });
        bands.push(ChartBand {
            colour,
            opacity: 0.2,
            points: pts
                .iter()
                .map(|&(x, y, s)| (x, y - 2.0 * s, y + 2.0 * s))
                .collect(),
        });
    }
    b.push(Block::Chart(Chart {
        title: "Positioning deviation".into(),
        x_label: "position (mm)".into(),
        y_label: "deviation (µm)".into(),
        lines,
        bands,
        note: "Mean deviation per direction with the ±2s band of the runs; as measured (no \
               reference line removed)."
            .into(),
    }));
}

fn straightness(r: &RunData, b: &mut Vec<Block>) {
    b.push(Block::Heading("Straightness (ISO 230-1)".into()));
    let mut rows = Vec::new();
    let mut charts = Vec::new();
    for (dof, st) in [
        (Dof::Dx, &r.eval.straightness_x),
        (Dof::Dz, &r.eval.straightness_z),
    ] {
        let (u, k) = expanded(r, dof);
        for (method, name) in [
            (ReferenceLine::LeastSquares, "least squares"),
            (ReferenceLine::EndPoint, "end points"),
        ] {
            let dir = |s: &Option<crate::evaluate::iso230_1::Straightness>| {
                opt(dof, s.as_ref().map(|s| s.line(method).straightness))
            };
            let m = st.mean.line(method);
            rows.push(vec![
                format!("{} ({})", dof.meaning(), dof.name()),
                name.into(),
                dir(&st.up),
                dir(&st.down),
                val(dof, m.straightness),
                fixed(m.slope_um_per_m(), 2).replace('-', "−"),
                format!("{} (k = {})", val(dof, u), k_text(k)),
            ]);
        }
        charts.push(straightness_chart(r, dof, st));
    }
    b.push(Block::Table(Table {
        columns: vec![
            Column::text("Error"),
            Column::text("Reference line"),
            Column::number("↑ (µm)"),
            Column::number("↓ (µm)"),
            Column::number("Mean (µm)"),
            Column::number("Slope (µm/m)"),
            Column::number("U (µm)"),
        ],
        rows,
        note: Some(
            "Straightness: the range of the deviations from the reference line. The slope is \
             the reference line's (the beam's alignment to the travel), removed before the \
             range is taken. U: largest expanded uncertainty of a mean point."
                .into(),
        ),
    }));
    b.extend(charts.into_iter().map(Block::Chart));
}

fn straightness_chart(r: &RunData, dof: Dof, st: &DirectionalStraightness) -> Chart {
    let ls = st.mean.line(ReferenceLine::LeastSquares);
    let pos = &r.eval.positions_mm;
    let prof = &r.eval.profiles[dof.index()];
    let rel = |vals: &[f64]| -> Vec<(f64, f64)> {
        pos.iter()
            .zip(vals)
            .map(|(p, v)| (*p, dof.to_user(v - (ls.intercept_mm + ls.slope * p))))
            .collect()
    };
    let mut lines = Vec::new();
    for (d, colour) in [(Direction::Up, 0), (Direction::Down, 1)] {
        if let Some(v) = prof.direction(d) {
            lines.push(ChartLine {
                label: format!("mean {}", arrow(d)),
                colour,
                dashed: true,
                markers: false,
                points: rel(v),
            });
        }
    }
    lines.push(ChartLine {
        label: "bidirectional mean".into(),
        colour: 2,
        dashed: false,
        markers: true,
        points: rel(&prof.mean),
    });
    // The check that the drawn mean is the one the figure was taken from.
    let fit = fit_line(pos, &prof.mean, ReferenceLine::LeastSquares);
    let slope = fit.map_or(ls.slope_um_per_m(), |f| f.slope_um_per_m());
    Chart {
        title: format!("{} ({})", capitalise(dof.meaning()), dof.name()),
        x_label: "position (mm)".into(),
        y_label: "deviation from the line (µm)".into(),
        lines,
        bands: Vec::new(),
        note: format!(
            "Relative to the least-squares reference line of the bidirectional mean: slope {} \
             µm/m and {} µm at 0 mm removed; straightness {} µm.",
            fixed(slope, 2).replace('-', "−"),
            fixed(ls.intercept_mm * 1e3, 2).replace('-', "−"),
            val(dof, ls.straightness)
        ),
    }
}

fn capitalise(s: &str) -> String {
    let mut c = s.chars();
    c.next()
        .map(|f| f.to_uppercase().collect::<String>() + c.as_str())
        .unwrap_or_default()
}

fn angular(r: &RunData, b: &mut Vec<Block>) {
    b.push(Block::Heading("Angular errors (ISO 230-1)".into()));
    let mut rows = Vec::new();
    let mut lines = Vec::new();
    for (i, (dof, a)) in [
        (Dof::Ex, &r.eval.pitch),
        (Dof::Ey, &r.eval.roll),
        (Dof::Ez, &r.eval.yaw),
    ]
    .into_iter()
    .enumerate()
    {
        let (u, k) = expanded(r, dof);
        rows.push(vec![
            format!("{} ({})", dof.meaning(), dof.name()),
            opt(dof, a.up),
            opt(dof, a.down),
            val(dof, a.mean),
            format!("{} (k = {})", val(dof, u), k_text(k)),
        ]);
        lines.push(ChartLine {
            label: format!("{} ({})", dof.meaning(), dof.name()),
            colour: i + 2,
            dashed: false,
            markers: true,
            points: r
                .eval
                .positions_mm
                .iter()
                .zip(&r.eval.profiles[dof.index()].mean)
                .map(|(p, v)| (*p, dof.to_user(*v)))
                .collect(),
        });
    }
    b.push(Block::Table(Table {
        columns: vec![
            Column::text("Error"),
            Column::number("↑ (arcsec)"),
            Column::number("↓ (arcsec)"),
            Column::number("Mean (arcsec)"),
            Column::number("U (arcsec)"),
        ],
        rows,
        note: Some(
            "Angular error: the range (max − min) of the mean angle over the travel. U: largest \
             expanded uncertainty of a mean point."
                .into(),
        ),
    }));
    b.push(Block::Chart(Chart {
        title: "Angular errors".into(),
        x_label: "position (mm)".into(),
        y_label: "angle (arcsec)".into(),
        lines,
        bands: Vec::new(),
        note: "Bidirectional mean angle at each target, relative to the zero reference.".into(),
    }));
}

/// "19.8 to 20.4 °C, mean 20.1 °C" over the values present.
fn span(vals: impl Iterator<Item = f64>) -> Option<String> {
    let v: Vec<f64> = vals.collect();
    if v.is_empty() {
        return None;
    }
    let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let mean = v.iter().sum::<f64>() / v.len() as f64;
    Some(format!(
        "{} to {} °C, mean {} °C ({} captures)",
        fixed(lo, 2),
        fixed(hi, 2),
        fixed(mean, 2),
        v.len()
    ))
}

fn environment(a: &Acceptance, b: &mut Vec<Block>) {
    let r = a.run;
    b.push(Block::Heading("Environment".into()));
    let t = &r.eval.thermal;
    let air = span(r.captures.iter().filter_map(|c| c.air_c))
        .unwrap_or_else(|| "not measured (no air sensor in the captures)".into());
    let material = span(r.captures.iter().filter_map(|c| c.material_c))
        .unwrap_or_else(|| "not measured (no material sensor in the captures)".into());
    let alpha = match a.machine.expansion_um_per_m_k {
        Some(v) => format!("{} µm/(m·K) (machine.expansion_um_per_m_k)", fixed(v, 2)),
        None => format!("{NOT_CONFIGURED} (machine.expansion_um_per_m_k)"),
    };
    let normalisation = if t.applied {
        format!(
            "applied: positioning normalised to 20 °C, largest correction {} µm",
            fixed(t.max_correction_mm * 1e3, 2)
        )
    } else {
        t.note.clone()
    };
    b.push(Block::Fields(vec![
        ("Air temperature".into(), air),
        ("Material temperature".into(), material),
        ("Expansion coefficient".into(), alpha),
        ("Normalisation to 20 °C".into(), normalisation),
    ]));
}

fn tables(r: &RunData, b: &mut Vec<Block>) {
    b.push(Block::Heading("Compensation tables in use".into()));
    let (list, source) = match &r.tables {
        ActiveTables::Recorded(v) => (v, "Read back from the PLC when the run started."),
        ActiveTables::Inferred(v) => (
            v,
            "From the publication log: the last table of each kind and axis the PLC accepted \
             before the run started (the log does not see changes made at the CNC).",
        ),
    };
    if list.is_empty() {
        b.push(Block::Paragraph(match &r.tables {
            ActiveTables::Recorded(_) => format!(
                "None: the PLC applied no table from axiscomp when the run started. {source}"
            ),
            // The log sees only what axiscomp published: a run stored by another program
            // (the demo's lab) or tables loaded at the CNC leave it empty.
            ActiveTables::Inferred(_) => "Not recorded: the run holds no read-back of the PLC, \
                 and the publication log has no table accepted before it. Tables loaded at the \
                 CNC, or by a program other than the service, are not known here."
                .to_string(),
        }));
        return;
    }
    b.push(Block::Table(Table {
        columns: vec![
            Column::text("Kind"),
            Column::text("Axis"),
            Column::number("Table"),
            Column::number("Sequence"),
            Column::text("Published"),
            Column::text("From run"),
            Column::text("CRC"),
        ],
        rows: list
            .iter()
            .map(|t| {
                vec![
                    t.kind.clone(),
                    t.axis.clone(),
                    t.table_id.map_or("–".into(), |id| id.to_string()),
                    t.sequence.to_string(),
                    when(t.published_us),
                    t.source_run.map_or("–".into(), |r| r.to_string()),
                    format!("{:08X}", t.crc),
                ]
            })
            .collect(),
        note: Some(format!(
            "{source} The run's deviations are what remained under these tables."
        )),
    }));
}

/// One figure's measured value (user unit) and largest expanded U, for the verdicts.
struct Measured {
    label: String,
    value: f64,
    u: f64,
    unit: &'static str,
    figure: &'static str,
}

fn measured(r: &RunData) -> Vec<Measured> {
    let mut out = Vec::new();
    let a = &r.eval.positioning.axis;
    let (u, _) = expanded(r, Dof::Dy);
    for (figure, label, v) in [
        ("A", "A  accuracy (bidirectional)", a.a),
        ("E", "E  systematic deviation (bidirectional)", a.e),
        ("R", "R  repeatability (bidirectional)", a.r),
        ("B", "B  reversal value", a.b),
        ("M", "M  mean deviation", a.m),
    ] {
        if let Some(v) = v {
            out.push(Measured {
                label: label.into(),
                value: v * 1e3,
                u: u * 1e3,
                unit: "µm",
                figure,
            });
        }
    }
    for (dof, st) in [
        (Dof::Dx, &r.eval.straightness_x),
        (Dof::Dz, &r.eval.straightness_z),
    ] {
        out.push(Measured {
            label: format!("{} ({}), least squares", dof.meaning(), dof.name()),
            value: dof.to_user(st.mean.line(ReferenceLine::LeastSquares).straightness),
            u: dof.to_user(expanded(r, dof).0),
            unit: "µm",
            figure: "straightness",
        });
    }
    for (dof, a, figure) in [
        (Dof::Ex, &r.eval.pitch, "pitch"),
        (Dof::Ey, &r.eval.roll, "roll"),
        (Dof::Ez, &r.eval.yaw, "yaw"),
    ] {
        out.push(Measured {
            label: format!("{} ({})", dof.meaning(), dof.name()),
            value: dof.to_user(a.mean),
            u: dof.to_user(expanded(r, dof).0),
            unit: "arcsec",
            figure,
        });
    }
    out
}

fn verdicts(a: &Acceptance, b: &mut Vec<Block>) {
    b.push(Block::Heading("Tolerances".into()));
    if a.tolerances.tolerances.is_empty() {
        b.push(Block::Paragraph(
            "No tolerances are configured ([acceptance] in the configuration): the report \
             gives no pass or fail verdict."
                .into(),
        ));
        return;
    }
    let mut rows = Vec::new();
    let (mut passed, mut failed) = (0, 0);
    for m in measured(a.run) {
        let Some(t) = a.tolerances.of(m.figure) else {
            continue;
        };
        let ok = m.value <= t.limit;
        if ok {
            passed += 1;
        } else {
            failed += 1;
        }
        rows.push(vec![
            m.label,
            format!("{} {}", fixed(m.value, 2), m.unit),
            format!("{} {}", fixed(m.u, 2), m.unit),
            format!("{} {}", fixed(t.limit, 2), t.unit),
            if ok { "pass" } else { "FAIL" }.into(),
        ]);
    }
    b.push(Block::Table(Table {
        columns: vec![
            Column::text("Figure"),
            Column::number("Measured"),
            Column::number("U (k = 2)"),
            Column::number("Tolerance"),
            Column::text("Result"),
        ],
        rows,
        note: Some(
            "Pass: the measured figure is at most the tolerance. The expanded uncertainty U is \
             stated beside it; no guard band is applied (ISO 14253-1 decision rules are for \
             the parties to agree)."
                .into(),
        ),
    }));
    b.push(Block::Paragraph(if failed == 0 {
        format!("Result: all {passed} toleranced figures pass.")
    } else {
        format!(
            "Result: {failed} of {} toleranced figures fail.",
            passed + failed
        )
    }));
}

/// A change with its sign ("+0.52", "−8.00", "0.00").
fn signed(v: f64) -> String {
    let s = fixed(v, 2);
    if s.starts_with('-') {
        s.replace('-', "−")
    } else if s.chars().any(|c| c.is_ascii_digit() && c != '0') {
        format!("+{s}")
    } else {
        s
    }
}

fn comparison(before: &RunData, after: &RunData, b: &mut Vec<Block>) {
    let (first, second) = if before.record.created_us <= after.record.created_us {
        (before, after)
    } else {
        (after, before)
    };
    let label = |r: &RunData| {
        format!(
            "run {} ({})",
            r.record.id.0,
            &when(r.record.created_us)[..10]
        )
    };
    b.push(Block::Heading("Before and after".into()));
    b.push(Block::Paragraph(format!(
        "Run {} (before, {}) against run {} (after, {}), axis {}; each evaluated as in the \
         sections above.",
        first.record.id.0,
        when(first.record.created_us),
        second.record.id.0,
        when(second.record.created_us),
        second.record.axis
    )));
    let (m1, m2) = (measured(first), measured(second));
    let rows = m1
        .iter()
        .filter_map(|x| {
            let y = m2.iter().find(|y| y.label == x.label)?;
            Some(vec![
                x.label.clone(),
                fixed(x.value, 2),
                fixed(y.value, 2),
                signed(y.value - x.value),
                x.unit.to_string(),
            ])
        })
        .collect();
    b.push(Block::Table(Table {
        columns: vec![
            Column::text("Figure"),
            Column::number(&format!("Before: {}", label(first))),
            Column::number(&format!("After: {}", label(second))),
            Column::number("Change"),
            Column::text("Unit"),
        ],
        rows,
        note: Some("Change: after − before; negative is better.".into()),
    }));
    let line = |r: &RunData, colour, label: String| ChartLine {
        label,
        colour,
        dashed: false,
        markers: true,
        points: r
            .eval
            .positioning
            .targets
            .iter()
            .filter_map(|t| Some((t.position_mm, t.x_mean? * 1e3)))
            .collect(),
    };
    b.push(Block::Chart(Chart {
        title: "Positioning before and after".into(),
        x_label: "position (mm)".into(),
        y_label: "mean deviation (µm)".into(),
        lines: vec![
            line(first, 3, format!("before: {}", label(first))),
            line(second, 2, format!("after: {}", label(second))),
        ],
        bands: Vec::new(),
        note: "Bidirectional mean deviation at each target, as measured.".into(),
    }));
}

fn uncertainty(r: &RunData, b: &mut Vec<Block>) {
    b.push(Block::Heading("Uncertainty".into()));
    let k = r.budget.as_ref().map_or(2.0, |b| b.k);
    let rows = Dof::ALL
        .iter()
        .map(|&dof| {
            vec![
                format!("{} ({})", dof.meaning(), dof.name()),
                standard(r, dof).map_or("–".into(), |u| val(dof, u)),
                val(dof, expanded(r, dof).0),
                dof.unit().to_string(),
            ]
        })
        .collect();
    b.push(Block::Table(Table {
        columns: vec![
            Column::text("Error"),
            Column::number("u, standard (largest)"),
            Column::number(&format!("U, expanded, k = {} (largest)", k_text(k))),
            Column::text("Unit"),
        ],
        rows,
        note: Some(
            "u: combined standard uncertainty of a mean point (ISO/TR 230-9 budget: PSD noise, \
             decoupling, stitching, follower, thermal, drift); U = k·u. Every term and point: the \
             command axiscomp report --json."
                .into(),
        ),
    }));
    if let Some(bu) = &r.budget {
        budget_tables(bu, b);
    }
}

/// A budget term in its DOF's unit to 0.001.
fn val3(dof: Dof, internal: f64) -> String {
    fixed(dof.to_user(internal), 3).replace('-', "−")
}

/// The budget per DOF: each component's largest standard uncertainty, the combined u and U,
/// then where each component comes from, in words.
fn budget_tables(bu: &Budget, b: &mut Vec<Block>) {
    let k = k_text(bu.k);
    b.push(Block::Subheading(format!(
        "Budget per ISO/TR 230-9 (k = {k})"
    )));
    let largest: Vec<_> = Dof::ALL.iter().map(|d| bu.largest(d.index())).collect();
    let mut rows: Vec<Vec<String>> = Component::ALL
        .iter()
        .map(|&c| {
            let mut row = vec![c.name().to_string()];
            for (dof, l) in Dof::ALL.iter().zip(&largest) {
                row.push(if bu.stated(c) {
                    val3(*dof, l.0[c.index()])
                } else {
                    "–".into()
                });
            }
            row
        })
        .collect();
    let mut total = |label: String, pick: fn(&([f64; COMPONENTS], f64, f64)) -> f64| {
        let mut row = vec![label];
        for (dof, l) in Dof::ALL.iter().zip(&largest) {
            row.push(val3(*dof, pick(l)));
        }
        rows.push(row);
    };
    total("combined standard uncertainty u".into(), |l| l.1);
    total(format!("expanded uncertainty U (k = {k})"), |l| l.2);
    let mut columns = vec![Column::text("Component")];
    columns.extend(
        Dof::ALL
            .iter()
            .map(|d| Column::number(&format!("{} ({})", d.name(), d.unit()))),
    );
    b.push(Block::Table(Table {
        columns,
        rows,
        note: Some(format!(
            "Standard uncertainties (k = 1) of each component, the largest over the DOF's \
             points (every target, each direction and their mean); u = √(Σ terms²) and \
             U = {k}·u, largest over the points. –: not stated or not recorded, so not in u \
             (its source below says why)."
        )),
    }));
    // Where each term comes from: label and value pairs, which wrap (a table cell is cut).
    let sources = bu.sources();
    b.push(Block::Paragraph(
        "Where each component comes from (its formula, then its source; S: PSD2's sensitivity \
         of the DOF, L: the distance from the zero reference, n: runs, φ: the beam's angle to \
         the travel, α: the scale's expansion coefficient):"
            .into(),
    ));
    b.push(Block::Fields(
        Component::ALL
            .iter()
            .map(|c| {
                (
                    c.name().to_string(),
                    format!("{} — {}", c.formula(), sources[c.index()]),
                )
            })
            .collect(),
    ));
}
