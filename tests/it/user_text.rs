//! What a user reads is words (issue 29, must-show 4): no Rust `{:?}` in a message, an error, a
//! log line or a value the API serves. The source under `src/` is read as text and every format
//! placeholder with `?` (`{:?}`, `{x:?}`, `{:#?}`, `{x:02x?}`) outside test code is a failure,
//! unless it is one of the allowed cases below: a string the user typed or a file holds,
//! quoted so an empty or blank one shows (`"unknown mode \"\""`), or text no one reads.
//! Developer checks (`assert!`, `panic!`, `expect(`, `debug!`/`trace!` logs) are not user text.

use std::path::{Path, PathBuf};

/// (file, text on the line, why `?` is right there). Each must still match a line: a stale
/// entry fails too.
const ALLOWED: &[(&str, &str, &str)] = &[
    (
        "src/report/pdf.rs",
        "the rule krilla names {other:?}",
        "a PDF/A rule krilla reports that the report's words do not cover: its name is all there is",
    ),
    (
        "src/report/pdf.rs",
        "its settings are refused: {e:?}",
        "krilla's configuration error has no Display; fixed settings, so a broken build",
    ),
    (
        "src/acquire/map.rs",
        "unknown mode {other:?}",
        "the mode a map file gave, quoted",
    ),
    (
        "src/acquire/map.rs",
        "unknown PSD layout {s:?}",
        "the layout a map file gave, quoted",
    ),
    (
        "src/modbus/codec.rs",
        "unknown word order {s:?}",
        "the word order a map gave, quoted",
    ),
    (
        "src/modbus/codec.rs",
        "unknown type {s:?}",
        "the type a map gave, quoted",
    ),
    (
        "src/plc/map.rs",
        "unknown length unit {unit:?}",
        "the unit a map gave, quoted",
    ),
    (
        "src/plc/map.rs",
        "unknown length unit {:?}",
        "the unit a map gave, quoted",
    ),
    (
        "src/plc/map.rs",
        "unknown scheme {other:?}",
        "the scheme a map gave, quoted",
    ),
    (
        "src/plc/map.rs",
        "unknown sign {other:?}",
        "the sign a map gave, quoted",
    ),
    (
        "src/plc/map.rs",
        "unknown byte order {other:?}",
        "the byte order a map gave, quoted",
    ),
    (
        "src/sim/closed_loop.rs",
        "the plan's axis {0:?}",
        "the axis a plan gave, quoted",
    ),
    (
        "src/service/composition.rs",
        "format!(\"kind {:?}\", s.kind)",
        "a stored table's kind, quoted",
    ),
    (
        "src/service/stored.rs",
        "format {:?}",
        "a stored table's format, quoted",
    ),
    (
        "src/service/stored.rs",
        "format!(\"kind {:?}\", self.kind)",
        "a stored table's kind, quoted",
    ),
    (
        "src/service/stored.rs",
        "direction {:?}",
        "a stored table's direction, quoted",
    ),
    (
        "src/service/tables.rs",
        "axis {:?} is not X, Y or Z",
        "a stored run's axis, quoted",
    ),
    (
        "src/store/records.rs",
        "unknown run state {s:?}",
        "a stored state, quoted",
    ),
    (
        "src/store/records.rs",
        "unknown direction {s:?}",
        "a stored direction, quoted",
    ),
    (
        "src/store/records.rs",
        "unknown handover kind {s:?}",
        "a stored kind, quoted",
    ),
    (
        "src/store/records.rs",
        "direction {other:?}",
        "a stored direction, quoted",
    ),
    (
        "src/store/records.rs",
        "result {other:?}",
        "a stored result, quoted",
    ),
    (
        "src/service/measure/mod.rs",
        "let text = format!(\"{d:?}\");",
        "hashed into the decoupler's name, never shown",
    ),
    (
        "src/report/xml_check.rs",
        ":?}",
        "a test helper (its module is cfg(test))",
    ),
];

fn sources(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        if p.is_dir() {
            if p.file_name().is_some_and(|n| n != "tests") {
                sources(&p, out);
            }
        } else if p.extension().is_some_and(|x| x == "rs")
            && p.file_name().is_some_and(|n| n != "tests.rs")
        {
            out.push(p);
        }
    }
}

/// Whether `line` holds a format placeholder with `?`: `{`, an optional argument, `:`, an
/// optional `#`, width and `x`, then `?}`.
fn debug_placeholder(line: &str) -> bool {
    let b = line.as_bytes();
    let mut i = 0;
    while let Some(open) = line[i..].find('{').map(|k| k + i) {
        // "{{" is a brace, not a placeholder.
        if b.get(open + 1) == Some(&b'{') {
            i = open + 2;
            continue;
        }
        let mut j = open + 1;
        while j < b.len() && (b[j].is_ascii_alphanumeric() || b[j] == b'_' || b[j] == b'.') {
            j += 1;
        }
        if j < b.len() && b[j] == b':' {
            j += 1;
            while j < b.len() && (b[j] == b'#' || b[j].is_ascii_digit() || b[j] == b'x') {
                j += 1;
            }
            if line[j..].starts_with("?}") {
                return true;
            }
        }
        i = open + 1;
    }
    false
}

/// Developer text near `at`: the line and the three before it.
fn for_developers(lines: &[&str], at: usize) -> bool {
    const MARKS: [&str; 9] = [
        "debug!",
        "trace!",
        "assert",
        "panic!",
        "unreachable!",
        ".expect(",
        "debug_struct",
        "unimplemented!",
        "todo!",
    ];
    lines[at.saturating_sub(3)..=at]
        .iter()
        .any(|l| MARKS.iter().any(|m| l.contains(m)))
}

/// Whether `line` gives a tracing field by its Debug (`?field`, `name = ?value`).
fn debug_field(line: &str) -> bool {
    let b = line.as_bytes();
    line.match_indices('?').any(|(k, _)| {
        let before = line[..k].trim_end();
        let after = b.get(k + 1).copied().unwrap_or(b' ');
        (after.is_ascii_alphabetic() || after == b'_' || after == b'(' || after == b'&')
            && (before.is_empty()
                || before.ends_with('(')
                || before.ends_with(',')
                || before.ends_with('='))
    })
}

/// Whether a string literal on `line` writes a range as Rust does (`1..=127`, `{lo}..={hi}`):
/// a user reads "1 to 127".
fn rust_range(line: &str) -> bool {
    line.split('"').skip(1).step_by(2).any(|lit| {
        lit.match_indices("..=").any(|(k, _)| {
            let before = lit[..k].chars().next_back();
            let after = lit[k + 3..].chars().next();
            before.is_some_and(|c| c.is_ascii_digit() || c == '}')
                && after.is_some_and(|c| c.is_ascii_digit() || c == '-' || c == '{')
        })
    })
}

/// Every `{…:?}` and Rust range (`1..=127`) in user text under `src/`, and every tracing field given by its Debug in an
/// `info!`, `warn!` or `error!` (what the service's log shows): (file, line number, line).
fn found(root: &Path) -> Vec<(String, usize, String)> {
    let mut files = Vec::new();
    sources(&root.join("src"), &mut files);
    files.sort();
    let mut out = Vec::new();
    for f in files {
        let text = std::fs::read_to_string(&f).expect("a source file");
        let lines: Vec<&str> = text.lines().collect();
        let name = f
            .strip_prefix(root)
            .unwrap_or(&f)
            .to_string_lossy()
            .replace('\\', "/");
        // Inside an info!, warn! or error! call (until its closing `);`).
        let mut in_log = false;
        for (i, line) in lines.iter().enumerate() {
            let t = line.trim_start();
            // Test code sits at the end of a file, after its cfg(test) module opens.
            if t.starts_with("#[cfg(test)]") {
                break;
            }
            if ["info!(", "warn!(", "error!("]
                .iter()
                .any(|m| line.contains(m))
            {
                in_log = true;
            }
            let field = in_log && debug_field(line);
            if line.contains(");") {
                in_log = false;
            }
            if t.starts_with("//") {
                continue;
            }
            let placeholder = line.contains('"') && (debug_placeholder(line) || rust_range(line));
            if (placeholder || field) && !for_developers(&lines, i) {
                out.push((name.clone(), i + 1, t.to_string()));
            }
        }
    }
    out
}

#[test]
fn the_range_scan_finds_rust_ranges_in_strings_only() {
    for yes in [
        r#"format!("{} is not a node id (1..=127)", n)"#,
        r#"format!("points {lo}..={hi}")"#,
        r#"#[error("outside {min}..={max}")]"#,
        r#""use -7..=7""#,
    ] {
        assert!(rust_range(yes), "{yes}");
    }
    for no in [
        r#"for k in 1..=127 {"#,
        r#"format!("{} is not a node id (1 to 127)", n)"#,
        r#"let r = 0..=n; format!("{r}")"#,
        r#""a..=b is not a range of numbers""#,
    ] {
        assert!(!rust_range(no), "{no}");
    }
}

#[test]
fn the_placeholder_scan_finds_what_it_must_and_only_that() {
    for yes in [
        r#"format!("{:?}", x)"#,
        r#"format!("{x:?}")"#,
        r#"write!(f, "{a.b:#?}")"#,
        r#"format!("{bytes:02x?}")"#,
        r#"#[error("no reply within {0:?}")]"#,
    ] {
        assert!(debug_placeholder(yes), "{yes}");
    }
    for yes in [
        r#"tracing::info!(?down, "off");"#,
        r#"tracing::warn!(from = ?state, "power state");"#,
        "    ?request,",
    ] {
        assert!(debug_field(yes), "{yes}");
    }
    for no in [
        r#"tracing::info!(down = %d, "off");"#,
        r#"x.map(|v| v?)"#,
        r#"let y = f()?;"#,
    ] {
        assert!(!debug_field(no), "{no}");
    }
    for no in [
        r#"format!("{x}")"#,
        r#"format!("{x:.2}")"#,
        r#"format!("{{:?}}")"#,
        r#"format!("{:>8}", "?")"#,
        r#"format!("why? {x}")"#,
    ] {
        assert!(!debug_placeholder(no), "{no}");
    }
}

#[test]
fn no_rust_debug_text_reaches_a_user() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let all = found(root);
    let mut used = vec![false; ALLOWED.len()];
    let mut bad = Vec::new();
    for (file, n, line) in &all {
        match ALLOWED
            .iter()
            .position(|(f, text, _)| f == file && line.contains(text))
        {
            Some(k) => used[k] = true,
            None => bad.push(format!("  {file}:{n}: {line}")),
        }
    }
    assert!(
        bad.is_empty(),
        "Rust debug text ({{:?}}) in user-facing text; say it in words (a name, a unit, \
         util::numbers, util::time::span), or add it to ALLOWED with the reason:\n{}",
        bad.join("\n")
    );
    let stale: Vec<String> = ALLOWED
        .iter()
        .zip(&used)
        .filter(|(_, u)| !**u)
        .map(|((f, t, _), _)| format!("  {f}: {t}"))
        .collect();
    assert!(
        stale.is_empty(),
        "allowed but no longer in the source (remove them from ALLOWED):\n{}",
        stale.join("\n")
    );
}
