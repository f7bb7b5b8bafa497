//! SocketCAN against the real kernel CAN stack: `vcan0` inside the vcan VM
//! (`bash tests/interop/vcan.sh`), with can-utils (`cansend`, `candump`) as the independent
//! peer. The tests share one bus: run them one at a time (`--test-threads=1`).

use crate::helpers::{CAN_WAIT, within};
use axiscomp::can::socketcan::SocketCan;
use axiscomp::can::{CanFrame, CanTransport};
use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

const IFACE: &str = "vcan0";

fn assorted() -> Vec<CanFrame> {
    vec![
        CanFrame::new(0x181, &[1, 2, 3, 4, 5, 6, 7, 8]).unwrap(),
        CanFrame::new_extended(0x1ABC_DEF0, &[0xFF]).unwrap(),
        CanFrame::remote(0x701, false, 1).unwrap(),
        CanFrame::remote(0x0001_2345, true, 8).unwrap(),
        CanFrame::new(0x000, &[]).unwrap(),
        CanFrame::new(0x7FF, &[0xDE, 0xAD, 0xBE, 0xEF]).unwrap(),
    ]
}

async fn recv_n(t: &impl CanTransport, n: usize) -> Vec<CanFrame> {
    let mut v = Vec::with_capacity(n);
    for _ in 0..n {
        v.push(within("recv on vcan0", t.recv()).await.unwrap());
    }
    v
}

/// Parse can-utils' notation: `123#0102`, `12345678#FF`, `701#R`, `701#R1`.
fn parse_cansend(s: &str) -> CanFrame {
    let (id, rest) = s.split_once('#').unwrap();
    let extended = id.len() == 8;
    let id = u32::from_str_radix(id, 16).unwrap();
    if let Some(len) = rest.strip_prefix('R') {
        let len = if len.is_empty() {
            0
        } else {
            len.parse().unwrap()
        };
        return CanFrame::remote(id, extended, len).unwrap();
    }
    let data: Vec<u8> = (0..rest.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&rest[i..i + 2], 16).unwrap())
        .collect();
    CanFrame::with_id(id, extended, &data).unwrap()
}

#[tokio::test]
#[ignore = "needs vcan0: run in the vcan VM by tests/interop/vcan.sh"]
async fn socketcan_endpoints_exchange_every_kind_of_frame() {
    let a = SocketCan::open(IFACE).unwrap();
    let b = SocketCan::open(IFACE).unwrap();
    for f in assorted() {
        a.send(&f).await.unwrap();
    }
    assert_eq!(recv_n(&b, 6).await, assorted());
    let back: Vec<CanFrame> = assorted().into_iter().rev().collect();
    for f in &back {
        b.send(f).await.unwrap();
    }
    assert_eq!(recv_n(&a, 6).await, back);
}

#[tokio::test]
#[ignore = "needs vcan0: run in the vcan VM by tests/interop/vcan.sh"]
async fn socketcan_own_frames_are_not_echoed() {
    let a = SocketCan::open(IFACE).unwrap();
    let b = SocketCan::open(IFACE).unwrap();
    let c = SocketCan::open(IFACE).unwrap();
    let x = CanFrame::new(0x111, &[1]).unwrap();
    let y = CanFrame::new(0x222, &[2]).unwrap();
    a.send(&x).await.unwrap();
    assert_eq!(within("b hears a", b.recv()).await.unwrap(), x);
    b.send(&y).await.unwrap();
    // x was looped back to every other socket before b could answer; had a received its
    // own frame, x would come first here.
    assert_eq!(within("a hears b", a.recv()).await.unwrap(), y);
    // other sockets on the host hear both (kernel loopback on)
    assert_eq!(recv_n(&c, 2).await, vec![x, y]);
}

/// candump, running, with its output lines on a channel.
struct Candump {
    child: Child,
    lines: mpsc::Receiver<String>,
}

impl Candump {
    fn start() -> Candump {
        let mut child = Command::new("candump")
            .args(["-L", IFACE])
            .stdout(Stdio::piped())
            .spawn()
            .expect("spawn candump (in the vcan VM's PATH)");
        let out = BufReader::new(child.stdout.take().unwrap());
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for l in out.lines().map_while(Result::ok) {
                if tx.send(l).is_err() {
                    break;
                }
            }
        });
        Candump { child, lines }
    }

    /// The frame text of the next line (`(1700000000.000000) vcan0 123#0102` -> `123#0102`).
    fn next(&self, wait: Duration) -> Option<String> {
        let l = self.lines.recv_timeout(wait).ok()?;
        let mut parts = l.split_whitespace();
        let (_ts, iface, frame) = (parts.next()?, parts.next()?, parts.next()?);
        assert_eq!(iface, IFACE, "{l}");
        Some(frame.to_owned())
    }
}

impl Drop for Candump {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[tokio::test]
#[ignore = "needs vcan0: run in the vcan VM by tests/interop/vcan.sh"]
async fn socketcan_frames_reach_candump_byte_for_byte() {
    let a = SocketCan::open(IFACE).unwrap();
    let dump = Candump::start();
    // Handshake: candump says nothing when it is ready, so send a marker frame until it
    // prints one (the pause only paces the retries; nothing is asserted about time).
    let marker = CanFrame::new(0x7FE, &[0xAA]).unwrap();
    let mut ready = false;
    for _ in 0..(CAN_WAIT.as_secs() * 4) {
        a.send(&marker).await.unwrap();
        if dump.next(Duration::from_millis(250)).is_some() {
            ready = true;
            break;
        }
    }
    assert!(ready, "candump printed nothing");
    for f in assorted() {
        a.send(&f).await.unwrap();
    }
    let mut seen = Vec::new();
    while seen.len() < assorted().len() {
        let text = dump.next(CAN_WAIT).expect("a candump line");
        if text == "7FE#AA" {
            continue; // a late marker
        }
        seen.push(text);
    }
    for (text, f) in seen.iter().zip(assorted()) {
        assert_eq!(parse_cansend(text), f, "candump printed {text}");
        if !f.is_remote() {
            // our Debug is candump's notation: the text itself must match
            assert_eq!(text, &format!("{f:?}"));
        }
    }
}

fn cansend(arg: &str) {
    let st = Command::new("cansend")
        .args([IFACE, arg])
        .status()
        .expect("spawn cansend (in the vcan VM's PATH)");
    assert!(st.success(), "cansend {arg}: {st}");
}

#[tokio::test]
#[ignore = "needs vcan0: run in the vcan VM by tests/interop/vcan.sh"]
async fn socketcan_receives_cansend_frames_and_never_fd_frames() {
    let b = SocketCan::open(IFACE).unwrap();
    let sent = [
        "123#DEADBEEF",
        "12345678#01020304050607",
        "321#R3",
        "1FFFFFFF#R",
        "000#",
    ];
    for s in sent {
        cansend(s);
    }
    let want: Vec<CanFrame> = sent.iter().map(|s| parse_cansend(s)).collect();
    assert_eq!(recv_n(&b, want.len()).await, want);
    // A CAN FD frame (`##<flags><data>`) is not delivered to a classic socket; the classic
    // frame after it is.
    cansend("456##1AABBCCDDEEFF00112233");
    cansend("457#01");
    assert_eq!(
        within("after FD", b.recv()).await.unwrap(),
        CanFrame::new(0x457, &[1]).unwrap()
    );
}
