//! The whole machine (issue 27): the twin's three-axis machines, their 21 errors as a model,
//! the Beckhoff volumetric file written to disk, read back and applied by the twin's CNC (the
//! truth's tables, a perfect measurement: the model, the file and the compensation held); and
//! the machine measured through the product's path with an optical square (ignored: run
//! optimised by .ci/run).

use crate::helpers::TempDir;
use axiscomp::comp::mapping::MachineAxis;
use axiscomp::machine::{
    ComponentTable, Grid, MachineModel, Squareness, Volumetric, component_names, exports, isg_csv,
};
use axiscomp::sim::Rng;
use axiscomp::sim::machine::{MachineSpec, TwinMachine};
use axiscomp::sim::machine_lab::{MachineLabSpec, measure_machine};
use axiscomp::store::Store;
use axiscomp::units::RAD_PER_ARCSEC;

/// Max and RMS (µm) of the tool point's error over `points` with `tool`, uncompensated or
/// compensated by `model`.
fn volumetric(
    twin: &TwinMachine,
    points: &[[f64; 3]],
    tool: [f64; 3],
    model: Option<&dyn Volumetric>,
) -> (f64, f64) {
    let f = twin.volumetric(points, tool, model);
    (f.max_mm * 1e3, f.rms_mm * 1e3)
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

/// Every control's files written to disk and read back by their own readers (`machine::exports`),
/// applied by the twin's CNC against the model they came from, on both machines: Beckhoff's
/// and HEIDENHAIN's carry the 21 errors (the same figures within 1 nm); FANUC's 10 mm grid
/// blends the truth's short waves between its corners (within 1 µm largest of the model);
/// Siemens's EEC and CEC tables carry no angles, so they leave the angles' share (seed 41's
/// machining centre 13.4 µm RMS of 40.8, seed 42's gantry 43.6 of 80.0: more than the model
/// leaves, less than three quarters of what the machine had).
#[test]
fn every_control_s_files_read_back_and_applied_give_the_model_s_figures() {
    let dir = TempDir::new("exports");
    let tool = [0.0, 0.0, -150.0];
    for (n, spec) in [MachineSpec::vertical_mc(), MachineSpec::gantry()]
        .into_iter()
        .enumerate()
    {
        let seed = 41 + n as u64;
        let twin = TwinMachine::new(&spec, seed);
        let truth = twin.truth_model(5.0).expect("model");
        let out = dir.path(&format!("m{n}"));
        std::fs::create_dir_all(&out).expect("dir");
        let files = exports::write_and_read_back(&truth, &out, &format!("seed {seed}"), tool)
            .expect("written and read back");
        let points = twin.random_points(500, &mut Rng::new(seed));
        let before = volumetric(&twin, &points, tool, None);
        let model = volumetric(&twin, &points, tool, Some(&truth));
        for e in &files {
            let after = volumetric(&twin, &points, tool, Some(e.applied.as_ref()));
            eprintln!(
                "{} seed {seed}: {}: {:.3} µm largest, {:.3} µm RMS (the model {:.3}, {:.3}; before {:.1}, {:.1})",
                spec.chain, e.control, after.0, after.1, model.0, model.1, before.0, before.1
            );
            let control = e.control.split_whitespace().next().unwrap_or("");
            match control {
                "Beckhoff" | "HEIDENHAIN" => assert!(
                    (after.0 - model.0).abs() < 1e-3 && (after.1 - model.1).abs() < 1e-3,
                    "{control}: {after:?} against {model:?}"
                ),
                "FANUC" => assert!(
                    after.0 - model.0 < 1.0 && after.1 - model.1 < 0.3,
                    "{after:?} against {model:?}"
                ),
                "Siemens" => assert!(
                    after.1 > model.1 + 1.0 && after.1 < 0.75 * before.1,
                    "{after:?} against {model:?}, before {before:?}"
                ),
                other => panic!("an export no test judges: {other}"),
            }
        }
    }
}

/// The whole machine measured by the product's path on the lab (`sim::machine_lab`): X with
/// its beam aligned, Y and Z through an optical square from X's beam (C0Y, B0Z), Z again
/// through a square from Y's beam (A0Z). Each set-up's six component errors against the truth
/// within issue 14's limits at its targets; each
/// squareness within 1.0″ of the truth and inside its U; the model of the measured tables and
/// squarenesses (each table every 5 mm from a spline through the targets) compensating the
/// twin's CNC, judged by its truth at 1000 points with a 150 mm tool.
#[test]
#[ignore = "four whole axes on the lab: run optimised by .ci/run"]
fn the_machine_measured_with_an_optical_square_compensates_the_machine() {
    let _machine = crate::helpers::heavy();
    let lab = MachineLabSpec::standard(MachineSpec::vertical_mc(), 31);
    let spec = lab.machine;
    let r = measure_machine(&lab, &mut |s| {
        let names = component_names(s.axis);
        let user: Vec<String> = (0..6)
            .map(|k| match k {
                0..=2 => format!("{} {:.2} µm", names[k], s.worst_off[k] * 1e3),
                _ => format!("{} {:.2}″", names[k], s.worst_off[k] / RAD_PER_ARCSEC),
            })
            .collect();
        eprintln!(
            "{} ({}): {:.1} min of machine time; worst |measured − truth|: {}",
            s.axis,
            s.beam,
            s.machine_s / 60.0,
            user.join(", ")
        );
    })
    .expect("the machine measured");
    for s in &r.setups {
        // Issue 14's limits: 1 µm positioning, 0.5 µm straightness, 0.5″ roll, 0.3″ pitch
        // and yaw.
        for (k, (name, off)) in component_names(s.axis).iter().zip(s.worst_off).enumerate() {
            let limit = match k {
                k if k == s.axis.index() => 1e-3,
                0..=2 => 0.5e-3,
                k if k - 3 == s.axis.index() => 0.5 * RAD_PER_ARCSEC,
                _ => 0.3 * RAD_PER_ARCSEC,
            };
            assert!(
                off <= limit,
                "{} ({}): {name}: {off:e} beyond {limit:e}",
                s.axis,
                s.beam
            );
        }
    }
    let mut measured = [0.0; 3];
    for sq in &r.squareness {
        let m = &sq.measured;
        let off = (m.value_rad - sq.truth_rad).abs();
        eprintln!(
            "{m}; truth {:+.2}″, off by {:.2}″ ({})",
            sq.truth_rad / RAD_PER_ARCSEC,
            off / RAD_PER_ARCSEC,
            m.terms
                .iter()
                .map(|t| format!("{} {:.3}″", t.name, t.u_rad / RAD_PER_ARCSEC))
                .collect::<Vec<_>>()
                .join(", ")
        );
        assert!(
            off <= 1.0 * RAD_PER_ARCSEC && off <= m.expanded_rad,
            "{m}: {:.2}″ off the truth",
            off / RAD_PER_ARCSEC
        );
        measured[m.pair.index()] = m.value_rad;
    }
    let twin = &r.twin;
    let model = &r.model;
    let machine_s = r.machine_s();
    let points = twin.random_points(1000, &mut Rng::new(31));
    let tool = [0.0, 0.0, -150.0];
    let before = volumetric(twin, &points, tool, None);
    let after = volumetric(twin, &points, tool, Some(model));
    eprintln!(
        "{}: {:.0} min of machine time for the four set-ups; volumetric before max {:.1} µm, RMS {:.1} µm; after max {:.2} µm, RMS {:.2} µm",
        spec.chain,
        machine_s / 60.0,
        before.0,
        before.1,
        after.0,
        after.1
    );
    // What each measured part costs: the model with that part measured and the rest true.
    type Part = fn(MachineAxis, usize) -> bool;
    let kinds: [(&str, Part); 4] = [
        ("positioning", |a, k| k == a.index()),
        ("straightness", |a, k| k < 3 && k != a.index()),
        ("roll", |a, k| k == 3 + a.index()),
        ("pitch and yaw", |a, k| k >= 3 && k != 3 + a.index()),
    ];
    let mut costs = Vec::new();
    for (name, measured_kind) in kinds {
        let mixed: Vec<ComponentTable> = model
            .tables()
            .iter()
            .map(|t| {
                let a = t.axis();
                ComponentTable::sample(a, 0.0, spec.travel_mm[a.index()], 5.0, |q| {
                    let (m, tr) = (t.at(q), twin.component_errors(a, q));
                    std::array::from_fn(|k| if measured_kind(a, k) { m[k] } else { tr[k] })
                })
                .expect("mixed table")
            })
            .collect();
        let alone = MachineModel::new(spec.chain, mixed, twin.squareness()).expect("model");
        let rms = volumetric(twin, &points, tool, Some(&alone)).1;
        costs.push(format!("{name} {rms:.2} µm"));
    }
    let truth_tables = twin.truth_model(5.0).expect("truth model");
    let squares_alone = MachineModel::new(
        spec.chain,
        truth_tables.tables().to_vec(),
        Squareness::from_array(measured),
    )
    .expect("model");
    costs.push(format!(
        "squarenesses {:.2} µm",
        volumetric(twin, &points, tool, Some(&squares_alone)).1
    ));
    eprintln!(
        "after RMS with one part measured and the rest true: {}",
        costs.join(", ")
    );
    assert!(
        after.0 <= 0.1 * before.0 && after.1 <= 1.5,
        "{after:?} after, {before:?} before"
    );
    // The machine as the product keeps it (must-show 3's record): each set-up's run stored
    // and attached in the plan's order, the model fitted again from the store, the same as the
    // lab's in memory (the stored captures evaluated and budgeted as a report does).
    let db = TempDir::new("machine-store");
    let mut store = Store::open(db.path("axiscomp.db")).expect("store");
    let id = r
        .store(&mut store, 1_700_000_000_000_000)
        .expect("stored and attached");
    let state = axiscomp::commission::stored::state(&store, id).expect("state");
    let stored = state.model().expect("the stored machine's model");
    assert_eq!(stored.squareness.to_array(), model.squareness.to_array());
    for (a, b) in stored.tables().iter().zip(model.tables()) {
        for q in [0.0, 123.4, 400.0] {
            let (x, y) = (a.at(q), b.at(q));
            assert!(
                (0..6).all(|k| (x[k] - y[k]).abs() <= 1e-12),
                "{}: {x:?} stored, {y:?} in memory at {q} mm",
                a.axis()
            );
        }
    }
    // The machine acceptance report from the store: the set-ups' runs one after another by
    // the machine's clock, the squarenesses as fitted, the uncompensated figure the model's
    // survey, and what each control's files leave of the model (Beckhoff's file carries it
    // exactly, Siemens's tables not the angles).
    let rep = TempDir::new("machine-report");
    let written = axiscomp::commission::report::write(
        &store,
        id,
        &rep.path("report"),
        &rep.path("controls"),
        1_700_000_000_000_000,
    )
    .expect("the report");
    let md = std::fs::read_to_string(rep.path("report/acceptance.md")).expect("acceptance.md");
    let pdf = std::fs::read(rep.path("report/acceptance.pdf")).expect("acceptance.pdf");
    assert!(pdf.starts_with(b"%PDF-") && written.report.len() >= 3);
    let mut last = i64::MIN;
    for run in state.attached.iter().flatten() {
        let rec = store.run(axiscomp::store::RunId(*run)).expect("run");
        assert!(rec.created_us > last && rec.created_us <= 1_700_000_000_000_000);
        last = rec.created_us;
    }
    let fitted = state.fit.as_ref().expect("fit");
    for q in &fitted.squareness {
        let row = md
            .lines()
            .find(|l| l.starts_with(&format!("| {} | {} |", q.pair.name(), q.pair)))
            .unwrap_or_else(|| panic!("no row for {}", q.pair.name()));
        let cell: f64 = row
            .split('|')
            .nth(3)
            .expect("value")
            .trim()
            .replace('−', "-")
            .parse()
            .expect("a number");
        assert!(
            (cell - q.value_rad / RAD_PER_ARCSEC).abs() <= 0.005,
            "{row}"
        );
    }
    let cell = |prefix: &str| -> f64 {
        let row = md
            .lines()
            .find(|l| l.starts_with(prefix))
            .unwrap_or_else(|| panic!("no row {prefix}"));
        row.split('|')
            .nth(2)
            .expect("largest")
            .trim()
            .parse()
            .expect("a number")
    };
    let survey = axiscomp::machine::volume::survey(stored, None, spec.travel_mm, tool);
    assert!((cell("| uncompensated |") - survey.max_mm * 1e3).abs() <= 0.005);
    assert!(cell("| after Beckhoff |") <= 0.01);
    assert!(
        cell("| after Siemens |") > 5.0,
        "Siemens's tables carry no angles"
    );
    // The measured model's files for every control, read back and applied (must-show 2):
    // the measured tables are smooth between their targets, so FANUC's 10 mm grid follows them.
    let dir = TempDir::new("machine-exports");
    let files = exports::write_and_read_back(model, &dir.path(""), "twin 31", tool)
        .expect("written and read back");
    for e in &files {
        let a = volumetric(twin, &points, tool, Some(e.applied.as_ref()));
        eprintln!(
            "{}: {:.2} µm largest, {:.2} µm RMS ({})",
            e.control, a.0, a.1, e.carries
        );
        let (dmax, drms) = match e.control.split_whitespace().next() {
            Some("Beckhoff" | "HEIDENHAIN") => (0.01, 0.01),
            // The blend between the grid's corners (curvature-balanced) moves the largest a
            // little either way: demo seeds 101-105 and 7 by −0.04 to +0.09 µm, RMS ≤ 0.01 µm.
            Some("FANUC") => (0.15, 0.02),
            _ => continue,
        };
        assert!(
            (a.0 - after.0).abs() <= dmax && (a.1 - after.1).abs() <= drms,
            "{}: {a:?} against the model's {after:?}",
            e.control
        );
    }
}
