//! Small shared pieces: numeric CSV, progress display, UTC timestamps, reconnect backoff,
//! fixed-rate pacing, socket options.

pub mod backoff;
pub mod csv;
pub mod pace;
pub mod progress;
pub mod sock;
pub mod time;

/// A TOML error on one line, with its line number in front.
pub fn toml_error_line(text: &str, e: &toml::de::Error) -> String {
    let msg = unknown_key_hint(&e.message().replace('\n', " "));
    match e.span() {
        Some(span) => {
            let before = &text[..span.start.min(text.len())];
            let line = before.matches('\n').count() + 1;
            // The table the line is in: the nearest `[header]` above it.
            let table = before
                .lines()
                .rev()
                .map(str::trim)
                .find(|l| l.starts_with('[') && l.ends_with(']'))
                .map(|h| format!(" in {h}"))
                .unwrap_or_default();
            format!("line {line}{table}: {msg}")
        }
        None => msg,
    }
}

/// serde's "unknown field `x`, expected one of `a`, `b`" in words, with the nearest known key
/// when one is close (a typo): "unknown key `adress`: did you mean `address`? (known: …)".
fn unknown_key_hint(msg: &str) -> String {
    let Some(rest) = msg.strip_prefix("unknown field `") else {
        return msg.to_string();
    };
    let Some((bad, tail)) = rest.split_once('`') else {
        return msg.to_string();
    };
    let known: Vec<&str> = tail
        .split('`')
        .skip(1)
        .step_by(2)
        .filter(|k| !k.is_empty())
        .collect();
    if known.is_empty() {
        return format!("unknown key `{bad}`: this table has no keys");
    }
    let nearest = known
        .iter()
        .map(|k| (edit_distance(bad, k), *k))
        .min()
        .filter(|(d, k)| *d <= (k.len().max(bad.len()) / 3).max(1));
    let list = known.join(", ");
    match nearest {
        Some((_, k)) => format!("unknown key `{bad}`: did you mean `{k}`? (known: {list})"),
        None => format!("unknown key `{bad}` (known: {list})"),
    }
}

/// Levenshtein distance of two short strings (characters).
pub fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut row: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut diag = row[0];
        row[0] = i + 1;
        for (j, cb) in b.iter().enumerate() {
            let up = row[j + 1];
            row[j + 1] = (up + 1).min(row[j] + 1).min(diag + usize::from(ca != *cb));
            diag = up;
        }
    }
    row[b.len()]
}

/// Piecewise-linear interpolation of `values` at `x`; the end values are held outside.
/// `positions` must be strictly increasing and as long as `values`; 0 for empty input.
pub fn interpolate(positions: &[f64], values: &[f64], x: f64) -> f64 {
    let n = positions.len().min(values.len());
    if n == 0 {
        return 0.0;
    }
    if x <= positions[0] {
        return values[0];
    }
    if x >= positions[n - 1] {
        return values[n - 1];
    }
    let k = positions[..n].partition_point(|&p| p <= x).clamp(1, n - 1);
    let (p0, p1) = (positions[k - 1], positions[k]);
    let t = (x - p0) / (p1 - p0);
    values[k - 1] + t * (values[k] - values[k - 1])
}
