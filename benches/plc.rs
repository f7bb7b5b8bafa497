//! PLC benchmark (DESIGN §6): publishing a 256-point table over loopback to the twin's PLC
//! (the whole push handshake: status polls, 6 writes, 6 read-backs, the commit and the echo;
//! time per publish), and the pull server's request rate (clients reading the table block —
//! the header, then the payload at most 120 registers per request — in a loop; requests/s
//! printed, for one client and for four at once). The twin's heartbeat counts on
//! every read here (period 1 µs), so a publish never waits for it: a real PLC's heartbeat
//! period adds up to one period. Run with `cargo bench --bench plc`.

use axiscomp::comp::{MachineAxis, TableKind};
use axiscomp::modbus::{Link, LinkConfig, ReadRange};
use axiscomp::optics::Layout;
use axiscomp::plc::serve::{PullConfig, PullServer};
use axiscomp::plc::{CncMap, PlcTable, PublishOutcome, TableDirection, Timeouts, publish};
use axiscomp::sim::plant::{Plant, PlantSpec};
use axiscomp::sim::plc::{TwinPlc, TwinPlcConfig};
use criterion::{Criterion, criterion_group, criterion_main};
use std::sync::Arc;
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

fn table() -> PlcTable {
    PlcTable {
        kind: TableKind::Positioning,
        axis: MachineAxis::Y,
        base_axis: MachineAxis::Y,
        direction: TableDirection::Both,
        start_mm: 0.0,
        interval_mm: 4.0,
        values_mm: (0..256).map(|k| (k as f64 * 0.05).sin() * 0.03).collect(),
        down_mm: None,
    }
}

fn bench(c: &mut Criterion) {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let map = CncMap::generic().expect("generic map");
    let t = table();
    let timeouts = Timeouts {
        poll: Duration::from_millis(1),
        ..Timeouts::default()
    };

    // ---- push ----
    let (twin, link) = rt.block_on(async {
        let plant = Arc::new(
            Plant::new(&Layout::reference(), &PlantSpec::default(), Instant::now()).expect("plant"),
        );
        let twin = TwinPlc::start(
            plant,
            map.clone(),
            TwinPlcConfig {
                heartbeat_period: Duration::from_micros(1),
                ..TwinPlcConfig::default()
            },
        )
        .await
        .expect("twin PLC");
        let link = Link::spawn(LinkConfig::new(twin.local_addr()));
        assert!(link.wait_connected(Duration::from_secs(5)).await, "link up");
        (twin, link)
    });
    let seq = AtomicU32::new(1);
    let publishes = |n: u64| {
        rt.block_on(async {
            let start = Instant::now();
            for _ in 0..n {
                let s = seq.fetch_add(1, Ordering::Relaxed);
                let r = publish(&link, &map, &t, s, timeouts).await;
                assert!(
                    matches!(r, Ok(PublishOutcome::Accepted { .. })),
                    "publish {s}: {r:?}"
                );
            }
            start.elapsed()
        })
    };
    publishes(20);
    let n = 300;
    let el = publishes(n);
    let st = link.stats();
    println!(
        "push (256-point table, generic map, twin PLC on loopback): {:.2} ms per publish over \
         {n} publishes ({:.0} publishes/s); link latency p50 {:?}, p99 {:?}; commits seen by \
         the twin: {}",
        el.as_secs_f64() * 1e3 / n as f64,
        n as f64 / el.as_secs_f64(),
        st.latency_p50.unwrap_or_default(),
        st.latency_p99.unwrap_or_default(),
        twin.commits().len(),
    );
    let mut g = c.benchmark_group("plc");
    g.sample_size(20);
    g.measurement_time(Duration::from_secs(5));
    g.bench_function(
        "publish a 256-point table to the twin PLC (loopback)",
        |b| b.iter_custom(&publishes),
    );

    // ---- pull ----
    let (srv, plink) = rt.block_on(async {
        let srv = PullServer::start(
            map.clone(),
            PullConfig::new("127.0.0.1:0".parse().expect("addr")),
        )
        .await
        .expect("pull server");
        srv.set_table(&t, 1).expect("table");
        let l = Link::spawn(LinkConfig::new(srv.local_addr()));
        assert!(l.wait_connected(Duration::from_secs(5)).await, "link up");
        (srv, l)
    });
    // The block: header (16..30) then the payload in 120-register reads.
    let mut reads = vec![ReadRange::new(16, 14).expect("range")];
    let mut a = 32u16;
    while a < 32 + 512 {
        let n = (32 + 512 - a).min(120);
        reads.push(ReadRange::new(a, n).expect("range"));
        a += n;
    }
    let requests = |n: u64, link: &Link| {
        rt.block_on(async {
            let start = Instant::now();
            for k in 0..n {
                let r = reads[k as usize % reads.len()];
                let v = link.read_holding_registers(1, r).await.expect("read");
                assert_eq!(v.len(), r.count() as usize);
            }
            start.elapsed()
        })
    };
    requests(2000, &plink);
    let n = 20_000;
    let el = requests(n, &plink);
    println!(
        "pull server, one client reading the block (header + 120-register payload reads): \
         {:.0} requests/s over {n} requests ({:.1} µs per request)",
        n as f64 / el.as_secs_f64(),
        el.as_secs_f64() * 1e6 / n as f64
    );
    let clients: Vec<Link> = (0..4)
        .map(|_| {
            rt.block_on(async {
                let l = Link::spawn(LinkConfig::new(srv.local_addr()));
                assert!(l.wait_connected(Duration::from_secs(5)).await, "link up");
                l
            })
        })
        .collect();
    let el = rt.block_on(async {
        let start = Instant::now();
        let mut tasks = Vec::new();
        for l in &clients {
            let (l, reads) = (l.clone(), reads.clone());
            tasks.push(tokio::spawn(async move {
                for k in 0..5000usize {
                    let r = reads[k % reads.len()];
                    l.read_holding_registers(1, r).await.expect("read");
                }
            }));
        }
        for t in tasks {
            t.await.expect("client task");
        }
        start.elapsed()
    });
    println!(
        "pull server, 4 concurrent clients: {:.0} requests/s in total over 20000 requests",
        20_000.0 / el.as_secs_f64()
    );
    g.bench_function("pull server: one read of the table block (loopback)", |b| {
        b.iter_custom(|n| requests(n, &plink))
    });
    g.finish();
    drop(srv);
}

criterion_group!(benches, bench);
criterion_main!(benches);
