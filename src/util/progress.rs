//! A progress bar on standard error. On a terminal it redraws one line; otherwise (logs, CI)
//! it prints a line at every 25 % so a long run still shows it is moving.

use std::io::{IsTerminal, Write};
use std::time::Instant;

/// Progress of one named stage.
pub struct Progress {
    label: String,
    total: u64,
    done: u64,
    tty: bool,
    last_quarter: u64,
    started: Instant,
    enabled: bool,
}

impl Progress {
    /// Start a stage of `total` steps.
    pub fn new(label: &str, total: u64) -> Self {
        let mut p = Progress {
            label: label.to_string(),
            total: total.max(1),
            done: 0,
            tty: std::io::stderr().is_terminal(),
            last_quarter: 0,
            started: crate::util::clock::now(),
            enabled: true,
        };
        p.draw();
        p
    }

    /// A progress that prints nothing (library callers, tests).
    pub fn hidden() -> Self {
        Progress {
            label: String::new(),
            total: 1,
            done: 0,
            tty: false,
            last_quarter: 0,
            started: crate::util::clock::now(),
            enabled: false,
        }
    }

    /// Advance to `done` steps.
    pub fn set(&mut self, done: u64) {
        self.done = done.min(self.total);
        self.draw();
    }

    /// Advance by one step.
    pub fn inc(&mut self) {
        self.set(self.done + 1);
    }

    /// Finish the stage with a closing note ("200 poses"; "done" or "" for none).
    pub fn finish(mut self, note: &str) {
        self.done = self.total;
        if !self.enabled {
            return;
        }
        let secs = self.started.elapsed().as_secs_f64();
        let line = closing(note, secs);
        let mut err = std::io::stderr().lock();
        if self.tty {
            let _ = writeln!(err, "\r{} {} {line}\x1b[K", self.label, bar(1.0));
        } else {
            let _ = writeln!(err, "{}: {line}", self.label);
        }
    }

    fn draw(&mut self) {
        if !self.enabled {
            return;
        }
        let frac = self.done as f64 / self.total as f64;
        let mut err = std::io::stderr().lock();
        if self.tty {
            let _ = write!(
                err,
                "\r{} {} {}/{}\x1b[K",
                self.label,
                bar(frac),
                self.done,
                self.total
            );
            let _ = err.flush();
        } else {
            let quarter = (frac * 4.0).floor() as u64;
            if quarter > self.last_quarter {
                self.last_quarter = quarter;
                let _ = writeln!(err, "{}: {}/{}", self.label, self.done, self.total);
            }
        }
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        if self.enabled && self.tty && self.done < self.total {
            let _ = writeln!(std::io::stderr());
        }
    }
}

/// What a stage's closing line says after its label: "done" and the note, once, with the time.
fn closing(note: &str, secs: f64) -> String {
    match note.trim() {
        "" | "done" => format!("done ({secs:.1} s)"),
        note => format!("done, {note} ({secs:.1} s)"),
    }
}

fn bar(frac: f64) -> String {
    let width = 30;
    let full = ((frac.clamp(0.0, 1.0)) * width as f64).round() as usize;
    format!("[{}{}]", "#".repeat(full), "-".repeat(width - full))
}

#[cfg(test)]
mod tests {
    use super::closing;

    #[test]
    fn a_stage_says_done_once() {
        // The demo printed "calibration fit: done, done (0.1 s)".
        assert_eq!(closing("done", 0.12), "done (0.1 s)");
        assert_eq!(closing("", 2.0), "done (2.0 s)");
        assert_eq!(closing("200 poses", 0.0), "done, 200 poses (0.0 s)");
    }
}
