//! The controls' files (HEIDENHAIN, FANUC, Siemens): each written, read back by its own reader
//! to the same model within the file's rounding, a value checked by hand, bad files refused in
//! words. (Beckhoff's `ISG_CSV` is tested in `tests.rs`.)

use crate::comp::mapping::MachineAxis;
use crate::machine::*;
use crate::machine::{fanuc_grid, heidenhain, siemens};
use crate::sim::Rng;
use crate::sim::machine::{MachineSpec, TwinMachine};
use MachineAxis::*;

fn flat(axis: MachineAxis, len: f64, row: [f64; 6]) -> ComponentTable {
    ComponentTable::new(axis, vec![0.0, len], vec![row, row]).unwrap()
}

fn only(axis: MachineAxis, row: [f64; 6], square: Squareness) -> MachineModel {
    let tables = MachineAxis::ALL
        .iter()
        .map(|&a| flat(a, 1000.0, if a == axis { row } else { [0.0; 6] }))
        .collect();
    MachineModel::new(Chain::cross_table(), tables, square).unwrap()
}

fn random_points(n: usize, seed: u64) -> Vec<[f64; 3]> {
    let mut rng = Rng::new(seed);
    (0..n)
        .map(|_| {
            [
                rng.uniform(0.0, 1000.0),
                rng.uniform(0.0, 600.0),
                rng.uniform(0.0, 500.0),
            ]
        })
        .collect()
}

fn text_of<'a>(files: &'a [(String, String)], name: &str) -> &'a str {
    &files.iter().find(|(n, _)| n == name).unwrap().1
}

#[test]
fn the_heidenhain_files_read_back_to_the_same_model() {
    let twin = TwinMachine::new(&MachineSpec::vertical_mc(), 7);
    let model = twin.truth_model(5.0).unwrap();
    let files = heidenhain::write(&model, "twin seed 7");
    let names: Vec<&str> = files.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(
        names,
        ["X.COM", "Y.COM", "Z.COM", "KINEMATICS.TAB", "README.txt"]
    );
    assert!(text_of(&files, "README.txt").starts_with("twin seed 7\n"));
    assert!(text_of(&files, "KINEMATICS.TAB").starts_with("BEGIN KINEMATICS.TAB\nNR "));
    let x = text_of(&files, "X.COM");
    assert!(x.starts_with("BEGIN X.COM MM\nNR "), "{x}");
    assert!(x.ends_with("[END]\n"));
    let back = heidenhain::KinematicsComp {
        tables: MachineAxis::ALL
            .into_iter()
            .map(|a| {
                let name = heidenhain::com_file(a);
                heidenhain::parse_com(text_of(&files, &name), &name, a).unwrap()
            })
            .collect(),
        squareness: heidenhain::parse_kinematics(
            text_of(&files, "KINEMATICS.TAB"),
            "KINEMATICS.TAB",
        )
        .unwrap(),
    };
    for (a, b) in model.tables().iter().zip(&back.tables) {
        assert_eq!(a.axis(), b.axis());
        for (pa, pb) in a.positions_mm().iter().zip(b.positions_mm()) {
            assert!((pa - pb).abs() <= 0.5e-4, "{pa} {pb}");
        }
        for (ra, rb) in a.values().iter().zip(b.values()) {
            for k in 0..6 {
                // 7 decimals of a mm; 10 of a degree.
                let half = if k < 3 {
                    0.5e-7
                } else {
                    0.5e-10_f64.to_radians()
                };
                assert!((ra[k] - rb[k]).abs() <= half * 1.0001, "{k}: {ra:?} {rb:?}");
            }
        }
    }
    for (a, b) in model
        .squareness
        .to_array()
        .iter()
        .zip(back.squareness.to_array())
    {
        assert!(
            (a - b).abs() <= 0.5e-10_f64.to_radians() * 1.0001,
            "{a} {b}"
        );
    }
}

#[test]
fn heidenhain_values_stand_in_the_manual_s_columns_and_units() {
    // EBX of 1″ is 1/3600° in C5 of X.COM; C0Y of 2″ a Trans about C before Y, taken back
    // after it.
    let arcsec = 1f64.to_radians() / 3600.0;
    let s = Squareness {
        c0y: 2.0 * arcsec,
        ..Squareness::default()
    };
    let model = only(X, [0.0, 0.0, 0.0, 0.0, arcsec, 0.0], s);
    let files = heidenhain::write(&model, "hand");
    let x = text_of(&files, "X.COM");
    let row: Vec<&str> = x.lines().nth(2).unwrap().split_whitespace().collect();
    assert_eq!(row[0], "0");
    assert_eq!(row[1], "+0.0000");
    assert_eq!(row[6], "+0.0002777778", "{x}");
    let k = text_of(&files, "KINEMATICS.TAB");
    let lines: Vec<&str> = k.lines().collect();
    let c0y = lines.iter().position(|l| l.contains(" C0Y ")).unwrap();
    assert!(lines[c0y].contains("Trans     C"), "{k}");
    assert!(lines[c0y].contains("+0.0005555556"), "{k}");
    assert!(lines[c0y + 1].contains("MachAxis  Y"), "{k}");
    assert!(lines[c0y + 2].contains("-C0Y") && lines[c0y + 2].contains("-0.0005555556"));
    assert!(k.contains(" EYX      Trans     Y"), "{k}");
    assert!(k.contains("X..C2"), "{k}");
    // A table of the manual's form with a comment and C2 alone: the rest is zero.
    let t = heidenhain::parse_com(
        "BEGIN Y.COM MM\nNR AXISPOS C2 ; straightness\n0 -10.0 0.001\n1 +90.0 0.003\n[END]\n",
        "Y.COM",
        Y,
    )
    .unwrap();
    assert_eq!(t.positions_mm(), [-10.0, 90.0]);
    assert_eq!(t.values()[1], [0.0, 0.003, 0.0, 0.0, 0.0, 0.0]);
    let refused = |text: &str| {
        heidenhain::parse_com(text, "X.COM", X)
            .unwrap_err()
            .to_string()
    };
    assert_eq!(
        refused("BEGIN X.COM MM\nNR AXISPOS C1\n0 0 0\n"),
        "X.COM, line 3: no [END] line: the table is cut short"
    );
    assert_eq!(
        refused("BEGIN X.COM MM\nNR POS C1\n[END]\n"),
        "X.COM, line 2: no AXISPOS column: the compensation points' positions stand there"
    );
    assert_eq!(
        refused("BEGIN X.COM MM\nNR AXISPOS C1\n0 0 1,5\n[END]\n"),
        "X.COM, line 3: 1,5 under C1 is not a number (with a decimal point)"
    );
    assert_eq!(
        refused("NR AXISPOS C1\n[END]\n"),
        "X.COM, line 1: a HEIDENHAIN table starts with its BEGIN line"
    );
    let e = heidenhain::parse_kinematics(
        "BEGIN K.TAB\nNR DOC KEY AXIS COORD\n0 C0Y Trans C\n[END]\n",
        "K.TAB",
    )
    .unwrap_err();
    assert_eq!(
        e.to_string(),
        "K.TAB, line 3: C0Y has no number under COORD (degrees) after Trans and its axis"
    );
}

#[test]
fn the_fanuc_grid_reads_back_with_the_same_corners() {
    let twin = TwinMachine::new(&MachineSpec::vertical_mc(), 7);
    let model = twin.truth_model(5.0).unwrap();
    let tool = [0.0, 0.0, -150.0];
    let grid = Grid::of_model(&model, [0.0; 3], [1000.0, 600.0, 500.0], [70.0; 3], tool).unwrap();
    let text = fanuc_grid::write(&grid, "twin seed 7");
    assert!(text.starts_with("; twin seed 7\n"), "{text}");
    assert!(text.contains("\nPOINTS 16 10 9\n"), "{text}");
    assert!(text.contains("\nEND 1000.000000 600.000000 500.000000\n"));
    let back = fanuc_grid::parse(&text, "grid.txt").unwrap();
    assert_eq!(back.counts(), grid.counts());
    assert_eq!(back.tool_mm(), tool);
    for k in 0..3 {
        assert!((back.step_mm()[k] - grid.step_mm()[k]).abs() < 1e-9);
    }
    let [nx, ny, nz] = grid.counts();
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let (a, b) = (grid.vector(i, j, k), back.vector(i, j, k));
                assert!((0..3).all(|m| (a[m] - b[m]).abs() <= 0.5e-7 * 1.0001));
            }
        }
    }
    for p in random_points(200, 9) {
        let (a, b) = (grid.at(p), back.at(p));
        assert!((0..3).all(|m| (a[m] - b[m]).abs() <= 1e-7), "{p:?}");
    }
    // By hand: a positioning error of X of +10 µm everywhere is −0.010 mm of compensation at
    // every corner, along X alone.
    let m = only(X, [0.010, 0.0, 0.0, 0.0, 0.0, 0.0], Squareness::default());
    let g = Grid::of_model(&m, [0.0; 3], [1000.0, 600.0, 500.0], [500.0; 3], tool).unwrap();
    let text = fanuc_grid::write(&g, "hand");
    assert!(
        text.contains("\n0 0 0 -0.0100000 +0.0000000 +0.0000000\n"),
        "{text}"
    );
    assert!(
        text.contains("\n2 1 1 -0.0100000 +0.0000000 +0.0000000\n"),
        "{text}"
    );
    let head = "UNIT MM\nORIGIN 0 0 0\nEND 10 10 10\nPOINTS 2 2 2\nTOOL 0 0 0\n";
    let corners = |skip: usize| {
        let mut s = String::from(head);
        for n in 0..8 {
            if n != skip {
                s += &format!("{} {} {} 0 0 0\n", n % 2, (n / 2) % 2, n / 4);
            }
        }
        s
    };
    assert!(fanuc_grid::parse(&corners(99), "g").is_ok());
    let refused = |text: &str| fanuc_grid::parse(text, "g").unwrap_err().to_string();
    assert_eq!(
        refused(&corners(5)),
        "g, line 12: corner 1 0 1 is missing: the grid needs all 8 corners"
    );
    assert_eq!(
        refused(&(corners(99) + "1 1 1 0 0 0\n")),
        "g, line 14: corner 1 1 1 is given twice"
    );
    assert_eq!(
        refused(&(corners(99) + "2 0 0 0 0 0\n")),
        "g, line 14: corner 2 0 0 is outside the grid of 2 × 2 × 2 corners (from 0)"
    );
    assert_eq!(
        refused(&corners(99).replace("UNIT MM", "UNIT INCH")),
        "g, line 1: UNIT INCH: axiscomp's grid is in mm (UNIT MM)"
    );
    assert_eq!(
        refused(&corners(99).replace("END 10 10 10\n", "")),
        "g, line 12: no END line: the grid's file gives UNIT, ORIGIN, END, POINTS and TOOL before its corners"
    );
    assert_eq!(
        refused(&corners(99).replace("POINTS 2 2 2", "POINTS 2 2")),
        "g, line 4: POINTS takes three numbers (X, Y, Z), found 2 2"
    );
    assert_eq!(
        refused(&(corners(99) + "0 0 0 0 0,1 0\n")),
        "g, line 14: 0,1 is not a number (mm, with a decimal point)"
    );
}

#[test]
fn the_siemens_programs_read_back_to_what_they_carry() {
    let twin = TwinMachine::new(&MachineSpec::vertical_mc(), 7);
    let model = twin.truth_model(5.0).unwrap();
    let files = siemens::write(&model, 5.0, "twin seed 7");
    let (eec, cec) = (
        text_of(&files, siemens::EEC_FILE),
        text_of(&files, siemens::CEC_FILE),
    );
    assert!(eec.starts_with("%_N_AX_EEC_INI\n; twin seed 7\n"), "{eec}");
    assert!(cec.contains("\nCHANDATA(1)\n") && cec.ends_with("M17\n"));
    assert!(eec.contains("\n$AA_ENC_COMP_STEP[0,X1]=5.000000\n"));
    assert!(eec.contains("\n$AA_ENC_COMP_MAX[0,Y1]=600.000000\n"));
    assert!(cec.contains("\n$AN_CEC_INPUT_AXIS[2]=(Y1)\n$AN_CEC_OUTPUT_AXIS[2]=(X1)\n"));
    let tables = siemens::parse(eec, "eec", cec, "cec").unwrap();
    let back = MachineModel::new(model.chain, tables, Squareness::default()).unwrap();
    // What the programs carry: the model without its angles, the squareness in the
    // straightness.
    let translations = MachineModel::new(
        model.chain,
        model
            .tables()
            .iter()
            .map(|t| {
                let v = t
                    .values()
                    .iter()
                    .map(|r| [r[0], r[1], r[2], 0.0, 0.0, 0.0])
                    .collect();
                ComponentTable::new(t.axis(), t.positions_mm().to_vec(), v).unwrap()
            })
            .collect(),
        model.squareness,
    )
    .unwrap();
    let tool = [0.0, 0.0, -150.0];
    for p in random_points(300, 11) {
        let (a, b) = (translations.error_at(p, tool), back.error_at(p, tool));
        // Three tables add into a direction, each rounded to 7 decimals.
        assert!(
            (0..3).all(|m| (a[m] - b[m]).abs() <= 1.5e-7 * 1.0001),
            "{p:?}: {a:?} {b:?}"
        );
    }
    // By hand: C0Y of 10 µrad leaves Y's line −10 µm in x at y = 1000 mm: +0.010 mm of
    // compensation on X1 at Y1's last point (table 2, 200 points of 5 mm).
    let m = only(
        X,
        [0.0; 6],
        Squareness {
            c0y: 1e-5,
            ..Squareness::default()
        },
    );
    let files = siemens::write(&m, 5.0, "hand");
    let cec = text_of(&files, siemens::CEC_FILE);
    assert!(cec.contains("\n$AN_CEC[2,200]=0.0100000\n"), "{cec}");
    assert!(cec.contains("\n$AN_CEC[2,100]=0.0050000\n"), "{cec}");
    let eec = text_of(&files, siemens::EEC_FILE).to_string();
    let refused = |cec: &str| {
        siemens::parse(&eec, "eec", cec, "cec")
            .unwrap_err()
            .to_string()
    };
    let good = text_of(&files, siemens::CEC_FILE).to_string();
    assert_eq!(
        refused(&good.replace("$AN_CEC_DIRECTION[3]=0", "$AN_CEC_DIRECTION[3]=1")),
        "cec, line 842: $AN_CEC_DIRECTION=1: axiscomp's model takes a table for both directions, unmultiplied, without modulo (0)"
    );
    assert!(
        refused(&good.replace("$AN_CEC_MAX[0]=1000.000000", "$AN_CEC_MAX[0]=990.0")).contains(
            "CEC table 0: 201 points every 5 mm from 0 mm end at 1000 mm, not at MAX 990 mm"
        ),
    );
    assert!(
        refused(&good.replace("$AN_CEC[1,7]=", "$AN_CEC[1,7]=x"))
            .contains("$AN_CEC: x0.0000000 is not a number (mm, with a decimal point)"),
    );
    assert!(
        refused(&good.replace("$AN_CEC[4,3]=0.0000000\n", ""))
            .ends_with("CEC table 4: point 3 has no value"),
    );
    assert!(
        refused(&good.replace("$AN_CEC_OUTPUT_AXIS[5]=(Y1)", "$AN_CEC_OUTPUT_AXIS[5]=(Z1)"))
            .ends_with("Z1 against itself is the EEC's positioning error, not a cross-axis table"),
    );
    assert!(
        refused(&good.replace("CHANDATA(1)", "$AA_ENC_COMP[0,0,X1]=0"))
            .ends_with("$AA_ENC_COMP does not belong in this program: it sets $AN_CEC… alone"),
    );
}

/// A parabola along X: the model at the corners blends to h²f″/8 off at a cell's middle; the
/// corners moved by a sixteenth of their second differences to h²f″/16, at the middle and at
/// the corners alike. On the twin's true tables (short waves) the largest deviation from the
/// model over the volume drops by more than a third.
#[test]
fn a_curvature_balanced_grid_halves_the_blend_s_largest_deviation() {
    // EXX = a·x² (mm), a = 1e-7 /mm: f″ = 2e-7, h = 10 mm, h²f″/8 = 2.5e-6 mm.
    let a = 1e-7;
    let x = ComponentTable::sample(X, 0.0, 1000.0, 1.0, |q| {
        [a * q * q, 0.0, 0.0, 0.0, 0.0, 0.0]
    })
    .unwrap();
    let tables = vec![x, flat(Y, 1000.0, [0.0; 6]), flat(Z, 1000.0, [0.0; 6])];
    let model = MachineModel::new(Chain::cross_table(), tables, Squareness::default()).unwrap();
    let tool = [0.0; 3];
    let sampled =
        Grid::of_model(&model, [0.0; 3], [1000.0, 600.0, 500.0], [10.0; 3], tool).unwrap();
    let balanced = sampled.curvature_balanced();
    let off =
        |g: &Grid, x: f64| g.at([x, 300.0, 250.0])[0] - model.error_at([x, 300.0, 250.0], tool)[0];
    let h2f = 100.0 * 2.0 * a;
    assert!(
        (off(&sampled, 505.0) - h2f / 8.0).abs() < 1e-9,
        "{}",
        off(&sampled, 505.0)
    );
    assert!(off(&sampled, 500.0).abs() < 1e-12);
    assert!((off(&balanced, 505.0) - h2f / 16.0).abs() < 1e-9);
    assert!((off(&balanced, 500.0) + h2f / 16.0).abs() < 1e-9);
    // The other directions are untouched: a field with no curvature is not moved.
    assert!(balanced.at([505.0, 300.0, 250.0])[1].abs() < 1e-15);
    // The twin's truth: largest |grid − model| over 2000 points.
    let twin = TwinMachine::new(&MachineSpec::vertical_mc(), 104);
    let truth = twin.truth_model(5.0).unwrap();
    let tool = [0.0, 0.0, -150.0];
    let g = Grid::of_model(&truth, [0.0; 3], [1000.0, 600.0, 500.0], [10.0; 3], tool).unwrap();
    let largest = |g: &Grid| {
        random_points(2000, 3)
            .into_iter()
            .map(|p| {
                let (u, v) = (g.at(p), truth.error_at(p, tool));
                (0..3).map(|m| (u[m] - v[m]).powi(2)).sum::<f64>().sqrt()
            })
            .fold(0.0f64, f64::max)
    };
    let (before, after) = (largest(&g), largest(&g.curvature_balanced()));
    assert!(after < 0.65 * before, "{after} against {before} mm");
}

/// The manuals' examples, cut to their first points (the manuals elide the rest with "…"):
/// EEC of X1 (Function Manual Extended Functions 03/2013, p. 242: +3, +10, +12 µm from −200 mm
/// every 1 mm) and CEC table 0 of the 802D sl manual (p. 222: X1 against AX2, "basic axis Y1",
/// 0, +10, +12 µm from −400 mm every 6.73 mm, with its comments). Read back as compensations,
/// so the errors are their negatives.
#[test]
fn the_siemens_manual_s_examples_read() {
    let eec = "%_N_AX_EEC_INI\nCHANDATA(1)\n\
               $AA_ENC_COMP[0,0,X1]=0.003 ; 1st compensation value (interpolation point 0): +3µm\n\
               $AA_ENC_COMP[0,1,X1]=0.01 ; 2nd compensation value (interpolation point 1): +10µm\n\
               $AA_ENC_COMP[0,2,X1]=0.012 ; 3rd compensation value (interpolation point 2): +12µm\n\
               $AA_ENC_COMP_STEP[0,X1]=1.0 ; Distance between interpolation points 1.0 mm\n\
               $AA_ENC_COMP_MIN[0,X1]=-200.0 ; Compensation starts at -200.0 mm\n\
               $AA_ENC_COMP_MAX[0,X1]=-198.0 ; (the manual's ends at 600.0 mm, point 800)\n\
               $AA_ENC_COMP_IS_MODULO[0,X1]=0 ; Compensation without modulo function\n\
               M17\n";
    let cec = "%_N_NC_CEC_INI\nCHANDATA(1)\n\
               $AN_CEC[0,0]=0 ; 1. Compensation value (interpolation point 0) for X1: ± 0 µm\n\
               $AN_CEC[0,1]=0.01 ; for X1: + 10 µm\n\
               $AN_CEC[0,2]=0.012 ; for X1: + 12 µm\n\
               $AN_CEC_INPUT_AXIS[0]=(AX2) ; basic axis Y1\n\
               $AN_CEC_OUTPUT_AXIS[0]=(AX1) ; compensation axis X1\n\
               $AN_CEC_STEP[0]=6.73 ; distance between interpolation points 6.73 mm\n\
               $AN_CEC_MIN[0]=-400.0 ; compensation starts at Y1 = -400 mm\n\
               $AN_CEC_MAX[0]=-386.54 ; (the manual's ends at +400 mm)\n\
               $AN_CEC_DIRECTION[0]=0 ; table applies in both traversing directions of Y1\n\
               $AN_CEC_MULT_BY_TABLE[0]=0\n\
               $AN_CEC_IS_MODULO[0]=0 ; compensation without modulo function\n\
               M17\n";
    // The model needs Z too: a table of Z1 into X1 of two points.
    let cec = cec.replace(
        "M17\n",
        "$AN_CEC[1,0]=0\n$AN_CEC[1,1]=0\n$AN_CEC_INPUT_AXIS[1]=(Z1)\n$AN_CEC_OUTPUT_AXIS[1]=(X1)\n\
         $AN_CEC_STEP[1]=500\n$AN_CEC_MIN[1]=0\n$AN_CEC_MAX[1]=500\nM17\n",
    );
    let t = siemens::parse(eec, "eec", &cec, "cec").unwrap();
    assert_eq!(t[0].positions_mm(), [-200.0, -199.0, -198.0]);
    assert_eq!(t[0].values()[1], [-0.01, 0.0, 0.0, 0.0, 0.0, 0.0]);
    let y = &t[1];
    assert_eq!(y.axis(), Y);
    assert!((y.positions_mm()[2] - (-386.54)).abs() < 1e-9);
    assert_eq!(y.values()[2], [-0.012, 0.0, 0.0, 0.0, 0.0, 0.0]);
    assert_eq!(t[2].positions_mm(), [0.0, 500.0]);
}
