//! Controller exports that real controls load (issue 16): golden files from the vendors' worked
//! examples (each test names the document and page), a test per defect fixed, the two new
//! families (Beckhoff ISG, Mitsubishi) with one-point sign tests and a refusal per limit, and
//! the `axiscomp export` CLI contract over a real store.

use crate::helpers::{TempDir, run};
use axiscomp::comp::beckhoff::{self, SsfkOptions};
use axiscomp::comp::fanuc::{self, PitchOptions, ValueRange};
use axiscomp::comp::heidenhain::{self, Backlash, ComOptions, Family};
use axiscomp::comp::linuxcnc::{self, CompFileOptions, CompFileType, Units};
use axiscomp::comp::mitsubishi::{self, MecOptions, Mode};
use axiscomp::comp::siemens::{self, CecOptions, EndHandling, LecOptions, SiemensControl};
use axiscomp::comp::{CompTable, MachineAxis, TableKind, TableValues};
use axiscomp::run::Direction;
use axiscomp::store::Store;

const UM: f64 = 1e-3;

fn table(positions: Vec<f64>, values: TableValues, reference_mm: f64) -> CompTable {
    CompTable {
        kind: TableKind::Positioning,
        name: "EXX".into(),
        base_axis: MachineAxis::X,
        comp_axis: MachineAxis::X,
        reference_mm,
        positions_mm: positions,
        values,
    }
}

fn single(v: Vec<f64>) -> TableValues {
    TableValues::Single {
        values: v,
        backlash_mm: None,
    }
}

/// +10 µm overshoot at 300 mm, zero elsewhere, over 0..500 mm.
fn overshoot() -> CompTable {
    let mut v = vec![0.0; 6];
    v[3] = 10.0 * UM;
    table((0..6).map(|k| 100.0 * k as f64).collect(), single(v), 0.0)
}

fn lines(text: &str) -> Vec<&str> {
    text.lines().collect()
}

// ---------------------------------------------------------------- Siemens

/// SINUMERIK 840D sl Function Manual Extended Functions (6FC5397-1BP40-3BA1, 03/2013), K3
/// §4.4.2.3 "Example", p. 242: machine axis X1, 801 points from −200 to 600 mm at 1 mm, the
/// first values +3, +10, +12 µm and the last 0.
#[test]
fn siemens_lec_reproduces_the_k3_example() {
    let positions: Vec<f64> = (0..801).map(|k| -200.0 + k as f64).collect();
    let mut v = vec![0.005; 801];
    v[0] = 0.003;
    v[1] = 0.010;
    v[2] = 0.012;
    v[800] = 0.0;
    let t = table(positions, single(v), 600.0);
    let x = siemens::lec(
        &t,
        &LecOptions {
            max_points: 801,
            step_mm: Some(1.0),
            ..LecOptions::new("X1")
        },
    )
    .unwrap();
    let l = lines(&x.text);
    for want in [
        "%_N_AX_EEC_INI",
        "CHANDATA(1)",
        "$AA_ENC_COMP[0,0,X1]=0.003",
        "$AA_ENC_COMP[0,1,X1]=0.01",
        "$AA_ENC_COMP[0,2,X1]=0.012",
        "$AA_ENC_COMP[0,800,X1]=0.0",
        "$AA_ENC_COMP_STEP[0,X1]=1.0",
        "$AA_ENC_COMP_MIN[0,X1]=-200.0",
        "$AA_ENC_COMP_MAX[0,X1]=600.0",
        "$AA_ENC_COMP_IS_MODULO[0,X1]=0",
        "M17",
    ] {
        assert!(l.contains(&want), "{want} missing");
    }
    // "MD38000 $MA_MM_ENC_COMP_MAX_POINTS ≥ 801".
    assert!(
        x.text
            .contains("MD38000 $MA_MM_ENC_COMP_MAX_POINTS[0,X1] >= 801")
    );
    // One point fewer allowed: refused with the limit, the value and the setting.
    let e = siemens::lec(
        &t,
        &LecOptions {
            max_points: 800,
            step_mm: Some(1.0),
            ..LecOptions::new("X1")
        },
    )
    .unwrap_err()
    .to_string();
    assert_eq!(
        e,
        "Siemens LEC: 801 points at the 1.0 mm spacing asked for exceeds MD38000 $MA_MM_ENC_COMP_MAX_POINTS = 800: raise comp.siemens.enc_comp_max_points (--max-points) with MD38000 on the control or give a larger --step-mm"
    );
    assert_eq!(e.lines().count(), 1);
}

/// Defect: the geometry letter was passed as the axis; K3 wants the machine axis name.
#[test]
fn siemens_refuses_a_geometry_letter() {
    for f in [
        siemens::lec(&overshoot(), &LecOptions::new("X")).map(|_| ()),
        siemens::cec(&overshoot(), &CecOptions::new("X1", "Y")).map(|_| ()),
    ] {
        let e = f.unwrap_err().to_string();
        assert!(e.contains("geometry axis letter"), "{e}");
        assert!(e.contains("MD10000"), "{e}");
        assert_eq!(e.lines().count(), 1);
    }
    assert_eq!(siemens::default_machine_axis("Y"), "Y1");
}

/// Defect: K3 p. 240 — the end values stay active beyond the table; `zero` adds a 0 point
/// beyond each end, `hold` says that it holds.
#[test]
fn siemens_end_handling_is_written_and_said() {
    let t = overshoot();
    let o = LecOptions {
        step_mm: Some(100.0),
        ..LecOptions::new("X1")
    };
    let held = siemens::lec(&t, &o).unwrap();
    assert!(held.text.contains("; ends: held"));
    assert!(held.text.contains("$AA_ENC_COMP_MIN[0,X1]=0.0"));
    assert!(held.text.contains("$AA_ENC_COMP[0,3,X1]=0.01"));
    let zero = siemens::lec(
        &t,
        &LecOptions {
            ends: EndHandling::Zero,
            ..o.clone()
        },
    )
    .unwrap();
    assert!(zero.text.contains("; ends: zero"));
    assert!(zero.text.contains("$AA_ENC_COMP_MIN[0,X1]=-100.0"));
    assert!(zero.text.contains("$AA_ENC_COMP_MAX[0,X1]=600.0"));
    assert!(zero.text.contains("$AA_ENC_COMP[0,0,X1]=0.0"));
    assert!(zero.text.contains("$AA_ENC_COMP[0,4,X1]=0.01"));
    assert!(zero.text.contains("$AA_ENC_COMP[0,7,X1]=0.0"));
    assert_eq!(zero.grid.unwrap().count, 8);
    // The two extra points count against MD38000.
    let e = siemens::lec(
        &t,
        &LecOptions {
            ends: EndHandling::Zero,
            max_points: 7,
            ..o
        },
    )
    .unwrap_err();
    assert!(e.to_string().contains("MD38000"), "{e}");
}

/// Defect: limits follow MD18342 and the 828D's fixed 200; the CEC sign is marked unconfirmed.
#[test]
fn siemens_cec_limits_and_unconfirmed_sign() {
    let t = overshoot();
    let e = siemens::cec(
        &t,
        &CecOptions {
            max_points: 201,
            control: SiemensControl::S828d,
            ..CecOptions::new("X1", "X1")
        },
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("828D's fixed 200 points"), "{e}");
    assert!(e.contains("comp.siemens.cec_max_points"), "{e}");
    let e = siemens::cec(
        &t,
        &CecOptions {
            max_points: 3,
            step_mm: Some(100.0),
            ..CecOptions::new("X1", "X1")
        },
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("6 points") && e.contains("MD18342 $MN_MM_CEC_MAX_POINTS = 3"),
        "{e}"
    );
    let x = siemens::cec(&t, &CecOptions::new("X1", "X1")).unwrap();
    assert!(x.text.contains("; CEC sign unconfirmed"));
}

// ---------------------------------------------------------------- FANUC

/// FANUC Series 0i-PB Parameter Manual B-63980EN/01, parameters 3620–3624, example 1, p. 100:
/// reference position at point 40, points 33…49 holding +2 +1 +1 −2 0 −1 0 −1 +2 +1 0 −1 −1 −2
/// 0 +1 +2. A table whose absolute compensation has these increments gives exactly this tape.
#[test]
fn fanuc_reproduces_the_parameter_manual_example() {
    let inc = [2, 1, 1, -2, 0, -1, 0, -1, 2, 1, 0, -1, -1, -2, 0, 1, 2];
    // Point N = 40 + k covers ((k − 1)·d, k·d]; C(0) = 0 at the reference.
    let c = |k: i64| -> i64 {
        if k >= 0 {
            (1..=k).map(|j| inc[(7 + j) as usize]).sum()
        } else {
            -(k + 1..=0).map(|j| inc[(7 + j) as usize]).sum::<i64>()
        }
    };
    let ks: Vec<i64> = (-8..=9).collect();
    let positions: Vec<f64> = ks.iter().map(|k| 50.0 * *k as f64).collect();
    let e: Vec<f64> = ks.iter().map(|k| -(c(*k) as f64) * UM).collect();
    let t = table(positions, single(e), 0.0);
    let o = PitchOptions {
        step_mm: Some(50.0),
        max_feed_mm_min: Some(24000.0),
        ..PitchOptions::new(1, 40)
    };
    let x = fanuc::pitch(&t, &o).unwrap();
    let l = lines(&x.text);
    for (i, v) in inc.iter().enumerate() {
        let want = format!("N{:05}P{v}", 10033 + i);
        assert!(l.contains(&want.as_str()), "{want} missing:\n{}", x.text);
    }
    for want in [
        "N03620A1P40",
        "N03621A1P33",
        "N03622A1P49",
        "N03623A1P1",
        "N03624A1P50000",
    ] {
        assert!(l.contains(&want), "{want}");
    }
}

/// Defect: 3620 was 0, so a reference in the middle of the travel failed. Now 3620 follows the
/// reference; a configured 3620 that is too small is refused naming 3620.
#[test]
fn fanuc_reference_number_follows_the_reference() {
    // Reference at 300 mm of 0..500 mm (a mill's reference at the positive end is the same).
    let mut t = overshoot();
    t.reference_mm = 300.0;
    let o = PitchOptions {
        reference_number: None,
        step_mm: Some(100.0),
        ..PitchOptions::new(1, 0)
    };
    let d = fanuc::pitch_data(&t, &o).unwrap();
    // Grid 0..500 through 300: k = −3..2, points for k = −2..2 → numbers 0..4, reference 2.
    assert_eq!(
        (d.reference_number, d.most_negative, d.most_positive),
        (2, 0, 4)
    );
    let e = fanuc::pitch(
        &t,
        &PitchOptions {
            reference_number: Some(0),
            ..o
        },
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("points -2 to 2 around reference number 3620 = 0"),
        "{e}"
    );
    assert!(
        e.contains("comp.fanuc.reference_number (parameter 3620) to 2"),
        "{e}"
    );
}

/// Defect: the minimum interval (max feed / 7500) was not checked.
#[test]
fn fanuc_minimum_interval_is_checked() {
    let o = PitchOptions {
        max_feed_mm_min: Some(30000.0),
        step_mm: Some(1.0),
        ..PitchOptions::new(1, 0)
    };
    let e = fanuc::pitch(&overshoot(), &o).unwrap_err().to_string();
    assert_eq!(
        e,
        "Fanuc pitch error: the interval 1.0 mm is below the minimum interval 4.0 mm (max feed 30000.0 mm/min / 7500, parameter 3624): give a --step-mm of at least 4.0 mm, or check comp.fanuc.max_feed_mm_min"
    );
    // Automatic spacing: at least 4 mm.
    let t = table(
        (0..101).map(|k| k as f64).collect(),
        single(vec![0.0; 101]),
        0.0,
    );
    let d = fanuc::pitch_data(&t, &PitchOptions { step_mm: None, ..o }).unwrap();
    assert_eq!(d.interval_increments, 4000);
}

/// Defect: the ±7 × magnification range of older controls was not offered.
#[test]
fn fanuc_legacy_range_is_seven() {
    let o = PitchOptions {
        step_mm: Some(100.0),
        range: ValueRange::Pm7,
        ..PitchOptions::new(1, 0)
    };
    let e = fanuc::pitch(&overshoot(), &o).unwrap_err().to_string();
    assert!(e.contains("= -10 at 300 mm is outside -7 to 7"), "{e}");
    let ok = fanuc::pitch_data(
        &overshoot(),
        &PitchOptions {
            magnification: 2,
            ..o
        },
    )
    .unwrap();
    assert!(ok.points.iter().any(|(_, v)| *v == -5));
    assert_eq!(ValueRange::from_family("legacy"), Some(ValueRange::Pm7));
}

/// Defect: bidirectional pitch error compensation was refused. A-77810E Table (a): 3605#0,
/// 3621/3622 for the positive direction, 3626 start of the negative set, 3627 the absolute
/// compensation at the reference approached in the negative direction.
#[test]
fn fanuc_bidirectional_tape() {
    let up = vec![0.0, 0.0, 0.0, 10.0 * UM, 0.0, 0.0];
    let down = vec![4.0 * UM, 5.0 * UM, 6.0 * UM, 14.0 * UM, 6.0 * UM, 4.0 * UM];
    let t = table(
        (0..6).map(|k| 100.0 * k as f64).collect(),
        TableValues::Bidirectional { up, down },
        0.0,
    );
    let o = PitchOptions {
        reference_number: None,
        step_mm: Some(100.0),
        ..PitchOptions::new(1, 0)
    };
    let x = fanuc::pitch(&t, &o).unwrap();
    let d = fanuc::pitch_data(&t, &o).unwrap();
    let l = lines(&x.text);
    assert!(l.contains(&"N03605A1P00000001"));
    assert!(l.contains(&"N03621A1P0") && l.contains(&"N03622A1P5"));
    assert!(l.contains(&"N03626A1P6"), "{}", x.text);
    // C↓ at the reference = −e↓(0) = −4 µm.
    assert!(l.contains(&"N03627A1P-4"));
    let n = d.negative.unwrap();
    let (at_ref, neg) = (n.at_reference, n.points);
    assert_eq!((n.start, at_ref), (6, -4));
    // Parse back the negative set: C↓(k) = 3627 + Σ increments, e↓ = −C↓.
    let mut c = at_ref;
    let mut e_down = vec![-(c as f64) * UM];
    for (_, v) in neg.iter().skip(1) {
        c += v;
        e_down.push(-(c as f64) * UM);
    }
    for (a, b) in e_down.iter().zip(t.reverse()) {
        assert!((a - b).abs() < 0.5 * UM, "{a} vs {b}");
    }
}

// ---------------------------------------------------------------- LinuxCNC

/// Defect: values were always mm; an inch machine reads every number in inches.
#[test]
fn linuxcnc_inch_file_is_in_inches() {
    let t = overshoot();
    let mm = linuxcnc::comp_file(&t, &CompFileOptions::new(CompFileType::Type1)).unwrap();
    let inch = linuxcnc::comp_file(
        &t,
        &CompFileOptions {
            units: Units::Inch,
            ..CompFileOptions::new(CompFileType::Type1)
        },
    )
    .unwrap();
    assert_eq!(lines(&mm.text)[3], "300.000000 -0.010000 -0.010000");
    // 300 mm = 11.811024 in; −10 µm = −0.00039370 in.
    assert_eq!(lines(&inch.text)[3], "11.81102362 -0.00039370 -0.00039370");
    let t0 = linuxcnc::comp_file(
        &t,
        &CompFileOptions {
            units: Units::Inch,
            ..CompFileOptions::new(CompFileType::Type0)
        },
    )
    .unwrap();
    assert_eq!(lines(&t0.text)[3], "11.81102362 11.81141732 11.81141732");
}

// ---------------------------------------------------------------- HEIDENHAIN

fn bidirectional() -> CompTable {
    table(
        (0..6).map(|k| 100.0 * k as f64).collect(),
        TableValues::Bidirectional {
            up: vec![0.0, 1.0 * UM, 2.0 * UM, 3.0 * UM, 4.0 * UM, 5.0 * UM],
            down: vec![4.0 * UM, 5.0 * UM, 6.0 * UM, 7.0 * UM, 8.0 * UM, 9.0 * UM],
        },
        0.0,
    )
}

/// Defects: AXISPOS is referred to the machine datum; BACKLASH can hold the reversal only.
#[test]
fn heidenhain_tnc640_datum_and_backlash() {
    let t = bidirectional();
    let o = ComOptions {
        step_mm: Some(100.0),
        datum_mm: -250.0,
        ..ComOptions::new("X.COM")
    };
    let x = heidenhain::com(&t, &o).unwrap();
    let l = lines(&x.text);
    assert_eq!(
        l[1].split_whitespace().collect::<Vec<_>>(),
        ["NR", "AXISPOS", "X", "BACKLASH"]
    );
    // Position 100 mm is 350 mm from a datum at −250 mm; BACKLASH = e↓ (the manual's words).
    assert_eq!(
        l[3].split_whitespace().collect::<Vec<_>>(),
        ["1", "+350.0000", "+0.0010", "+0.0050"]
    );
    let r = heidenhain::com(
        &t,
        &ComOptions {
            backlash: Backlash::Reversal,
            ..o
        },
    )
    .unwrap();
    assert_eq!(
        lines(&r.text)[3].split_whitespace().collect::<Vec<_>>(),
        ["1", "+350.0000", "+0.0010", "+0.0040"]
    );
    let cma = heidenhain::cma(&t, "X.COM", None);
    assert!(cma.contains("X.COM") && cma.starts_with("BEGIN"));
}

/// TNC 407 Technical Manual §1.6.4 (p. 4-28): 7 mm asked for → "possible power of two = 2^16 =
/// 6.5536 mm"; the table starts at the datum with 0 and runs positive; at most 256 entries.
#[test]
fn heidenhain_tnc4xx_power_of_two_from_the_datum() {
    assert_eq!(heidenhain::power_of_two_step(7.0).0, 17);
    assert_eq!(heidenhain::power_of_two_step(6.5).1, 6.5536);
    let t = table(
        (0..11).map(|k| 50.0 * k as f64).collect(),
        single((0..11).map(|k| k as f64 * UM).collect()),
        0.0,
    );
    let o = ComOptions {
        family: Family::Tnc4xx,
        step_mm: Some(6.5),
        ..ComOptions::new("X.COM")
    };
    let x = heidenhain::com(&t, &o).unwrap();
    let l = lines(&x.text);
    assert_eq!(l[1], "DATUM +0.0000");
    assert_eq!(l[2], "SPACING 16");
    assert_eq!(
        l[4].split_whitespace().collect::<Vec<_>>(),
        ["0", "+0.0000"]
    );
    // 500 mm / 6.5536 mm → 77 intervals, 78 rows (the manual's Y example: 77).
    assert_eq!(x.grid.unwrap().count, 78);
    // Data below the datum is refused.
    let mut below = t.clone();
    below.reference_mm = 100.0;
    let e = heidenhain::com(&below, &o).unwrap_err().to_string();
    assert!(
        e.contains("below the reference 100.0 mm") && e.contains("--reference-mm"),
        "{e}"
    );
    // More than 256 rows at the spacing asked for.
    let e = heidenhain::com(
        &t,
        &ComOptions {
            step_mm: Some(1.0),
            ..o
        },
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("256 entries per table"), "{e}");
}

// ---------------------------------------------------------------- Beckhoff

/// Beckhoff TF5200 Axis compensation, "Example – Non-equidistant bilateral SSFK": setpoints
/// −200000, −199306, −198667 (0.1 µm); pos 0, 24, −102; neg 0, 67, 80.
#[test]
fn beckhoff_reproduces_the_manual_example() {
    let t = table(
        vec![-20.0, -19.9306, -19.8667],
        TableValues::Bidirectional {
            up: vec![0.0, 2.4 * UM, -10.2 * UM],
            down: vec![0.0, 6.7 * UM, 8.0 * UM],
        },
        -20.0,
    );
    let x = beckhoff::ssfk(&t, &SsfkOptions::new(2, "Y")).unwrap();
    let kv: Vec<(String, String)> = x
        .text
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| {
            let mut f = l.split_whitespace();
            (f.next().unwrap().into(), f.next().unwrap().into())
        })
        .collect();
    let get = |k: &str| kv.iter().find(|(a, _)| a == k).map(|(_, v)| v.as_str());
    for (k, v) in [
        ("kopf.achs_nr", "2"),
        ("kw.ssfk.interval", "0"),
        ("kw.ssfk.kw_startpos", "-200000"),
        ("kw.ssfk.kw_nr_max", "3"),
        ("kw.ssfk.unit", "1"),
        ("kw.ssfk.bilateral", "1"),
        ("kw.ssfk.table[0].setpoint", "-200000"),
        ("kw.ssfk.table[1].setpoint", "-199306"),
        ("kw.ssfk.table[2].setpoint", "-198667"),
        ("kw.ssfk.table[1].pos", "24"),
        ("kw.ssfk.table[2].pos", "-102"),
        ("kw.ssfk.table[1].neg", "67"),
        ("kw.ssfk.table[2].neg", "80"),
    ] {
        assert_eq!(get(k), Some(v), "{k}");
    }
}

/// One point: +10 µm overshoot → +100 (0.1 µm, value = measured − setpoint); refusal beyond
/// P-COMP-00059.
#[test]
fn beckhoff_one_point_sign_and_limit() {
    let x = beckhoff::ssfk(&overshoot(), &SsfkOptions::new(1, "X")).unwrap();
    assert!(
        x.text
            .lines()
            .any(|l| l.split_whitespace().eq(["kw.ssfk.table[3].pos", "100"]))
    );
    assert!(x.text.contains("kw.ssfk.bilateral            0"));
    assert!(!x.text.contains(".neg"));
    let long = table(
        (0..2001).map(|k| k as f64).collect(),
        single(vec![0.0; 2001]),
        0.0,
    );
    let e = beckhoff::ssfk(
        &long,
        &SsfkOptions {
            step_mm: Some(1.0),
            ..SsfkOptions::new(1, "X")
        },
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("2001 points") && e.contains("P-COMP-00059 kw.ssfk.max_points = 1500"),
        "{e}"
    );
}

// ---------------------------------------------------------------- Mitsubishi

/// One point: +10 µm overshoot at 300 mm → absolute −10 at that division point; incremental
/// −10 into it and +10 out of it; the range −128..127 is refused with the scale factor named.
#[test]
fn mitsubishi_one_point_sign_and_range() {
    let o = MecOptions {
        step_mm: Some(100.0),
        ..MecOptions::new("X")
    };
    let a = mitsubishi::mec_data(&overshoot(), &o).unwrap();
    assert_eq!(a.values[3], (4, -10));
    assert_eq!(a.reference_number, 1);
    let x = mitsubishi::mec(&overshoot(), &o).unwrap();
    assert!(x.text.lines().any(|l| l == "#4104 -10"));
    assert!(x.text.contains("unconfirmed"));
    let i = mitsubishi::mec_data(
        &overshoot(),
        &MecOptions {
            mode: Mode::Incremental,
            ..o.clone()
        },
    )
    .unwrap();
    assert_eq!(
        i.values.iter().map(|v| v.1).collect::<Vec<_>>(),
        [0, 0, 0, -10, 10, 0]
    );
    let mut big = overshoot();
    if let TableValues::Single { values, .. } = &mut big.values {
        values[3] = 200.0 * UM;
    }
    let e = mitsubishi::mec(&big, &o).unwrap_err().to_string();
    assert!(
        e.contains("-200") && e.contains("-128 to 127") && e.contains("#4006 sc"),
        "{e}"
    );
    assert!(mitsubishi::mec(&big, &MecOptions { scale: 2, ..o }).is_ok());
}

// ---------------------------------------------------------------- CLI contract

/// A store with one X run (0..400 mm, 5 targets, both directions, +10 µm at 200 mm up).
fn store_with_run(dir: &TempDir) -> std::path::PathBuf {
    let path = dir.path("axiscomp.db");
    let mut store = Store::open(&path).unwrap();
    crate::helpers::store_synthetic_run(&mut store, None, |t, _, d| {
        (if t == 2 { 10.0 } else { 0.0 }) + if d == Direction::Down { 4.0 } else { 0.0 }
    });
    path
}

#[test]
fn export_cli_contract() {
    let dir = TempDir::new("comp-export");
    let db = store_with_run(&dir);
    let db = db.to_str().unwrap();
    let out = dir.path("X.out");
    let o = out.to_str().unwrap();
    let export = |extra: &[&str]| {
        let mut a = vec!["export", "--run", "1", "--db", db, "--out", o];
        a.extend_from_slice(extra);
        run(&a, "")
    };
    // Siemens: the default machine axis name X1, never the letter.
    let r = export(&["--format", "siemens-lec"]);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let text = std::fs::read_to_string(&out).unwrap();
    assert!(text.contains("$AA_ENC_COMP[0,0,X1]="), "{text}");
    // --machine-axis overrides.
    let r = export(&["--format", "siemens-lec", "--machine-axis", "AX1"]);
    assert!(r.status.success());
    assert!(
        std::fs::read_to_string(&out)
            .unwrap()
            .contains("$AA_ENC_COMP_STEP[0,AX1]=")
    );
    // --max-points with --step-mm: one line naming limit, value and setting; exit 2 or 1, no file change.
    std::fs::remove_file(&out).unwrap();
    let r = export(&[
        "--format",
        "siemens-lec",
        "--max-points",
        "3",
        "--step-mm",
        "100",
    ]);
    assert!(!r.status.success());
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(err.contains("5 points at the 100.0 mm spacing asked for exceeds MD38000 $MA_MM_ENC_COMP_MAX_POINTS = 3"), "{err}");
    assert!(!out.exists(), "nothing written on refusal");
    // --reference-mm: FANUC's 3620 point sits at 200 mm; the table is zero there.
    let r = export(&[
        "--format",
        "fanuc",
        "--reference-mm",
        "200",
        "--step-mm",
        "100",
    ]);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let tape = std::fs::read_to_string(&out).unwrap();
    assert!(
        tape.contains("N03620A1P1\n") && tape.contains("N03621A1P0\n"),
        "{tape}"
    );
    // --units inch, and the joint named.
    let r = export(&["--format", "linuxcnc-type1", "--units", "inch"]);
    assert!(r.status.success());
    let comp = std::fs::read_to_string(&out).unwrap();
    assert_eq!(
        comp.lines().nth(2).unwrap(),
        "7.87401575 -0.00039370 -0.00055118"
    );
    assert!(String::from_utf8_lossy(&r.stderr).contains("[JOINT_0] COMP_FILE"));
    // --family: a wrong word is refused naming the choices.
    let r = export(&["--format", "fanuc", "--family", "31i"]);
    assert!(!r.status.success());
    assert!(String::from_utf8_lossy(&r.stderr).contains("\"0i\", \"legacy\", \"30i\""));
    let com = dir.path("X.COM");
    let r = run(
        &[
            "export",
            "--run",
            "1",
            "--db",
            db,
            "--out",
            com.to_str().unwrap(),
            "--format",
            "heidenhain",
            "--family",
            "tnc640",
        ],
        "",
    );
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    assert!(
        std::fs::read_to_string(&com)
            .unwrap()
            .starts_with("BEGIN X.COM MM\n")
    );
    assert!(dir.path("X.CMA").exists());
    let r = export(&[
        "--format",
        "mitsubishi",
        "--family",
        "incremental",
        "--step-mm",
        "100",
    ]);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    assert!(
        std::fs::read_to_string(&out)
            .unwrap()
            .contains("#4000 Pinc 1\n")
    );
    // [comp.linuxcnc] from --config: a gantry's two joints, inch; the flag overrides the file.
    let cfg = dir.write(
        "gantry.toml",
        "[comp.linuxcnc]\nunits = \"inch\"\njoints = [0, 3]\n",
    );
    let cfg = cfg.to_str().unwrap();
    let r = export(&["--format", "linuxcnc-type1", "--config", cfg]);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(
        err.contains("[JOINT_0] COMP_FILE") && err.contains("[JOINT_3] COMP_FILE"),
        "{err}"
    );
    assert_eq!(
        std::fs::read_to_string(&out)
            .unwrap()
            .lines()
            .nth(2)
            .unwrap(),
        "7.87401575 -0.00039370 -0.00055118"
    );
    let r = export(&[
        "--format",
        "linuxcnc-type1",
        "--config",
        cfg,
        "--units",
        "mm",
    ]);
    assert!(r.status.success());
    assert_eq!(
        std::fs::read_to_string(&out)
            .unwrap()
            .lines()
            .nth(2)
            .unwrap(),
        "200.000000 -0.010000 -0.014000"
    );
    // A bad value in [comp.*] names the key and the file.
    let bad = dir.write("bad.toml", "[comp.siemens]\nends = \"ramp\"\n");
    let r = export(&["--format", "siemens-lec", "--config", bad.to_str().unwrap()]);
    assert_eq!(r.status.code(), Some(2));
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(
        err.contains("bad.toml")
            && err.contains("comp.siemens.ends")
            && err.contains("\"ramp\" is not one of \"hold\", \"zero\""),
        "{err}"
    );
    // --help says what is unconfirmed.
    let h = run(&["export", "--help"], "");
    let h = String::from_utf8_lossy(&h.stdout);
    assert!(
        h.contains("Unconfirmed") && h.contains("--machine-axis") && h.contains("--reference-mm")
    );
}

// ---------------------------------------------------------------- LinuxCNC as a peer
// Run by tests/interop/linuxcnc.sh after installing linuxcnc-uspace.

/// Canonical moves and dwells from LinuxCNC's `rs274` for `program`: (x, dwell after it).
fn rs274_moves(program: &str, dir: &TempDir, name: &str) -> Vec<(f64, f64)> {
    let file = dir.path(name);
    std::fs::write(&file, program).unwrap();
    let out = std::process::Command::new("rs274")
        .arg("-g")
        .arg(&file)
        .output()
        .expect("rs274 (linuxcnc-uspace) on PATH");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "rs274 failed: {text}");
    let mut moves: Vec<(f64, f64)> = Vec::new();
    for l in text.lines() {
        let call = l.split_whitespace().nth(2).unwrap_or("");
        let args = |c: &str| -> Vec<f64> {
            c.split_once('(')
                .and_then(|(_, a)| a.strip_suffix(')'))
                .map(|a| a.split(',').filter_map(|x| x.trim().parse().ok()).collect())
                .unwrap_or_default()
        };
        let rest: String = l.split_whitespace().skip(2).collect::<Vec<_>>().join(" ");
        if call.starts_with("STRAIGHT_FEED") || call.starts_with("STRAIGHT_TRAVERSE") {
            moves.push((args(&rest)[0], 0.0));
        } else if call.starts_with("DWELL") {
            moves.last_mut().expect("a dwell after a move").1 += args(&rest)[0];
        }
        assert!(!l.contains("ERROR"), "{l}");
    }
    moves
}

/// The generated LinuxCNC part program through LinuxCNC's own interpreter: every target of
/// every run and direction is reached in order, from its direction's side, with its dwell, and
/// the axis overruns the end targets before each reversal.
#[test]
#[ignore = "needs rs274 from linuxcnc-uspace: tests/interop/linuxcnc.sh"]
fn linuxcnc_rs274_runs_the_plan() {
    use axiscomp::run::program::generate;
    use axiscomp::run::{CaptureMode, Dialect, Plan, PlanSpec};
    let dir = TempDir::new("rs274");
    let plan = Plan::new(PlanSpec {
        axis: "X".into(),
        start_mm: 0.0,
        end_mm: 200.0,
        targets: 5,
        runs: 2,
        overrun_mm: 5.0,
        dwell_s: 1.5,
        feed_mm_min: 1000.0,
        lead_mm: 10.0,
        reference_mm: None,
    })
    .unwrap();
    let program = generate(&plan, Dialect::LinuxCnc, CaptureMode::Stability).unwrap();
    let moves = rs274_moves(&program, &dir, "cycle.ngc");
    let t = &plan.targets;
    let (first, last) = (t[0], *t.last().unwrap());
    let mut i = 0;
    let mut prev = f64::NAN;
    let mut find = |want: f64, dwell: f64| {
        while i < moves.len() && (moves[i].0 - want).abs() > 1e-4 {
            prev = moves[i].0;
            i += 1;
        }
        assert!(i < moves.len(), "target {want} mm not reached in order");
        assert!(
            (moves[i].1 - dwell).abs() < 1e-9,
            "dwell at {want}: {}",
            moves[i].1
        );
        let from = prev;
        prev = moves[i].0;
        i += 1;
        from
    };
    for _run in 0..plan.spec.runs {
        find(first - plan.spec.overrun_mm, 0.0);
        for &x in t {
            let from = find(x, plan.spec.dwell_s);
            assert!(from < x, "up target {x} approached from {from}");
        }
        find(last + plan.spec.overrun_mm, 0.0);
        for &x in t.iter().rev() {
            let from = find(x, plan.spec.dwell_s);
            assert!(from > x, "down target {x} approached from {from}");
        }
    }
    let dwells = moves.iter().filter(|m| m.1 > 0.0).count();
    assert_eq!(dwells, 2 * t.len() * plan.spec.runs as usize);
}

/// A headless LinuxCNC machine (one linear joint, trivkins, motor command looped back) loading
/// `comp` as `[JOINT_0]COMP_FILE` with `comp_type`, in `units`; runs the display script and
/// returns its JSON result.
fn run_linuxcnc(comp: &str, comp_type: u8, units: Units, moves: &[Vec<f64>]) -> serde_json::Value {
    use std::os::unix::fs::PermissionsExt;
    let dir = TempDir::new(&format!("linuxcnc-{}-{comp_type}", units.name()));
    let (unit, limit, vel, acc, gcode) = match units {
        Units::Mm => ("mm", 400.0, 50.0, 500.0, "G21"),
        Units::Inch => ("inch", 400.0 / 25.4, 2.0, 80.0, "G20"),
    };
    dir.write("comp.dat", comp);
    dir.write("tool.tbl", "");
    dir.write("sim.var", "");
    dir.write(
        "core.hal",
        "loadrt [KINS]KINEMATICS\n\
         loadrt [EMCMOT]EMCMOT servo_period_nsec=[EMCMOT]SERVO_PERIOD num_joints=[KINS]JOINTS\n\
         addf motion-command-handler servo-thread\n\
         addf motion-controller servo-thread\n\
         net j0pos joint.0.motor-pos-cmd => joint.0.motor-pos-fb\n\
         net estop-loop iocontrol.0.user-enable-out => iocontrol.0.emc-enable-in\n\
         net tool-prep-loop iocontrol.0.tool-prepare => iocontrol.0.tool-prepared\n\
         net tool-change-loop iocontrol.0.tool-change => iocontrol.0.tool-changed\n",
    );
    let ui = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/linuxcnc_ui.py");
    let ini = format!(
        "[EMC]\nVERSION = 1.1\nMACHINE = axiscomp-comp-{unit}\n\
         [DISPLAY]\nDISPLAY = {ui}\n\
         [TASK]\nTASK = milltask\nCYCLE_TIME = 0.010\n\
         [RS274NGC]\nPARAMETER_FILE = sim.var\n\
         [EMCMOT]\nEMCMOT = motmod\nCOMM_TIMEOUT = 1.0\nSERVO_PERIOD = 1000000\n\
         [EMCIO]\nEMCIO = io\nCYCLE_TIME = 0.100\nTOOL_TABLE = tool.tbl\n\
         [HAL]\nHALFILE = core.hal\n\
         [TRAJ]\nCOORDINATES = X\nLINEAR_UNITS = {unit}\nANGULAR_UNITS = degree\nMAX_LINEAR_VELOCITY = {vel}\n\
         [KINS]\nKINEMATICS = trivkins coordinates=X\nJOINTS = 1\n\
         [AXIS_X]\nMAX_VELOCITY = {vel}\nMAX_ACCELERATION = {acc}\nMIN_LIMIT = -{limit}\nMAX_LIMIT = {limit}\n\
         [JOINT_0]\nTYPE = LINEAR\nHOME = 0\nHOME_OFFSET = 0\nHOME_SEARCH_VEL = 0\nHOME_LATCH_VEL = 0\n\
         HOME_SEQUENCE = 0\nMAX_VELOCITY = {vel}\nMAX_ACCELERATION = {acc}\nMIN_LIMIT = -{limit}\n\
         MAX_LIMIT = {limit}\nFERROR = 10\nMIN_FERROR = 10\nCOMP_FILE = comp.dat\nCOMP_FILE_TYPE = {comp_type}\n",
        ui = ui.display()
    );
    let ini = dir.write("machine.ini", &ini);
    // As root, rtapi_app runs as $RTAPI_UID: its FIFO must be in a directory that uid can write.
    let fifo = std::env::temp_dir().join(format!("axiscomp-rtapi-{}", std::process::id()));
    std::fs::create_dir_all(&fifo).unwrap();
    std::fs::set_permissions(&fifo, std::fs::Permissions::from_mode(0o777)).unwrap();
    let result = dir.path("result.json");
    let mut child = std::process::Command::new("linuxcnc")
        .arg(&ini)
        .current_dir(dir.path(""))
        .env("RTAPI_FIFO_PATH", fifo.join("rtapi_fifo"))
        .env("RESULT_FILE", &result)
        .env("UNITS_GCODE", gcode)
        .env("MOVES", serde_json::to_string(moves).unwrap())
        .env("FEED", if units == Units::Mm { "3000" } else { "118" })
        .stdout(std::process::Stdio::null())
        .spawn()
        .expect("linuxcnc (linuxcnc-uspace) on PATH");
    let end = axiscomp::util::clock::now() + std::time::Duration::from_secs(180);
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if axiscomp::util::clock::now() > end {
            let _ = child.kill();
            panic!("linuxcnc did not finish within 180 s");
        }
        std::thread::sleep(std::time::Duration::from_millis(200));
    };
    let _ = std::fs::remove_dir_all(&fifo);
    let text = std::fs::read_to_string(&result)
        .unwrap_or_else(|_| panic!("no result from the display (linuxcnc exited {status})"));
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert!(v.get("error").is_none(), "display: {v}");
    v
}

/// A bidirectional table with a curved profile, a reversal and a reference at 100 mm.
fn linuxcnc_table() -> CompTable {
    let p: Vec<f64> = (0..7).map(|k| 50.0 * k as f64).collect();
    let up: Vec<f64> = [-6.0, -2.5, 0.0, 4.0, 9.0, 7.5, 12.0]
        .iter()
        .map(|v| v * UM)
        .collect();
    let down: Vec<f64> = up
        .iter()
        .zip([5.0, 4.0, 3.5, 4.0, 4.5, 5.0, 6.0])
        .map(|(u, b)| u + b * UM)
        .collect();
    table(p, TableValues::Bidirectional { up, down }, 100.0)
}

/// LinuxCNC loads our comp files (types 0 and 1, mm and inch) and applies −e: the correction
/// motor-pos-cmd − pos-cmd read from HAL at table points and between them, approached in both
/// directions, equals −e of that direction, interpolated linearly.
fn linuxcnc_applies(units: Units) {
    let t = linuxcnc_table();
    let u = units.mm();
    let mut at: Vec<f64> = t.positions_mm.clone();
    at.extend(t.positions_mm.windows(2).map(|w| 0.5 * (w[0] + w[1])));
    at.extend([30.0, 212.5]);
    // Approach each point from 20 mm below and from 20 mm above.
    let moves: Vec<Vec<f64>> = at
        .iter()
        .flat_map(|x| [vec![(x - 20.0) / u, x / u], vec![(x + 20.0) / u, x / u]])
        .collect();
    for (ty, file_type) in [(0u8, CompFileType::Type0), (1, CompFileType::Type1)] {
        let comp = linuxcnc::comp_file(
            &t,
            &CompFileOptions {
                units,
                ..CompFileOptions::new(file_type)
            },
        )
        .unwrap();
        let r = run_linuxcnc(&comp.text, ty, units, &moves);
        let rows = r.as_array().unwrap();
        assert_eq!(rows.len(), moves.len());
        // The correction LinuxCNC applies at a reading, and −e of its approach direction.
        let judged = |row: &serde_json::Value| -> (f64, f64, f64, f64) {
            let x = row["x"].as_f64().unwrap() * u;
            let from = row["from"].as_f64().unwrap() * u;
            let correction =
                (row["motor_pos_cmd"].as_f64().unwrap() - row["pos_cmd"].as_f64().unwrap()) * u;
            let profile = if from < x {
                t.primary().to_vec()
            } else {
                t.reverse()
            };
            (
                x,
                from,
                correction,
                -axiscomp::comp::interpolate(&t.positions_mm, &profile, x),
            )
        };
        let report: String = rows
            .iter()
            .map(|row| {
                let (x, from, c, _) = judged(row);
                format!("{x} from {from}: {c:.6}\n")
            })
            .collect();
        // A reading off −e is approached again on a fresh LinuxCNC, once: on a loaded CI
        // machine one reading of 30 (type 1 inch, 50 mm from 70) once held +1.5 µm where −e
        // is −1.5 µm, every other right. A comp file LinuxCNC applies wrongly reads wrong
        // twice; both readings are printed.
        let off: Vec<usize> = (0..rows.len())
            .filter(|&i| {
                let (_, _, c, minus_e) = judged(&rows[i]);
                (c - minus_e).abs() >= 2e-6
            })
            .collect();
        let again = (!off.is_empty()).then(|| {
            let moves: Vec<Vec<f64>> = off.iter().map(|&i| moves[i].clone()).collect();
            run_linuxcnc(&comp.text, ty, units, &moves)
        });
        let mut worst: f64 = 0.0;
        for (i, row) in rows.iter().enumerate() {
            let (x, from, first, minus_e) = judged(row);
            let correction = match (&again, off.iter().position(|&j| j == i)) {
                (Some(a), Some(k)) => {
                    let (_, _, c, _) = judged(&a.as_array().unwrap()[k]);
                    eprintln!(
                        "type {ty} {}: at {x} mm from {from} mm read {first:.6} mm, −e {minus_e:.6} mm; approached again: {c:.6} mm",
                        units.name()
                    );
                    c
                }
                _ => first,
            };
            worst = worst.max((correction - minus_e).abs());
            assert!(
                (correction - minus_e).abs() < 2e-6,
                "type {ty} {}: at {x} mm from {from} mm LinuxCNC applies {:.6} mm, −e = {:.6} mm; all readings (mm):\n{report}",
                units.name(),
                correction,
                minus_e
            );
        }
        eprintln!(
            "LinuxCNC type {ty} {}: {} readings, largest |correction + e| {:.2e} mm",
            units.name(),
            rows.len(),
            worst
        );
    }
}

#[test]
#[ignore = "needs linuxcnc-uspace: tests/interop/linuxcnc.sh"]
fn linuxcnc_applies_the_comp_file_mm() {
    linuxcnc_applies(Units::Mm);
}

#[test]
#[ignore = "needs linuxcnc-uspace: tests/interop/linuxcnc.sh"]
fn linuxcnc_applies_the_comp_file_inch() {
    linuxcnc_applies(Units::Inch);
}

// ---------------------------------------------------------------- parse-back of the new formats

/// A curved bidirectional table over 0..500 mm with its reference at 0.
fn curved() -> CompTable {
    let p: Vec<f64> = (0..11).map(|k| 50.0 * k as f64).collect();
    let up: Vec<f64> = p.iter().map(|x| (x / 80.0).sin() * 7.0 * UM).collect();
    let down: Vec<f64> = up.iter().map(|u| u + 4.2 * UM).collect();
    table(p, TableValues::Bidirectional { up, down }, 0.0)
}

#[test]
fn beckhoff_parses_back() {
    let t = curved();
    let x = beckhoff::ssfk(&t, &SsfkOptions::new(1, "X")).unwrap();
    let val = |key: &str| -> Vec<f64> {
        x.text
            .lines()
            .filter(|l| {
                l.starts_with("kw.ssfk.table[")
                    && l.split_whitespace().next().unwrap().ends_with(key)
            })
            .map(|l| l.split_whitespace().nth(1).unwrap().parse::<f64>().unwrap() * 1e-4)
            .collect()
    };
    let (p, pos, neg) = (val("].setpoint"), val("].pos"), val("].neg"));
    assert_eq!(p.len(), 11);
    for i in 0..11 {
        assert!((p[i] - t.positions_mm[i]).abs() < 1e-9);
        assert!((pos[i] - t.primary()[i]).abs() <= 0.5e-4 + 1e-12);
        assert!((neg[i] - t.reverse()[i]).abs() <= 0.5e-4 + 1e-12);
    }
}

#[test]
fn mitsubishi_parses_back() {
    let mut t = curved();
    t.values = single(t.primary().to_vec());
    let o = MecOptions {
        step_mm: Some(50.0),
        ..MecOptions::new("X")
    };
    let read = |text: &str| -> Vec<i64> {
        text.lines()
            .filter_map(|l| l.strip_prefix("#41"))
            .map(|l| l.split_whitespace().nth(1).unwrap().parse().unwrap())
            .collect()
    };
    let abs = read(&mitsubishi::mec(&t, &o).unwrap().text);
    let inc = read(
        &mitsubishi::mec(
            &t,
            &MecOptions {
                mode: Mode::Incremental,
                ..o
            },
        )
        .unwrap()
        .text,
    );
    // Absolute: −e in µm; incremental from the reference (point 0) upwards sums to it.
    let mut c = 0;
    for i in 0..11 {
        assert!((-(abs[i] as f64) * UM - t.primary()[i]).abs() <= 0.5 * UM);
        c += inc[i];
        assert_eq!(c, abs[i], "incremental sum at {i}");
    }
}

#[test]
fn heidenhain_tnc4xx_parses_back() {
    let mut t = curved();
    t.values = single(t.primary().to_vec());
    let x = heidenhain::com(
        &t,
        &ComOptions {
            family: Family::Tnc4xx,
            ..ComOptions::new("X.COM")
        },
    )
    .unwrap();
    let l = lines(&x.text);
    let datum: f64 = l[1].strip_prefix("DATUM ").unwrap().parse().unwrap();
    let k: i32 = l[2].strip_prefix("SPACING ").unwrap().parse().unwrap();
    let step = 1e-4 * 2f64.powi(k);
    assert_eq!(
        step, 52.4288,
        "the power of two at or above the 50 mm targets"
    );
    for (n, row) in l[4..l.len() - 1].iter().enumerate() {
        let f: Vec<&str> = row.split_whitespace().collect();
        let pos = datum + n as f64 * step;
        let want = axiscomp::comp::interpolate(&t.positions_mm, t.primary(), pos);
        assert!(
            (f[1].parse::<f64>().unwrap() - want).abs() <= 0.5e-4 + 1e-12,
            "row {n}"
        );
    }
}
