//! CAN transports over real sockets on loopback: cannelloni UDP endpoints, python-can
//! multicast endpoints (and python-can itself, when installed), and the fault injector.

use crate::helpers::{unused_udp_port, within};
use axiscomp::can::cannelloni::{Cannelloni, MAX_DATAGRAM};
use axiscomp::can::fault::{FaultStats, Faults, Faulty, RX_STREAM};
use axiscomp::can::memory::MemoryBus;
use axiscomp::can::pycan::{self, PyCanMulticast};
use axiscomp::can::{CanError, CanFrame, CanTransport};
use std::io::{BufRead, BufReader};
use std::net::{Ipv4Addr, UdpSocket};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;
use tokio::time::Instant;

const LO: Ipv4Addr = Ipv4Addr::LOCALHOST;

fn std_frame(id: u16, data: &[u8]) -> CanFrame {
    CanFrame::new(id, data).unwrap()
}

/// A mix of every kind of classic frame.
fn assorted() -> Vec<CanFrame> {
    vec![
        std_frame(0x181, &[1, 2, 3, 4, 5, 6, 7, 8]),
        CanFrame::new_extended(0x1ABC_DEF0, &[0xFF]).unwrap(),
        CanFrame::remote(0x701, false, 1).unwrap(),
        CanFrame::remote(0x0001_2345, true, 8).unwrap(),
        std_frame(0x000, &[]),
        std_frame(0x7FF, &[0xDE, 0xAD, 0xBE, 0xEF]),
    ]
}

async fn recv_n(t: &impl CanTransport, n: usize) -> Vec<CanFrame> {
    let mut v = Vec::with_capacity(n);
    for _ in 0..n {
        v.push(within("recv", t.recv()).await.unwrap());
    }
    v
}

/// Two cannelloni endpoints on loopback, each the other's remote.
fn cannelloni_pair() -> (Cannelloni, Cannelloni) {
    let sa = UdpSocket::bind((LO, 0)).unwrap();
    let sb = UdpSocket::bind((LO, 0)).unwrap();
    let (aa, ab) = (sa.local_addr().unwrap(), sb.local_addr().unwrap());
    (
        Cannelloni::from_std(sa, ab).unwrap(),
        Cannelloni::from_std(sb, aa).unwrap(),
    )
}

// ---------------------------------------------------------------- cannelloni

#[tokio::test]
async fn cannelloni_endpoints_exchange_every_kind_of_frame() {
    let (a, b) = cannelloni_pair();
    for f in assorted() {
        a.send(&f).await.unwrap();
    }
    assert_eq!(recv_n(&b, 6).await, assorted());
    let back: Vec<CanFrame> = assorted().into_iter().rev().collect();
    for f in &back {
        b.send(f).await.unwrap();
    }
    assert_eq!(recv_n(&a, 6).await, back);
    assert_eq!(a.stats().frames_sent, 6);
    assert_eq!(b.stats().frames_received, 6);
}

#[tokio::test]
async fn cannelloni_datagrams_on_the_wire_follow_the_spec() {
    let peer = tokio::net::UdpSocket::bind((LO, 0)).await.unwrap();
    let a = Cannelloni::open((LO, 0).into(), peer.local_addr().unwrap())
        .await
        .unwrap();
    let mut buf = [0u8; 2048];
    a.send(&std_frame(0x123, &[0xDE, 0xAD])).await.unwrap();
    let (n, from) = within("datagram 0", peer.recv_from(&mut buf))
        .await
        .unwrap();
    assert_eq!(from, a.local_addr().unwrap());
    // version 2, DATA, seq 0, count 1 | can_id 0x123 | len 2 | data
    assert_eq!(&buf[..n], &[2, 0, 0, 0, 1, 0, 0, 0x01, 0x23, 2, 0xDE, 0xAD]);
    a.send(&CanFrame::remote(0x1234_5678, true, 3).unwrap())
        .await
        .unwrap();
    let (n, _) = within("datagram 1", peer.recv_from(&mut buf))
        .await
        .unwrap();
    // seq 1 | 0x12345678 | EFF | RTR = 0xD2345678 | DLC 3, no data
    assert_eq!(&buf[..n], &[2, 0, 1, 0, 1, 0xD2, 0x34, 0x56, 0x78, 3]);

    // And a hand-made cannelloni datagram (seq 9, two frames) comes in as two frames.
    #[rustfmt::skip]
    let dgram = [
        2, 0, 9, 0, 2,               // v2, DATA, seq 9, count 2
        0x00, 0x00, 0x07, 0x05, 1, 0x05,  // 0x705 len 1: heartbeat, operational
        0x80, 0x00, 0x00, 0x80, 0,        // extended 0x80, len 0
    ];
    peer.send_to(&dgram, a.local_addr().unwrap()).await.unwrap();
    assert_eq!(
        recv_n(&a, 2).await,
        vec![
            std_frame(0x705, &[5]),
            CanFrame::new_extended(0x80, &[]).unwrap()
        ]
    );
}

#[tokio::test]
async fn cannelloni_bursts_arrive_whole_and_in_order() {
    let (a, b) = cannelloni_pair();
    let burst: Vec<CanFrame> = (0..500u32)
        .map(|i| CanFrame::new_extended(i * 7, &i.to_be_bytes()).unwrap())
        .collect();
    for f in &burst {
        a.send(f).await.unwrap();
    }
    assert_eq!(recv_n(&b, burst.len()).await, burst);
    assert_eq!(a.stats().frames_sent, 500);

    // A batch is packed for certain: 200 eight-byte frames, 13 bytes each after a 5-byte
    // header, 91 to a datagram of at most MAX_DATAGRAM bytes -> 3 datagrams.
    let before = b.stats().datagrams_received;
    let batch: Vec<CanFrame> = (0..200u16).map(|i| std_frame(i, &[i as u8; 8])).collect();
    a.send_batch(&batch).await.unwrap();
    assert_eq!(recv_n(&b, batch.len()).await, batch);
    let per = (MAX_DATAGRAM - 5) / 13;
    assert_eq!(
        b.stats().datagrams_received - before,
        batch.len().div_ceil(per) as u64
    );
    assert_eq!(b.stats().seq_gaps, 0);
}

#[tokio::test]
async fn cannelloni_survives_malformed_and_foreign_datagrams() {
    let (a, b) = cannelloni_pair();
    let b_addr = b.local_addr().unwrap();
    let raw = UdpSocket::bind((LO, 0)).unwrap();
    // version 7
    raw.send_to(&[7, 0, 0, 0, 1, 0, 0, 1, 0x23, 0], b_addr)
        .unwrap();
    match within("malformed", b.recv()).await {
        Err(e @ CanError::Malformed(_)) => {
            assert!(e.to_string().contains("version 7"), "{e}");
            assert!(e.is_transient());
        }
        other => panic!("expected Malformed, got {other:?}"),
    }
    // count 2 with one record
    raw.send_to(&[2, 0, 0, 0, 2, 0, 0, 1, 0x23, 0], b_addr)
        .unwrap();
    match within("truncated", b.recv()).await {
        Err(CanError::Malformed(m)) => assert!(m.contains("record 1 of 2"), "{m}"),
        other => panic!("expected Malformed, got {other:?}"),
    }
    // a valid datagram from another address (127.0.0.2) is not the remote's: ignored
    let stranger = UdpSocket::bind(("127.0.0.2", 0)).unwrap();
    stranger
        .send_to(&[2, 0, 0, 0, 1, 0, 0, 0x06, 0x66, 0], b_addr)
        .unwrap();
    // the link still works, and the stranger's frame 0x666 never shows up
    a.send(&std_frame(0x181, &[42])).await.unwrap();
    assert_eq!(
        within("after", b.recv()).await.unwrap(),
        std_frame(0x181, &[42])
    );
    let s = b.stats();
    assert_eq!((s.malformed, s.foreign, s.frames_received), (2, 1, 1));
}

// ---------------------------------------------------------------- python-can multicast

#[tokio::test]
async fn pycan_endpoints_hear_each_other_but_not_themselves() {
    let port = unused_udp_port();
    let a = PyCanMulticast::open(pycan::DEFAULT_GROUP, port, LO)
        .await
        .unwrap();
    let b = PyCanMulticast::open(pycan::DEFAULT_GROUP, port, LO)
        .await
        .unwrap();
    for f in assorted() {
        a.send(&f).await.unwrap();
    }
    assert_eq!(recv_n(&b, 6).await, assorted());
    // a's own six frames reached a's socket before b could answer: if a heard itself, its
    // first frame would be one of them, not b's answer.
    let answer = std_frame(0x0FF, &[9, 9]);
    b.send(&answer).await.unwrap();
    assert_eq!(within("answer", a.recv()).await.unwrap(), answer);
    // and a third node hears both
    let c = PyCanMulticast::open(pycan::DEFAULT_GROUP, port, LO)
        .await
        .unwrap();
    a.send(&std_frame(1, &[1])).await.unwrap();
    b.send(&std_frame(2, &[2])).await.unwrap();
    assert_eq!(
        recv_n(&c, 2).await,
        vec![std_frame(1, &[1]), std_frame(2, &[2])]
    );
}

#[tokio::test]
async fn pycan_malformed_datagram_is_reported_and_skipped() {
    let port = unused_udp_port();
    let a = PyCanMulticast::open(pycan::DEFAULT_GROUP, port, LO)
        .await
        .unwrap();
    let b = PyCanMulticast::open(pycan::DEFAULT_GROUP, port, LO)
        .await
        .unwrap();
    let raw = UdpSocket::bind((LO, 0)).unwrap();
    raw.set_multicast_loop_v4(true).unwrap();
    // msgpack {"arbitration_id": "x"}: a map, but the id is a str
    let bad = [&[0x81, 0xae][..], b"arbitration_id", &[0xa1, b'x']].concat();
    raw.send_to(&bad, (pycan::DEFAULT_GROUP, port)).unwrap();
    match within("malformed", b.recv()).await {
        Err(CanError::Malformed(m)) => assert!(m.contains("`arbitration_id` is str"), "{m}"),
        other => panic!("expected Malformed, got {other:?}"),
    }
    a.send(&std_frame(0x222, &[2])).await.unwrap();
    assert_eq!(
        within("after", b.recv()).await.unwrap(),
        std_frame(0x222, &[2])
    );
}

/// Parse the peer's candump-style notation (`123#0102`, `1ABCDEF0#FF`, `701#R1`).
fn parse_notation(s: &str) -> CanFrame {
    let (id, rest) = s.split_once('#').unwrap();
    let extended = id.len() == 8;
    let id = u32::from_str_radix(id, 16).unwrap();
    if let Some(len) = rest.strip_prefix('R') {
        return CanFrame::remote(id, extended, len.parse().unwrap()).unwrap();
    }
    let data: Vec<u8> = (0..rest.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&rest[i..i + 2], 16).unwrap())
        .collect();
    CanFrame::with_id(id, extended, &data).unwrap()
}

fn python() -> String {
    std::env::var("PYTHON").unwrap_or_else(|_| "python3".into())
}

/// The python-can peer, started and READY.
struct Peer {
    child: std::process::Child,
    lines: std::sync::mpsc::Receiver<String>,
}

impl Peer {
    fn start(port: u16, mode: &[&str]) -> Peer {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop/pycan_peer.py");
        let mut child = Command::new(python())
            .arg(script)
            .args(["--port", &port.to_string(), "--iface", "127.0.0.1"])
            .args(mode)
            .stdout(Stdio::piped())
            .spawn()
            .expect("start python3 tests/interop/pycan_peer.py");
        let out = BufReader::new(child.stdout.take().unwrap());
        let (tx, lines) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for l in out.lines().map_while(Result::ok) {
                if tx.send(l).is_err() {
                    break;
                }
            }
        });
        let p = Peer { child, lines };
        assert_eq!(p.line(), "READY");
        p
    }

    fn line(&self) -> String {
        self.lines
            .recv_timeout(crate::helpers::CAN_WAIT)
            .expect("a line from the python-can peer")
    }

    fn finish(mut self) {
        let status = self.child.wait().unwrap();
        assert!(status.success(), "python-can peer: {status}");
    }
}

#[tokio::test]
#[ignore = "needs python-can: run by .ci/run"]
async fn python_can_peer_echoes_our_frames_byte_for_byte() {
    let port = unused_udp_port();
    let us = PyCanMulticast::open(pycan::DEFAULT_GROUP, port, LO)
        .await
        .unwrap();
    // every kind of frame, with room for the answer's identifier + 1
    let mut frames = assorted();
    frames.retain(|f| f.id() != 0x7FF);
    frames.push(std_frame(0x7FE, &[0xDE, 0xAD, 0xBE, 0xEF]));
    frames.push(CanFrame::new_extended(0x1FFF_FFFE, &[0; 8]).unwrap());
    let peer = Peer::start(port, &["echo", &frames.len().to_string()]);
    for f in &frames {
        us.send(f).await.unwrap();
        // python-can decoded exactly what we sent...
        assert_eq!(parse_notation(peer.line().strip_prefix("RX ").unwrap()), *f);
        // ...and its encoding of the answer decodes to exactly the answer.
        let want = if f.is_remote() {
            CanFrame::remote(f.id() + 1, f.is_extended(), f.len() as u8).unwrap()
        } else {
            CanFrame::with_id(f.id() + 1, f.is_extended(), f.data()).unwrap()
        };
        assert_eq!(within("echo", us.recv()).await.unwrap(), want);
    }
    peer.finish();
}

#[tokio::test]
#[ignore = "needs python-can: run by .ci/run"]
async fn python_can_peer_script_arrives_byte_for_byte() {
    let port = unused_udp_port();
    let us = PyCanMulticast::open(pycan::DEFAULT_GROUP, port, LO)
        .await
        .unwrap();
    let peer = Peer::start(port, &["script"]);
    // pycan_peer.py's SCRIPT, written out independently here
    let want = vec![
        std_frame(0x181, &[1, 2, 3, 4, 5, 6, 7, 8]),
        CanFrame::new_extended(0x1ABC_DEF0, &[0xFF]).unwrap(),
        CanFrame::remote(0x701, false, 1).unwrap(),
        std_frame(0x000, &[]),
        CanFrame::remote(0x12345, true, 8).unwrap(),
        std_frame(0x7FF, &[0xDE, 0xAD, 0xBE, 0xEF]),
    ];
    assert_eq!(recv_n(&us, want.len()).await, want);
    peer.finish();
}

// ---------------------------------------------------------------- fault injection

#[tokio::test]
async fn faulty_drops_every_nth_frame_sent() {
    let bus = MemoryBus::default();
    let a = Faulty::with_faults(
        bus.port(),
        1,
        Faults {
            drop_every: 3,
            ..Faults::NONE
        },
        Faults::NONE,
    );
    let b = bus.port();
    for i in 1..=10u16 {
        a.send(&std_frame(i, &[])).await.unwrap();
    }
    let ids: Vec<u32> = recv_n(&b, 7).await.iter().map(|f| f.id()).collect();
    assert_eq!(ids, [1, 2, 4, 5, 7, 8, 10]);
    let s = a.control().stats();
    assert_eq!((s.tx_passed, s.tx_dropped), (7, 3));
}

#[tokio::test]
async fn faulty_random_drops_are_the_seeded_ones() {
    let bus = MemoryBus::default();
    let a = bus.port();
    let seed = 2024;
    let p = 0.3;
    let b = Faulty::with_faults(
        bus.port(),
        seed,
        Faults::NONE,
        Faults {
            drop_probability: p,
            ..Faults::NONE
        },
    );
    let n = 420u16;
    for i in 0..n {
        a.send(&std_frame(i, &[])).await.unwrap();
    }
    // Independent computation of the survivors from the documented stream (xorshift64*,
    // as can::fault documents it).
    let mut x = (seed ^ (RX_STREAM << 32))
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .max(1);
    let mut unit = || {
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        (x.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    };
    let want: Vec<u32> = (0..n as u32).filter(|_| unit() >= p).collect();
    assert!((250..340).contains(&want.len()), "{}", want.len());
    let got: Vec<u32> = recv_n(&b, want.len())
        .await
        .iter()
        .map(|f| f.id())
        .collect();
    assert_eq!(got, want);
    // frames up to the last survivor have been read: each one passed or was dropped
    let read = *want.last().unwrap() as u64 + 1;
    let s = b.control().stats();
    assert_eq!(s.rx_passed, want.len() as u64);
    assert_eq!(s.rx_dropped, read - want.len() as u64);
}

/// Keep `b` receiving until its counters satisfy `done`; a frame getting through fails.
async fn receive_nothing_until<T: CanTransport>(b: &Faulty<T>, done: impl Fn(FaultStats) -> bool) {
    let control = b.control();
    within("frames to be dropped", async {
        tokio::select! {
            r = b.recv() => panic!("a frame got through: {r:?}"),
            _ = async {
                while !done(control.stats()) {
                    tokio::time::sleep(Duration::from_millis(1)).await;
                }
            } => {}
        }
    })
    .await
}

#[tokio::test]
async fn faulty_link_cut_and_restore() {
    let bus = MemoryBus::default();
    let a = bus.port();
    let b = Faulty::new(bus.port(), 5);
    let link = b.control();
    link.cut();
    assert!(!link.is_up());
    a.send(&std_frame(0x100, &[1])).await.unwrap();
    // b's receive discards what arrives while the link is down
    receive_nothing_until(&b, |s| s.rx_dropped == 1).await;
    b.send(&std_frame(0x200, &[2])).await.unwrap(); // lost on the cut link
    link.restore();
    b.send(&std_frame(0x201, &[3])).await.unwrap();
    a.send(&std_frame(0x101, &[4])).await.unwrap();
    assert_eq!(within("a", a.recv()).await.unwrap(), std_frame(0x201, &[3]));
    assert_eq!(within("b", b.recv()).await.unwrap(), std_frame(0x101, &[4]));
    let s = link.stats();
    assert_eq!(
        (s.tx_passed, s.tx_dropped, s.rx_passed, s.rx_dropped),
        (1, 1, 1, 1)
    );
}

#[tokio::test]
async fn faulty_delays_received_frames_in_order_and_cancel_safely() {
    let bus = MemoryBus::default();
    let a = bus.port();
    let delay = Duration::from_millis(200);
    let b = Faulty::with_faults(
        bus.port(),
        0,
        Faults::NONE,
        Faults {
            delay,
            ..Faults::NONE
        },
    );
    let t0 = Instant::now();
    a.send(&std_frame(1, &[1])).await.unwrap();
    a.send(&std_frame(2, &[2])).await.unwrap();
    // Both frames are read (and queued) during this receive, which is cancelled before
    // they are due: none may be lost.
    assert!(
        tokio::time::timeout(Duration::from_millis(20), b.recv())
            .await
            .is_err()
    );
    assert_eq!(within("1", b.recv()).await.unwrap(), std_frame(1, &[1]));
    assert!(t0.elapsed() >= delay, "returned before the delay");
    assert_eq!(within("2", b.recv()).await.unwrap(), std_frame(2, &[2]));
}

#[tokio::test]
async fn faulty_delays_sent_frames_in_order() {
    let bus = MemoryBus::default();
    let delay = Duration::from_millis(100);
    let a = Faulty::with_faults(
        bus.port(),
        0,
        Faults {
            delay,
            ..Faults::NONE
        },
        Faults::NONE,
    );
    let b = bus.port();
    let t0 = Instant::now();
    for i in 0..5u16 {
        a.send(&std_frame(i, &[i as u8])).await.unwrap();
    }
    let first = within("first", b.recv()).await.unwrap();
    assert!(t0.elapsed() >= delay, "handed on before the delay");
    let mut got = vec![first];
    got.extend(recv_n(&b, 4).await);
    let want: Vec<CanFrame> = (0..5u16).map(|i| std_frame(i, &[i as u8])).collect();
    assert_eq!(got, want);
}

#[tokio::test]
async fn faulty_wraps_a_cannelloni_link() {
    let (a, b) = cannelloni_pair();
    let b = Faulty::new(b, 9);
    let link = b.control();
    a.send(&std_frame(0x701, &[5])).await.unwrap();
    assert_eq!(
        within("up", b.recv()).await.unwrap(),
        std_frame(0x701, &[5])
    );
    // heartbeat loss: every frame from the drive side is dropped while set
    link.set_rx(Faults {
        drop_probability: 1.0,
        ..Faults::NONE
    });
    a.send(&std_frame(0x701, &[5])).await.unwrap();
    receive_nothing_until(&b, |s| s.rx_dropped == 1).await;
    link.set_rx(Faults::NONE);
    a.send(&std_frame(0x702, &[5])).await.unwrap();
    assert_eq!(
        within("restored", b.recv()).await.unwrap(),
        std_frame(0x702, &[5])
    );
    assert_eq!(b.inner().stats().frames_received, 3);
}
