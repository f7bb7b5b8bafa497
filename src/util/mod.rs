//! Small shared pieces: numeric CSV, progress display, UTC timestamps.

pub mod csv;
pub mod progress;
pub mod time;
