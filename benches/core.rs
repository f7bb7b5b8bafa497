//! Measurement-core benchmarks (issue 2): tracing, forward model, linear and nonlinear
//! decoupling, calibration fits. Run with `cargo bench --bench core`.

use axiscomp::Errors6;
use axiscomp::calibrate::{ModelFitOptions, PoseSample, fit_linear, fit_model};
use axiscomp::decouple::{self, Linear, SolveOptions, solve_nonlinear};
use axiscomp::optics::{Layout, Pose};
use axiscomp::sim::{Hexapod, InstallSpec, PoseWindow, Rng, TwinHead};
use axiscomp::util::progress::Progress;
use criterion::{Criterion, criterion_group, criterion_main};
use std::hint::black_box;

fn pose() -> Pose {
    Pose::new(
        Errors6::from_user([12.0, -30.0, 8.0, 15.0, -20.0, 25.0]),
        100.0,
        100.3,
    )
}

fn pose_set(n: usize) -> (Layout, Vec<PoseSample>) {
    let layout = Layout::reference();
    let mut rng = Rng::new(2);
    let head = TwinHead::random(&layout, &InstallSpec::default(), 1e-3, &mut rng).unwrap();
    let poses = PoseWindow::default().draw(n, &mut rng);
    let (samples, _) = Hexapod::default().acquire(&head, &poses, &mut rng, &mut Progress::hidden());
    (layout, samples)
}

fn bench(c: &mut Criterion) {
    let layout = Layout::reference();
    let p = pose();
    c.bench_function("trace three paths (apertures checked)", |b| {
        b.iter(|| black_box(&layout).forward(black_box(&p)))
    });
    c.bench_function("forward model (geometry only)", |b| {
        b.iter(|| decouple::model_readings(black_box(&layout), black_box(&p)))
    });
    let r = layout.forward(&p).vector().unwrap();
    let beta = decouple::jacobian(&layout, &Pose::new(Errors6::ZERO, 100.0, 100.3)).unwrap();
    let offset =
        decouple::model_readings(&layout, &Pose::new(Errors6::ZERO, 100.0, 100.3)).unwrap();
    let lin = Linear::new(beta, offset, &[1e-3; 6]).unwrap();
    c.bench_function("linear decoupling", |b| b.iter(|| lin.solve(black_box(&r))));
    c.bench_function("beta(D) central differences", |b| {
        b.iter(|| decouple::jacobian(black_box(&layout), black_box(&p)))
    });
    let opts = SolveOptions::default();
    c.bench_function("nonlinear decoupling (with beta(D))", |b| {
        b.iter(|| solve_nonlinear(&layout, black_box(&r), 100.0, 100.3, &[1e-3; 6], &opts))
    });
    let (l200, s200) = pose_set(200);
    c.bench_function("linear calibration fit, N = 200", |b| {
        b.iter(|| fit_linear(black_box(&s200), &l200))
    });
    let mut g = c.benchmark_group("model calibration");
    g.sample_size(10);
    g.bench_function("Levenberg-Marquardt fit, N = 200", |b| {
        b.iter(|| {
            fit_model(
                black_box(&s200),
                &l200,
                &ModelFitOptions::default(),
                &mut |_, _| {},
            )
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
