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
    let msg = e.message().replace('\n', " ");
    match e.span() {
        Some(span) => {
            let line = text[..span.start.min(text.len())].matches('\n').count() + 1;
            format!("line {line}: {msg}")
        }
        None => msg,
    }
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
