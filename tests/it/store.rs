//! The store survives a real crash: a writer process is killed with SIGKILL in the middle of
//! storing captures, and every capture it reported as committed is there, exactly once, in a
//! sound file. A reader in another connection sees each commit while the writer goes on (WAL).
//!
//! The writer is this test binary itself, re-run with `WRITER_ENV` set so that only
//! `crash_writer_child` runs and it does the writing (no helper binary).

use crate::helpers::TempDir;
use axiscomp::run::{Capture, Direction, TargetKey};
use axiscomp::store::{NewRun, RunId, Store};
use axiscomp::units::Errors6;
use std::collections::BTreeSet;
use std::io::{BufRead, BufReader};
use std::os::unix::process::ExitStatusExt;
use std::process::{Child, Command, Stdio};

/// Set in the child: the database path and the run id, separated by a newline.
const WRITER_ENV: &str = "AXISCOMP_IT_STORE_WRITER";
/// The prefix of the child's "this capture is committed" lines.
const COMMITTED: &str = "committed ";
/// Targets per run in the writer's sequence.
const TARGETS: u32 = 1000;

/// The i-th capture the writer stores: runs 1.., targets 0..TARGETS, both directions.
fn nth_capture(i: u32) -> Capture {
    let run = 1 + i / (2 * TARGETS);
    let target_index = (i / 2) % TARGETS;
    let direction = if i.is_multiple_of(2) {
        Direction::Up
    } else {
        Direction::Down
    };
    let x = f64::from(i);
    Capture {
        run,
        target_index,
        target_mm: 0.5 * f64::from(target_index),
        direction,
        errors: Errors6::from_array([1e-3 * x, -1e-4 * x, 1e-5, 1e-6 * x, 2e-7, -3e-7]),
        frame_sd: Errors6::from_array([1e-4, 1e-4, 1e-4, 1e-7, 1e-7, 1e-7]),
        u: Errors6::from_array([1e-5; 6]),
        frames: 100 + i,
        material_c: Some(20.0 + 1e-3 * x),
        air_c: None,
        unix_us: 1_700_000_000_000_000 + i64::from(i),
    }
}

fn key_line(k: &TargetKey) -> String {
    format!(
        "{COMMITTED}{} {} {}",
        k.run,
        k.target_index,
        k.direction.sign()
    )
}

/// The key in a "committed" line. The harness may have printed "test … ... " without a newline
/// just before the first one, so the marker is looked for anywhere in the line.
fn parse_key(line: &str) -> Option<TargetKey> {
    let mut f = line.split_once(COMMITTED)?.1.split(' ');
    let run = f.next()?.parse().ok()?;
    let target_index = f.next()?.parse().ok()?;
    let direction = match f.next()? {
        "+" => Direction::Up,
        "-" => Direction::Down,
        _ => return None,
    };
    Some(TargetKey {
        run,
        target_index,
        direction,
    })
}

/// The writer: a no-op in a normal test run; in the child, store captures one after the other
/// and print each key once `insert_capture` has returned (committed), until killed.
#[test]
fn crash_writer_child() {
    let Ok(spec) = std::env::var(WRITER_ENV) else {
        return;
    };
    let (path, run) = spec.split_once('\n').expect("path and run id");
    let run = RunId(run.parse().expect("run id"));
    let mut store = Store::open(path).expect("writer opens the store");
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    // Bounded, so an orphaned child ends by itself; the parent kills it long before.
    for i in 0..20 * TARGETS {
        let c = nth_capture(i);
        assert!(store.insert_capture(run, &c).expect("insert"));
        writeln!(out, "{}", key_line(&TargetKey::of(&c))).expect("parent reads");
        out.flush().expect("parent reads");
    }
}

/// Kills the child on drop, so a failing assertion does not leave it running.
struct KillOnDrop(Child);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn spawn_writer(path: &std::path::Path, run: RunId) -> KillOnDrop {
    let exe = std::env::current_exe().expect("test binary");
    let child = Command::new(exe)
        .args([
            "store::crash_writer_child",
            "--exact",
            "--nocapture",
            "--test-threads=1",
        ])
        .env(WRITER_ENV, format!("{}\n{}", path.display(), run.0))
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("spawn the writer");
    KillOnDrop(child)
}

#[test]
fn captures_survive_sigkill_of_the_writer() {
    let dir = TempDir::new("store-crash");
    let path = dir.path("store.sqlite");
    let run = {
        let mut store = Store::open(&path).unwrap();
        store
            .create_run(&NewRun {
                axis: "Y".into(),
                plan: serde_json::json!({"targets": TARGETS}),
                config: serde_json::json!({}),
                calibration: None,
                notes: String::new(),
            })
            .unwrap()
    };

    let mut child = spawn_writer(&path, run);
    let stdout = child.0.stdout.take().expect("child stdout");
    let mut lines = BufReader::new(stdout).lines();
    let mut printed: Vec<TargetKey> = Vec::new();
    let mut reader: Option<Store> = None;
    // Vary the moment between runs without a random source: some kills land after SQLite's
    // first automatic checkpoint (about 1000 WAL pages, some 470 captures), some before.
    let kill_after = 200 + (std::process::id() as usize % 600);

    while printed.len() < kill_after {
        let line = lines
            .next()
            .expect("the writer stopped before it was killed")
            .expect("read the writer's output");
        let Some(key) = parse_key(&line) else {
            continue; // the test harness's own lines
        };
        printed.push(key);
        if printed.len() == 20 {
            // A second connection while the writer is busy (WAL: it neither blocks nor is blocked).
            reader = Some(Store::open_read_only(&path).unwrap());
        }
        if let Some(r) = &reader
            && printed.len().is_multiple_of(10)
        {
            let seen = r.completed_keys(run).unwrap();
            assert!(
                seen.contains(&key),
                "{key:?} was reported committed but a reader does not see it"
            );
            assert!(seen.len() >= printed.len());
        }
    }

    // SIGKILL while it is inserting (it never pauses between captures).
    child.0.kill().unwrap();
    let status = child.0.wait().unwrap();
    assert_eq!(status.signal(), Some(libc::SIGKILL), "killed, not exited");
    // Lines written before the kill but not yet read are committed captures too.
    for line in lines {
        if let Some(key) = parse_key(&line.unwrap()) {
            printed.push(key);
        }
    }
    drop(reader);
    assert!(printed.len() >= kill_after);
    // The writer never closed the file: its commits are in the WAL, to be recovered on open.
    let wal = std::fs::metadata(dir.path("store.sqlite-wal")).map_or(0, |m| m.len());
    assert!(wal > 0, "the killed writer left its write-ahead log");

    let mut store = Store::open(&path).unwrap();
    assert_eq!(store.integrity_check().unwrap(), ["ok"]);
    let stored = store.captures(run).unwrap();
    eprintln!(
        "killed after {} printed keys; WAL {wal} bytes; {} captures recovered",
        printed.len(),
        stored.len()
    );
    let keys = store.completed_keys(run).unwrap();
    // Exactly once: no duplicate keys among the rows.
    assert_eq!(keys.len(), stored.len());
    // Every printed key is there, with the values the writer gave it, in order; at most the one
    // capture in flight at the kill was committed without being printed.
    assert!(
        stored.len() == printed.len() || stored.len() == printed.len() + 1,
        "{} stored, {} printed",
        stored.len(),
        printed.len()
    );
    for (i, key) in printed.iter().enumerate() {
        assert_eq!(TargetKey::of(&stored[i]), *key);
        assert_eq!(stored[i], nth_capture(i as u32));
    }
    let printed_set: BTreeSet<_> = printed.iter().copied().collect();
    assert!(printed_set.is_subset(&keys));
    // Offered again after the restart, they are not stored twice; the next one is.
    for i in 0..printed.len() as u32 {
        assert!(!store.insert_capture(run, &nth_capture(i)).unwrap());
    }
    let next = nth_capture(stored.len() as u32);
    assert!(!keys.contains(&TargetKey::of(&next)));
    assert!(store.insert_capture(run, &next).unwrap());
    assert_eq!(store.captures(run).unwrap().len(), stored.len() + 1);
    assert_eq!(store.integrity_check().unwrap(), ["ok"]);
}

#[test]
fn a_reader_thread_sees_commits_while_another_connection_writes() {
    let dir = TempDir::new("store-wal");
    let path = dir.path("store.sqlite");
    let run = {
        let mut store = Store::open(&path).unwrap();
        store
            .create_run(&NewRun {
                axis: "X".into(),
                plan: serde_json::json!({}),
                config: serde_json::json!({}),
                calibration: None,
                notes: String::new(),
            })
            .unwrap()
    };
    let n = 200u32;
    let done = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let reader = {
        let path = path.clone();
        let done = done.clone();
        std::thread::spawn(move || {
            let r = Store::open_read_only(&path).unwrap();
            let mut last = 0;
            let mut reads = 0u32;
            loop {
                let finished = done.load(std::sync::atomic::Ordering::Acquire);
                let now = r.captures(run).unwrap();
                // A snapshot is a prefix of the writing order: never partial, never shrinking.
                assert!(now.len() >= last);
                for (i, c) in now.iter().enumerate() {
                    assert_eq!(*c, nth_capture(i as u32));
                }
                last = now.len();
                reads += 1;
                if finished {
                    return (last, reads);
                }
            }
        })
    };
    let mut writer = Store::open(&path).unwrap();
    for i in 0..n {
        assert!(writer.insert_capture(run, &nth_capture(i)).unwrap());
    }
    done.store(true, std::sync::atomic::Ordering::Release);
    let (last, reads) = reader.join().unwrap();
    assert_eq!(last, n as usize, "the final read sees every commit");
    assert!(reads >= 1);
}
