//! Small shared pieces: numeric CSV, range checks of input numbers, progress display, UTC
//! timestamps, reconnect backoff, fixed-rate pacing, socket options.

pub mod backoff;
pub mod clock;
pub mod csv;
pub mod pace;
pub mod progress;
pub mod range;
pub mod sock;
pub mod spline;
pub mod time;

/// A TOML error on one line, with its line number in front.
pub fn toml_error_line(text: &str, e: &toml::de::Error) -> String {
    let msg = type_words(&unknown_key_hint(&e.message().replace('\n', " ")));
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

/// serde's Rust type names in words: "expected f64" → "expected a number", "expected u32" →
/// "expected a whole number from 0 to 4294967295" (what a user of the file can act on).
fn type_words(msg: &str) -> String {
    let mut out = msg.to_string();
    for (rust, words) in [
        ("expected f64", "expected a number"),
        ("expected f32", "expected a number"),
        ("expected u8", "expected a whole number from 0 to 255"),
        ("expected u16", "expected a whole number from 0 to 65535"),
        (
            "expected u32",
            "expected a whole number from 0 to 4294967295",
        ),
        ("expected u64", "expected a whole number, 0 or more"),
        ("expected usize", "expected a whole number, 0 or more"),
        ("expected i8", "expected a whole number from -128 to 127"),
        (
            "expected i16",
            "expected a whole number from -32768 to 32767",
        ),
        ("expected i32", "expected a whole number"),
        ("expected i64", "expected a whole number"),
        ("expected a boolean", "expected true or false"),
    ] {
        // Whole words only: "expected u8" is not the start of "expected u80".
        let mut from = 0;
        while let Some(i) = out[from..].find(rust) {
            let at = from + i;
            let end = at + rust.len();
            if out[end..].starts_with(|c: char| c.is_ascii_alphanumeric()) {
                from = end;
                continue;
            }
            out.replace_range(at..end, words);
            from = at + words.len();
        }
    }
    out
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
/// Numbers as a user reads them, in brackets: "[0.1, 0, 1]".
pub fn numbers(v: &[f64]) -> String {
    let parts: Vec<String> = v.iter().map(f64::to_string).collect();
    format!("[{}]", parts.join(", "))
}

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

/// The standard normal distribution's quantile Φ⁻¹(p) for 0 < p < 1 (NaN outside), by
/// Acklam's rational approximation (relative error below 1.2e-9: far below what a coverage
/// factor needs).
pub fn normal_quantile(p: f64) -> f64 {
    const A: [f64; 6] = [
        -3.969683028665376e1,
        2.209460984245205e2,
        -2.759285104469687e2,
        1.38357751867269e2,
        -3.066479806614716e1,
        2.506628277459239,
    ];
    const B: [f64; 5] = [
        -5.447609879822406e1,
        1.615858368580409e2,
        -1.556989798598866e2,
        6.680131188771972e1,
        -1.328068155288572e1,
    ];
    const C: [f64; 6] = [
        -7.784894002430293e-3,
        -3.223964580411365e-1,
        -2.400758277161838,
        -2.549732539343734,
        4.374664141464968,
        2.938163982698783,
    ];
    const D: [f64; 4] = [
        7.784695709041462e-3,
        3.224671290700398e-1,
        2.445134137142996,
        3.754408661907416,
    ];
    const LOW: f64 = 0.02425;
    if !(p > 0.0 && p < 1.0) {
        return f64::NAN;
    }
    let tail = |q: f64| {
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    };
    if p < LOW {
        tail((-2.0 * p.ln()).sqrt())
    } else if p > 1.0 - LOW {
        -tail((-2.0 * (1.0 - p).ln()).sqrt())
    } else {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    }
}

/// The coverage factor that holds `n` normal errors, each against its own standard
/// uncertainty, all at once with probability `level` (Šidák: each at `level^(1/n)`; true for
/// any correlation between them, and close when they are independent).
pub fn simultaneous_k(n: usize, level: f64) -> f64 {
    let each = level.powf(1.0 / n.max(1) as f64);
    normal_quantile(0.5 + each / 2.0)
}

#[cfg(test)]
mod stats_tests {
    #[test]
    fn rust_type_names_read_as_words() {
        // `check` said: invalid type: string "fast", expected f64.
        assert_eq!(
            super::type_words("invalid type: string \"fast\", expected f64"),
            "invalid type: string \"fast\", expected a number"
        );
        assert_eq!(
            super::type_words("invalid value: integer `-1`, expected u32"),
            "invalid value: integer `-1`, expected a whole number from 0 to 4294967295"
        );
        assert_eq!(
            super::type_words("expected u80 and u8"),
            "expected u80 and u8"
        );
        let text = "[io]\nrate_hz = \"fast\"\n";
        #[derive(serde::Deserialize, Debug)]
        #[allow(dead_code)]
        struct Io {
            rate_hz: f64,
        }
        #[derive(serde::Deserialize, Debug)]
        #[allow(dead_code)]
        struct File {
            io: Io,
        }
        let e = toml::from_str::<File>(text).unwrap_err();
        assert_eq!(
            super::toml_error_line(text, &e),
            "line 2 in [io]: invalid type: string \"fast\", expected a number"
        );
    }

    use super::*;

    /// Against Python's statistics.NormalDist().inv_cdf.
    #[test]
    fn the_normal_quantile_matches_an_independent_implementation() {
        for (p, want) in [
            (0.5, 0.0),
            (0.9, 1.2815515655446008),
            (0.975, 1.9599639845400536),
            (0.995, 2.5758293035489),
            (0.999907, 3.7373093852766632),
            (1e-6, -4.753424308822899),
            (0.02425, -1.9729610513118845),
        ] {
            let got = normal_quantile(p);
            assert!(
                (got - want).abs() <= 1e-8 * want.abs().max(1.0),
                "p {p}: {got} against {want}"
            );
        }
        assert!(normal_quantile(0.0).is_nan() && normal_quantile(1.0).is_nan());
        assert!(normal_quantile(f64::NAN).is_nan());
    }

    /// Šidák's k against Python's inv_cdf(1 − (1 − 0.95^(1/n))/2).
    #[test]
    fn the_simultaneous_factor_grows_with_the_points() {
        for (n, want) in [
            (1, 1.9599639845400536),
            (54, 3.3051001037085923),
            (267, 3.7291965675041787),
        ] {
            let got = simultaneous_k(n, 0.95);
            assert!((got - want).abs() < 1e-8, "n {n}: {got} against {want}");
        }
    }
}
