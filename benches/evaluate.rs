//! Evaluation and compensation benchmarks (issue 4): 41 targets × 5 runs, both directions, from
//! the twin's axis. Run with `cargo bench --bench evaluate`.

use axiscomp::Errors6;
use axiscomp::comp::fanuc::{self, PitchOptions};
use axiscomp::comp::heidenhain::{self, ComOptions};
use axiscomp::comp::linuxcnc::{self, CompFileOptions, CompFileType};
use axiscomp::comp::siemens::{self, CecOptions, LecOptions};
use axiscomp::comp::{AxisMapping, MachineAxis, PositioningMode, TableSpec, build_tables, neutral};
use axiscomp::evaluate::axis::synthetic_capture;
use axiscomp::evaluate::{EvalOptions, ReferenceLine, evaluate_captures, iso230_2};
use axiscomp::run::{Capture, Direction};
use axiscomp::sim::Rng;
use axiscomp::sim::axis::{self as twin, AxisProfile, AxisSpec};
use criterion::{Criterion, criterion_group, criterion_main};
use std::hint::black_box;

fn captures() -> Vec<Capture> {
    let mut rng = Rng::new(4);
    let profile = AxisProfile::random(&AxisSpec::default(), &mut rng);
    let mut v = Vec::new();
    for t in 0..41u32 {
        let p = 5.0 + 24.5 * t as f64 + rng.uniform(-2.0, 2.0);
        for run in 1..=5 {
            for (d, td) in [
                (Direction::Up, twin::Direction::Up),
                (Direction::Down, twin::Direction::Down),
            ] {
                let noise = Errors6::from_user(std::array::from_fn(|_| rng.normal() * 0.3));
                let e = Errors6::from_array(std::array::from_fn(|k| {
                    profile.errors(p, td, 0.0).to_array()[k] + noise.to_array()[k]
                }));
                v.push(synthetic_capture(
                    t,
                    p,
                    run,
                    d,
                    e,
                    Errors6::from_user([0.3; 6]),
                ));
            }
        }
    }
    v
}

fn bench(c: &mut Criterion) {
    let caps = captures();
    let opts = EvalOptions::default();
    c.bench_function(
        "evaluate 41 targets x 5 runs x 2 directions (six DOFs)",
        |b| b.iter(|| evaluate_captures(black_box(&caps), &opts)),
    );
    let samples: Vec<iso230_2::Sample> = caps
        .iter()
        .map(|c| iso230_2::Sample {
            target_index: c.target_index,
            target_mm: c.target_mm,
            run: c.run,
            direction: c.direction,
            line: None,
            value: c.errors.dy,
        })
        .collect();
    c.bench_function("ISO 230-2 only, 410 deviations", |b| {
        b.iter(|| iso230_2::evaluate(black_box(&samples)))
    });
    let eval = evaluate_captures(&caps, &opts).unwrap();
    let spec = TableSpec {
        mapping: AxisMapping::standard(MachineAxis::Y),
        reference_mm: 0.0,
        positioning: PositioningMode::Unidirectional,
        straightness_line: ReferenceLine::LeastSquares,
        functional_point_mm: Some([0.0, 0.0, -150.0]),
    };
    c.bench_function("build tables (positioning, 2 straightness, Abbe)", |b| {
        b.iter(|| build_tables(black_box(&eval), &spec))
    });
    let set = build_tables(&eval, &spec).unwrap();
    let p = &set.positioning;
    let cec = CecOptions {
        step_mm: Some(10.0),
        ..CecOptions::new("AX2", "AX1")
    };
    let lec = LecOptions {
        step_mm: Some(10.0),
        ..LecOptions::new("AX2")
    };
    let fan = PitchOptions {
        step_mm: Some(10.0),
        ..PitchOptions::new(2, 20)
    };
    let com = ComOptions::new("Y.COM");
    let lcnc = CompFileOptions::new(CompFileType::Type1);
    c.bench_function(
        "all exports (LEC, CEC, Fanuc, .COM, LinuxCNC, CSV, JSON)",
        |b| {
            b.iter(|| {
                (
                    siemens::lec(black_box(p), &lec).map(|x| x.text.len()),
                    siemens::cec(black_box(&set.straightness[0]), &cec).map(|x| x.text.len()),
                    fanuc::pitch(black_box(p), &fan).map(|x| x.text.len()),
                    heidenhain::com(black_box(p), &com).map(|x| x.text.len()),
                    linuxcnc::comp_file(black_box(p), &lcnc).map(|x| x.text.len()),
                    neutral::csv(black_box(p)).len(),
                    neutral::json(black_box(p)).map(|s| s.len()),
                )
            })
        },
    );
    c.bench_function("captures to all tables and exports", |b| {
        b.iter(|| {
            let e = evaluate_captures(black_box(&caps), &opts).ok()?;
            let s = build_tables(&e, &spec).ok()?;
            Some((
                siemens::lec(&s.positioning, &lec).ok()?.text.len(),
                siemens::cec(&s.straightness[0], &cec).ok()?.text.len(),
                siemens::cec(&s.straightness[1], &cec).ok()?.text.len(),
                fanuc::pitch(&s.positioning, &fan).ok()?.text.len(),
            ))
        })
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
