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
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::io::Read as _;
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

/// The objects of a PDF by number, after checking the file's frame: the PDF 1.7 header with the
/// binary comment PDF/A asks for, the cross-reference table (every in-use entry's offset is where
/// "N 0 obj" starts, the trailer's /Size matches) and each stream's /Length (its exact byte
/// count). Returns the objects and the trailer dictionary.
fn objects(pdf: &[u8]) -> (BTreeMap<usize, Vec<u8>>, String) {
    assert!(pdf.starts_with(b"%PDF-1.7\n%"), "header");
    assert!(
        pdf[10..14].iter().all(|&b| b > 127),
        "PDF/A's binary comment"
    );
    let tail = String::from_utf8_lossy(&pdf[pdf.len().saturating_sub(64)..]).into_owned();
    assert!(tail.trim_end().ends_with("%%EOF"), "{tail}");
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
    assert!(trailer.starts_with("trailer\n"), "{trailer}");
    assert_eq!(int(&trailer, "Size"), Some(count), "{trailer}");
    let mut out = BTreeMap::new();
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
        let body = &obj[head.len()..];
        let body = match find(body, b"\nstream\n") {
            Some(s) => {
                let dict = String::from_utf8_lossy(&body[..s]).into_owned();
                let len = int(&dict, "Length").expect("stream length");
                let data = &body[s + 8..s + 8 + len];
                assert!(
                    body[s + 8 + len..].starts_with(b"\nendstream\nendobj"),
                    "object {i}: /Length {len} is the stream's length"
                );
                let mut b = dict.into_bytes();
                b.extend_from_slice(b"\nstream\n");
                b.extend_from_slice(data);
                b
            }
            None => body[..find(body, b"\nendobj").expect("endobj")].to_vec(),
        };
        out.insert(i, body);
    }
    (out, trailer)
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

/// The text after `/key` in a dictionary (the key whole: /Length is not /Length1).
fn value<'a>(dict: &'a str, key: &str) -> Option<&'a str> {
    let pat = format!("/{key}");
    let mut from = 0;
    while let Some(i) = dict[from..].find(&pat) {
        let rest = &dict[from + i + pat.len()..];
        if !rest.starts_with(|c: char| c.is_ascii_alphanumeric()) {
            return Some(rest.trim_start());
        }
        from += i + pat.len();
    }
    None
}

/// An integer (or a reference's object number) after `/key`.
fn int(dict: &str, key: &str) -> Option<usize> {
    let v = value(dict, key)?;
    let end = v.find(|c: char| !c.is_ascii_digit()).unwrap_or(v.len());
    v[..end].parse().ok()
}

/// The object numbers referred to in `s` ("12 0 R 14 0 R").
fn refs(s: &str) -> Vec<usize> {
    let t: Vec<&str> = s
        .split(|c: char| c.is_whitespace() || "[]<>/".contains(c))
        .filter(|t| !t.is_empty())
        .collect();
    t.windows(3)
        .filter(|w| w[1] == "0" && w[2] == "R")
        .filter_map(|w| w[0].parse().ok())
        .collect()
}

/// A dictionary's text (before any stream data).
fn dict_of(obj: &[u8]) -> String {
    let end = find(obj, b"\nstream\n").unwrap_or(obj.len());
    String::from_utf8_lossy(&obj[..end]).into_owned()
}

/// A stream's data, inflated when it is FlateDecode'd (the only filter krilla uses).
fn stream_of(obj: &[u8]) -> Vec<u8> {
    let s = find(obj, b"\nstream\n").expect("a stream");
    let data = &obj[s + 8..];
    if dict_of(obj).contains("/FlateDecode") {
        let mut out = Vec::new();
        flate2::read::ZlibDecoder::new(data)
            .read_to_end(&mut out)
            .expect("inflate");
        out
    } else {
        data.to_vec()
    }
}

/// A ToUnicode CMap: code → text (bfchar entries and bfrange runs).
fn to_unicode(cmap: &str) -> HashMap<u32, String> {
    let hex = |t: &str| u32::from_str_radix(t.trim_matches(|c| c == '<' || c == '>'), 16);
    let utf16 = |t: &str| -> String {
        let t = t.trim_matches(|c| c == '<' || c == '>');
        let units: Vec<u16> = (0..t.len() / 4)
            .map(|i| u16::from_str_radix(&t[4 * i..4 * i + 4], 16).expect("hex"))
            .collect();
        String::from_utf16(&units).expect("utf-16")
    };
    let mut map = HashMap::new();
    for section in cmap.split("beginbfchar").skip(1) {
        let body = section.split("endbfchar").next().expect("endbfchar");
        let t: Vec<&str> = body.split_whitespace().collect();
        for pair in t.chunks(2) {
            map.insert(hex(pair[0]).expect("code"), utf16(pair[1]));
        }
    }
    for section in cmap.split("beginbfrange").skip(1) {
        let body = section.split("endbfrange").next().expect("endbfrange");
        let t: Vec<&str> = body.split_whitespace().collect();
        for r in t.chunks(3) {
            let (lo, hi) = (hex(r[0]).expect("lo"), hex(r[1]).expect("hi"));
            let first: Vec<char> = utf16(r[2]).chars().collect();
            for code in lo..=hi {
                let mut s: String = first.iter().collect();
                let last = s.pop().expect("a character");
                s.push(char::from_u32(last as u32 + code - lo).expect("char"));
                map.insert(code, s);
            }
        }
    }
    map
}

/// A page's fonts by resource name: each a Type0 font whose program is embedded (FontFile2)
/// as a subset (a six-letter tag and '+' before its name), with its ToUnicode map.
fn page_fonts(
    objs: &BTreeMap<usize, Vec<u8>>,
    page: &str,
    fonts_seen: &mut BTreeSet<String>,
) -> HashMap<String, HashMap<u32, String>> {
    let get = |n: usize| dict_of(&objs[&n]);
    let resources = match value(page, "Resources") {
        Some(v) if v.starts_with("<<") => v.to_string(),
        _ => get(int(page, "Resources").expect("resources")),
    };
    let fonts = value(&resources, "Font").expect("fonts");
    let fonts = match fonts.strip_prefix("<<") {
        Some(inline) => inline.split(">>").next().expect("font dict").to_string(),
        None => get(int(&resources, "Font").expect("font dict")),
    };
    let mut out = HashMap::new();
    for entry in fonts.split('/').skip(1) {
        let name = entry
            .split(|c: char| c.is_whitespace())
            .next()
            .expect("name");
        let Some(&n) = refs(entry).first() else {
            continue;
        };
        let font = get(n);
        assert!(font.contains("/Subtype/Type0"), "font {name}: {font}");
        let base = value(&font, "BaseFont").expect("BaseFont");
        let base = base[1..].split(['/', ' ', '>']).next().expect("name");
        let (tag, _) = base.split_once('+').expect("a subset's tag");
        assert!(
            tag.len() == 6 && tag.bytes().all(|b| b.is_ascii_uppercase()),
            "{base} is a subset"
        );
        let cid = get(refs(value(&font, "DescendantFonts").expect("cid font"))[0]);
        let descriptor = get(int(&cid, "FontDescriptor").expect("descriptor"));
        let file = int(&descriptor, "FontFile2").expect("an embedded TrueType program");
        assert!(
            stream_of(&objs[&file]).starts_with(&[0, 1, 0, 0]),
            "{base}'s program"
        );
        fonts_seen.insert(base.to_string());
        let cmap = stream_of(&objs[&int(&font, "ToUnicode").expect("ToUnicode")]);
        out.insert(
            name.to_string(),
            to_unicode(&String::from_utf8_lossy(&cmap)),
        );
    }
    out
}

/// A PDF literal string's bytes: `s` starts after the '('; returns the bytes and the length read.
fn literal(s: &[u8]) -> (Vec<u8>, usize) {
    let (mut out, mut depth, mut i) = (Vec::new(), 0, 0);
    while i < s.len() {
        match s[i] {
            b'\\' => {
                i += 1;
                match s[i] {
                    b'n' => out.push(b'\n'),
                    b'r' => out.push(b'\r'),
                    b't' => out.push(b'\t'),
                    b'b' => out.push(8),
                    b'f' => out.push(12),
                    b'0'..=b'7' => {
                        let n = s[i..]
                            .iter()
                            .take(3)
                            .take_while(|b| b.is_ascii_digit())
                            .count();
                        let oct = std::str::from_utf8(&s[i..i + n]).expect("octal");
                        out.push(u8::from_str_radix(oct, 8).expect("octal"));
                        i += n - 1;
                    }
                    b => out.push(b),
                }
            }
            b'(' => {
                depth += 1;
                out.push(b'(');
            }
            b')' if depth == 0 => return (out, i + 1),
            b')' => {
                depth -= 1;
                out.push(b')');
            }
            b => out.push(b),
        }
        i += 1;
    }
    panic!("unterminated string");
}

/// The text of each text object (`BT` … `ET`) of a content stream, in order: what its `Tj`
/// and `TJ` operators show, decoded through the current font's ToUnicode map (two-byte codes),
/// or a marked-content span's /ActualText in place of the glyphs inside it (krilla marks a
/// letter with its combining mark so, e.g. B̄).
fn shown_strings(stream: &[u8], fonts: &HashMap<String, HashMap<u32, String>>) -> Vec<String> {
    let mut out = Vec::new();
    let mut font: Option<&HashMap<u32, String>> = None;
    let mut name = String::new();
    // The string operands since the last operator, the text object's text so far, and whether
    // an /ActualText span is open.
    let mut strings: Vec<Vec<u8>> = Vec::new();
    let mut text = String::new();
    let mut actual = false;
    let mut i = 0;
    while i < stream.len() {
        let at = |op: &[u8]| {
            (i == 0 || !stream[i - 1].is_ascii_alphanumeric())
                && stream[i..].starts_with(op)
                && stream
                    .get(i + op.len())
                    .is_none_or(|b| !b.is_ascii_alphanumeric())
        };
        match stream[i] {
            b'(' => {
                let (bytes, n) = literal(&stream[i + 1..]);
                strings.push(bytes);
                i += n + 1;
                continue;
            }
            // A dictionary (marked content's properties) is not a string.
            b'<' if stream.get(i + 1) == Some(&b'<') => {
                i += 2;
                continue;
            }
            b'<' => {
                let end = i + stream[i..].iter().position(|&b| b == b'>').expect(">");
                let hex = std::str::from_utf8(&stream[i + 1..end]).expect("hex");
                let hex: String = hex.split_whitespace().collect();
                strings.push(
                    (0..hex.len() / 2)
                        .map(|k| u8::from_str_radix(&hex[2 * k..2 * k + 2], 16).expect("hex"))
                        .collect(),
                );
                i = end + 1;
                continue;
            }
            b'/' => {
                let end = i
                    + 1
                    + stream[i + 1..]
                        .iter()
                        .position(|b| b" /[]<>()\n\r\t".contains(b))
                        .unwrap_or(stream.len() - i - 1);
                name = String::from_utf8_lossy(&stream[i + 1..end]).into_owned();
                i = end;
                continue;
            }
            _ if at(b"BT") => {
                text.clear();
                strings.clear();
            }
            _ if at(b"ET") => out.push(std::mem::take(&mut text)),
            _ if at(b"Tf") => font = fonts.get(&name),
            _ if at(b"Tj") || at(b"TJ") => {
                let map = font.expect("a font set before text");
                if !actual {
                    for c in strings.concat().chunks(2) {
                        let code = u32::from(c[0]) << 8 | u32::from(c[1]);
                        let s = map
                            .get(&code)
                            .unwrap_or_else(|| panic!("code {code:04X} has no ToUnicode entry"));
                        text.push_str(s);
                    }
                }
                strings.clear();
            }
            _ if at(b"BDC") => {
                let utf16be = strings.last().expect("/ActualText");
                let units: Vec<u16> = utf16be
                    .chunks(2)
                    .map(|c| u16::from_be_bytes([c[0], c[1]]))
                    .skip_while(|&u| u == 0xFEFF)
                    .collect();
                text.push_str(&String::from_utf16(&units).expect("utf-16"));
                actual = true;
                strings.clear();
            }
            _ if at(b"EMC") => actual = false,
            _ => {}
        }
        i += 1;
    }
    out
}

/// Each page's shown strings, in page order (the /Kids order), and the fonts the pages use
/// (each checked embedded and subset).
fn pages(pdf: &[u8]) -> (Vec<Vec<String>>, Vec<String>) {
    let (objs, trailer) = objects(pdf);
    let get = |n: usize| dict_of(&objs[&n]);
    let catalog = get(int(&trailer, "Root").expect("root"));
    assert!(catalog.contains("/Type/Catalog"), "{catalog}");
    assert!(value(&catalog, "Metadata").is_some() && value(&catalog, "OutputIntents").is_some());
    let tree = get(int(&catalog, "Pages").expect("pages"));
    let kids = refs(
        value(&tree, "Kids")
            .expect("kids")
            .split(']')
            .next()
            .expect("kids"),
    );
    let mut fonts = BTreeSet::new();
    let pages = kids
        .iter()
        .map(|&k| {
            let page = get(k);
            assert!(page.contains("/Type/Page"), "{page}");
            assert!(page.contains("/MediaBox[0 0 595.276 841.89]"), "{page}");
            let used = page_fonts(&objs, &page, &mut fonts);
            let contents = stream_of(&objs[&int(&page, "Contents").expect("contents")]);
            shown_strings(&contents, &used)
        })
        .collect();
    (pages, fonts.into_iter().collect())
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
    let (pages, fonts) = pages(&pdf);
    // DejaVu Sans and its bold, each embedded once as a subset.
    let mut names: Vec<&str> = fonts.iter().map(|f| &f[7..]).collect();
    names.sort_unstable();
    assert_eq!(names, ["DejaVuSans", "DejaVuSans-Bold"], "{fonts:?}");
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
    // ISO 230-2 per direction and bidirectional, the directions as arrows.
    assert!(
        all.iter().any(|s| s == "↑ (µm)") && all.iter().any(|s| s == "↓ (µm)"),
        "the direction columns"
    );
    assert_eq!(after(&all, "A  accuracy", 3), ["4.34", "4.34", "6.34"]);
    assert_eq!(
        after(&all, "E  systematic deviation", 3),
        ["3.08", "3.08", "5.08"]
    );
    assert_eq!(after(&all, "R  repeatability", 3), ["1.26", "1.26", "3.26"]);
    assert_eq!(after(&all, "M  mean deviation", 3), ["–", "–", "3.08"]);
    assert_eq!(after(&all, "B  reversal value", 3), ["–", "–", "2.00"]);
    // B̄ with its combining macron, read back as the two characters.
    assert_eq!(
        after(&all, "B\u{304}  mean reversal value", 3),
        ["–", "–", "2.00"]
    );
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
    assert_eq!(cmp, ["13.08", "5.08", "−8.00", "µm"], "a real minus sign");
    // The uncertainty budget's formulas, with their symbols (no words spelled for them).
    for formula in ["√(Σ sd²/frames)/n", "s/√n", "L·(1 − cos φ)/√12"] {
        assert!(
            all.iter().any(|s| s.contains(formula)),
            "{formula} in the budget"
        );
    }
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

/// With poppler (installed by `.ci/run`): `pdffonts` lists the two fonts embedded as subsets,
/// `pdfinfo` the title and PDF 1.7 (PDF/A-2), `pdftotext` reads the sections, figures and
/// symbols back and `pdftoppm` renders every page, into a directory the test prints (kept after
/// the test; `REPORT_KEEP=dir` copies the PDF, its text and the pages there too).
#[test]
#[ignore = "needs poppler-utils (pdffonts, pdfinfo, pdftotext, pdftoppm); .ci/run installs them"]
fn poppler_reads_and_renders_the_acceptance_pdf() {
    let dir = TempDir::new("report-poppler");
    let out = make_report(&dir, &[]);
    let pdf = out.join("acceptance.pdf");
    let poppler = |cmd: &str, args: &[&str]| -> String {
        let o = std::process::Command::new(cmd)
            .args(args)
            .output()
            .unwrap_or_else(|e| panic!("{cmd} (apt-get install poppler-utils): {e}"));
        assert!(o.status.success(), "{cmd}: {}", stderr(&o));
        assert!(o.stderr.is_empty(), "{cmd} complained: {}", stderr(&o));
        stdout(&o)
    };
    let path = pdf.to_str().expect("path");

    // Every font embedded ("emb") as a subset ("sub", the "ABCDEF+" tag), with a ToUnicode map.
    let fonts = poppler("pdffonts", &[path]);
    let rows: Vec<Vec<&str>> = fonts
        .lines()
        .skip(2)
        .map(|l| l.split_whitespace().collect())
        .collect();
    let mut names: Vec<&str> = rows.iter().map(|r| r[0]).collect();
    for (r, name) in rows.iter().zip(&mut names) {
        // name, type ("CID TrueType"), encoding, emb, sub, uni, object number, generation
        assert_eq!(
            r[r.len() - 5..r.len() - 2],
            ["yes", "yes", "yes"],
            "{fonts}"
        );
        let (tag, base) = name.split_once('+').expect("a subset's tag");
        assert!(
            tag.len() == 6 && tag.bytes().all(|b| b.is_ascii_uppercase()),
            "{fonts}"
        );
        *name = base;
    }
    names.sort_unstable();
    assert_eq!(names, ["DejaVuSans", "DejaVuSans-Bold"], "{fonts}");

    let info = poppler("pdfinfo", &[path]);
    let field = |name: &str| -> String {
        info.lines()
            .find_map(|l| l.strip_prefix(name))
            .unwrap_or_else(|| panic!("{name} in {info}"))
            .trim()
            .to_string()
    };
    assert_eq!(field("PDF version:"), "1.7", "PDF/A-2 is PDF 1.7");
    assert_eq!(field("Title:"), "Acceptance report — VMC 850 #3, axis X");
    assert_eq!(
        field("Creator:"),
        format!("axiscomp {}", env!("CARGO_PKG_VERSION"))
    );
    let page_count: usize = field("Pages:").parse().expect("pages");

    let txt = out.join("acceptance.txt");
    poppler(
        "pdftotext",
        &[
            "-layout",
            "-enc",
            "UTF-8",
            path,
            txt.to_str().expect("path"),
        ],
    );
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
    // The symbols as themselves: units, arrows, the minus sign and the budget's formulas (this
    // report's angles are in arcsec, and no formula of it has σ or ″).
    for shown in [
        "slope 20.00 µm/m",
        "20.40 to 20.60 °C",
        "11.50 µm/(m·K)",
        "↑ (µm)",
        "↓ (µm)",
        "−8.00",
        "u = √(Σ terms²) and U = 2·u",
        "√(Σ sd²/frames)/n",
        "s/√n",
        "L·(1 − cos φ)/√12",
        "B\u{304} mean reversal value",
    ] {
        assert!(text.contains(shown), "{shown:?} not in:\n{text}");
    }

    // Every page rendered, at 50 dpi, into a directory that outlives the test.
    let pages = Path::new(env!("CARGO_TARGET_TMPDIR")).join("report-poppler-pages");
    let _ = std::fs::remove_dir_all(&pages);
    std::fs::create_dir_all(&pages).expect("pages dir");
    poppler(
        "pdftoppm",
        &[
            "-png",
            "-r",
            "50",
            path,
            pages.join("page").to_str().expect("path"),
        ],
    );
    let mut pngs: Vec<PathBuf> = std::fs::read_dir(&pages)
        .expect("dir")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "png"))
        .collect();
    pngs.sort();
    assert_eq!(pngs.len(), page_count, "every page rendered");
    for p in &pngs {
        let (w, h) = png_size(p);
        // A4 at 50 dpi: 413 × 585 pixels.
        assert!(
            (413..=414).contains(&w) && h == 585,
            "{}: {w} × {h}",
            p.display()
        );
    }
    println!("{} pages rendered into {}", pngs.len(), pages.display());
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
