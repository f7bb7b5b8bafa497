//! The Modbus link against our server scaffolding on loopback: timeouts and the off-by-one
//! reply, exceptions, writes, the allow-list, link state and shutdown.

use axiscomp::modbus::server::{MemoryBank, ServerConfig, ServerHandle};
use axiscomp::modbus::{Exception, Link, LinkConfig, LinkError, LinkState, ReadRange};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

async fn server(allow: Option<Vec<std::net::IpAddr>>) -> (ServerHandle, Arc<MemoryBank>) {
    // Input register k holds k; holding registers 0..20, writable 10..15.
    let bank = Arc::new(MemoryBank::new(
        (0..200).collect(),
        vec![0; 20],
        Some((10, 5)),
    ));
    let cfg = ServerConfig {
        allow,
        ..ServerConfig::new("127.0.0.1:0".parse().unwrap())
    };
    let h = ServerHandle::start(cfg, bank.clone()).await.unwrap();
    (h, bank)
}

fn link(addr: SocketAddr, timeout_ms: u64) -> Link {
    Link::spawn(LinkConfig {
        timeout: Duration::from_millis(timeout_ms),
        backoff_min: Duration::from_millis(20),
        backoff_max: Duration::from_millis(200),
        ..LinkConfig::new(addr)
    })
}

fn r(start: u16, count: u16) -> ReadRange {
    ReadRange::new(start, count).unwrap()
}

#[tokio::test(start_paused = true)]
async fn a_timed_out_call_never_shifts_the_next_reply() {
    let (srv, _) = server(None).await;
    let link = link(srv.local_addr(), 100);
    assert_eq!(link.read_input_registers(1, r(0, 2)).await, Ok(vec![0, 1]));
    srv.set_delay(Duration::from_millis(300));
    assert_eq!(
        link.read_input_registers(1, r(0, 2)).await,
        Err(LinkError::Timeout(Duration::from_millis(100)))
    );
    srv.set_delay(Duration::ZERO);
    // The late reply to (0, 2) is on its way; the link dropped that connection, so the next
    // call gets its own answer, not the stale [0, 1]. (Calls made before the new connection
    // is up fail fast with `Disconnected`.)
    let t0 = axiscomp::util::clock::now();
    while link.stats().reconnects == 0 {
        assert!(
            axiscomp::util::clock::since(t0) < Duration::from_secs(2),
            "reconnected"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    assert_eq!(
        link.read_input_registers(1, r(50, 2)).await,
        Ok(vec![50, 51])
    );
    for k in 0..20u16 {
        assert_eq!(
            link.read_input_registers(1, r(k, 1)).await,
            Ok(vec![k]),
            "call {k} after the timeout"
        );
    }
    let st = link.stats();
    assert_eq!(st.timeouts, 1);
    assert!(st.reconnects >= 1);
    assert_eq!(srv.stats().accepted, 2);
}

#[tokio::test(start_paused = true)]
async fn an_exception_keeps_the_connection() {
    let (srv, _) = server(None).await;
    let link = link(srv.local_addr(), 500);
    srv.set_exception(Some(Exception::ServerDeviceBusy));
    let e = link.read_input_registers(1, r(0, 1)).await.unwrap_err();
    assert_eq!(e, LinkError::Exception(Exception::ServerDeviceBusy));
    assert_eq!(
        e.to_string(),
        "the device answered with exception 0x06 (server device busy)"
    );
    // Connected, answering with exceptions only: refusing, not up, the exception named.
    let st = *link.state().borrow();
    assert_eq!(st.name(), "refusing");
    assert!(
        st.to_string()
            .ends_with("is exception 0x06 (server device busy)"),
        "{st}"
    );
    assert_eq!(
        link.stats().last_exception.map(|(x, _)| x),
        Some(Exception::ServerDeviceBusy)
    );
    srv.set_exception(None);
    assert_eq!(link.read_input_registers(1, r(199, 1)).await, Ok(vec![199]));
    assert!(link.state().borrow().is_up(), "up after a good reply");
    assert_eq!(
        link.read_input_registers(1, r(150, 60)).await,
        Err(LinkError::Exception(Exception::IllegalDataAddress))
    );
    let st = link.stats();
    assert_eq!((st.exceptions, st.reconnects, st.ok), (2, 0, 1));
    assert_eq!(srv.stats().accepted, 1);
}

#[tokio::test(start_paused = true)]
async fn writes_round_trip_within_the_writable_range() {
    let (srv, bank) = server(None).await;
    let link = link(srv.local_addr(), 500);
    link.write_single_register(1, 10, 0xBEEF).await.unwrap();
    link.write_multiple_registers(1, 11, &[1, 2, 3])
        .await
        .unwrap();
    assert_eq!(
        link.read_holding_registers(1, r(9, 6)).await,
        Ok(vec![0, 0xBEEF, 1, 2, 3, 0])
    );
    assert_eq!(&bank.holding()[10..14], &[0xBEEF, 1, 2, 3]);
    assert_eq!(
        link.write_single_register(1, 15, 1).await,
        Err(LinkError::Exception(Exception::IllegalDataAddress))
    );
    assert!(matches!(
        link.write_multiple_registers(1, 0, &[0; 124]).await,
        Err(LinkError::Address(_))
    ));
    assert!(matches!(
        link.write_multiple_registers(1, 0, &[]).await,
        Err(LinkError::Address(_))
    ));
}

/// At most `max_connections` at once: the next is closed on accept (counted, logged), and a
/// place that frees up is taken again.
#[tokio::test]
async fn connections_beyond_the_limit_are_closed_on_accept() {
    use tokio::io::AsyncReadExt;
    let bank = Arc::new(MemoryBank::new((0..200).collect(), vec![0; 20], None));
    let srv = ServerHandle::start(
        ServerConfig {
            max_connections: 2,
            ..ServerConfig::new("127.0.0.1:0".parse().unwrap())
        },
        bank,
    )
    .await
    .unwrap();
    let addr = srv.local_addr();
    let mut kept = Vec::new();
    for tid in 1..=2u16 {
        let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
        // Answered: the connection is in.
        let reply = crate::helpers::raw_request(&mut s, tid, 1, &[4, 0, 5, 0, 1]).await;
        assert_eq!(reply, [4, 2, 0, 5]);
        kept.push(s);
    }
    let mut third = tokio::net::TcpStream::connect(addr).await.unwrap();
    let mut buf = [0u8; 16];
    let n = tokio::time::timeout(Duration::from_secs(2), third.read(&mut buf))
        .await
        .expect("closed at once");
    assert!(matches!(n, Ok(0) | Err(_)), "{n:?}");
    assert_eq!(srv.stats().refused, 1);
    drop(kept.pop());
    // The server frees the place when it reads the close, which a loaded kernel may deliver
    // late: wait for it (real time; this test's clock runs) rather than for a fixed while.
    tokio::time::timeout(Duration::from_secs(20), async {
        while srv.stats().open > 1 {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await
    .expect("the server notices the dropped connection");
    let mut again = tokio::net::TcpStream::connect(addr).await.unwrap();
    let reply = crate::helpers::raw_request(&mut again, 9, 1, &[4, 0, 7, 0, 1]).await;
    assert_eq!(reply, [4, 2, 0, 7]);
    assert_eq!(srv.stats().accepted, 3);
}

#[tokio::test(start_paused = true)]
async fn peers_outside_the_allow_list_are_closed_on_accept() {
    let (srv, _) = server(Some(vec!["192.0.2.1".parse().unwrap()])).await;
    let link = link(srv.local_addr(), 300);
    // The TCP connect succeeds, then the server closes it: the call fails and nothing is read.
    let e = link.read_input_registers(1, r(0, 1)).await.unwrap_err();
    assert!(
        matches!(e, LinkError::Io(_) | LinkError::Disconnected),
        "{e}"
    );
    tokio::time::sleep(Duration::from_millis(100)).await;
    let st = srv.stats();
    assert!(
        st.refused >= 1 && st.accepted == 0 && st.requests == 0,
        "{st:?}"
    );

    let (ok, _) = server(Some(vec!["127.0.0.1".parse().unwrap()])).await;
    let link = self::link(ok.local_addr(), 300);
    assert_eq!(link.read_input_registers(1, r(7, 1)).await, Ok(vec![7]));
}

#[tokio::test(start_paused = true)]
async fn link_state_follows_the_device_and_ends_with_the_handles() {
    let (srv, _) = server(None).await;
    let link = link(srv.local_addr(), 300);
    assert!(link.wait_connected(Duration::from_secs(2)).await);
    srv.stop().await;
    assert!(!srv.is_running());
    // The next call notices the closed connection; reconnects are refused while stopped.
    assert!(link.read_input_registers(1, r(0, 1)).await.is_err());
    let mut st = link.state();
    // (Hold no watch `Ref` across awaits: it blocks the link task's next state update.)
    let down = tokio::time::timeout(
        Duration::from_secs(2),
        st.wait_for(|s| {
            matches!(
                s,
                LinkState::Down {
                    error: LinkError::Connect(std::io::ErrorKind::ConnectionRefused),
                    ..
                }
            )
        }),
    )
    .await
    .is_ok();
    assert!(down, "state {:?}", *link.state().borrow());
    assert_eq!(
        link.read_input_registers(1, r(0, 1)).await,
        Err(LinkError::Disconnected),
        "calls fail fast while down"
    );
    srv.restart().await.unwrap();
    assert!(link.wait_connected(Duration::from_secs(2)).await);
    assert_eq!(link.read_input_registers(1, r(3, 1)).await, Ok(vec![3]));
    let mut st = link.state();
    drop(link);
    let closed = tokio::time::timeout(
        Duration::from_secs(2),
        st.wait_for(|s| *s == LinkState::Closed),
    )
    .await
    .is_ok();
    assert!(closed, "the task ends when the handles are gone");
}

// ---------- the paced reader (modbus::paced) ----------

use axiscomp::modbus::paced::Reply;
use axiscomp::modbus::{PacedReader, RegisterKind};

fn paced(addr: SocketAddr, timeout_ms: u64, range: ReadRange) -> PacedReader {
    let cfg = LinkConfig {
        timeout: Duration::from_millis(timeout_ms),
        backoff_min: Duration::from_millis(20),
        backoff_max: Duration::from_millis(200),
        ..LinkConfig::new(addr)
    };
    PacedReader::new(cfg, RegisterKind::Input, 1, range).0
}

/// Tick `reader` every 5 ms until it reports, at most `within`.
async fn next_outcome(reader: &mut PacedReader, within: Duration) -> Result<Reply, LinkError> {
    let t0 = axiscomp::util::clock::now();
    loop {
        if let Some(r) = reader.tick().await {
            return r;
        }
        assert!(
            axiscomp::util::clock::since(t0) < within,
            "no outcome within {within:?}"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// The first outcome matching `want` after the device changed its behaviour, within 2 s. A
/// request is always in flight and the device may answer it (and, while a stop takes effect,
/// one more) the old way.
async fn after_change(
    reader: &mut PacedReader,
    want: impl Fn(&Result<Reply, LinkError>) -> bool,
) -> Result<Reply, LinkError> {
    let t0 = axiscomp::util::clock::now();
    let mut seen = Vec::new();
    loop {
        let r = next_outcome(reader, Duration::from_secs(2)).await;
        if want(&r) {
            return r;
        }
        seen.push(r);
        assert!(
            axiscomp::util::clock::since(t0) < Duration::from_secs(2) && seen.len() <= 3,
            "{seen:?}"
        );
    }
}

#[tokio::test(start_paused = true)]
async fn a_late_paced_reply_times_out_and_never_becomes_the_next_frame() {
    let (srv, bank) = server(None).await;
    let (mut reader, monitor) = {
        let cfg = LinkConfig {
            timeout: Duration::from_millis(100),
            backoff_min: Duration::from_millis(20),
            backoff_max: Duration::from_millis(200),
            ..LinkConfig::new(srv.local_addr())
        };
        PacedReader::new(cfg, RegisterKind::Input, 1, r(0, 2))
    };
    assert_eq!(
        next_outcome(&mut reader, Duration::from_secs(2))
            .await
            .map(|r| r.registers),
        Ok(vec![0, 1])
    );
    srv.set_delay(Duration::from_millis(300));
    assert_eq!(
        after_change(&mut reader, Result::is_err).await,
        Err(LinkError::Timeout(Duration::from_millis(100)))
    );
    assert!(!monitor.state().borrow().is_up());
    srv.set_delay(Duration::ZERO);
    bank.set_input(0, &[7, 8]);
    // The late [0, 1] (or [7, 8] sampled late) went down with the dropped connection: the
    // next outcome is a fresh reply on a new connection.
    let fresh = next_outcome(&mut reader, Duration::from_secs(2)).await;
    assert_eq!(fresh.map(|r| r.registers), Ok(vec![7, 8]));
    let st = monitor.stats();
    assert_eq!((st.timeouts, st.reconnects), (1, 1));
    assert_eq!(srv.stats().accepted, 2);
}

#[tokio::test(start_paused = true)]
async fn a_paced_exception_keeps_the_connection_and_a_lost_device_reconnects() {
    let (srv, _) = server(None).await;
    let mut reader = paced(srv.local_addr(), 500, r(0, 1));
    let first = next_outcome(&mut reader, Duration::from_secs(2)).await;
    assert!(first.is_ok(), "{first:?}");
    srv.set_exception(Some(Exception::ServerDeviceBusy));
    assert_eq!(
        after_change(&mut reader, Result::is_err).await,
        Err(LinkError::Exception(Exception::ServerDeviceBusy))
    );
    srv.set_exception(None);
    let back = after_change(&mut reader, Result::is_ok).await;
    assert!(back.is_ok(), "{back:?}");
    assert_eq!(srv.stats().accepted, 1, "kept across the exception");
    // The device goes away: the outstanding request fails (connection closed), then the
    // reader backs off and reconnects once the device listens again.
    srv.stop().await;
    let e = after_change(&mut reader, Result::is_err)
        .await
        .expect_err("the device is off");
    assert!(
        e.drops_connection() || matches!(e, LinkError::Connect(_)),
        "{e}"
    );
    srv.restart().await.expect("listen again");
    let t0 = axiscomp::util::clock::now();
    loop {
        if next_outcome(&mut reader, Duration::from_secs(2))
            .await
            .is_ok()
        {
            break;
        }
        assert!(
            axiscomp::util::clock::since(t0) < Duration::from_secs(2),
            "reconnected within 2 s"
        );
    }
}

// ---------- the pipelined reader (modbus::pipelined) ----------

use axiscomp::modbus::PipelinedReader;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// A reply ADU to a read of input registers (function 4) with `regs`.
fn fc4_reply(tid: u16, unit: u8, regs: &[u16]) -> Vec<u8> {
    let mut v = tid.to_be_bytes().to_vec();
    v.extend_from_slice(&[0, 0]);
    v.extend_from_slice(&(3 + 2 * regs.len() as u16).to_be_bytes());
    v.extend_from_slice(&[unit, 4, 2 * regs.len() as u8]);
    for r in regs {
        v.extend_from_slice(&r.to_be_bytes());
    }
    v
}

/// Read `n` request ADUs of 12 bytes; their transaction ids, each checked against the
/// Application Protocol's read-input-registers request (unit 1, start 10, quantity 2).
async fn requests(s: &mut tokio::net::TcpStream, n: usize) -> Vec<u16> {
    let mut buf = vec![0u8; 12 * n];
    tokio::time::timeout(Duration::from_secs(2), s.read_exact(&mut buf))
        .await
        .expect("requests within 2 s")
        .expect("read the requests");
    buf.chunks_exact(12)
        .map(|a| {
            assert_eq!(
                a[2..],
                [0, 0, 0, 6, 1, 4, 0, 10, 0, 2],
                "request ADU {a:02X?}"
            );
            u16::from_be_bytes([a[0], a[1]])
        })
        .collect()
}

/// A listener for a hand-written module and a pipelined reader of input registers 10..12 of
/// unit 1 on it (`timeout_ms` per read, `depth` in flight, quick reconnects).
async fn hand_written_module(
    timeout_ms: u64,
    depth: usize,
) -> (
    tokio::net::TcpListener,
    PipelinedReader,
    axiscomp::modbus::Monitor,
) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let cfg = LinkConfig {
        timeout: Duration::from_millis(timeout_ms),
        backoff_min: Duration::from_millis(20),
        backoff_max: Duration::from_millis(200),
        ..LinkConfig::new(listener.local_addr().unwrap())
    };
    let (reader, monitor) = PipelinedReader::new(cfg, RegisterKind::Input, 1, r(10, 2), depth);
    (listener, reader, monitor)
}

/// Four reads go out before any reply (pipelining); replies answered out of order are each
/// matched to their request by transaction id; an exception keeps the connection; a reply
/// to no request in flight drops it and the reader reconnects. A hand-written module, so the
/// bytes on the wire are the test's (Implementation Guide v1.0b §3.1.3, Application
/// Protocol v1.1b3 §6.4).
#[tokio::test(start_paused = true)]
async fn the_pipelined_reader_keeps_four_reads_in_flight_and_matches_replies_by_id() {
    let (listener, mut reader, monitor) = hand_written_module(500, 4).await;
    let module = tokio::spawn(async move {
        let (mut s, _) = listener.accept().await.unwrap();
        // Four requests before any reply, consecutive ids.
        let tids = requests(&mut s, 4).await;
        assert_eq!(tids, [1, 2, 3, 4]);
        // Answered 2, 1, 4, 3: each reply carries its id in the first register.
        let mut out = Vec::new();
        for t in [2u16, 1, 4, 3] {
            out.extend(fc4_reply(t, 1, &[t, 0xBEEF]));
        }
        s.write_all(&out).await.unwrap();
        // The reader tops up as it takes replies: four more.
        let tids = requests(&mut s, 4).await;
        assert_eq!(tids, [5, 6, 7, 8]);
        // An exception (02, illegal data address) to 5, a good reply to 6.
        s.write_all(&[0, 5, 0, 0, 0, 3, 1, 0x84, 0x02])
            .await
            .unwrap();
        s.write_all(&fc4_reply(6, 1, &[6, 0xBEEF])).await.unwrap();
        assert_eq!(requests(&mut s, 2).await, [9, 10]);
        // A reply to no request in flight: the reader drops the connection.
        s.write_all(&fc4_reply(0x7777, 1, &[0, 0])).await.unwrap();
        let mut rest = Vec::new();
        let eof = tokio::time::timeout(Duration::from_secs(2), s.read_to_end(&mut rest)).await;
        assert!(matches!(eof, Ok(Ok(_))), "the reader closed the connection");
        // It comes back with four fresh reads.
        let (mut s, _) = listener.accept().await.unwrap();
        let tids = requests(&mut s, 4).await;
        let mut out = Vec::new();
        for t in &tids {
            out.extend(fc4_reply(*t, 1, &[*t, 0xCAFE]));
        }
        s.write_all(&out).await.unwrap();
        // Keep the connection open until the reader is done.
        let _ = s.read_to_end(&mut rest).await;
    });
    for want in [2u16, 1, 4, 3] {
        let b = reader.next().await.expect("a reply");
        assert_eq!(b.registers, [want, 0xBEEF]);
        assert!(b.at >= b.sent);
    }
    assert!(monitor.state().borrow().is_up());
    assert_eq!(
        reader.next().await,
        Err(LinkError::Exception(Exception::IllegalDataAddress))
    );
    assert!(matches!(
        *monitor.state().borrow(),
        LinkState::Refusing {
            exception: Exception::IllegalDataAddress,
            ..
        }
    ));
    assert_eq!(reader.next().await.expect("a reply").registers, [6, 0xBEEF]);
    assert!(monitor.state().borrow().is_up());
    match reader.next().await {
        Err(LinkError::InvalidReply(axiscomp::modbus::link::ReplyFault::Header)) => {}
        other => panic!("a reply to no request in flight gave {other:?}"),
    }
    assert!(matches!(*monitor.state().borrow(), LinkState::Down { .. }));
    let b = reader.next().await.expect("a reply after the reconnect");
    assert_eq!(b.registers[1], 0xCAFE);
    let st = monitor.stats();
    assert_eq!((st.ok, st.exceptions, st.reconnects), (6, 1, 1), "{st:?}");
    drop(reader);
    module.abort();
}

/// A module that never answers: the oldest read times out, the connection is dropped (a late
/// reply can never be taken for another read) and the link is down, never up.
#[tokio::test(start_paused = true)]
async fn the_pipelined_reader_times_out_a_silent_module_and_never_calls_it_up() {
    let (listener, mut reader, monitor) = hand_written_module(200, 3).await;
    let module = tokio::spawn(async move {
        let (mut s, _) = listener.accept().await.unwrap();
        assert_eq!(requests(&mut s, 3).await, [1, 2, 3]);
        let mut rest = Vec::new();
        let _ = s.read_to_end(&mut rest).await;
        rest.len()
    });
    let t0 = axiscomp::util::clock::now();
    assert_eq!(
        reader.next().await,
        Err(LinkError::Timeout(Duration::from_millis(200)))
    );
    let waited = axiscomp::util::clock::since(t0);
    assert!(
        waited >= Duration::from_millis(190) && waited < Duration::from_secs(2),
        "{waited:?}"
    );
    assert!(matches!(*monitor.state().borrow(), LinkState::Down { .. }));
    // The module saw the connection close with no request beyond the first three.
    let extra = tokio::time::timeout(Duration::from_secs(2), module)
        .await
        .expect("the connection closed")
        .unwrap();
    assert_eq!(extra, 0);
    assert_eq!(monitor.stats().timeouts, 1);
}
