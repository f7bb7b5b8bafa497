//! Tables into the PLC over loopback: our publisher against the twin's PLC for every shipped
//! map (the plant then carries the table's corrections), its faults (a link drop mid-publish,
//! a corrupted payload, a rejection, no echo), the pull server read and written by a client,
//! and the twin's PLC pulling from it. Ignored (run by tests/interop/plc.sh): independent peers
//! — a pymodbus PLC taking our pushed table, mbpoll and a pymodbus client reading the pull
//! server.

use crate::helpers::*;
use axiscomp::comp::{MachineAxis, TableKind};
use axiscomp::modbus::{Exception, Link, LinkConfig, LinkError, ReadRange};
use axiscomp::plc::serve::{PullConfig, PullServer};
use axiscomp::plc::table::{self, RejectCode};
use axiscomp::plc::{PlcTable, PublishError, PublishOutcome, TableDirection, publish};
use axiscomp::sim::axis::Direction;
use axiscomp::sim::plant::Plant;
use axiscomp::sim::plc::{CommitResult, PullClientConfig, spawn_pull_client};
use std::path::Path;
use std::time::Duration;

/// A smooth table of `n` points 4 mm apart, peak about ±40 µm.
fn smooth(n: usize, phase: f64) -> PlcTable {
    let v: Vec<f64> = (0..n)
        .map(|k| 40.0 * (k as f64 * 0.05 + phase).sin())
        .collect();
    plc_table(&v, 4.0)
}

/// The plant's correction at `x` (mm) equals `−e(x)` of `t` within the payload's rounding.
fn assert_applied(plant: &Plant, t: &PlcTable, what: &str) {
    let c = plant.compensation();
    let dy =
        c.dy.as_ref()
            .unwrap_or_else(|| panic!("{what}: no dy compensation"));
    assert_eq!(dy.positions_mm, t.positions(), "{what}");
    for (k, (c, e)) in dy.up_mm.iter().zip(&t.values_mm).enumerate() {
        // 0.1 µm counts: rounding within 0.05 µm.
        assert!(
            (c + e).abs() <= 0.5e-4 + 1e-12,
            "{what}: point {k}: {c} vs −{e}"
        );
    }
}

async fn link(addr: std::net::SocketAddr) -> Link {
    let l = axiscomp_link(addr);
    assert!(l.wait_connected(Duration::from_secs(5)).await, "link up");
    l
}

fn axiscomp_link(addr: std::net::SocketAddr) -> Link {
    Link::spawn(LinkConfig {
        timeout: Duration::from_millis(500),
        backoff_min: Duration::from_millis(20),
        backoff_max: Duration::from_millis(200),
        ..LinkConfig::new(addr)
    })
}

#[tokio::test(start_paused = true)]
async fn publish_to_the_twin_plc_for_every_map() {
    for file in cnc_map_files() {
        let map = cnc_map(&file);
        let (twin, plant) = twin_plc(map.clone()).await;
        let l = link(twin.local_addr()).await;
        let t = smooth(256, 0.3);
        let r = within_s(20, &file, publish(&l, &map, &t, 1, plc_timeouts())).await;
        assert_eq!(
            r,
            Ok(PublishOutcome::Accepted {
                sequence: 1,
                active_sequence: 1
            }),
            "{file}"
        );
        assert_applied(&plant, &t, &file);
        // The PLC's staging area holds exactly the encoding.
        let want = table::encode(&t, &map, 1).unwrap();
        let holding = twin.holding();
        for (a, v) in want.registers() {
            assert_eq!(holding[a as usize], v, "{file}: register {a}");
        }
        let st = twin.status();
        assert_eq!((st.active_sequence, st.status_sequence), (1, 1), "{file}");
        // The read-back helper decodes what the PLC holds.
        let rb = axiscomp::plc::read_table(&l, &map).await.unwrap();
        assert_eq!(rb.header.sequence, 1);
        assert_eq!(rb.counts, want.counts, "{file}");
        assert!(rb.table.is_ok(), "{file}: {:?}", rb.table);
    }
}

/// The protocol end to end: a bidirectional table of the plant's own positioning error,
/// published, leaves (almost) no error at the grid points in either direction.
#[tokio::test(start_paused = true)]
async fn a_published_table_of_the_true_error_cancels_it() {
    let map = cnc_map("generic.toml");
    let (twin, plant) = twin_plc(map.clone()).await;
    let l = link(twin.local_addr()).await;
    let x: Vec<f64> = (0..=250).map(|k| 4.0 * k as f64).collect();
    let e = |dir| -> Vec<f64> {
        x.iter()
            .map(|&p| plant.axis.errors(p, dir, 0.0).dy)
            .collect()
    };
    let t = PlcTable {
        kind: TableKind::Positioning,
        axis: MachineAxis::Y,
        base_axis: MachineAxis::Y,
        direction: TableDirection::Bidirectional,
        start_mm: 0.0,
        interval_mm: 4.0,
        values_mm: e(Direction::Up),
        down_mm: Some(e(Direction::Down)),
    };
    let r = publish(&l, &map, &t, 3, plc_timeouts()).await;
    assert!(
        matches!(r, Ok(PublishOutcome::Accepted { sequence: 3, .. })),
        "{r:?}"
    );
    // Moves on the plant's own clock: each starts where the last ended.
    let mut now = axiscomp::util::clock::now();
    let mut largest: f64 = 0.0;
    for (target, dir) in [
        (600.0, Direction::Up),
        (200.0, Direction::Down),
        (900.0, Direction::Up),
        (100.0, Direction::Down),
    ] {
        plant.move_carriage(target, now);
        now = plant.carriage_move_end() + Duration::from_millis(1);
        let truth = plant.truth(now);
        assert!(!truth.moving);
        let before = plant.axis.errors(target, dir, 0.0).dy;
        largest = largest.max(before.abs());
        assert!(
            truth.errors.dy.abs() <= 0.5e-4 + 1e-9,
            "{dir:?} at {target}: residual {} mm (was {before})",
            truth.errors.dy
        );
    }
    assert!(
        largest > 2e-3,
        "the axis had errors to cancel ({largest} mm)"
    );
}

#[tokio::test(start_paused = true)]
async fn straightness_tables_act_across_the_travel() {
    let map = cnc_map("generic.toml");
    let (twin, plant) = twin_plc(map.clone()).await;
    let l = link(twin.local_addr()).await;
    // Y axis, standard mapping: head x = +X, head z = +Z.
    let mut tx = smooth(50, 0.0);
    tx.kind = TableKind::Straightness;
    tx.axis = MachineAxis::X;
    let mut tz = smooth(50, 1.0);
    tz.kind = TableKind::Straightness;
    tz.axis = MachineAxis::Z;
    for (k, t) in [&tx, &tz].into_iter().enumerate() {
        let r = publish(&l, &map, t, 10 + k as u32, plc_timeouts()).await;
        assert!(matches!(r, Ok(PublishOutcome::Accepted { .. })), "{r:?}");
    }
    let c = plant.compensation();
    assert!(c.dy.is_none());
    for (p, t) in [(c.dx.unwrap(), &tx), (c.dz.unwrap(), &tz)] {
        for (a, e) in p.up_mm.iter().zip(&t.values_mm) {
            assert!((a + e).abs() <= 0.5e-4 + 1e-12);
        }
    }
    let active = twin.active_tables();
    assert_eq!(active[0].as_ref().map(|a| a.0), Some(10));
    assert_eq!(active[2].as_ref().map(|a| a.0), Some(11));
}

#[tokio::test(start_paused = true)]
async fn a_link_drop_mid_publish_commits_nothing_and_a_retry_succeeds() {
    let map = cnc_map("generic.toml");
    let (twin, plant) = twin_plc(map.clone()).await;
    let l = link(twin.local_addr()).await;
    let a = smooth(256, 0.0);
    let r = publish(&l, &map, &a, 1, plc_timeouts()).await;
    assert!(matches!(r, Ok(PublishOutcome::Accepted { .. })), "{r:?}");
    let before = plant.compensation();
    let writes = twin.writes();

    // The PLC drops out after 3 more writes (header + 2 payload chunks) and is back 300 ms
    // later.
    twin.go_silent_after_writes(3, Duration::from_millis(300));
    let b = smooth(256, 2.0);
    let r = within_s(
        20,
        "publish into a dropping PLC",
        publish(&l, &map, &b, 2, plc_timeouts()),
    )
    .await;
    let e = r.unwrap_err();
    let PublishError::Link {
        commit_sent, step, ..
    } = &e
    else {
        panic!("{e}")
    };
    assert!(!commit_sent, "{e}");
    assert!(step.starts_with("writing registers 272..392"), "{step}");
    // Reported (and stored) as failed, not as a PLC answer.
    assert!(
        matches!(
            axiscomp::plc::publication_outcome(&Err(e.clone())),
            axiscomp::store::PublicationOutcome::Failed { .. }
        ),
        "{e}"
    );
    assert_eq!(
        twin.writes(),
        writes + 3,
        "three writes served, the fourth dropped"
    );
    assert_eq!(twin.commits().len(), 1, "no commit after the drop");
    assert_eq!(twin.status().active_sequence, 1);
    assert_eq!(
        plant.compensation(),
        before,
        "the active table is unchanged"
    );

    // A retry (new sequence) once the PLC is back goes through.
    let r = within_s(20, "retry", publish(&l, &map, &b, 3, plc_timeouts())).await;
    assert_eq!(
        r,
        Ok(PublishOutcome::Accepted {
            sequence: 3,
            active_sequence: 3
        })
    );
    assert_applied(&plant, &b, "retry");
    assert!(l.stats().reconnects >= 1);
}

#[tokio::test(start_paused = true)]
async fn a_corrupted_payload_is_rejected_with_the_crc_code() {
    let map = cnc_map("generic.toml");
    let (twin, plant) = twin_plc(map.clone()).await;
    let l = link(twin.local_addr()).await;
    let a = smooth(100, 0.0);
    assert!(publish(&l, &map, &a, 1, plc_timeouts()).await.is_ok());
    let before = plant.compensation();
    // One payload register flipped in the PLC after the read-back, before validation.
    twin.corrupt_next_commit(17);
    let r = publish(&l, &map, &smooth(100, 1.0), 2, plc_timeouts()).await;
    assert_eq!(
        r,
        Ok(PublishOutcome::Rejected {
            sequence: 2,
            code: RejectCode::Crc,
            active_sequence: 1
        })
    );
    let last = twin.commits().pop().unwrap();
    assert!(
        matches!(&last.result, CommitResult::Rejected(r) if r.code == RejectCode::Crc),
        "{last:?}"
    );
    assert_eq!(plant.compensation(), before);
    let st = twin.status();
    assert_eq!(
        (st.error_code, st.status_sequence, st.active_sequence),
        (1, 2, 1)
    );
    // The store's record of it.
    assert_eq!(
        axiscomp::plc::publication_outcome(&r),
        axiscomp::store::PublicationOutcome::Rejected {
            code: Some(1),
            text: "CRC mismatch".into()
        }
    );
}

#[tokio::test(start_paused = true)]
async fn a_refusal_and_a_missing_echo_are_reported() {
    let map = cnc_map("generic.toml");
    let (twin, plant) = twin_plc(map.clone()).await;
    let l = link(twin.local_addr()).await;
    twin.reject_next(256);
    let r = publish(&l, &map, &smooth(20, 0.0), 1, plc_timeouts()).await;
    assert_eq!(
        r,
        Ok(PublishOutcome::Rejected {
            sequence: 1,
            code: RejectCode::Other(256),
            active_sequence: 0
        })
    );
    assert_eq!(plant.compensation(), Default::default());

    twin.ignore_next_commit();
    let to = axiscomp::plc::Timeouts {
        echo: Duration::from_millis(300),
        ..plc_timeouts()
    };
    let r = publish(&l, &map, &smooth(20, 0.0), 2, to).await;
    let e = r.unwrap_err();
    assert!(matches!(e, PublishError::NoEcho { sequence: 2, .. }), "{e}");
    assert!(e.commit_sent());
    let writes = twin.writes();
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert_eq!(
        twin.writes(),
        writes,
        "nothing is written after the timeout"
    );
    assert_eq!(twin.status().active_sequence, 0);
    assert!(matches!(
        axiscomp::plc::publication_outcome(&Err(e)),
        axiscomp::store::PublicationOutcome::Failed { code: None, .. }
    ));
}

#[tokio::test(start_paused = true)]
async fn a_plc_not_ready_or_not_alive_gets_nothing() {
    let map = cnc_map("generic.toml");
    let (twin, _) = twin_plc(map.clone()).await;
    let l = link(twin.local_addr()).await;
    let to = axiscomp::plc::Timeouts {
        ready: Duration::from_millis(400),
        heartbeat: Duration::from_millis(300),
        ..plc_timeouts()
    };
    twin.set_ready(false);
    let e = publish(&l, &map, &smooth(20, 0.0), 1, to)
        .await
        .unwrap_err();
    assert!(matches!(e, PublishError::NotReady { .. }), "{e}");
    twin.set_ready(true);
    twin.freeze_heartbeat(true);
    let e = publish(&l, &map, &smooth(20, 0.0), 1, to)
        .await
        .unwrap_err();
    assert!(matches!(e, PublishError::NotAlive { .. }), "{e}");
    assert_eq!(twin.writes(), 0);
    twin.freeze_heartbeat(false);
    assert!(publish(&l, &map, &smooth(20, 0.0), 1, to).await.is_ok());
}

// ---------- the pull server ----------

fn r(start: u16, count: u16) -> ReadRange {
    ReadRange::new(start, count).unwrap()
}

/// Read the table block as a PLC would (≤ 120 registers per read) and decode it.
async fn pull_read(
    l: &Link,
    map: &axiscomp::plc::CncMap,
) -> (u32, Result<PlcTable, axiscomp::plc::Reject>) {
    let published = l.read_holding_registers(1, r(8, 2)).await.unwrap();
    let published = (published[0] as u32) << 16 | published[1] as u32;
    let mut regs = vec![0u16; 4128];
    regs[16..30].copy_from_slice(&l.read_holding_registers(1, r(16, 14)).await.unwrap());
    let h = table::decode_header(map, &|a| regs[a as usize]);
    let n = table::payload_len(map, &h);
    let mut a = 32u16;
    while (a as usize) < 32 + 2 * n {
        let c = (32 + 2 * n - a as usize).min(120) as u16;
        let v = l.read_holding_registers(1, r(a, c)).await.unwrap();
        regs[a as usize..a as usize + c as usize].copy_from_slice(&v);
        a += c;
    }
    let counts = table::decode_payload(map, n, &|a| regs[a as usize]);
    (
        published,
        table::validate(map, &h, &counts, Some(published)),
    )
}

#[tokio::test(start_paused = true)]
async fn the_pull_server_serves_the_table_and_guards_the_ack_range() {
    let map = cnc_map("generic.toml");
    // Writers: only 127.0.0.2; this test connects from 127.0.0.1.
    let srv = PullServer::start(
        map.clone(),
        PullConfig {
            writers: Some(vec!["127.0.0.2".parse().unwrap()]),
            ..PullConfig::new("127.0.0.1:0".parse().unwrap())
        },
    )
    .await
    .unwrap();
    let t = smooth(256, 0.7);
    let enc = srv.set_table(&t, 5).unwrap();
    let l = link(srv.local_addr()).await;
    let (published, got) = pull_read(&l, &map).await;
    assert_eq!(published, 5);
    let got = got.expect("the CRC matches and the table validates");
    assert_eq!(got.values_mm.len(), 256);
    for (g, w) in got.values_mm.iter().zip(&t.values_mm) {
        assert!((g - w).abs() <= 0.5e-4 + 1e-12);
    }
    let crc = l.read_holding_registers(1, r(28, 2)).await.unwrap();
    assert_eq!((crc[0] as u32) << 16 | crc[1] as u32, enc.crc);

    let before = l.read_holding_registers(1, r(0, 120)).await.unwrap();
    // Outside the ack range: the header, the published sequence, a run over the boundary.
    for (start, values) in [(16u16, vec![9u16]), (8, vec![0, 6]), (6, vec![0, 0, 0])] {
        assert_eq!(
            l.write_multiple_registers(1, start, &values).await,
            Err(LinkError::Exception(Exception::IllegalDataAddress)),
            "write at {start}"
        );
    }
    // Inside it, but from a peer that may not write.
    assert_eq!(
        l.write_single_register(1, 2, 2).await,
        Err(LinkError::Exception(Exception::IllegalFunction))
    );
    // Quantities are validated: 126 registers is an illegal data value.
    let mut s = tokio::net::TcpStream::connect(srv.local_addr())
        .await
        .unwrap();
    let pdu = raw_request(&mut s, 1, 1, &[0x03, 0x00, 0x00, 0x00, 126]).await;
    assert_eq!(pdu, [0x83, 0x03]);
    // Nothing changed, and the connection was kept throughout.
    assert_eq!(
        l.read_holding_registers(1, r(0, 120)).await.unwrap(),
        before
    );
    assert_eq!(srv.acks().borrow().writes, 0);
    assert_eq!(l.stats().reconnects, 0);
    assert_eq!(srv.published(), 5);

    // A server whose writer is this peer takes the acknowledgement.
    let srv2 = PullServer::start(
        map.clone(),
        PullConfig {
            writers: Some(vec!["127.0.0.1".parse().unwrap()]),
            ..PullConfig::new("127.0.0.1:0".parse().unwrap())
        },
    )
    .await
    .unwrap();
    srv2.set_table(&t, 6).unwrap();
    let l2 = link(srv2.local_addr()).await;
    l2.write_multiple_registers(1, 0, &[1, 77, 2, 0, 0, 6, 0, 6])
        .await
        .unwrap();
    let ack = srv2.wait_ack(6, Duration::from_secs(2)).await.expect("ack");
    assert_eq!(ack.status.heartbeat, 77);
    assert_eq!(ack.status.active_sequence, 6);
}

/// The pull server's limits (`plc.pull_max_connections`, `plc.pull_idle_timeout_s`): a peer
/// beyond the limit is closed on accept; a peer that sends nothing, and one that trickles a
/// frame byte by byte, are closed once no request came for the idle timeout, and not before;
/// a PLC polling more often than that stays connected; the places freed are taken again.
#[tokio::test(start_paused = true)]
async fn the_pull_server_closes_idle_peers_and_refuses_beyond_its_limit() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    use tokio::net::TcpStream;
    let idle = Duration::from_millis(1000);
    let srv = PullServer::start(
        cnc_map("generic.toml"),
        PullConfig {
            max_connections: 3,
            idle_timeout: idle,
            ..PullConfig::new("127.0.0.1:0".parse().unwrap())
        },
    )
    .await
    .unwrap();
    let addr = srv.local_addr();
    // Read holding register 0 (function 3) from unit 1, the generic map's.
    let read = [3u8, 0, 0, 0, 1];
    let mut plc = TcpStream::connect(addr).await.unwrap();
    assert_eq!(raw_request(&mut plc, 1, 1, &read).await, [3, 2, 0, 0]);
    let opened = axiscomp::util::clock::now();
    let mut silent = TcpStream::connect(addr).await.unwrap();
    let mut slow = TcpStream::connect(addr).await.unwrap();
    // An MBAP header announcing 253 bytes, one byte every 100 ms: never a whole request.
    let trickle = tokio::spawn(async move {
        for b in [0u8, 9, 0, 0, 0, 253, 1, 3].into_iter().chain([0u8; 40]) {
            if slow.write_all(&[b]).await.is_err() {
                break;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        slow
    });
    tokio::time::sleep(Duration::from_millis(200)).await;
    let mut fourth = TcpStream::connect(addr).await.unwrap();
    let mut buf = [0u8; 16];
    let n = tokio::time::timeout(Duration::from_secs(2), fourth.read(&mut buf))
        .await
        .expect("the fourth connection is closed on accept");
    assert!(matches!(n, Ok(0) | Err(_)), "{n:?}");
    assert_eq!(srv.server().stats().refused, 1);

    // The PLC polls every 200 ms for 2.4 s (more than twice the idle timeout): always answered.
    let poller = tokio::spawn(async move {
        for tid in 2..14u16 {
            tokio::time::sleep(Duration::from_millis(200)).await;
            assert_eq!(raw_request(&mut plc, tid, 1, &read).await, [3, 2, 0, 0]);
        }
        plc
    });
    let n = tokio::time::timeout(Duration::from_secs(5), silent.read(&mut buf))
        .await
        .expect("the silent peer is closed within 5 s");
    assert!(matches!(n, Ok(0) | Err(_)), "{n:?}");
    let closed_after = axiscomp::util::clock::since(opened);
    assert!(
        closed_after >= idle,
        "closed after {closed_after:?}, before the idle timeout"
    );
    let mut slow = trickle.await.unwrap();
    let n = tokio::time::timeout(Duration::from_secs(5), slow.read(&mut buf))
        .await
        .expect("the trickling peer is closed");
    assert!(matches!(n, Ok(0) | Err(_)), "{n:?}");
    let mut plc = poller.await.unwrap();
    assert_eq!(raw_request(&mut plc, 20, 1, &read).await, [3, 2, 0, 0]);
    // Two places are free again (the server closed both itself; wait until it counts them).
    for _ in 0..1000 {
        if srv.server().stats().open <= 1 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    assert_eq!(
        srv.server().stats().open,
        1,
        "the idle peers' places are freed"
    );
    let mut again = TcpStream::connect(addr).await.unwrap();
    assert_eq!(raw_request(&mut again, 21, 1, &read).await, [3, 2, 0, 0]);
}

#[tokio::test(start_paused = true)]
async fn the_twin_plc_pulls_from_the_pull_server() {
    let map = cnc_map("generic.toml");
    let srv = PullServer::start(map.clone(), PullConfig::new("127.0.0.1:0".parse().unwrap()))
        .await
        .unwrap();
    let plant = plant();
    let client = spawn_pull_client(
        axiscomp_link(srv.local_addr()),
        map.clone(),
        plant.clone(),
        PullClientConfig::default(),
    );
    let t = smooth(256, 0.2);
    srv.set_table(&t, 1).unwrap();
    let ack = srv
        .wait_ack(1, Duration::from_secs(10))
        .await
        .expect("ack 1");
    assert_eq!(ack.status.status, axiscomp::plc::StatusCode::Accepted);
    assert_applied(&plant, &t, "pulled");
    // A newer table replaces it; the heartbeat keeps counting.
    let t2 = smooth(128, 1.5);
    srv.set_table(&t2, 2).unwrap();
    let ack2 = srv
        .wait_ack(2, Duration::from_secs(10))
        .await
        .expect("ack 2");
    assert!(ack2.status.heartbeat != ack.status.heartbeat);
    assert_eq!(ack2.status.active_sequence, 2);
    assert_applied(&plant, &t2, "pulled again");
    // The client records its commit just after writing the acknowledgement.
    let commits = within_s(5, "the client's record", async {
        loop {
            let c = client.state().commits;
            if c.len() >= 2 {
                return c;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await;
    let seqs: Vec<u32> = commits.iter().map(|c| c.sequence).collect();
    assert_eq!(seqs, [1, 2]);
    assert!(commits.iter().all(|c| c.result == CommitResult::Accepted));
}

// ---------- independent peers (run by tests/interop/plc.sh) ----------

/// Kill the child we started when the test ends, pass or fail.
struct Reap(std::process::Child);
impl Drop for Reap {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// Start `tests/interop/plc_peer.py` with `args` and return it with its first stdout line.
async fn peer(args: &[&str]) -> (Reap, String) {
    use std::io::BufRead;
    use std::process::{Command, Stdio};
    let mut child = Reap(
        Command::new("python3")
            .arg(root().join("tests/interop/plc_peer.py"))
            .args(args)
            .current_dir(root())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("run python3 tests/interop/plc_peer.py"),
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
    .expect("the script's first line");
    (child, line)
}

/// The values of the interop table, e in µm with 9 decimals, and their text: the script gets
/// the numbers, never our encoding.
fn interop_values() -> (Vec<f64>, String) {
    let text: Vec<String> = (0..300)
        .map(|k| {
            let k = k as f64;
            format!(
                "{:.9}",
                (k * 0.173).sin() * 63.25 + (k * 0.021).cos() * 11.5 - 11.5
            )
        })
        .collect();
    let values = text.iter().map(|t| t.parse().expect("number")).collect();
    (values, text.join(","))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs pymodbus/mbpoll: run by .ci/run"]
async fn interop_pymodbus_plc_takes_pushed_tables_in_every_word_order() {
    let (values, values_arg) = interop_values();
    let mut t = plc_table(&values, 2.5);
    t.start_mm = -12.5;
    t.kind = TableKind::Straightness;
    t.axis = MachineAxis::Z;
    std::fs::create_dir_all(env!("CARGO_TARGET_TMPDIR")).unwrap();
    let values_file = Path::new(env!("CARGO_TARGET_TMPDIR")).join("plc-interop-values.txt");
    std::fs::write(&values_file, &values_arg).unwrap();
    // Each shipped map as it is (ABCD and CDAB, holding and input PLC fields), and the
    // generic map (ABCD) in the other three word orders: every order on one layout.
    let mut cases: Vec<(String, Option<&str>)> =
        cnc_map_files().into_iter().map(|f| (f, None)).collect();
    for o in ["CDAB", "BADC", "DCBA"] {
        cases.push(("generic.toml".into(), Some(o)));
    }
    for (seq, (file, order)) in cases.into_iter().enumerate() {
        let seq = seq as u32 + 1;
        let port = free_port().to_string();
        let map_path = root().join("plc-maps/cnc").join(&file);
        let mut args = vec![
            "plc".to_string(),
            "--port".into(),
            port.clone(),
            "--map".into(),
            map_path.display().to_string(),
            "--values-file".into(),
            values_file.display().to_string(),
            "--start-mm".into(),
            "-12.5".into(),
            "--interval-mm".into(),
            "2.5".into(),
            "--kind".into(),
            "2".into(),
            "--axis".into(),
            "3".into(),
            "--base-axis".into(),
            "2".into(),
            "--sequence".into(),
            seq.to_string(),
        ];
        let mut map = cnc_map(&file);
        if let Some(o) = order {
            args.push("--word-order".into());
            args.push(o.into());
            let o: axiscomp::modbus::WordOrder = o.parse().unwrap();
            for f in [
                &mut map.handshake.plc_ready,
                &mut map.handshake.plc_heartbeat,
                &mut map.handshake.status,
                &mut map.handshake.error_code,
                &mut map.handshake.status_sequence,
                &mut map.handshake.active_sequence,
                &mut map.handshake.commit,
                &mut map.header.kind,
                &mut map.header.axis,
                &mut map.header.base_axis,
                &mut map.header.direction,
                &mut map.header.points,
                &mut map.header.unit,
                &mut map.header.start,
                &mut map.header.interval,
                &mut map.header.sequence,
                &mut map.header.crc,
            ] {
                f.order = o;
            }
            map.payload.order = o;
        }
        let arg_refs: Vec<&str> = args.iter().map(String::as_str).collect();
        let (_child, line) = peer(&arg_refs).await;
        assert!(line.starts_with("listening"), "{file}: {line}");
        let l = Link::spawn(LinkConfig {
            backoff_max: Duration::from_millis(200),
            ..LinkConfig::new(format!("127.0.0.1:{port}").parse().unwrap())
        });
        assert!(
            l.wait_connected(Duration::from_secs(10)).await,
            "pymodbus up"
        );
        let r = within_s(30, &file, publish(&l, &map, &t, seq, plc_timeouts())).await;
        // The script accepts only if every register it received equals its own encoding of
        // the values (and the CRC it computed matches); otherwise it rejects with code 1000
        // + the first differing register's offset.
        assert_eq!(
            r,
            Ok(PublishOutcome::Accepted {
                sequence: seq,
                active_sequence: seq
            }),
            "{file} {order:?}"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs pymodbus/mbpoll: run by .ci/run"]
async fn interop_mbpoll_and_pymodbus_read_the_pull_server() {
    let map = cnc_map("generic.toml");
    let srv = PullServer::start(
        map.clone(),
        PullConfig {
            // Only 127.0.0.2 may write; the peers connect from 127.0.0.1.
            writers: Some(vec!["127.0.0.2".parse().unwrap()]),
            ..PullConfig::new("127.0.0.1:0".parse().unwrap())
        },
    )
    .await
    .unwrap();
    let (values, _) = interop_values();
    let t = plc_table(&values, 2.5);
    let enc = srv.set_table(&t, 77).unwrap();
    let port = srv.local_addr().port().to_string();

    // mbpoll: the header (16..30), unsigned 16-bit, PDU addressing.
    let p = port.clone();
    let out = tokio::task::spawn_blocking(move || {
        std::process::Command::new("mbpoll")
            .args([
                "-m", "tcp", "-a", "1", "-0", "-r", "16", "-c", "14", "-t", "4", "-1",
            ])
            .args(["-p", &p, "127.0.0.1"])
            .output()
    })
    .await
    .unwrap()
    .expect("run mbpoll");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "mbpoll failed: {text}");
    let mut header = vec![None; 14];
    for line in text.lines() {
        if let Some((k, v)) = line
            .trim()
            .strip_prefix('[')
            .and_then(|l| l.split_once("]:"))
        {
            let k: usize = k.parse().unwrap();
            let v: u16 = v.split_whitespace().next().unwrap().parse().unwrap();
            header[k - 16] = Some(v);
        }
    }
    let header: Vec<u16> = header
        .into_iter()
        .map(|r| r.expect("14 registers"))
        .collect();
    let regs = enc.registers();
    let want: Vec<u16> = (16..30).map(|a| regs[&a]).collect();
    assert_eq!(header, want, "{text}");
    // mbpoll's write to the header: an exception, nothing changed.
    let p = port.clone();
    let out = tokio::task::spawn_blocking(move || {
        std::process::Command::new("mbpoll")
            .args(["-m", "tcp", "-a", "1", "-0", "-r", "16", "-t", "4", "-1"])
            .args(["-p", &p, "127.0.0.1", "9"])
            .output()
    })
    .await
    .unwrap()
    .expect("run mbpoll");
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    // libmodbus names the exception: 02, illegal data address (the header is read-only).
    assert!(
        !out.status.success() && text.to_lowercase().contains("illegal data address"),
        "{text}"
    );

    // pymodbus: reads the block, checks the CRC itself, tries writes outside the ack range and
    // from a non-writer, and reports.
    let (_child, line) = peer(&[
        "pull",
        "--port",
        &port,
        "--map",
        "plc-maps/cnc/generic.toml",
    ])
    .await;
    let report: serde_json::Value = serde_json::from_str(&line).expect("JSON from plc_peer.py");
    assert_eq!(report["published"], 77, "{report}");
    assert_eq!(report["crc_ok"], true, "{report}");
    assert_eq!(report["points"], 300, "{report}");
    let got: Vec<f64> = serde_json::from_value(report["values_um"].clone()).unwrap();
    for (g, w) in got.iter().zip(&values) {
        assert!((g - w).abs() <= 0.05 + 1e-9, "{g} vs {w}");
    }
    // Illegal data address (2) outside the ack range, illegal function (1) from a non-writer.
    for (k, code) in [
        ("write_header", 2),
        ("write_published", 2),
        ("write_ack_not_writer", 1),
    ] {
        assert_eq!(report[k], code, "{k}: {report}");
    }
    assert_eq!(srv.published(), 77);
    assert_eq!(srv.acks().borrow().writes, 0, "nothing written");
    let regs_now: Vec<u16> = {
        let l = link(srv.local_addr()).await;
        l.read_holding_registers(1, r(16, 14)).await.unwrap()
    };
    assert_eq!(regs_now, want);
}

// ---------- the service: tables from a stored run, published through the control API ----------

/// A finished run of synthetic captures: the twin's true errors (no noise) at 11 targets over
/// 0..1000 mm, 3 bidirectional runs. Inserted straight into the service's store (a real run on
/// the twin takes minutes; `sim::lab` measures one on a virtual clock) — what is tested here
/// is everything after the captures: evaluation, tables, publishing, read-back.
fn store_synthetic_run(store: &std::path::Path, plant: &Plant) -> i64 {
    store_synthetic_run_recorded(store, plant, true)
}

/// As [`store_synthetic_run`]; `record`: whether the tables active during it are recorded.
fn store_synthetic_run_recorded(store: &std::path::Path, plant: &Plant, record: bool) -> i64 {
    use axiscomp::Errors6;
    use axiscomp::run::{Capture, Direction as RunDirection};
    use axiscomp::store::{NewRun, RunState, Store};
    let mut s = Store::open(store).expect("open the service's store");
    let id = s
        .create_run(&NewRun {
            axis: "Y".into(),
            plan: serde_json::json!({"reference_mm": 0.0}),
            config: serde_json::json!({"synthetic": true}),
            calibration: None,
            notes: "synthetic captures of the twin's true errors".into(),
        })
        .expect("create run");
    s.set_run_state(id, RunState::Running).expect("running");
    if record {
        crate::helpers::record_no_tables(&mut s, id);
    }
    let small = Errors6 {
        dx: 1e-4,
        dy: 1e-4,
        dz: 1e-4,
        ex: 1e-6,
        ey: 1e-6,
        ez: 1e-6,
    };
    for run in 1..=3u32 {
        for (dir, rdir) in [
            (Direction::Up, RunDirection::Up),
            (Direction::Down, RunDirection::Down),
        ] {
            for k in 0..=10u32 {
                let x = 100.0 * k as f64;
                let c = Capture {
                    run,
                    target_index: k,
                    target_mm: x,
                    direction: rdir,
                    errors: plant.axis.errors(x, dir, 0.0),
                    frame_sd: small,
                    u: small,
                    frames: 100,
                    material_c: None,
                    air_c: None,
                    unix_us: 0,
                };
                s.insert_capture(id, &c).expect("capture");
            }
        }
    }
    s.set_run_state(id, RunState::Finished).expect("finished");
    id.0
}

/// Issue 24 (must-show 4): nothing from a run the store cannot vouch for. `table generate`,
/// publish and `export` refuse a run with a flagged capture left open, and a run without a
/// record of the tables the PLC applied while it ran, each with the reason; the residual is
/// written only when asked for by name; the audit log shows the refusals as refused.
#[tokio::test(start_paused = true)]
async fn tables_refuse_runs_with_open_flags_or_without_the_active_tables_recorded() {
    use axiscomp::service::api::Request;
    use axiscomp::store::{AuditOutcome, RunId, Store, now_us};
    let rig = ServiceRig::start(RigOptions {
        twin_plc: true,
        ..RigOptions::default()
    })
    .await;
    let generate = |run_id: i64, residual_only: bool| Request::TableGenerate {
        run_id,
        residual_only,
    };
    // A table from a run with nothing open, then one capture of that run flagged (as the
    // judge's review moves a stored capture out).
    let run = store_synthetic_run(&rig.store, &rig.twin.plant);
    let v = rig.request(generate(run, false)).await.expect("generate");
    let table_id = v["tables"][0]["id"].as_i64().expect("a table");
    {
        let mut s = Store::open(&rig.store).expect("store");
        let c = s.captures(RunId(run)).expect("captures")[3];
        s.flag_capture(
            RunId(run),
            &c,
            "run 2, target 2 +: off the other 2 captures of its target and direction by dy +3.5 µm",
            true,
            now_us(),
        )
        .expect("flag");
        assert_eq!(s.captures(RunId(run)).expect("captures").len(), 65);
    }
    let e = rig
        .request(generate(run, false))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(&format!(
            "run {run} has 1 flagged capture neither retaken nor excluded"
        )) && e.contains("dy +3.5 µm"),
        "{e}"
    );
    let e = rig
        .request(Request::TablePublish {
            table_id,
            confirm: true,
        })
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(&format!("table {table_id} is from run {run}")) && e.contains("flagged"),
        "{e}"
    );
    let db = rig.store.to_str().expect("path").to_string();
    let dir = TempDir::new("refusals");
    let out = dir.path("refused.csv");
    let o = out.to_str().expect("path").to_string();
    let export = |run: i64, extra: &[&str]| {
        let run = run.to_string();
        let mut a = vec![
            "export", "--run", &run, "--db", &db, "--format", "csv", "--out", &o,
        ];
        a.extend_from_slice(extra);
        crate::helpers::run(&a, "")
    };
    let r = export(run, &[]);
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(
        !r.status.success() && err.contains("flagged capture"),
        "{err}"
    );
    assert!(!out.exists(), "nothing written");

    // A run with no record of what the PLC applied: refused; the residual by name only.
    let bare = store_synthetic_run_recorded(&rig.store, &rig.twin.plant, false);
    let e = rig
        .request(generate(bare, false))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(&format!(
            "run {bare} has no record of the tables the PLC applied while it ran"
        )) && e.contains("--residual-only"),
        "{e}"
    );
    let r = export(bare, &[]);
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(!r.status.success() && err.contains("no record"), "{err}");
    let v = rig
        .request(generate(bare, true))
        .await
        .expect("residual by name");
    assert!(!v["tables"].as_array().expect("tables").is_empty(), "{v}");
    let r = export(bare, &["--residual-only"]);
    assert!(
        r.status.success() && out.exists(),
        "{}",
        String::from_utf8_lossy(&r.stderr)
    );

    // The operator excludes the flag with a reason: audited, shown, no longer holding the
    // run back on that count (the capture stays out of the run).
    let flags = rig
        .request(Request::RunFlags { run_id: run })
        .await
        .expect("run_flags");
    let flag = flags["flags"][0]["flag"].as_i64().expect("a flag");
    assert_eq!(flags["flags"][0]["state"], "open", "{flags:#}");
    let e = rig
        .request(Request::RunExclude {
            run_id: run,
            flag,
            reason: " ".into(),
        })
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("give the reason"), "{e}");
    let v = rig
        .request(Request::RunExclude {
            run_id: run,
            flag,
            reason: "the carriage was knocked by the operator at that capture".into(),
        })
        .await
        .expect("run_exclude");
    assert!(v["open"].is_null(), "{v:#}");
    let flags = rig
        .request(Request::RunFlags { run_id: run })
        .await
        .expect("run_flags");
    let state = flags["flags"][0]["state"].as_str().unwrap_or_default();
    assert!(
        state.starts_with("excluded by") && state.contains("knocked"),
        "{flags:#}"
    );

    // The refusals in the audit log, as refused, with their reasons.
    let s = Store::open_read_only(&rig.store).expect("store");
    let refused: Vec<String> = s
        .audit_entries(50)
        .expect("audit")
        .into_iter()
        .filter_map(|a| match a.entry.outcome {
            AuditOutcome::Refused(why) => Some(format!("{} {why}", a.entry.action)),
            _ => None,
        })
        .collect();
    assert_eq!(refused.len(), 4, "{refused:#?}");
    assert!(
        refused.iter().any(|r| r.contains("flagged capture"))
            && refused.iter().any(|r| r.contains("is from run"))
            && refused.iter().any(|r| r.contains("no record"))
            && refused.iter().any(|r| r.contains("give the reason")),
        "{refused:#?}"
    );
}

/// The service with the twin's I/O module, drive and PLC on loopback: generate the tables of a
/// stored run, publish without and with confirmation, read the PLC's table back, and a PLC
/// that rejects (issue 5: control API and CLI).
#[tokio::test(start_paused = true)]
async fn the_service_generates_publishes_and_reads_back_tables() {
    use axiscomp::service::api::Request;
    use axiscomp::service::stored::StoredTable;
    use axiscomp::service::tables::{PublishView, StatusView, TableView};
    use axiscomp::store::{PublicationOutcome, Store, TableId};
    let rig = ServiceRig::start(RigOptions {
        twin_plc: true,
        ..RigOptions::default()
    })
    .await;
    let plc = rig.plc.as_ref().expect("twin PLC");
    let map = plc.map().clone();
    let run_id = store_synthetic_run(&rig.store, &rig.twin.plant);

    // Nothing published yet.
    let st: StatusView =
        serde_json::from_value(rig.request(Request::TableStatus).await.expect("status"))
            .expect("status view");
    assert_eq!(st.verdict, "empty", "{}", st.message);
    // A staging area never written is no staged table, not an invalid one (the console read
    // "staged table invalid: code 3 (point count out of range): 0 points" on a healthy PLC).
    assert!(
        st.staged.is_none(),
        "{:?}",
        st.staged.as_ref().map(|s| &s.invalid)
    );

    // Generate: positioning and both straightnesses, stored with their run.
    let v = rig
        .request(Request::TableGenerate {
            run_id,
            residual_only: false,
        })
        .await
        .expect("generate");
    let tables: Vec<TableView> = serde_json::from_value(v["tables"].clone()).expect("tables");
    let names: Vec<&str> = tables.iter().map(|t| t.name.as_str()).collect();
    assert_eq!(names, ["EYY", "EXY", "EZY"], "{v:#}");
    assert!(tables.iter().all(|t| t.source_run == Some(run_id)));
    let pos = &tables[0];
    assert_eq!(
        (pos.kind.as_str(), pos.direction.as_str()),
        ("positioning", "bidirectional")
    );
    // The true positioning error peaks at ±30 µm (plus the periodic term).
    assert!(pos.max_um - pos.min_um > 20.0, "{pos:?}");

    // Without confirmation: refused, nothing written to the PLC.
    let writes = plc.writes();
    let e = rig
        .request(Request::TablePublish {
            table_id: pos.id,
            confirm: false,
        })
        .await
        .expect_err("publish without confirm");
    assert!(e.to_string().contains("\"confirm\": true"), "{e}");
    assert_eq!(plc.writes(), writes);

    // Publish the positioning table and both straightnesses.
    let mut sequences = Vec::new();
    for t in &tables {
        let p: PublishView = publish_by_api(&rig, t.id).await;
        assert_eq!(p.result, "committed", "{p:?}");
        assert_eq!(p.active_sequence, Some(p.sequence));
        sequences.push(p.sequence);
    }
    assert_eq!(sequences, [1, 2, 3]);

    // The twin's PLC holds exactly the encoded tables, and the plant carries them.
    let store = Store::open_read_only(&rig.store).expect("store");
    let stored: Vec<axiscomp::plc::PlcTable> = tables
        .iter()
        .map(|t| {
            let rec = store.table(TableId(t.id)).expect("stored table");
            StoredTable::from_record(&rec)
                .and_then(|s| s.plc_table())
                .expect("plc table")
        })
        .collect();
    let active = plc.active_tables();
    for (slot, (k, seq)) in [(1usize, (0usize, 1u32)), (0, (1, 2)), (2, (2, 3))] {
        let (s, t) = active[slot].clone().expect("active table");
        assert_eq!(s, seq, "head axis {slot}");
        let enc = table::encode(&stored[k], &map, seq).expect("encode");
        let back = table::encode(&t, &map, seq).expect("encode the active table");
        assert_eq!(back.registers(), enc.registers(), "head axis {slot}");
    }
    // The last publish is what the staging area holds: register for register.
    let enc = table::encode(&stored[2], &map, 3).expect("encode");
    let holding = plc.holding();
    for (a, r) in enc.registers() {
        assert_eq!(holding[a as usize], r, "register {a}");
    }
    let c = rig.twin.plant.compensation();
    let dy = c.dy.as_ref().expect("dy compensation");
    assert_eq!(dy.positions_mm, stored[0].positions());
    for (k, (c, e)) in dy.up_mm.iter().zip(&stored[0].values_mm).enumerate() {
        assert!((c + e).abs() <= 0.5e-4 + 1e-12, "point {k}: {c} vs −{e}");
    }
    assert!(c.dx.is_some() && c.dz.is_some());

    // The status reads the PLC back and compares its CRC with the store's.
    let st: StatusView =
        serde_json::from_value(rig.request(Request::TableStatus).await.expect("status"))
            .expect("status view");
    assert_eq!(
        (st.verdict.as_str(), st.table_id),
        ("matches", Some(tables[2].id)),
        "{}",
        st.message
    );
    assert!(st.message.contains("CRC"), "{}", st.message);
    // It carries the values read back, and the list the stored ones, for a per-point diff.
    let staged = st.staged.as_ref().expect("staging area read back");
    assert_eq!(staged.values_um.len(), tables[2].points);
    assert_eq!(tables[2].values_um.len(), tables[2].points);
    for (k, (plc_um, e)) in staged
        .values_um
        .iter()
        .zip(&stored[2].values_mm)
        .enumerate()
    {
        assert!(
            (plc_um - e * 1e3).abs() <= 0.05 + 1e-9,
            "point {k}: {plc_um} vs {e} mm"
        );
        assert!((tables[2].values_um[k] - e * 1e3).abs() < 1e-9, "point {k}");
    }

    // A PLC that rejects: recorded as rejected, its active table and the status unchanged.
    plc.reject_next(9);
    let p: PublishView = publish_by_api(&rig, pos.id).await;
    assert_eq!(
        (p.result.as_str(), p.code, p.sequence),
        ("rejected", Some(9), 4),
        "{p:?}"
    );
    assert!(
        p.message.contains("cannot take a table now"),
        "{}",
        p.message
    );
    assert_eq!(plc.active_tables()[1].as_ref().map(|a| a.0), Some(1));
    assert_eq!(plc.status().active_sequence, 3);
    let last = store.publications(None).expect("publications");
    assert_eq!(last.len(), 4);
    assert_eq!(
        last[3].publication.outcome,
        PublicationOutcome::Rejected {
            code: Some(9),
            text: "the PLC cannot take a table now".into()
        }
    );
    let st: StatusView =
        serde_json::from_value(rig.request(Request::TableStatus).await.expect("status"))
            .expect("status view");
    assert_eq!(
        (st.verdict.as_str(), st.table_id),
        ("matches", Some(tables[2].id)),
        "{}",
        st.message
    );

    // The list shows each table's latest publication; the audit log who published.
    let v = rig
        .request(Request::TableList { limit: None })
        .await
        .expect("list");
    let listed: Vec<TableView> = serde_json::from_value(v["tables"].clone()).expect("list");
    let pos_listed = listed.iter().find(|t| t.id == pos.id).expect("listed");
    let lp = pos_listed.last_publication.as_ref().expect("publication");
    assert_eq!((lp.result.as_str(), lp.sequence), ("rejected", 4));
    let audit = store.audit_entries(50).expect("audit");
    let publishes = audit
        .iter()
        .filter(|a| a.entry.action == "table_publish")
        .count();
    assert_eq!(publishes, 5, "{audit:?}");
    assert!(audit.iter().any(|a| a.entry.action == "table_generate"));

    // The CLI against the running service: the status, and a refused request (exit 2).
    let socket = rig.socket.display().to_string();
    let o = tokio::task::spawn_blocking(move || {
        (
            run(&["table", "status", "--socket", &socket], ""),
            run(
                &["table", "generate", "--run", "999", "--socket", &socket],
                "",
            ),
        )
    })
    .await
    .expect("cli");
    assert_eq!(o.0.status.code(), Some(0), "{}", stderr(&o.0));
    assert!(
        stdout(&o.0).contains(&format!("matches table {}", tables[2].id)),
        "{}",
        stdout(&o.0)
    );
    assert_eq!(o.1.status.code(), Some(2), "{}", stderr(&o.1));
    assert!(
        stderr(&o.1).contains("run 999 is not in the store"),
        "{}",
        stderr(&o.1)
    );
    rig.stop().await;
}

/// Pull only (`[plc] pull = true`, push off): `table_publish` serves the table on the pull
/// server, the twin's PLC pulls it, applies it and acknowledges; the reply and the status come
/// from that acknowledgement.
#[tokio::test(start_paused = true)]
async fn the_service_serves_a_published_table_for_pull() {
    use axiscomp::service::api::Request;
    use axiscomp::service::tables::{PublishView, StatusView, TableView};
    let port = free_port();
    let rig = ServiceRig::start(RigOptions {
        service_toml: format!(
            "[plc]\npull = true\npull_bind = \"127.0.0.1:{port}\"\nstraightness = false\n"
        ),
        ..RigOptions::default()
    })
    .await;
    let run_id = store_synthetic_run(&rig.store, &rig.twin.plant);
    let v = rig
        .request(Request::TableGenerate {
            run_id,
            residual_only: false,
        })
        .await
        .expect("generate");
    let tables: Vec<TableView> = serde_json::from_value(v["tables"].clone()).expect("tables");
    assert_eq!(tables.len(), 1, "{v:#}");
    let client = spawn_pull_client(
        axiscomp_link(format!("127.0.0.1:{port}").parse().expect("addr")),
        axiscomp::plc::CncMap::generic().expect("map"),
        rig.twin.plant.clone(),
        PullClientConfig::default(),
    );
    let p: PublishView = publish_by_api(&rig, tables[0].id).await;
    assert_eq!((p.result.as_str(), p.sequence), ("committed", 1), "{p:?}");
    assert!(p.target.contains("pulled from"), "{}", p.target);
    assert!(rig.twin.plant.compensation().dy.is_some());
    assert_eq!(client.state().commits.len(), 1);
    let st: StatusView =
        serde_json::from_value(rig.request(Request::TableStatus).await.expect("status"))
            .expect("status view");
    assert_eq!(
        (st.verdict.as_str(), st.table_id),
        ("matches", Some(tables[0].id)),
        "{}",
        st.message
    );
    drop(client);
    rig.stop().await;
}

/// `table_publish` with confirm through the control API, its reply decoded.
async fn publish_by_api(
    rig: &crate::helpers::ServiceRig,
    table_id: i64,
) -> axiscomp::service::tables::PublishView {
    use axiscomp::service::api::Request;
    serde_json::from_value(
        rig.request(Request::TablePublish {
            table_id,
            confirm: true,
        })
        .await
        .expect("publish"),
    )
    .expect("publish view")
}
