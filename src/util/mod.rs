//! Small shared pieces: numeric CSV, progress display, UTC timestamps.

pub mod csv;
pub mod progress;
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
