//! Compensation (issue 4): tables from an evaluation, a golden file per controller format,
//! a parse-back of every format with a small independent parser, the one-point sign rule of
//! every controller, Abbe offsets against Δ = ε × r, and a closed loop on the twin's axis.

use axiscomp::Errors6;
use axiscomp::comp::fanuc::{self, PitchOptions, ValueRange};
use axiscomp::comp::heidenhain::{self, ComOptions};
use axiscomp::comp::linuxcnc::{self, CompFileOptions, CompFileType};
use axiscomp::comp::neutral;
use axiscomp::comp::siemens::{self, CecOptions, LecOptions};
use axiscomp::comp::{
    AxisMapping, CompError, CompTable, Exported, MachineAxis, PositioningMode, TableKind, TableSet,
    TableSpec, TableValues, build_tables,
};
use axiscomp::evaluate::axis::synthetic_capture;
use axiscomp::evaluate::{AxisEvaluation, EvalOptions, ReferenceLine, evaluate_captures};
use axiscomp::run::Direction;
use axiscomp::sim::Rng;
use axiscomp::sim::axis::{self as twin, AxisProfile, AxisSpec};
use serde_json::Value;

const UM: f64 = 1e-3;

/// A small Y axis: 6 targets, 0..500 mm, 2 runs, both directions (values in µm / arcsec).
fn small_eval() -> AxisEvaluation {
    let dy_up = [0.0, 3.0, 5.0, 4.0, 7.0, 10.0];
    let reversal = [4.0, 4.5, 4.0, 3.5, 4.0, 4.0];
    let dx = [0.0, 2.0, 5.0, 3.0, 1.0, 4.0];
    let dz = [1.0, -1.0, -2.0, 0.0, 2.0, 1.0];
    let pitch = [0.0, 1.0, 2.0, 3.0, 2.0, 1.0];
    let yaw = [0.0, -1.0, -1.0, 0.0, 1.0, 2.0];
    let mut caps = Vec::new();
    for t in 0..6 {
        for run in 1..=2u32 {
            for d in [Direction::Up, Direction::Down] {
                let j = if run == 1 { -0.1 } else { 0.1 };
                let dy = dy_up[t]
                    + if d == Direction::Down {
                        reversal[t]
                    } else {
                        0.0
                    };
                let e = Errors6::from_user([dx[t], dy + j, dz[t], pitch[t], 0.5, yaw[t]]);
                caps.push(synthetic_capture(
                    t as u32,
                    100.0 * t as f64,
                    run,
                    d,
                    e,
                    Errors6::from_user([0.1; 6]),
                ));
            }
        }
    }
    evaluate_captures(&caps, &EvalOptions::default()).unwrap()
}

fn spec(mode: PositioningMode) -> TableSpec {
    TableSpec {
        mapping: AxisMapping::standard(MachineAxis::Y),
        reference_mm: 0.0,
        positioning: mode,
        straightness_line: ReferenceLine::LeastSquares,
        functional_point_mm: Some([0.0, 0.0, -150.0]),
    }
}

fn tables(mode: PositioningMode) -> TableSet {
    build_tables(&small_eval(), &spec(mode)).unwrap()
}

fn lec_opts() -> LecOptions {
    LecOptions {
        step_mm: Some(50.0),
        ..LecOptions::new("AX2")
    }
}

fn cec_opts() -> CecOptions {
    CecOptions {
        table_index: 0,
        input_axis: "AX2".into(),
        output_axis: "AX1".into(),
        max_points: 100,
        step_mm: Some(50.0),
        ..CecOptions::new("AX2", "AX1")
    }
}

fn fanuc_opts() -> PitchOptions {
    PitchOptions {
        step_mm: Some(50.0),
        ..PitchOptions::new(2, 20)
    }
}

fn com_opts() -> ComOptions {
    ComOptions {
        step_mm: Some(50.0),
        ..ComOptions::new("Y.COM")
    }
}

#[test]
fn tables_follow_the_evaluation() {
    let uni = tables(PositioningMode::Unidirectional);
    let p = &uni.positioning;
    assert_eq!((p.kind, p.name.as_str()), (TableKind::Positioning, "EYY"));
    let TableValues::Single {
        values,
        backlash_mm,
    } = &p.values
    else {
        panic!("unidirectional")
    };
    // The + profile zeroed at 0 mm, and the mean reversal (4 µm) as backlash.
    let want = [0.0, 3.0, 5.0, 4.0, 7.0, 10.0];
    for (v, w) in values.iter().zip(want) {
        assert!((v - w * UM).abs() < 1e-12, "{v} vs {w}");
    }
    assert!((backlash_mm.unwrap() - 4.0 * UM).abs() < 1e-12);
    // Straightness tables act on the transverse axes X (EXY) and Z (EZY).
    let s: Vec<(&str, MachineAxis)> = uni
        .straightness
        .iter()
        .map(|t| (t.name.as_str(), t.comp_axis))
        .collect();
    assert_eq!(s, [("EXY", MachineAxis::X), ("EZY", MachineAxis::Z)]);
    // Least-squares residuals sum to zero before zeroing at the reference; after, v[0] = 0.
    assert_eq!(uni.straightness[0].primary()[0], 0.0);

    let bi = tables(PositioningMode::Bidirectional);
    let TableValues::Bidirectional { up, down } = &bi.positioning.values else {
        panic!("bidirectional")
    };
    assert!((down[1] - up[1] - 4.5 * UM).abs() < 1e-12);
    assert_eq!(up[0], 0.0);
}

#[test]
fn abbe_offsets_are_epsilon_cross_r() {
    let eval = small_eval();
    let set = build_tables(&eval, &spec(PositioningMode::Unidirectional)).unwrap();
    // r = (0, 0, −150) mm; ε = (pitch, roll, yaw) about (X, Y, Z) for the standard Y mapping.
    // Δ = ε × r = (εY·rZ − εZ·rY, εZ·rX − εX·rZ, εX·rY − εY·rX) = (−150·εY, 150·εX, 0).
    // Roll is constant, so Δx is constant and vanishes after zeroing: only Δy remains.
    let names: Vec<&str> = set.abbe.iter().map(|t| t.name.as_str()).collect();
    assert_eq!(names, ["ABBE_Y"]);
    let t = &set.abbe[0];
    assert_eq!(t.comp_axis, MachineAxis::Y);
    let arcsec = std::f64::consts::PI / 648_000.0;
    for (i, v) in t.primary().iter().enumerate() {
        let pitch = eval.profiles[3].mean[i];
        let want = 150.0 * pitch - 150.0 * eval.profiles[3].mean[0];
        assert!((v - want).abs() < 1e-15, "{i}: {v} vs {want}");
    }
    // 3″ of pitch at 150 mm: 2.18 µm.
    assert!((t.primary()[3] - 150.0 * 3.0 * arcsec).abs() < 1e-12);
}

#[test]
fn golden_files() {
    let uni = tables(PositioningMode::Unidirectional);
    let bi = tables(PositioningMode::Bidirectional);
    let text = |r: Result<Exported, CompError>| r.unwrap().text;
    insta::assert_snapshot!(
        "siemens_lec",
        text(siemens::lec(&uni.positioning, &lec_opts()))
    );
    insta::assert_snapshot!(
        "siemens_cec_straightness_x",
        text(siemens::cec(&uni.straightness[0], &cec_opts()))
    );
    insta::assert_snapshot!(
        "siemens_cec_bidirectional",
        text(siemens::cec(
            &bi.positioning,
            &CecOptions {
                output_axis: "AX2".into(),
                ..cec_opts()
            }
        ))
    );
    insta::assert_snapshot!(
        "fanuc_pitch",
        text(fanuc::pitch(&uni.positioning, &fanuc_opts()))
    );
    insta::assert_snapshot!(
        "heidenhain_com",
        text(heidenhain::com(&bi.positioning, &com_opts()))
    );
    insta::assert_snapshot!(
        "linuxcnc_type0",
        text(linuxcnc::comp_file(
            &bi.positioning,
            &CompFileOptions::new(CompFileType::Type0)
        ))
    );
    insta::assert_snapshot!(
        "linuxcnc_type1",
        text(linuxcnc::comp_file(
            &uni.positioning,
            &CompFileOptions::new(CompFileType::Type1)
        ))
    );
    insta::assert_snapshot!("neutral_csv", neutral::csv(&bi.positioning));
    insta::assert_snapshot!("neutral_json", neutral::json(&uni.positioning).unwrap());
}

// ---- independent parsers: each reads a format back into (positions, forward, reverse) ----

/// `name[...]=value` lines → (bracket contents, value).
fn siemens_assignments(text: &str, name: &str) -> Vec<(Vec<String>, String)> {
    text.lines()
        .filter_map(|l| l.strip_prefix(name)?.strip_prefix('['))
        .map(|rest| {
            let (idx, val) = rest.split_once("]=").expect("name[..]=value");
            (
                idx.split(',').map(str::to_string).collect(),
                val.to_string(),
            )
        })
        .collect()
}

fn num(s: &str) -> f64 {
    s.trim()
        .trim_start_matches('(')
        .trim_end_matches(')')
        .parse()
        .unwrap_or_else(|_| panic!("not a number: {s:?}"))
}

fn parse_lec(text: &str) -> (Vec<f64>, Vec<f64>) {
    assert!(text.starts_with("%_N_AX_EEC_INI\nCHANDATA(1)\n"), "{text}");
    assert!(text.ends_with("M17\n"));
    let one = |n: &str| num(&siemens_assignments(text, n)[0].1);
    let (step, min, max) = (
        one("$AA_ENC_COMP_STEP"),
        one("$AA_ENC_COMP_MIN"),
        one("$AA_ENC_COMP_MAX"),
    );
    let vals = siemens_assignments(text, "$AA_ENC_COMP");
    let count = ((max - min) / step).round() as usize + 1;
    assert_eq!(vals.len(), count, "points = (MAX − MIN)/STEP + 1");
    let mut v = vec![f64::NAN; count];
    for (idx, val) in vals {
        assert_eq!(idx[0], "0");
        assert_eq!(idx[2], "AX2");
        v[idx[1].parse::<usize>().unwrap()] = num(&val);
    }
    ((0..count).map(|k| min + k as f64 * step).collect(), v)
}

/// Tables of a CEC file: (index, direction, positions, values).
fn parse_cec(text: &str) -> Vec<(usize, i32, Vec<f64>, Vec<f64>)> {
    assert!(text.starts_with("%_N_NC_CEC_INI\nCHANDATA(1)\n"), "{text}");
    let by_t = |n: &str, t: usize| {
        siemens_assignments(text, n)
            .into_iter()
            .find(|(i, _)| i[0] == t.to_string())
            .map(|(_, v)| v)
    };
    let mut out = Vec::new();
    for t in 0..8 {
        let Some(step) = by_t("$AN_CEC_STEP", t) else {
            continue;
        };
        let (step, min, max) = (
            num(&step),
            num(&by_t("$AN_CEC_MIN", t).unwrap()),
            num(&by_t("$AN_CEC_MAX", t).unwrap()),
        );
        let count = ((max - min) / step).round() as usize + 1;
        let mut v = vec![f64::NAN; count];
        for (i, val) in siemens_assignments(text, "$AN_CEC") {
            if i.len() == 2 && i[0] == t.to_string() {
                v[i[1].parse::<usize>().unwrap()] = num(&val);
            }
        }
        assert!(v.iter().all(|x| x.is_finite()), "every point written");
        let dir = num(&by_t("$AN_CEC_DIRECTION", t).unwrap()) as i32;
        out.push((
            t,
            dir,
            (0..count).map(|k| min + k as f64 * step).collect(),
            v,
        ));
    }
    out
}

/// Fanuc tape → (positions, e) from the parameters and the incremental data, at the points
/// from `from_mm` on (the tape also implies the start of the first interval, which may lie
/// before the table).
fn parse_fanuc(
    text: &str,
    unit_mm: f64,
    increment_mm: f64,
    reference_mm: f64,
    from_mm: f64,
) -> (Vec<f64>, Vec<f64>) {
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!((lines[0], *lines.last().unwrap()), ("%", "%"));
    let mut params = std::collections::HashMap::new();
    let mut data = std::collections::BTreeMap::new();
    for l in &lines[1..lines.len() - 1] {
        let body = l.strip_prefix('N').unwrap();
        if let Some((n, rest)) = body.split_once('A') {
            let (_, p) = rest.split_once('P').unwrap();
            params.insert(n.parse::<u32>().unwrap(), p.parse::<i64>().unwrap());
        } else {
            let (n, p) = body.split_once('P').unwrap();
            data.insert(n.parse::<i64>().unwrap() - 10000, p.parse::<i64>().unwrap());
        }
    }
    let (r, lo, hi) = (params[&3620], params[&3621], params[&3622]);
    let d = params[&3624] as f64 * increment_mm;
    assert_eq!(
        data.keys().copied().collect::<Vec<_>>(),
        (lo..=hi).collect::<Vec<_>>()
    );
    // Absolute compensation C(k) at k·d from the reference: C(0) = 0, C(k) − C(k−1) = value
    // of point r + k.
    let (k_lo, k_hi) = (lo - r - 1, hi - r);
    let mut pos = Vec::new();
    let mut e = Vec::new();
    for k in k_lo..=k_hi {
        let c: i64 = if k >= 0 {
            (r + 1..=r + k).map(|n| data[&n]).sum()
        } else {
            -(r + k + 1..=r).map(|n| data[&n]).sum::<i64>()
        };
        let p = reference_mm + k as f64 * d;
        if p >= from_mm - 1e-9 {
            pos.push(p);
            e.push(-(c as f64) * unit_mm);
        }
    }
    (pos, e)
}

/// `.COM` → (positions, column, BACKLASH column if any).
fn parse_com(text: &str, key: &str) -> (Vec<f64>, Vec<f64>, Option<Vec<f64>>) {
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines[0], "BEGIN Y.COM MM");
    assert_eq!(*lines.last().unwrap(), "[END]");
    let head: Vec<&str> = lines[1].split_whitespace().collect();
    assert_eq!(&head[..3], ["NR", "AXISPOS", key]);
    let has_b = head.get(3) == Some(&"BACKLASH");
    let (mut p, mut v, mut b) = (Vec::new(), Vec::new(), Vec::new());
    for (i, l) in lines[2..lines.len() - 1].iter().enumerate() {
        let f: Vec<&str> = l.split_whitespace().collect();
        assert_eq!(f[0], i.to_string());
        p.push(num(f[1]));
        v.push(num(f[2]));
        if has_b {
            b.push(num(f[3]));
        }
    }
    (p, v, has_b.then_some(b))
}

/// Comp file → (positions, e forward, e reverse).
fn parse_linuxcnc(text: &str, ty: CompFileType) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let (mut p, mut f, mut r) = (Vec::new(), Vec::new(), Vec::new());
    for l in text.lines() {
        let x: Vec<f64> = l.split(' ').map(num).collect();
        assert_eq!(x.len(), 3, "three numbers per line, nothing else: {l:?}");
        p.push(x[0]);
        match ty {
            CompFileType::Type0 => {
                f.push(x[1] - x[0]);
                r.push(x[2] - x[0]);
            }
            CompFileType::Type1 => {
                f.push(-x[1]);
                r.push(-x[2]);
            }
        }
    }
    assert!(p.windows(2).all(|w| w[1] > w[0]), "ascending nominals");
    (p, f, r)
}

fn close(a: &[f64], b: &[f64], tol: f64, what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: length");
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!((x - y).abs() <= tol, "{what}[{i}]: {x} vs {y}");
    }
}

#[test]
fn every_format_parses_back_to_its_table() {
    let uni = tables(PositioningMode::Unidirectional);
    let bi = tables(PositioningMode::Bidirectional);

    let x = siemens::lec(&uni.positioning, &lec_opts()).unwrap();
    let (p, v) = parse_lec(&x.text);
    close(&p, &x.table.positions_mm, 1e-9, "LEC positions");
    close(&v, x.table.primary(), 0.5e-7, "LEC values");
    assert_eq!(p.len(), 11);

    let x = siemens::cec(&uni.straightness[1], &cec_opts()).unwrap();
    let t = parse_cec(&x.text);
    assert_eq!(t.len(), 1);
    assert_eq!(t[0].1, 0);
    close(&t[0].2, &x.table.positions_mm, 1e-9, "CEC positions");
    close(&t[0].3, x.table.primary(), 0.5e-7, "CEC values");
    assert!(x.text.contains("$AN_CEC_OUTPUT_AXIS[0]=(AX1)"));

    let x = siemens::cec(&bi.positioning, &cec_opts()).unwrap();
    let t = parse_cec(&x.text);
    assert_eq!(
        t.iter().map(|t| (t.0, t.1)).collect::<Vec<_>>(),
        [(0, 1), (1, -1)]
    );
    close(&t[0].3, x.table.primary(), 0.5e-7, "CEC up");
    close(&t[1].3, &x.table.reverse(), 0.5e-7, "CEC down");

    let o = fanuc_opts();
    let x = fanuc::pitch(&uni.positioning, &o).unwrap();
    let (p, e) = parse_fanuc(
        &x.text,
        o.unit_mm(),
        o.input_increment_mm,
        0.0,
        x.table.positions_mm[0],
    );
    close(&p, &x.table.positions_mm, 1e-9, "Fanuc positions");
    close(
        &e,
        x.table.primary(),
        o.unit_mm() / 2.0 + 1e-12,
        "Fanuc values",
    );
    assert!(x.text.contains("N01851A2P4\n"), "backlash 4 µm: {}", x.text);

    let x = heidenhain::com(&bi.positioning, &com_opts()).unwrap();
    let (p, v, b) = parse_com(&x.text, "Y");
    close(&p, &x.table.positions_mm, 0.5e-4, "COM positions");
    close(&v, x.table.primary(), 0.5e-4, "COM values");
    close(&b.unwrap(), &x.table.reverse(), 0.5e-4, "COM BACKLASH");
    let x = heidenhain::com(&uni.straightness[0], &com_opts()).unwrap();
    let (_, v, b) = parse_com(&x.text, "X");
    close(&v, x.table.primary(), 0.5e-4, "COM straightness");
    assert!(b.is_none());

    for ty in [CompFileType::Type0, CompFileType::Type1] {
        let x = linuxcnc::comp_file(&bi.positioning, &CompFileOptions::new(ty)).unwrap();
        let (p, f, r) = parse_linuxcnc(&x.text, ty);
        close(&p, &bi.positioning.positions_mm, 1e-9, "LinuxCNC positions");
        close(&f, bi.positioning.primary(), 1e-6, "LinuxCNC forward");
        close(&r, &bi.positioning.reverse(), 1e-6, "LinuxCNC reverse");
    }
    // Backlash is folded into the reverse column (LinuxCNC ignores BACKLASH with a comp file).
    let x =
        linuxcnc::comp_file(&uni.positioning, &CompFileOptions::new(CompFileType::Type1)).unwrap();
    let (_, f, r) = parse_linuxcnc(&x.text, CompFileType::Type1);
    assert!((r[2] - f[2] - 4.0 * UM).abs() < 2e-6);

    let csv = neutral::csv(&bi.positioning);
    let mut rows = csv.lines().filter(|l| !l.starts_with('#'));
    assert_eq!(rows.next(), Some("position_mm,e_up_um,e_down_um"));
    let (mut p, mut u, mut d) = (Vec::new(), Vec::new(), Vec::new());
    for l in rows {
        let f: Vec<f64> = l.split(',').map(num).collect();
        p.push(f[0]);
        u.push(f[1] * UM);
        d.push(f[2] * UM);
    }
    close(&p, &bi.positioning.positions_mm, 1e-9, "CSV positions");
    close(&u, bi.positioning.primary(), 1e-9, "CSV up");
    close(&d, &bi.positioning.reverse(), 1e-9, "CSV down");
    assert!(csv.contains("# base_axis: Y\n# compensated_axis: Y\n"));

    let j: Value = serde_json::from_str(&neutral::json(&uni.positioning).unwrap()).unwrap();
    let arr = |k: &str| -> Vec<f64> {
        j[k].as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect()
    };
    close(
        &arr("positions_mm"),
        &uni.positioning.positions_mm,
        0.0,
        "JSON positions",
    );
    let up: Vec<f64> = arr("e_up_um").iter().map(|v| v * UM).collect();
    close(&up, uni.positioning.primary(), 1e-15, "JSON values");
    assert!((j["backlash_um"].as_f64().unwrap() - 4.0).abs() < 1e-9);
    assert_eq!(j["sign"], "e = measured - nominal");
}

/// +10 µm overshoot at 300 mm only (the carriage stops 10 µm beyond nominal), zero elsewhere.
fn overshoot() -> CompTable {
    let mut v = vec![0.0; 6];
    v[3] = 10.0 * UM;
    CompTable {
        kind: TableKind::Positioning,
        name: "EYY".into(),
        base_axis: MachineAxis::Y,
        comp_axis: MachineAxis::Y,
        reference_mm: 0.0,
        positions_mm: (0..6).map(|k| 100.0 * k as f64).collect(),
        values: TableValues::Single {
            values: v,
            backlash_mm: None,
        },
    }
}

#[test]
fn one_point_sign_rule_of_every_controller() {
    let t = overshoot();
    let step = Some(100.0);
    // Siemens: value = +e ("a positive compensation value moves the axis negative").
    let x = siemens::lec(
        &t,
        &LecOptions {
            step_mm: step,
            ..LecOptions::new("AX2")
        },
    )
    .unwrap();
    assert!(
        x.text.contains("\n$AA_ENC_COMP[0,3,AX2]=0.01\n"),
        "{}",
        x.text
    );
    assert!(x.text.contains("\n$AA_ENC_COMP[0,2,AX2]=0.0\n"));
    let x = siemens::cec(
        &t,
        &CecOptions {
            step_mm: step,
            ..cec_opts()
        },
    )
    .unwrap();
    assert!(x.text.contains("\n$AN_CEC[0,3]=0.01\n"), "{}", x.text);
    // Fanuc: the command is corrected by −10 µm over the interval ending at 300 mm (point
    // 20 + 3) and back by +10 µm over the next.
    let d = fanuc::pitch_data(
        &t,
        &PitchOptions {
            step_mm: step,
            ..fanuc_opts()
        },
    )
    .unwrap();
    let at = |n: u16| d.points.iter().find(|p| p.0 == n).unwrap().1;
    assert_eq!((at(22), at(23), at(24)), (0, -10, 10));
    assert_eq!((d.most_negative, d.most_positive), (20, 25));
    // Heidenhain: value = +e.
    let x = heidenhain::com(
        &t,
        &ComOptions {
            step_mm: step,
            ..ComOptions::new("Y.COM")
        },
    )
    .unwrap();
    assert!(
        x.text
            .lines()
            .any(|l| l.split_whitespace().collect::<Vec<_>>() == ["3", "+300.0000", "+0.0100"]),
        "{}",
        x.text
    );
    // LinuxCNC: type 0 actual = nominal + e; type 1 trim = −e.
    let x = linuxcnc::comp_file(&t, &CompFileOptions::new(CompFileType::Type0)).unwrap();
    assert!(
        x.text.contains("300.000000 300.010000 300.010000\n"),
        "{}",
        x.text
    );
    let x = linuxcnc::comp_file(&t, &CompFileOptions::new(CompFileType::Type1)).unwrap();
    assert!(
        x.text.contains("300.000000 -0.010000 -0.010000\n"),
        "{}",
        x.text
    );
    // Ours: +e in µm.
    assert!(neutral::csv(&t).contains("\n300.0,10.000000\n"));
    let j: Value = serde_json::from_str(&neutral::json(&t).unwrap()).unwrap();
    assert!((j["e_up_um"][3].as_f64().unwrap() - 10.0).abs() < 1e-9);
}

#[test]
fn limits_and_refusals() {
    let uni = tables(PositioningMode::Unidirectional);
    // 3 points at most cannot hold the table at its measured spacing: refused (a 5-point
    // limit resampled a 1000 mm table 264 mm apart), with the spacing that would fit.
    let mean = uni.positioning.mean_step_mm();
    let e = siemens::lec(
        &uni.positioning,
        &LecOptions {
            max_points: 3,
            ..LecOptions::new("AX2")
        },
    )
    .unwrap_err()
    .to_string();
    assert_eq!(mean, 100.0);
    assert_eq!(
        e,
        "Siemens LEC: 6 points at the measured targets' spacing of 100.0 mm (they would be 266.667 mm apart) exceeds MD38000 $MA_MM_ENC_COMP_MAX_POINTS = 3: raise comp.siemens.enc_comp_max_points (--max-points) with MD38000 on the control, or ask for the coarser table with --step-mm 266.667"
    );
    // Asked for by --step-mm, the coarser table is written: 3 points over 0..500 mm.
    let x = siemens::lec(
        &uni.positioning,
        &LecOptions {
            max_points: 3,
            step_mm: Some(250.0),
            ..LecOptions::new("AX2")
        },
    )
    .unwrap();
    let g = x.grid.unwrap();
    assert!(g.count <= 3 && g.end_mm() >= 500.0, "{g:?}");
    // A reference point far outside the measured range is refused.
    let mut far = uni.positioning.clone();
    far.reference_mm = 5000.0;
    let e = siemens::lec(&far, &LecOptions::new("AX2"))
        .unwrap_err()
        .to_string();
    assert!(
        e.starts_with("Siemens LEC: the reference point 5000.0 mm is 4500.0 mm outside the measured range 0.0 to 500.0 mm (more than one spacing, 100.0 mm)"),
        "{e}"
    );
    // int8 overflow is refused with a hint; a magnification makes it fit.
    let mut big = overshoot();
    if let TableValues::Single { values, .. } = &mut big.values {
        values[3] = 300.0 * UM;
    }
    let o = PitchOptions {
        step_mm: Some(100.0),
        ..fanuc_opts()
    };
    let e = fanuc::pitch(&big, &o).unwrap_err().to_string();
    assert!(
        e.contains("point 23 = -300 at 300 mm is outside -128 to 127"),
        "{e}"
    );
    assert!(e.contains("raise the magnification"), "{e}");
    assert!(
        fanuc::pitch(
            &big,
            &PitchOptions {
                magnification: 3,
                ..o.clone()
            }
        )
        .is_ok()
    );
    assert!(
        fanuc::pitch(
            &big,
            &PitchOptions {
                range: ValueRange::Int16,
                ..o
            }
        )
        .is_ok()
    );
    // Format limits.
    let bi = tables(PositioningMode::Bidirectional);
    let e = siemens::lec(&bi.positioning, &lec_opts())
        .unwrap_err()
        .to_string();
    assert!(e.contains("LEC is not direction-dependent"), "{e}");
    let e = siemens::lec(&uni.straightness[0], &lec_opts())
        .unwrap_err()
        .to_string();
    assert!(e.contains("use cec"), "{e}");
    let e = siemens::lec(&uni.positioning, &LecOptions::new("X 1"))
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("option machine_axis: \"X 1\""), "{e}");
    let e = heidenhain::com(&uni.positioning, &ComOptions::new("Y.TXT")).unwrap_err();
    assert!(e.to_string().contains("Y.COM"), "{e}");
    // A bidirectional table needs both directions.
    let mut caps = Vec::new();
    for t in 0..3 {
        for run in 1..=2 {
            caps.push(synthetic_capture(
                t,
                10.0 * t as f64,
                run,
                Direction::Up,
                Errors6::ZERO,
                Errors6::ZERO,
            ));
        }
    }
    let eval = evaluate_captures(&caps, &EvalOptions::default()).unwrap();
    let e = build_tables(&eval, &spec(PositioningMode::Bidirectional)).unwrap_err();
    assert!(e.to_string().contains("needs both directions"), "{e}");
}

#[test]
fn closed_loop_on_the_twin_axis() {
    // The twin's true errors as captures (no noise); tables back to the controller; the
    // compensated axis at the grid points is flat up to the controller's resolution.
    let profile = AxisProfile::random(&AxisSpec::default(), &mut Rng::new(7));
    let mut caps = Vec::new();
    for t in 0..41u32 {
        let p = 25.0 * t as f64;
        for run in 1..=5 {
            for (d, td) in [
                (Direction::Up, twin::Direction::Up),
                (Direction::Down, twin::Direction::Down),
            ] {
                caps.push(synthetic_capture(
                    t,
                    p,
                    run,
                    d,
                    profile.errors(p, td, 0.0),
                    Errors6::ZERO,
                ));
            }
        }
    }
    let eval = evaluate_captures(&caps, &EvalOptions::default()).unwrap();
    let set = build_tables(&eval, &spec(PositioningMode::Unidirectional)).unwrap();
    let TableValues::Single { backlash_mm, .. } = set.positioning.values else {
        panic!()
    };
    // The twin's backlash, recovered.
    assert!((backlash_mm.unwrap() - 5.0 * UM).abs() < 1e-12);
    let up = |p: f64| profile.errors(p, twin::Direction::Up, 0.0).dy;
    let e0 = up(0.0);

    // LinuxCNC type 1 at the measured nominals: commanded + trim lands on nominal (relative to
    // the reference point, where the table is zero).
    let x =
        linuxcnc::comp_file(&set.positioning, &CompFileOptions::new(CompFileType::Type1)).unwrap();
    let (p, f, _) = parse_linuxcnc(&x.text, CompFileType::Type1);
    for (p, f) in p.iter().zip(&f) {
        let residual = (up(*p) - e0) - f;
        assert!(residual.abs() < 1e-6, "{p} mm: {residual}");
    }
    // Fanuc on a 50 mm grid: at the grid points the residual is within half a unit.
    let o = PitchOptions {
        step_mm: Some(50.0),
        ..fanuc_opts()
    };
    let x = fanuc::pitch(&set.positioning, &o).unwrap();
    let (p, e) = parse_fanuc(&x.text, o.unit_mm(), o.input_increment_mm, 0.0, 0.0);
    assert_eq!(p.len(), 21);
    for (p, e) in p.iter().zip(&e) {
        let residual = (up(*p) - e0) - e;
        assert!(residual.abs() <= 0.5 * UM + 1e-12, "{p} mm: {residual}");
    }
}
