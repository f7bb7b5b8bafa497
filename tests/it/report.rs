//! The acceptance report (`axiscomp report`): a store with two runs of known errors, a table
//! published between them and the operator in the audit log; the PDF's structure checked by an
//! independent reader here (xref offsets, stream lengths, the text of every page), the figures
//! against hand computation, and — with poppler installed (`.ci/run`) — `pdftotext` and
//! `pdftoppm` on the same file.

use crate::helpers::{TempDir, bin, stderr, stdout};
use axiscomp::evaluate::axis::synthetic_capture;
use axiscomp::run::{Direction, Plan, PlanSpec};
use axiscomp::store::{
    Actor, AuditEntry, NewRun, Publication, PublicationOutcome, RunId, RunState, Store, TableEntry,
};
use axiscomp::units::Errors6;
use std::path::{Path, PathBuf};

/// Run-to-run offsets of positioning (µm): sample s = √0.1 = 0.316228 µm at every target.
const RUN_OFFSET_UM: [f64; 5] = [-0.4, -0.2, 0.0, 0.2, 0.4];

/// One run over 0..400 mm (5 targets, 5 runs, both directions): positioning `slope_um_per_m`
/// plus a reversal of 2 µm (up +1, down −1) and the run offsets; vertical straightness a
/// 20 µm/m tilt with a 1.5 µm bump at 200 mm; pitch 2″ over the travel; air 20.4…20.6 °C,
/// material 20.2 °C.
fn add_run(store: &mut Store, slope_um_per_m: f64, notes: &str) -> RunId {
    let plan = Plan::new(PlanSpec {
        axis: "X".into(),
        start_mm: 0.0,
        end_mm: 400.0,
        targets: 5,
        runs: 5,
        overrun_mm: 5.0,
        dwell_s: 2.0,
        feed_mm_min: 2000.0,
        lead_mm: 0.0,
        reference_mm: None,
    })
    .expect("plan");
    let id = store
        .create_run(&NewRun {
            axis: "X".into(),
            plan: serde_json::to_value(&plan).expect("plan json"),
            config: serde_json::json!({}),
            calibration: None,
            notes: notes.into(),
        })
        .expect("run");
    for (t, &x) in plan.targets.iter().enumerate() {
        for (r, off) in RUN_OFFSET_UM.iter().enumerate() {
            for d in [Direction::Up, Direction::Down] {
                let rev = if d == Direction::Up { 1.0 } else { -1.0 };
                let dy = slope_um_per_m * x / 1000.0 + rev + off;
                let dz = 20.0 * x / 1000.0 + if t == 2 { 1.5 } else { 0.0 };
                let pitch = 2.0 * x / 400.0;
                let mut c = synthetic_capture(
                    t as u32,
                    x,
                    r as u32 + 1,
                    d,
                    Errors6::from_user([0.0, dy, dz, pitch, 0.0, 0.0]),
                    Errors6::from_user([0.05; 6]),
                );
                c.air_c = Some(20.4 + 0.05 * r as f64);
                c.material_c = Some(20.2);
                store.insert_capture(id, &c).expect("capture");
            }
        }
    }
    id
}

/// The store: run 1 at 30 µm/m, a positioning table published and accepted, the operator's
/// run_start in the audit log, run 2 at 10 µm/m.
fn store(dir: &TempDir) -> PathBuf {
    let path = dir.path("axiscomp.db");
    let mut s = Store::open(&path).expect("store");
    let first = add_run(&mut s, 30.0, "commissioning, uncompensated");
    let table = s
        .insert_table(&TableEntry {
            kind: "positioning".into(),
            axis: "X".into(),
            direction: None,
            generated_us: axiscomp::store::now_us(),
            source_run: Some(first),
            values: serde_json::json!([0.0, -6.0, -12.0]),
            crc: 0x1234_abcd,
        })
        .expect("table");
    s.insert_publication(&Publication {
        table,
        target: "plc".into(),
        sequence: 7,
        outcome: PublicationOutcome::Accepted,
        unix_us: axiscomp::store::now_us(),
    })
    .expect("publication");
    s.audit(&AuditEntry {
        unix_us: axiscomp::store::now_us(),
        who: Actor {
            uid: Some(1000),
            user: Some("maria".into()),
            pid: Some(1),
        },
        role: "operator".into(),
        action: "run_start".into(),
        details: serde_json::json!({}),
        outcome: Default::default(),
    })
    .expect("audit");
    std::thread::sleep(std::time::Duration::from_millis(5));
    let second = add_run(&mut s, 10.0, "verification under the table");
    for run in [first, second] {
        s.set_run_state(run, RunState::Running).expect("state");
        s.set_run_state(run, RunState::Finished).expect("state");
    }
    path
}

const CONFIG: &str = r#"
[head]
serial = "H-0042"

[machine]
name = "VMC 850 #3"
serial = "SN 12-3456"
customer = "Muster GmbH"
expansion_um_per_m_k = 11.5

[acceptance]
e_um = 8.0
r_um = 3.0
straightness_um = 2.0
"#;

/// `axiscomp report --run 2 --compare 1` into `out`; returns the directory.
fn make_report(dir: &TempDir, extra: &[&str]) -> PathBuf {
    let mut args = vec!["--compare", "1"];
    args.extend_from_slice(extra);
    report_of(dir, CONFIG, "2", "report", &args)
}

/// `axiscomp report --run RUN` of the test's store with `config` into `dir/name`, with `extra`
/// arguments; returns the directory.
fn report_of(dir: &TempDir, config: &str, run: &str, name: &str, extra: &[&str]) -> PathBuf {
    let db = store(dir);
    let config = dir.write(&format!("{name}.toml"), config);
    let out = dir.path(name);
    let mut args: Vec<&str> = vec![
        "report",
        "--db",
        db.to_str().expect("path"),
        "--config",
        config.to_str().expect("path"),
        "--run",
        run,
        "--out",
        out.to_str().expect("path"),
    ];
    args.extend_from_slice(extra);
    let o = bin().args(&args).output().expect("run axiscomp");
    assert!(o.status.success(), "{}{}", stdout(&o), stderr(&o));
    out
}

// ---------------------------------------------------------------- an independent PDF reader

/// The objects of a PDF by number, after checking the cross-reference table: every in-use
/// entry's offset is where "N 0 obj" starts, the trailer's /Size matches, and each stream's
/// /Length is its exact byte count.
fn objects(pdf: &[u8]) -> Vec<(usize, Vec<u8>)> {
    assert!(pdf.starts_with(b"%PDF-1.4\n"), "header");
    let tail = String::from_utf8_lossy(&pdf[pdf.len().saturating_sub(64)..]).into_owned();
    assert!(tail.ends_with("%%EOF\n"), "{tail}");
    let start: usize = tail
        .rsplit("startxref\n")
        .next()
        .and_then(|t| t.lines().next())
        .and_then(|l| l.trim().parse().ok())
        .expect("startxref");
    let xref = &pdf[start..];
    assert!(
        xref.starts_with(b"xref\n0 "),
        "startxref points at the xref table"
    );
    let head = String::from_utf8_lossy(&xref[..32]).into_owned();
    let count: usize = head.lines().nth(1).expect("subsection")[2..]
        .trim()
        .parse()
        .expect("count");
    let entries_at =
        start + head.find('\n').expect("nl") + 1 + head.lines().nth(1).expect("l").len() + 1;
    let trailer = String::from_utf8_lossy(&pdf[entries_at + 20 * count..]).into_owned();
    assert!(
        trailer.starts_with("trailer\n") && trailer.contains(&format!("/Size {count} ")),
        "{trailer}"
    );
    let mut out = Vec::new();
    for i in 0..count {
        let e = &pdf[entries_at + 20 * i..entries_at + 20 * (i + 1)];
        let e = std::str::from_utf8(e).expect("ascii entry");
        assert!(
            e.ends_with(" \n") || e.ends_with("\r\n"),
            "entry {i} is 20 bytes: {e:?}"
        );
        if i == 0 {
            assert!(e.starts_with("0000000000 65535 f"), "{e}");
            continue;
        }
        assert_eq!(&e[17..18], "n", "entry {i}");
        let off: usize = e[..10].parse().expect("offset");
        let obj = &pdf[off..];
        let head = format!("{i} 0 obj\n");
        assert!(obj.starts_with(head.as_bytes()), "object {i} at {off}");
        let end = find(obj, b"\nendobj\n").expect("endobj");
        let body = obj[head.len()..end].to_vec();
        if let Some(s) = find(&body, b"stream\n") {
            let dict = String::from_utf8_lossy(&body[..s]).into_owned();
            let len: usize = dict
                .split("/Length ")
                .nth(1)
                .and_then(|t| t.split_whitespace().next())
                .and_then(|t| t.parse().ok())
                .expect("stream length");
            assert!(
                body[s + 7 + len..].starts_with(b"\nendstream"),
                "object {i}: /Length {len} is the stream's length"
            );
        }
        out.push((i, body));
    }
    out
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

/// WinAnsi to Unicode for the codes the report uses.
fn winansi_char(b: u8) -> char {
    match b {
        0x96 => '–',
        0x97 => '—',
        0x85 => '…',
        0x95 => '•',
        0x92 => '’',
        b => char::from(b), // ASCII, and Latin-1 above 0xA0
    }
}

/// The strings shown by `Tj` in a content stream, in order.
fn shown_strings(stream: &[u8]) -> Vec<String> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < stream.len() {
        if stream[i] != b'(' {
            i += 1;
            continue;
        }
        let mut s = String::new();
        i += 1;
        while i < stream.len() && stream[i] != b')' {
            if stream[i] == b'\\' {
                i += 1;
                if stream[i].is_ascii_digit() {
                    let oct = std::str::from_utf8(&stream[i..i + 3]).expect("octal");
                    s.push(winansi_char(u8::from_str_radix(oct, 8).expect("octal")));
                    i += 3;
                    continue;
                }
                s.push(char::from(stream[i]));
            } else {
                s.push(winansi_char(stream[i]));
            }
            i += 1;
        }
        i += 1;
        if stream[i..].starts_with(b" Tj") {
            out.push(s);
        }
    }
    out
}

/// Each page's shown strings, in page order (the /Kids order).
fn pages(pdf: &[u8]) -> Vec<Vec<String>> {
    let objs = objects(pdf);
    let get = |n: usize| &objs.iter().find(|(i, _)| *i == n).expect("object").1;
    let pages_obj = String::from_utf8_lossy(get(2)).into_owned();
    let kids = pages_obj.split("/Kids [").nth(1).expect("kids");
    let kids: Vec<usize> = kids
        .split(']')
        .next()
        .expect("kids")
        .split(" 0 R")
        .filter_map(|k| k.trim().parse().ok())
        .collect();
    kids.iter()
        .map(|&k| {
            let page = String::from_utf8_lossy(get(k)).into_owned();
            assert!(page.contains("/MediaBox [0 0 595.28 841.89]"), "{page}");
            let c: usize = page
                .split("/Contents ")
                .nth(1)
                .and_then(|t| t.split_whitespace().next())
                .and_then(|t| t.parse().ok())
                .expect("contents");
            shown_strings(get(c))
        })
        .collect()
}

/// The strings following `label` in one page's text.
fn after<'a>(text: &'a [String], label: &str, n: usize) -> Vec<&'a str> {
    let i = text
        .iter()
        .position(|s| s == label)
        .unwrap_or_else(|| panic!("{label:?} not shown: {text:?}"));
    text[i + 1..i + 1 + n].iter().map(String::as_str).collect()
}

// Hand computation, run 2 (10 µm/m) normalised to 20 °C: α·ΔT = 11.5 · 0.2 = 2.3 µm/m, so
// 7.7 µm/m over 400 mm: E↑ = E↓ = 3.08 µm, M = 3.08, with the 2 µm reversal E = 5.08; s =
// 0.316228 µm: R↑ = 4s = 1.26, R = 2s + 2s + B = 3.26, A↑ = E↑ + 4s = 4.34, A = E + 4s = 6.34.
// Run 1 (30 µm/m → 27.7): E = 11.08 + 2 = 13.08; the change is −8.00.

#[test]
fn the_acceptance_pdf_is_sound_and_shows_the_figures() {
    let dir = TempDir::new("report-acceptance");
    let out = make_report(&dir, &[]);
    for f in [
        "acceptance.html",
        "acceptance.md",
        "acceptance.pdf",
        "chart-1.svg",
    ] {
        assert!(out.join(f).exists(), "{f} written");
    }
    let pdf = std::fs::read(out.join("acceptance.pdf")).expect("pdf");
    let pages = pages(&pdf);
    assert!(pages.len() >= 3, "{} pages", pages.len());
    let all: Vec<String> = pages.concat();
    for (i, p) in pages.iter().enumerate() {
        let footer = format!("page {} of {}", i + 1, pages.len());
        assert!(p.contains(&footer), "page {} has its footer", i + 1);
    }
    for section in [
        "1 Machine and run",
        "2 Instrument",
        "3 Test plan",
        "4 Positioning (ISO 230-2)",
        "5 Straightness (ISO 230-1)",
        "6 Angular errors (ISO 230-1)",
        "7 Environment",
        "8 Compensation tables in use",
        "9 Tolerances",
        "10 Before and after",
        "11 Uncertainty",
        "12 Signatures",
    ] {
        assert!(all.iter().any(|s| s == section), "section {section:?}");
    }
    // Identification, from the configuration and the audit log.
    assert_eq!(after(&all, "Machine", 1), ["VMC 850 #3"]);
    assert_eq!(after(&all, "Serial number", 1), ["SN 12-3456"]);
    assert_eq!(after(&all, "Customer", 1), ["Muster GmbH"]);
    assert_eq!(after(&all, "Operator", 1), ["maria"]);
    assert!(after(&all, "Head", 1)[0].ends_with("serial H-0042"));
    // The plan as a table: target 5 at 400.000 mm, 100.000 mm after the fourth.
    assert_eq!(after(&all, "Travel", 1), ["0.000 to 400.000 mm"]);
    // ISO 230-2 per direction and bidirectional (↑ ↓ are words in WinAnsi).
    assert!(
        all.iter().any(|s| s == "up (\u{b5}m)"),
        "the ↑ column says up"
    );
    assert_eq!(after(&all, "A  accuracy", 3), ["4.34", "4.34", "6.34"]);
    assert_eq!(
        after(&all, "E  systematic deviation", 3),
        ["3.08", "3.08", "5.08"]
    );
    assert_eq!(after(&all, "R  repeatability", 3), ["1.26", "1.26", "3.26"]);
    assert_eq!(after(&all, "M  mean deviation", 3), ["–", "–", "3.08"]);
    assert_eq!(after(&all, "B  reversal value", 3), ["–", "–", "2.00"]);
    // Straightness: 1.5 µm bump, the 20 µm/m line removed and stated.
    let st = after(&all, "vertical straightness (dz)", 6);
    assert_eq!(st[..5], ["least squares", "1.50", "1.50", "1.50", "20.00"]);
    assert!(st[5].contains("(k = 2)"), "{st:?}");
    assert!(
        all.concat().contains("slope 20.00 \u{b5}m/m"),
        "the dz chart states its reference line's slope"
    );
    let pitch = after(&all, "pitch (ex)", 3);
    assert_eq!(pitch, ["2.00", "2.00", "2.00"]);
    // Environment and normalisation.
    assert!(after(&all, "Air temperature", 1)[0].starts_with("20.40 to 20.60 \u{b0}C"));
    assert!(after(&all, "Material temperature", 1)[0].starts_with("20.20 to 20.20 \u{b0}C"));
    assert!(after(&all, "Normalisation to 20 \u{b0}C", 1)[0].starts_with("applied"));
    // The table published before run 2 (sequence 7, CRC 1234ABCD, from run 1).
    let t = after(&all, "positioning", 6);
    assert_eq!(
        (t[0], t[1], t[2], t[4], t[5]),
        ("X", "1", "7", "1", "1234ABCD")
    );
    assert!(t[3].ends_with(" UTC"), "{t:?}");
    // Tolerances with pass/fail.
    let e = after(&all, "E  systematic deviation (bidirectional)", 4);
    assert_eq!((e[0], e[2], e[3]), ("5.08 \u{b5}m", "8.00 \u{b5}m", "pass"));
    let r = after(&all, "R  repeatability (bidirectional)", 4);
    assert_eq!((r[0], r[2], r[3]), ("3.26 \u{b5}m", "3.00 \u{b5}m", "FAIL"));
    assert!(
        all.iter()
            .any(|s| s == "Result: 1 of 4 toleranced figures fail.")
    );
    // Before and after: run 1 then run 2.
    let c = after(&all, "E  systematic deviation (bidirectional)", 1);
    assert_eq!(c, ["5.08 \u{b5}m"], "the verdict row comes first");
    let rows: Vec<usize> = all
        .iter()
        .enumerate()
        .filter(|(_, s)| *s == "E  systematic deviation (bidirectional)")
        .map(|(i, _)| i)
        .collect();
    let cmp = &all[rows[1] + 1..rows[1] + 5];
    assert_eq!(cmp, ["13.08", "5.08", "-8.00", "\u{b5}m"]);
    // No debug prints and no raw JSON anywhere.
    let text = all.concat();
    for bad in ["Some(", "None", "{\"", "CaptureSettings"] {
        assert!(!text.contains(bad), "{bad} in the report");
    }
}

#[test]
fn html_and_markdown_carry_the_same_document() {
    let dir = TempDir::new("report-html-md");
    let out = make_report(&dir, &["--format", "html,md", "--operator", "J. Doe"]);
    assert!(
        !out.join("acceptance.pdf").exists(),
        "only the formats asked for"
    );
    let html = std::fs::read_to_string(out.join("acceptance.html")).expect("html");
    assert!(
        html.contains("<td>J. Doe</td>"),
        "--operator over the audit log"
    );
    assert!(
        html.contains("<svg") && !html.contains("<script"),
        "inline charts, no scripts"
    );
    assert!(html.contains("<td class=\"n\">5.08</td>"));
    let md = std::fs::read_to_string(out.join("acceptance.md")).expect("md");
    assert!(
        md.contains("| E  systematic deviation | 3.08 | 3.08 | 5.08 |"),
        "{md}"
    );
    let charts = md.matches("](chart-").count();
    assert!(charts >= 5, "{charts} charts referenced");
    for n in 1..=charts {
        assert!(out.join(format!("chart-{n}.svg")).exists());
    }
    // The legend is below the plot area: no legend text inside it.
    let svg = std::fs::read_to_string(out.join("chart-1.svg")).expect("svg");
    assert!(svg.contains(">mean ↑ ± 2s</text>"), "{svg}");
}

#[test]
fn report_refuses_bad_input_by_name() {
    let dir = TempDir::new("report-bad");
    let db = store(&dir);
    let run = |args: &[&str]| {
        let mut a = vec!["report", "--db", db.to_str().expect("p"), "--out"];
        let out = dir.path("o");
        let out = out.to_str().expect("p").to_string();
        a.push(&out);
        a.extend_from_slice(args);
        let o = bin().args(&a).output().expect("run");
        assert!(!o.status.success());
        stderr(&o)
    };
    let e = run(&["--run", "2", "--format", "docx"]);
    assert!(e.contains("--format docx: use html, md, pdf or raw"), "{e}");
    let e = run(&["--run", "2", "--compare", "2"]);
    assert!(e.contains("--compare 2: that is the run reported"), "{e}");
    let e = run(&["--run", "9"]);
    assert!(e.contains('9'), "{e}");
}

/// With poppler (installed by `.ci/run`): `pdftotext` reads the sections and figures back and
/// `pdftoppm` renders every page.
#[test]
#[ignore = "needs poppler-utils (pdftotext, pdftoppm); .ci/run installs them"]
fn poppler_reads_and_renders_the_acceptance_pdf() {
    let dir = TempDir::new("report-poppler");
    let out = make_report(&dir, &[]);
    let pdf = out.join("acceptance.pdf");
    let txt = out.join("acceptance.txt");
    let o = std::process::Command::new("pdftotext")
        .args(["-layout"])
        .arg(&pdf)
        .arg(&txt)
        .output()
        .expect("pdftotext (apt-get install poppler-utils)");
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(o.stderr.is_empty(), "pdftotext complained: {}", stderr(&o));
    let text = std::fs::read_to_string(&txt).expect("text");
    let line = |label: &str| -> Vec<String> {
        text.lines()
            .find(|l| l.contains(label))
            .unwrap_or_else(|| panic!("{label:?} not in:\n{text}"))
            .split_whitespace()
            .map(str::to_string)
            .collect()
    };
    for section in [
        "1 Machine and run",
        "4 Positioning (ISO 230-2)",
        "5 Straightness (ISO 230-1)",
        "7 Environment",
        "9 Tolerances",
        "10 Before and after",
        "12 Signatures",
    ] {
        assert!(text.contains(section), "{section}");
    }
    let last3 = |v: Vec<String>| v[v.len() - 3..].to_vec();
    assert_eq!(
        last3(line("systematic deviation")),
        ["3.08", "3.08", "5.08"]
    );
    assert_eq!(last3(line("accuracy")), ["4.34", "4.34", "6.34"]);
    assert!(line("Customer").contains(&"Muster".to_string()));
    assert!(text.contains("slope 20.00 µm/m"), "µ survives WinAnsi");
    assert!(text.contains("20.40 to 20.60 °C"), "° survives WinAnsi");
    let o = std::process::Command::new("pdftoppm")
        .args(["-r", "50", "-png"])
        .arg(&pdf)
        .arg(out.join("page"))
        .output()
        .expect("pdftoppm");
    assert!(o.status.success(), "{}", stderr(&o));
    let pngs: Vec<PathBuf> = std::fs::read_dir(&out)
        .expect("dir")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "png"))
        .collect();
    assert!(pngs.len() >= 3, "{} pages rendered", pngs.len());
    for p in &pngs {
        let (w, h) = png_size(p);
        // A4 at 50 dpi: 413 × 585 pixels.
        assert!(
            (413..=414).contains(&w) && h == 585,
            "{}: {w} × {h}",
            p.display()
        );
    }
    if let Ok(keep) = std::env::var("REPORT_KEEP") {
        for p in pngs.iter().chain([&txt, &pdf]) {
            let _ = std::fs::copy(p, Path::new(&keep).join(p.file_name().expect("name")));
        }
    }
}

fn png_size(p: &Path) -> (u32, u32) {
    let b = std::fs::read(p).expect("png");
    assert!(b.starts_with(b"\x89PNG\r\n\x1a\n"), "{}", p.display());
    let be = |i: usize| u32::from_be_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
    (be(16), be(20))
}

/// The report says what signing accepts and what compensation it knows, without contradicting
/// itself (issue 29: "no pass or fail verdict" then "signing accepts the axis against the
/// tolerances in section 9"; "None: measured without compensation" for a run whose tables were
/// never recorded).
#[test]
fn without_tolerances_or_recorded_tables_the_report_says_so() {
    let dir = TempDir::new("report-no-tolerances");
    // Run 1 was measured before the store's table was published.
    let no_tolerances = &CONFIG[..CONFIG.find("[acceptance]").expect("the test's config")];
    let out = report_of(&dir, no_tolerances, "1", "bare", &["--format", "md"]);
    let md = std::fs::read_to_string(out.join("acceptance.md")).expect("md");
    assert!(
        md.contains("the report gives no pass or fail verdict"),
        "{md}"
    );
    assert!(
        md.contains("no tolerances were configured, so signing accepts the figures as measured, not a verdict")
            && !md.contains("against the tolerances in section 9"),
        "{md}"
    );
    assert!(
        md.contains("Not recorded: the run holds no read-back of the PLC")
            && !md.contains("measured without compensation"),
        "{md}"
    );
    // With tolerances, signing accepts the axis against them.
    let other = TempDir::new("report-tolerances");
    let with = make_report(&other, &["--format", "md"]);
    let md = std::fs::read_to_string(with.join("acceptance.md")).expect("md");
    assert!(md.contains("signing accepts the axis against the tolerances in section 9"));
}
