//! Fuzzing on stable Rust (issue 18): proptest feeds arbitrary bytes and mutations of seed
//! inputs (literal frames from the specifications and the shipped files) to every decoder:
//! Modbus replies (the paced client's own decoder and tokio-modbus behind the link) and
//! requests (our server, the twin's I/O module and PLC, the pull server, over TCP), register
//! codecs, cannelloni and python-can msgpack datagrams, CANopen frames (SDO client, heartbeat
//! consumer, EMCY, TPDO, the whole master), control-API lines, the configuration, I/O and CNC
//! maps, pose and deviation CSVs, calibration TOML and the twin CNC's G-code; the twin's
//! configuration, ISO plans, the self-calibration's spec and hexapod plan CSVs.
//!
//! Numbers at the edges: a mutation replaces a number of a seed with one of
//! [`EXTREME_NUMBERS`] (±0, subnormals, 1e±300, ±inf, nan, the integer extremes), so every
//! numeric key, field and column meets them; the structured targets draw their numbers from
//! [`extreme_f64`] and [`extreme_u64`]. A number out of range must be refused by name, never
//! reach a `Duration`, an allocation or a loop.
//!
//! Each target checks: no panic (proptest catches it and shrinks the input), no unbounded
//! allocation (a counting allocator bounds the peak bytes a decode may allocate by its input's
//! size), and for text inputs an error that names the input (its file or label).
//!
//! Plain `cargo test` runs about 20,000 cases in all (3,000 for the biggest targets, fewer for
//! the slow ones) with a fixed seed. `PROPTEST_CASES` sets the budget of the biggest targets
//! and the others scale with it (the link target gets a tenth); `PROPTEST_RNG_SEED` sets the
//! seed. `.ci/run` runs a long budget.

use crate::helpers::{TempDir, run};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngSeed, TestCaseError, TestRunner};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::OnceLock;
use std::time::Duration;

// ---------- a counting allocator: the peak bytes live on this thread ----------

struct Counting;

thread_local! {
    static LIVE: Cell<usize> = const { Cell::new(0) };
    static PEAK: Cell<usize> = const { Cell::new(0) };
}

fn grew(n: usize) {
    let _ = LIVE.try_with(|l| {
        let v = l.get().saturating_add(n);
        l.set(v);
        let _ = PEAK.try_with(|p| p.set(p.get().max(v)));
    });
}

fn shrank(n: usize) {
    let _ = LIVE.try_with(|l| l.set(l.get().saturating_sub(n)));
}

// SAFETY: every call is forwarded to the system allocator unchanged; the counters are
// thread-local cells without destructors, touched through `try_with`.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded as is.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            grew(layout.size());
        }
        p
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded as is.
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            grew(layout.size());
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        shrank(layout.size());
        // SAFETY: forwarded as is.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: forwarded as is.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            shrank(layout.size());
            grew(new_size);
        }
        p
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// Run `f` and return its result with the peak bytes it had allocated at once (this thread).
fn peak_of<R>(f: impl FnOnce() -> R) -> (R, usize) {
    let base = LIVE.with(Cell::get);
    PEAK.with(|p| p.set(base));
    let r = f();
    (r, PEAK.with(Cell::get).saturating_sub(base))
}

/// The allocation a decoder may make for `len` bytes of input: proportional to it, plus a
/// fixed allowance (a 4 GB `Vec::with_capacity` from a length field fails this by far).
fn alloc_bound(len: usize, per_byte: usize) -> usize {
    (1 << 20) + per_byte * len
}

fn check_alloc(what: &str, peak: usize, len: usize, per_byte: usize) -> Result<(), TestCaseError> {
    prop_assert!(
        peak <= alloc_bound(len, per_byte),
        "{what}: {peak} bytes allocated for {len} bytes of input"
    );
    Ok(())
}

// ---------- the runner and the mutator ----------

/// The default cases of the biggest targets, which `PROPTEST_CASES` replaces.
const FULL: u32 = 3000;

/// Cases per target: `default_cases`, scaled by `PROPTEST_CASES` / [`FULL`] when that is
/// set; the seed `PROPTEST_RNG_SEED`, or 18.
fn fuzz<S: Strategy>(
    name: &str,
    default_cases: u32,
    strategy: S,
    test: impl Fn(S::Value) -> Result<(), TestCaseError>,
) {
    let mut config = Config {
        failure_persistence: None,
        max_shrink_iters: 2000,
        ..Config::default()
    };
    config.cases = match std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse::<u64>().ok())
    {
        Some(budget) => (budget * u64::from(default_cases) / u64::from(FULL)).max(1) as u32,
        None => default_cases,
    };
    if std::env::var_os("PROPTEST_RNG_SEED").is_none() {
        config.rng_seed = RngSeed::Fixed(18);
    }
    let cases = config.cases;
    let t0 = axiscomp::util::clock::now();
    let mut runner = TestRunner::new(config);
    if let Err(e) = runner.run(&strategy, test) {
        panic!("fuzz target {name}: {e}");
    }
    eprintln!(
        "fuzz {name}: {cases} cases in {:.1} s",
        axiscomp::util::clock::since(t0).as_secs_f64()
    );
}

/// One edit of a seed. Positions are taken modulo the length at that point.
#[derive(Clone, Debug)]
enum Edit {
    Flip(usize, u8),
    Set(usize, u8),
    Insert(usize, Vec<u8>),
    Delete(usize, usize),
    Duplicate(usize, usize),
    Token(usize, usize),
    Truncate(usize),
    /// The n-th number of the text (modulo their count) replaced by an extreme one.
    Number(usize, usize),
}

/// Numbers at the edges of every range: zeros of both signs, subnormals, the smallest
/// normal, 1e±300, the largest finite, infinities and NaN as TOML, JSON and CSV write them,
/// and the integer types' extremes.
const EXTREME_NUMBERS: &[&str] = &[
    "0",
    "-0",
    "0.0",
    "-0.0",
    "5e-324",
    "-5e-324",
    "2.2250738585072014e-308",
    "1e-300",
    "-1e-300",
    "1e300",
    "-1e300",
    "1.7976931348623157e308",
    "-1.7976931348623157e308",
    "inf",
    "-inf",
    "+inf",
    "nan",
    "-nan",
    "NaN",
    "-1",
    "65535",
    "4294967295",
    "9223372036854775807",
    "-9223372036854775808",
    "18446744073709551615",
];

/// The extremes as floats, and any float, for the structured targets.
fn extreme_f64() -> impl Strategy<Value = f64> {
    prop_oneof![
        3 => proptest::sample::select(
            EXTREME_NUMBERS
                .iter()
                .filter_map(|s| s.parse::<f64>().ok())
                .collect::<Vec<_>>()
        ),
        1 => any::<f64>(),
        2 => -2000.0..2000.0f64,
    ]
}

/// Integer extremes, and small counts, for the structured targets.
fn extreme_u64() -> impl Strategy<Value = u64> {
    prop_oneof![
        Just(0),
        Just(1),
        Just(u64::from(u32::MAX)),
        Just(i64::MAX as u64),
        Just(u64::MAX),
        0..2000u64,
    ]
}

/// Where the numbers of `v` are: runs of digits (with a sign, a point, an exponent) that do
/// not continue a name (`X1_um`, `u32`), outside `#` comments.
fn number_spans(v: &[u8]) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < v.len() {
        let word = |b: u8| b.is_ascii_alphanumeric() || b == b'_';
        if v[i] == b'#' {
            while i < v.len() && v[i] != b'\n' {
                i += 1;
            }
        } else if v[i].is_ascii_digit() && (i == 0 || !word(v[i - 1])) {
            let start = if i > 0 && v[i - 1] == b'-' { i - 1 } else { i };
            let mut end = i;
            while end < v.len()
                && (v[end].is_ascii_digit()
                    || v[end] == b'.'
                    || ((v[end] == b'e' || v[end] == b'E') && end > i)
                    || ((v[end] == b'-' || v[end] == b'+') && matches!(v[end - 1], b'e' | b'E')))
            {
                end += 1;
            }
            out.push((start, end));
            i = end;
        } else {
            i += 1;
        }
    }
    out
}

/// Tokens that move parsers into their edge cases.
const TOKENS: &[&str] = &[
    "\n",
    ",",
    "=",
    "\"",
    "[",
    "]",
    "{",
    "}",
    ":",
    "#",
    "-",
    "+",
    ".",
    "0",
    "-1",
    "65535",
    "65536",
    "4294967296",
    "1e308",
    "-1e308",
    "nan",
    "inf",
    "NaN",
    "1e-320",
    "18446744073709551616",
    "true",
    "[[",
    "]]",
    "\\u0000",
    "\u{FEFF}",
    "é",
    "\r\n",
    "  ",
    "G1",
    "X",
    "Y",
    "Z",
    "F",
    "%",
    "(",
    ")",
    ";",
    "M2",
    "M30",
    "G4 P",
    "O",
    "N",
    "\t",
    "\0",
    "\u{7F}",
    "\u{FFFD}",
];

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        (any::<usize>(), 0u8..8).prop_map(|(p, b)| Edit::Flip(p, b)),
        (
            any::<usize>(),
            prop_oneof![
                Just(0u8),
                Just(0xFF),
                Just(0x7F),
                Just(0x80),
                Just(0x01),
                any::<u8>()
            ]
        )
            .prop_map(|(p, b)| Edit::Set(p, b)),
        (any::<usize>(), prop::collection::vec(any::<u8>(), 1..16))
            .prop_map(|(p, v)| Edit::Insert(p, v)),
        (any::<usize>(), 1usize..32).prop_map(|(p, n)| Edit::Delete(p, n)),
        (any::<usize>(), 1usize..64).prop_map(|(p, n)| Edit::Duplicate(p, n)),
        (any::<usize>(), 0..TOKENS.len()).prop_map(|(p, k)| Edit::Token(p, k)),
        any::<usize>().prop_map(Edit::Truncate),
        (any::<usize>(), 0..EXTREME_NUMBERS.len()).prop_map(|(p, k)| Edit::Number(p, k)),
        (any::<usize>(), 0..EXTREME_NUMBERS.len()).prop_map(|(p, k)| Edit::Number(p, k)),
    ]
}

fn apply(seed: &[u8], edits: &[Edit]) -> Vec<u8> {
    let mut v = seed.to_vec();
    for e in edits {
        let at = |p: usize, len: usize| if len == 0 { 0 } else { p % (len + 1) };
        match e {
            Edit::Flip(p, b) if !v.is_empty() => {
                let i = p % v.len();
                v[i] ^= 1 << b;
            }
            Edit::Set(p, b) if !v.is_empty() => {
                let i = p % v.len();
                v[i] = *b;
            }
            Edit::Insert(p, bytes) => {
                let i = at(*p, v.len());
                v.splice(i..i, bytes.iter().copied());
            }
            Edit::Delete(p, n) if !v.is_empty() => {
                let i = p % v.len();
                let end = (i + n).min(v.len());
                v.drain(i..end);
            }
            Edit::Duplicate(p, n) if !v.is_empty() => {
                let i = p % v.len();
                let end = (i + n).min(v.len());
                let part: Vec<u8> = v[i..end].to_vec();
                v.splice(end..end, part);
            }
            Edit::Token(p, k) => {
                let i = at(*p, v.len());
                v.splice(i..i, TOKENS[*k].bytes());
            }
            Edit::Truncate(p) => {
                let n = at(*p, v.len());
                v.truncate(n);
            }
            Edit::Number(p, k) => {
                let spans = number_spans(&v);
                if !spans.is_empty() {
                    let (a, b) = spans[p % spans.len()];
                    v.splice(a..b, EXTREME_NUMBERS[*k].bytes());
                }
            }
            _ => {}
        }
    }
    v
}

/// Mutations of the seeds (three in four) and arbitrary bytes (one in four, up to `max`).
fn bytes_from(seeds: Vec<Vec<u8>>, max: usize) -> impl Strategy<Value = Vec<u8>> {
    assert!(!seeds.is_empty());
    let n = seeds.len();
    prop_oneof![
        3 => (0..n, prop::collection::vec(edit(), 0..8))
            .prop_map(move |(k, edits)| apply(&seeds[k], &edits)),
        1 => prop::collection::vec(any::<u8>(), 0..max),
    ]
}

/// A seed whole but for one to three of its numbers, each replaced by an extreme one: every
/// key, field and column of a file meets the extremes with the rest of it valid.
fn numbers_from(seeds: Vec<Vec<u8>>) -> impl Strategy<Value = Vec<u8>> {
    let n = seeds.len();
    let number = (any::<usize>(), 0..EXTREME_NUMBERS.len()).prop_map(|(p, k)| Edit::Number(p, k));
    (0..n, prop::collection::vec(number, 1..4)).prop_map(move |(k, edits)| apply(&seeds[k], &edits))
}

/// Text inputs: mutated seeds taken as UTF-8 (invalid sequences replaced), half of them with
/// extreme numbers only.
fn text_from(seeds: Vec<String>) -> impl Strategy<Value = String> {
    let max = seeds.iter().map(String::len).max().unwrap_or(64);
    let seeds: Vec<Vec<u8>> = seeds.into_iter().map(String::into_bytes).collect();
    prop_oneof![bytes_from(seeds.clone(), max), numbers_from(seeds),]
        .prop_map(|b| String::from_utf8_lossy(&b).into_owned())
}

fn repo_file(path: &str) -> String {
    let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(path);
    std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

fn hex(s: &str) -> Vec<u8> {
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&s[i..i + 2], 16).expect("hex"))
        .collect()
}

// ---------- Modbus ----------

use axiscomp::modbus::paced::decode_read;
use axiscomp::modbus::{ReadRange, RegisterKind, ValueType, WordOrder};

/// Modbus TCP ADUs from the specifications (Application Protocol v1.1b3 §6.3, §6.4, §7;
/// Messaging on TCP/IP Implementation Guide §3.1.3), as requests and replies.
fn modbus_seeds() -> Vec<Vec<u8>> {
    vec![
        // Read input registers 0x006B x3, and its reply (§6.4: 0x000A).
        vec![0x12, 0x34, 0, 0, 0, 6, 7, 4, 0x00, 0x6B, 0x00, 0x03],
        vec![
            0x12, 0x34, 0, 0, 0, 9, 7, 4, 6, 0x02, 0x2B, 0x00, 0x00, 0x00, 0x64,
        ],
        // Read holding registers 108..110 (§6.3) and its reply 0x022B 0x0000 0x0064.
        vec![0, 1, 0, 0, 0, 6, 1, 3, 0x00, 0x6B, 0x00, 0x03],
        vec![
            0, 1, 0, 0, 0, 9, 1, 3, 6, 0x02, 0x2B, 0x00, 0x00, 0x00, 0x64,
        ],
        // Write single register 2 = 0x0003 (§6.6), write multiple 2 registers at 1 (§6.12).
        vec![0, 2, 0, 0, 0, 6, 1, 6, 0x00, 0x01, 0x00, 0x03],
        vec![
            0, 3, 0, 0, 0, 11, 1, 0x10, 0x00, 0x01, 0x00, 0x02, 0x04, 0x00, 0x0A, 0x01, 0x02,
        ],
        // Exception 02 to function 4 (§7), and an MBAP length that lies.
        vec![0x12, 0x34, 0, 0, 0, 3, 7, 0x84, 0x02],
        vec![0, 4, 0, 0, 0xFF, 0xFF, 1, 3, 0, 0, 0, 9],
        // Read 125 holding registers (the most one read may ask for).
        vec![0, 5, 0, 0, 0, 6, 1, 3, 0, 0, 0, 125],
    ]
}

#[test]
fn fuzz_modbus_client_reply_decoder() {
    let range = ReadRange::new(0x6B, 3).expect("range");
    fuzz(
        "modbus paced reply",
        3000,
        bytes_from(modbus_seeds(), 300),
        |buf| {
            for kind in [RegisterKind::Input, RegisterKind::Holding] {
                let (r, peak) = peak_of(|| decode_read(&buf, 0x1234, 7, kind, range));
                check_alloc("decode_read", peak, buf.len(), 4)?;
                match r {
                    Ok(Some(regs)) => prop_assert_eq!(regs.len(), 3, "a reply of the asked size"),
                    Ok(None) => prop_assert!(buf.len() < 260, "incomplete only while short"),
                    Err(e) => prop_assert!(!e.to_string().is_empty()),
                }
            }
            Ok(())
        },
    );
}

#[test]
fn fuzz_register_codecs() {
    let orders = [
        WordOrder::Abcd,
        WordOrder::Cdab,
        WordOrder::Badc,
        WordOrder::Dcba,
    ];
    fuzz(
        "register codecs",
        2000,
        (
            prop::collection::vec(any::<u16>(), 0..4),
            0..ValueType::ALL.len(),
            0..orders.len(),
        ),
        |(regs, t, o)| {
            // The value at the start of the registers: an error only when they are too few,
            // and registers after the value change nothing.
            let (ty, order) = (ValueType::ALL[t], orders[o]);
            let need = ty.words() as usize;
            match axiscomp::modbus::codec::decode(ty, order, &regs) {
                Ok(v) => {
                    prop_assert!(regs.len() >= need);
                    let head = axiscomp::modbus::codec::decode(ty, order, &regs[..need]);
                    prop_assert_eq!(head.map(f64::to_bits), Ok(v.to_bits()));
                }
                Err(e) => {
                    prop_assert!(regs.len() < need);
                    prop_assert!(!e.to_string().is_empty());
                }
            }
            Ok(())
        },
    );
}

/// A raw peer on loopback: write `bytes` on a fresh connection, close the write side, read
/// what comes back until the server closes or 300 ms pass. Whatever the server does with
/// the bytes, it must not answer more than it was asked: bounded.
async fn poke(addr: std::net::SocketAddr, bytes: &[u8]) -> Vec<u8> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let Ok(mut s) = tokio::net::TcpStream::connect(addr).await else {
        return Vec::new();
    };
    let _ = s.write_all(bytes).await;
    let _ = s.shutdown().await;
    let mut out = Vec::new();
    let _ = tokio::time::timeout(Duration::from_millis(300), s.read_to_end(&mut out)).await;
    out
}

/// Whether a Modbus server at `addr` still answers a valid read of `kind` (unit `unit`).
async fn still_serves(addr: std::net::SocketAddr, unit: u8, kind: RegisterKind, start: u16) {
    let link = crate::helpers::link(addr);
    assert!(link.wait_connected(Duration::from_secs(5)).await, "{addr}");
    let r = link
        .read(kind, unit, ReadRange::new(start, 1).expect("range"))
        .await;
    assert!(r.is_ok(), "{addr} serves after the fuzz: {r:?}");
}

/// Mutated and arbitrary ADUs at every Modbus server we run: ours (a register bank), the
/// twin's I/O module, the twin's PLC and the pull server. Each must stay up and in step.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fuzz_modbus_servers_over_tcp() {
    use axiscomp::modbus::{MemoryBank, ServerConfig, ServerHandle};
    use axiscomp::plc::serve::{PullConfig, PullServer};
    use std::sync::Arc;
    let bank = Arc::new(MemoryBank::new(
        (0..200).collect(),
        vec![0; 20],
        Some((10, 5)),
    ));
    let ours = ServerHandle::start(
        ServerConfig::new("127.0.0.1:0".parse().expect("addr")),
        bank,
    )
    .await
    .expect("server");
    let io = crate::helpers::twin(crate::helpers::plant()).await;
    let (plc, _plant) = crate::helpers::twin_plc(crate::helpers::cnc_map("generic.toml")).await;
    let pull = PullServer::start(
        crate::helpers::cnc_map("generic.toml"),
        PullConfig::new("127.0.0.1:0".parse().expect("addr")),
    )
    .await
    .expect("pull server");
    let targets = [
        ("our server", ours.local_addr(), RegisterKind::Input, 0),
        (
            "the twin's I/O module",
            io.local_addr(),
            RegisterKind::Input,
            0,
        ),
        ("the twin's PLC", plc.local_addr(), RegisterKind::Holding, 0),
        (
            "the pull server",
            pull.local_addr(),
            RegisterKind::Holding,
            0,
        ),
    ];
    let handle = tokio::runtime::Handle::current();
    for (name, addr, kind, start) in targets {
        let h = handle.clone();
        let answered = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let counted = answered.clone();
        tokio::task::spawn_blocking(move || {
            fuzz(name, 150, bytes_from(modbus_seeds(), 300), |bytes| {
                let reply = h.block_on(poke(addr, &bytes));
                if !reply.is_empty() {
                    counted.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                }
                // A reply per request at most: 9 + 250 bytes per ADU in the input.
                prop_assert!(
                    reply.len() <= 259 * (bytes.len() / 8 + 1),
                    "{} reply bytes to {} request bytes",
                    reply.len(),
                    bytes.len()
                );
                Ok(())
            });
        })
        .await
        .expect("fuzz task");
        // The mutations keep many requests well-formed: the server answered those.
        let answered = answered.load(std::sync::atomic::Ordering::Relaxed);
        eprintln!("{name}: answered {answered} of the fuzzed connections");
        assert!(answered > 0, "{name} answered none of the fuzzed requests");
        let unit = if name == "the twin's PLC" || name == "the pull server" {
            crate::helpers::cnc_map("generic.toml").unit_id
        } else {
            1
        };
        still_serves(addr, unit, kind, start).await;
    }
}

/// Mutated and arbitrary replies to the link's reads (tokio-modbus's client decoder behind
/// our checks): every read ends in data of the asked size or an error; the link recovers.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fuzz_link_replies() {
    use axiscomp::modbus::{Link, LinkConfig};
    use std::sync::{Arc, Mutex};
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let addr = listener.local_addr().expect("addr");
    // The reply the fake device sends next (its transaction id patched to the request's).
    let next: Arc<Mutex<Vec<u8>>> = Arc::new(Mutex::new(Vec::new()));
    let served = next.clone();
    tokio::spawn(async move {
        loop {
            let Ok((mut s, _)) = listener.accept().await else {
                return;
            };
            let served = served.clone();
            tokio::spawn(async move {
                let mut req = [0u8; 12];
                while s.read_exact(&mut req).await.is_ok() {
                    let mut reply = served.lock().map(|v| v.clone()).unwrap_or_default();
                    if reply.len() >= 2 {
                        reply[..2].copy_from_slice(&req[..2]);
                    }
                    if s.write_all(&reply).await.is_err() {
                        return;
                    }
                }
            });
        }
    });
    let link = Link::spawn(LinkConfig {
        timeout: Duration::from_millis(50),
        backoff_min: Duration::from_millis(1),
        backoff_max: Duration::from_millis(5),
        ..LinkConfig::new(addr)
    });
    let handle = tokio::runtime::Handle::current();
    let l2 = link.clone();
    let n2 = next.clone();
    tokio::task::spawn_blocking(move || {
        fuzz(
            "link replies",
            300,
            bytes_from(modbus_seeds(), 300),
            |reply| {
                *n2.lock().expect("lock") = reply;
                let r = handle.block_on(async {
                    // The link may be reconnecting after the previous case's bad reply.
                    l2.wait_connected(Duration::from_secs(2)).await;
                    l2.read(
                        RegisterKind::Holding,
                        1,
                        ReadRange::new(0x6B, 3).expect("range"),
                    )
                    .await
                });
                match r {
                    Ok(v) => prop_assert_eq!(v.len(), 3),
                    Err(e) => prop_assert!(!e.to_string().is_empty()),
                }
                Ok(())
            },
        );
    })
    .await
    .expect("fuzz task");
    // A good reply again: the link is in step.
    *next.lock().expect("lock") = vec![0, 0, 0, 0, 0, 9, 1, 3, 6, 0x02, 0x2B, 0, 0, 0, 0x64];
    link.wait_connected(Duration::from_secs(2)).await;
    let mut ok = None;
    for _ in 0..5 {
        ok = Some(
            link.read(
                RegisterKind::Holding,
                1,
                ReadRange::new(0x6B, 3).expect("range"),
            )
            .await,
        );
        if matches!(ok, Some(Ok(_))) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(ok, Some(Ok(vec![0x022B, 0, 0x64])));
}

// ---------- CAN transports ----------

/// python-can 4.6.1 `pack_message` datagrams (the literal hex of src/can/pycan.rs's tests).
const PY_STD: &str = "8ba974696d657374616d70cb41d954fc40100000ae6172626974726174696f6e5f6964cd0181ae69735f657874656e6465645f6964c2af69735f72656d6f74655f6672616d65c2ae69735f6572726f725f6672616d65c2a76368616e6e656cc0a3646c6308a464617461c4080102030405060708a569735f6664c2ae626974726174655f737769746368c2b56572726f725f73746174655f696e64696361746f72c2";
const PY_EXT: &str = "8ba974696d657374616d70cb3fe0000000000000ae6172626974726174696f6e5f6964ce1abcdef0ae69735f657874656e6465645f6964c3af69735f72656d6f74655f6672616d65c2ae69735f6572726f725f6672616d65c2a76368616e6e656cc0a3646c6301a464617461c401ffa569735f6664c2ae626974726174655f737769746368c2b56572726f725f73746174655f696e64696361746f72c2";
const PY_REORDERED: &str = "86a464617461c4021020a7782d6578747261920181a16bc0a3646c6302ae6172626974726174696f6e5f6964cd07ffae69735f657874656e6465645f6964c2a974696d657374616d7007";

#[test]
fn fuzz_python_can_msgpack() {
    let mut seeds = vec![hex(PY_STD), hex(PY_EXT), hex(PY_REORDERED)];
    // Containers whose headers claim 2^32 - 1 elements or bytes.
    seeds.push(vec![0xdd, 0xff, 0xff, 0xff, 0xff]);
    seeds.push(vec![0xdf, 0xff, 0xff, 0xff, 0xff, 0xa1, b'a']);
    seeds.push(vec![0xc6, 0xff, 0xff, 0xff, 0xff, 0]);
    fuzz("python-can msgpack", 3000, bytes_from(seeds, 400), |buf| {
        let (r, peak) = peak_of(|| axiscomp::can::pycan::decode_message(&buf));
        check_alloc("pycan::decode_message", peak, buf.len(), 64)?;
        if let Err(e) = r {
            let m = e.to_string();
            prop_assert!(m.starts_with("malformed CAN datagram: "), "{}", m);
        }
        let (r, peak) = peak_of(|| axiscomp::can::msgpack::decode(&buf).map(|_| ()));
        check_alloc("msgpack::decode", peak, buf.len(), 64)?;
        if let Err(e) = r {
            let m = e.to_string();
            prop_assert!(m.starts_with("malformed CAN datagram: "), "{}", m);
        }
        Ok(())
    });
}

#[test]
fn fuzz_cannelloni_datagrams() {
    use axiscomp::can::cannelloni::wire::Packet;
    let seeds = vec![
        // The v2 DATA datagram of one frame 0x123 [DE AD BE EF] (cannelloni's format).
        vec![
            0x02, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x01, 0x23, 0x04, 0xDE, 0xAD, 0xBE, 0xEF,
        ],
        // Three records: extended 0x1ABCDEF0 [11], RTR 0x701 len 1, empty 0x000.
        vec![
            0x02, 0x00, 0x05, 0x00, 0x03, 0x9A, 0xBC, 0xDE, 0xF0, 0x01, 0x11, 0x40, 0x00, 0x07,
            0x01, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00,
        ],
        // A CAN FD record (length bit 0x80, flags byte) and a count that lies.
        vec![
            0x02, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x01, 0x23, 0x8C, 0x01, 0, 1, 2, 3, 4, 5, 6,
            7, 8, 9, 10, 11,
        ],
        vec![0x02, 0x00, 0x00, 0xFF, 0xFF, 0x00, 0x00, 0x01, 0x23, 0x00],
    ];
    fuzz("cannelloni", 3000, bytes_from(seeds, 300), |buf| {
        let (r, peak) = peak_of(|| match Packet::new_checked(&buf[..]) {
            Ok(p) => {
                let mut frames = 0usize;
                for rec in p.records() {
                    if let Ok(Some(_)) = rec.to_frame() {
                        frames += 1;
                    }
                }
                Ok(frames)
            }
            Err(e) => Err(e.to_string()),
        });
        check_alloc("cannelloni", peak, buf.len(), 16)?;
        match r {
            // At least 5 bytes of record per frame after the 5-byte header.
            Ok(n) => prop_assert!(n * 5 + 5 <= buf.len().max(5)),
            Err(e) => prop_assert!(e.contains("cannelloni"), "{e}"),
        }
        Ok(())
    });
}

// ---------- CANopen ----------

use axiscomp::can::CanFrame;

/// Frames from CiA 301 for node 1: SDO responses (expedited upload of 0x1000 = 0x00020192,
/// download acknowledge, segmented upload initiate and segment, abort 0x06020000), EMCY
/// 0x2310 (current at device output), heartbeat operational and boot-up, TPDO1.
fn canopen_seeds() -> Vec<Vec<u8>> {
    let f = |id: u16, d: &[u8]| {
        let mut v = id.to_be_bytes().to_vec();
        v.push(d.len() as u8);
        v.extend_from_slice(d);
        v
    };
    vec![
        f(0x581, &[0x43, 0x00, 0x10, 0x00, 0x92, 0x01, 0x02, 0x00]),
        f(0x581, &[0x60, 0x17, 0x10, 0x00, 0, 0, 0, 0]),
        f(0x581, &[0x41, 0x08, 0x10, 0x00, 0x40, 0, 0, 0]),
        f(0x581, &[0x00, b'a', b'x', b'i', b's', b'c', b'o', b'm']),
        f(0x581, &[0x80, 0x00, 0x10, 0x00, 0x00, 0x00, 0x02, 0x06]),
        f(0x081, &[0x10, 0x23, 0x02, 0, 0, 0, 0, 0]),
        f(0x701, &[0x05]),
        f(0x701, &[0x00]),
        f(0x181, &[0x37, 0x06, 0x10, 0x27, 0, 0]),
    ]
}

/// A sequence of frames: each encoded as id (2 bytes, big-endian), length, data.
fn frames_of(bytes: &[u8]) -> Vec<CanFrame> {
    let mut out = Vec::new();
    let mut rest = bytes;
    while rest.len() >= 3 {
        let id = u16::from_be_bytes([rest[0], rest[1]]) & 0x7FF;
        let len = (rest[2] as usize % 9).min(rest.len() - 3);
        if let Some(f) = CanFrame::new(id, &rest[3..3 + len]) {
            out.push(f);
        }
        rest = &rest[3 + len..];
    }
    out
}

fn canopen_frames() -> impl Strategy<Value = Vec<CanFrame>> {
    let seeds = canopen_seeds();
    let joined: Vec<Vec<u8>> = (0..seeds.len())
        .map(|k| {
            seeds[k..]
                .iter()
                .chain(&seeds[..k])
                .flatten()
                .copied()
                .collect()
        })
        .collect();
    bytes_from(joined, 200).prop_map(|b| frames_of(&b))
}

#[test]
fn fuzz_canopen_frames() {
    use axiscomp::canopen::nmt::HeartbeatConsumer;
    use axiscomp::canopen::{Command, DriveConfig, Emcy, Master, NodeId, ObjAddr, SdoClient};
    let node = NodeId::new(1).expect("node");
    fuzz("canopen", 1500, canopen_frames(), |frames| {
        let t0 = axiscomp::util::clock::now();
        let mut now = t0;
        // The SDO client mid-upload and mid-download.
        for download in [false, true] {
            let mut sdo = SdoClient::new(node, Duration::from_millis(100));
            let obj = ObjAddr {
                index: 0x1008,
                sub: 0,
            };
            if download {
                sdo.download(obj, vec![1, 2, 3, 4, 5, 6, 7, 8, 9, 10], now)
            } else {
                sdo.upload(obj, now)
            }
            .map_err(|e| TestCaseError::fail(e.to_string()))?;
            let (_, peak) = peak_of(|| {
                for f in &frames {
                    now += Duration::from_millis(1);
                    sdo.handle_frame(f, now);
                    while sdo.poll_transmit().is_some() {}
                    while sdo.poll_outcome().is_some() {}
                }
            });
            check_alloc("SDO client", peak, frames.len() * 8, 256)?;
        }
        // The heartbeat consumer, EMCY and TPDO1 decoders.
        let mut hb = HeartbeatConsumer::new(node, Duration::from_millis(350));
        for f in &frames {
            now += Duration::from_millis(1);
            hb.handle_frame(f, now);
            let _ = Emcy::decode(f.data()).map(|e| e.to_string());
            let _ = axiscomp::canopen::pdo::decode_tpdo1(f.data());
        }
        // The whole master, idle and configuring.
        for configure in [false, true] {
            let mut m = Master::new(&DriveConfig::default())
                .map_err(|e| TestCaseError::fail(e.to_string()))?;
            if configure {
                m.submit(Command::Configure, now);
            }
            for f in &frames {
                now += Duration::from_millis(2);
                m.handle_frame(f, now);
                m.handle_timeout(now);
                while m.poll_transmit().is_some() {}
                while m.poll_event().is_some() {}
            }
        }
        Ok(())
    });
}

// ---------- text inputs: configuration, maps, CSVs, calibration, G-code, control lines ----------

/// Check a parse result of a text input labelled `label`: an error names it.
fn names_input<T, E: std::fmt::Display>(r: Result<T, E>, label: &str) -> Result<(), TestCaseError> {
    if let Err(e) = r {
        let m = e.to_string();
        prop_assert!(m.contains(label), "the error does not name {label}: {m}");
    }
    Ok(())
}

#[test]
fn fuzz_io_maps_and_blocks() {
    let seeds: Vec<String> = [
        "generic.toml",
        "beckhoff-bk9000-kl3404.toml",
        "wago-750-352-750-456.toml",
    ]
    .iter()
    .map(|f| repo_file(&format!("plc-maps/io/{f}")))
    .collect();
    fuzz(
        "I/O maps",
        600,
        (
            text_from(seeds),
            prop::collection::vec(any::<u16>(), 0..130),
        ),
        |(text, regs)| {
            let (r, peak) = peak_of(|| axiscomp::acquire::IoMap::parse(&text, "fuzz-io.toml"));
            check_alloc("IoMap::parse", peak, text.len(), 512)?;
            match r {
                Ok(map) => {
                    // Any block of the right length decodes or says why not; others fail.
                    let n = map.block.count() as usize;
                    let mut block = regs.clone();
                    block.resize(n, 0x8000);
                    let _ = axiscomp::acquire::decode::decode(&map, &block);
                    if regs.len() != n {
                        prop_assert!(axiscomp::acquire::decode::decode(&map, &regs).is_err());
                    }
                }
                Err(e) => names_input(Err::<(), _>(e), "fuzz-io.toml")?,
            }
            Ok(())
        },
    );
}

#[test]
fn fuzz_cnc_maps() {
    let seeds: Vec<String> = [
        "generic.toml",
        "beckhoff-twincat.toml",
        "codesys.toml",
        "siemens-s7-1500.toml",
    ]
    .iter()
    .map(|f| repo_file(&format!("plc-maps/cnc/{f}")))
    .collect();
    fuzz(
        "CNC maps",
        600,
        (text_from(seeds), prop::collection::vec(any::<u16>(), 1..64)),
        |(text, regs)| {
            let (r, peak) = peak_of(|| axiscomp::plc::CncMap::parse(&text, "fuzz-cnc.toml"));
            check_alloc("CncMap::parse", peak, text.len(), 512)?;
            match r {
                Ok(map) => {
                    let at = |a: u16| regs[a as usize % regs.len()];
                    let h = axiscomp::plc::table::decode_header(&map, &at);
                    let count = h.points as usize;
                    let _ = axiscomp::plc::table::decode_payload(&map, count, &at);
                }
                Err(e) => names_input(Err::<(), _>(e), "fuzz-cnc.toml")?,
            }
            Ok(())
        },
    );
}

#[test]
fn fuzz_service_configuration() {
    let dir = TempDir::new("fuzz-config");
    let seeds = vec![
        repo_file("configs/axiscomp.toml"),
        repo_file("configs/twin-service.toml"),
        "[io]\naddress = \"127.0.0.1:502\"\nrate_hz = 500.0\n[follower]\nnode_id = 1\n".into(),
    ];
    fuzz("configuration", 600, text_from(seeds), |text| {
        let path = dir.write("fuzz-axiscomp.toml", &text);
        let r = axiscomp::config::load(&axiscomp::config::Layers {
            etc: None,
            file: Some(path),
            env: vec![],
        });
        names_input(r, "fuzz-axiscomp.toml")
    });
}

#[test]
fn fuzz_twin_configuration() {
    fuzz(
        "twin configuration",
        300,
        text_from(vec![repo_file("configs/sim.toml")]),
        |text| {
            let r = axiscomp::sim::config::parse(&text, "fuzz-sim.toml");
            names_input(r, "fuzz-sim.toml")?;
            let r = axiscomp::sim::hexapod_servers::spec_from_config(&text, "fuzz-sim.toml");
            names_input(r, "fuzz-sim.toml")
        },
    );
}

/// An accepted ISO plan is one the service can run: its cycle, its motion time and the
/// lab's time limit from it are finite and bounded.
fn plan_is_runnable(plan: &axiscomp::run::Plan) -> Result<(), TestCaseError> {
    let steps = plan.steps();
    prop_assert!(steps.len() <= 2 * 100 * 1002, "{} steps", steps.len());
    let t = plan.motion_time_s(500.0);
    prop_assert!(t.is_finite() && t >= 0.0, "motion time {t}");
    prop_assert!(Duration::try_from_secs_f64(3.0 * t).is_ok(), "{t} s");
    let (lo, hi) = plan.travel_mm();
    prop_assert!(lo.is_finite() && hi.is_finite());
    Ok(())
}

/// An accepted self-calibration plan stops a bounded number of times.
fn selfcal_is_bounded(spec: axiscomp::follower::selfcal::Spec) -> Result<(), TestCaseError> {
    if let Ok(plan) = axiscomp::follower::selfcal::Plan::new(spec) {
        prop_assert!(
            plan.stops().len() <= 100 * 3 * 40_000,
            "{} stops",
            plan.stops().len()
        );
    }
    Ok(())
}

/// Plans as files: an ISO plan (`run start --plan plan.toml`) and a hexapod plan CSV
/// (`calibrate run --plan`), mutated with extreme numbers.
#[test]
fn fuzz_plan_files() {
    use axiscomp::hexapod::plan::{PlanError, PlanSpec as HexSpec, PosePlan};
    use axiscomp::run::{Plan, PlanSpec};
    let iso = toml::to_string(&PlanSpec {
        reference_mm: Some(10.0),
        ..PlanSpec::default()
    })
    .expect("plan TOML");
    let hexapod = PosePlan::generate(&HexSpec {
        poses: 12,
        ..HexSpec::default()
    })
    .to_csv();
    fuzz("plan files", 800, text_from(vec![iso, hexapod]), |text| {
        if let Ok(spec) = toml::from_str::<PlanSpec>(&text)
            && let Ok(plan) = Plan::new(spec)
        {
            plan_is_runnable(&plan)?;
        }
        let (r, peak) = peak_of(|| PosePlan::parse(&text, "fuzz-plan.csv"));
        check_alloc("PosePlan::parse", peak, text.len(), 512)?;
        match r {
            Ok(p) => {
                for pose in &p.poses {
                    prop_assert!(pose.pose.0.iter().all(|x| x.is_finite()));
                }
            }
            Err(e @ PlanError::Csv(_)) => names_input(Err::<(), _>(e), "fuzz-plan.csv")?,
            Err(_) => {}
        }
        Ok(())
    });
}

/// The numbers of an ISO plan, a self-calibration and the level stations drawn from the
/// extremes: refused by name, or a plan that runs in bounded time and memory.
#[test]
fn fuzz_plan_numbers() {
    use axiscomp::run::{Plan, PlanSpec};
    let plan = (
        prop::collection::vec(extreme_f64(), 7),
        extreme_u64(),
        extreme_u64(),
    );
    let selfcal = (
        prop::collection::vec(extreme_f64(), 3),
        extreme_u64(),
        extreme_u64(),
    );
    fuzz(
        "plan numbers",
        2000,
        (plan, selfcal),
        |((f, targets, runs), (g, passes, probe))| {
            let spec = PlanSpec {
                start_mm: f[0],
                end_mm: f[1],
                targets: targets as usize,
                runs: runs.min(u64::from(u32::MAX)) as u32,
                overrun_mm: f[2],
                dwell_s: f[3],
                feed_mm_min: f[4],
                lead_mm: f[5],
                reference_mm: Some(f[6]).filter(|x| *x != 0.0),
                ..PlanSpec::default()
            };
            match Plan::new(spec) {
                Ok(plan) => plan_is_runnable(&plan)?,
                Err(e) => prop_assert!(e.to_string().starts_with("test plan: "), "{e}"),
            }
            selfcal_is_bounded(axiscomp::follower::selfcal::Spec {
                from_mm: g[0],
                to_mm: g[1],
                step_mm: g[2],
                passes: passes as usize,
                probe_every: probe as usize,
            })?;
            let level = axiscomp::service::api::LevelRequest {
                from_mm: Some(g[0]),
                to_mm: Some(g[1]),
                station_mm: Some(g[2]),
                readings: Some(passes as usize),
                ..Default::default()
            };
            if level.check().is_ok() && g[0] < g[1] {
                let n = axiscomp::follower::level::stations((g[0], g[1]), g[2]).len();
                prop_assert!(n <= 20_002, "{n} stations");
            }
            Ok(())
        },
    );
}

/// A pose CSV and a calibration file made by the binary (`calibrate simulate`, `fit`).
fn calibration_seeds() -> &'static (String, String) {
    static SEEDS: OnceLock<(String, String)> = OnceLock::new();
    SEEDS.get_or_init(|| {
        let dir = TempDir::new("fuzz-cal");
        let poses = dir.path("poses.csv");
        let cal = dir.path("cal.toml");
        let (p, c) = (poses.to_str().expect("path"), cal.to_str().expect("path"));
        let cli = |args: &[&str]| {
            let o = run(args, "");
            assert!(o.status.success(), "{}", crate::helpers::stderr(&o));
        };
        cli(&[
            "calibrate",
            "simulate",
            "--poses",
            "30",
            "--seed",
            "18",
            "--output",
            p,
        ]);
        cli(&[
            "calibrate",
            "fit",
            "--input",
            p,
            "--output",
            c,
            "--method",
            "linear",
        ]);
        (
            std::fs::read_to_string(&poses).expect("poses"),
            std::fs::read_to_string(&cal).expect("cal"),
        )
    })
}

#[test]
fn fuzz_pose_and_deviation_csvs() {
    let (poses, _) = calibration_seeds();
    let deviations = repo_file("tests/it/fixtures/iso230_2_psi_ecmc.csv");
    fuzz(
        "CSVs",
        800,
        text_from(vec![poses.clone(), deviations]),
        |text| {
            let (r, peak) =
                peak_of(|| axiscomp::calibrate::poses::parse_pose_csv(&text, "fuzz-poses.csv"));
            check_alloc("parse_pose_csv", peak, text.len(), 512)?;
            names_input(r, "fuzz-poses.csv")?;
            let (r, peak) = peak_of(|| {
                axiscomp::evaluate::input::parse_deviation_csv(&text, "fuzz-captures.csv")
            });
            check_alloc("parse_deviation_csv", peak, text.len(), 512)?;
            names_input(r, "fuzz-captures.csv")
        },
    );
}

#[test]
fn fuzz_calibration_files() {
    let (_, cal) = calibration_seeds();
    fuzz(
        "calibration TOML",
        600,
        text_from(vec![cal.clone()]),
        |text| {
            let (r, peak) = peak_of(|| {
                axiscomp::calibrate::file::CalibrationFile::parse(&text, "fuzz-cal.toml")
            });
            check_alloc("CalibrationFile::parse", peak, text.len(), 512)?;
            names_input(r, "fuzz-cal.toml")
        },
    );
}

#[test]
fn fuzz_twin_cnc_gcode() {
    use axiscomp::run::program::{CaptureMode, generate};
    use axiscomp::run::{Dialect, Plan};
    let plan = Plan::new(crate::helpers::short_plan()).expect("plan");
    let seeds: Vec<String> = [Dialect::Iso, Dialect::LinuxCnc]
        .into_iter()
        .filter_map(|d| generate(&plan, d, CaptureMode::Stability).ok())
        .collect();
    assert!(!seeds.is_empty());
    fuzz("twin CNC G-code", 800, text_from(seeds), |text| {
        for d in [Dialect::Iso, Dialect::LinuxCnc] {
            let (r, peak) = peak_of(|| axiscomp::sim::cnc::parse(&text, d, "X"));
            check_alloc("sim::cnc::parse", peak, text.len(), 512)?;
            if let Err(e) = r {
                prop_assert!(!e.to_string().is_empty());
            }
        }
        Ok(())
    });
}

#[test]
fn fuzz_control_api_lines() {
    use axiscomp::service::api::Request;
    let seeds: Vec<String> = [
        r#"{"cmd":"status"}"#,
        r#"{"cmd":"subscribe","hz":10.0}"#,
        r#"{"cmd":"nominal","mm":12.5}"#,
        r#"{"cmd":"follower","action":"move","mm":1.0}"#,
        r#"{"cmd":"run_start","plan":{"axis":"X","start_mm":0,"end_mm":100,"targets":11,"runs":5,"overrun_mm":2,"dwell_s":2,"feed_mm_min":3000,"lead_mm":10,"reference_mm":5}}"#,
        r#"{"cmd":"runs","limit":50}"#,
        r#"{"cmd":"audit","limit":50}"#,
        r#"{"cmd":"run_result","run_id":3}"#,
        r#"{"cmd":"table_publish","table_id":4,"confirm":true}"#,
        r#"{"cmd":"hexapod_start","poses":200}"#,
        r#"{"cmd":"align_read","at_mm":100.5}"#,
        r#"{"cmd":"align_target","psd":2,"x":1.5,"y":-0.5}"#,
        r#"{"cmd":"align_advice","from_mm":0,"to_mm":900,"axis":"X"}"#,
        r#"{"cmd":"follower_map","id":2}"#,
        r#"{"cmd":"follower_map_start","from_mm":0,"to_mm":400,"step_mm":3.75,"passes":2,"frames":1000,"lead_mm":5,"probe_every":13,"feed_mm_min":2000}"#,
        r#"{"cmd":"follower_level_start","from_mm":0,"to_mm":400,"station_mm":100,"readings":20,"feed_mm_min":2000}"#,
        r#"{"cmd":"follower_level_reading","arcsec":1.5}"#,
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    fuzz("control lines", 3000, text_from(seeds), |line| {
        let (r, peak) = peak_of(|| serde_json::from_str::<Request>(&line));
        check_alloc("control line", peak, line.len(), 256)?;
        let r = match r {
            Ok(r) => r,
            Err(e) => {
                prop_assert!(!e.to_string().is_empty());
                return Ok(());
            }
        };
        // Checked, then what the service does with the numbers first: none may panic.
        if let Err(e) = r.check() {
            prop_assert!(!e.is_empty());
            return Ok(());
        }
        match r {
            Request::Subscribe { hz: Some(hz) } => {
                prop_assert!(axiscomp::config::SNAPSHOT_HZ.period(hz).is_ok(), "{hz}");
            }
            Request::RunStart { plan, .. } => {
                if let Ok(plan) = axiscomp::run::Plan::new(plan) {
                    plan_is_runnable(&plan)?;
                }
            }
            Request::FollowerMapStart(m) => {
                let d = axiscomp::follower::selfcal::Spec::default();
                selfcal_is_bounded(axiscomp::follower::selfcal::Spec {
                    from_mm: m.from_mm.unwrap_or(d.from_mm),
                    to_mm: m.to_mm.unwrap_or(d.to_mm),
                    step_mm: m.step_mm.unwrap_or(d.step_mm),
                    passes: m.passes.unwrap_or(d.passes),
                    probe_every: m.probe_every.unwrap_or(d.probe_every),
                })?;
            }
            Request::FollowerLevelStart(l) => {
                if let (Some(a), Some(b)) = (l.from_mm, l.to_mm)
                    && a < b
                {
                    let n =
                        axiscomp::follower::level::stations((a, b), l.station_mm.unwrap_or(100.0));
                    prop_assert!(n.len() <= 20_002, "{} stations", n.len());
                }
            }
            _ => {}
        }
        Ok(())
    });
}

#[test]
fn fuzz_follower_certificates() {
    let seed = axiscomp::sim::follower::FollowerModel::new(
        Default::default(),
        100.0,
        &mut axiscomp::sim::Rng::new(1),
    )
    .certificate(&mut axiscomp::sim::Rng::new(2));
    fuzz(
        "follower certificates",
        600,
        text_from(vec![seed]),
        |text| {
            let (r, peak) =
                peak_of(|| axiscomp::follower::Certificate::parse(&text, "fuzz-cert.csv"));
            check_alloc("Certificate::parse", peak, text.len(), 512)?;
            match r {
                // A certificate that reads is sound: finite, increasing per direction, u > 0.
                Ok(c) => {
                    for pts in [&c.up, &c.down] {
                        for w in pts.windows(2) {
                            prop_assert!(w[1].position_mm > w[0].position_mm);
                        }
                        for p in pts.iter() {
                            prop_assert!(p.error_mm.is_finite() && p.uncertainty_mm > 0.0);
                        }
                    }
                }
                Err(e) => names_input(Err::<(), _>(e), "fuzz-cert.csv")?,
            }
            Ok(())
        },
    );
}
