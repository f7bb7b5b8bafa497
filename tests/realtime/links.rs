//! The links on the real clock: what a simulated clock cannot show (the kernel's receive
//! stamps, latency, the rate of reads as fast as the module answers).

use crate::helpers::{link, plant, twin};
use axiscomp::acquire::map::IoMap;
use axiscomp::acquire::{AcquireConfig, Acquisition};
use axiscomp::modbus::paced::Reply;
use axiscomp::modbus::server::{MemoryBank, ServerConfig, ServerHandle};
use axiscomp::modbus::{LinkConfig, LinkError, LinkState, PacedReader, ReadRange, RegisterKind};
use std::sync::Arc;
use std::time::Duration;

async fn server(allow: Option<Vec<std::net::IpAddr>>) -> (ServerHandle, Arc<MemoryBank>) {
    // Input register k holds k.
    let bank = Arc::new(MemoryBank::new((0..200).collect(), vec![0; 20], None));
    let cfg = ServerConfig {
        allow,
        ..ServerConfig::new("127.0.0.1:0".parse().expect("address"))
    };
    let h = ServerHandle::start(cfg, bank.clone())
        .await
        .expect("server");
    (h, bank)
}

fn r(start: u16, count: u16) -> ReadRange {
    ReadRange::new(start, count).expect("range")
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

#[tokio::test]
async fn the_paced_reader_collects_each_reply_at_the_next_tick() {
    let (srv, bank) = server(None).await;
    let (mut reader, monitor) = PacedReader::new(
        LinkConfig::new(srv.local_addr()),
        RegisterKind::Input,
        1,
        r(10, 4),
    );
    // The first tick connects and sends; nothing to collect yet: connected, not up until
    // the first reply is in.
    assert_eq!(reader.tick().await, None);
    assert_eq!(monitor.state().borrow().name(), "connected");
    // A reply holds the registers as they were at some time between its request's send and
    // its collection: the values when it was sent, or the ones set after (when the device
    // served it late). Never older ones.
    let mut at_send = vec![10, 11, 12, 13];
    let mut last_at = None;
    for k in 0..20u16 {
        tokio::time::sleep(Duration::from_millis(20)).await;
        let now = vec![k, k + 1, 100, 100 + k];
        bank.set_input(10, &now);
        tokio::time::sleep(Duration::from_millis(5)).await;
        // Collects the reply to the request sent at the previous tick, sends the next one.
        let reply = next_outcome(&mut reader, Duration::from_secs(2))
            .await
            .expect("a good reply");
        assert!(
            reply.registers == at_send || reply.registers == now,
            "reply {k}: {:?}, sent with {at_send:?} in the registers, then {now:?}",
            reply.registers
        );
        at_send = now;
        // Stamped with the kernel's receive time: after the send, before we looked.
        assert!(
            reply.sent < reply.at && reply.at <= axiscomp::util::clock::now(),
            "{reply:?}"
        );
        if let Some(l) = last_at {
            assert!(reply.at > l);
        }
        last_at = Some(reply.at);
    }
    assert!(monitor.state().borrow().is_up(), "up once replies came");
    let st = monitor.stats();
    assert_eq!((st.ok, st.errors, st.reconnects), (20, 0, 0));
    assert!(
        st.latency_p50
            .is_some_and(|l| l < Duration::from_millis(20))
    );
    // One connection; 20 requests answered and the 21st in flight (served or not yet).
    let ss = srv.stats();
    assert!(
        ss.accepted == 1 && (20..=21).contains(&ss.requests),
        "{ss:?}"
    );
    drop(reader);
    assert_eq!(*monitor.state().borrow(), LinkState::Closed);
}

/// Read as fast as the module answers, on the runtime production uses: the link measures a
/// latency and a rate (on a simulated clock both are degenerate: every reply at once).
#[tokio::test]
async fn unthrottled_frames_have_a_latency_and_a_rate() {
    let module = twin(plant()).await;
    let link = link(module.local_addr());
    let acq = Acquisition::spawn(
        link.clone(),
        Arc::new(IoMap::generic().expect("generic map")),
        AcquireConfig {
            rate_hz: 0.0,
            ..AcquireConfig::default()
        },
    );
    let mut rx = acq.subscribe();
    let mut last = None;
    for _ in 0..300 {
        let f = rx.recv().await.expect("a frame");
        if let Some(s) = last {
            assert_eq!(f.seq, s + 1, "frames in order");
        }
        last = Some(f.seq);
    }
    let ls = link.stats();
    assert_eq!((ls.errors, ls.reconnects), (0, 0));
    assert!(ls.latency_p50.is_some(), "{ls:?}");
    assert!(ls.rate_hz > 0.0, "{ls:?}");
}
