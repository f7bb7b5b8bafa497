//! Acquisition against the twin's I/O module on loopback: decoding, reconnect after an outage,
//! blocked beams, server exceptions; and (ignored, run by tests/interop/modbus.sh) against
//! independent peers: a pymodbus server and the mbpoll client.

use crate::helpers::{free_port, link, link_config, plant, raw_request, twin};
use axiscomp::acquire::map::IoMap;
use axiscomp::acquire::{AcquireConfig, Acquisition, Frame};
use axiscomp::modbus::{Link, LinkConfig};
use axiscomp::optics::Spot;
use axiscomp::sim::iomodule::{FixedSource, IoModule, IoModuleConfig, Served};
use axiscomp::sim::plant::PsdSample;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpStream;
use tokio::sync::broadcast;

/// Half a count of the generic map (±10 V over ±32767 counts, 1 mm/V), plus rounding slack.
const HALF_COUNT_MM: f64 = 0.5 * 10.0 / 32767.0 + 1e-12;

async fn next(rx: &mut broadcast::Receiver<Frame>) -> Frame {
    tokio::time::timeout(Duration::from_secs(5), rx.recv())
        .await
        .expect("a frame within 5 s")
        .expect("frame channel open")
}

fn maps_dir() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("plc-maps/io")
}

/// Frame `f` against the sample the module served for it, within `tol` (mm and V).
fn assert_frame_matches(f: &Frame, s: &Served, tol: f64) {
    for k in 0..3 {
        match (f.spots[k], s.sample.spots[k]) {
            (Some(a), Some(b)) => {
                assert!(
                    (a.x - b.x).abs() <= tol && (a.y - b.y).abs() <= tol,
                    "frame {} PSD{}: decoded ({}, {}) vs plant ({}, {})",
                    f.seq,
                    k + 1,
                    a.x,
                    a.y,
                    b.x,
                    b.y
                );
            }
            (None, None) => {}
            (a, b) => panic!("frame {} PSD{}: {a:?} vs plant {b:?}", f.seq, k + 1),
        }
        assert!(
            (f.sums[k] - s.sample.sums[k]).abs() <= tol,
            "frame {} SUM{}: {} vs {}",
            f.seq,
            k + 1,
            f.sums[k],
            s.sample.sums[k]
        );
    }
}

/// 300 unthrottled frames from `acq` (dropped afterwards): valid, in order, each the
/// module's sample for its own request within quantisation (one client, no errors: frame seq
/// k is the module's k-th served read), and fresh samples, not one cached block.
async fn frames_match_the_served_samples(module: &IoModule, acq: Acquisition) {
    let mut rx = acq.subscribe();
    let mut frames = Vec::new();
    while frames.len() < 300 {
        frames.push(next(&mut rx).await);
    }
    drop(acq);
    let served = module.served();
    assert!(frames.iter().all(Frame::is_valid), "beam on every PSD");
    let wall_2020_us = 1_577_836_800_000_000i64;
    for w in frames.windows(2) {
        assert_eq!(w[1].seq, w[0].seq + 1);
        assert!(w[1].at >= w[0].at && w[1].unix_us >= w[0].unix_us);
    }
    assert!(frames[0].unix_us > wall_2020_us);
    for f in &frames {
        let s = served
            .iter()
            .find(|s| s.index == f.seq)
            .expect("served read recorded");
        assert!(
            s.at <= f.at,
            "frame {} sampled before its reply arrived",
            f.seq
        );
        assert_frame_matches(f, s, HALF_COUNT_MM);
    }
    // PSD noise (1 µm) moves the spots.
    let x2: Vec<f64> = frames.iter().map(|f| f.spots[1].unwrap().x).collect();
    assert!(x2.iter().any(|&x| (x - x2[0]).abs() > 3.0 * HALF_COUNT_MM));
}

#[tokio::test(start_paused = true)]
async fn frames_equal_the_plant_sample_within_quantisation() {
    let module = twin(plant()).await;
    let link = link(module.local_addr());
    let acq = Acquisition::spawn(
        link.clone(),
        Arc::new(IoMap::generic().unwrap()),
        AcquireConfig {
            rate_hz: 0.0,
            ..AcquireConfig::default()
        },
    );
    frames_match_the_served_samples(&module, acq).await;
    let ls = link.stats();
    assert_eq!((ls.errors, ls.reconnects), (0, 0));
    // Its latency and rate are the real clock's (tests/realtime).
}

/// Unthrottled through the pipelined reader, four reads in flight: every frame is still the
/// module's sample for its own request, in order (the module answers in order).
#[tokio::test(start_paused = true)]
async fn pipelined_frames_equal_the_plant_sample_in_order() {
    let module = twin(plant()).await;
    let acq = Acquisition::spawn_pipelined(
        link_config(module.local_addr()),
        Arc::new(IoMap::generic().unwrap()),
        AcquireConfig {
            rate_hz: 0.0,
            pipeline: 4,
            ..AcquireConfig::default()
        },
    );
    let link = acq.link().clone();
    frames_match_the_served_samples(&module, acq).await;
    let ls = link.stats();
    assert_eq!((ls.errors, ls.reconnects), (0, 0));
    assert!(ls.ok >= 300 && ls.latency_p50.is_some());
}

/// Paced at 500 Hz through the paced reader: every frame is the module's sample for its
/// request, stamped when the reply arrived (the kernel's receive time), in order.
#[tokio::test(start_paused = true)]
async fn paced_frames_equal_the_plant_sample_and_carry_the_reply_time() {
    let module = twin(plant()).await;
    let acq = Acquisition::spawn_paced(
        link_config(module.local_addr()),
        Arc::new(IoMap::generic().unwrap()),
        AcquireConfig {
            rate_hz: 500.0,
            ..AcquireConfig::default()
        },
    );
    let mut rx = acq.subscribe();
    let mut frames = Vec::new();
    while frames.len() < 200 {
        let f = next(&mut rx).await;
        assert!(
            f.at <= axiscomp::util::clock::now(),
            "published after its reply arrived"
        );
        frames.push(f);
    }
    let served = module.served();
    for w in frames.windows(2) {
        assert_eq!(w[1].seq, w[0].seq + 1);
        assert!(w[1].at > w[0].at && w[1].unix_us >= w[0].unix_us);
    }
    for f in &frames {
        let s = served
            .iter()
            .find(|s| s.index == f.seq)
            .expect("served read recorded");
        assert!(
            s.at <= f.at,
            "frame {} stamped before the module sampled",
            f.seq
        );
        assert_frame_matches(f, s, HALF_COUNT_MM);
    }
    let ls = acq.link().stats();
    assert_eq!((ls.errors, ls.reconnects), (0, 0));
    assert!(ls.latency_p50.is_some());
}

#[tokio::test(start_paused = true)]
async fn module_outage_reconnects_and_frames_resume_within_2_s() {
    outage_reconnects_within_2_s(|addr, map, config| Acquisition::spawn(link(addr), map, config))
        .await;
}

#[tokio::test(start_paused = true)]
async fn module_outage_reconnects_and_paced_frames_resume_within_2_s() {
    outage_reconnects_within_2_s(|addr, map, config| {
        Acquisition::spawn_paced(link_config(addr), map, config)
    })
    .await;
}

#[tokio::test(start_paused = true)]
async fn module_outage_reconnects_and_pipelined_frames_resume_within_2_s() {
    outage_reconnects_within_2_s(|addr, map, config| {
        Acquisition::spawn_pipelined(link_config(addr), map, config)
    })
    .await;
}

async fn outage_reconnects_within_2_s(
    spawn: impl FnOnce(std::net::SocketAddr, Arc<IoMap>, AcquireConfig) -> Acquisition,
) {
    let module = twin(plant()).await;
    let acq = spawn(
        module.local_addr(),
        Arc::new(IoMap::generic().unwrap()),
        AcquireConfig {
            rate_hz: 200.0,
            ..AcquireConfig::default()
        },
    );
    let link = acq.link().clone();
    let mut rx = acq.subscribe();
    for _ in 0..20 {
        next(&mut rx).await;
    }
    module.server().stop().await;
    let stopped = axiscomp::util::clock::now();
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert!(!link.state().borrow().is_up(), "the link saw the outage");
    module.server().restart().await.expect("listen again");
    let restarted = axiscomp::util::clock::now();
    // Frames until the first one read after the restart; the largest gap between frames.
    let mut last: Option<Frame> = None;
    let mut max_gap = Duration::ZERO;
    loop {
        let f = match rx.recv().await {
            Ok(f) => f,
            Err(broadcast::error::RecvError::Lagged(_)) => continue,
            Err(e) => panic!("{e}"),
        };
        if let Some(l) = last {
            max_gap = max_gap.max(f.at.saturating_duration_since(l.at));
        }
        last = Some(f);
        if f.at > restarted {
            break;
        }
        assert!(
            axiscomp::util::clock::since(stopped) < Duration::from_secs(10),
            "frames never resumed"
        );
    }
    assert!(
        max_gap <= Duration::from_secs(2),
        "gap of {max_gap:?} across a 500 ms outage"
    );
    assert!(link.state().borrow().is_up());
    let st = acq.stats();
    assert!(st.read_errors >= 1, "{st:?}");
    assert!(link.stats().reconnects >= 1);
    // And the frames keep coming.
    for _ in 0..10 {
        assert!(next(&mut rx).await.is_valid());
    }
}

#[tokio::test(start_paused = true)]
async fn blocked_beam_makes_frames_invalid_until_unblocked() {
    let plant = plant();
    let module = twin(plant.clone()).await;
    let acq = Acquisition::spawn(
        link(module.local_addr()),
        Arc::new(IoMap::generic().unwrap()),
        AcquireConfig {
            rate_hz: 500.0,
            ..AcquireConfig::default()
        },
    );
    let mut rx = acq.subscribe();
    assert!(next(&mut rx).await.is_valid());
    plant.set_blocked(1, true);
    let blocked_at = axiscomp::util::clock::now() + Duration::from_millis(50);
    let mut seen = 0;
    while seen < 20 {
        let f = next(&mut rx).await;
        if f.at < blocked_at {
            continue;
        }
        seen += 1;
        assert!(!f.is_valid() && f.readings().is_none());
        assert_eq!(f.spots[1], None);
        assert!(f.spots[0].is_some() && f.spots[2].is_some());
        assert!(f.sums[1] < 0.5 && f.sums[0] > 4.0, "{:?}", f.sums);
    }
    assert!(acq.stats().invalid_frames >= 20);
    plant.set_blocked(1, false);
    let clear_at = axiscomp::util::clock::now() + Duration::from_millis(50);
    loop {
        let f = next(&mut rx).await;
        if f.at > clear_at {
            assert!(f.is_valid() && f.readings().is_some());
            break;
        }
    }
}

#[tokio::test(start_paused = true)]
async fn server_answers_bad_requests_with_exceptions_and_keeps_the_connection() {
    let module = twin(plant()).await;
    let mut s = TcpStream::connect(module.local_addr()).await.unwrap();
    let cases: [(&[u8], u8, &[u8]); 8] = [
        (&[0x04, 0, 0, 0, 0], 1, &[0x84, 0x03]),         // quantity 0
        (&[0x04, 0, 0, 0, 126], 1, &[0x84, 0x03]),       // quantity 126
        (&[0x04, 0, 5, 0, 9], 1, &[0x84, 0x02]),         // past the block
        (&[0x04, 0xFF, 0xF0, 0, 100], 1, &[0x84, 0x02]), // past 65535
        (&[0x03, 0, 0, 0, 9], 1, &[0x83, 0x02]),         // the other register table
        (&[0x01, 0, 0, 0, 8], 1, &[0x81, 0x01]),         // read coils: unsupported
        (&[0x07], 1, &[0x87, 0x01]),                     // read exception status: unsupported
        (&[0x04, 0, 0, 0, 9], 9, &[0x84, 0x0B]),         // another unit id
    ];
    for (tid, (pdu, unit, want)) in cases.iter().enumerate() {
        let got = raw_request(&mut s, tid as u16 + 1, *unit, pdu).await;
        assert_eq!(got, *want, "request {pdu:02X?}");
    }
    // Same connection, a good read: 9 registers.
    let ok = raw_request(&mut s, 100, 1, &[0x04, 0, 0, 0, 9]).await;
    assert_eq!((ok[0], ok[1], ok.len()), (0x04, 18, 20));
    let st = module.server().stats();
    assert_eq!((st.accepted, st.exceptions), (1, 8));
}

#[tokio::test(start_paused = true)]
async fn twin_serves_the_product_maps_in_both_modes() {
    for file in ["wago-750-352-750-456.toml", "beckhoff-bk9000-kl3404.toml"] {
        let map = IoMap::load(&maps_dir().join(file)).unwrap();
        let plant = plant();
        plant.set_blocked(2, true);
        let module = IoModule::start(plant.clone(), map.clone(), IoModuleConfig::default())
            .await
            .unwrap();
        let acq = Acquisition::spawn(
            link(module.local_addr()),
            Arc::new(map),
            AcquireConfig {
                rate_hz: 0.0,
                ..AcquireConfig::default()
            },
        );
        let mut rx = acq.subscribe();
        let mut frames = Vec::new();
        while frames.len() < 50 {
            frames.push(next(&mut rx).await);
        }
        drop(acq);
        let served = module.served();
        for f in &frames {
            let s = served.iter().find(|s| s.index == f.seq).unwrap();
            // WAGO: 8 counts lost to the status bits (2.4 µm at 1 mm/V); Beckhoff electrodes:
            // 0.3 mV counts on ~1.25 V electrodes over a 9 mm PSD.
            assert_frame_matches(f, s, 5e-3);
            assert_eq!(f.spots[2], None, "{file}: PSD3 blocked");
        }
    }
}

// ---------- independent peers (run by tests/interop/modbus.sh) ----------

/// The JSON line `tests/interop/pymodbus_io.py` prints before serving.
#[derive(serde::Deserialize)]
struct PyExpect {
    registers: Vec<u16>,
    spots: Vec<Option<[f64; 2]>>,
    sums: Vec<f64>,
}

/// Kill the child we started when the test ends, pass or fail.
struct Reap(std::process::Child);
impl Drop for Reap {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs pymodbus/mbpoll: run by .ci/run"]
async fn interop_pymodbus_io_frames() {
    use std::io::BufRead;
    use std::process::{Command, Stdio};
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let port = free_port();
    let mut child = Reap(
        Command::new("python3")
            .arg(root.join("tests/interop/pymodbus_io.py"))
            .args(["--port", &port.to_string(), "--map"])
            .arg(root.join("plc-maps/io/generic.toml"))
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("run python3 tests/interop/pymodbus_io.py"),
    );
    let stdout = child.0.stdout.take().expect("stdout");
    let line = tokio::task::spawn_blocking(move || {
        let mut line = String::new();
        std::io::BufReader::new(stdout)
            .read_line(&mut line)
            .map(|_| line)
    })
    .await
    .unwrap()
    .expect("the script's JSON line");
    let want: PyExpect = serde_json::from_str(&line).expect("JSON from pymodbus_io.py");
    let addr = format!("127.0.0.1:{port}").parse().unwrap();
    // The server may still be starting: the link retries until it listens.
    let link = Link::spawn(LinkConfig {
        backoff_max: Duration::from_millis(200),
        ..LinkConfig::new(addr)
    });
    assert!(
        link.wait_connected(Duration::from_secs(10)).await,
        "pymodbus up"
    );
    let map = Arc::new(IoMap::generic().unwrap());
    let raw = link
        .read(map.kind, map.unit_id, map.block)
        .await
        .expect("raw block");
    assert_eq!(raw, want.registers, "registers as pymodbus holds them");
    // Through the link task, then the service's paths: the paced reader at a fixed rate, the
    // pipelined reader unthrottled at its default depth, one read at a time (pymodbus 3.16
    // drops a request queued behind another now and then: 2 timeouts in 6111 reads at depth 4).
    let cfg = LinkConfig {
        backoff_max: Duration::from_millis(200),
        ..LinkConfig::new(addr)
    };
    let acquisitions = [
        Acquisition::spawn(link, map.clone(), AcquireConfig::default()),
        Acquisition::spawn_paced(
            cfg.clone(),
            map.clone(),
            AcquireConfig {
                rate_hz: 500.0,
                ..AcquireConfig::default()
            },
        ),
        Acquisition::spawn_pipelined(
            cfg,
            map,
            AcquireConfig {
                rate_hz: 0.0,
                ..AcquireConfig::default()
            },
        ),
    ];
    for (way, acq) in ["link task", "paced", "pipelined"].iter().zip(acquisitions) {
        let mut rx = acq.subscribe();
        for _ in 0..200 {
            let f = next(&mut rx).await;
            for k in 0..3 {
                match (f.spots[k], want.spots[k]) {
                    (Some(Spot { x, y }), Some([wx, wy])) => {
                        assert!(
                            (x - wx).abs() < 1e-9 && (y - wy).abs() < 1e-9,
                            "PSD{}",
                            k + 1
                        );
                    }
                    (None, None) => {}
                    (a, b) => panic!("PSD{}: {a:?} vs pymodbus {b:?}", k + 1),
                }
                assert!((f.sums[k] - want.sums[k]).abs() < 1e-9);
            }
            assert!(!f.is_valid(), "PSD3 is blocked in the script's registers");
        }
        let st = acq.link().stats();
        assert_eq!(st.errors, 0, "{way}: {st:?}, {:?}", acq.stats());
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs pymodbus/mbpoll: run by .ci/run"]
async fn interop_mbpoll_reads_the_twin() {
    let sample = PsdSample {
        spots: [
            Some(Spot { x: 1.0, y: -2.0 }),
            Some(Spot { x: -0.5, y: 4.25 }),
            None,
        ],
        sums: [5.0, 3.0, 0.02],
    };
    let module = IoModule::start(
        Arc::new(FixedSource::new(sample)),
        IoMap::generic().unwrap(),
        IoModuleConfig::default(),
    )
    .await
    .unwrap();
    let port = module.local_addr().port().to_string();
    let out = tokio::task::spawn_blocking(move || {
        std::process::Command::new("mbpoll")
            .args([
                "-m", "tcp", "-a", "1", "-0", "-r", "0", "-c", "9", "-t", "3", "-1",
            ])
            .args(["-p", &port, "127.0.0.1"])
            .output()
    })
    .await
    .unwrap()
    .expect("run mbpoll");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "mbpoll failed: {text}");
    // Lines "[k]: \t<unsigned> (<signed>)"; take the unsigned value.
    let mut regs = vec![None; 9];
    for line in text.lines() {
        if let Some((k, v)) = line
            .trim()
            .strip_prefix('[')
            .and_then(|l| l.split_once("]:"))
        {
            let k: usize = k.parse().unwrap();
            let v: u16 = v.split_whitespace().next().unwrap().parse().unwrap();
            regs[k] = Some(v);
        }
    }
    let regs: Vec<u16> = regs.into_iter().map(|r| r.expect("9 registers")).collect();
    // Hand-computed at 32767 counts per 10 V (1 mm/V): 1 mm = 3276.7 → 3277; -2 mm = -6553
    // (0xE667); 5 V = 16383.5 → 16384; -0.5 → -1638 (0xF99A); 4.25 → 13926; 3 V → 9830;
    // PSD3 blocked: centred, 0.02 V = 65.5 → 66.
    assert_eq!(
        regs,
        [3277, 0xE667, 16384, 0xF99A, 13926, 9830, 0, 0, 66],
        "{text}"
    );
}
