use super::*;
use super::{from_head, isg_csv};

mod exports;
use crate::comp::mapping::MachineAxis;
use crate::sim::Rng;
use crate::sim::machine::{MachineSpec, TwinMachine};
use MachineAxis::*;

fn flat(axis: MachineAxis, len: f64, row: [f64; 6]) -> ComponentTable {
    ComponentTable::new(axis, vec![0.0, len], vec![row, row]).unwrap()
}

/// A model with every error zero but `row` on `axis` and `square`.
fn only(axis: MachineAxis, row: [f64; 6], square: Squareness, chain: Chain) -> MachineModel {
    let tables = MachineAxis::ALL
        .iter()
        .map(|&a| flat(a, 1000.0, if a == axis { row } else { [0.0; 6] }))
        .collect();
    MachineModel::new(chain, tables, square).unwrap()
}

#[test]
fn component_names_follow_iso_230_1() {
    assert_eq!(
        component_names(X),
        ["EXX", "EYX", "EZX", "EAX", "EBX", "ECX"]
    );
    assert_eq!(component_names(Z)[4], "EBZ");
}

#[test]
fn a_table_interpolates_linearly_and_holds_its_ends() {
    let t = ComponentTable::new(
        Y,
        vec![0.0, 10.0, 30.0],
        vec![[0.0; 6], [1e-3, 2e-3, 0.0, 1e-6, 0.0, 0.0], [3e-3; 6]],
    )
    .unwrap();
    // 20 mm is halfway from 10 to 30 mm.
    let v = t.at(20.0);
    assert!((v[0] - 2e-3).abs() < 1e-15 && (v[1] - 2.5e-3).abs() < 1e-15);
    assert!((v[3] - (1e-6 + 3e-3) / 2.0).abs() < 1e-15);
    assert_eq!(t.at(-5.0), [0.0; 6]);
    assert_eq!(t.at(31.0), [3e-3; 6]);
    assert_eq!(t.at(10.0)[1], 2e-3);
}

#[test]
fn a_bad_table_is_refused_in_words() {
    let e = ComponentTable::new(X, vec![0.0, 10.0, 5.0], vec![[0.0; 6]; 3]).unwrap_err();
    assert_eq!(
        e.to_string(),
        "component errors of X: positions must increase: row 3 is 5 mm after 10 mm"
    );
    let mut rows = vec![[0.0; 6]; 2];
    rows[1][4] = f64::NAN;
    let e = ComponentTable::new(Z, vec![0.0, 10.0], rows).unwrap_err();
    assert_eq!(
        e.to_string(),
        "component errors of Z: row 2 at 10 mm: EBZ is not a number"
    );
    let e = ComponentTable::new(X, vec![0.0], vec![[0.0; 6]]).unwrap_err();
    assert!(e.to_string().contains("at least two positions"), "{e}");
    let e = MachineModel::new(
        Chain::cross_table(),
        vec![flat(X, 1.0, [0.0; 6]), flat(Z, 1.0, [0.0; 6])],
        Squareness::default(),
    )
    .unwrap_err();
    assert_eq!(
        e.to_string(),
        "machine model: no component errors for axis Y: the model needs all three"
    );
}

#[test]
fn chains_name_each_axis_once() {
    assert_eq!(
        Chain::cross_table().to_string(),
        "workpiece – X – Y – bed – Z – tool"
    );
    assert_eq!(
        Chain::gantry().to_string(),
        "workpiece – bed – Y – X – Z – tool"
    );
    let e = Chain::new([X, X, Z], 0).unwrap_err();
    assert_eq!(
        e.to_string(),
        "chain workpiece – bed – X – X – Z – tool: X appears 2 times, Y is missing: name each of X, Y and Z once"
    );
}

#[test]
fn single_errors_reach_the_tool_as_the_geometry_says() {
    let tool = [0.0, 0.0, -100.0];
    let cmd = [400.0, 250.0, 300.0];
    // X's pitch (about Y) turns what X carries after it in the cross table's chain: Y, Z and
    // the tool, a lever of (0, 250, 300 − 100) mm: dx = θ·200 mm.
    let th = 1e-5;
    let m = only(
        X,
        [0.0, 0.0, 0.0, 0.0, th, 0.0],
        Squareness::default(),
        Chain::cross_table(),
    );
    let e = m.error_at(cmd, tool);
    assert!(
        (e[0] - th * 200.0).abs() < 1e-15 && e[1] == 0.0 && e[2] == 0.0,
        "{e:?}"
    );
    // Z is last: its pitch turns only the tool, dx = θ·(−100 mm).
    let m = only(
        Z,
        [0.0, 0.0, 0.0, 0.0, th, 0.0],
        Squareness::default(),
        Chain::cross_table(),
    );
    assert!((m.error_at(cmd, tool)[0] + th * 100.0).abs() < 1e-15);
    // Y's line turned by C0Y about Z: at y = 250 mm the tool is −C0Y·250 mm off in x.
    let s = Squareness {
        c0y: 2e-5,
        ..Squareness::default()
    };
    let m = only(X, [0.0; 6], s, Chain::cross_table());
    let e = m.error_at(cmd, tool);
    assert!((e[0] + 2e-5 * 250.0).abs() < 1e-15 && e[1] == 0.0, "{e:?}");
    // Z leaning by B0Z towards +X, by A0Z towards −Y.
    let s = Squareness {
        b0z: 1e-5,
        a0z: 3e-5,
        ..Squareness::default()
    };
    let m = only(X, [0.0; 6], s, Chain::cross_table());
    let e = m.error_at(cmd, tool);
    assert!((e[0] - 1e-5 * 300.0).abs() < 1e-15 && (e[1] + 3e-5 * 300.0).abs() < 1e-15);
    // A straightness adds as it is.
    let m = only(
        Y,
        [0.0, 0.0, 4e-3, 0.0, 0.0, 0.0],
        Squareness::default(),
        Chain::gantry(),
    );
    assert_eq!(m.error_at(cmd, tool), [0.0, 0.0, 4e-3]);
}

/// The first-order model of the twin's true tables against the twin's exact chain, on both
/// machines and five seeds: the second order is below 0.05 µm where the errors reach tens of
/// µm; without the squarenesses or with the chain reversed the model is microns off.
#[test]
fn the_first_order_model_matches_the_twin_s_exact_chain() {
    for spec in [MachineSpec::vertical_mc(), MachineSpec::gantry()] {
        for seed in 1..=5u64 {
            let twin = TwinMachine::new(&spec, seed);
            let model = twin.truth_model(1.0).unwrap();
            let mut unsquare = model.clone();
            unsquare.squareness = Squareness::default();
            let o = spec.chain.order();
            let mut reversed = model.clone();
            reversed.chain = Chain::new([o[2], o[1], o[0]], 0).unwrap();
            let tool = [25.0, -40.0, -150.0];
            let mut rng = Rng::new(seed + 100);
            let (mut worst, mut largest, mut off_square, mut off_chain) =
                (0.0f64, 0.0f64, 0.0f64, 0.0f64);
            for p in twin.random_points(300, &mut rng) {
                let truth = twin.error(p, tool);
                let dist = |e: [f64; 3]| {
                    (0..3)
                        .map(|k| (e[k] - truth[k]).powi(2))
                        .sum::<f64>()
                        .sqrt()
                };
                worst = worst.max(dist(model.error_at(p, tool)));
                off_square = off_square.max(dist(unsquare.error_at(p, tool)));
                off_chain = off_chain.max(dist(reversed.error_at(p, tool)));
                largest = largest.max(truth.iter().map(|v| v * v).sum::<f64>().sqrt());
            }
            eprintln!(
                "{} seed {seed}: largest {:.1} µm, model off the exact chain {:.4} µm, without squareness {:.1} µm, chain reversed {:.1} µm",
                spec.chain,
                largest * 1e3,
                worst * 1e3,
                off_square * 1e3,
                off_chain * 1e3
            );
            assert!(
                worst < 0.05e-3,
                "{} seed {seed}: model {:.4} µm off the exact chain",
                spec.chain,
                worst * 1e3
            );
            assert!(largest > 20e-3, "seed {seed}: largest error {largest} mm");
            assert!(
                off_square > 2e-3 && off_chain > 1e-3,
                "{off_square} {off_chain}"
            );
        }
    }
}

#[test]
fn the_beckhoff_file_reads_back_to_the_same_model() {
    let twin = TwinMachine::new(&MachineSpec::vertical_mc(), 7);
    let model = twin.truth_model(5.0).unwrap();
    let text = isg_csv::write(model.tables(), model.squareness, "twin seed 7\nsecond line");
    assert!(
        text.starts_with("// twin seed 7\n// second line\n"),
        "{text}"
    );
    assert!(
        text.contains("\nX EXX EYX EZX EAX EBX ECX\n0.000 "),
        "{text}"
    );
    assert!(text.contains("\n#\n// Component errors of the Y axis\nY EXY EYY EZY EAY EBY ECY\n"));
    let back = isg_csv::parse(&text, "vol.csv").unwrap();
    assert_eq!(back.tables.len(), 3);
    for (a, b) in model.tables().iter().zip(&back.tables) {
        assert_eq!(a.axis(), b.axis());
        assert_eq!(a.positions_mm(), b.positions_mm());
        for (ra, rb) in a.values().iter().zip(b.values()) {
            for k in 0..6 {
                let half_digit = if k < 3 { 0.5e-7 } else { 0.5e-10 };
                assert!(
                    (ra[k] - rb[k]).abs() <= half_digit * 1.0001,
                    "{ra:?} {rb:?}"
                );
            }
        }
    }
    let s = back.squareness.unwrap().to_array();
    for (a, b) in model.squareness.to_array().iter().zip(s) {
        assert!((a - b).abs() <= 0.5e-10);
    }
}

#[test]
fn the_manual_s_example_reads_and_what_the_model_cannot_take_is_refused() {
    // TF5280 "ISG CSV format", component errors of the X axis (two rows).
    let manual = "// The header contains the argument \"X\" and component errors.\n\
                  X      EXX    EYX    EZX    EAX    EBX    ECX\n\
                  0.0    0.02   0.01   0.07   0.00   0.0042 0.003\n\
                  10.0   0.00   -0.1   0.01   0.00   0.0011 0.002\n";
    let f = isg_csv::parse(manual, "x.csv").unwrap();
    assert_eq!(f.tables.len(), 1);
    assert_eq!(
        f.tables[0].values()[1],
        [0.0, -0.1, 0.01, 0.0, 0.0011, 0.002]
    );
    assert_eq!(f.squareness, None);
    // Columns reordered, a subset, ';' between them: an absent error is zero.
    let f = isg_csv::parse("EYZ;Z;EAZ\n1;0;2\n3;5;4\n", "z.csv").unwrap();
    assert_eq!(f.tables[0].positions_mm(), [0.0, 5.0]);
    assert_eq!(f.tables[0].values()[1], [0.0, 3.0, 0.0, 4.0, 0.0, 0.0]);
    let refused = |text: &str| isg_csv::parse(text, "v.csv").unwrap_err().to_string();
    assert_eq!(
        refused("// two arguments\nZ X EXX\n0 0 0.1\n"),
        "v.csv, line 2: a block against 2 arguments (Z, X): axiscomp's model takes each table against its own axis alone"
    );
    assert!(refused("X EXX EQX\n").starts_with("v.csv, line 1: column EQX is not"));
    assert_eq!(
        refused("X EXX\n0 1\n10\n"),
        "v.csv, line 3: 1 values under a header of 2 columns (line 1)"
    );
    assert_eq!(
        refused("X EXX\n0 1,5\n"),
        "v.csv, line 2: 3 values under a header of 2 columns (line 1)"
    );
    assert_eq!(
        refused("X EXX\n0 abc\n"),
        "v.csv, line 2: abc is not a number (mm or rad, with a decimal point)"
    );
    assert_eq!(
        refused("X EXX EXY\n"),
        "v.csv, line 1: EXY is a component error of Y, in a block against X: give each axis a block of its own"
    );
    assert!(refused("X EXX\n5 0\n0 0\n").contains("positions must increase"));
    assert_eq!(
        refused("C0Y B0Z A0Z\n0 0 0\n0 0 0\n"),
        "v.csv, line 1: position errors take one data row, found 2"
    );
}

/// Trilinear between corners reproduces a field linear in each axis exactly: constant angles
/// and squarenesses make the model's error such a field (products of one position with a
/// constant), so the grid must equal the model everywhere, beyond its faces held.
#[test]
fn a_grid_reproduces_a_linear_field_and_its_corners() {
    let row = |a: f64| [1e-3 * a, -2e-3, 0.5e-3, 1e-5 * a, -2e-5, 3e-5];
    let tables = MachineAxis::ALL
        .iter()
        .map(|&a| flat(a, 1000.0, row(a.index() as f64 + 1.0)))
        .collect();
    let s = Squareness {
        c0y: 4e-5,
        b0z: -3e-5,
        a0z: 2e-5,
    };
    let model = MachineModel::new(Chain::cross_table(), tables, s).unwrap();
    let tool = [10.0, 0.0, -120.0];
    let grid = Grid::of_model(&model, [0.0; 3], [1000.0, 600.0, 500.0], [70.0; 3], tool).unwrap();
    // 1000 / 70 rounds up to 15 cells of 66.7 mm.
    assert_eq!(grid.counts(), [16, 10, 9]);
    assert!((grid.step_mm()[0] - 1000.0 / 15.0).abs() < 1e-12);
    let mut rng = Rng::new(5);
    for _ in 0..200 {
        let p = [
            rng.uniform(0.0, 1000.0),
            rng.uniform(0.0, 600.0),
            rng.uniform(0.0, 500.0),
        ];
        let (g, m) = (grid.at(p), model.error_at(p, tool));
        for k in 0..3 {
            assert!((g[k] - m[k]).abs() < 1e-12, "{p:?}: {g:?} against {m:?}");
        }
    }
    assert_eq!(
        grid.at([1200.0, -5.0, 250.0]),
        grid.at([1000.0, 0.0, 250.0])
    );
    // A curved field is met at the corners and not between them.
    let twin = TwinMachine::new(&MachineSpec::vertical_mc(), 3);
    let truth = twin.truth_model(5.0).unwrap();
    let grid = Grid::of_model(&truth, [0.0; 3], [1000.0, 600.0, 500.0], [100.0; 3], tool).unwrap();
    let corner = [300.0, 200.0, 100.0];
    let (g, m) = (grid.at(corner), truth.error_at(corner, tool));
    assert!((0..3).all(|k| (g[k] - m[k]).abs() < 1e-12));
    let mid = [350.0, 250.0, 150.0];
    let (g, m) = (grid.at(mid), truth.error_at(mid, tool));
    assert!((0..3).any(|k| (g[k] - m[k]).abs() > 1e-5), "{g:?} {m:?}");
    let e = Grid::of_model(&truth, [0.0; 3], [1000.0, 0.0, 500.0], [10.0; 3], tool).unwrap_err();
    assert_eq!(
        e.to_string(),
        "machine model: a grid from 0 to 0 mm every 10 mm along Y: give a positive span and step"
    );
}

/// The machine's frame is its axes' reference lines: every straightness table has no
/// least-squares line left over its travel. The single-axis twin of `plant_spec` carries the
/// very axis, and its straightness differs from the machine's by a line alone.
#[test]
fn the_twin_machine_s_axes_are_the_single_axis_twin_s_on_their_reference_lines() {
    use crate::optics::Layout;
    use crate::sim::plant::{Plant, PlantSpec};
    let twin = TwinMachine::new(&MachineSpec::vertical_mc(), 21);
    let layout = Layout::reference();
    for axis in MachineAxis::ALL {
        let len = twin.spec.travel_mm[axis.index()];
        let spec = twin.plant_spec(axis, PlantSpec::default());
        let plant = Plant::new(&layout, &spec, std::time::Instant::now()).unwrap();
        assert_eq!(&plant.axis, twin.axis_profile(axis), "{axis}");
        let m = crate::comp::mapping::AxisMapping::standard(axis);
        let qs: Vec<f64> = (0..=1000).map(|i| len * i as f64 / 1000.0).collect();
        // The two straightness directions of this axis in the machine's frame.
        let across: Vec<usize> = MachineAxis::ALL
            .iter()
            .filter(|a| **a != axis)
            .map(|a| a.index())
            .collect();
        for &k in &across {
            let y: Vec<f64> = qs
                .iter()
                .map(|&q| twin.component_errors(axis, q)[k])
                .collect();
            let (mx, my) = (len / 2.0, y.iter().sum::<f64>() / y.len() as f64);
            let slope = qs
                .iter()
                .zip(&y)
                .map(|(x, v)| (x - mx) * (v - my))
                .sum::<f64>()
                / qs.iter().map(|x| (x - mx).powi(2)).sum::<f64>();
            assert!(
                my.abs() < 1e-12 && slope.abs() < 1e-15,
                "{axis} {k}: {my} {slope}"
            );
            // The plant's straightness minus the machine's is a line.
            let d: Vec<f64> = qs
                .iter()
                .map(|&q| {
                    let h = plant.axis.errors(q, crate::sim::axis::Direction::Up, 0.0);
                    let h = h.to_array();
                    m.to_machine([h[0], h[1], h[2]])[k] - twin.component_errors(axis, q)[k]
                })
                .collect();
            let step = d[1] - d[0];
            assert!(d.windows(2).all(|w| ((w[1] - w[0]) - step).abs() < 1e-12));
        }
        // Positioning and the angles are the plant's own.
        let q = 0.37 * len;
        let h = plant
            .axis
            .errors(q, crate::sim::axis::Direction::Up, 0.0)
            .to_array();
        let e = twin.component_errors(axis, q);
        assert_eq!(m.to_machine([h[3], h[4], h[5]]), [e[3], e[4], e[5]]);
        assert_eq!(
            m.to_machine([0.0, h[1], 0.0])[axis.index()],
            e[axis.index()]
        );
    }
}

/// The head on Z (x = +X, z = −Y): its dx is EXZ, its dz is −EYZ, its dy EZZ; rotations
/// likewise. A line in a straightness (the beam's pointing) and a constant vanish; the
/// positioning and the angles stay as measured.
#[test]
fn a_head_s_table_goes_onto_the_machine_on_its_reference_line() {
    let m = crate::comp::mapping::AxisMapping::standard(Z);
    let positions = [0.0, 100.0, 250.0, 400.0, 500.0];
    let bow = |q: f64| 1e-3 * ((q - 250.0) / 250.0).powi(2);
    let head: Vec<[f64; 6]> = positions
        .iter()
        .map(|&q| {
            [
                bow(q) + 2e-3 + 3e-6 * q,
                -5e-6 * q,
                -(0.5 * bow(q)) - 1e-6 * q,
                2e-6,
                q * 1e-9,
                -3e-6,
            ]
        })
        .collect();
    let t = from_head::table_from_head(&m, &positions, &head).unwrap();
    assert_eq!(t.axis(), Z);
    // The bow's least-squares line over these positions, by hand: its mean and slope.
    let b: Vec<f64> = positions.iter().map(|&q| bow(q)).collect();
    let mb = b.iter().sum::<f64>() / 5.0;
    let mx = positions.iter().sum::<f64>() / 5.0;
    let slope = positions
        .iter()
        .zip(&b)
        .map(|(x, v)| (x - mx) * (v - mb))
        .sum::<f64>()
        / positions.iter().map(|x| (x - mx).powi(2)).sum::<f64>();
    for (i, (&q, row)) in positions.iter().zip(t.values()).enumerate() {
        let rest = bow(q) - mb - slope * (q - mx);
        assert!((row[0] - rest).abs() < 1e-15, "EXZ at {i}");
        assert!((row[1] - 0.5 * rest).abs() < 1e-15, "EYZ at {i}");
        assert_eq!(row[2], -5e-6 * q);
        assert_eq!([row[3], row[4], row[5]], [2e-6, 3e-6, q * 1e-9]);
    }
    let e = from_head::table_from_head(&m, &positions[..4], &head).unwrap_err();
    assert_eq!(
        e.to_string(),
        "component errors of Z: 4 positions but 5 rows of the head's errors"
    );
}

/// A table of the twin's axes every 20 mm, refined to every 5 mm through the spline, follows
/// the axis between its rows better than the 20 mm table's straight lines: its translations
/// against the truth every millimetre, RMS at most half and worst no larger (the twin's
/// shortest waves are 1/9 of an axis, 56 mm on a 500 mm Z: 2.8 rows a wave, where a spline
/// gains least).
#[test]
fn a_refined_table_follows_the_axis_between_its_targets() {
    let (mut worst_lines, mut worst_spline) = (0.0f64, 0.0f64);
    for seed in 1..=5u64 {
        let twin = TwinMachine::new(&MachineSpec::vertical_mc(), seed);
        for axis in MachineAxis::ALL {
            let len = twin.spec.travel_mm[axis.index()];
            let coarse =
                ComponentTable::sample(axis, 0.0, len, 20.0, |q| twin.component_errors(axis, q))
                    .unwrap();
            let fine = coarse.refined(5.0).unwrap();
            assert_eq!(fine.positions_mm().len(), (len / 5.0) as usize + 1);
            let (mut lines, mut spline) = ((0.0f64, 0.0f64), (0.0f64, 0.0f64));
            let mut n = 0.0;
            for i in 0..=(len as usize) {
                let q = i as f64;
                let t = twin.component_errors(axis, q);
                let (c, f) = (coarse.at(q), fine.at(q));
                for k in 0..3 {
                    let (a, b) = ((c[k] - t[k]).abs(), (f[k] - t[k]).abs());
                    lines = (lines.0.max(a), lines.1 + a * a);
                    spline = (spline.0.max(b), spline.1 + b * b);
                    n += 1.0;
                }
            }
            let (rms_lines, rms_spline) = ((lines.1 / n).sqrt(), (spline.1 / n).sqrt());
            assert!(
                rms_spline * 2.0 <= rms_lines && spline.0 <= lines.0,
                "seed {seed}, {axis}: RMS {rms_spline:e} mm refined, {rms_lines:e} mm in lines; worst {:e}, {:e} mm",
                spline.0,
                lines.0
            );
            worst_lines = worst_lines.max(lines.0);
            worst_spline = worst_spline.max(spline.0);
        }
    }
    eprintln!(
        "worst translation off the truth between 20 mm rows: {:.2} µm in straight lines, {:.2} µm refined",
        worst_lines * 1e3,
        worst_spline * 1e3
    );
}
