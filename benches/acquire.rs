//! Acquisition benchmark: the acquisition loop reading the twin's I/O module (generic map) on
//! loopback, unthrottled (rate 0), through the link task (one read at a time, a queue, a task
//! switch and a timer per frame) and through the pipelined reader at depths 1 and 4 (what the
//! service uses at rate 0). Criterion measures the time per frame; the frames/s and the
//! per-frame request-to-reply latency (p50, p99) over a fixed run are printed for each. Run
//! with `cargo bench --bench acquire`; benches/acquire_ratio.sh compares the whole service
//! with a C libmodbus client.

use axiscomp::acquire::map::IoMap;
use axiscomp::acquire::{AcquireConfig, Acquisition};
use axiscomp::modbus::{Link, LinkConfig};
use axiscomp::optics::Layout;
use axiscomp::sim::iomodule::IoModule;
use axiscomp::sim::plant::{Plant, PlantSpec};
use criterion::{Criterion, criterion_group, criterion_main};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::broadcast::error::RecvError;

fn bench(c: &mut Criterion) {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let module = rt.block_on(async {
        let plant = Arc::new(
            Plant::new(&Layout::reference(), &PlantSpec::default(), Instant::now()).expect("plant"),
        );
        IoModule::generic(plant).await.expect("I/O module")
    });
    let map = Arc::new(IoMap::generic().expect("generic map"));
    let config = AcquireConfig {
        rate_hz: 0.0,
        ..AcquireConfig::default()
    };
    let mut g = c.benchmark_group("acquire");
    g.sample_size(20);
    g.measurement_time(Duration::from_secs(5));
    for way in ["link task", "pipelined, depth 1", "pipelined, depth 4"] {
        let acq = rt.block_on(async {
            let cfg = LinkConfig::new(module.local_addr());
            let acq = match way {
                "link task" => Acquisition::spawn(Link::spawn(cfg), map.clone(), config),
                "pipelined, depth 1" => Acquisition::spawn_pipelined(
                    cfg,
                    map.clone(),
                    AcquireConfig {
                        pipeline: 1,
                        ..config
                    },
                ),
                _ => Acquisition::spawn_pipelined(
                    cfg,
                    map.clone(),
                    AcquireConfig {
                        pipeline: 4,
                        ..config
                    },
                ),
            };
            assert!(
                acq.link().wait_connected(Duration::from_secs(5)).await,
                "link up"
            );
            acq
        });
        // Frames that arrive while `iters` frames are awaited (lagged frames count as arrived).
        let frames = |iters: u64| {
            rt.block_on(async {
                let mut rx = acq.subscribe();
                let start = Instant::now();
                let mut n = 0u64;
                while n < iters {
                    match rx.recv().await {
                        Ok(_) => n += 1,
                        Err(RecvError::Lagged(k)) => n += k,
                        Err(RecvError::Closed) => panic!("acquisition ended"),
                    }
                }
                start.elapsed()
            })
        };
        // A fixed run for the figures the report quotes.
        frames(2000);
        let n = 20_000;
        let elapsed = frames(n);
        let st = acq.stats();
        let ls = acq.link().stats();
        println!(
            "acquire ({way}; twin I/O module on loopback, unthrottled): {:.0} frames/s over {n} \\
             frames; per-frame latency p50 {:?}, p99 {:?} (window of the last 1024); \\
             invalid {}, read errors {}, link errors {}",
            n as f64 / elapsed.as_secs_f64(),
            st.latency_p50.unwrap_or_default(),
            st.latency_p99.unwrap_or_default(),
            st.invalid_frames,
            st.read_errors,
            ls.errors,
        );
        g.bench_function(format!("frame from the twin's I/O module ({way})"), |b| {
            b.iter_custom(&frames)
        });
        drop(acq);
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
